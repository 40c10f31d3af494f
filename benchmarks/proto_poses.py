"""Prototype (not in the package): every verified pose of the recognition benchmark, kept.

``ModelDatabase.match`` scores a stored view by its best fitted pose, rigid or articulated,
and an object by its best view; everything below that maximum is thrown away. This script
keeps it, so that rules for scoring a pose (how much an articulation may cost, how the
explained and precision terms combine) can be compared on saved numbers instead of one
full benchmark run each.

``run`` matches, as the package did at 467070b (run 10: the alignment's starts alone,
``MatchSettings(pose_starts=0)``):

* every test view of the 128 x 128 benchmark from its recovery cache, each figure and all
  figures together (``match_figures``), verified on its range image;
* every stored view seen again (``view_observation``) against the database with itself
  left out, as ``ModelDatabase.calibrate`` does,

and saves, per query and per fitted pose of every stored view (its alignment start), the
verification's explained and precision terms at the three tolerances, rigid and
articulated, and the articulation's size: each part's rotation relative to the root part
(degrees) and the root's own motion relative to the rigid pose (degrees, and its
translation in the query's scales). Output: ``/tmp/sqparts_poses.json`` (13 MB, not
kept in the repository). ``analyse`` replays run 10's rule from it (the check: the same
decisions as ``results/recognition_128_levels.json``) and alternatives: articulation
priors, margins, the tolerances' weights, the explained term's exponent. ``truth`` verifies
the true object's stored views at the pose the benchmark's ground truth gives (the
learning and test views' rotations; translation fitted), against the best pose matching
found, on the views named (default: every test view but the person's). ``figures``
matches the views named as the package does now (``match_figures``) and prints, per
object, its score and the query it came from: which figure (its pixels and parts) or all
figures together (-1).

    JAX_PLATFORMS=cpu python benchmarks/proto_poses.py run     # about 36 minutes
    python benchmarks/proto_poses.py analyse
    JAX_PLATFORMS=cpu python benchmarks/proto_poses.py truth goathead/test7 fish/test7
    JAX_PLATFORMS=cpu python benchmarks/proto_poses.py figures cat/test7 human/test4
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_recognition as B
import numpy as np
from scipy.spatial.transform import Rotation

import sqparts._recognize as R
from sqparts._compile import concurrently, enable_caches
from sqparts._database import match_figures, transform_parts, view_observation
from sqparts._describe import describe, part_volume
from sqparts._encoding import part_vectors, render_nearest
from sqparts._part import stack_parts
from sqparts._recognize import MatchSettings, calibrate_threshold, lead

OUT = Path("/tmp/sqparts_poses.json")
SETTINGS = R.MatchSettings()


def components(solids, observation, figure, tau, levels):
    """(k, levels, 2) explained and precision of each solid (``verify_poses``'s terms)."""
    window, camera = R.verification_lattice(observation.camera, figure)
    vectors = [part_vectors(s) for s in solids]
    owner = np.repeat(np.arange(len(vectors)), [len(v) for v in vectors])
    rendered = render_nearest(np.concatenate(vectors), owner, len(vectors), camera)
    depth, fig = observation.depth[window][None], np.asarray(figure, bool)[window][None]
    seen, model = np.isfinite(depth), np.isfinite(rendered)
    both = seen & model
    difference = rendered - np.where(seen, depth, 0.0)
    out = np.zeros((len(solids), levels, 2))
    for level in range(levels):
        t = tau / 2.0**level
        agree = np.where(both, np.exp(-0.5 * (difference / t) ** 2), 0.0)
        hidden = both & (difference > 2.0 * t)
        out[:, level, 0] = (agree * fig).sum((1, 2)) / max(int(fig.sum()), 1)
        visible = model & ~hidden
        out[:, level, 1] = (agree * visible).sum((1, 2)) / np.maximum(visible.sum((1, 2)), 1)
    return out


def articulation_size(tree, pose, motion, scale):
    """Each part's rotation relative to the root's (degrees, the root's own 0), and the
    root's motion relative to the rigid pose (degrees, translation / scale)."""
    root = tree.order[0]
    rel = np.einsum("ab,nbc->nac", np.linalg.inv(pose), motion)  # model frame -> model frame
    r_root = rel[root, :3, :3]
    angles = Rotation.from_matrix(np.einsum("ba,nbc->nac", r_root, rel[:, :3, :3])).magnitude()
    root_angle = Rotation.from_matrix(r_root).magnitude()
    return (
        np.degrees(angles).round(2).tolist(),
        round(float(np.degrees(root_angle)), 2),
        round(float(np.linalg.norm(rel[root, :3, 3]) / scale), 4),
    )


def match_poses(db, query, observation, figure, exclude=None) -> list:
    """Every fitted pose of every stored view for one query figure, as records."""
    items = [(n, k, v) for n, views in db.objects.items() for k, v in enumerate(views) if exclude != (n, k)]
    rows = concurrently(lambda it: (it[0], it[1], R.align_candidates(query, it[2].main.description, SETTINGS)), items)
    points = R.observed_points(observation, figure)

    def fitted(row):
        name, k, aligned = row
        model = db.objects[name][k].main
        sigma = SETTINGS.alignment_tolerance * max(query.scale, model.description.scale)
        poses = [R.fit_pose(points, model.description, a.pose, sigma) for a in aligned]
        motions = [R.articulate(model.tree, points, p, sigma) if len(model.tree.order) > 1 else None for p in poses]
        return list(zip(poses, motions))

    solids, index = [], []
    fits_all = concurrently(fitted, rows)
    for r, (row, fits) in enumerate(zip(rows, fits_all)):
        model = db.objects[row[0]][row[1]].main
        for j, (pose, motion) in enumerate(fits):
            solids.append(transform_parts(model.parts, pose))
            index.append((r, j, "rigid"))
            if motion is not None:
                solids.append(transform_parts(model.parts, motion))
                index.append((r, j, "art"))
    if not solids:
        return []
    tau = SETTINGS.verification_tolerance * query.scale
    comp = components(solids, observation, figure, tau, SETTINGS.verification_levels)
    records: dict = {}
    for (r, j, kind), c in zip(index, comp):
        name, k, aligned = rows[r]
        rec = records.setdefault((r, j), {"object": name, "view": k, "start": j, "align": float(aligned[j].score)})
        rec[kind] = np.round(c, 5).tolist()
        if kind == "art":
            model = db.objects[name][k].main
            pose, motion = fits_all[r][j]
            rec["angles"], rec["root_angle"], rec["root_shift"] = articulation_size(
                model.tree, pose, motion, query.scale
            )
    return list(records.values())


def test_queries(name, spec, entry, figures, meshes):
    """A test view's range image (rendered again, the same seed) with its figures' masks,
    and its queries as ``match_figures`` makes them: each figure, and all together."""
    depth, camera = B.render(name, spec, meshes)
    labels = np.asarray(entry["labels"]).reshape(depth.shape)
    masks = np.stack([labels == k for k in range(len(figures))])
    queries = [(f, masks[i]) for i, f in enumerate(figures)]
    if len(figures) > 1:
        queries.append((stack_parts([p for f in figures for p in f]), masks.any(0)))
    return R.Observation(depth, camera, masks), queries


def run() -> None:
    enable_caches()
    B.set_resolution(128)
    views, meshes = B.plan(), B.all_meshes()
    cache = json.loads(B.CACHE.read_text())
    db = B.learnt_database(views, cache, tempfile.mkdtemp())
    results: dict = {"test": {}, "calibration": []}
    t_all = time.perf_counter()
    for name, stored in db.objects.items():
        for k, view in enumerate(stored):
            query, observation = view_observation(view)
            poses = match_poses(db, query, observation, observation.figures[0], exclude=(name, k))
            results["calibration"].append({"object": name, "view": k, "queries": [poses]})
            print(f"{name}/{k}: {len(poses)} poses, {time.perf_counter() - t_all:.0f} s", flush=True)
    print(f"calibration {time.perf_counter() - t_all:.0f} s", flush=True)
    for key, name, role, spec in views:
        if role != "test":
            continue
        t0 = time.perf_counter()
        entry = cache[key]
        figures = [B._parts(f) for f in entry["figures"]]
        if not figures:
            results["test"][key] = {"object": name, "queries": []}
            continue
        observation, queries = test_queries(name, spec, entry, figures, meshes)
        results["test"][key] = {
            "object": name,
            "queries": [match_poses(db, describe(parts), observation, mask) for parts, mask in queries],
        }
        print(key, f"{time.perf_counter() - t0:.0f} s", flush=True)
    OUT.write_text(json.dumps(results) + "\n")
    print(f"all {time.perf_counter() - t_all:.0f} s")


def _score(components, exponent=0.5, weights=(1.0, 1.0, 1.0)) -> float:
    """A pose's verification from its saved terms: the weighted mean over the tolerances
    of explained^a precision^(1-a) (run 10: a = 1/2, equal weights)."""
    c, w = np.asarray(components), np.asarray(weights, float) / np.sum(weights)
    return float(np.sum(w * c[:, 0] ** exponent * c[:, 1] ** (1 - exponent)))


def rule(exponent=0.5, weights=(1.0, 1.0, 1.0), articulated=True, theta=None, margin=0.0):
    """A pose's score: the better of its rigid and articulated verification, the latter
    times exp(-Σθ²/2theta²) over the parts' angles to the root and less ``margin``."""

    def score(record):
        s = _score(record["rigid"], exponent, weights)
        if articulated and "art" in record:
            a = _score(record["art"], exponent, weights)
            if theta is not None:
                a *= float(np.exp(-0.5 * np.sum((np.asarray(record["angles"]) / theta) ** 2)))
            s = max(s, a - margin)
        return s

    return score


def object_scores(queries, score, drop=None) -> dict:
    """Each object's best over every pose of every query (figure)."""
    best: dict = {}
    for query in queries:
        for record in query:
            if record["object"] != drop:
                best[record["object"]] = max(best.get(record["object"], -1.0), score(record))
    return best


def evaluate(data, score) -> tuple[float, dict]:
    """The threshold calibrated on the stored views and, on all test views and each half,
    top-1, known views rejected, unknown views accepted, ROC area, and the known views
    rejected at the lead that rejects 90% of the unknown ones."""

    def evidence(s):
        ranked = sorted(s, key=lambda n: -s[n])
        return ranked[0], lead(s[ranked[0]], [s[n] for n in ranked[1:]])

    genuine, impostor = [], []
    for v in data["calibration"]:
        s = object_scores(v["queries"], score)
        others = sorted((x for n, x in s.items() if n != v["object"]), reverse=True)
        genuine.append(lead(s[v["object"]], others))
        impostor.append(lead(others[0], others[1:]))
    threshold = calibrate_threshold(genuine, impostor)
    out = {}
    for half, keep in (
        ("all", lambda k: True),
        ("test0-3", lambda k: int(k[-1]) < 4),
        ("test4-7", lambda k: int(k[-1]) >= 4),
    ):
        top1 = rejected = accepted = 0
        known, unknown = [], []
        for key, t in data["test"].items():
            if not keep(key):
                continue
            top, e = evidence(object_scores(t["queries"], score))
            _, u = evidence(object_scores(t["queries"], score, drop=t["object"]))
            top1 += top == t["object"]
            rejected += not (top == t["object"] and e >= threshold)
            accepted += u >= threshold
            known.append(e if top == t["object"] else -1.0)
            unknown.append(u)
        k, u = np.array(known), np.array(unknown)
        bar = np.sort(u)[::-1][int(np.floor(0.1 * len(u)))]
        auc = float(np.mean([(a > b) + 0.5 * (a == b) for a in k for b in u]))
        out[half] = dict(
            n=len(k),
            top1=top1,
            known_rejected=rejected,
            unknown_accepted=accepted,
            roc_area=round(auc, 3),
            known_rejected_at_90=int(np.sum(k <= bar)),
        )
    return threshold, out


def analyse() -> None:
    data = json.loads(OUT.read_text())
    rules = {"run 10": rule(), "rigid only": rule(articulated=False)}
    rules.update({f"articulation prior θ = {t}°": rule(theta=t) for t in (30, 60, 90, 120)})
    rules.update({f"articulation margin {m}": rule(margin=m) for m in (0.01, 0.02, 0.04)})
    rules.update({f"tolerance weights {w}": rule(weights=w) for w in ((1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 2, 1))})
    rules.update({f"explained exponent {a}": rule(exponent=a) for a in (0.3, 0.4, 0.6, 0.7)})
    for name, score in rules.items():
        threshold, out = evaluate(data, score)
        cells = " | ".join(
            f"{h}: top-1 {o['top1']}/{o['n']}, rejected {o['known_rejected']}, accepted {o['unknown_accepted']}, "
            f"ROC {o['roc_area']}, rejected at 90% {o['known_rejected_at_90']}"
            for h, o in out.items()
        )
        print(f"| {name} | {threshold:.3f} | {cells} |")


def truth(keys) -> None:
    """The true object's stored views verified at the ground truth's pose (the rotation
    from the learning and test views' azimuth and elevation, the translation from it and
    then fitted, rigid and articulated), against the best pose matching found (run 10)."""
    enable_caches()
    B.set_resolution(128)
    views, meshes = B.plan(), B.all_meshes()
    cache = json.loads(B.CACHE.read_text())
    db = B.learnt_database(views, cache, tempfile.mkdtemp())
    saved = json.loads(B.result_path("recognition_128_levels").read_text())
    found = {r["view"]: r for r in saved["rows"]}

    def centre(key):  # the learnt view's centre, as view_from_parts takes it
        parts = stack_parts([p for f in cache[key]["figures"] for p in B._parts(f)])
        vol = part_volume(np.asarray(parts.size, float), np.asarray(parts.squareness, float))
        return (np.asarray(parts.position, float) * vol[:, None]).sum(0) / vol.sum()

    for key, name, role, spec in views:
        if role != "test" or name == "human" or (keys and key not in keys):
            continue
        entry = cache[key]
        figures = [B._parts(f) for f in entry["figures"]]
        observation, queries = test_queries(name, spec, entry, figures, meshes)
        turn = B._rotation(spec["azimuth"], spec["elevation"])[:3, :3]
        best = 0.0
        for parts, mask in queries:
            query, points = describe(parts), R.observed_points(observation, mask)
            solids = []
            for k, (azimuth, elevation) in enumerate(B.LEARN_VIEWS):
                model = db.objects[name][k].main
                r = turn @ B._rotation(azimuth, elevation)[:3, :3].T
                pose = np.eye(4)
                pose[:3, :3] = r
                pose[:3, 3] = r @ (centre(f"{name}/learn{k}") - [0, 0, B.DISTANCE]) + [0, 0, B.DISTANCE * spec["scale"]]
                sigma = SETTINGS.alignment_tolerance * max(query.scale, model.description.scale)
                fitted = R.fit_pose(points, model.description, pose, sigma)
                solids += [transform_parts(model.parts, pose), transform_parts(model.parts, fitted)]
                if len(model.tree.order) > 1:
                    solids.append(transform_parts(model.parts, R.articulate(model.tree, points, fitted, sigma)))
            tau = SETTINGS.verification_tolerance * query.scale
            best = max(best, float(R.verify_poses(solids, observation, mask, tau, SETTINGS.verification_levels).max()))
        row = found[key]
        print(
            f"{key}: found {row['scores'][name]:.3f} (top {row['top']} {row['top_score']:.3f}), at the true pose {best:.3f}",
            flush=True,
        )


def figures(keys) -> None:
    """Each named test view matched as ``sqparts.recognize`` matches it (every figure and
    all together, today's settings), with the query each object's best came from."""
    enable_caches()
    B.set_resolution(128)
    views, meshes = B.plan(), B.all_meshes()
    cache = json.loads(B.CACHE.read_text())
    db = B.learnt_database(views, cache, tempfile.mkdtemp())
    specs = {key: (name, spec) for key, name, role, spec in views if role == "test"}
    for key in keys:
        name, spec = specs[key]
        entry = cache[key]
        parts = [B._parts(f) for f in entry["figures"]]
        observation, _ = test_queries(name, spec, entry, parts, meshes)
        t0 = time.perf_counter()
        _, matches = match_figures(parts, database=db, settings=MatchSettings(), observation=observation)
        shown = ", ".join(f"{m.name} {m.score:.3f} ({m.figure})" for m in matches)
        sizes = [(int(f.sum()), len(p)) for f, p in zip(observation.figures, parts)]
        print(
            f"{key} ({name}; figures' pixels and parts {sizes}; {time.perf_counter() - t0:.0f} s): {shown}", flush=True
        )


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=["run", "analyse", "truth", "figures"])
    parser.add_argument(
        "views", nargs="*", help="truth: the test views (default: all but the person's); figures: the test views"
    )
    args = parser.parse_args()
    if args.command == "truth":
        truth(args.views)
    elif args.command == "figures":
        figures(args.views)
    else:
        {"run": run, "analyse": analyse}[args.command]()
