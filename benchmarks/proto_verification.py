"""Prototype (not in the package): how a verified pose should score.

Session 43 put one variant in the package (``MatchSettings.verification_levels``, the
tolerance a fraction of the query's scale, a view scoring its verification alone); this
script keeps the measurement that chose it.

Until then (``ModelDatabase.match`` at 15af839) a stored view scored sqrt(a x v): a, its
whole-solid alignment with the query's recovered parts; v, the verification of its best
fitted pose (``verify_poses``) at τ = 0.1 x the larger of the query's and the model's
scales. Every fitted pose of every stored view (rigid and articulated, as the package
fits them) is rendered once per query figure here and scored several ways at once:

* ``base``: v at τ = 0.1 x max(query scale, model scale), as at 15af839;
* ``query_tau``: τ = 0.1 x the query's scale, one tolerance for every object the query
  is compared with (a larger model is no longer judged more leniently);
* ``multi_tau`` / ``multi_query``: the mean of v at τ, τ/2, τ/4 (either τ);
* ``half_tau``: v at τ/2 alone;
* ``normals`` / ``normals_sq``: each pixel's agreement also times |cos| (or cos⁴) of the
  angle between the observed and the rendered surface normals (central differences);

each combined with the alignment as a^w v^(1-w): w = 1/2 (the name alone, as at
15af839), w = 1/4 (``_a25``), w = 0 (``_vonly``: the verification alone), for the
``base``, ``query_tau`` and ``multi_query`` tolerances.

``run`` matches every test view of the 128 x 128 recognition benchmark from its recovery
cache against the database learnt as ``bench_recognition.py`` learns it, each figure and
all figures together as ``match_figures`` does, and saves every object's best score per
variant in ``results/verification_variants.json`` (about 30 minutes on 2 cores).
``analyse`` prints, per variant, top-1 and how well the evidence (the top score's lead
over the mean of the rest) separates known views from unknown ones: the area under the
ROC of known leads against unknown leads (each view with its own object left out) and
the share of known views rejected at the lead that rejects 90% of the unknown ones, on
all views and on each half: ``test0-3`` chose the variant, ``test4-7`` checks it.

    JAX_PLATFORMS=cpu python benchmarks/proto_verification.py run
    python benchmarks/proto_verification.py analyse
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
from _common import RESULTS

import sqparts._recognize as R
from sqparts._compile import concurrently, enable_caches
from sqparts._database import transform_parts
from sqparts._describe import describe
from sqparts._encoding import part_vectors, render_layers
from sqparts._part import stack_parts

OUT = RESULTS / "verification_variants.json"
SETTINGS = R.MatchSettings()


def normals(points):
    """(..., H, W, 3) camera-frame points -> unit normals by central differences, NaN at the
    image's edge and across depth jumps (neighbours more than 5% of the depth apart)."""
    dx = points[..., 1:-1, 2:, :] - points[..., 1:-1, :-2, :]
    dy = points[..., 2:, 1:-1, :] - points[..., :-2, 1:-1, :]
    n = np.cross(dx, dy)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    out = np.full(points.shape, np.nan)
    out[..., 1:-1, 1:-1, :] = n
    z = np.abs(points[..., 1:-1, 1:-1, 2])
    jump = np.zeros(points.shape[:-1], bool)
    for step in (dx, dy):
        jump[..., 1:-1, 1:-1] |= ~(np.linalg.norm(step, axis=-1) < 0.05 * z)
    out[jump] = np.nan
    return out


def verify_variants(solids, observation, figure, taus, query_taus) -> dict:
    """Per verification variant, (k,) scores of ``solids`` (``verify_poses``'s formula,
    the same lattice and renderer)."""
    window, camera = R.verification_lattice(observation.camera, figure)
    vectors = [part_vectors(s) for s in solids]
    layers = render_layers(np.concatenate(vectors), camera)
    bounds = np.cumsum([0, *map(len, vectors)])
    rendered = np.stack([np.asarray(layers[a:b]).min(0) for a, b in zip(bounds[:-1], bounds[1:])]).astype(float)
    depth, fig = observation.depth[window][None], np.asarray(figure, bool)[window][None]
    seen, model = np.isfinite(depth), np.isfinite(rendered)
    both = seen & model
    diff = rendered - np.where(seen, depth, 0.0)
    origins, directions = (np.asarray(a, float) for a in camera.rays())
    observed_n = normals(origins + np.where(seen, depth, np.nan)[..., None] * directions)[0]
    model_n = normals(origins + np.where(model, rendered, np.nan)[..., None] * directions)
    cos = np.abs((observed_n[None] * model_n).sum(-1))
    cos = np.where(np.isfinite(cos), cos, 1.0)

    def score(tau, weight=1.0):
        tau = np.asarray(tau, float)[:, None, None]
        agree = np.where(both, np.exp(-0.5 * (diff / tau) ** 2), 0.0) * weight
        hidden = both & (depth < rendered - 2.0 * tau)
        explained = (agree * fig).sum((1, 2)) / max(int(fig.sum()), 1)
        visible = model & ~hidden
        precision = (agree * visible).sum((1, 2)) / np.maximum(visible.sum((1, 2)), 1)
        return np.sqrt(explained * precision)

    t, q = np.asarray(taus, float), np.asarray(query_taus, float)
    return {
        "base": score(t),
        "query_tau": score(q),
        "multi_tau": (score(t) + score(t / 2) + score(t / 4)) / 3,
        "multi_query": (score(q) + score(q / 2) + score(q / 4)) / 3,
        "half_tau": score(t / 2),
        "normals": score(t, cos),
        "normals_sq": score(t, cos**4),
    }


def match_variants(db, query, observation, figure) -> dict:
    """Per variant, each object's best score for one query figure (``ModelDatabase.match``'s
    alignment, fitting and articulation, as at 15af839)."""
    items = [(n, k, v) for n, views in db.objects.items() for k, v in enumerate(views)]
    rows = concurrently(lambda it: (it[0], it[1], R.align_candidates(query, it[2].main.description, SETTINGS)), items)
    points = R.observed_points(observation, figure)

    def fitted(row):
        name, k, aligned = row
        model = db.objects[name][k].main
        sigma = SETTINGS.alignment_tolerance * max(query.scale, model.description.scale)
        poses = [R.fit_pose(points, model.description, a.pose, sigma) for a in aligned]
        motions = [R.articulate(model.tree, points, p, sigma) if len(model.tree.order) > 1 else None for p in poses]
        return list(zip(poses, motions))

    solids, taus, query_taus, index = [], [], [], []
    for r, (row, fits) in enumerate(zip(rows, concurrently(fitted, rows))):
        model = db.objects[row[0]][row[1]].main
        tau = SETTINGS.verification_tolerance * max(query.scale, model.description.scale)
        for j, (pose, motion) in enumerate(fits):
            for m in [pose] if motion is None else [pose, motion]:
                solids.append(transform_parts(model.parts, m))
                taus.append(tau)
                query_taus.append(SETTINGS.verification_tolerance * query.scale)
                index.append((r, j))
    out: dict = {}
    if not solids:
        return out
    for variant, values in verify_variants(solids, observation, figure, taus, query_taus).items():
        per: dict = {}  # a pose: the better of its rigid and articulated renderings
        for key, v in zip(index, values):
            per[key] = max(per.get(key, -1.0), float(v))
        weights = (
            ((0.5, ""), (0.0, "_vonly"), (0.25, "_a25"))
            if variant in ("base", "query_tau", "multi_query")
            else ((0.5, ""),)
        )
        for (r, j), v in per.items():
            name, _, aligned = rows[r]
            a = max(aligned[j].score, 0.0)
            for w, tag in weights:
                best = out.setdefault(variant + tag, {})
                best[name] = max(best.get(name, 0.0), a**w * v ** (1 - w))
    return out


def run() -> None:
    enable_caches()
    B.set_resolution(128)
    views, meshes = B.plan(), B.all_meshes()
    cache = json.loads(B.CACHE.read_text())
    db = B.learnt_database(views, cache, tempfile.mkdtemp())
    results = {}
    for key, name, role, spec in views:
        if role != "test":
            continue
        t0 = time.perf_counter()
        entry = cache[key]
        figures = [B._parts(f) for f in entry["figures"]]
        depth, camera = B.render(name, spec, meshes)
        labels = np.asarray(entry["labels"]).reshape(depth.shape)
        masks = np.stack([labels == k for k in range(len(figures))])
        observation = R.Observation(depth, camera, masks)
        queries = [(f, masks[i]) for i, f in enumerate(figures)]
        if len(figures) > 1:
            queries.append((stack_parts([p for f in figures for p in f]), masks.any(0)))
        scores: dict = {}
        for parts, mask in queries:
            for variant, best in match_variants(db, describe(parts), observation, mask).items():
                for n, s in best.items():
                    scores.setdefault(variant, {})[n] = max(scores.get(variant, {}).get(n, 0.0), s)
        results[key] = {"object": name, "scores": scores, "seconds": time.perf_counter() - t0}
        print(key, f"{results[key]['seconds']:.0f} s", flush=True)
    OUT.write_text(json.dumps(results) + "\n")


def analyse() -> None:
    results = json.loads(OUT.read_text())

    def lead(s):
        return s[0] - (np.mean(s[1:]) if len(s) > 1 else 0.0)

    halves = {
        "all": sorted(results),
        "test0-3": [k for k in sorted(results) if int(k[-1]) < 4],
        "test4-7": [k for k in sorted(results) if int(k[-1]) >= 4],
    }
    print("| variant | " + " | ".join(f"{h}: top-1, ROC area, known rejected at 90%" for h in halves) + " |")
    for variant in next(iter(results.values()))["scores"]:
        cells = []
        for keys in halves.values():
            top1, known, unknown = 0, [], []
            for k in keys:
                scores, name = results[k]["scores"][variant], results[k]["object"]
                ranked = sorted(scores, key=lambda n: -scores[n])
                top1 += ranked[0] == name
                known.append(lead([scores[n] for n in ranked]))
                unknown.append(lead([scores[n] for n in ranked if n != name]))
            known, unknown = np.array(known), np.array(unknown)
            auc = np.mean([(a > b) + 0.5 * (a == b) for a in known for b in unknown])
            bar = np.sort(unknown)[::-1][int(np.floor(0.1 * len(unknown)))]  # leads above it: accepted
            cells.append(f"{top1}/{len(keys)}, {auc:.3f}, {np.mean(known <= bar):.3f}")
        print(f"| {variant} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=["run", "analyse"])
    {"run": run, "analyse": analyse}[parser.parse_args().command]()
