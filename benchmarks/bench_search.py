"""Local search: accuracy on synthetic single parts, sampling densities, throughput.

Cases: random single parts (sizes 0.08-0.25 m, squareness 0.2-1.8, any orientation),
half with taper and bend; pinhole and orthographic; each variant clean, with Gaussian
noise (σ_n = 2 mm), quantised to 6 bits, or half occluded by a box in front. A case
succeeds when the symmetric surface Chamfer distance between the best candidate and the
truth (both tessellated, 2000 points each) is at most 2% of the part's size (its
largest dimension, 2·max a_i). The region's figure is its piece of the rubber sheet
(:func:`sqparts.torn_components`: the image torn at depth jumps), as figure/ground gives
it in recovery, so an occluder in front is another figure that hides the part.

    python benchmarks/bench_search.py [--cases 16] [--grids coarse default ...]

Case i cycles through the 16 combinations (pinhole or not, variant, deformed or not), so
``--cases 48`` runs each three times with different random parts.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax
import numpy as np
from _common import chamfer, make_case, result_path, save

import sqparts

VARIANTS = ("clean", "noise", "6-bit", "occluded")
CUSTOM = {
    "orient-45": sqparts.Grid(axis_step=45.0, roll_step=45.0),
    "orient-30": sqparts.Grid(axis_step=30.0, roll_step=30.0, bends=(0.0,)),
    "sizes-5": sqparts.Grid(lengths=(0.2, 0.3, 0.45, 0.7, 1.0), axis_step=45.0, roll_step=45.0, bends=(0.0,)),
}


def run_grid(name, grid, cases, refine=None):
    """Every case fitted with the ``region`` preset on ``grid`` (``refine``: its
    ``refine_orientations``, None: the preset's)."""
    fields = {} if refine is None else {"refine_orientations": refine}
    rows = []
    t_compile = None
    for k, c in enumerate(cases):
        data = sqparts.prepare(c["depth"], c["camera"], figure=c["figure"])
        st = sqparts.make_settings(data, grid=grid, max_size=0.3, **fields)
        t0 = time.perf_counter()
        fit = sqparts.fit_region(data, st, c["centre"])
        jax.block_until_ready(fit.gamma)
        wall = time.perf_counter() - t0
        if k == 0:  # the first case pays compilation: time it again warm
            t0 = time.perf_counter()
            fit = sqparts.fit_region(data, st, c["centre"])
            jax.block_until_ready(fit.gamma)
            warm = time.perf_counter() - t0
            t_compile, wall = wall - warm, warm
        size = 2 * float(np.max(np.asarray(c["truth"].size)))
        ch = chamfer(fit.parts[0], c["truth"]) / size
        g = np.asarray(fit.gamma)
        rows.append(
            {
                "case": k,
                "variant": c["variant"],
                "pinhole": c["pinhole"],
                "deformed": c["deformed"],
                "chamfer_rel": ch,
                "success": bool(ch <= 0.02),
                "gamma": float(g[0]),
                "visible_pixels": c["visible"],
                "ratio": fit.ratio,
                "wall_s": wall,
            }
        )
        print(
            f"  {name} case {k:2d} {c['variant']:8s} {'pin' if c['pinhole'] else 'ortho'} "
            f"{'deformed' if c['deformed'] else 'plain   '} chamfer {ch:.3f} Γ {g[0]:.0f}/{c['visible']} "
            f"ratio {fit.ratio:.2f} {wall:.2f} s",
            flush=True,
        )
    return {
        "grid": name,
        "refine_orientations": st.refine_orientations,
        "hypotheses": grid.size,
        "compile_s": t_compile,
        "median_wall_s": statistics.median(r["wall_s"] for r in rows),
        "success_rate": float(np.mean([r["success"] for r in rows])),
        "success_rate_5pct": float(np.mean([r["chamfer_rel"] <= 0.05 for r in rows])),
        "median_chamfer_rel": float(np.median([r["chamfer_rel"] for r in rows])),
        "median_ratio": float(np.median([r["ratio"] for r in rows])),
        "cases": rows,
    }


def throughput(repeats: int = 3):
    """Hypotheses/s per region, pruned against brute force in the same run, and s/image."""
    s = sqparts.builtin_scene("human")
    depth = np.asarray(sqparts.render_range_image(s.parts, s.camera))
    data = sqparts.prepare(depth, s.camera)
    out = {}
    for grid in ("coarse", "default"):
        st = sqparts.make_settings(data, grid=grid)
        centre = np.array([52, 63])
        res = {}
        for label, prune in (("pruned", True), ("brute", False)):
            st = dataclasses.replace(st, prune=prune)
            sqparts.fit_region(data, st, centre)  # compile
            times = []
            for _ in range(repeats if (grid == "coarse" or prune) else 1):
                t0 = time.perf_counter()
                jax.block_until_ready(sqparts.fit_region(data, st, centre).gamma)
                times.append(time.perf_counter() - t0)
            res[label] = statistics.median(times)
        t0 = time.perf_counter()
        fits, _, _ = sqparts.fit_image(
            depth, s.camera, dataclasses.replace(sqparts.SEARCH_PRESETS["region"], grid=grid)
        )
        jax.block_until_ready([f.gamma for f in fits])
        per_image = time.perf_counter() - t0
        out[grid] = {
            "hypotheses": st.grid.size,
            "window": st.window,
            "pruned_s_per_region": res["pruned"],
            "brute_s_per_region": res["brute"],
            "speedup": res["brute"] / res["pruned"],
            "hypotheses_per_s_pruned": st.grid.size / res["pruned"],
            "hypotheses_per_s_brute": st.grid.size / res["brute"],
            "regions": len(fits),
            "s_per_image": per_image,
        }
        print(f"  throughput {grid}: {out[grid]}", flush=True)
    return out


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for r in results:
        name = r["grid"] + (f" +{r['refine_orientations']}" if r["refine_orientations"] else "")
        ax[0].scatter(r["hypotheses"], r["success_rate"], label=name)
        ax[0].annotate(name, (r["hypotheses"], r["success_rate"]))
        ax[1].scatter(r["median_wall_s"], r["median_chamfer_rel"])
        ax[1].annotate(name, (r["median_wall_s"], r["median_chamfer_rel"]))
    ax[0].set_xscale("log")
    ax[0].set_xlabel("hypotheses per region")
    ax[0].set_ylabel("success rate (Chamfer <= 2%)")
    ax[1].set_xlabel("median s per region (warm)")
    ax[1].set_ylabel("median relative Chamfer")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=16)
    ap.add_argument("--grids", nargs="*", default=["coarse", "default", "orient-45", "orient-30", "sizes-5"])
    ap.add_argument(
        "--refine-orientations",
        nargs="*",
        type=int,
        default=[None],
        help="each grid once per value (survivors refined in orientation; default: the region preset's)",
    )
    ap.add_argument("--no-throughput", action="store_true")
    args = ap.parse_args()
    cases = [make_case(i, VARIANTS) for i in range(args.cases)]
    results = []
    for name, refine in ((n, r) for n in args.grids for r in args.refine_orientations):
        grid = CUSTOM[name] if name in CUSTOM else sqparts.grid_preset(name)
        results.append(run_grid(name, grid, cases, refine))
        r = results[-1]
        print(
            f"{name} (refine_orientations {r['refine_orientations']}): {grid.size} hypotheses, "
            f"success {r['success_rate']:.0%}, median Chamfer {r['median_chamfer_rel']:.3f}, "
            f"{r['median_wall_s']:.2f} s/region",
            flush=True,
        )
    payload = {"cases": args.cases, "image": "64x64", "dtype": "float32", "densities": results}
    if not args.no_throughput:
        payload["throughput"] = throughput()
    if results:
        plot(results, result_path("sampling_densities", "png"))
    save("search", payload)


if __name__ == "__main__":
    main()
