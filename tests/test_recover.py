import json
import warnings

import numpy as np
import pytest

import sqparts
from sqparts.cli import main

CAM = sqparts.PinholeCamera(64, 64, 280.0, 280.0, 31.5, 31.5)
SCENE = sqparts.stack_parts(
    [
        sqparts.Part(
            size=[0.06, 0.06, 0.2], squareness=[0.5, 1.0], position=[-0.08, 0.0, 2.0], orientation=[0.0, 0.0, 0.3]
        ),
        sqparts.Part(
            size=[0.05, 0.05, 0.16], squareness=[1.0, 1.0], position=[0.1, -0.02, 2.05], orientation=[1.57, 0.0, 0.0]
        ),
    ]
)


@pytest.fixture(scope="module")
def depth():
    return np.asarray(sqparts.render_range_image(SCENE, CAM))


@pytest.fixture(scope="module")
def recovery(depth):
    return sqparts.recover(depth, CAM, search=sqparts.SearchSettings(max_size=0.22))


def test_recover_two_parts(recovery, depth):
    fig = np.isfinite(depth)
    assert 2 <= len(recovery.parts) <= 3
    assert recovery.fraction_explained >= 0.75
    assert recovery.commission_fraction <= 0.1
    # E by direct count: rebuild it from the model's own rendering.
    data = sqparts.prepare(depth, CAM)
    costs = sqparts.Costs.from_encoding(data.encoding, int(fig.sum()))
    model = np.asarray(sqparts.render_range_image(recovery.parts, CAM))
    hit = np.isfinite(model)
    with np.errstate(invalid="ignore"):
        explained = hit & fig & (np.abs(model - depth) <= data.encoding.sigma / 2)
    direct = sqparts.description_length(explained[None], (hit & ~fig)[None], costs) + costs.part * (
        len(recovery.parts) - 1
    )
    assert recovery.description_length == pytest.approx(direct, abs=costs.omission * 3)


def test_refinement_lowers_the_encoding_cost(recovery):
    assert recovery.cost.total <= recovery.initial_cost.total
    stages = [e for _, e in recovery.history]
    assert all(b <= a + 1e-9 for a, b in zip(stages, stages[1:]))


def test_refine_drops_a_useless_part(depth):
    data = sqparts.prepare(depth, CAM)
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    useless = sqparts.Part(size=[0.02, 0.02, 0.02], position=[0.0, 0.25, 2.0])
    parts = sqparts.stack_parts([SCENE[0], SCENE[1], useless])
    refined, cost, history = sqparts.refine_parts(parts, data, costs, rounds=0, merge=False)
    assert len(refined) == 2 and cost.total < history[0][1]


def test_joint_polish_grows_a_part_onto_its_unexplained_pixels(depth):
    # Part 0 looks along the viewing ray; started 40% short, its front face lies 2.4 cm
    # behind the data, so it explains none of its own pixels. Joint refinement grows it
    # onto the unexplained pixels next to it, while background rays keep it inside the
    # silhouette. Reference: the truth's own labels.
    data = sqparts.prepare(depth, CAM)
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    _, truth = sqparts.render_range_image(SCENE, CAM, return_labels=True)
    own = np.asarray(truth) == 0
    p = SCENE[0]
    short = sqparts.Part(
        size=np.asarray(p.size) * [1.0, 1.0, 0.6],
        squareness=p.squareness,
        position=p.position,
        orientation=p.orientation,
    )
    parts = sqparts.stack_parts([short, SCENE[1]])
    before = sqparts.encoding_cost(parts, data, costs)
    refined, cost, _ = sqparts.refine_parts(parts, data, costs, rounds=2, merge=False)
    assert (before.explained_mask & own).sum() == 0
    assert len(refined) == 2 and (cost.explained_mask & own).sum() >= 0.95 * own.sum()
    assert cost.commission <= 0.02 * data.figure_mask.sum() and cost.total < before.total


def test_refinement_splits_a_part_that_spans_two():
    # A wide block above a narrow one, both facing the camera, started as one part
    # spanning both (like the human's torso with its pelvis). Without splitting,
    # refinement keeps one compromise part; with it, two parts explain far more of the
    # truth's own pixels at a lower E.
    cam = sqparts.PinholeCamera(64, 64, 280.0, 280.0, 31.5, 31.5)
    turn = [np.pi / 2, 0.0, 0.0]  # local z along the image's y axis
    scene = sqparts.stack_parts(
        [
            sqparts.Part(size=[0.07, 0.04, 0.12], squareness=[0.3, 0.3], position=[0.0, -0.09, 2.0], orientation=turn),
            sqparts.Part(size=[0.04, 0.04, 0.06], squareness=[0.3, 0.3], position=[0.0, 0.09, 2.0], orientation=turn),
        ]
    )
    depth, truth = (np.asarray(a) for a in sqparts.render_range_image(scene, cam, return_labels=True))
    # σ of 6-bit data (an eighth of a footprint here), not prepare's floor of half a
    # footprint: the wider window lets the compromise part explain more of both blocks.
    data = sqparts.prepare(depth, cam, encoding=sqparts.encoding_for(depth[np.isfinite(depth)]))
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    one = sqparts.stack_parts(
        [sqparts.Part(size=[0.06, 0.04, 0.18], squareness=[0.3, 0.3], position=[0.0, -0.06, 2.0], orientation=turn)]
    )
    kw = dict(rounds=2, merge=False, stretch=False)  # stretching alone takes the compromise part further
    kept, kept_cost, _ = sqparts.refine_parts(one, data, costs, split=False, **kw)
    split, split_cost, history = sqparts.refine_parts(one, data, costs, split=True, **kw)
    assert len(kept) == 1 and len(split) == 2 and dict(history)["split"] < dict(history)["polish 2"]
    explained = split_cost.explained_mask
    assert (explained & (truth == 0)).sum() >= 0.9 * (truth == 0).sum()
    assert explained.sum() >= 1.5 * kept_cost.explained_mask.sum()
    assert split_cost.total < kept_cost.total and split_cost.commission <= 0.02 * data.figure_mask.sum()


def test_edit_costs_match_rendering_the_edited_scene(depth, monkeypatch):
    # Every shape of edit (add one, add two, remove, replace in place, replace two by
    # one), all evaluated together, against rendering the edited scene from scratch.
    data = sqparts.prepare(depth, CAM)
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    vec = np.stack([np.asarray(SCENE[i].to_vector()) for i in range(len(SCENE))]).astype(np.float32)
    base = sqparts.encoding_cost(SCENE[:1], data, costs)
    moved = vec[1] + np.r_[0.03, np.zeros(13)].astype(np.float32)
    edits = [
        sqparts.Edit((), vec[1:2]),
        sqparts.Edit((), moved[None]),
        sqparts.Edit((), np.stack([vec[1], moved])),
        sqparts.Edit((0,), vec[1:2]),
    ]
    two = sqparts.encoding_cost(SCENE, data, costs)
    both = [sqparts.Edit((0,)), sqparts.Edit((1,), moved[None]), sqparts.Edit((0, 1), moved[None])]
    # Several replacements of one part (each put onto the others' nearest hit, composed once).
    lifted = vec[0] + np.r_[0.0, -0.02, 0.01, np.zeros(11)].astype(np.float32)
    both += [sqparts.Edit((1,), vec[1:2] * 1.01), sqparts.Edit((0,), lifted[None]), sqparts.Edit((0,), vec[1:2])]
    for start, start_vec, batch in ((base, vec[:1], edits), (two, vec, both)):
        for edit, cost in zip(batch, sqparts.edit_costs(start, batch, data, costs)):
            edited = edit.apply(start_vec, edit.add)
            full = sqparts.encoding_cost(sqparts.Part.from_vector(edited), data, costs)
            assert cost.total == full.total and cost.explained == full.explained and cost.commission == full.commission
            assert np.array_equal(cost.labels, full.labels)
        # The totals an accept rule ranks by (each edit's parts counted on the others'
        # nearest depth), the same E as the full evaluation, bit for bit.
        totals = sqparts.edit_totals(start, batch, data, costs)
        assert totals.tolist() == [c.total for c in sqparts.edit_costs(start, batch, data, costs)]
    # Counted only where the new parts show, a few edits per numpy call: a part out of
    # view among others that replace the same part, and a group none of whose parts shows.
    from sqparts import _encoding

    away = vec[1] + np.r_[50.0, np.zeros(13)].astype(np.float32)
    batch = both + [sqparts.Edit((1,), away[None]), sqparts.Edit((0, 1), away[None]), sqparts.Edit((), away[None])]
    want = [c.total for c in sqparts.edit_costs(two, batch, data, costs)]
    for pixels in (1, 2 * depth.size, _encoding.COUNT_PIXELS):
        monkeypatch.setattr(_encoding, "COUNT_PIXELS", pixels)
        assert sqparts.edit_totals(two, batch, data, costs).tolist() == want
    # Indices as a list or a numpy array are the same edit as their tuple (several parts
    # removed included: the removed set keys the composition shared by edits).
    for remove in ([0, 1], np.array([0, 1]), (np.int64(0), np.int64(1))):
        edit = sqparts.Edit(remove, list(moved))
        assert edit.remove == (0, 1) and edit.add.shape == (1, 14) and edit.add.dtype == np.float32
        (got,) = sqparts.edit_costs(two, [edit], data, costs)
        assert got.total == sqparts.edit_costs(two, [sqparts.Edit((0, 1), moved[None])], data, costs)[0].total
    for bad in ([0.5], [True], "01", None):
        with pytest.raises(ValueError, match=r"remove: got .*, expected a sequence of part indices \(integers\)"):
            sqparts.Edit(bad)
    with pytest.raises(ValueError, match=r"add: got shape \(2, 13\), expected \(k, 14\) part vectors"):
        sqparts.Edit((0,), np.zeros((2, 13)))
    # A one-for-one replacement keeps its place; otherwise the new parts follow the rest.
    assert np.array_equal(both[1].apply(vec, moved[None])[1], moved)
    assert np.array_equal(both[2].apply(vec, moved[None]), moved[None])
    assert np.array_equal(sqparts.Edit((0,), np.stack([moved, moved])).apply(vec, np.stack([moved, moved]))[0], vec[1])


def test_composing_one_layer_onto_the_rest_matches_a_brute_force_nearest_hit(depth):
    """Composition.adding (the rest's nearest hit composed once, one layer put on it)
    against a per-pixel loop: the nearest finite depth, ties to the earlier part, none
    where every layer misses; E from the same pixel counts."""
    from sqparts._encoding import Composition, layers_cost

    data = sqparts.prepare(depth, CAM)
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    rng = np.random.default_rng(3)
    h, w = depth.shape
    # Depths drawn from a few values near the data's, so that many pixels tie.
    values = np.nanmedian(depth) + np.array([-0.05, 0.0, 0.0, 0.02], np.float32)
    for m in (0, 1, 4):
        stack = np.where(rng.random((m + 2, h, w)) < 0.5, rng.choice(values, (m + 2, h, w)), np.inf).astype(np.float32)
        rest = Composition(stack[:m])
        for layer in stack[m:]:
            got = rest.adding(layer, data, costs)
            full = np.concatenate([stack[:m], layer[None]])
            want = np.full((h, w), -1)
            for r in range(h):
                for c in range(w):
                    column = full[:, r, c]
                    if np.isfinite(column).any():
                        want[r, c] = int(np.flatnonzero(column == column.min())[0])
            assert np.array_equal(got.labels, want)
            nearest = np.where(want >= 0, full.min(0), np.nan)
            assert np.array_equal(got.rendered, nearest, equal_nan=True)
            plain = layers_cost(full, data, costs)
            assert (got.total, got.explained, got.commission) == (plain.total, plain.explained, plain.commission)
            assert np.array_equal(got.layers, full)


def test_selection_on_the_joint_rendering_against_brute_force(depth):
    # Candidates: the two true parts and five swollen copies of one. The swollen copies
    # share most of their commission ring, which Eq. (7)'s pairwise area matrices credit
    # k(k-1)/2 times over, so the quadratic's optimum takes them all; the best-first
    # correction on the joint rendering must reach the brute-force optimum of E counted
    # pixel by pixel (numpy, every subset).
    from sqparts._encoding import render_layers

    data = sqparts.prepare(depth, CAM)
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    truth = np.asarray(SCENE.to_vector())
    swollen = [truth[0] * np.r_[1, 1, 1, 1, 1, 1, s, s, s, 1, 1, 1, 1, 1] for s in (1.3, 1.35, 1.4, 1.45, 1.5)]
    vectors = np.concatenate([truth, swollen]).astype(np.float32)
    layers = render_layers(vectors, CAM)
    fig = np.isfinite(depth)
    with np.errstate(invalid="ignore"):
        explained = np.isfinite(layers) & fig & (np.abs(layers - depth) <= data.encoding.sigma / 2)
    commission = np.isfinite(layers) & ~fig  # nothing off the figure: every pixel rendered there counts

    def joint(x):  # E of the chosen candidates rendered together, counted in numpy
        z = layers[x].min(0) if x.any() else np.full(depth.shape, np.inf)
        with np.errstate(invalid="ignore"):
            e = (np.isfinite(z) & fig & (np.abs(z - depth) <= data.encoding.sigma / 2)).sum()
        return costs.total(x.sum(), e, (np.isfinite(z) & ~fig).sum())

    subsets = [np.array([(k >> i) & 1 for i in range(len(vectors))], bool) for k in range(2 ** len(vectors))]
    brute = min(joint(x) for x in subsets)
    quadratic, _ = sqparts.select_exact(sqparts.SelectionProblem.from_masks(explained, commission, costs))
    assert joint(quadratic) > brute + costs.part  # the pairwise model is fooled here
    for start in (None, quadratic):
        chosen = sqparts.select_rendered(layers, data, costs, start=start)
        assert joint(chosen) == pytest.approx(brute)
    assert np.array_equal(sqparts.select_rendered(layers, data, costs, start=quadratic)[:2], [True, True])


def test_omitted_blobs_are_not_joined_by_slivers():
    from sqparts._refine import omitted_blobs

    mask = np.zeros((20, 30), bool)
    mask[2:8, 2:10] = True  # a lid
    mask[10:17, 18:27] = True  # a handle
    mask[7, 9:20] = True  # a one-pixel sliver along an outline joins them...
    mask[8:11, 19] = True
    mask[15, 0:3] = True  # ...and a sliver on its own
    labels, count = omitted_blobs(mask)
    assert count == 2
    assert set(np.unique(labels[2:8, 2:10])) == {labels[4, 4]} and set(np.unique(labels[10:17, 18:27])) == {
        labels[13, 22]
    }
    assert labels[4, 4] != labels[13, 22] and labels[4, 4] > 0 and labels[13, 22] > 0
    assert (labels[mask] > 0).sum() < mask.sum() and not labels[15, 0:3].any() and not labels[~mask].any()


def test_refinement_fills_a_gap_the_first_search_left():
    # A long block with a small knob at its lower end (a forearm and its hand): started
    # from the block alone, refinement only grows the block; searching the unexplained
    # blob again at its own scale adds the knob.
    cam = sqparts.PinholeCamera(64, 64, 280.0, 280.0, 31.5, 31.5)
    turn = [np.pi / 2, 0.0, 0.0]  # local z along the image's y axis
    scene = sqparts.stack_parts(
        [
            sqparts.Part(size=[0.05, 0.04, 0.12], squareness=[0.3, 0.3], position=[0.0, -0.03, 2.0], orientation=turn),
            sqparts.Part(size=[0.03, 0.03, 0.03], squareness=[1.0, 1.0], position=[0.0, 0.12, 1.99]),
        ]
    )
    depth, truth = (np.asarray(a) for a in sqparts.render_range_image(scene, cam, return_labels=True))
    data = sqparts.prepare(depth, cam)
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    settings = sqparts.make_settings(data, "fast", max_size=0.12)
    kw = dict(rounds=1, split=False, merge=False)
    alone, alone_cost, _ = sqparts.refine_parts(scene[:1], data, costs, **kw)
    filled, filled_cost, history = sqparts.refine_parts(scene[:1], data, costs, search=settings, **kw)
    knob = truth == 1
    assert len(alone) == 1 and (alone_cost.explained_mask & knob).sum() <= 0.3 * knob.sum()
    assert len(filled) == 2 and dict(history)["fill gaps"] < dict(history)["polish 1"]
    assert (filled_cost.explained_mask & knob).sum() >= 0.8 * knob.sum()
    assert filled_cost.commission <= 0.02 * data.figure_mask.sum()


def test_cli_round_trip(tmp_path, depth):
    np.save(tmp_path / "range.npy", depth)
    (tmp_path / "cam.json").write_text(json.dumps(CAM.to_json()))
    rc = main(
        [
            "recover",
            str(tmp_path / "range.npy"),
            "--camera",
            str(tmp_path / "cam.json"),
            "--out",
            str(tmp_path / "out"),
            "--max-size",
            "0.22",
            "--quiet",
        ]
    )
    assert rc == 0
    for name in ("parts.json", "model.ply", "report.png"):
        assert (tmp_path / "out" / name).stat().st_size > 100
    data = json.loads((tmp_path / "out" / "parts.json").read_text())
    assert {"description_length_bits", "timings_s", "settings", "fraction_explained"} <= set(data)
    assert all({"gamma", "bits_saved"} <= set(p) for p in data["parts"])
    # Re-render the recovered parts through the CLI and compare with the input.
    assert (
        main(
            [
                "render",
                str(tmp_path / "out" / "parts.json"),
                "--camera",
                str(tmp_path / "cam.json"),
                "--out",
                str(tmp_path / "again.npy"),
                "--quiet",
            ]
        )
        == 0
    )
    again = np.load(tmp_path / "again.npy")
    both = np.isfinite(again) & np.isfinite(depth)
    iou = both.sum() / (np.isfinite(again) | np.isfinite(depth)).sum()
    assert iou > 0.8
    assert np.median(np.abs(again[both] - depth[both])) < 0.02


def test_cli_recover_errors(tmp_path, capsys, depth):
    np.save(tmp_path / "range.npy", depth)
    assert main(["recover", str(tmp_path / "range.npy"), "--out", str(tmp_path / "o")]) == 2
    assert "which carries no camera, expected --camera CAM.json" in capsys.readouterr().err
    (tmp_path / "cam.json").write_text(json.dumps(sqparts.PinholeCamera(10, 10, 5, 5, 4.5, 4.5).to_json()))
    assert (
        main(
            [
                "recover",
                str(tmp_path / "range.npy"),
                "--camera",
                str(tmp_path / "cam.json"),
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 2
    )
    assert "got a 10x10 camera for" in capsys.readouterr().err
    assert main(["recover", str(tmp_path / "nothing.npy"), "--out", str(tmp_path / "o")]) == 2
    assert "input: got" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["recover", str(tmp_path / "empty"), "--out", str(tmp_path / "o")]) == 2
    assert "expected range images in it" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_builtin_scenes_render():
    for name in sqparts.BUILTIN_SCENES:
        s = sqparts.builtin_scene(name)
        d = np.asarray(sqparts.render_range_image(s.parts, s.camera))
        assert np.isfinite(d).mean() > 0.01 and len(s.part_names) == len(s.parts)
    with pytest.raises(ValueError, match=r"scene: got .*, expected one of"):
        sqparts.builtin_scene("car")


def test_joint_rendering_in_buckets_matches_one_pass():
    # Refinement renders 8 parts per compiled call and merges by depth; the human's 16
    # parts (two buckets, a forearm in front of the body) must match the one-pass renderer.
    from sqparts._encoding import render_labels

    s = sqparts.builtin_scene("human", resolution=48)
    depth, labels = (np.asarray(a) for a in sqparts.render_range_image(s.parts, s.camera, return_labels=True))
    got_depth, got_labels = render_labels(s.parts, s.camera)
    assert len(s.parts) > 8 and (labels >= 8).any()
    np.testing.assert_array_equal(got_labels, labels)
    np.testing.assert_allclose(got_depth, depth, atol=1e-5)


def _knob_scene():
    """A long block with a small knob at its lower end (a forearm and its hand)."""
    turn = [np.pi / 2, 0.0, 0.0]  # local z along the image's y axis
    return sqparts.stack_parts(
        [
            sqparts.Part(size=[0.05, 0.04, 0.12], squareness=[0.3, 0.3], position=[0.0, -0.03, 2.0], orientation=turn),
            sqparts.Part(size=[0.03, 0.03, 0.03], squareness=[1.0, 1.0], position=[0.0, 0.12, 1.99]),
        ]
    )


def test_settling_a_small_part_removes_its_commission():
    # The knob started 10% too large and a third of a pixel off: it hangs over the
    # silhouette by 14 pixels.
    # The pattern search on E itself brings it back to about the truth's own cost.
    # References: the truth rendered with the block, and full joint renderings.
    from sqparts._encoding import render_layers
    from sqparts._refine import settle_part

    cam = sqparts.PinholeCamera(64, 64, 280.0, 280.0, 31.5, 31.5)
    scene = _knob_scene()
    depth, truth = (np.asarray(a) for a in sqparts.render_range_image(scene, cam, return_labels=True))
    data = sqparts.prepare(depth, cam)
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    knob = np.asarray(scene[1].to_vector())
    start = knob + np.r_[0.0, 0.002, 0.0, 0, 0, 0, 0.003, 0.003, 0.003, np.zeros(5)]
    block = render_layers(np.asarray(scene[:1].to_vector()), cam)
    settled = settle_part(start, render_layers(start[None], cam)[0], block.min(0), data, costs)

    def cost(v):
        return sqparts.encoding_cost(sqparts.stack_parts([scene[0], sqparts.Part.from_vector(v)]), data, costs)

    before, after, ideal = cost(start), cost(settled), cost(knob)
    assert before.commission >= 5 and after.commission <= 1
    assert after.total < before.total and after.total <= ideal.total + 2 * costs.omission
    assert (after.explained_mask & (truth == 1)).sum() >= 0.9 * (truth == 1).sum()


def _render_one(part, cam):
    """One part's pixel labels (0 = the part), prepared data and costs."""
    depth, truth = (
        np.asarray(a) for a in sqparts.render_range_image(sqparts.stack_parts([part]), cam, return_labels=True)
    )
    data = sqparts.prepare(depth, cam)
    return truth, data, sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))


def test_coordinate_neighbours_step_one_parameter_each():
    # Every neighbour differs from its part in one parameter, by the step the docstring
    # gives (closed forms: a pixel along a camera axis, a 0.1 rad turn about the part's
    # own axis, 10% of a semi-axis, a factor 1.4 in squareness, 0.1 in bend and taper),
    # both ways, and stays in range (a squareness at its bound).
    from scipy.spatial.transform import Rotation

    from sqparts._refine import _coordinate_neighbours

    rng = np.random.default_rng(0)
    v = np.concatenate(
        [
            rng.normal(0, 0.1, (3, 3)) + [0, 0, 2],
            rng.normal(0, 1, (3, 3)),
            rng.uniform(0.05, 0.2, (3, 3)),
            [[0.1, 0.5], [1.0, 2.0], [0.3, 0.3]],
            rng.uniform(-0.5, 0.5, (3, 3)),
        ],
        axis=1,
    ).astype(np.float32)
    pixels = np.array([0.01, 0.02, 0.005])
    out = _coordinate_neighbours(v, pixels, 0.5)
    assert out.shape == (3, 28, 14)
    for i in range(3):
        changed = [np.flatnonzero(np.abs(t - v[i]) > 1e-6) for t in out[i]]
        for k in range(3):  # position
            np.testing.assert_allclose(
                out[i, 2 * k : 2 * k + 2, k] - v[i, k], [0.5 * pixels[i], -0.5 * pixels[i]], atol=1e-6
            )
        r = Rotation.from_rotvec(v[i, 3:6]).as_matrix()
        turned = [Rotation.from_rotvec(t[3:6]).as_matrix() for t in out[i, 6:12]]
        axes = [0, 1, 2, 0, 1, 2]
        for t, axis, sign in zip(turned, axes, [1, 1, 1, -1, -1, -1]):
            local = r.T @ t  # the turn in the part's own frame
            np.testing.assert_allclose(local[:, axis], np.eye(3)[axis], atol=1e-5)
            assert abs(np.arccos(np.clip((np.trace(local) - 1) / 2, -1, 1)) - 0.05) < 1e-4
            assert np.sign(Rotation.from_matrix(local).as_rotvec()[axis]) == sign
        np.testing.assert_allclose(out[i, 12:18, 6:9].max(0), v[i, 6:9] * 1.05, rtol=1e-6)
        np.testing.assert_allclose(out[i, 12:18, 6:9].min(0), v[i, 6:9] * 0.95, rtol=1e-6)
        for j, k in enumerate((9, 10)):
            want = np.clip(v[i, k] * np.array([1.2, 1 / 1.2]), 0.1, 2.0)
            np.testing.assert_allclose(out[i, 18 + 2 * j : 20 + 2 * j, k], want, rtol=1e-6)
        for j, k in enumerate((11, 12, 13)):
            np.testing.assert_allclose(out[i, 22 + 2 * j : 24 + 2 * j, k] - v[i, k], [0.05, -0.05], atol=1e-6)
        assert all(len(c) <= 3 for c in changed) and all(len(c) <= 1 for c in changed[:6] + changed[12:])
        assert all(set(c) <= {3, 4, 5} for c in changed[6:12])
    assert (out[..., 9:11] >= 0.1).all() and (out[..., 9:11] <= 2.0).all()


def test_settling_on_e_moves_a_part_toward_the_truth():
    # The paper's final optimisation (section 3.5): a known part started with its
    # squareness, size and bend off, on its own rendering: each pass keeps the step that
    # lowers E most, E comes 90% of the way down to the truth's own E (a coordinate
    # descent; 3 752 bits above it at the start), and the parameters set off come back
    # toward the truth's. References: the known part and its E on the same image.
    cam = sqparts.PinholeCamera(64, 64, 280.0, 280.0, 31.5, 31.5)
    truth = sqparts.Part(
        size=[0.06, 0.09, 0.12], squareness=[0.3, 0.3], position=[0.0, 0.0, 2.0], orientation=[0.4, -0.3, 0.2]
    )
    _, data, costs = _render_one(truth, cam)
    v = np.asarray(truth.to_vector(), np.float32)
    start = v.copy()
    start[7] *= 1.15
    start[9:11] = [0.1, 0.8]
    start[11] = 0.2
    moves = (sqparts.SettleParts(scale=1.0), sqparts.SettleParts(scale=0.5))
    parts, cost, history = sqparts.refine_moves(sqparts.Part.from_vector(start[None]), data, costs, moves)
    start_cost = history[0][1]
    true_cost = sqparts.encoding_cost(sqparts.Part.from_vector(v[None]), data, costs).total
    got = np.asarray(parts.to_vector())[0]
    assert true_cost <= cost.total < true_cost + 0.1 * (start_cost - true_cost)  # 90% of the way in E
    assert abs(got[7] - v[7]) < 0.5 * abs(start[7] - v[7]) and abs(got[11]) < 0.1
    assert np.abs(np.log(got[9:11] / v[9:11])).max() < 0.5 * np.abs(np.log(start[9:11] / v[9:11])).max()
    assert sqparts.SettleParts().propose(np.zeros((0, 14), np.float32), cost, data, costs, 0) == [[]]


def test_settling_with_halved_steps_lowers_e_below_the_full_steps():
    # A known part set off by less than the full steps (0.4 pixel across the image, 4%
    # in two semi-axes): once the full steps stop, the default's halved steps bring E
    # further down toward the truth's own E (2 344 bits at the start, 1 800 after the
    # full steps, 1 640 after the halved ones; the truth 1 184).
    cam = sqparts.PinholeCamera(64, 64, 280.0, 280.0, 31.5, 31.5)
    truth = sqparts.Part(
        size=[0.07, 0.09, 0.13], squareness=[0.5, 0.8], position=[0.0, 0.0, 2.0], orientation=[0.3, 0.2, -0.4]
    )
    _, data, costs = _render_one(truth, cam)
    start = np.asarray(truth.to_vector(), np.float32).copy()
    start[0:2] += 0.4 * 2.0 / 280.0
    start[6:8] *= [1.04, 0.96]

    def settled(scales):
        moves = [sqparts.SettleParts(scale=s) for s in scales]
        return sqparts.refine_moves(sqparts.Part.from_vector(start[None]), data, costs, moves)[1].total

    assert sqparts.RefineSettings().settle == (1.0, 0.5, 0.25)
    full_e, halved_e = settled((1.0,)), settled(sqparts.RefineSettings().settle)
    start_e = sqparts.encoding_cost(sqparts.Part.from_vector(start[None]), data, costs).total
    true_e = sqparts.encoding_cost(truth, data, costs).total
    assert true_e <= halved_e < full_e - 0.1 * (full_e - true_e) and full_e < start_e


def test_refinement_merges_two_halves_of_a_bent_part():
    # One limb bent in the image plane, started as two straight halves (the elbow's
    # two sides): merging replaces them by one bent part (section 4.1) at a lower E.
    # Reference: the truth's own pixels.
    from sqparts._part import rotation_vector
    from sqparts._scenes import limb

    cam = sqparts.PinholeCamera(64, 64, 280.0, 280.0, 31.5, 31.5)
    c, length, bend = np.array([0.0, -0.02, 2.0]), 0.15, 0.3
    rot = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # local z -> image x, local x -> image y
    truth_part = sqparts.Part(
        size=[0.035, 0.035, length], position=c, orientation=rotation_vector(rot), bend=[bend, 0.0]
    )
    truth, data, costs = _render_one(truth_part, cam)
    tips = [c + [-length, bend * length, 0.0], c + [length, bend * length, 0.0]]
    halves = sqparts.stack_parts([limb(tips[0], c, 0.035), limb(c, tips[1], 0.035)])
    kw = dict(rounds=1, split=False, absorb=False)  # merging alone (absorbing one half also gives one part)
    two, two_cost, _ = sqparts.refine_parts(halves, data, costs, merge=False, **kw)
    one, one_cost, history = sqparts.refine_parts(halves, data, costs, merge=True, **kw)
    assert len(two) == 2 and len(one) == 1 and one_cost.total < two_cost.total
    assert (one_cost.explained_mask & (truth == 0)).sum() >= 0.9 * (truth == 0).sum()
    assert one_cost.commission <= 0.02 * data.figure_mask.sum()
    assert abs(float(one.bend[0, 0])) >= 0.1


def test_refinement_summarises_a_plate_seen_as_patches():
    # A thin tilted plate (a laptop lid), started as four rounded patches, one per
    # quadrant: merging by moments replaces all four by one flat box-like part at a
    # lower E. References: the truth's own pixels, its normal and semi-axes.
    from scipy.spatial.transform import Rotation

    cam = sqparts.PinholeCamera(64, 64, 280.0, 280.0, 31.5, 31.5)
    rot = Rotation.from_euler("xy", [30, -20], degrees=True)
    centre = np.array([0.0, 0.0, 2.0])
    truth_part = sqparts.Part(
        size=[0.1, 0.004, 0.14], squareness=[0.1, 0.1], position=centre, orientation=rot.as_rotvec()
    )
    truth, data, costs = _render_one(truth_part, cam)
    m = rot.as_matrix()
    patches = sqparts.stack_parts(
        [
            sqparts.Part(
                size=[0.05, 0.02, 0.07], position=centre + m @ [sx * 0.05, 0.02, sz * 0.07], orientation=rot.as_rotvec()
            )
            for sx in (-1, 1)
            for sz in (-1, 1)
        ]
    )
    kw = dict(rounds=1, split=False, absorb=False, stretch=False)  # absorbing patches after stretching them: one too
    four, four_cost, _ = sqparts.refine_parts(patches, data, costs, merge=False, **kw)
    one, one_cost, _ = sqparts.refine_parts(patches, data, costs, merge=True, **kw)
    assert len(four) == 4 and len(one) == 1 and one_cost.total < four_cost.total
    assert (one_cost.explained_mask & (truth == 0)).sum() >= 0.95 * (truth == 0).sum()
    assert one_cost.commission <= 0.05 * data.figure_mask.sum()
    size = np.sort(np.asarray(one.size[0]))
    np.testing.assert_allclose(size[1:], [0.1, 0.14], rtol=0.1)
    thin = Rotation.from_rotvec(np.asarray(one.orientation[0])).as_matrix()[:, int(np.argmin(np.asarray(one.size[0])))]
    assert np.degrees(np.arccos(min(1.0, abs(thin @ m[:, 1])))) < 3.0


def test_refinement_summarises_a_plate_bent_through_itself_seen_as_strips():
    # A curved panel (a chair's back: thin, bent 0.3 through itself, the bend along the
    # view), started as three flat strips across its length: merging replaces them by
    # one part bent about the true axis by the true bend, at a lower E. References: the
    # truth's own pixels and its bend vector.
    from scipy.spatial.transform import Rotation

    cam = sqparts.PinholeCamera(64, 64, 280.0, 280.0, 31.5, 31.5)
    # local x (the bend) along the view, local z (the length) along the image's x, tilted.
    rot = Rotation.from_euler("x", 25, degrees=True) * Rotation.from_matrix(
        np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]).T
    )
    m, centre, bend = rot.as_matrix(), np.array([0.0, 0.0, 2.0]), 0.3
    truth_part = sqparts.Part(
        size=[0.008, 0.09, 0.14], squareness=[0.2, 0.2], position=centre, orientation=rot.as_rotvec(), bend=[bend, 0.0]
    )
    truth, data, costs = _render_one(truth_part, cam)
    strips = []
    for t in (-2 / 3, 0.0, 2 / 3):  # each strip flat, on the panel's surface at its third
        z = t * 0.14
        strips.append(
            sqparts.Part(
                size=[0.008, 0.09, 0.14 / 3],
                squareness=[0.2, 0.2],
                position=centre + m @ [bend * z * z / 0.14, 0.0, z],
                orientation=(rot * Rotation.from_euler("y", 2 * bend * z / 0.14)).as_rotvec(),
            )
        )
    kw = dict(rounds=1, split=False)
    three, three_cost, _ = sqparts.refine_parts(sqparts.stack_parts(strips), data, costs, merge=False, **kw)
    one, one_cost, _ = sqparts.refine_parts(sqparts.stack_parts(strips), data, costs, merge=True, **kw)
    assert len(one) == 1 and one_cost.total < three_cost.total
    assert (one_cost.explained_mask & (truth == 0)).sum() >= 0.9 * (truth == 0).sum()
    r = Rotation.from_rotvec(np.asarray(one.orientation[0])).as_matrix()
    long = int(np.argmax(np.asarray(one.size[0])))
    assert long == 2 and np.degrees(np.arccos(min(1.0, abs(r[:, 2] @ m[:, 2])))) < 8.0
    assert np.linalg.norm(float(one.bend[0, 0]) * r[:, 0] - bend * m[:, 0]) < 0.1


def test_recover_finds_a_bent_cylinder_as_one_bent_part():
    # A bent cylinder (round cross-section, flat ends, bend 0.3 in the image plane)
    # rendered from a known part and recovered by recover's defaults: one part whose
    # long axis and bend (the bend vector |b| x_bend, which the superquadric's
    # symmetries leave unchanged) match the truth's. Reference: the known part.
    from scipy.spatial.transform import Rotation

    from sqparts._part import rotation_vector

    rot = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # local z -> image x, local x -> image y
    truth = sqparts.Part(
        size=[0.04, 0.04, 0.16],
        squareness=[0.2, 1.0],
        position=[0.0, -0.03, 2.0],
        orientation=rotation_vector(Rotation.from_euler("y", 20, degrees=True).as_matrix() @ rot),  # tilted in depth
        bend=[0.3, 0.0],
    )
    m = Rotation.from_rotvec(np.asarray(truth.orientation)).as_matrix()
    depth = np.asarray(sqparts.render_range_image(truth, CAM))
    rec = sqparts.recover(depth, CAM, search=sqparts.SearchSettings(max_size=0.22))
    assert len(rec.parts) == 1
    part = rec.parts[0]
    r = Rotation.from_rotvec(np.asarray(part.orientation)).as_matrix()
    long = int(np.argmax(np.asarray(part.size)))
    assert long == 2  # the bend acts on the longest axis
    angle = np.degrees(np.arccos(min(1.0, abs(r[:, 2] @ m[:, 2]))))
    assert angle < 8.0
    b = float(part.bend[0])
    bend_vector, true_vector = b * r[:, 0], 0.3 * m[:, 0]
    assert np.linalg.norm(bend_vector - true_vector) < 0.08
    np.testing.assert_allclose(np.sort(np.asarray(part.size)), [0.04, 0.04, 0.16], rtol=0.15)
    assert rec.fraction_explained >= 0.95


def test_moments_give_a_visible_surfaces_bend_taper_and_rim_depth():
    # The front half of a bent, tapered cylinder (radius r (1 + t z/a3), centre line
    # x = b z²/a3, seen along +y) in the moment frame's columns (along, across, view):
    # closed forms for the bend, the taper and the half-depth behind the rim (r at z = 0).
    from sqparts._refine import _deformation_moments, _rim_depth

    rng = np.random.default_rng(0)
    a3, r, b, t = 0.2, 0.04, 0.25, 0.3
    z = rng.uniform(-a3, a3, 4000)
    theta = rng.uniform(-np.pi / 2, np.pi / 2, 4000)
    radius = r * (1 + t * z / a3)
    local = np.stack([z, b * z**2 / a3 + radius * np.sin(theta), -radius * np.cos(theta)], 1)
    offset, bend, taper = _deformation_moments(local, a3)
    np.testing.assert_allclose(bend, [b, 0.0], atol=0.01)
    assert abs(taper - t) < 0.03
    assert abs(offset[0]) < 0.002
    assert abs(_rim_depth(local, 0.001) - r) < 0.05 * r
    # An elliptical cross-section 1.5 times as deep as wide: the half-depth, not the width.
    oval = np.stack([z, 0.04 * np.sin(theta), -0.06 * np.cos(theta)], 1)
    assert abs(_rim_depth(oval, 0.001) - 0.06) < 0.003
    # A face at one depth (a plane seen by an orthographic camera): no slice says
    # anything, so the half-depth is σ/2 (numpy's fit failed on it: LinAlgError); a nearly
    # flat one: no numpy rank warning reaches the terminal (it did, even under --quiet).
    flat = np.stack([z, 0.04 * np.sin(theta), np.zeros_like(z)], 1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _rim_depth(flat, 0.001) == 0.0005
        flat[:, 2] = 1e-7 * np.round(rng.uniform(0, 1, len(z)))
        assert _rim_depth(flat, 0.001) >= 0.0005


@pytest.mark.parametrize("size", [(0.02, 0.22, 0.25), (0.02, 0.12, 0.25), (0.02, 0.25, 0.12)])
@pytest.mark.parametrize("bend", [0.3, -0.3])
def test_moments_give_a_plate_bent_through_itself(size, bend):
    # A plate bent through its thickness (a chair's back), its bend (local x) roughly
    # along the view, rendered and turned at random about it: the plate start of its
    # visible points' moments (a quadric fit's larger principal curvature) bends about
    # the true axis, by the true bend, with the true outline; a plate bent along its
    # shorter side (the last size) is found along that side.
    from scipy.spatial.transform import Rotation

    from sqparts._refine import _moment_candidates

    cam = sqparts.PinholeCamera(96, 96, 240.0, 240.0, 47.5, 47.5)
    rng = np.random.default_rng(int(100 * size[1] + 10 * bend))
    across_view = Rotation.from_matrix(np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]))
    turn = Rotation.from_euler("xyz", [rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(0.0, np.pi)])
    m = (turn * across_view).as_matrix()
    part = sqparts.Part(
        size=size,
        squareness=[0.2, 0.2],
        position=[0, 0, 2.0],
        orientation=Rotation.from_matrix(m).as_rotvec(),
        bend=[bend, 0.0],
    )
    depth = np.asarray(sqparts.render_range_image(part, cam))
    points = cam.points(depth).reshape(-1, 3)[np.isfinite(depth).reshape(-1)]
    start = _moment_candidates(points, 0.005)[-1]
    r = Rotation.from_rotvec(start[3:6]).as_matrix()
    assert np.degrees(np.arccos(min(1.0, abs(r[:, 2] @ m[:, 2])))) < 5.0
    assert np.linalg.norm(start[11] * r[:, 0] - bend * m[:, 0]) < 0.05
    np.testing.assert_allclose(start[7:9], size[1:], rtol=0.1)
    assert start[6] < 0.01  # thin along the view


@pytest.mark.parametrize("tilt", [35.0, 55.0, 70.0])
@pytest.mark.parametrize("size", [(0.08, 0.08, 0.03), (0.1, 0.07, 0.02)])
def test_moments_give_a_disc_on_its_least_axis(tilt, size):
    # A disc (a cylinder, round or elliptical, its thin axis local z) whose normal is
    # tilted ``tilt`` degrees from the view, turned at random about the view and
    # rendered: its visible top face and front rim give a start (the second last) whose
    # local z lies near the disc's normal (the rim band tilts the points' least axis
    # toward it: 5-16 degrees here, within fitting's reach, which the refinement test
    # below checks) and whose outline and thickness are the disc's.
    from scipy.spatial.transform import Rotation

    from sqparts._refine import _moment_candidates

    cam = sqparts.PinholeCamera(96, 96, 300.0, 300.0, 47.5, 47.5)
    rng = np.random.default_rng(int(tilt + 1000 * size[1]))
    face_camera = Rotation.from_euler("x", 180.0, degrees=True)  # local z toward the camera
    turn = Rotation.from_euler("z", rng.uniform(0.0, 360.0), degrees=True) * Rotation.from_euler(
        "x", tilt, degrees=True
    )
    m = (turn * face_camera).as_matrix()
    part = sqparts.Part(
        size=size, squareness=[0.3, 1.0], position=[0, 0, 1.5], orientation=Rotation.from_matrix(m).as_rotvec()
    )
    depth = np.asarray(sqparts.render_range_image(part, cam))
    points = cam.points(depth).reshape(-1, 3)[np.isfinite(depth).reshape(-1)]
    start = _moment_candidates(points, 0.002, disc=True)[-2]
    r = Rotation.from_rotvec(start[3:6]).as_matrix()
    assert np.degrees(np.arccos(min(1.0, abs(r[:, 2] @ m[:, 2])))) < 20.0
    np.testing.assert_allclose(start[6:8], size[:2], rtol=0.1)
    assert abs(start[8] - size[2]) < 0.35 * size[2]
    assert tuple(start[9:11]) == (0.5, 1.0)


def test_refinement_merges_a_disc_fitted_as_two_plates():
    # A disc (round, its rim rounded: ε = (0.5, 1)) tilted 60 degrees from the view,
    # started as two halves each described with local y as the disc's normal (a plate
    # whose round outline a superquadric cannot give about y): merging replaces them by
    # one part on the disc's normal, at the true part's E; without merging two stay.
    from scipy.spatial.transform import Rotation

    cam = sqparts.PinholeCamera(80, 80, 260.0, 260.0, 39.5, 39.5)
    turn = Rotation.from_euler("z", 25.0, degrees=True) * Rotation.from_euler("x", 60.0, degrees=True)
    m = (turn * Rotation.from_euler("x", 180.0, degrees=True)).as_matrix()
    truth = sqparts.Part(
        size=[0.08, 0.08, 0.03],
        squareness=[0.5, 1.0],
        position=[0, 0, 1.5],
        orientation=Rotation.from_matrix(m).as_rotvec(),
    )
    _, data, costs = _render_one(truth, cam)
    sideways = m @ np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # local y on the normal
    halves = sqparts.stack_parts(
        [
            sqparts.Part(
                size=[0.04, 0.03, 0.08],
                squareness=[1.0, 0.5],
                position=np.array([0.0, 0.0, 1.5]) + side * 0.04 * sideways[:, 0],
                orientation=Rotation.from_matrix(sideways).as_rotvec(),
            )
            for side in (-1.0, 1.0)
        ]
    )
    kw = dict(rounds=1, split=False, stretch=False)
    kept, kept_cost, _ = sqparts.refine_parts(halves, data, costs, merge=False, **kw)
    new, new_cost, _ = sqparts.refine_parts(halves, data, costs, merge=True, **kw)
    assert len(kept) == 2 and len(new) == 1
    true_cost = sqparts.encoding_cost(sqparts.stack_parts([truth]), data, costs).total
    assert new_cost.total <= true_cost + 1.0 < kept_cost.total
    r = Rotation.from_rotvec(np.asarray(new.orientation[0])).as_matrix()
    assert np.degrees(np.arccos(min(1.0, abs(r[:, 2] @ m[:, 2])))) < 3.0
    np.testing.assert_allclose(np.asarray(new.size[0]), [0.08, 0.08, 0.03], rtol=0.05)


def test_refinement_redescribes_a_straight_fit_of_a_bent_tapered_part():
    # A bent, tapered limb (bend 0.4, taper 0.3) started as one straight, untapered,
    # box-like part over its pixels: the merge stage's re-description of a single part
    # (moment starts bent and tapered as the pixels' centre line and width say) replaces
    # it by one part whose bend vector and taper match the truth's, at a lower E.
    from scipy.spatial.transform import Rotation

    from sqparts._part import rotation_vector

    cam = sqparts.PinholeCamera(64, 64, 280.0, 280.0, 31.5, 31.5)
    rot = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # local z -> image x, local x -> image y
    truth_part = sqparts.Part(
        size=[0.035, 0.035, 0.15],
        position=[0.0, -0.03, 2.0],
        orientation=rotation_vector(rot),
        bend=[0.4, 0.0],
        taper=0.3,
    )
    _, data, costs = _render_one(truth_part, cam)
    straight = sqparts.Part(
        size=[0.05, 0.035, 0.15], squareness=[0.3, 0.3], position=[0.0, 0.0, 2.0], orientation=rotation_vector(rot)
    )
    kw = dict(rounds=1, split=False, stretch=False)  # the merge's re-description alone
    kept, kept_cost, _ = sqparts.refine_parts(straight, data, costs, merge=False, **kw)
    new, new_cost, _ = sqparts.refine_parts(straight, data, costs, merge=True, **kw)
    assert len(new) == 1 and new_cost.total < kept_cost.total
    m = np.asarray(rot)
    r = Rotation.from_rotvec(np.asarray(new.orientation[0])).as_matrix()
    assert np.degrees(np.arccos(min(1.0, abs(r[:, 2] @ m[:, 2])))) < 8.0
    assert np.linalg.norm(float(new.bend[0, 0]) * r[:, 0] - 0.4 * m[:, 0]) < 0.1
    # The taper is odd along the axis: its sign follows the axis' direction.
    assert abs(float(new.taper[0]) * np.sign(r[:, 2] @ m[:, 2]) - 0.3) < 0.1


def test_thin_members_join_collinear_pieces_and_skip_slivers():
    # Pixels on a plane z = 2 (1 cm apart): a diagonal bar two pixels across, crossed
    # (and cut in three) by two explained horizontal rails, and a one-pixel sliver along
    # a rail's outline. The bar's three pieces are one member; the sliver is none.
    from sqparts._refine import thin_members

    h, w = 40, 80
    rows, cols = np.mgrid[0:h, 0:w]
    points = np.stack([cols * 0.01, rows * 0.01, np.full((h, w), 2.0)], -1)
    bar = np.abs(rows - (5 + 0.35 * cols)) < 1.0  # two pixels across, about 19 degrees
    bar &= (cols >= 2) & (cols <= 78)
    shown = np.zeros((h, w), bool)
    shown[14:17, :] = True  # the rails, explained
    shown[26:29, :] = True
    sliver = np.zeros((h, w), bool)
    sliver[13, 50:75] = True  # along the first rail's top
    omitted = (bar | sliver) & ~shown
    members = thin_members(omitted, shown, np.zeros((h, w), np.int64), points, reach=0.02)
    assert len(members) == 1
    assert np.array_equal(members[0], bar & ~shown & ~sliver | (members[0] & sliver))
    assert not (members[0] & sliver).any()
    # Pieces off the bar's line stay apart: the bar and a parallel one 8 pixels lower.
    other = np.abs(rows - (13 + 0.35 * cols)) < 1.0
    other &= (cols >= 40) & (cols <= 60) & ~shown
    two = thin_members((bar | other) & ~shown & ~(bar & other), shown, np.zeros((h, w), np.int64), points, reach=0.02)
    assert len(two) == 2 and {int(m.sum()) for m in two} == {
        int((bar & ~shown & ~other).sum()),
        int((other & ~bar).sum()),
    }


def _gate_without(drop):
    """The built-in gate (Figure 10: members two pixels across, nothing between them),
    its prepared data and costs, and its true parts without the indices ``drop``."""
    scene = sqparts.builtin_scene("gate")
    depth = np.asarray(sqparts.render_range_image(scene.parts, scene.camera))
    data = sqparts.prepare(depth, scene.camera)
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    keep = [i for i in range(len(scene.parts)) if i not in drop]
    return scene, data, costs, scene.parts[np.array(keep)]


def test_refinement_finds_a_thin_brace_across_the_rails():
    # Started from the gate's posts and rails, the brace (two pixels across, cut in
    # three by the rails it crosses, so no 3x3 neighbourhood fits in it) is found by the
    # gap search from its pixels' moments, along the true brace's direction.
    scene, data, costs, start = _gate_without([5])
    settings = sqparts.make_settings(data, "fast", max_size=1.2)
    parts, cost, history = sqparts.refine_parts(start, data, costs, rounds=0, split=False, merge=False, search=settings)
    assert len(parts) == 6 and dict(history)["fill gaps"] < dict(history)["initial"]
    true_axis = np.asarray(scene.parts.rotation())[5][:, 2]
    new_axis = np.asarray(parts.rotation())[5][:, 2]
    assert np.degrees(np.arccos(min(1.0, abs(float(true_axis @ new_axis))))) < 2.0
    _, labels = (np.asarray(a) for a in sqparts.render_range_image(scene.parts, scene.camera, return_labels=True))
    brace = labels == 5
    assert (cost.explained_mask & brace).sum() >= 0.9 * brace.sum()


def test_refinement_merges_the_halves_of_a_box_bar_between_its_neighbours():
    # The gate's top rail (a box: squareness 0.2) started as two overlapping halves, each
    # adjacent to a post and the brace, so no group of adjacent parts is the two alone:
    # the pair's own starts (a straight bar of the halves' squareness) merge them.
    from sqparts._refine import _merge_candidates
    from sqparts._scenes import limb

    scene, data, costs, start = _gate_without([2])
    w = float(scene.parts.size[2, 0])
    halves = [
        limb([-2.4, -0.8, 20.0], [0.3, -0.8, 20.0], w, w, (0.2, 0.2)),
        limb([-0.6, -0.8, 20.0], [2.4, -0.8, 20.0], w, w, (0.2, 0.2)),
    ]
    # Closed form: one start is the whole rail, end to end, straight, with its squareness.
    from sqparts._encoding import part_vectors

    starts = _merge_candidates(*part_vectors(sqparts.stack_parts(halves)))
    rail = part_vectors(scene.parts)[2]
    straight = [v for v in starts if np.allclose(v[9:11], 0.2) and not v[11:].any()]
    assert len(straight) == 1
    axis = np.asarray(sqparts.Part.from_vector(straight[0]).rotation())[:, 2]
    np.testing.assert_allclose(straight[0][[0, 1, 2, 8]], rail[[0, 1, 2, 8]], atol=0.05)
    assert abs(axis[0]) > 0.9999
    parts = sqparts.stack_parts([start[i] for i in range(len(start))] + halves)
    before = sqparts.encoding_cost(parts, data, costs)
    merged, cost, _ = sqparts.refine_moves(parts, data, costs, [sqparts.MergeParts()])
    assert len(merged) == 6 and cost.total < before.total - 0.5 * costs.part
    _, labels = (np.asarray(a) for a in sqparts.render_range_image(scene.parts, scene.camera, return_labels=True))
    pixels = labels == 2
    assert (cost.explained_mask & pixels).sum() >= 0.9 * (before.explained_mask & pixels).sum()


def test_a_scene_in_millimetres_recovers_as_in_metres():
    """The same image in other units (depth times 1 000, the same pinhole camera) came
    back as two round parts (437 bits against 270): polishing's prior, damping and
    tolerances are not scale-free, so it is posed in metre-like units. The reference is
    the truth: the parts in metres, scaled."""
    cam = sqparts.PinholeCamera(32, 32, 40.0, 40.0, 16.0, 16.0)
    truth = sqparts.Part(size=[0.3, 0.2, 0.4], squareness=[0.5, 1.0], position=[0, 0, 2.0], orientation=[0.3, 0.2, 0.1])
    depth = np.asarray(sqparts.render_range_image(truth, cam))
    for scale in (1.0, 1000.0, 0.01):
        rec = sqparts.recover(depth * scale, cam, refine=sqparts.RefineSettings.none())
        (got,) = rec.parts.to_vector().reshape(-1, 14)
        np.testing.assert_allclose(np.sort(got[6:9]) / scale, [0.2, 0.3, 0.4], rtol=0.06)
        np.testing.assert_allclose(got[0:3] / scale, [0, 0, 2.0], atol=0.03)
