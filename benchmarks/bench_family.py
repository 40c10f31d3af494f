"""Recovery results of this checkout against another (``--base``) over a family of
scenes and draws of imperceptible noise: is a change's effect on E more than a
recovery's own spread?

A recovery can move by several percent when the depth moves by a hundredth of σ (session
39: the teapot from above 5 959-7 043 bits over four draws), so one image per scene cannot
tell whether a change that alters the arithmetic (not the method) made results worse.
Here every scene of :func:`proto_coarse_to_fine.scenes` (the built-in scenes, the
castings heap from six other seeds, the chair turned three other ways, the person in
five poses; none chosen for this) is recovered with :func:`sqparts.recover`'s defaults as
it is (draw 0) and with ``--draws`` - 1 draws of Gaussian depth noise of ``--noise``
times each pixel's depth (seeded by the draw), by both checkouts, each in one process.
Per scene and draw: parts, E, fraction explained, seconds (the first recovery of each
process compiles). The summary pairs the two checkouts draw by draw: how many came out
shorter and longer, the mean and median change of E, and per checkout the sum of E.

    git worktree add --detach /tmp/wt-base <commit>
    JAX_PLATFORMS=cpu python benchmarks/bench_family.py --base /tmp/wt-base [--draws 2]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import CHILD_PREAMBLE, run_in_checkout, save

ROOT = Path(__file__).resolve().parents[1]

CHILD = (
    CHILD_PREAMBLE
    + r"""
sys.path.insert(0, sys.argv[1])
from proto_coarse_to_fine import scenes
draws, noise = int(sys.argv[2]), float(sys.argv[3])
rows = []
for name, parts, cam in scenes():
    depth = np.asarray(sqparts.render_range_image(parts, cam))
    for draw in range(draws):
        d = depth if draw == 0 else (depth * (1.0 + np.random.default_rng(draw).normal(0.0, noise, depth.shape))).astype(np.float32)
        t = time.perf_counter()
        r = sqparts.recover(d, cam)
        rows.append({"scene": name, "draw": draw, "parts": len(r.parts), "E": r.cost.total,
                     "explained": r.fraction_explained, "seconds": time.perf_counter() - t})
        print(name, draw, len(r.parts), round(r.cost.total, 1), file=sys.stderr, flush=True)
print("RESULT " + json.dumps(rows))
"""
)


def summary(base: list[dict], new: list[dict]) -> dict:
    """Draw-by-draw comparison of two checkouts' rows (the same scenes and draws)."""
    diff = np.array([b["E"] - a["E"] for a, b in zip(base, new, strict=True)])
    return {
        "pairs": len(diff),
        "shorter": int((diff < -0.5).sum()),
        "longer": int((diff > 0.5).sum()),
        "same": int((np.abs(diff) <= 0.5).sum()),
        "mean_E_change_bits": float(diff.mean()),
        "median_E_change_bits": float(np.median(diff)),
        "sum_E_bits": {"base": float(sum(a["E"] for a in base)), "new": float(sum(b["E"] for b in new))},
        "parts_changed": int(sum(a["parts"] != b["parts"] for a, b in zip(base, new))),
        "seconds_after_the_first": {
            v: float(sum(r["seconds"] for r in rows[1:])) for v, rows in (("base", base), ("new", new))
        },
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--base", type=Path, required=True, help="a checkout (git worktree) to compare against")
    ap.add_argument("--draws", type=int, default=2, help="draws per scene: the image as it is, then noisy ones")
    ap.add_argument("--noise", type=float, default=1e-5, help="noise, relative to each pixel's depth")
    args = ap.parse_args()
    here = str(Path(__file__).resolve().parent)
    got = {
        v: run_in_checkout(checkout, CHILD, here, str(args.draws), str(args.noise))
        for v, checkout in (("base", args.base.resolve()), ("new", ROOT))
    }
    for a, b in zip(got["base"], got["new"]):
        print(
            f"{a['scene']:22s} draw {a['draw']}: {a['parts']:2d} -> {b['parts']:2d} parts, "
            f"E {a['E']:8.1f} -> {b['E']:8.1f} ({b['E'] - a['E']:+7.1f}), {a['seconds']:5.1f} -> {b['seconds']:5.1f} s"
        )
    result = summary(got["base"], got["new"])
    print(json.dumps(result, indent=1))
    save("family", {"base": str(args.base), "draws": args.draws, "noise": args.noise, "rows": got, "summary": result})


if __name__ == "__main__":
    main()
