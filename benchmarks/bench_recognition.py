"""Recognition by parts, and the three stabilities of section 1, measured.

Objects: the ten meshes of ``shared/data/models`` and the Utah teapot (each centred and
scaled so that its longest side is ``OBJECT_SIZE`` m), and the built-in person
(:func:`sqparts.posed_human`). Each is learnt from 3 views (meshes: azimuths 0, 120, 240
degrees at 20 degrees elevation; the person standing, from the front and 40 degrees to
either side) and recognised in 8 unseen views: other azimuths and elevations, 1-1.6x the
learning distance, 1 mm of depth noise, 2 of the 8 partly hidden by a plate in front (the
person: 8 other poses or viewpoints). The views are drawn from a fixed seed before
anything is learnt, and nothing is tuned to them: the rejection threshold is calibrated
by the database on its own learnt views (leave one view out).

Reported: top-1 accuracy; rejection of unknown objects (each test view matched against
the database without its own object: ``best`` must be null); known views wrongly
rejected; seconds per recognition (recovery + matching, warm); a confusion matrix
(``results/recognition_confusion.png``); and the stability table: part-count spread and
description distance (1 - match score against the first view of the series) for one
object at several distances (scale), with depth noise, from several viewpoints, and for
the person in every pose (configuration).

    python benchmarks/bench_recognition.py            # about 20-30 min on 2 CPU cores
    python benchmarks/bench_recognition.py --from-cache   # re-match cached recoveries
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
import trimesh
from _common import RESULTS, result_path, save

import sqparts
from sqparts._database import STATISTICS, ModelDatabase, _coarse_levels, match_figures, view_from_parts
from sqparts._describe import describe
from sqparts._io import scene_from_dict, scene_to_dict
from sqparts._mesh import render_mesh
from sqparts._part import Part, matrix_to_rotation_vector, stack_parts
from sqparts._recognize import MatchSettings, Observation, match_descriptions

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
MESHES = ["spot", "fish", "penguin", "wingnut", "koala", "scorpion", "goathead", "cat", "boot", "hammer"]
OBJECT_SIZE = 0.8  # m, longest side after normalising
RESOLUTION = 64
DISTANCE = 2.5  # m, learning distance
FOCAL = RESOLUTION * DISTANCE / 1.1
NOISE = 0.001  # m
RECOVER = dict(refine=sqparts.RefineSettings(rounds=1))
LEARN_VIEWS = [(0, 20), (120, 20), (240, 20)]
HUMAN_LEARN = [("standing", 0), ("standing", 40), ("standing", -40)]
HUMAN_TEST = [
    ("arms up", 0),
    ("t-pose", 20),
    ("walking", 0),
    ("waving", -20),
    ("pointing", 10),
    ("straddle", 0),
    ("walking", 30),
    ("waving", 15),
]
STABILITY_OBJECTS = ["spot", "teapot"]
CACHE = RESULTS / "recognition_cache.json"


def set_resolution(resolution: int) -> None:
    """Render every view ``resolution`` pixels square, the focal length scaled with it (the
    objects then cover the same share of the image), and keep its recoveries in a cache of
    their own (64, the default: ``recognition_cache.json``)."""
    global RESOLUTION, FOCAL, CACHE
    RESOLUTION, FOCAL = resolution, resolution * DISTANCE / 1.1
    CACHE = RESULTS / ("recognition_cache.json" if resolution == 64 else f"recognition_cache_{resolution}.json")


def camera(focal=None):
    c = (RESOLUTION - 1) / 2
    f = FOCAL if focal is None else focal
    return sqparts.PinholeCamera(RESOLUTION, RESOLUTION, f, f, c, c)


def normalised_mesh(path: Path) -> trimesh.Trimesh:
    mesh = trimesh.load(path, force="mesh")
    mesh.apply_translation(-mesh.bounds.mean(0))
    mesh.apply_scale(OBJECT_SIZE / mesh.extents.max())
    return mesh


def all_meshes() -> dict:
    """The ten model meshes and the teapot, normalised, by object name."""
    meshes = {name: normalised_mesh(DATA / "models" / f"{name}.obj") for name in MESHES}
    meshes["teapot"] = normalised_mesh(DATA / "teapot.obj")
    return meshes


def _rotation(azimuth, elevation):
    r = trimesh.transformations.rotation_matrix
    return r(np.radians(elevation), [1, 0, 0]) @ r(np.radians(azimuth), [0, 1, 0])


def mesh_view(mesh, azimuth, elevation, scale=1.0, *, plate=False, noise=0.0, rng=None):
    """Range image of ``mesh`` turned by azimuth (about its y) and elevation, ``scale`` x
    the learning distance away; optionally a plate 0.7 m in front hiding about a third of it."""
    m = mesh.copy()
    m.apply_transform(_rotation(azimuth, elevation))
    m.apply_translation([0, 0, DISTANCE * scale])
    if plate:
        box = trimesh.creation.box(extents=[0.22, 0.5, 0.03])
        box.apply_translation([0.19 * (1 if rng.random() < 0.5 else -1), 0, DISTANCE * scale - 0.7])
        m = trimesh.util.concatenate([m, box])
    depth = render_mesh(m, camera())
    if noise:
        depth = depth + rng.normal(0, noise, depth.shape).astype(np.float32)
    return depth


def human_view(pose, azimuth, scale=1.0, *, noise=0.0, rng=None):
    s = sqparts.posed_human(pose)
    p = s.parts
    centre = np.array([0.0, 0.0, 4.0])
    r = _rotation(azimuth, 0)[:3, :3]
    pos = (np.asarray(p.position, float) - centre) @ r.T + np.array([0, 0, 4.0 * scale])
    rot = np.einsum("ij,njk->nik", r, np.asarray(p.rotation(), float))
    ori = np.stack([np.asarray(matrix_to_rotation_vector(m.astype(np.float32))) for m in rot])
    parts = Part(
        size=p.size,
        squareness=p.squareness,
        position=pos.astype(np.float32),
        orientation=ori,
        bend=p.bend,
        taper=p.taper,
    )
    cam = camera(focal=RESOLUTION * 4.0 / 2.4)
    depth = np.asarray(sqparts.render_range_image(parts, cam))
    if noise:
        depth = depth + rng.normal(0, noise, depth.shape).astype(np.float32)
    return depth, cam


def plan(seed: int = 0):
    """Every view of the benchmark, drawn before anything is learnt: (key, object, role, spec)."""
    rng = np.random.default_rng(seed)
    views = []
    for name in MESHES + ["teapot"]:
        for k, (az, el) in enumerate(LEARN_VIEWS):
            views.append((f"{name}/learn{k}", name, "learn", dict(azimuth=az, elevation=el, scale=1.0)))
        azimuths = rng.permutation(np.arange(8) * 45 + 20 + rng.uniform(-8, 8, 8))
        for k in range(8):
            spec = dict(
                azimuth=float(azimuths[k]),
                elevation=float(rng.choice([-10, 5, 35, 50])),
                scale=float(rng.uniform(1.0, 1.6)),
                noise=NOISE,
                plate=k >= 6,
                seed=int(rng.integers(1 << 30)),
            )
            views.append((f"{name}/test{k}", name, "test", spec))
    for k, (pose, az) in enumerate(HUMAN_LEARN):
        views.append((f"human/learn{k}", "human", "learn", dict(pose=pose, azimuth=az, scale=1.0)))
    for k, (pose, az) in enumerate(HUMAN_TEST):
        views.append(
            (
                f"human/test{k}",
                "human",
                "test",
                dict(
                    pose=pose,
                    azimuth=az,
                    scale=float(rng.uniform(1.0, 1.6)),
                    noise=NOISE,
                    seed=int(rng.integers(1 << 30)),
                ),
            )
        )
    for name in STABILITY_OBJECTS:
        for s in (1.0, 1.3, 1.6, 2.0):
            views.append((f"{name}/scale{s}", name, "stability-scale", dict(azimuth=60, elevation=20, scale=s)))
        for n in (0.0, 0.001, 0.003):
            views.append(
                (
                    f"{name}/noise{n}",
                    name,
                    "stability-noise",
                    dict(azimuth=60, elevation=20, scale=1.0, noise=n, seed=7),
                )
            )
        for az in (0, 60, 120, 180, 240, 300):
            views.append((f"{name}/view{az}", name, "stability-viewpoint", dict(azimuth=az, elevation=20, scale=1.0)))
    for pose in sqparts.HUMAN_POSES:
        views.append((f"human/pose-{pose}", "human", "stability-configuration", dict(pose=pose, azimuth=0, scale=1.0)))
    return views


def render(name, spec, meshes):
    rng = np.random.default_rng(spec.get("seed", 0))
    if name == "human":
        return human_view(spec["pose"], spec["azimuth"], spec["scale"], noise=spec.get("noise", 0), rng=rng)
    depth = mesh_view(
        meshes[name],
        spec["azimuth"],
        spec["elevation"],
        spec["scale"],
        plate=spec.get("plate", False),
        noise=spec.get("noise", 0),
        rng=rng,
    )
    return depth, camera()


def _parts_json(parts):
    return scene_to_dict(parts)["parts"]


def _parts(data):
    return scene_from_dict({"parts": data})[0]


def recover_all(views, meshes, cache: dict) -> dict:
    for i, (key, name, role, spec) in enumerate(views):
        if key in cache and (role != "test" or "labels" in cache[key]):  # test views verify on their figures
            continue
        depth, cam = render(name, spec, meshes)
        t0 = time.perf_counter()
        try:
            rec = sqparts.recover_scene(depth, cam, **RECOVER)
        except ValueError as e:  # e.g. the plate taken for background and too little left: a failure, counted
            cache[key] = {
                "figures": [],
                "seconds": time.perf_counter() - t0,
                "error": str(e),
                "pixels": int(np.isfinite(depth).sum()),
            }
            print(f"[{i + 1}/{len(views)}] {key}: recovery failed: {e}", flush=True)
            continue
        seconds = time.perf_counter() - t0
        labels = np.full(depth.shape, -1, np.int64)
        for k, r in enumerate(rec.figures):
            labels[np.asarray(r.figure, bool)] = k
        entry = {
            "figures": [_parts_json(r.parts) for r in rec.figures],
            "seconds": seconds,
            "pixels": int(np.isfinite(depth).sum()),
            "labels": labels.ravel().tolist(),  # figure of each pixel (-1: none), to verify poses on
        }
        if role == "learn":
            entry["initial"] = _parts_json(rec.figures[0].initial_parts)
            t0 = time.perf_counter()
            entry["levels"] = [_parts_json(p) for p in _coarse_levels(rec, 2)]
            entry["level_seconds"] = time.perf_counter() - t0
        cache[key] = entry
        print(f"[{i + 1}/{len(views)}] {key}: {[len(f) for f in entry['figures']]} parts, {seconds:.1f} s", flush=True)
        CACHE.write_text(json.dumps(cache) + "\n")
    return cache


def learnt_database(views, cache: dict, folder) -> ModelDatabase:
    """The database of the learnt views' cached recoveries, in ``folder`` (uncalibrated)."""
    db = ModelDatabase(folder)
    for key, name, role, _spec in views:
        if role == "learn":
            e = cache[key]  # as view_from_recovery: all figures are the object
            others = [p for f in e["figures"][1:] for p in _parts(f)]
            view = view_from_parts(
                stack_parts([p for f in e["figures"] for p in _parts(f)]),
                source=key,
                initial=stack_parts([*_parts(e["initial"]), *others]),
                levels=[stack_parts([*_parts(p), *others]) for p in e["levels"]],
            )
            db.add_view(name, view, calibrate=False)
    return db


_WORKER_DB: dict = {}


def recognise_view(job) -> dict:
    """One test view matched by one matcher (run in a worker process): the database read
    from its folder, the view rendered again (the same seed), its figures' cached parts
    and masks, the poses verified on that range image."""
    folder, resolution, threshold, settings, key, name, spec, e = job
    set_resolution(resolution)
    if folder not in _WORKER_DB:
        import sqparts._compile

        sqparts._compile.enable_caches()
        _WORKER_DB[folder] = ModelDatabase(folder)
        _WORKER_DB["meshes"] = all_meshes()
    db = _WORKER_DB[folder]
    db.threshold = threshold
    figures = [_parts(f) for f in e["figures"]]
    observation = None
    if figures:
        depth, cam = render(name, spec, _WORKER_DB["meshes"])
        labels = np.asarray(e["labels"]).reshape(depth.shape)
        observation = Observation(depth, cam, np.stack([labels == k for k in range(len(figures))]))
    t0 = time.perf_counter()
    _, matches = match_figures(figures, database=db, settings=settings, observation=observation)
    match_s = time.perf_counter() - t0
    names = [m.name for m in matches]
    row = {
        "view": key,
        "object": name,
        "spec": spec,
        "parts": [len(f) for f in figures],
        "top": names[0] if names else None,
        "top_score": matches[0].score if matches else 0.0,
        "true_score": next((m.score for m in matches if m.name == name), 0.0),
        "rank": names.index(name) + 1 if name in names else None,
        "recovery_s": e["seconds"],
        "matching_s": match_s,
        "recovery_error": e.get("error"),
        "scores": {m.name: m.score for m in matches},  # every object's: decide() accepts or rejects
    }
    decide([row], db)
    print(
        f"{key}: best {row['best']} ({row['top_score']:.2f}; true {row['true_score']:.2f}), without it: {row['unknown_best']}"
    )
    return row


def decide(rows, db: ModelDatabase, statistic: str | None = None) -> ModelDatabase:
    """Accept or reject each row's best object by the calibrated database's rule
    (:meth:`ModelDatabase.evidence` against its threshold), for the view as it is (known)
    and for the database without the view's object (unknown: the same matches less its
    own, each object's best being found on its own, so no second match is needed),
    calibrated as a database that never had it (:meth:`ModelDatabase.without`, exact
    from the same stored views' scores), and, for comparison with runs before session
    48, by the whole database's threshold (``unknown_best_shared``). ``statistic``: the
    rule forced on every database (:func:`compare_statistics`). Returns the database
    the known views were decided by."""

    def calibrated(d: ModelDatabase) -> ModelDatabase:
        if statistic is not None:
            d.calibrate_from(d.calibration["views"], statistic=statistic)
        return d

    known = calibrated(db.without())
    left: dict[str, ModelDatabase] = {}
    for r in rows:
        name, scores = r["object"], r["scores"]
        if name not in left:
            left[name] = calibrated(db.without(name)) if name in db.objects else known
        unknown = {n: s for n, s in scores.items() if n != name}
        top = max(unknown, key=unknown.__getitem__) if unknown else None
        r["evidence"] = known.evidence(scores.values())
        r["best"] = r["top"] if scores and r["evidence"] >= known.threshold else None
        r["unknown_evidence"] = left[name].evidence(unknown.values())
        r["unknown_threshold"] = left[name].threshold
        r["unknown_top_score"] = max(unknown.values(), default=0.0)
        r["unknown_best"] = top if unknown and r["unknown_evidence"] >= left[name].threshold else None
        shared = known.evidence(unknown.values())
        r["unknown_best_shared"] = top if unknown and shared >= known.threshold else None
    return known


def summarise(rows, threshold, calibrate_s, calibration) -> dict:
    seconds = [r["recovery_s"] + r["matching_s"] for r in rows]
    return {
        "summary": {
            "objects": len({r["object"] for r in rows}),
            "test_views": len(rows),
            "top1": float(np.mean([r["top"] == r["object"] for r in rows])),
            "top3": float(np.mean([r["rank"] is not None and r["rank"] <= 3 for r in rows])),
            "plate_views_top1": int(sum(r["top"] == r["object"] for r in rows if r["spec"].get("plate"))),
            "accepted_and_correct": float(np.mean([r["best"] == r["object"] for r in rows])),
            "known_wrongly_rejected": float(np.mean([r["best"] is None for r in rows])),
            "unknown_rejected": float(np.mean([r["unknown_best"] is None for r in rows])),
            "unknown_rejected_shared_threshold": float(np.mean([r["unknown_best_shared"] is None for r in rows])),
            "threshold": threshold,
            "seconds_per_recognition_median": float(np.median(seconds)),
            "seconds_per_recognition_mean": float(np.mean(seconds)),
            "matching_seconds_median": float(np.median([r["matching_s"] for r in rows])),
            "calibration_s": calibrate_s,
        },
        "calibration": calibration,
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--from-cache", action="store_true", help="reuse results/recognition_cache.json's recoveries")
    ap.add_argument(
        "--whole-object",
        action="store_true",
        help="also weigh each match by the whole objects' shape distributions (MatchSettings(shape_tolerance=0.5)); "
        "results saved as recognition_shape*",
    )
    ap.add_argument(
        "--plot-only",
        action="store_true",
        help="redraw the pictures from the saved results JSON (no recovery, no matching)",
    )
    ap.add_argument(
        "--resolution",
        type=int,
        default=RESOLUTION,
        help="render views this many pixels square (focal length scaled with it; own recovery cache, "
        "results saved with a _<resolution> suffix unless it is 64)",
    )
    ap.add_argument(
        "--rescore",
        action="store_true",
        help="decide the saved results' rows again (accept or reject each view's best object) under today's rule, "
        "from the run's own per-view calibration scores (or a database calibrated now from the cached learnt "
        "views, for runs that saved none); the matching itself is not repeated",
    )
    ap.add_argument(
        "--recalibrate",
        action="store_true",
        help="with --rescore: calibrate the database of the cached learnt views again now, by today's "
        "calibration, instead of deciding from the run's saved calibration scores",
    )
    ap.add_argument(
        "--verified-only",
        action="store_true",
        help="match by the verified matcher alone (no same-run comparison with the matcher before "
        "verification; about 40%% less time)",
    )
    args = ap.parse_args()
    set_resolution(args.resolution)
    settings = MatchSettings(shape_tolerance=0.5) if args.whole_object else MatchSettings()
    # The matcher before verification (run 4) is measured in the same run, on the same recoveries.
    matchers = {"verified": settings}
    if settings.verification_tolerance is not None and not args.verified_only:
        matchers = {"parts and alignment": dataclasses.replace(settings, verification_tolerance=None), **matchers}
    tag = "recognition_shape" if args.whole_object else "recognition"
    if RESOLUTION != 64:
        tag += f"_{RESOLUTION}"
    if args.plot_only:
        saved = json.loads(result_path(tag).read_text())
        c = saved["confusion"]
        plot_confusion(np.array(c["counts"]), c["rows"], result_path(f"{tag}_confusion", "png"))
        plot_top1(saved["rows"], c["rows"], result_path(f"{tag}_confusion_top1", "png"))
        return
    if args.rescore:
        rescore(tag, settings, recalibrate=args.recalibrate)
        return
    import sqparts._compile

    sqparts._compile.enable_caches()
    views = plan()
    meshes = all_meshes()
    cache = json.loads(CACHE.read_text()) if args.from_cache and CACHE.exists() else {}
    t_start = time.perf_counter()
    # Warm-up (compilation), reported apart: one learning view recovered twice.
    key, name, role, spec = views[0]
    depth, cam = render(name, spec, meshes)
    t0 = time.perf_counter()
    sqparts.recover_scene(depth, cam, **RECOVER)
    cold = time.perf_counter() - t0
    cache = recover_all(views, meshes, cache)
    recovery_wall = time.perf_counter() - t_start

    # --- the database, from the learnt views only -------------------------------------
    import tempfile

    folder = Path(tempfile.mkdtemp(prefix="sqparts-bench-db-"))
    db = learnt_database(views, cache, folder)
    objects = MESHES + ["teapot", "human"]
    # --- recognition, by each matcher in the same run ----------------------------------
    tests = [(key, name, spec, cache[key]) for key, name, role, spec in views if role == "test"]
    runs = {}
    for label, ms in matchers.items():
        # As `sqparts learn` grows a database: the others calibrated, then the last object
        # added, which matches only the pairs it changes (ModelDatabase.calibrate).
        t0 = time.perf_counter()
        others = db.without(objects[-1])
        others.calibrate(settings=ms)
        without_last_s = time.perf_counter() - t0
        db.calibration = others.calibration
        t0 = time.perf_counter()
        threshold = db.calibrate(settings=ms)
        add_last_s = time.perf_counter() - t0
        calibrate_s = without_last_s + add_last_s
        print(
            f"{label}: threshold {threshold:.3f} from {len(db.calibration['genuine'])} genuine and "
            f"{len(db.calibration['impostor'])} impostor scores ({without_last_s:.0f} s for "
            f"{len(others.objects)} objects, then {add_last_s:.0f} s to add {objects[-1]})",
            flush=True,
        )
        jobs = [(str(folder), RESOLUTION, threshold, ms, key, name, spec, e) for key, name, spec, e in tests]
        with multiprocessing.get_context("spawn").Pool(2) as pool:  # matching is numpy on one core
            rows = pool.map(recognise_view, jobs, chunksize=1)
        decide(rows, db)  # by the database as calibrated for this matcher
        confusion = confusion_counts(rows, objects)
        runs[label] = summarise(rows, threshold, calibrate_s, dict(db.calibration))
        runs[label]["summary"].update(calibration_without_last_s=without_last_s, calibration_add_last_s=add_last_s)
        runs[label].update(rows=rows, confusion=confusion, settings=dataclasses.asdict(ms))
        print(label, json.dumps(runs[label]["summary"], indent=1), flush=True)
    label = "verified" if "verified" in runs else next(iter(runs))
    rows, confusion, threshold = runs[label]["rows"], runs[label]["confusion"], runs[label]["summary"]["threshold"]

    # --- stability --------------------------------------------------------------------
    stability = []
    for kind in ("scale", "noise", "viewpoint", "configuration"):
        names = ["human"] if kind == "configuration" else STABILITY_OBJECTS
        for name in names:
            keys = [k for k, o, role, _ in views if role == f"stability-{kind}" and o == name]
            keys = [k for k in keys if cache[k]["figures"]]
            descs = [describe(stack_parts([p for f in cache[k]["figures"] for p in _parts(f)])) for k in keys]
            counts = [len(d) for d in descs]
            dist = [1.0 - match_descriptions(d, descs[0], settings).score for d in descs[1:]]
            stability.append(
                {
                    "kind": kind,
                    "object": name,
                    "views": keys,
                    "part_counts": counts,
                    "part_count_spread": int(max(counts) - min(counts)),
                    "part_count_std": float(np.std(counts)),
                    "description_distance_mean": float(np.mean(dist)),
                    "description_distance_max": float(np.max(dist)),
                }
            )

    summary = dict(runs[label]["summary"], compile_plus_first_recovery_s=cold, recovery_wall_s=recovery_wall)
    print(json.dumps(summary, indent=1))
    for s in stability:
        print(
            f"{s['kind']:13s} {s['object']:8s} parts {s['part_counts']} distance mean {s['description_distance_mean']:.3f} "
            f"max {s['description_distance_max']:.3f}"
        )
    save(
        tag,
        {
            "settings": {
                "resolution": RESOLUTION,
                "object_size_m": OBJECT_SIZE,
                "distance_m": DISTANCE,
                "noise_m": NOISE,
                "recover": {k: dataclasses.asdict(v) for k, v in RECOVER.items()},
                "match": runs[label]["settings"],
                "learn_views": LEARN_VIEWS,
                "human_learn": HUMAN_LEARN,
                "human_test": HUMAN_TEST,
                "dtype": "float32",
            },
            "matcher": label,
            "summary": summary,
            "calibration": runs[label]["calibration"],
            "stability": stability,
            "rows": rows,
            "confusion": {"rows": objects, "columns": objects + ["(rejected)"], "counts": confusion.tolist()},
            "same_run": {k: {"settings": r["settings"], "summary": r["summary"]} for k, r in runs.items()},
            "statistics": compare_statistics(rows, db),
        },
    )
    plot_confusion(confusion, objects, result_path(f"{tag}_confusion", "png"))
    plot_top1(rows, objects, result_path(f"{tag}_confusion_top1", "png"))


def confusion_counts(rows, objects) -> np.ndarray:
    confusion = np.zeros((len(objects), len(objects) + 1), int)
    for row in rows:
        confusion[objects.index(row["object"]), objects.index(row["best"]) if row["best"] else len(objects)] += 1
    return confusion


def roc_area(a, b) -> float:
    """P(a value of ``a`` > one of ``b``), ties counted half."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.mean(a[:, None] > b[None, :]) + 0.5 * np.mean(a[:, None] == b[None, :]))


def compare_statistics(rows, db: ModelDatabase) -> dict:
    """Each rejection statistic (the best score, its lead) on the same rows, thresholded
    as the database would calibrate it from the same stored views' scores (the unknown
    views by the database without their object, as :func:`decide`): known views
    rejected, unknown views rejected; and, for reference, the ROC area of the known
    views' evidence against the unknown views' and the known views rejected at the
    threshold that rejects 90% of the unknown ones (chosen on the test views: not a
    result, a measure of separation)."""
    out = {}
    for statistic in STATISTICS:
        decided = [dict(r) for r in rows]
        other = decide(decided, db, statistic)
        known = np.array([r["evidence"] for r in decided])
        unknown = np.array([r["unknown_evidence"] for r in decided])
        out[statistic] = {
            "threshold": other.threshold,
            "accepted_and_correct": float(np.mean([r["best"] == r["object"] for r in decided])),
            "known_wrongly_rejected": float(np.mean([r["best"] is None for r in decided])),
            "unknown_rejected": float(np.mean([r["unknown_best"] is None for r in decided])),
            "roc_area_known_vs_unknown": roc_area(known, unknown),
            "known_rejected_at_90pct_unknown_rejected": float(np.mean(known <= np.quantile(unknown, 0.9))),
        }
    return out


def rescore(tag: str, settings: MatchSettings, *, recalibrate: bool = False) -> None:
    """The saved run's rows decided again (:func:`decide`) under today's rule, by a
    database calibrated from the saved calibration's per-view scores or, when the run
    saved none or with ``recalibrate``, calibrated now from the cached learnt views (the
    run's own database: calibration is deterministic, and matching does not depend on
    the threshold); the summary, confusion matrix and pictures remade, the previous
    summary kept under ``before_rescore``."""
    import tempfile

    import sqparts._compile

    sqparts._compile.enable_caches()
    saved = json.loads(result_path(tag).read_text())
    cache = json.loads(CACHE.read_text())
    db = learnt_database(plan(), cache, Path(tempfile.mkdtemp(prefix="sqparts-bench-db-")))
    before = saved["summary"]
    if "views" in saved["calibration"] and not recalibrate:  # the run's own calibration, decided again
        db.calibrate_from(saved["calibration"]["views"])
        calibrate_s = before["calibration_s"]
    else:
        t0 = time.perf_counter()
        db.calibrate(settings=settings)
        calibrate_s = time.perf_counter() - t0
    rows = saved["rows"]
    decide(rows, db)
    objects = saved["confusion"]["rows"]
    confusion = confusion_counts(rows, objects)
    summary = summarise(rows, db.threshold, calibrate_s, dict(db.calibration))
    saved.update(
        summary={**before, **summary["summary"], "statistic": db.statistic},
        calibration=summary["calibration"],
        statistics=compare_statistics(rows, db),
        confusion={**saved["confusion"], "counts": confusion.tolist()},
        before_rescore={"when": saved.pop("when", None), "machine": saved.pop("machine", None), "summary": before},
    )
    print(json.dumps({"summary": saved["summary"], "statistics": saved["statistics"]}, indent=1))
    save(tag, saved)
    plot_confusion(confusion, objects, result_path(f"{tag}_confusion", "png"))
    plot_top1(rows, objects, result_path(f"{tag}_confusion_top1", "png"))


def plot_top1(rows, objects, path):
    """The confusion of the top match, whatever its score (no rejection)."""
    confusion = np.zeros((len(objects), len(objects) + 1), int)
    for r in rows:
        confusion[objects.index(r["object"]), objects.index(r["top"]) if r["top"] else len(objects)] += 1
    plot_confusion(confusion, objects, path, xlabel="top match (no threshold)")


def plot_confusion(confusion, objects, path, *, xlabel="recognised as (best)"):
    from sqparts._plot import _subplots

    fig, ax = _subplots(figsize=(7.5, 6.5), dpi=100)
    ax.imshow(confusion, cmap="Blues")
    for i in range(confusion.shape[0]):
        for j in range(confusion.shape[1]):
            if confusion[i, j]:
                ax.text(
                    j,
                    i,
                    str(confusion[i, j]),
                    ha="center",
                    va="center",
                    color="white" if confusion[i, j] > confusion.max() / 2 else "black",
                )
    ax.set_xticks(range(len(objects) + 1), objects + ["(rejected)"], rotation=60, ha="right")
    ax.set_yticks(range(len(objects)), objects)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("true object")
    ax.set_title("sqparts recognize: unseen views, database of 12 objects")
    fig.savefig(path, bbox_inches="tight")
    print(f"saved {path}")


if __name__ == "__main__":
    main()
