"""Pilot (not the full benchmark): recognition with the views rendered at another
resolution, on a subset of the test views fixed in advance (session 33; see
benchmarks/README.md).

``run``: every learnt view and the chosen test views (``--tests``, e.g. test0, test3 and
test6 of every object: two plain views and one behind the plate) rendered at
``--resolution`` pixels square (the focal length scaled with it, so the objects cover
the same share of the image), recovered as the benchmark does (kept in
``results/recognition_cache_<resolution>.json``, which a full run with ``--from-cache``
reuses), matched by the verified matcher against the database of the learnt views, and
the database calibrated. ``compare``: the same test views' rows of a saved 64 x 64 run
beside the pilot's: top-1, top-3, ROC area of the true object's score against the best
other object's, and known views rejected at the threshold that rejects 90% of unknown
ones.

    JAX_PLATFORMS=cpu python benchmarks/proto_resolution.py run --resolution 128 --tests test0,test3,test6
    JAX_PLATFORMS=cpu python benchmarks/proto_resolution.py compare --resolution 128
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_recognition as B
from _common import result_path, save

import sqparts._compile
from sqparts._recognize import MatchSettings

BASELINE = "recognition_session32_shortlist32"  # run 6: 64 x 64, the verified matcher


def run(resolution: int, tests: list[str]) -> None:
    B.set_resolution(resolution)
    sqparts._compile.enable_caches()
    meshes = B.all_meshes()
    views = [v for v in B.plan() if v[2] == "learn" or (v[2] == "test" and v[0].split("/")[1] in tests)]
    cache = json.loads(B.CACHE.read_text()) if B.CACHE.exists() else {}
    t0 = time.perf_counter()
    cache = B.recover_all(views, meshes, cache)
    recovery_s = time.perf_counter() - t0
    folder = tempfile.mkdtemp(prefix="sqparts-pilot-db-")
    db = B.learnt_database(views, cache, folder)
    settings = MatchSettings()
    jobs = [(folder, resolution, 1.0, settings, k, n, s, cache[k]) for k, n, role, s in views if role == "test"]
    with multiprocessing.get_context("spawn").Pool(2) as pool:  # matching is numpy on one core
        rows = pool.map(B.recognise_view, jobs, chunksize=1)
    t0 = time.perf_counter()
    threshold = db.calibrate(settings=settings)
    finish(resolution, tests, rows, threshold, time.perf_counter() - t0, dict(db.calibration), recovery_s)


def finish(resolution, tests, rows, threshold, calibrate_s, calibration, recovery_s) -> None:
    """Apply the calibrated threshold to the rows, summarise them as the benchmark does
    and save ``results/recognition_pilot_<resolution>.json``."""
    for r in rows:  # the calibrated threshold, as recognise_view applies it
        r["best"] = r["top"] if r["top_score"] >= threshold else None
        other = max((n for n in r["scores"] if n != r["object"]), key=r["scores"].get)
        r["unknown_best"] = r["unknown_best_shared"] = other if r["unknown_top_score"] >= threshold else None
    out = B.summarise(rows, threshold, calibrate_s, calibration)
    out["summary"]["recovery_wall_s"] = recovery_s
    save(
        f"recognition_pilot_{resolution}",
        {"settings": {"resolution": resolution, "tests": tests, "match": "MatchSettings()"}, **out, "rows": rows},
    )
    print(json.dumps(out["summary"], indent=1))


def compare(resolution: int) -> None:
    pilot = json.loads(result_path(f"recognition_pilot_{resolution}").read_text())
    base = {r["view"]: r for r in json.loads(result_path(BASELINE).read_text())["rows"]}
    for label, rows in (("64", [base[r["view"]] for r in pilot["rows"]]), (str(resolution), pilot["rows"])):
        known = [r["true_score"] for r in rows]
        unknown = [r["unknown_top_score"] for r in rows]
        tau = np.quantile(unknown, 0.9)
        print(
            f"{label:>4s}: top-1 {sum(r['top'] == r['object'] for r in rows)}/{len(rows)}, "
            f"top-3 {sum((r['rank'] or 99) <= 3 for r in rows)}, "
            f"plate views top-1 {sum(r['top'] == r['object'] for r in rows if r['spec'].get('plate'))}, "
            f"ROC area {B.roc_area(known, unknown):.3f}, known rejected at 90% unknown rejected "
            f"{np.mean(np.asarray(known) < tau):.0%}, median true {np.median(known):.3f}, "
            f"median best other {np.median(unknown):.3f}"
        )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=["run", "compare"])
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--tests", default="test0,test3,test6", help="test views of every object, by name")
    args = ap.parse_args()
    if args.what == "run":
        run(args.resolution, args.tests.split(","))
    else:
        compare(args.resolution)


if __name__ == "__main__":
    main()
