"""Settings objects: presets, resolution on the data, validation, and what results record."""

import dataclasses
import json

import numpy as np
import pytest

import sqparts
from sqparts.cli import main

CAM = sqparts.PinholeCamera(48, 48, 180.0, 180.0, 23.5, 23.5)
PART = sqparts.Part(
    size=[0.05, 0.07, 0.11], squareness=[0.6, 1.0], position=[0.0, 0.0, 1.2], orientation=[0.3, 0.2, 0.0]
)
FAST = dict(search=sqparts.SearchSettings(max_size=0.14, window=40), refine=sqparts.RefineSettings(rounds=1))


@pytest.fixture(scope="module")
def depth():
    return np.asarray(sqparts.render_range_image(PART, CAM))


def test_presets_by_name_and_object():
    assert sqparts.search_preset("fast") is sqparts.SEARCH_PRESETS["fast"]
    # The tables are read-only: one assignment changed every later recovery's "fast".
    tables = (sqparts.SEARCH_PRESETS, sqparts.SCENE_PRESETS, sqparts.PRESETS, sqparts.BUILTIN_SCENES)
    for table in (*tables, sqparts.HUMAN_POSES):
        with pytest.raises(TypeError):
            table["fast"] = "garbage"  # type: ignore[index]
    own = sqparts.SearchSettings(grid="default", top_k=2)
    assert sqparts.search_preset(own) is own
    # A grid given by name is the preset Grid; the presets differ where their docs say.
    assert sqparts.SearchSettings(grid="coarse").grid == sqparts.grid_preset("coarse")
    fast, paper, region = (sqparts.SEARCH_PRESETS[k] for k in ("fast", "paper", "region"))
    assert fast.grid.size == 3168 and paper.grid.size == sqparts.grid_preset("default").size
    assert region.restarts > 0 == fast.restarts and region.polish_candidates > fast.polish_candidates
    assert sqparts.scene_preset("synthetic") == sqparts.SceneSettings(resolution=None, clean=False, figure_ground=False)
    with pytest.raises(ValueError, match=r"^search: got 'quick', expected a SearchSettings or one of"):
        sqparts.search_preset("quick")
    with pytest.raises(ValueError, match=r"^scene: got 3, expected"):
        sqparts.scene_preset(3)


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: sqparts.SearchSettings(top_k=0), "top_k: got 0"),
        (lambda: sqparts.SearchSettings(max_size=float("nan")), "max_size: got nan"),
        (lambda: sqparts.SearchSettings(window=-3), "window: got -3"),
        (lambda: sqparts.SearchSettings(region_method="random"), "region_method: got 'random'"),
        (lambda: sqparts.SearchSettings(grid="huge"), "grid: got 'huge'"),
        (lambda: sqparts.SearchSettings(lattices=(8, 0)), "lattices: got"),
        (lambda: sqparts.SearchSettings(lattices=8), "lattices: got 8"),
        (lambda: sqparts.SelectSettings(method="annealing"), "method: got 'annealing'"),
        (lambda: sqparts.RefineSettings(rounds=-1), "rounds: got -1"),
        (lambda: sqparts.RefineSettings(split="yes"), "split: got 'yes'"),
        (lambda: sqparts.SceneSettings(up=(0, 0, 0)), "up: got"),
        (lambda: sqparts.SceneSettings(depth_range=(2.0, 1.0)), "depth_range: got"),
        (lambda: sqparts.SceneSettings(resolution=-1), "resolution: got -1"),
        (lambda: sqparts.SceneSettings(max_angle=120.0), "max_angle: got 120.0"),
    ],
)
def test_bad_settings_are_refused_where_they_are_made(make, message):
    with pytest.raises(ValueError, match="^" + message):
        make()


def test_resolve_fills_scale_and_window_from_the_data(depth):
    data = sqparts.prepare(depth, CAM)
    resolved = sqparts.SEARCH_PRESETS["fast"].resolve(data)
    # Independent reference: a quarter of the figure's largest metric extent, from the
    # pinhole model by hand.
    v, u = np.nonzero(np.isfinite(depth))
    z = depth[v, u].astype(np.float64)
    pts = np.stack([(u - CAM.cx) / CAM.fx * z, (v - CAM.cy) / CAM.fy * z, z], -1)
    assert resolved.max_size == pytest.approx(np.ptp(pts, axis=0).max() / 4, rel=1e-4)
    pixel = float(np.median(z)) / CAM.fx
    assert resolved.window >= 2 * resolved.max_size / pixel  # covers the largest part's diameter
    kept = sqparts.SearchSettings(max_size=0.1, window=32).resolve(data)
    assert (kept.max_size, kept.window) == (0.1, 32)
    with pytest.raises(ValueError, match=r"^window: got 400, expected at most 128"):
        sqparts.SearchSettings(window=400).resolve(data)


def test_a_result_records_the_objects_it_ran_with(depth, tmp_path):
    rec = sqparts.recover(depth, CAM, select=sqparts.SelectSettings(method="best-first"), **FAST)
    # Resolved: the stride of a compact figure (no member thinner than 4 pixels) is 4.
    assert rec.search == dataclasses.replace(FAST["search"], stride=4) and rec.refine == FAST["refine"]
    assert rec.select.method == "best-first" and rec.selection_method == "best-first"
    with pytest.raises(dataclasses.FrozenInstanceError):
        rec.parts = rec.initial_parts  # type: ignore[misc]
    saved = rec.scene_dict()["settings"]
    assert saved["search"]["max_size"] == 0.14 and saved["search"]["window"] == 40
    as_json = lambda x: json.loads(json.dumps(x))  # noqa: E731 (tuples are JSON lists)
    assert saved["search"]["grid"] == as_json(dataclasses.asdict(sqparts.grid_preset("coarse")))
    assert saved["refine"] == as_json(dataclasses.asdict(FAST["refine"])) and saved["select"]["method"] == "best-first"
    assert as_json(saved) == saved  # JSON as it is


def test_no_refinement_returns_the_selection(depth):
    rec = sqparts.recover(depth, CAM, search=FAST["search"], refine=sqparts.RefineSettings.none())
    assert [s for s, _ in rec.history] == ["initial"]
    np.testing.assert_array_equal(rec.parts.to_vector(), rec.initial_parts.to_vector())
    assert rec.cost.total == pytest.approx(rec.initial_cost.total)


def test_wrong_kinds_of_settings_are_type_errors(depth, tmp_path):
    with pytest.raises(TypeError, match=r"^refine: got .*expected a sqparts.RefineSettings"):
        sqparts.recover(depth, CAM, refine={"rounds": 1})  # type: ignore[arg-type]
    np.save(tmp_path / "x.npy", depth)
    with pytest.raises(TypeError, match=r"^grid: got it as a setting, expected one of"):
        sqparts.recover_many([tmp_path / "x.npy"], out=tmp_path / "out", camera=CAM, grid="coarse")
    assert not (tmp_path / "out").exists()  # refused before any work


def test_the_command_line_builds_the_same_objects(depth, tmp_path):
    np.save(tmp_path / "x.npy", depth)
    (tmp_path / "cam.json").write_text(json.dumps(CAM.to_json()))
    argv = ["recover", str(tmp_path / "x.npy"), "--camera", str(tmp_path / "cam.json"), "--out", str(tmp_path / "o")]
    argv += ["--grid", "coarse", "--max-size", "0.14", "--refine-rounds", "1", "--selection", "exact", "--quiet"]
    argv += ["--resolution", "0", "--no-figure-ground"]
    assert main(argv) == 0
    settings = json.loads((tmp_path / "o" / "parts.json").read_text())["settings"]
    assert settings["scene"] == dataclasses.asdict(sqparts.SceneSettings(resolution=0, figure_ground=False))
    (figure,) = settings["figures"]
    assert figure["search"]["max_size"] == 0.14 and figure["refine"]["rounds"] == 1
    assert figure["select"]["method"] == "exact"
