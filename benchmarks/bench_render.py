"""Renderer throughput: rays/s and hypotheses/s for 32x32 and 64x64 windows.

Each configuration renders a batch of random parts (taper and bend included) over one
window, chunked with ``jax.lax.map(batch_size=...)``. One warm-up call (compile time
reported separately), then the median of ``--repeats`` timed calls.

    python benchmarks/bench_render.py [--hypotheses 4096] [--repeats 5]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax
import numpy as np

import sqparts
from sqparts._render import cast_batch

from _common import save, time_call


def random_parts(n: int, seed: int = 0) -> sqparts.Part:
    rng = np.random.default_rng(seed)
    return sqparts.Part(
        size=rng.uniform(0.05, 0.3, (n, 3)).astype(np.float32),
        squareness=rng.uniform(0.2, 1.8, (n, 2)).astype(np.float32),
        position=np.c_[rng.uniform(-0.1, 0.1, (n, 2)), np.full(n, 2.0)].astype(np.float32),
        orientation=rng.normal(size=(n, 3)).astype(np.float32),
        bend=rng.uniform(-0.3, 0.3, (n, 2)).astype(np.float32),
        taper=rng.uniform(-0.4, 0.4, n).astype(np.float32),
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hypotheses", type=int, default=4096)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--batch-size", type=int, default=128)
    args = ap.parse_args()
    parts = random_parts(args.hypotheses)
    rows = []
    for window in (32, 64):
        cam = sqparts.PinholeCamera(window, window, window * 1.25, window * 1.25, (window - 1) / 2, (window - 1) / 2)
        o, d = cam.rays()
        for steps in (6, 8):
            fn = jax.jit(lambda p, s=steps: cast_batch(p, o, d, batch_size=args.batch_size, newton_steps=s))
            first, median, times = time_call(fn, parts, repeats=args.repeats)
            rays = args.hypotheses * window * window
            row = {
                "window": window,
                "newton_steps": steps,
                "hypotheses": args.hypotheses,
                "batch_size": args.batch_size,
                "dtype": "float32",
                "compile_s": first - median,
                "median_s": median,
                "times_s": times,
                "rays_per_s": rays / median,
                "hypotheses_per_s": args.hypotheses / median,
            }
            rows.append(row)
            print(f"{window}x{window} steps={steps}: {row['rays_per_s'] / 1e6:.2f} M rays/s, "
                  f"{row['hypotheses_per_s']:.0f} hyp/s, compile {row['compile_s']:.2f} s")
    save("render", {"rows": rows})


if __name__ == "__main__":
    main()
