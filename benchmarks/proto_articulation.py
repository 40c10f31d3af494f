"""Prototype (not in the package): verification with the stored parts articulated.

Session 42 put the ``joint`` mode in the package (``MatchSettings.articulated``,
``sqparts._recognize.articulate``), with the tree made once per stored view and a step
that also moves the whole solid; this script keeps session 41's measurement.

The verified matcher (``ModelDatabase.match``) fits each stored view to the observed
points as one rigid solid (``fit_pose``) and renders it there (``verify_poses``). The
person is learnt standing and shown walking, waving, straddling: a rigid pose cannot
put its limbs on the data (section 1's stability under configuration). Two
articulations of each posed solid, before it is rendered, are tried here; a pose then
verifies as the better of its rigid and its articulated rendering:

* ``free``: every stored part refined on its own by ICP (weighted Kabsch) on the
  observed points nearest its surface;
* ``joint``: a kinematic tree over the parts that touch (the largest part its root,
  breadth first), each part rotated with the parts beyond it about its joint with its
  parent (the midpoint of the closest pair of surface points), fitted by Kabsch about
  that point on the observed points nearest the moved parts.

``run --mode M`` matches a fixed set of test views of the 128 x 128 benchmark from its
recovery cache (all eight views of the person; ``test1`` of every other object, fixed by
name before any articulated score was seen) and saves every object's score per view in
``results/articulation_<M>.json``; ``analyse`` prints the table of ``benchmarks/README.md``.

    JAX_PLATFORMS=cpu python benchmarks/proto_articulation.py run --mode rigid
    JAX_PLATFORMS=cpu python benchmarks/proto_articulation.py run --mode free
    JAX_PLATFORMS=cpu python benchmarks/proto_articulation.py run --mode joint
    python benchmarks/proto_articulation.py analyse
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import KDTree
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_recognition as B

import sqparts._database as D
import sqparts._recognize as Rz
from sqparts import Observation, Part, describe
from sqparts._describe import surface_samples

ITERATIONS = 6
VIEWS = [f"human/test{k}" for k in range(8)] + [f"{m}/test1" for m in [*B.MESHES, "teapot"]]


def _kabsch(src, dst, w, centre=None):
    """Weighted rotation (and translation, unless about a fixed ``centre``) taking src to dst."""
    sc = np.average(src, 0, w) if centre is None else centre
    dc = np.average(dst, 0, w) if centre is None else centre
    u, _, vt = np.linalg.svd(((src - sc) * w[:, None]).T @ (dst - dc))
    r = vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
    return r, dc - r @ sc


def articulate(parts: Part, points: np.ndarray, sigma: float, mode: str) -> Part:
    size = np.asarray(parts.size, float).reshape(-1, 3)
    rot = Rotation.from_rotvec(np.asarray(parts.orientation, float).reshape(-1, 3)).as_matrix()
    pos = np.asarray(parts.position, float).reshape(-1, 3).copy()
    n = len(size)
    sq = np.asarray(parts.squareness, float).reshape(-1, 2)
    bend, taper = np.asarray(parts.bend, float).reshape(-1, 2), np.asarray(parts.taper, float).reshape(-1)
    local = [surface_samples(size[i], sq[i], bend[i], taper[i], np.eye(3), np.zeros(3), count=10) for i in range(n)]
    owner = np.concatenate([np.full(len(s), i) for i, s in enumerate(local)])
    flat = np.concatenate(local)

    def surface():
        return np.einsum("nab,nb->na", rot[owner], flat) + pos[owner]

    order, parent = [int(np.argmax(np.prod(size, 1)))], np.full(n, -1)
    if mode == "joint" and n > 1:
        touch = describe(parts).touching
        k = 0
        while k < len(order):
            for c in np.flatnonzero(touch[order[k]]):
                if int(c) not in order:
                    parent[c] = order[k]
                    order.append(int(c))
            k += 1
    joints = np.zeros((n, 3))
    s = surface()
    for c in order[1:]:
        a, b = s[owner == c], s[owner == parent[c]]
        d, j = KDTree(b).query(a)
        m = int(np.argmin(d))
        joints[c] = 0.5 * (a[m] + b[j[m]])

    def beyond(i):
        out = [i]
        for c in order:
            if parent[c] == i:
                out += beyond(c)
        return out

    gate = 8.0 * sigma
    for _ in range(ITERATIONS):
        d, j = KDTree(surface()).query(points, distance_upper_bound=gate)
        near = np.isfinite(d)
        d, j, dst = d[near], j[near], points[near]
        w = np.exp(-0.125 * (d / sigma) ** 2) + 1e-12
        for c in order[1:] if mode == "joint" else range(n):
            group = beyond(c) if mode == "joint" else [c]
            sel = np.isin(owner[j], group)
            if sel.sum() < 8:
                continue
            src = surface()[j[sel]]
            r, t = _kabsch(src, dst[sel], w[sel], joints[c] if mode == "joint" else None)
            for i in group:
                rot[i], pos[i] = r @ rot[i], r @ pos[i] + t
                joints[i] = r @ joints[i] + t if i != c else joints[i]
    return Part(
        size=parts.size,
        squareness=parts.squareness,
        position=pos.astype(np.float32),
        orientation=Rotation.from_matrix(rot).as_rotvec().astype(np.float32),
        bend=parts.bend,
        taper=parts.taper,
    )


def run(mode: str) -> None:
    B.set_resolution(128)
    rigid_verify = Rz.verify_poses

    def verify(solids, observation, figure, tolerance):
        solids = list(solids)
        rigid = rigid_verify(solids, observation, figure, tolerance)
        if mode == "rigid" or not solids:
            return rigid
        points = Rz.observed_points(observation, figure)
        taus = np.broadcast_to(np.asarray(tolerance, float), (len(solids),))
        moved = [articulate(s, points, 0.8 * t, mode) for s, t in zip(solids, taus)]
        return np.maximum(rigid, rigid_verify(moved, observation, figure, tolerance))

    D.verify_poses = verify
    views, meshes = B.plan(), B.all_meshes()
    cache = json.loads(B.CACHE.read_text())
    db = B.learnt_database(views, cache, tempfile.mkdtemp(prefix="sqparts-articulation-"))
    rows = {}
    for key, name, role, spec in views:
        if role != "test" or key not in VIEWS:
            continue
        e = cache[key]
        figures = [B._parts(f) for f in e["figures"]]
        depth, cam = B.render(name, spec, meshes)
        labels = np.asarray(e["labels"]).reshape(depth.shape)
        observation = Observation(depth, cam, np.stack([labels == k for k in range(len(figures))]))
        t0 = time.perf_counter()
        _, matches = D.match_figures(figures, database=db, observation=observation)
        rows[key] = {"object": name, "seconds": time.perf_counter() - t0, "scores": {m.name: m.score for m in matches}}
        print(key, mode, f"{rows[key]['seconds']:.0f} s", list(rows[key]["scores"].items())[:3], flush=True)
    (B.RESULTS / f"articulation_{mode}.json").write_text(json.dumps({"mode": mode, "rows": rows}, indent=1) + "\n")


def analyse() -> None:
    runs = {
        m: json.loads((B.RESULTS / f"articulation_{m}.json").read_text())["rows"] for m in ("rigid", "free", "joint")
    }
    print("| view | " + " | ".join(f"{m}: true, best other" for m in runs) + " |")
    summary = {m: {"top1": [0, 0], "lead": [[], []]} for m in runs}
    for key in VIEWS:
        cells = []
        for m, rows in runs.items():
            row = rows[key]
            scores, name = row["scores"], row["object"]
            true = scores.get(name, 0.0)
            other = max(v for k, v in scores.items() if k != name)
            cells.append(f"{true:.3f}, {other:.3f}")
            person = int(name == "human")
            summary[m]["top1"][person] += int(true > other)
            summary[m]["lead"][person].append(true - other)
        print(f"| {key} | " + " | ".join(cells) + " |")
    for m, s in summary.items():
        print(
            f"{m}: top-1 person {s['top1'][1]}/8, others {s['top1'][0]}/11; median lead person "
            f"{np.median(s['lead'][1]):+.3f}, others {np.median(s['lead'][0]):+.3f}"
        )


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=["run", "analyse"])
    ap.add_argument("--mode", choices=["rigid", "free", "joint"], default="rigid")
    args = ap.parse_args()
    run(args.mode) if args.what == "run" else analyse()
