"""Renderer throughput: rays/s and hypotheses/s for 32x32 and 64x64 windows.

Each configuration renders a batch of random parts (taper and bend included) over one
window, chunked with ``jax.lax.map(batch_size=...)``. One warm-up call (compile time
reported separately), then the median of ``--repeats`` timed calls.

With ``--baseline DIR`` the ``sqparts`` package of another checkout (for instance
``git worktree add /tmp/base <commit>``) is timed in the same run, its calls interleaved
with this checkout's, and the speed-up is the ratio of the two medians. Its rays are
checked against this checkout's (hit masks' IoU, depth difference).

    python benchmarks/bench_render.py [--hypotheses 4096] [--repeats 5] [--baseline DIR]
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax
import numpy as np
from _common import save

import sqparts
import sqparts._render


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


def load_baseline(path: Path):
    """The ``sqparts`` package under ``path`` imported as ``sqparts_baseline``."""
    init = path / "sqparts" / "__init__.py"
    if not init.is_file():
        raise SystemExit(f"--baseline: expected a checkout with sqparts/__init__.py, got {path}")
    spec = importlib.util.spec_from_file_location(
        "sqparts_baseline", init, submodule_search_locations=[str(init.parent)]
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules["sqparts_baseline"] = module
    spec.loader.exec_module(module)
    return module


def git_revision(path: Path) -> str | None:
    try:
        out = subprocess.run(
            ["git", "-C", str(path), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=10
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def timed(fn, arg) -> tuple[float, float]:
    """(wall, CPU) seconds of one call: on a shared machine the CPU time of this process
    (all its threads) is the less disturbed of the two."""
    t0, c0 = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn(arg))
    return time.perf_counter() - t0, time.process_time() - c0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hypotheses", type=int, default=4096)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--batch-size", type=int, default=128)
    ap.add_argument("--baseline", type=Path, default=None, help="another checkout to time in the same run")
    args = ap.parse_args()
    parts = random_parts(args.hypotheses)
    here = Path(__file__).resolve().parents[1]
    codes = {"this": (sqparts._render, parts, git_revision(here))}
    if args.baseline is not None:
        base = load_baseline(args.baseline.resolve())
        base_parts = base.Part.from_vector(np.asarray(parts.to_vector()))
        codes["baseline"] = (
            importlib.import_module("sqparts_baseline._render"),
            base_parts,
            git_revision(args.baseline),
        )
    # cast_batch (render_each's kernel), and the search's pattern: lax.map over chunks of
    # hypotheses of cast_part (sqparts._search._map_hypotheses), which gets no ray tiles.
    configs = [
        (32, 6, "cast_batch"),
        (32, 8, "cast_batch"),
        (64, 6, "cast_batch"),
        (64, 8, "cast_batch"),
        (32, 6, "lax.map(cast_part)"),
    ]
    rows = []
    for window, steps, entry in configs:
        cam = sqparts.PinholeCamera(window, window, window * 1.25, window * 1.25, (window - 1) / 2, (window - 1) / 2)
        o, d = cam.rays()
        fns, first, outputs = {}, {}, {}
        for code, (render, prt, _) in codes.items():
            if entry == "cast_batch":
                fn = lambda p, s=steps, r=render: r.cast_batch(p, o, d, batch_size=args.batch_size, newton_steps=s)  # noqa: E731
            else:
                fn = lambda p, s=steps, r=render: jax.lax.map(  # noqa: E731
                    lambda q: r.cast_part(q, o, d, s), p, batch_size=args.batch_size
                )
            fns[code] = jax.jit(fn)
            t0 = time.perf_counter()
            outputs[code] = jax.block_until_ready(fns[code](prt))
            first[code] = time.perf_counter() - t0
        times = {code: [] for code in codes}
        cpu_times = {code: [] for code in codes}
        for _ in range(args.repeats):  # interleaved, so that other load hits both alike
            for code, (_, prt, _) in codes.items():
                wall, cpu = timed(fns[code], prt)
                times[code].append(wall)
                cpu_times[code].append(cpu)
        rays = args.hypotheses * window * window
        for code, (_, _, revision) in codes.items():
            median = statistics.median(times[code])
            row = {
                "code": code,
                "entry": entry,
                "revision": revision,
                "window": window,
                "newton_steps": steps,
                "hypotheses": args.hypotheses,
                "batch_size": args.batch_size,
                "dtype": "float32",
                "compile_s": first[code] - median,
                "median_s": median,
                "times_s": times[code],
                "median_cpu_s": statistics.median(cpu_times[code]),
                "cpu_times_s": cpu_times[code],
                "rays_per_s": rays / median,
                "hypotheses_per_s": args.hypotheses / median,
            }
            if code == "baseline":
                t_new, hit_new = map(np.asarray, outputs["this"])
                t_old, hit_old = map(np.asarray, outputs[code])
                both = hit_new & hit_old
                row["speedup_of_this"] = median / statistics.median(times["this"])
                row["cpu_speedup_of_this"] = row["median_cpu_s"] / statistics.median(cpu_times["this"])
                row["hit_iou_with_this"] = float(both.sum() / max((hit_new | hit_old).sum(), 1))
                row["max_depth_difference_with_this"] = (
                    float(np.abs(t_new[both] - t_old[both]).max()) if both.any() else 0.0
                )
            rows.append(row)
            print(
                f"{code:8s} {entry} {window}x{window} steps={steps}: {row['rays_per_s'] / 1e6:.2f} M rays/s, "
                f"{row['hypotheses_per_s']:.0f} hyp/s, compile {row['compile_s']:.2f} s"
                + (
                    f", this is {row['speedup_of_this']:.2f}x faster ({row['cpu_speedup_of_this']:.2f}x in CPU time), hit IoU {row['hit_iou_with_this']:.5f}, "
                    f"max |dt| {row['max_depth_difference_with_this']:.1e}"
                    if code == "baseline"
                    else ""
                )
            )
    save("render", {"rows": rows})


if __name__ == "__main__":
    main()
