"""Prototype (not in the package): would dividing a view's verified scores by how well its
own recovered parts verify on the same image separate known from unknown objects better?
Offline, on bench run 5's rows (``results/recognition_verified.json``) and the cached test
recoveries; prints the ROC area of the true object's score against the best other
object's score, raw and normalised (session 30; see benchmarks/README.md).

    JAX_PLATFORMS=cpu python benchmarks/proto_rejection.py
"""

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_recognition as B

import sqparts
from sqparts._describe import describe
from sqparts._recognize import Observation, verify_poses

res = json.loads((B.ROOT / "benchmarks" / "results" / "recognition_verified.json").read_text())
cache = json.loads(B.CACHE.read_text())
meshes = {n: B.normalised_mesh(B.DATA / "models" / f"{n}.obj") for n in B.MESHES}
meshes["teapot"] = B.normalised_mesh(B.DATA / "teapot.obj")
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


def roc_area(a, b):
    return float(np.mean(a[:, None] > b[None, :]) + 0.5 * np.mean(a[:, None] == b[None, :]))


for name, f in [
    ("raw", lambda s: s),
    ("score / sqrt(self)", lambda s: s / np.sqrt(own)),
    ("score / self", lambda s: s / own),
]:
    a, b = f(true), f(other)
    tau = np.quantile(b, 0.9)
    print(f"{name:20s} ROC area {roc_area(a, b):.3f}; at 90% unknown rejected, known rejected {np.mean(a < tau):.2f}")
