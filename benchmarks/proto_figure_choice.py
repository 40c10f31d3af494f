"""Prototype (not in the package): which figure of a test view should decide recognition?

``match_figures`` matches every figure of a view on its own and all of them together,
keeps each object's best score over those queries and accepts the top object when its
lead over the others (``sqparts.lead``) reaches the calibrated threshold (rule A). An
occluding plate, or a fragment torn off at a depth jump, is a figure of its own, and its
best match can then outscore the object's own figure. The alternative tried here (rule
B): cohort-normalise each query on its own (its top object's lead over the rest of *its*
list) and answer with the query whose lead is largest; B.25 considers only queries with
at least a quarter of the largest query's pixels (fragments give chance leads).

``run`` matches every test view of the 128 x 128 benchmark again, from its recovery
cache, with today's ``ModelDatabase.match`` (the verified matcher), and keeps every
query's full score list (``results/figure_choice.json``; ``--part i --parts n`` runs
every n-th view, so two processes can share the work). ``analyse`` decides every view
under each rule with run 8's calibrated lead threshold, for the known case and with the
view's own object left out (unknown), and prints the figures of ``benchmarks/README.md``;
the first 31 views matched (``EXPLORATION``) were looked at before the rules were fixed,
the other 65 are held out.

    JAX_PLATFORMS=cpu python benchmarks/proto_figure_choice.py run --part 0 --parts 2 &
    JAX_PLATFORMS=cpu python benchmarks/proto_figure_choice.py run --part 1 --parts 2
    python benchmarks/proto_figure_choice.py analyse
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_recognition as B

from sqparts import Observation, describe, lead, stack_parts
from sqparts._recognize import MatchSettings

OUT = B.RESULTS / "figure_choice.json"  # the summary; the rows of each part beside it
THRESHOLD = 0.14527608009866277
"""Run 8's lead threshold, calibrated on the learnt views (``results/recognition_128.json``)."""
EXPLORATION = [
    "spot/test0", "spot/test2", "spot/test4", "spot/test6", "fish/test0", "fish/test2", "fish/test4",
    "fish/test6", "penguin/test0", "penguin/test2", "penguin/test4", "penguin/test6", "wingnut/test0",
    "wingnut/test2", "wingnut/test4", "spot/test1", "spot/test3", "spot/test5", "spot/test7",
    "fish/test1", "fish/test3", "fish/test5", "fish/test7", "penguin/test1", "penguin/test3",
    "penguin/test5", "penguin/test7", "wingnut/test1", "wingnut/test3", "wingnut/test5",
    "wingnut/test7",
]  # fmt: skip


def run(part: int, parts: int) -> None:
    B.set_resolution(128)
    cache = json.loads(B.CACHE.read_text())
    views = B.plan()
    db = B.learnt_database(views, cache, Path(tempfile.mkdtemp(prefix="sqparts-figure-choice-")))
    meshes = B.all_meshes()
    out, path = [], OUT.with_name(f"figure_choice_part{part}.json")
    for key, name, spec in [(k, n, s) for k, n, r, s in views if r == "test"][part::parts]:
        t0 = time.perf_counter()
        figures = [B._parts(f) for f in cache[key]["figures"]]
        depth, cam = B.render(name, spec, meshes)
        labels = np.asarray(cache[key]["labels"]).reshape(depth.shape)
        obs = Observation(depth, cam, np.stack([labels == k for k in range(len(figures))]))
        queries = [(i, f, obs.figures[i]) for i, f in enumerate(figures)]
        if len(figures) > 1:  # as match_figures: all figures together too
            queries.append((-1, stack_parts([p for f in figures for p in f]), obs.figures.any(0)))
        rows = []
        for i, q, mask in queries:
            found = db.match(describe(q), settings=MatchSettings(), observation=obs, figure=None if i < 0 else mask)
            rows.append({"query": i, "parts": len(q), "pixels": int(mask.sum()), "scores": {r[0]: r[1] for r in found}})
        out.append({"view": key, "object": name, "plate": bool(spec.get("plate")), "queries": rows})
        path.write_text(json.dumps(out) + "\n")
        print(f"{key}: {time.perf_counter() - t0:.1f} s", flush=True)


def _lead(scores: dict) -> float:
    """The top score's :func:`sqparts.lead` over the rest of ``scores``."""
    s = sorted(scores.values(), reverse=True)
    return lead(s[0], s[1:])


def rule_a(queries, drop=None):
    """Each object's best over the queries; the top object's lead over that list."""
    best: dict = {}
    for q in queries:
        for n, v in q["scores"].items():
            if n != drop:
                best[n] = max(best.get(n, -np.inf), v)
    return max(best, key=best.get), _lead(best)


def rule_b(queries, drop=None, min_share=0.0):
    """The query whose own top object leads its own list by most (queries with fewer than
    ``min_share`` x the largest query's pixels left out)."""
    largest = max(q["pixels"] for q in queries)
    leads = []
    for q in queries:
        if q["pixels"] >= min_share * largest:
            s = {n: v for n, v in q["scores"].items() if n != drop}
            leads.append((_lead(s), max(s, key=s.get)))
    lead, top = max(leads)
    return top, lead


RULES = {"A (today)": rule_a, "B": rule_b, "B.25": functools.partial(rule_b, min_share=0.25)}


def analyse() -> None:
    rows = []
    for path in sorted(OUT.parent.glob("figure_choice_part*.json")):
        rows += json.loads(path.read_text())
    summary = {}
    for subset, chosen in (
        ("held out", [r for r in rows if r["view"] not in EXPLORATION]),
        ("exploration", [r for r in rows if r["view"] in EXPLORATION]),
        ("all", rows),
    ):
        for label, rule in RULES.items():
            known = [rule(r["queries"]) for r in chosen]
            unknown = np.array([rule(r["queries"], drop=r["object"])[1] for r in chosen])
            evidence = np.array([e for _, e in known])
            right = np.array([t == r["object"] for (t, _), r in zip(known, chosen)])
            tau = np.quantile(unknown, 0.9)
            row = {
                "views": len(chosen),
                "top1": int(right.sum()),
                "accepted_and_correct": float(np.mean(right & (evidence >= THRESHOLD))),
                "known_wrongly_rejected": float(np.mean(evidence < THRESHOLD)),
                "unknown_rejected": float(np.mean(unknown < THRESHOLD)),
                "roc_area": B.roc_area(evidence, unknown),
                "known_rejected_at_90pct_unknown_rejected": float(np.mean(evidence < tau)),
            }
            summary[f"{subset} / {label}"] = row
            print(
                f"{subset:12s} {label:10s} views {row['views']:3d} top-1 {row['top1']:3d} "
                f"accepted and correct {row['accepted_and_correct']:.1%} known rejected "
                f"{row['known_wrongly_rejected']:.1%} unknown rejected {row['unknown_rejected']:.1%} "
                f"ROC {row['roc_area']:.3f} known rejected at 90% unknown {row['known_rejected_at_90pct_unknown_rejected']:.1%}"
            )
    B.save("figure_choice", {"threshold": THRESHOLD, "exploration": EXPLORATION, "summary": summary})


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("step", choices=["run", "analyse"])
    ap.add_argument("--part", type=int, default=0)
    ap.add_argument("--parts", type=int, default=1)
    args = ap.parse_args()
    run(args.part, args.parts) if args.step == "run" else analyse()
