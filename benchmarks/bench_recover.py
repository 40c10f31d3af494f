"""End-to-end recovery of the built-in scenes, and how often best-first selection is optimal.

Per scene: parts found vs true, fraction of figure pixels explained within ±σ/2,
commission (fraction of figure pixels), description length (bits), parameter count, and
wall time per stage. Each scene is recovered once cold and ``WARM_RUNS`` times warm:
the stage times are the warm runs' medians (recovery is deterministic: the results
are the same each time), and the cold run's excess over the median total is reported as
compile time. The human is also recovered from four copies of its depth with 3 µm of
noise, to show how far float rounding alone moves the result.

The built-in scenes go through :func:`sqparts.recover`'s defaults (``thin-chair``: the
chair with legs 2.4 pixels across, all four in view; issue #27); ``thin-chair-scene``
is that chair and ``gate-scene`` the gate (Figure 10: members two pixels across, nothing behind them)
through :func:`sqparts.recover_scene`'s defaults (what ``sqparts recover`` runs: hole
policy ``auto``) with prettifying (``up`` = -y). Each row also says which true parts were
found (some recovered part, rendered alone, has silhouette IoU >= 0.5 with the true
part rendered alone) and, for the gate, how far the recovered rails and posts are from
horizontal and vertical.

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

SCENE_OPTIONS = {"human": {}, "chair": {}, "castings": {}, "gate": {}, "thin-chair": {}}
"""Options of :func:`sqparts.recover` per built-in scene."""
EXTRA_ROWS = {
    "gate-scene": ("gate", {}, {"prettify": True, "up": (0.0, -1.0, 0.0)}),
    "thin-chair-scene": ("thin-chair", {}, {}),
}
"""Issue #27's rows: (built-in scene, its keyword arguments, :class:`sqparts.SceneSettings`
fields for :func:`sqparts.recover_scene`, or None for :func:`sqparts.recover`'s defaults)."""
WARM_RUNS = 3


def _masks(parts, camera) -> np.ndarray:
    return np.isfinite(np.asarray(sqparts.render_each(parts, camera)))


def true_parts_found(truth, found, camera, names) -> dict:
    """Per true part: the best silhouette IoU of a recovered part (each rendered alone),
    and whether it reaches 0.5."""
    a, b = _masks(truth, camera), _masks(found, camera)
    inter = np.einsum("ihw,jhw->ij", a.astype(np.int64), b.astype(np.int64))
    union = a.sum((1, 2))[:, None] + b.sum((1, 2))[None, :] - inter
    iou = (inter / np.maximum(union, 1)).max(axis=1)
    return {n: {"iou": float(x), "found": bool(x >= 0.5)} for n, x in zip(names, iou)}


def gate_angles(found, truth, camera, names) -> dict:
    """For each true rail and post, the recovered part that best overlaps it and the
    angle (degrees) of that part's longest axis from horizontal (rails) or vertical
    (posts); the brace's angle from its true direction."""
    a, b = _masks(truth, camera), _masks(found, camera)
    inter = np.einsum("ihw,jhw->ij", a.astype(np.int64), b.astype(np.int64))
    up = np.array([0.0, -1.0, 0.0])
    axes = np.asarray(found.rotation())[:, :, 2]
    true_axes = np.asarray(truth.rotation())[:, :, 2]
    out = {}
    for i, n in enumerate(names):
        j = int(np.argmax(inter[i]))
        if inter[i, j] == 0:
            out[n] = None
            continue
        elevation = float(np.degrees(np.arcsin(min(1.0, abs(float(axes[j] @ up))))))
        if n.startswith("post"):
            out[n] = 90.0 - elevation
        elif n.startswith("bar"):
            out[n] = elevation
        else:
            out[n] = float(np.degrees(np.arccos(min(1.0, abs(float(axes[j] @ true_axes[i]))))))
    return out


def recover_scene(name):
    base, scene_kwargs, scene_options = EXTRA_ROWS.get(name, (name, {}, None))
    s = sqparts.builtin_scene(base, **scene_kwargs)
    depth = np.asarray(sqparts.render_range_image(s.parts, s.camera))

    def run():
        if scene_options is None:
            return sqparts.recover(depth, s.camera, **SCENE_OPTIONS.get(name, {}))
        return sqparts.recover_scene(depth, s.camera, scene=sqparts.SceneSettings(**scene_options))

    t0 = time.perf_counter()
    run()
    cold = time.perf_counter() - t0
    warm = [run() for _ in range(WARM_RUNS)]
    assert len({round(w.cost.total, 6) for w in warm}) == 1, "recovery is not deterministic"
    r = warm[-1]
    timings = {k: float(np.median([w.timings[k] for w in warm])) for k in r.timings}
    found = true_parts_found(s.parts, r.parts, s.camera, s.part_names)
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
        "raw_bits": r.settings.get("raw_bits"),
        "candidates": getattr(r, "candidates", None),
        "regions": r.settings.get("regions"),
        "selection": getattr(r, "selection_method", None),
        "via": "recover" if scene_options is None else "recover_scene",
        "true_parts_found": found,
        "true_found_count": int(sum(v["found"] for v in found.values())),
        "timings_s": timings,
        "warm_runs_total_s": [w.timings["total"] for w in warm],
        "compile_s": cold - timings["total"],
    }
    if base == "gate":
        row["angles_deg"] = gate_angles(r.parts, s.parts, s.camera, s.part_names)
        row["prettify"] = getattr(r, "prettify", None)
    print(
        f"{name}: {row['found_parts']}/{row['true_parts']} parts ({row['true_found_count']} true parts found), "
        f"explained {row['fraction_explained']:.1%}, commission {row['commission_fraction']:.1%}, "
        f"E {row['description_length_bits']:.0f} bits, {timings['total']:.1f} s warm (median of {WARM_RUNS}), "
        f"compile {row['compile_s']:.1f} s" + (f", angles {row['angles_deg']}" if "angles_deg" in row else ""),
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
    names = list(SCENE_OPTIONS) + list(EXTRA_ROWS)
    ap.add_argument("--scenes", nargs="+", choices=names, default=names)
    args = ap.parse_args()
    rows = []
    for name in args.scenes:
        row, r = recover_scene(name)
        rows.append(row)
        from sqparts._plot import save_report

        save_report(result_path(f"report_{name}", "png"), r, title=name)
    spread = perturbation_spread("human") if "human" in args.scenes else None
    if not {"human", "castings"} <= set(args.scenes):
        save("recover", {"scenes": rows, "perturbation": spread, "selection": None})
        return
    sel = best_first_vs_exact([candidate_problem("human"), candidate_problem("castings")])
    print(
        f"best-first optimal in {sel['best_first_optimal_rate']:.0%} of {sel['trials']} problems, "
        f"mean excess {sel['mean_excess_bits']:.1f} bits",
        flush=True,
    )
    save("recover", {"scenes": rows, "perturbation": spread, "selection": sel})


if __name__ == "__main__":
    main()
