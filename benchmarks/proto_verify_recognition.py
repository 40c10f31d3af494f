"""Prototype (session 28, not part of the package): verify recognition candidates by
rendering the stored parts into the query's camera and comparing with its depth.

For every test view of ``bench_recognition.py`` (from its cached recoveries) and every
stored view of every object: the best part-match score, and the alignment's refined
starts (each a pose of the stored main solid in the query's camera). Each pose's stored
parts are rendered into the query camera (``render_layers``) and scored against the
observed depth D (all finite pixels; the plate is not masked): agreement
exp(-(R - D)² / 2τ²), τ = k x the object's scale; explained = agreement summed over D's
pixels / their count; precision = agreement summed over R's pixels / those not hidden
behind a nearer observed surface. An object's score is its best over views and poses.
``refine`` (session 29) first fits every pose to the observed points by ICP
(``sqparts.fit_pose``, what the package now does) and renders again.

    JAX_PLATFORMS=cpu python benchmarks/proto_verify_recognition.py candidates  # ~18 min
    JAX_PLATFORMS=cpu python benchmarks/proto_verify_recognition.py render      # ~4 min
    JAX_PLATFORMS=cpu python benchmarks/proto_verify_recognition.py analyse
    JAX_PLATFORMS=cpu python benchmarks/proto_verify_recognition.py refine      # ~15 min
    JAX_PLATFORMS=cpu python benchmarks/proto_verify_recognition.py analyse-refined

Intermediate pickles go to ``$SQPARTS_VERIFY_WORK`` (default /tmp/sqparts-verify).
"""

from __future__ import annotations

import json
import os
import pickle
import sys
import tempfile
import time
from multiprocessing import Pool
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_recognition as B
import numpy as np

from sqparts._database import transform_parts
from sqparts._describe import describe
from sqparts._encoding import part_vectors, render_layers
from sqparts._part import stack_parts
from sqparts._recognize import (
    MatchSettings,
    Observation,
    align_candidates,
    fit_pose,
    match_descriptions,
    observed_points,
)

WORK = Path(os.environ.get("SQPARTS_VERIFY_WORK", "/tmp/sqparts-verify"))


def build_db():
    views = B.plan()
    cache = json.loads(B.CACHE.read_text())
    return views, cache, B.learnt_database(views, cache, tempfile.mkdtemp())


_DB = None


def _work(args):
    key, figs = args
    settings = MatchSettings()
    figures = [B._parts(f) for f in figs]
    queries = list(enumerate(figures))
    if len(figures) > 1:
        queries.append((-1, stack_parts([p for f in figures for p in f])))
    res = []
    for f, parts in queries:
        query = describe(parts)
        for name, stored_views in _DB.objects.items():
            for k, view in enumerate(stored_views):
                pm = max(match_descriptions(query, s.description, settings).score for s in view.descriptions)
                found = align_candidates(query, view.main.description, settings)
                res.append(dict(figure=f, name=name, view=k, part=pm, align=[(a.score, a.pose) for a in found]))
    return key, res


def candidates():
    global _DB
    views, cache, _DB = build_db()
    jobs = [(k, cache[k]["figures"]) for k, _n, r, _s in views if r == "test" and cache[k]["figures"]]
    t0 = time.time()
    with Pool(2) as pool:
        out = dict(pool.map(_work, jobs, chunksize=1))
    pickle.dump(out, open(WORK / "candidates.pkl", "wb"))
    print(len(out), f"{time.time() - t0:.0f} s")


def render():
    views, _cache, db = build_db()
    meshes = B.all_meshes()
    cands = pickle.load(open(WORK / "candidates.pkl", "rb"))
    out = {}
    for key, name, _r, spec in views:
        if key not in cands:
            continue
        depth, cam = B.render(name, spec, meshes)
        vecs, owners = [], []
        for ci, c in enumerate(cands[key]):
            stored = db.objects[c["name"]][c["view"]].main.parts
            for j, (_a, pose) in enumerate(c["align"]):
                v = part_vectors(transform_parts(stored, pose))
                owners.append((ci, j, len(v)))
                vecs.append(v)
        layers = render_layers(np.concatenate(vecs), cam)
        bounds = np.cumsum([0] + [n for *_, n in owners])
        renders = np.stack([np.min(layers[a:b], 0) for a, b in zip(bounds[:-1], bounds[1:])])
        meta = [(c["figure"], c["name"], c["view"], c["part"], [a for a, _ in c["align"]]) for c in cands[key]]
        out[key] = dict(depth=depth, renders=renders.astype(np.float32), owners=owners, meta=meta)
        print(key, len(owners), flush=True)
    pickle.dump(out, open(WORK / "renders.pkl", "wb"))


def refine():
    """Every candidate pose refined by ICP onto the observed points, then rendered again."""
    views, _cache, db = build_db()
    cands = pickle.load(open(WORK / "candidates.pkl", "rb"))
    rendered = pickle.load(open(WORK / "renders.pkl", "rb"))
    out = {}
    t0 = time.time()
    for key, name, _r, _spec in views:
        if key not in cands:
            continue
        depth = rendered[key]["depth"]
        cam = B.camera() if name != "human" else B.camera(focal=B.RESOLUTION * 4.0 / 2.4)
        pts = observed_points(Observation(depth, cam, np.isfinite(depth)[None]), np.isfinite(depth))
        vecs, owners = [], []
        for ci, c in enumerate(cands[key]):
            stored = db.objects[c["name"]][c["view"]].main
            sigma = 0.08 * stored.description.scale
            for j, (_a, pose) in enumerate(c["align"]):
                better = fit_pose(pts, stored.description, pose, sigma)
                v = part_vectors(transform_parts(stored.parts, better))
                owners.append((ci, j, len(v)))
                vecs.append(v)
        layers = render_layers(np.concatenate(vecs), cam)
        bounds = np.cumsum([0] + [n for *_, n in owners])
        renders = np.stack([np.min(layers[a:b], 0) for a, b in zip(bounds[:-1], bounds[1:])])
        out[key] = dict(rendered[key], renders=renders.astype(np.float32))
        print(key, len(owners), f"{time.time() - t0:.0f} s", flush=True)
    pickle.dump(out, open(WORK / "refined.pkl", "wb"))


def _verify(depth, rendered, tau):
    seen, model = np.isfinite(depth), np.isfinite(rendered)
    both = seen & model
    agree = np.zeros(depth.shape)
    agree[both] = np.exp(-0.5 * ((rendered[both] - depth[both]) / tau) ** 2)
    hidden = both & (depth < rendered - 2 * tau)
    return agree[seen].sum() / max(seen.sum(), 1), agree[model].sum() / max((model & ~hidden).sum(), 1)


COMBINE = {
    "part match x alignment (today)": lambda ex, pr, p, a: np.sqrt(p * a),
    "verification": lambda ex, pr, p, a: np.sqrt(ex * pr),
    "verification F1": lambda ex, pr, p, a: 2 * ex * pr / (ex + pr + 1e-9),
    "verification x part match": lambda ex, pr, p, a: (ex * pr * p) ** (1 / 3),
    "verification x part match x alignment": lambda ex, pr, p, a: (ex * pr * p * a) ** (1 / 4),
    "verification x alignment": lambda ex, pr, p, a: (ex * pr * a) ** (1 / 3),
}


def analyse(which="renders"):
    _views, _cache, db = build_db()
    rendered = pickle.load(open(WORK / f"{which}.pkl", "rb"))
    scale = {n: np.mean([v.main.description.scale for v in vs]) for n, vs in db.objects.items()}
    for k in (0.05, 0.1, 0.2):
        for label, combine in COMBINE.items():
            correct = 0
            for key, e in rendered.items():
                best: dict[str, float] = {}
                for (ci, j, _n), r in zip(e["owners"], e["renders"]):
                    _f, name, _view, part, align = e["meta"][ci]
                    s = combine(*_verify(e["depth"], r, k * scale[name]), part, align[j])
                    best[name] = max(best.get(name, -1.0), s)
                correct += max(best, key=best.__getitem__) == key.split("/")[0]
            print(f"tau {k:.2f} x scale  {label:40s} top-1 {correct} / {len(rendered)}")


if __name__ == "__main__":
    WORK.mkdir(parents=True, exist_ok=True)
    {
        "candidates": candidates,
        "render": render,
        "refine": refine,
        "analyse": analyse,
        "analyse-refined": lambda: analyse("refined"),
    }[sys.argv[1]]()
