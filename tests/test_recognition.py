"""Part-structure descriptions, the model database and matching (issue 28).

Most tests build descriptions straight from known parts (the built-in scenes), so they
test the description and the matching rather than recovery; one CLI test recovers tiny
renders end to end."""

import dataclasses
import json
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial import KDTree
from scipy.spatial.transform import Rotation

import sqparts
from sqparts._database import (
    ModelDatabase,
    match_figures,
    transform_parts,
    view_from_parts,
    view_observation,
)
from sqparts._describe import SHAPE_BINS, SHAPE_RANGE, Description, describe, shape_distribution, surface_cloud
from sqparts._part import stack_parts
from sqparts._recognize import (
    _SHORTLIST,
    Observation,
    _rank_poses,
    _similarity,
    align_candidates,
    align_descriptions,
    articulate,
    fit_pose,
    kinematic_tree,
    observed_points,
    propose_poses,
    rotation_lattice,
    shape_similarity,
    verify_poses,
)
from sqparts.cli import main


def moved(parts, rotvec=(0.3, -1.2, 0.5), t=(0.4, -0.2, 1.5)):
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    pose[:3, 3] = t
    return transform_parts(parts, pose), pose


@pytest.mark.parametrize("scene", ["human", "chair", "castings"])
def test_description_is_invariant_to_the_camera_pose(scene):
    parts = sqparts.builtin_scene(scene).parts
    a = describe(parts)
    b = describe(moved(parts)[0])
    np.testing.assert_allclose(b.attributes, a.attributes, atol=1e-5)
    np.testing.assert_allclose(b.relations, a.relations, atol=2e-4)
    np.testing.assert_allclose(b.scale, a.scale, rtol=1e-6)
    assert np.array_equal(a.touching, b.touching)


def test_description_is_in_the_objects_own_scale():
    parts = sqparts.builtin_scene("human").parts
    big = sqparts.Part(
        size=np.asarray(parts.size) * 3,
        squareness=parts.squareness,
        position=np.asarray(parts.position) * 3,
        orientation=parts.orientation,
        bend=parts.bend,
        taper=parts.taper,
    )
    a, b = describe(parts), describe(big)
    np.testing.assert_allclose(b.scale, 3 * a.scale, rtol=1e-5)
    np.testing.assert_allclose(b.attributes, a.attributes, atol=1e-5)
    np.testing.assert_allclose(b.relations, a.relations, atol=2e-4)


def test_human_description_names_touching_limbs():
    s = sqparts.builtin_scene("human")
    d = describe(s.parts, names=s.part_names)
    i, j = s.part_names.index("right upper arm"), s.part_names.index("right forearm")
    assert d.touching[i, j] and d.touching[j, i]
    assert not d.touching[s.part_names.index("head"), s.part_names.index("left foot")]
    g = d.graph()
    assert g.number_of_nodes() == 16 and g.nodes[0]["name"] == "head"
    assert g.edges[i, j]["touch"] is True


def test_description_json_round_trips():
    d = describe(sqparts.builtin_scene("chair").parts)
    e = Description.from_json(json.loads(json.dumps(d.to_json())))
    np.testing.assert_array_equal(e.attributes, d.attributes)
    np.testing.assert_array_equal(e.relations, d.relations)
    np.testing.assert_array_equal(e.rotations, d.rotations)


@pytest.mark.parametrize(
    "bad, match",
    [
        ({"scale": 1, "nodes": []}, r"description.nodes: got list, expected a non-empty list"),
        ({"scale": -1, "nodes": [{}]}, r"description.scale: got -1.0, expected a number > 0"),
        ({"scale": 1, "nodes": [{"size_1": "x"}]}, r"description.nodes\[0\].size_1: got 'x', expected a finite number"),
        ([], r"description: got list, expected an object with 'scale', 'nodes' and 'edges'"),
    ],
)
def test_bad_description_json_is_named(bad, match):
    with pytest.raises(ValueError, match=match):
        Description.from_json(bad)


def test_identical_descriptions_score_one_and_the_pose_is_the_motion():
    parts = sqparts.builtin_scene("human").parts
    query, pose = moved(parts)
    m = sqparts.match_descriptions(describe(query), describe(parts))
    assert m.score == pytest.approx(1.0, abs=1e-6)
    assert sorted(map(tuple, m.pairs)) == [(i, i) for i in range(16)]
    np.testing.assert_allclose(m.pose, pose, atol=1e-4)


def test_a_model_with_parts_removed_still_matches():
    """Occlusion: three parts of the person missing from the query; it still matches the
    person, each remaining part to itself, and far better than the other objects."""
    human = sqparts.builtin_scene("human")
    keep = [i for i in range(16) if i not in (2, 7, 12)]  # torso, left upper arm, right calf
    query = describe(moved(stack_parts([human.parts[i] for i in keep]))[0])
    scores = {
        name: sqparts.match_descriptions(query, describe(sqparts.builtin_scene(name).parts)).score
        for name in ("human", "chair", "castings")
    }
    m = sqparts.match_descriptions(query, describe(human.parts))
    assert scores["human"] > 0.5 > max(scores["chair"], scores["castings"]) + 0.2
    assert {(keep[i], j) for i, j in m.pairs} == {(k, k) for k in keep}


def test_an_extra_part_still_matches():
    chair = sqparts.builtin_scene("chair").parts
    extra = sqparts.Part(size=[0.1, 0.1, 0.1], position=[1.0, 0.0, 3.0])
    m = sqparts.match_descriptions(describe(stack_parts([*chair, extra])), describe(chair))
    assert m.score > 0.7 and len(m.pairs) == 6


def _database(path, names=("human", "chair", "castings")):
    db = sqparts.ModelDatabase(path)
    for name in names:
        db.add_view(name, view_from_parts(sqparts.builtin_scene(name).parts, source=name), calibrate=False)
    db.calibrate()
    return db


def test_database_round_trips(tmp_path):
    db = _database(tmp_path / "db")
    assert sorted(p.name for p in (tmp_path / "db").iterdir()) == [
        "castings.json",
        "chair.json",
        "database.json",
        "human.json",
    ]
    again = ModelDatabase(tmp_path / "db")
    assert again.names == db.names and again.threshold == pytest.approx(db.threshold, abs=1e-5)
    for name in db.names:
        (v,), (w,) = db.objects[name], again.objects[name]
        assert [s.kind for s in v.descriptions] == [s.kind for s in w.descriptions]
        for s, t in zip(v.descriptions, w.descriptions):
            np.testing.assert_allclose(t.description.attributes, s.description.attributes, rtol=1e-5, atol=1e-6)
            np.testing.assert_allclose(t.description.relations, s.description.relations, rtol=1e-5, atol=1e-5)
            np.testing.assert_allclose(np.asarray(t.parts.size), np.asarray(s.parts.size), rtol=1e-5)
            assert t.description.surface is not None and s.description.surface is not None
            # Made again from the parts as read back (to 6 digits): the same surface, though
            # a draw may move to a neighbouring cell of the area grid (up to a few cm on a
            # big flat face), well within the alignment's tolerance (8% of the scale).
            a, b = s.description.surface, t.description.surface
            for d in (KDTree(a).query(b)[0], KDTree(b).query(a)[0]):
                assert np.mean(d) < 0.05 * s.description.scale and d.max() < 0.1 * s.description.scale
    text = (tmp_path / "db" / "chair.json").read_text()
    assert text.count("\n") > 100 and '"format": "sqparts-model/1"' in text  # readable, line by line


def test_recognition_best_and_rejection(tmp_path):
    db = _database(tmp_path / "db")
    chair = sqparts.builtin_scene("chair").parts
    best, matches = match_figures([moved(chair[1:])[0]], database=db)  # a leg hidden
    assert best == "chair" and matches[0].name == "chair"
    others = db.without("castings")
    best, matches = match_figures([sqparts.builtin_scene("castings").parts], database=others)
    assert others.statistic == "score"  # two objects, fewer than a cohort: the score decides
    assert best is None and matches[0].score < others.threshold


def test_a_database_without_an_object_is_calibrated_as_one_that_never_had_it(tmp_path):
    """without() calibrates from the kept per-view scores (nothing matched): the same
    threshold, statistic and scores as calibrating the remaining objects from nothing."""
    db = _database(tmp_path / "db")
    before = json.loads(json.dumps(db.calibration))
    left = db.without("human")
    assert db.calibration == before and db.names == ["castings", "chair", "human"]
    fresh = _database(tmp_path / "fresh", names=("chair", "castings"))
    assert left.names == fresh.names and left.statistic == fresh.statistic
    assert left.threshold == pytest.approx(fresh.threshold, abs=1e-6)
    assert left.threshold != pytest.approx(db.threshold, abs=1e-3)
    for v, w in zip(left.calibration["views"], fresh.calibration["views"], strict=True):
        assert (v["object"], v["view"]) == (w["object"], w["view"])
        assert v["scores"] == pytest.approx(w["scores"], abs=1e-6)
    assert left.calibrated_for() and db.calibrated_for()


def test_the_lead_is_the_best_score_less_the_mean_of_the_others(tmp_path):
    assert sqparts.lead(0.9, [0.5, 0.2]) == pytest.approx(0.55)
    assert sqparts.lead(0.7, []) == pytest.approx(0.7)
    db = ModelDatabase(tmp_path / "db")
    assert db.statistic == "score" and db.evidence([0.3, 0.8, 0.5]) == pytest.approx(0.8)
    db.statistic = "lead"
    assert db.evidence([0.3, 0.8, 0.5]) == pytest.approx(0.8 - 0.4) and db.evidence([]) == 0.0
    with pytest.raises(ValueError, match=r"statistic: got 'median', expected one of score, lead"):
        db.calibrate_from([], statistic="median")


def test_calibration_keeps_every_views_scores_and_bounds_their_leads(tmp_path, monkeypatch):
    """The threshold is calibrate_threshold over the leads (numpy, from the stored
    per-view scores), and those scores are what matching each view, left out, gives.
    (Three objects taken for a cohort here, to keep the test small.)"""
    monkeypatch.setattr(sqparts._database, "COHORT", 3)
    db = _database(tmp_path / "db")
    assert db.statistic == "lead"
    views = db.calibration["views"]
    assert [(v["object"], v["view"]) for v in views] == [(n, 0) for n in db.objects]
    first = views[0]
    query, observation = view_observation(db.objects[first["object"]][0])
    again = {n: s for n, s, *_ in db.match(query, exclude=(first["object"], 0), observation=observation)}
    assert again == pytest.approx(first["scores"])
    impostor = []
    for v in views:
        others = np.sort([s for n, s in v["scores"].items() if n != v["object"]])[::-1]
        impostor.append(others[0] - others[1:].mean())
    assert db.calibration["impostor"] == pytest.approx(sorted(impostor))
    assert db.threshold == pytest.approx(sqparts.calibrate_threshold([], impostor))
    # Fewer objects than the cohort: the score itself.
    two = _database(tmp_path / "two", names=("chair", "castings"))
    assert two.statistic == "score"
    assert two.calibration["impostor"] == pytest.approx(
        sorted(max(s for n, s in v["scores"].items() if n != v["object"]) for v in two.calibration["views"])
    )


def test_recalibration_matches_only_what_changed_and_equals_a_full_one(tmp_path, monkeypatch):
    """Adding an object matches the old views against it alone and its view against all;
    the scores and threshold equal a calibration from nothing. A database read back (its
    files) matches nothing again, unless the settings differ."""
    db = _database(tmp_path / "db", names=("chair", "castings"))
    calls = []
    real = ModelDatabase.match
    monkeypatch.setattr(
        ModelDatabase, "match", lambda self, *a, **k: calls.append(sorted(self.objects)) or real(self, *a, **k)
    )
    db.add_view("human", view_from_parts(sqparts.builtin_scene("human").parts, source="human"))
    assert calls == [["human"], ["human"], ["castings", "chair", "human"]]
    incremental, threshold = db.calibration["views"], db.threshold
    db.calibration = {}
    calls.clear()
    db.calibrate()
    assert len(calls) == 3 and all(c == ["castings", "chair", "human"] for c in calls)
    assert [(v["object"], v["view"]) for v in incremental] == [
        (v["object"], v["view"]) for v in db.calibration["views"]
    ]
    for a, b in zip(incremental, db.calibration["views"]):
        assert a["scores"] == pytest.approx(b["scores"], rel=1e-12)
    assert threshold == pytest.approx(db.threshold, rel=1e-12)
    calls.clear()
    again = ModelDatabase(tmp_path / "db")
    assert again.calibrate() == pytest.approx(db.threshold, abs=1e-5) and calls == []
    again.calibrate(settings=sqparts.MatchSettings(alignment_starts=2))
    assert len(calls) == 3


def test_a_version_1_database_is_read_with_its_score_threshold(tmp_path, monkeypatch):
    monkeypatch.setattr(sqparts._database, "COHORT", 3)
    db = _database(tmp_path / "db", names=("chair", "castings", "human"))
    index = tmp_path / "db" / "database.json"
    data = json.loads(index.read_text())
    assert data["format"] == "sqparts-database/2" and data["statistic"] == "lead"
    data.update(format="sqparts-database/1", threshold=0.6)
    del data["statistic"]
    index.write_text(json.dumps(data))
    old = ModelDatabase(tmp_path / "db")
    assert old.statistic == "score" and old.threshold == 0.6 and old.names == db.names
    data.update(format="sqparts-database/2", statistic="median")
    index.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"database.statistic: got 'median', expected one of score, lead"):
        ModelDatabase(tmp_path / "db")


def test_threshold_is_calibrated_between_genuine_and_impostor_scores():
    assert sqparts.calibrate_threshold([0.8, 0.9], [0.2, 0.3]) == pytest.approx(0.55)
    assert sqparts.calibrate_threshold([], [0.6]) == pytest.approx(0.65)
    assert sqparts.calibrate_threshold([], []) == 0.45
    # Of n impostor scores the largest k with (k + 1) / (n + 1) <= 5% (found by brute
    # force) pass: the threshold sits between the (k + 1)th highest and the next score
    # above it, whatever the genuine scores below it.
    for n in (10, 36, 38, 39, 40, 59, 79, 100, 400):
        impostor = np.linspace(0.0, 0.78, n)
        k = max([j for j in range(n) if (j + 1) / (n + 1) <= 0.05 + 1e-12], default=0)
        t = sqparts.calibrate_threshold([0.1, 0.9], impostor)
        upper = impostor[n - k] if k else 0.9  # the next score above the highest rejected one
        assert t == pytest.approx(0.5 * (impostor[n - 1 - k] + upper)), n
        assert np.sum(impostor >= t) == k
    assert sqparts.calibrate_threshold([0.1, 0.9], impostor, false_accept=0.0) == pytest.approx(0.84)


def test_threshold_bounds_the_chance_that_a_new_impostor_passes():
    """The calibrated threshold's promise, checked by simulation: a new impostor score
    drawn like the n stored ones passes with probability at most (k + 1) / (n + 1) <= 5%,
    whatever the law of the scores (the split-conformal bound; k of the n pass)."""
    rng = np.random.default_rng(0)
    laws = (rng.uniform, rng.standard_normal, rng.exponential, lambda size: rng.pareto(3.0, size), rng.uniform)
    for n, law in zip((36, 100, 19, 59, 10), laws):
        trials = 4000
        draws = law(size=(trials, n + 1))
        t = np.array([sqparts.calibrate_threshold([], d[:n]) for d in draws])
        k = int(np.sum(draws[0, :n] >= t[0]))
        assert all(np.sum(d[:n] >= s) == k for d, s in zip(draws, t))
        bound = (k + 1) / (n + 1)
        assert bound <= 0.05 if n >= 19 else bound == 1 / (n + 1)  # too few values: all rejected
        assert np.mean(draws[:, n] >= t) <= bound + 3 * np.sqrt(bound * (1 - bound) / trials), n


@pytest.mark.parametrize("name", ["", "a/b", ".hidden", "database", "x" * 101, 3])
def test_bad_object_names_are_refused(tmp_path, name):
    with pytest.raises(ValueError, match=r"name: got .*, expected 1-100 letters"):
        sqparts.ModelDatabase(tmp_path).add_view(name, view_from_parts(sqparts.builtin_scene("chair").parts))


def test_a_broken_model_file_is_named(tmp_path):
    (tmp_path / "x.json").write_text(
        json.dumps({"format": "sqparts-model/1", "name": "x", "views": [{"main": {"parts": []}}]})
    )
    with pytest.raises(ValueError, match=r"x.json.views\[0\].main"):
        ModelDatabase(tmp_path)
    # A model with no views was loaded, and every recognition missed it with exit 0.
    (tmp_path / "x.json").write_text(json.dumps({"format": "sqparts-model/1", "name": "x", "views": []}))
    with pytest.raises(ValueError, match=r"^x.json.views: got none, expected at least one view"):
        ModelDatabase(tmp_path)


def test_a_hand_edited_database_is_refused_by_name(tmp_path):
    """Session 40's fuzzing: a calibration that is not an object raised AttributeError
    in ``learn`` after the new model file was written; ``"threshold": true`` was read as
    1; a model file naming another object replaced it silently; a negative size in a
    stored description failed deep in matching."""
    db = ModelDatabase(tmp_path)
    db.add_view("chair", view_from_parts(sqparts.builtin_scene("chair").parts))
    index, model = tmp_path / "database.json", tmp_path / "chair.json"
    good, data = json.loads(index.read_text()), json.loads(model.read_text())
    for calibration, match in (
        ("abc", r"database.calibration: got 'abc'"),
        ({"objects": [1]}, r"database.calibration.objects: got \[1\]"),
        ({"views": [{"object": "chair", "view": True, "scores": {}}]}, r"database.calibration.views\[0\]"),
    ):
        index.write_text(json.dumps(dict(good, calibration=calibration)))
        with pytest.raises(ValueError, match=match):
            ModelDatabase(tmp_path)
    index.write_text(json.dumps(dict(good, threshold=True)))
    with pytest.raises(ValueError, match=r"database.threshold: got True"):
        ModelDatabase(tmp_path)
    index.write_text(json.dumps(good))
    model.write_text(json.dumps(dict(data, name="box")))
    with pytest.raises(ValueError, match=r"chair.json: got name 'box', expected 'chair'"):
        ModelDatabase(tmp_path)
    for value, match in ((-1, r"size_1: got -1, expected a number > 0"), (True, r"size_1: got True")):
        bad = json.loads(json.dumps(data))
        bad["views"][0]["main"]["description"]["nodes"][0]["size_1"] = value
        model.write_text(json.dumps(bad))
        with pytest.raises(ValueError, match=r"chair.json.views\[0\].main.description.nodes\[0\]." + match):
            ModelDatabase(tmp_path)
    model.write_text(json.dumps(data))
    assert ModelDatabase(tmp_path).names == ["chair"]


@pytest.mark.parametrize("pose", sorted(sqparts.HUMAN_POSES))
def test_posed_human_keeps_its_limbs(pose):
    s = sqparts.posed_human(pose, resolution=48)
    base = sqparts.builtin_scene("human")
    assert len(s.parts) == 16 and s.part_names == base.part_names
    np.testing.assert_allclose(
        np.sort(np.asarray(s.parts.size), 1)[[0, 2, 3]], np.sort(np.asarray(base.parts.size), 1)[[0, 2, 3]], rtol=1e-5
    )
    depth = np.asarray(sqparts.render_range_image(s.parts, s.camera))
    assert 100 < np.isfinite(depth).sum() < depth.size / 2


def test_unknown_pose_is_refused():
    with pytest.raises(ValueError, match=r"pose: got 'dab', expected one of"):
        sqparts.posed_human("dab")


CAMERA = {"width": 48, "height": 48, "intrinsic_matrix": [80.0, 0, 0, 0, 80.0, 0, 23.5, 23.5, 1]}
FAST = ["--resolution", "0", "--refine-rounds", "0", "--quiet"]
OBJECTS = {
    "cigar": [
        {
            "size": [0.1, 0.1, 0.4],
            "squareness": [1.0, 1.0],
            "position": [0, 0, 2.0],
            "rotation": [[0, 0, 1], [0, 1, 0], [-1, 0, 0]],
        }
    ],
    "slab": [
        {
            "size": [0.35, 0.35, 0.05],
            "squareness": [0.2, 0.2],
            "position": [0, 0, 2.0],
            "rotation": [[1, 0, 0], [0, 0.8, -0.6], [0, 0.6, 0.8]],
        }
    ],
}


@pytest.mark.slow
def test_learn_and_recognize_from_the_command_line(tmp_path, capsys):
    cam = sqparts.camera_from_json(CAMERA)
    (tmp_path / "cam.json").write_text(json.dumps(CAMERA))
    for name, parts in OBJECTS.items():
        scene, _, _ = sqparts.scene_from_dict({"parts": parts})
        np.save(tmp_path / f"{name}.npy", np.asarray(sqparts.render_range_image(scene, cam)))
        assert (
            main(
                [
                    "learn",
                    name,
                    str(tmp_path / f"{name}.npy"),
                    "--camera",
                    str(tmp_path / "cam.json"),
                    "--db",
                    str(tmp_path / "db"),
                    "--levels",
                    "1",
                    *FAST,
                ]
            )
            == 0
        )
    assert sorted(ModelDatabase(tmp_path / "db").names) == ["cigar", "slab"]
    cigar, _, _ = sqparts.scene_from_dict({"parts": OBJECTS["cigar"]})
    r = Rotation.from_rotvec([0.0, 0.5, 0.3]).as_matrix()  # turned about its centre, moved back
    turned, _ = moved(cigar, rotvec=(0.0, 0.5, 0.3), t=np.array([0.05, 0, 2.2]) - r @ [0, 0, 2.0])
    np.save(tmp_path / "query.npy", np.asarray(sqparts.render_range_image(turned, cam)))
    # As an earlier version left it: calibrated for another matcher; recognising calibrates it again.
    ModelDatabase(tmp_path / "db").calibrate(settings=sqparts.MatchSettings(articulated=False))
    capsys.readouterr()
    out = tmp_path / "out"
    assert (
        main(
            [
                "recognize",
                str(tmp_path / "query.npy"),
                "--camera",
                str(tmp_path / "cam.json"),
                "--db",
                str(tmp_path / "db"),
                "--out",
                str(out),
                *FAST[:-1],  # not --quiet: the calibration is announced
            ]
        )
        == 0
    )
    assert "calibrated with other match settings or model files; calibrating it again" in capsys.readouterr().err
    assert ModelDatabase(tmp_path / "db").calibrated_for()
    assert sorted(p.name for p in (out / "query").iterdir()) == ["parts.json", "recognition.json", "report.png"]
    result = json.loads((out / "query" / "recognition.json").read_text())
    assert result["best"] == "cigar" and [m["name"] for m in result["matches"]] == ["cigar", "slab"]
    # Two objects: the evidence is the best score, at or above the threshold it passed.
    assert result["statistic"] == "score" and result["evidence"] == pytest.approx(result["matches"][0]["score"])
    assert result["evidence"] >= result["threshold"]
    assert np.asarray(result["matches"][0]["pose"]).shape == (4, 4) and result["matches"][0]["parts"]
    # Never overwritten silently; --overwrite replaces it.
    assert (
        main(
            [
                "recognize",
                str(tmp_path / "query.npy"),
                "--camera",
                str(tmp_path / "cam.json"),
                "--db",
                str(tmp_path / "db"),
                "--out",
                str(out),
                *FAST,
            ]
        )
        == 2
    )
    assert "which exists, expected a new path (or --overwrite)" in capsys.readouterr().err
    # Several inputs are a batch: an input that fails (no returns at all) gets its line
    # in results.jsonl and the others are recognised; exit status 1.
    np.save(tmp_path / "empty.npy", np.full((CAMERA["height"], CAMERA["width"]), np.nan, np.float32))
    batch = tmp_path / "batch"
    argv = [
        "recognize",
        str(tmp_path / "empty.npy"),
        str(tmp_path / "query.npy"),
        "--camera",
        str(tmp_path / "cam.json"),
    ]
    capsys.readouterr()
    assert main([*argv, "--db", str(tmp_path / "db"), "--out", str(batch), *FAST]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("sqparts: error: input: got 1 of 2 inputs failing (first ") and "results.jsonl" in err
    lines = [json.loads(line) for line in (batch / "results.jsonl").read_text().splitlines()]
    assert [(r["output"], r["status"], r["best"]) for r in lines] == [
        ("empty", "error", None),
        ("query", "ok", "cigar"),
    ]
    assert lines[0]["error"] and lines[1]["error"] is None
    assert sorted(p.name for p in batch.iterdir()) == ["query", "results.jsonl"]
    # An earlier run's results.jsonl is never replaced silently.
    assert main([*argv, "--db", str(tmp_path / "db"), "--out", str(batch), *FAST]) == 2
    assert "results.jsonl of an earlier run" in capsys.readouterr().err
    # Outputs never go into the database's folder (sub-folders beside its model files).
    before = sorted(p.name for p in (tmp_path / "db").iterdir())
    for inside in (tmp_path / "db", tmp_path / "db" / "o"):
        assert main([*argv, "--db", str(tmp_path / "db"), "--out", str(inside), "--overwrite", *FAST]) == 2
        assert "which is in --db" in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "db").iterdir()) == before


def test_recognize_with_an_empty_database_is_one_line(tmp_path, capsys):
    np.save(tmp_path / "x.npy", np.ones((4, 4), np.float32))
    (tmp_path / "cam.json").write_text(
        json.dumps({"width": 4, "height": 4, "intrinsic_matrix": [4.0, 0, 0, 0, 4.0, 0, 1.5, 1.5, 1]})
    )
    (tmp_path / "empty").mkdir()
    for db, says in (("none", "which is not a folder"), ("empty", "with no objects")):
        argv = ["recognize", str(tmp_path / "x.npy"), "--camera", str(tmp_path / "cam.json")]
        assert main([*argv, "--db", str(tmp_path / db), "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("sqparts: error: --db: got") and says in err, err
        assert "expected a database made by sqparts learn" in err and "\n" not in err
        assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "argv, start",
    [
        (["learn", "a/b", "x.npy"], "sqparts: error: name: got 'a/b', expected 1-100 letters"),
        (["learn", "ok", "missing.npy"], "sqparts: error: input: got"),
        (["learn", "ok", "x.npy", "--levels", "9"], "sqparts: error: --levels: got '9', expected an integer in [1, 4]"),
    ],
)
def test_learn_errors_are_one_line_before_any_work(tmp_path, capsys, monkeypatch, argv, start):
    monkeypatch.chdir(tmp_path)
    np.save(tmp_path / "x.npy", np.ones((4, 4), np.float32))
    assert main([*argv, "--db", str(tmp_path / "db")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(start) and "\n" not in err
    assert not (tmp_path / "db").exists()


def test_a_database_path_that_is_a_file_is_refused(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(NotADirectoryError, match=r"--db: got .*, which is a file, expected a database folder"):
        ModelDatabase(tmp_path / "f")


def test_bad_match_settings_are_refused():
    with pytest.raises(ValueError, match=r"weighting: got 'x', expected 'fraction' or 'volume'"):
        sqparts.MatchSettings(weighting="x")
    with pytest.raises(ValueError, match=r"alignment_tolerance: got 0, expected a number > 0 or None"):
        sqparts.MatchSettings(alignment_tolerance=0)
    with pytest.raises(ValueError, match=r"alignment_pairs: got True, expected an integer >= 1"):
        sqparts.MatchSettings(alignment_pairs=True)
    with pytest.raises(ValueError, match=r"verification_tolerance: got -1, expected a number > 0 or None"):
        sqparts.MatchSettings(verification_tolerance=-1)
    with pytest.raises(ValueError, match=r"articulated: got 'yes', expected True or False"):
        sqparts.MatchSettings(articulated="yes")
    # Fields that failed deep in scipy or numpy, or silently gave a self-match score 0.
    for field, value in [
        ("size_tolerance", float("nan")),
        ("distance_tolerance", 0),
        ("angle_tolerance", "x"),
        ("iterations", 1.5),
        ("iterations", -1),
        ("min_similarity", float("nan")),
        ("verification_levels", 0),
        ("verification_levels", 2.0),
        ("pose_rotations", 0),
        ("pose_starts", -1),
        ("pose_starts", True),
    ]:
        with pytest.raises(ValueError, match=rf"{field}: got .*, expected"):
            sqparts.MatchSettings(**{field: value})


# --- the whole solid: its outer surface, aligned -----------------------------------------


def test_surface_cloud_covers_the_outer_surface_of_two_overlapping_spheres():
    """Two spheres (radii 0.2 and 0.1, centres 0.25 apart): every point lies on one sphere
    and outside the other, and the share on each is its exposed area's (closed form:
    a sphere of radius r loses a cap of area 2 pi r h to the other)."""
    r1, r2, d = 0.2, 0.1, 0.25
    spheres = stack_parts(
        [
            sqparts.Part(size=[r1] * 3, squareness=[1.0, 1.0], position=[0.0, 0.0, 2.0]),
            sqparts.Part(size=[r2] * 3, squareness=[1.0, 1.0], position=[d, 0.0, 2.0]),
        ]
    )
    pts = surface_cloud(spheres)
    a = np.linalg.norm(pts - [0.0, 0.0, 2.0], axis=1)
    b = np.linalg.norm(pts - [d, 0.0, 2.0], axis=1)
    on_first = np.abs(a - r1) < 1e-5
    assert np.all(on_first | (np.abs(b - r2) < 1e-5))
    assert np.all(a >= r1 - 1e-5) and np.all(b >= r2 - 1e-5)  # nothing inside the other sphere
    x = (d * d + r1 * r1 - r2 * r2) / (2 * d)  # the plane of the circle where the spheres meet
    exposed1 = 4 * np.pi * r1**2 - 2 * np.pi * r1 * (r1 - x)
    exposed2 = 4 * np.pi * r2**2 - 2 * np.pi * r2 * (r2 - (d - x))
    assert on_first.mean() == pytest.approx(exposed1 / (exposed1 + exposed2), abs=0.03)


@pytest.mark.parametrize("scene", ["chair", "castings"])
def test_aligning_a_moved_solid_finds_the_motion(scene):
    parts = sqparts.builtin_scene(scene).parts
    query, pose = moved(parts)
    a = align_descriptions(describe(query), describe(parts))
    assert a.score > 0.99
    np.testing.assert_allclose(a.pose, pose, atol=2e-3)
    others = [n for n in ("human", "chair", "castings") if n != scene]
    for other in others:
        assert align_descriptions(describe(query), describe(sqparts.builtin_scene(other).parts)).score < 0.5


def test_alignment_tolerates_a_hidden_part_and_ignores_how_the_solid_is_cut():
    """The chair with a leg hidden still aligns with the chair (pose as moved) better than
    with the other objects; the bar-and-head solid cut 40/60 aligns with the uncut one
    far better than another object does, where the part graph changes."""
    chair = sqparts.builtin_scene("chair").parts
    query, pose = moved(chair[1:])
    a = align_descriptions(describe(query), describe(chair))
    np.testing.assert_allclose(a.pose, pose, atol=1e-2)  # within 1 cm: the hidden leg pulls a little
    for other in ("human", "castings"):
        assert a.score > align_descriptions(describe(query), describe(sqparts.builtin_scene(other).parts)).score + 0.3
    bar = sqparts.Part(size=[0.05, 0.05, 0.4], squareness=[0.3, 1.0], position=[0.0, 0.0, 2.0])
    head = sqparts.Part(size=[0.15, 0.12, 0.1], squareness=[0.5, 0.5], position=[0.0, 0.0, 2.5])
    pieces = [
        sqparts.Part(size=[0.05, 0.05, 0.16], squareness=[0.3, 1.0], position=[0.0, 0.0, 1.76]),
        sqparts.Part(size=[0.05, 0.05, 0.24], squareness=[0.3, 1.0], position=[0.0, 0.0, 2.16]),
    ]
    model = describe(stack_parts([bar, head]))
    cut = align_descriptions(describe(moved(stack_parts([*pieces, head]))[0]), model)
    other = describe(stack_parts([head, dataclasses.replace(head, position=np.array([0.0, 0.3, 2.5]))]))
    # Not 1: the two pieces' rounded ends pinch the bar where it was cut.
    assert cut.score > 0.8 and cut.score > align_descriptions(other, model).score + 0.3


# --- verification: stored parts rendered into the query's camera ----------------------

ORTHO = sqparts.OrthographicCamera(48, 48, 0.01, 23.5, 23.5)


def _observed(parts, camera=ORTHO):
    depth = np.asarray(sqparts.render_range_image(parts, camera))
    return Observation(depth, camera, np.isfinite(depth)[None])


def test_verification_of_a_solid_moved_along_the_rays_is_the_closed_form():
    """Orthographic rays along z: a solid moved by d along z keeps its silhouette and
    every rendered depth moves by exactly d, so explained = precision = exp(-d²/2τ²); a
    solid moved off the figure explains nothing."""
    box = sqparts.Part(size=[0.1, 0.07, 0.05], squareness=[0.3, 0.5], position=[0.0, 0.0, 1.0], taper=0.2)
    obs, tau = _observed(stack_parts([box])), 0.02
    shifts = [0.0, 0.01, 0.02, 0.04]
    solids = [stack_parts([dataclasses.replace(box, position=np.array([0.0, 0.0, 1.0 + d]))]) for d in shifts]
    solids.append(stack_parts([dataclasses.replace(box, position=np.array([0.3, 0.0, 1.0]))]))
    got = verify_poses(solids, obs, obs.figures[0], [tau] * len(solids))
    want = [np.exp(-0.5 * (d / tau) ** 2) for d in shifts] + [0.0]
    np.testing.assert_allclose(got, want, atol=2e-3)


def test_verification_at_several_tolerances_is_the_mean_of_their_closed_forms():
    """``levels=3``: the mean of exp(-d²/2τ_k²) over τ, τ/2 and τ/4 for a solid moved by d
    along orthographic rays (every d within 2τ/4, so that no pixel is taken for hidden)."""
    box = sqparts.Part(size=[0.1, 0.07, 0.05], squareness=[0.3, 0.5], position=[0.0, 0.0, 1.0], taper=0.2)
    obs, tau = _observed(stack_parts([box])), 0.04
    shifts = [0.0, 0.005, 0.01, 0.015]
    solids = [stack_parts([dataclasses.replace(box, position=np.array([0.0, 0.0, 1.0 + d]))]) for d in shifts]
    got = verify_poses(solids, obs, obs.figures[0], tau, levels=3)
    want = [np.mean([np.exp(-0.5 * (d / (tau / 2**k)) ** 2) for k in range(3)]) for d in shifts]
    np.testing.assert_allclose(got, want, atol=2e-3)
    assert got[3] < verify_poses(solids[3:], obs, obs.figures[0], tau)[0] - 0.2  # tighter than τ alone
    with pytest.raises(ValueError, match=r"levels: got 0, expected an integer >= 1"):
        verify_poses(solids, obs, obs.figures[0], tau, levels=0)


def test_verification_does_not_count_a_model_hidden_by_an_occluder():
    """A plate in front hides the left half of a sphere: the true sphere still scores
    about 1 on the figure it explains (its visible half), since the hidden half is behind
    observed surface; a sphere twice as wide spills off the figure and scores less."""
    sphere = sqparts.Part(size=[0.12] * 3, squareness=[1.0, 1.0], position=[0.0, 0.0, 1.0])
    plate = sqparts.Part(size=[0.1, 0.3, 0.01], squareness=[0.1, 0.1], position=[-0.1, 0.0, 0.7])
    depth, labels = sqparts.render_range_image(stack_parts([sphere, plate]), ORTHO, return_labels=True)
    obs = Observation(np.asarray(depth), ORTHO, (np.asarray(labels) == 0)[None])
    big = dataclasses.replace(sphere, size=np.array([0.2, 0.12, 0.12]))
    score = verify_poses([stack_parts([sphere]), stack_parts([big])], obs, obs.figures[0], 0.01)
    assert score[0] > 0.98 and score[1] < 0.85


def test_verification_picks_the_pose_the_range_image_shows():
    """Two boxes seen from the front, and two candidate poses of them that differ by a
    half turn about the viewing axis: the one that reproduces the image scores 1, the
    other about the share of the image the two have in common (0.45)."""
    box = sqparts.Part(size=[0.15, 0.05, 0.05], squareness=[0.2, 0.2], position=[0.05, 0.0, 1.0])
    wedge = sqparts.Part(size=[0.05, 0.12, 0.05], squareness=[0.2, 0.2], position=[0.15, 0.05, 1.0])
    model = stack_parts([box, wedge])
    obs = _observed(model)
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])  # a half turn about the z axis (through (0, 0, 1))
    good, bad = verify_poses([model, transform_parts(model, flip)], obs, obs.figures[0], 0.02)
    assert good > 0.99 and bad < 0.6


def test_verified_matching_prefers_the_object_in_the_image(tmp_path):
    """The chair's range image, matched with the image: the chair's stored parts at their
    best pose reproduce it (score near 1: at the tightest tolerance, a quarter of 10% of
    the chair's scale, the fitted pose's millimetres show); the other objects score far
    lower."""
    db = _database(tmp_path / "db")
    s = sqparts.builtin_scene("chair")
    obs = _observed(s.parts, s.camera)
    best, matches = match_figures([s.parts], database=db, observation=obs)
    verified = {m.name: m.score for m in matches}
    assert best == "chair" and verified["chair"] > 0.92
    for name in ("human", "castings"):
        assert verified[name] < verified["chair"] - 0.3
    with pytest.raises(ValueError, match=r"observation: got 1 figure masks, expected one per figure \(2\)"):
        match_figures([s.parts, s.parts], database=db, observation=obs)


def test_fitting_a_pose_to_the_observed_points_recovers_the_motion():
    """The chair, moved and seen by its camera (the visible side only): a pose 4 degrees
    and 3 cm off is brought back onto the observed points to within 1 cm, and its
    verification rises to about 1."""
    s = sqparts.builtin_scene("chair")
    model = view_from_parts(s.parts).main  # centred: the model frame
    centre = np.asarray(s.parts.position, float).mean(0) - np.asarray(model.parts.position, float).mean(0)
    truth = np.eye(4)
    truth[:3, 3] = centre
    obs = _observed(transform_parts(model.parts, truth), s.camera)
    off = np.eye(4)
    off[:3, :3] = Rotation.from_rotvec([0.0, np.radians(4.0), 0.0]).as_matrix()
    off[:3, 3] = centre + [0.03, -0.01, 0.02]
    points = observed_points(obs, obs.figures[0])
    fitted = fit_pose(points, model.description, off, 0.08 * model.description.scale)
    probe = np.asarray(model.parts.position, float)
    moved_by = lambda pose: probe @ pose[:3, :3].T + pose[:3, 3]  # noqa: E731
    assert np.abs(moved_by(off) - moved_by(truth)).max() > 0.03
    assert np.abs(moved_by(fitted) - moved_by(truth)).max() < 0.01
    tau = 0.1 * model.description.scale
    before, after = verify_poses(
        [transform_parts(model.parts, off), transform_parts(model.parts, fitted)], obs, obs.figures[0], tau
    )
    assert after > 0.97 and after > before + 0.1
    np.testing.assert_array_equal(fit_pose(points[:2], model.description, off, 0.05), off)  # too few: as given
    far = off.copy()
    far[2, 3] += 5.0  # 5 m behind: no observed point within 8 sigma (0.4 m) of its surface
    np.testing.assert_array_equal(fit_pose(points, model.description, far, 0.05), far)  # out of reach: as given


def test_the_rotation_lattice_covers_every_rotation_evenly():
    """512 lattice rotations: proper rotations, no two closer than 15 degrees, and every
    one of 2000 random rotations (scipy's uniform draw) within 30 degrees of one of them,
    where 512 random rotations leave some 36 degrees away."""
    lattice = rotation_lattice(512)
    np.testing.assert_allclose(
        np.einsum("nab,ncb->nac", lattice, lattice), np.broadcast_to(np.eye(3), (512, 3, 3)), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(lattice), 1.0, atol=1e-12)
    rotations = Rotation.from_matrix(lattice)
    nearest = lambda r, among: (among.inv() * r).magnitude().min()  # noqa: E731
    others = [nearest(rotations[k], rotations[np.arange(512) != k]) for k in range(512)]
    assert np.degrees(min(others)) > 15.0
    probes = Rotation.random(2000, random_state=1)
    assert np.degrees(max(nearest(r, rotations) for r in probes)) < 30.0
    drawn = Rotation.random(512, random_state=2)
    assert np.degrees(max(nearest(r, drawn) for r in probes)) > 33.0


def test_poses_proposed_from_the_observed_points_alone_find_the_object_turned_any_way():
    """The chair turned 8 random ways and seen by its camera (its visible side only): of
    four poses proposed from the observed points (no query description), each fitted to
    them, the best verified one puts the chair's part centres within 3 cm of the truth
    and verifies above 0.75 (at τ, τ/2 and τ/4) in at least 6 of the 8. The proposals are
    proper rigid motions and distinct; none without a surface or points."""
    s = sqparts.builtin_scene("chair")
    model = view_from_parts(s.parts).main
    sigma, tau = 0.08 * model.description.scale, 0.1 * model.description.scale
    probe = np.asarray(model.parts.position, float)
    found = 0
    for k in range(8):
        truth = np.eye(4)
        truth[:3, :3] = Rotation.random(random_state=k).as_matrix()
        truth[:3, 3] = np.asarray(s.parts.position, float).mean(0)
        obs = _observed(transform_parts(model.parts, truth), s.camera)
        points = observed_points(obs, obs.figures[0])
        proposed = propose_poses(points, model.description, sigma, rotations=512, count=4)
        assert len(proposed) == 4
        for pose in proposed:
            np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-9)
            assert np.linalg.det(pose[:3, :3]) == pytest.approx(1.0) and np.array_equal(pose[3], [0, 0, 0, 1])
        assert min(np.linalg.norm(a[:3, :3] - b[:3, :3]) for i, a in enumerate(proposed) for b in proposed[:i]) > 0.3
        fitted = [fit_pose(points, model.description, pose, sigma) for pose in proposed]
        scores = verify_poses([transform_parts(model.parts, f) for f in fitted], obs, obs.figures[0], tau, levels=3)
        best = fitted[int(np.argmax(scores))]
        error = np.abs(probe @ (best[:3, :3] - truth[:3, :3]).T + best[:3, 3] - truth[:3, 3]).max()
        found += bool(error < 0.03 and scores.max() > 0.75)
    assert found >= 6
    assert propose_poses(points[:2], model.description, sigma, rotations=512, count=4) == []
    assert (
        propose_poses(points, dataclasses.replace(model.description, surface=None), sigma, rotations=8, count=4) == []
    )


@pytest.mark.parametrize("turn", [0, 1, 2])
def test_a_query_cut_unlike_any_stored_view_is_posed_by_its_image(tmp_path, turn):
    """The chair turned a random way, its recovery standing in as one box over the whole
    figure (parts that resemble none of the stored chair's): the alignment of the two
    recoveries has nothing to go on, the poses proposed from the image do. With them
    (``pose_starts``, the default) the chair verifies above 0.88 and comes first; with
    the alignment's starts alone (0) below 0.65, under the person or the castings."""
    db = _database(tmp_path / "db")
    s = sqparts.builtin_scene("chair")
    turned = np.eye(4)
    turned[:3, :3] = Rotation.random(random_state=turn).as_matrix()
    centre = np.asarray(s.parts.position, float).mean(0)
    turned[:3, 3] = centre - turned[:3, :3] @ centre
    obs = _observed(transform_parts(s.parts, turned), s.camera)
    seen = np.asarray(s.camera.points(obs.depth))[obs.figures[0]]
    lo, hi = seen.min(0), seen.max(0)
    blob = stack_parts([sqparts.Part(size=(hi - lo) / 2, squareness=[0.5, 0.5], position=(hi + lo) / 2)])
    best, matches = match_figures([blob], database=db, observation=obs)
    assert best == "chair" and matches[0].name == "chair" and matches[0].score > 0.88
    _, alone = match_figures([blob], database=db, observation=obs, settings=sqparts.MatchSettings(pose_starts=0))
    assert {m.name: m.score for m in alone}["chair"] < 0.65


def test_a_view_seen_again_is_its_own_parts_from_its_own_side():
    """view_observation renders the stored parts from the side they were learnt from: the
    nearest point of the rendering is the parts' nearest point along -z (closed form for
    an axis-aligned box, moved 6 radii away), and the view verified against its own
    rendering at the identity pose scores 1."""
    box = sqparts.Part(size=[0.2, 0.1, 0.05], squareness=[0.1, 0.1], position=[0.3, 0.1, 2.0])
    view = view_from_parts(stack_parts([box]))
    query, obs = view_observation(view)
    radius = 0.2  # the stored part is centred: |position| 0 plus its largest semi-axis
    assert np.nanmin(obs.depth) == pytest.approx(6 * radius - 0.05, abs=2e-3)
    assert obs.figures.shape == (1, 64, 64) and obs.figures.sum() > 200
    pose = np.eye(4)
    pose[:3, 3] = query.positions[0] - np.asarray(view.main.parts.position)[0]
    assert verify_poses([transform_parts(view.main.parts, pose)], obs, obs.figures[0], 0.01)[0] > 0.99


def test_moving_parts_moves_their_surface_rigidly():
    """transform_parts against the motion applied to the surface points themselves."""
    parts = sqparts.builtin_scene("castings").parts
    moved_parts, pose = moved(parts)
    np.testing.assert_allclose(
        surface_cloud(moved_parts), surface_cloud(parts) @ pose[:3, :3].T + pose[:3, 3], atol=2e-5
    )


def test_verification_on_a_lattice_equals_the_full_image_formula_at_those_pixels(monkeypatch):
    """verify_poses renders a large figure's image on a lattice of every s-th pixel;
    against numpy on the full image's rendering at those pixels (the formula written out
    again), for a pose that fits and one that spills."""
    import sqparts._recognize as R
    from sqparts._encoding import part_vectors, render_layers

    s = sqparts.builtin_scene("chair")
    obs = _observed(s.parts, s.camera)
    figure = obs.figures[0]
    off = np.eye(4)
    off[:3, 3] = [0.05, 0.0, 0.0]
    solids = [s.parts, transform_parts(s.parts, off)]
    tau = 0.02
    for pixels in (R.VERIFY_PIXELS, int(figure.sum()) // 4):  # the default, then a step of 2
        monkeypatch.setattr(R, "VERIFY_PIXELS", pixels)
        window, camera = R.verification_lattice(s.camera, figure)
        got = verify_poses(solids, obs, figure, tau)
        want = []
        for solid in solids:
            full = render_layers(part_vectors(solid), s.camera).min(0)[window]
            d, f = obs.depth[window], figure[window]
            agree = np.zeros(d.shape)
            both = np.isfinite(full) & np.isfinite(d)
            agree[both] = np.exp(-0.5 * ((full[both] - d[both]) / tau) ** 2)
            visible = np.isfinite(full) & ~(both & (np.nan_to_num(d, nan=np.inf) < full - 2 * tau))
            want.append(np.sqrt(agree[f].sum() / f.sum() * agree[visible].sum() / visible.sum()))
        np.testing.assert_allclose(got, want, atol=1e-5)
        assert got[0] > 0.99 > got[1]
    assert window[0].step == 2 and camera.width == len(range(*window[1].indices(s.camera.width)))
    assert R.verification_lattice(s.camera, figure[:1])[0] == (slice(None), slice(None))  # a small figure: every pixel


def test_coarse_to_fine_ranking_keeps_the_brute_force_best_poses():
    """Against brute force (every proposal's mean similarity on all its points): the
    shortlist's values are exact, and the best poses come first in the same order."""
    cloud = surface_cloud(sqparts.builtin_scene("chair").parts)
    surface, tree, sigma = cloud[::5], KDTree(cloud), 0.02
    rng = np.random.default_rng(3)
    rot = Rotation.random(300, random_state=4).as_matrix()
    rot[:5] = Rotation.from_rotvec(rng.normal(0, 0.05, (5, 3))).as_matrix()  # five near the truth
    trans = surface.mean(0) - rot @ surface.mean(0) + rng.normal(0, 0.01, (300, 3))
    exact = np.array([_similarity(tree, surface @ r.T + t, sigma).mean() for r, t in zip(rot, trans)])  # one at a time
    rank = _rank_poses(tree, rot, trans, surface, sigma)
    best = np.argsort(-exact, kind="stable")[:5]
    np.testing.assert_array_equal(np.argsort(-rank, kind="stable")[:5], best)
    shortlisted = rank > -1.0
    assert shortlisted.sum() == _SHORTLIST
    np.testing.assert_allclose(rank[shortlisted], exact[shortlisted], rtol=1e-12)
    assert rank[~shortlisted].max() < rank[shortlisted].min()


def test_every_refined_alignment_is_a_rigid_motion_best_first():
    parts = sqparts.builtin_scene("chair").parts
    query = describe(moved(parts)[0])
    found = align_candidates(query, describe(parts))
    assert 1 < len(found) <= sqparts.MatchSettings().alignment_starts
    assert [a.score for a in found] == sorted((a.score for a in found), reverse=True)
    for a in found:
        r = a.pose[:3, :3]
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(r) == pytest.approx(1.0) and np.array_equal(a.pose[3], [0, 0, 0, 1])
    assert align_candidates(dataclasses.replace(query, surface=None), describe(parts)) == []


def test_bad_observations_are_refused():
    with pytest.raises(
        ValueError, match=r"observation: got depth \(4, 4\) and figures \(1, 4, 4\), expected \(48, 48\)"
    ):
        Observation(np.zeros((4, 4)), ORTHO, np.zeros((1, 4, 4), bool))


# --- the whole-object term: the D2 shape distribution of the parts' surfaces -----------


def _bin_masses(cdf):
    edges = np.linspace(0, SHAPE_RANGE, SHAPE_BINS + 1)
    return np.diff(cdf(edges))


def test_shape_distribution_of_a_sphere_is_the_closed_form():
    """Two uniform points on a sphere of radius R are d apart with P(D <= d) = d² / 4R²."""
    r = 0.3
    sphere = sqparts.Part(size=[r, r, r], squareness=[1.0, 1.0], position=[0.1, -0.2, 2.0])
    h = shape_distribution(sphere)
    scale = np.cbrt(4 / 3 * np.pi * r**3)
    expected = _bin_masses(lambda d: np.clip((d * scale) ** 2 / (4 * r * r), 0, 1))
    np.testing.assert_allclose(h.sum(), 1.0, atol=1e-9)
    assert np.abs(np.cumsum(h) - np.cumsum(expected)).max() < 0.03


def test_shape_distribution_of_two_boxes_matches_a_trimesh_reference():
    """Two touching boxy parts (ε = 0.1) against the same solid as a trimesh mesh, its
    surface sampled uniformly at random (an independent estimate of D2)."""
    import trimesh

    parts = stack_parts(
        [
            sqparts.Part(size=[0.3, 0.1, 0.1], squareness=[0.1, 0.1], position=[0.0, 0.0, 2.0]),
            sqparts.Part(size=[0.1, 0.2, 0.1], squareness=[0.1, 0.1], position=[0.4, 0.1, 2.0]),
        ]
    )
    h = shape_distribution(parts)
    mesh = trimesh.util.concatenate(
        [
            trimesh.creation.box(extents=[0.6, 0.2, 0.2]).apply_translation([0.0, 0.0, 2.0]),
            trimesh.creation.box(extents=[0.2, 0.4, 0.2]).apply_translation([0.4, 0.1, 2.0]),
        ]
    )
    rng = np.random.default_rng(0)
    a = trimesh.sample.sample_surface(mesh, 200_000, seed=1)[0]
    b = trimesh.sample.sample_surface(mesh, 200_000, seed=2)[0]
    scale = np.cbrt(0.6 * 0.2 * 0.2 + 0.2 * 0.4 * 0.2)  # boxes of ε 0.1 are within 2% of their volume
    d = np.linalg.norm(a - b[rng.permutation(len(b))], axis=1) / scale
    ref, _ = np.histogram(np.minimum(d, SHAPE_RANGE - 1e-9), bins=SHAPE_BINS, range=(0, SHAPE_RANGE))
    ref = ref / ref.sum()
    emd = np.abs(np.cumsum(h) - np.cumsum(ref)).sum() * SHAPE_RANGE / SHAPE_BINS
    assert emd < 0.06  # 12 x 24 cells a part, each standing for its area at its centre: 0.04 here


@pytest.mark.parametrize("scene", ["human", "chair"])
def test_shape_distribution_is_invariant_to_a_rigid_motion_and_units(scene):
    parts = sqparts.builtin_scene(scene).parts
    moved_parts, _ = moved(parts)
    big = dataclasses.replace(parts, size=np.asarray(parts.size) * 2.5, position=np.asarray(parts.position) * 2.5)
    a, b, c = (shape_distribution(p) for p in (parts, moved_parts, big))
    np.testing.assert_allclose(b, a, atol=2e-4)
    np.testing.assert_allclose(c, a, atol=2e-4)
    np.testing.assert_array_equal(describe(parts).shape_distribution, a)
    settings = sqparts.MatchSettings(shape_tolerance=0.5)
    assert sqparts.match_descriptions(describe(moved_parts), describe(parts), settings).score == pytest.approx(
        1.0, abs=1e-3
    )


def test_a_part_split_in_two_keeps_the_whole_object_term():
    """A bar recovered as two unequal pieces (a 40/60 cut) instead of one: the part graph
    changes, the whole object's shape distribution barely; a different object's does."""
    bar = sqparts.Part(size=[0.05, 0.05, 0.4], squareness=[0.3, 1.0], position=[0.0, 0.0, 2.0])
    head = sqparts.Part(size=[0.15, 0.12, 0.1], squareness=[0.5, 0.5], position=[0.0, 0.0, 2.5])
    model = describe(stack_parts([bar, head]))
    pieces = [
        sqparts.Part(size=[0.05, 0.05, 0.16], squareness=[0.3, 1.0], position=[0.0, 0.0, 1.76]),
        sqparts.Part(size=[0.05, 0.05, 0.24], squareness=[0.3, 1.0], position=[0.0, 0.0, 2.16]),
    ]
    split = describe(moved(stack_parts([*pieces, head]))[0])
    other = describe(stack_parts([head, dataclasses.replace(head, position=np.array([0.0, 0.3, 2.5]))]))
    assert shape_similarity(split, model) > 0.75  # the cut adds two end faces inside the bar
    assert shape_similarity(other, model) < 0.5
    settings = sqparts.MatchSettings(shape_tolerance=0.5)
    assert (
        sqparts.match_descriptions(split, model, settings).score
        > sqparts.match_descriptions(other, model, settings).score
    )


def test_descriptions_without_a_shape_distribution_still_read_and_match():
    d = describe(sqparts.builtin_scene("chair").parts)
    data = d.to_json()
    assert len(data["shape_distribution"]) == SHAPE_BINS
    del data["shape_distribution"]
    old = Description.from_json(data)
    assert old.shape_distribution is None and shape_similarity(old, d, 0.5) == 1.0
    with pytest.raises(ValueError, match=r"description.shape_distribution: got values summing to 2"):
        Description.from_json({**d.to_json(), "shape_distribution": [2.0] + [0.0] * (SHAPE_BINS - 1)})
    with pytest.raises(ValueError, match=r"shape_tolerance: got -1, expected a number > 0 or None"):
        sqparts.MatchSettings(shape_tolerance=-1)


# --- articulation: stored parts turned about their joints (configuration) ----------------

ARM_CAMERA = sqparts.OrthographicCamera(80, 48, 0.01, 28.0, 23.5)


def _arm(bend_degrees=0.0):
    """An upper arm along x (long axis a3 turned onto x, its ends' centres at x = ±0.15)
    and a forearm touching its end at (0.15, 0, 1), turned by ``bend_degrees`` about the
    viewing axis through that joint."""
    turn = Rotation.from_rotvec([0.0, np.pi / 2, 0.0])  # local z onto x
    bend = Rotation.from_rotvec([0.0, 0.0, np.radians(bend_degrees)])
    joint = np.array([0.15, 0.0, 1.0])
    upper = sqparts.Part(
        size=[0.04, 0.04, 0.15], squareness=[0.2, 1.0], position=[0.0, 0.0, 1.0], orientation=turn.as_rotvec()
    )
    fore = sqparts.Part(
        size=[0.03, 0.03, 0.12],
        squareness=[0.2, 1.0],
        position=joint + bend.apply([0.12, 0.0, 0.0]),
        orientation=(bend * turn).as_rotvec(),
    )
    return stack_parts([upper, fore]), joint


def test_the_kinematic_tree_of_an_arm_joins_its_parts_where_they_touch():
    """The larger part is the root; the forearm's joint is where the two flat ends meet
    (both ends' centres are surface samples: the closed form)."""
    arm, joint = _arm()
    tree = kinematic_tree(arm, describe(arm).touching)
    assert tree.order == (0, 1) and tree.parent.tolist() == [-1, 0]
    np.testing.assert_allclose(tree.joints[1], joint, atol=1e-4)
    assert tree.subtree.tolist() == [[True, True], [False, True]]
    lone = stack_parts([arm[0]])
    assert kinematic_tree(lone, describe(lone).touching).order == (0,)


def test_articulating_a_straight_arm_onto_a_bent_one_recovers_the_bend():
    """The straight arm's tree, articulated onto the range image of the same arm bent 30
    degrees at the elbow: the forearm's motion is the 30-degree turn about the joint (its
    far end within 1 cm of the truth, 6 cm away rigidly), the upper arm stays (its ends
    within 1 cm), and the
    articulated rendering verifies where the rigid one does not. A solid of one part is
    left at the rigid pose."""
    straight, joint = _arm()
    bent, _ = _arm(30.0)
    obs = _observed(bent, ARM_CAMERA)
    points = observed_points(obs, obs.figures[0])
    sigma = 0.08 * describe(straight).scale
    motion = articulate(kinematic_tree(straight, describe(straight).touching), points, np.eye(4), sigma)
    far = np.array([0.39, 0.0, 1.0])  # the straight forearm's far end
    truth = joint + Rotation.from_rotvec([0.0, 0.0, np.radians(30.0)]).apply(far - joint)
    assert np.linalg.norm(far - truth) > 0.06
    assert np.linalg.norm(motion[1, :3, :3] @ far + motion[1, :3, 3] - truth) < 0.01
    ends = np.array([[-0.15, 0.0, 1.0], [0.15, 0.0, 1.0]])  # the upper arm's (a turn about its axis is no motion)
    assert np.abs(ends @ motion[0, :3, :3].T + motion[0, :3, 3] - ends).max() < 0.01
    articulated = transform_parts(straight, motion)
    rigid_score, articulated_score = verify_poses([straight, articulated], obs, obs.figures[0], 0.01)
    assert articulated_score > 0.9 and articulated_score > rigid_score + 0.2
    lone = stack_parts([straight[0]])
    pose = moved(lone)[1]
    np.testing.assert_array_equal(
        articulate(kinematic_tree(lone, describe(lone).touching), points, pose, sigma)[0], pose
    )


def test_moving_each_part_by_its_own_motion_is_moving_them_one_by_one():
    parts = sqparts.builtin_scene("castings").parts
    poses = np.stack([moved(parts, rotvec=(0.2 * i, -0.5, 0.1 * i), t=(i, 0.0, 1.0))[1] for i in range(len(parts))])
    together = transform_parts(parts, poses)
    for i in range(len(parts)):
        alone = transform_parts(stack_parts([parts[i]]), poses[i])
        np.testing.assert_allclose(np.asarray(together.position)[i], np.asarray(alone.position)[0], atol=1e-5)
        np.testing.assert_allclose(np.asarray(together[i].rotation()), np.asarray(alone[0].rotation()), atol=1e-5)


def test_a_bent_arm_is_recognised_by_its_straight_view_articulated(tmp_path):
    """The arm learnt straight, seen bent 30 degrees: matched with articulation it scores
    higher than rigidly, its match keeps the motions, the matched model's parts lie on the seen ones, and
    its rendering explains the image where the best rigid pose's does less well."""
    straight, _ = _arm()
    bent, _ = _arm(30.0)
    db = ModelDatabase(tmp_path / "db")
    db.add_view("arm", view_from_parts(straight), calibrate=False)
    obs = _observed(bent, ARM_CAMERA)
    _, (rigid,) = match_figures([bent], database=db, observation=obs, settings=sqparts.MatchSettings(articulated=False))
    _, (art,) = match_figures([bent], database=db, observation=obs)
    assert rigid.articulation is None and art.articulation is not None and art.articulation.shape == (2, 4, 4)
    assert art.score > rigid.score + 0.05
    np.testing.assert_allclose(np.asarray(art.posed_parts().position), np.asarray(bent.position), atol=0.02)
    tau = 0.1 * describe(bent).scale  # verification_tolerance's (the query's scale)
    rigid_check, art_check = verify_poses([rigid.posed_parts(), art.posed_parts()], obs, obs.figures[0], tau)
    assert art_check > 0.8 and art_check > rigid_check + 0.15
    assert np.array(json.loads(json.dumps(art.to_json()))["articulation"]).shape == (2, 4, 4)


def test_a_database_calibrated_for_other_settings_is_calibrated_again(tmp_path):
    """A threshold is on the scale of the scores of the matcher it was calibrated for:
    recognising with other settings (here a database calibrated before articulation and
    verification at several tolerances, as one learnt with an earlier version is) calibrates it again first and writes it, and
    the threshold is then the one a calibration from nothing with those settings gives."""
    db = _database(tmp_path / "db")  # calibrated with the defaults
    rigid = sqparts.MatchSettings(articulated=False, verification_levels=1)
    assert db.calibrated_for() and not db.calibrated_for(rigid)
    stale_threshold = db.calibrate(settings=rigid)
    stale = ModelDatabase(tmp_path / "db")
    assert stale.calibrated_for(rigid) and not stale.calibrated_for()
    reference = stale.without()  # the same views as read back, calibrated from nothing, in memory
    reference.path, reference.calibration = tmp_path / "nowhere", {}
    default = reference.calibrate()
    assert not (tmp_path / "nowhere").exists()
    s = sqparts.builtin_scene("chair")
    obs = _observed(s.parts, s.camera)
    recovery = SimpleNamespace(parts=s.parts, figure=obs.figures[0], depth=obs.depth, camera=s.camera)
    result = sqparts.recognize(database=stale, recovery=recovery)
    assert stale_threshold != pytest.approx(default, abs=1e-4)
    assert result.best == "chair" and result.threshold == pytest.approx(default, rel=1e-9)
    assert ModelDatabase(tmp_path / "db").calibrated_for()


def test_a_database_whose_model_files_changed_is_calibrated_again(tmp_path):
    """database.json records the model files it was calibrated on: one removed or edited
    by hand since makes the threshold stale (calibrated_for is False), and recognising
    calibrates it again to the threshold a calibration from nothing of the files as they
    now are gives."""
    _database(tmp_path / "db", names=("chair", "castings", "human"))
    assert ModelDatabase(tmp_path / "db").calibrated_for()
    (tmp_path / "db" / "castings.json").unlink()  # database.json still names it
    left = ModelDatabase(tmp_path / "db")
    assert left.names == ["chair", "human"] and not left.calibrated_for()
    reference = left.without()
    reference.path, reference.calibration = tmp_path / "nowhere", {}
    fresh = reference.calibrate()
    s = sqparts.builtin_scene("chair")
    obs = _observed(s.parts, s.camera)
    recovery = SimpleNamespace(parts=s.parts, figure=obs.figures[0], depth=obs.depth, camera=s.camera)
    result = sqparts.recognize(database=left, recovery=recovery)
    assert result.threshold == pytest.approx(fresh, abs=1e-5)
    assert set(left.calibration["objects"]) == {"chair", "human"}
    assert [v["object"] for v in left.calibration["views"]] == ["chair", "human"]
    assert all(set(v["scores"]) <= {"chair", "human"} for v in left.calibration["views"])
    assert ModelDatabase(tmp_path / "db").calibrated_for()
    edited = tmp_path / "db" / "chair.json"
    data = json.loads(edited.read_text())
    data["views"][0]["main"]["parts"][0]["size"][0] *= 1.5
    edited.write_text(json.dumps(data))
    assert not ModelDatabase(tmp_path / "db").calibrated_for()


def test_matching_on_threads_equals_matching_one_view_after_another(tmp_path, monkeypatch):
    """ModelDatabase.match runs the stored views on a thread each (SQPARTS_THREADS): the
    same scores, poses and articulations as one after another, whatever the threads."""
    db = _database(tmp_path / "db", names=("human", "chair"))
    s = sqparts.builtin_scene("human")
    obs = _observed(s.parts, s.camera)
    query = describe(s.parts)
    monkeypatch.setenv("SQPARTS_THREADS", "1")
    alone = db.match(query, observation=obs)
    monkeypatch.setenv("SQPARTS_THREADS", "2")
    again = db.match(query, observation=obs)
    assert [r[:4] for r in again] == [r[:4] for r in alone]
    for (*_, m, _), (*_, n, _) in zip(again, alone):
        np.testing.assert_array_equal(m.pose, n.pose)
        np.testing.assert_array_equal(m.pairs, n.pairs)
        assert (m.articulation is None) == (n.articulation is None)
        if m.articulation is not None:
            np.testing.assert_array_equal(m.articulation, n.articulation)
