"""Selection (Eq. 7) by tabu search against the integer program, on the problems that
recoveries meet.

Every selection problem (area matrices and costs, :class:`sqparts.SelectionProblem`) that
:func:`sqparts.recover` solves is collected while recovering the scenes of
:func:`proto_coarse_to_fine.scenes` (the built-in scenes, the castings heap from six other
seeds, the chair turned three ways, the person in five poses) and, with ``--real``,
the real inputs of ``bench_real.py`` (the Kinect and stereo frames, the teapot's three
views; ``recover_scene``'s defaults). Each problem's groups of interacting candidates
(:meth:`~sqparts.SelectionProblem.groups`) with two or more candidates are then solved
by best-first, by tabu search (:func:`sqparts.select_tabu`) and by HiGHS to proven
optimality (:func:`sqparts.select_exact` without a node limit), each timed on its own.
Per group: candidates, E of each method above the proven optimum, seconds. The summary:
how often tabu search and best-first reach the optimum, and the seconds each method
takes in all.

    JAX_PLATFORMS=cpu python benchmarks/bench_select.py [--real]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import save

import sqparts
from sqparts import _select

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def collected(run) -> list:
    """The selection problems ``run()`` solves (every call of ``select_parts``)."""
    got, solve = [], _select.select_parts

    def keep(problem, **kw):
        got.append(problem)
        return solve(problem, **kw)

    _select.select_parts = keep
    try:
        run()
    finally:
        _select.select_parts = solve
    return got


def inputs(real: bool):
    from proto_coarse_to_fine import scenes

    for name, parts, cam in scenes():
        depth = np.asarray(sqparts.render_range_image(parts, cam))
        yield name, lambda d=depth, c=cam: sqparts.recover(d, c)
    if real:
        from bench_real import teapot_views

        for name, file in (("kinect", "grabber_frame0.pcd"), ("mug", "table_scene_mug_stereo_textured.pcd")):
            depth, cam = sqparts.read_range_image(DATA / file)
            yield name, lambda d=depth, c=cam: sqparts.recover_scene(d, c)
        for view, (depth, cam, up) in teapot_views().items():
            yield (
                f"teapot-{view}",
                lambda d=depth, c=cam, u=up: sqparts.recover_scene(d, c, scene=sqparts.SceneSettings(up=u)),
            )


def timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--real", action="store_true", help="the real inputs of bench_real.py too")
    args = ap.parse_args()
    # Compile best-first's program before anything is timed.
    sqparts.select_best_first(
        sqparts.SelectionProblem(
            np.eye(2),
            np.zeros((2, 2)),
            sqparts.Costs(part=1.0, explained=1.0, commission=1.0, omission=2.0, figure_pixels=2),
        )
    )
    rows = []
    for name, run in inputs(args.real):
        for problem in collected(run):
            for group in problem.groups():
                if len(group) < 2:
                    continue
                sub = problem.subproblem(group)
                (exact, optimal), t_exact = timed(lambda: sqparts.select_exact(sub, time_limit=600.0))
                tabu, t_tabu = timed(lambda: sqparts.select_tabu(sub))
                greedy, t_greedy = timed(lambda: sqparts.select_best_first(sub))
                best = sub.energy(exact)
                row = {
                    "input": name,
                    "candidates": len(group),
                    "proven": bool(optimal),
                    "E_optimum": best,
                    "tabu_above": sub.energy(tabu) - best,
                    "best_first_above": sub.energy(greedy) - best,
                    "exact_s": t_exact,
                    "tabu_s": t_tabu,
                    "best_first_s": t_greedy,
                }
                rows.append(row)
                print(
                    f"{name}: {len(group)} candidates, exact {t_exact:.3f} s, tabu {t_tabu:.3f} s "
                    f"(+{row['tabu_above']:.1f} bits), best-first +{row['best_first_above']:.1f} bits",
                    flush=True,
                )
    tabu_opt = sum(r["tabu_above"] <= 1e-6 for r in rows)
    greedy_opt = sum(r["best_first_above"] <= 1e-6 for r in rows)
    summary = {
        "groups": len(rows),
        "tabu_optimal": tabu_opt,
        "best_first_optimal": greedy_opt,
        "tabu_worst_above_bits": max((r["tabu_above"] for r in rows), default=0.0),
        "exact_s_total": sum(r["exact_s"] for r in rows),
        "tabu_s_total": sum(r["tabu_s"] for r in rows),
        "best_first_s_total": sum(r["best_first_s"] for r in rows),
        "exact_s_max": max((r["exact_s"] for r in rows), default=0.0),
        "tabu_s_max": max((r["tabu_s"] for r in rows), default=0.0),
    }
    print(summary)
    save("select" + ("_real" if args.real else ""), {"summary": summary, "rows": rows})


if __name__ == "__main__":
    main()
