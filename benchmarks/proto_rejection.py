"""Prototype (not in the package): would dividing a view's verified scores by how well its
own recovered parts verify on the same image separate known from unknown objects better?
Offline, on bench run 5's rows (``results/recognition_verified.json``) and the cached test
recoveries; prints the ROC area of the true object's score against the best other
object's score, raw and normalised (session 30; see benchmarks/README.md).

    JAX_PLATFORMS=cpu python benchmarks/proto_rejection.py [self | margin [--every K]]

``margin``: every K-th test view (default 3) matched again by the verified matcher with
every object's score kept; the known case is the view's own list, the unknown case the
list without its object. Compares the ROC area of the best score with that of the
margin (best minus second best) and of their product.
"""

import argparse
import json
import multiprocessing
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_recognition as B

import sqparts
from sqparts._describe import describe
from sqparts._recognize import MatchSettings, Observation, verify_poses


def report(label: str, known, unknown) -> None:
    """ROC area of a statistic on known against unknown views, and the fraction of known
    views rejected at the threshold that rejects 90% of the unknown ones."""
    tau = np.quantile(unknown, 0.9)
    print(
        f"{label:20s} ROC area {B.roc_area(known, unknown):.3f}; at 90% unknown rejected, known rejected {np.mean(known < tau):.2f}"
    )


def self_normalised():
    res = json.loads((B.ROOT / "benchmarks" / "results" / "recognition_verified.json").read_text())
    cache = json.loads(B.CACHE.read_text())
    meshes = B.all_meshes()
    out = []
    for r in res["rows"]:
        e = cache[r["view"]]
        figs = [B._parts(f) for f in e["figures"]]
        if not figs:
            out.append(dict(r, self=None))
            continue
        depth, cam = B.render(r["object"], r["spec"], meshes)
        labels = np.asarray(e["labels"]).reshape(depth.shape)
        obs = Observation(depth, cam, np.stack([labels == k for k in range(len(figs))]))
        parts = sqparts.stack_parts([p for f in figs for p in f])
        scale = describe(parts).scale
        v0 = float(verify_poses([parts], obs, obs.figures.any(0), 0.1 * scale)[0])
        out.append(dict(r, self=v0))
        print(r["view"], round(v0, 3), round(r["true_score"], 3), round(r["unknown_top_score"], 3), flush=True)

    rows = [r for r in out if r["self"]]
    true, other, own = (np.array([r[k] for r in rows]) for k in ("true_score", "unknown_top_score", "self"))

    for name, f in [
        ("raw", lambda s: s),
        ("score / sqrt(self)", lambda s: s / np.sqrt(own)),
        ("score / self", lambda s: s / own),
    ]:
        report(name, f(true), f(other))


def margin(every: int):
    cache = json.loads(B.CACHE.read_text())
    views = B.plan()
    folder = Path(tempfile.mkdtemp(prefix="sqparts-proto-db-"))
    B.learnt_database(views, cache, folder)
    tests = [(key, name, spec, cache[key]) for key, name, role, spec in views if role == "test"][::every]
    jobs = [(str(folder), 1.0, MatchSettings(), key, name, spec, e) for key, name, spec, e in tests]
    with multiprocessing.get_context("spawn").Pool(2) as pool:
        rows = [r for r in pool.map(B.recognise_view, jobs, chunksize=1) if r["scores"]]
    known, unknown = [], []
    for r in rows:
        s = sorted(r["scores"].values(), reverse=True)
        known.append((s[0], s[0] - s[1], r["top"] == r["object"]))
        o = sorted((v for n, v in r["scores"].items() if n != r["object"]), reverse=True)
        unknown.append((o[0], o[0] - o[1]))
    k, u = np.array([x[:2] for x in known]), np.array(unknown)
    print(f"{len(rows)} views, top-1 {np.mean([x[2] for x in known]):.2f}")
    for label, f in [
        ("best", lambda a: a[:, 0]),
        ("margin", lambda a: a[:, 1]),
        ("best x margin", lambda a: a[:, 0] * a[:, 1]),
    ]:
        report(label, f(k), f(u))
    out = Path(tempfile.gettempdir()) / "proto_rejection_margin.json"
    out.write_text(json.dumps(rows))
    print("rows:", out)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("mode", nargs="?", default="self", choices=["self", "margin"])
    ap.add_argument("--every", type=int, default=3)
    args = ap.parse_args()
    self_normalised() if args.mode == "self" else margin(args.every)
