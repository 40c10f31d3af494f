"""The grid search of a whole image (``fit_image``: every region's grid, candidates and
their polishing) against another checkout, warm, in one process per scene, grid and
checkout, the checkouts' processes interleaved. Records each run's warm times, the XLA
programs its first search built, and whether every region's candidates and Γ are the
same, bit for bit, as the other checkout's.

    git worktree add --detach /tmp/wt-base <rev>
    JAX_PLATFORMS=cpu python benchmarks/bench_search_image.py --base /tmp/wt-base \\
        --scenes human castings --grids coarse default --runs 3 --rounds 2

Writes ``benchmarks/results/search_image.json``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import CHILD_PREAMBLE, interleaved, run_in_checkout, save, warm_fields

ROOT = Path(__file__).resolve().parents[1]

CHILD = (
    CHILD_PREAMBLE
    + r"""
scene, grid, runs = sys.argv[1], sys.argv[2], int(sys.argv[3])
s = sqparts.builtin_scene(scene)
depth = np.asarray(sqparts.render_range_image(s.parts, s.camera))
settings = sqparts.SearchSettings(grid=grid)
built[0] = 0
t = time.perf_counter()
fits, _, _ = sqparts.fit_image(depth, s.camera, settings)
cold, programs = time.perf_counter() - t, built[0]
times = []
for _ in range(runs):
    t = time.perf_counter()
    fits, _, _ = sqparts.fit_image(depth, s.camera, settings)
    times.append(time.perf_counter() - t)
print("RESULT " + json.dumps({"regions": len(fits), "cold_s": cold, "programs": programs, "warm_s": times,
    "vectors": [np.asarray(f.parts.to_vector()).tolist() for f in fits],
    "gamma": [np.asarray(f.gamma).tolist() for f in fits]}))
"""
)


def run(checkout: Path, scene: str, grid: str, runs: int) -> dict:
    return run_in_checkout(checkout, CHILD, scene, grid, str(runs))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--base", required=True, type=Path, help="checkout of the baseline")
    ap.add_argument("--scenes", nargs="+", default=["human", "castings"])
    ap.add_argument("--grids", nargs="+", default=["coarse", "default"])
    ap.add_argument("--runs", type=int, default=3, help="warm searches per process")
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    checkouts = {"base": args.base.resolve(), "new": ROOT}
    rows = []
    for scene in args.scenes:
        for grid in args.grids:
            got = interleaved(checkouts, args.rounds, lambda v, checkout: run(checkout, scene, grid, args.runs))
            timing = warm_fields(got)
            warm = timing["warm_median_s"]
            base, new = got["base"][-1], got["new"][-1]
            row = {
                "scene": scene,
                "grid": grid,
                "regions": new["regions"],
                "identical": base["vectors"] == new["vectors"] and base["gamma"] == new["gamma"],
                **timing,
                "programs_first_search": {v: got[v][-1]["programs"] for v in checkouts},
            }
            rows.append(row)
            print(
                f"{scene} ({grid}, {row['regions']} regions): base {warm['base']:.2f} s, "
                f"new {warm['new']:.2f} s "
                f"(x{row['speedup']:.2f}); identical: {row['identical']}",
                flush=True,
            )
    save("search_image", {"base": str(checkouts["base"]), "runs": args.runs, "rounds": args.rounds, "rows": rows})


if __name__ == "__main__":
    main()
