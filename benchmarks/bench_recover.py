"""End-to-end recovery of the built-in scenes, and how often best-first selection is optimal.

Per scene: parts found vs true, fraction of figure pixels explained within ±σ/2,
commission (fraction of figure pixels), description length (bits), parameter count, and
wall time per stage. Each scene is recovered once cold and ``WARM_RUNS`` times warm:
the stage times are the warm runs' medians (recovery is deterministic: the results
are the same each time), and the cold run's excess over the median total is reported as
compile time. The human is also recovered from four copies of its depth with 3 µm of
noise, to show how far float rounding alone moves the result.

    python benchmarks/bench_recover.py [--scenes human chair ...]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import result_path, save

import sqparts

SCENE_OPTIONS = {"human": {}, "chair": {}, "castings": {}, "gate": {}}
WARM_RUNS = 3


def recover_scene(name):
    s = sqparts.builtin_scene(name)
    depth = np.asarray(sqparts.render_range_image(s.parts, s.camera))
    t0 = time.perf_counter()
    sqparts.recover(depth, s.camera, **SCENE_OPTIONS[name])
    cold = time.perf_counter() - t0
    warm = [sqparts.recover(depth, s.camera, **SCENE_OPTIONS[name]) for _ in range(WARM_RUNS)]
    assert len({round(w.cost.total, 6) for w in warm}) == 1, "recovery is not deterministic"
    r = warm[-1]
    timings = {k: float(np.median([w.timings[k] for w in warm])) for k in r.timings}
    row = {
        "scene": name,
        "image": f"{s.camera.width}x{s.camera.height}",
        "camera": type(s.camera).__name__,
        "true_parts": len(s.parts),
        "found_parts": len(r.parts),
        "parameters": 14 * len(r.parts),
        "fraction_explained": r.fraction_explained,
        "commission_fraction": r.commission_fraction,
        "description_length_bits": r.cost.total,
        "raw_bits": r.settings["raw_bits"],
        "candidates": r.candidates,
        "regions": r.settings["regions"],
        "selection": r.selection_method,
        "timings_s": timings,
        "warm_runs_total_s": [w.timings["total"] for w in warm],
        "compile_s": cold - timings["total"],
    }
    print(
        f"{name}: {row['found_parts']}/{row['true_parts']} parts, explained {row['fraction_explained']:.1%}, "
        f"commission {row['commission_fraction']:.1%}, {timings['total']:.1f} s warm (median of {WARM_RUNS}), compile {row['compile_s']:.1f} s",
        flush=True,
    )
    return row, r


def perturbation_spread(name, sigma: float = 3e-6, seeds: int = 4):
    """Recovery of a scene whose depth carries Gaussian noise of ``sigma`` metres (3 µm:
    about the float32 rounding of a depth, and what separates a GPU's rendering from a
    CPU's): the spread of parts found, fraction explained and description length."""
    s = sqparts.builtin_scene(name)
    depth = np.asarray(sqparts.render_range_image(s.parts, s.camera))
    rows = []
    for seed in range(seeds):
        noisy = depth + np.random.default_rng(seed).normal(0.0, sigma, depth.shape).astype(np.float32)
        r = sqparts.recover(noisy, s.camera, **SCENE_OPTIONS[name])
        rows.append(
            {
                "seed": seed,
                "found_parts": len(r.parts),
                "fraction_explained": r.fraction_explained,
                "description_length_bits": r.cost.total,
            }
        )
    print(
        f"{name} with {sigma * 1e6:.0f} µm noise: parts {[r['found_parts'] for r in rows]}, explained "
        f"{[round(100 * r['fraction_explained'], 1) for r in rows]}%",
        flush=True,
    )
    return {"scene": name, "sigma_m": sigma, "runs": rows}


def best_first_vs_exact(recovery_problems, trials: int = 40, seed: int = 0):
    """On random sub-problems of real candidate sets: how often best-first reaches the
    exact optimum, the mean excess in bits, and the time of each."""
    rng = np.random.default_rng(seed)
    rows = []
    for problem in recovery_problems:
        n = problem.size
        for _ in range(trials):
            k = int(rng.integers(min(8, n), min(40, n) + 1))
            idx = np.sort(rng.choice(n, k, replace=False))
            sub = sqparts.SelectionProblem(
                problem.area[np.ix_(idx, idx)], problem.commission[np.ix_(idx, idx)], problem.costs
            )
            t0 = time.perf_counter()
            g = sqparts.select_best_first(sub)
            t1 = time.perf_counter()
            x, optimal = sqparts.select_exact(sub)
            t2 = time.perf_counter()
            rows.append(
                {
                    "n": k,
                    "optimal": bool(optimal),
                    "best_first_bits": sub.energy(g),
                    "exact_bits": sub.energy(x),
                    "best_first_s": t1 - t0,
                    "exact_s": t2 - t1,
                }
            )
    same = np.mean([abs(r["best_first_bits"] - r["exact_bits"]) < 1e-6 for r in rows])
    return {
        "trials": len(rows),
        "best_first_optimal_rate": float(same),
        "mean_excess_bits": float(np.mean([r["best_first_bits"] - r["exact_bits"] for r in rows])),
        "median_best_first_s": float(np.median([r["best_first_s"] for r in rows])),
        "median_exact_s": float(np.median([r["exact_s"] for r in rows])),
        "rows": rows,
    }


def candidate_problem(name):
    """The selection problem of a scene's full candidate set."""
    from sqparts._recover import _candidates

    s = sqparts.builtin_scene(name)
    depth = np.asarray(sqparts.render_range_image(s.parts, s.camera))
    fits, data, _ = sqparts.fit_image(depth, s.camera, "fast")  # the candidates recover selects from
    parts, _, explained, commission = _candidates(fits, data)
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    return sqparts.SelectionProblem.from_masks(explained, commission, costs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", choices=list(SCENE_OPTIONS), default=list(SCENE_OPTIONS))
    args = ap.parse_args()
    rows = []
    for name in args.scenes:
        row, r = recover_scene(name)
        rows.append(row)
        from sqparts._plot import save_report

        save_report(result_path(f"report_{name}", "png"), r, title=name)
    spread = perturbation_spread("human") if "human" in args.scenes else None
    sel = best_first_vs_exact([candidate_problem("human"), candidate_problem("castings")])
    print(
        f"best-first optimal in {sel['best_first_optimal_rate']:.0%} of {sel['trials']} problems, "
        f"mean excess {sel['mean_excess_bits']:.1f} bits",
        flush=True,
    )
    save("recover", {"scenes": rows, "perturbation": spread, "selection": sel})


if __name__ == "__main__":
    main()
