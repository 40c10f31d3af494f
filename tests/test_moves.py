"""Refinement's loop over moves: the accept rule, the loop, and moves alone, each against
the encoding cost of the edited scene rendered from scratch or the scene's truth."""

import dataclasses
from typing import ClassVar

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_recover import CAM, SCENE, _render_one  # two parts side by side, 64 x 64

import sqparts
from sqparts._encoding import part_vectors
from sqparts._refine import _face_neighbours, _grown_edits, _stretched_over, _turned_twin

TRUTH = part_vectors(SCENE)
SHIFT = np.r_[0.02, 0.01, 0.0, np.zeros(11)].astype(np.float32)


@pytest.fixture(scope="module")
def image():
    depth = np.asarray(sqparts.render_range_image(SCENE, CAM))
    data = sqparts.prepare(depth, CAM)
    return data, sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))


def _cost(vectors, data, costs):
    return sqparts.encoding_cost(sqparts.Part.from_vector(vectors), data, costs)


def test_accept_keeps_the_best_edit_of_each_part_and_every_compatible_improvement(image):
    data, costs = image
    start = TRUTH + SHIFT
    cost = _cost(start, data, costs)
    half = TRUTH + SHIFT / 2
    edits = [
        sqparts.Edit((0,), half[0:1]),  # better, not best, for part 0
        sqparts.Edit((0,), TRUTH[0:1]),  # best for part 0
        sqparts.Edit((1,), TRUTH[1:2]),  # best for part 1
        sqparts.Edit((1,), (TRUTH[1] + 3 * SHIFT)[None]),  # worse for part 1
        sqparts.Edit((), TRUTH[0:1]),  # a duplicate: explains nothing new
        sqparts.Edit((0, 1), TRUTH[0:1]),  # part 1 lost
    ]
    vectors, final = sqparts.accept_edits(start, cost, edits, data, costs)
    np.testing.assert_array_equal(vectors, TRUTH)
    truth = _cost(TRUTH, data, costs)
    assert final.total == truth.total and np.array_equal(final.labels, truth.labels)
    # Nothing that lowers E: nothing changes.
    same, same_cost = sqparts.accept_edits(TRUTH, truth, edits[3:], data, costs)
    assert same is TRUTH and same_cost is truth


def test_accept_reindexes_edits_after_a_removal(image):
    # A stray third part is dropped first (the best edit); the edit of part 2's
    # neighbour, proposed with the old indices, then applies to the right part.
    data, costs = image
    stray = TRUTH[0] + np.r_[0.0, 0.15, 0.0, np.zeros(11)].astype(np.float32)
    start = np.stack([stray, TRUTH[0], TRUTH[1] + SHIFT])
    cost = _cost(start, data, costs)
    edits = [sqparts.Edit((0,)), sqparts.Edit((2,), TRUTH[1:2])]
    vectors, final = sqparts.accept_edits(start, cost, edits, data, costs)
    np.testing.assert_array_equal(vectors, TRUTH)
    assert final.total == _cost(TRUTH, data, costs).total


def test_drop_parts_alone_drops_the_stray_part(image):
    data, costs = image
    stray = TRUTH[0] + np.r_[0.0, 0.15, 0.0, np.zeros(11)].astype(np.float32)
    start = sqparts.Part.from_vector(np.concatenate([TRUTH, stray[None]]))
    parts, cost, history = sqparts.refine_moves(start, data, costs, [sqparts.DropParts()])
    np.testing.assert_array_equal(part_vectors(parts), TRUTH)
    assert [s for s, _ in history] == ["initial", "drop"] and history[-1][1] < history[0][1]
    assert cost.total == _cost(TRUTH, data, costs).total


def test_absorb_parts_alone_gives_a_cut_members_piece_back():
    # A bar the search cut in two (the bar shortened, its end a part of its own): dropping
    # the piece alone (DropParts) loses its pixels; dropping it while the bar grows over
    # them gives the bar back whole, the truth's E.
    bar = sqparts.Part(
        size=[0.04, 0.04, 0.15], squareness=[0.3, 1.0], position=[0.0, 0.0, 2.0], orientation=[0.0, np.pi / 2, 0.0]
    )
    data = sqparts.prepare(np.asarray(sqparts.render_range_image(bar, CAM)), CAM)
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    truth = part_vectors(bar)
    cut, piece = truth.copy(), truth.copy()
    cut[0, [0, 8]] = [-0.03, 0.12]  # from -0.15 to 0.09 along x
    piece[0, [0, 8]] = [0.12, 0.03]  # from 0.09 to 0.15
    start = sqparts.Part.from_vector(np.concatenate([cut, piece]))
    exact = _cost(truth, data, costs).total
    _, alone, _ = sqparts.refine_moves(start, data, costs, [sqparts.DropParts()])
    assert alone.total > exact + 100
    parts, cost, history = sqparts.refine_moves(start, data, costs, [sqparts.AbsorbParts()])
    assert [s for s, _ in history] == ["initial", "absorb"] and len(parts.size) == 1
    assert cost.total == pytest.approx(exact, abs=1.0)
    np.testing.assert_allclose(part_vectors(parts)[0, [0, 8]], [0.0, 0.15], atol=0.003)


def test_absorb_parts_gives_an_ls_corner_piece_back_at_the_round_that_pays():
    # An L of two bars seen from above and aside (orthographic, 120 x 80) as the search and
    # refinement left it before: the upright bar cut above the corner, the corner a part
    # of its own, the other bar short of it. Absorbing the corner piece pays after one
    # round of growing; more rounds grow both bars into the corner and cost more than the
    # three parts. The accept rule picks the round: two parts, near the truth's E.
    camera = sqparts.OrthographicCamera(width=120, height=80, pixel_size=0.18 / 19, cx=59.5, cy=39.5)
    rot = [[0.5125, -0.8587, 0.0], [-0.2710, -0.1618, -0.9489], [0.8148, 0.4863, -0.3156]]
    upright = sqparts.Part(
        size=[0.04, 0.04, 0.2],
        squareness=[0.2, 0.2],
        position=[0.0, -0.1518, 0.9495],
        orientation=Rotation.from_matrix(rot).as_rotvec(),
    )
    across = sqparts.Part(
        size=[0.16, 0.04, 0.04],
        squareness=[0.2, 0.2],
        position=[0.0615, -0.0325, 1.0978],
        orientation=Rotation.from_matrix(np.array(rot) @ [[1, 0, 0], [0, 0, -1], [0, 1, 0]]).as_rotvec(),
    )
    truth = np.concatenate([part_vectors(upright), part_vectors(across)])
    depth = np.asarray(sqparts.render_range_image(sqparts.Part.from_vector(truth), camera))
    returns = np.isfinite(depth)
    data = sqparts.prepare(depth, camera, figure=returns | sqparts.missing_returns(depth, camera, returns))
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    start = np.array(  # across, upright cut above the corner, the corner
        [
            [0.073, -0.038, 1.116, -1.708, -1.868, 0.206, 0.041, 0.041, 0.164, 0.366, 0.233, -0.003, -0.048, 0.014],
            [-0.002, -0.207, 0.94, -0.219, 1.706, 2.384, 0.059, 0.062, 0.145, 0.264, 1.751, 0.001, -0.168, 0.015],
            [0.007, -0.048, 0.995, -1.15, 0.245, 0.395, 0.04, 0.053, 0.091, 0.29, 0.248, 0.016, 0.021, 0.112],
        ],
        np.float32,
    )
    exact = _cost(truth, data, costs).total
    three = _cost(start, data, costs)
    assert len(np.unique(three.labels[three.labels >= 0])) == 3 and three.total > exact + 40
    parts, cost, _ = sqparts.refine_moves(sqparts.Part.from_vector(start), data, costs, [sqparts.AbsorbParts()])
    assert len(parts.size) == 2 and cost.total <= exact + 10 * costs.omission  # a few pixels short of it
    # The corner piece absorbed by both bars as they are, round by round: the last round
    # alone (all that was proposed before) costs more than the three parts.
    move = sqparts.AbsorbParts()
    trial = sqparts.Edit((2, 0, 1), start[:2])
    edits = _grown_edits(
        [trial], start, three, data, costs, rounds=move.rounds, steps=move.steps, grow=move.grow, every=True
    )
    totals = sqparts.edit_totals(three, edits, data, costs)
    assert len(edits) == move.rounds and totals.min() < three.total < totals[-1]


def test_merge_parts_refits_a_bent_seat_from_its_own_pixels():
    # A chair seen from above and aside (orthographic, 140 x 120), its seat (a thin
    # plate, nearly edge-on) as refinement left it before: bent, tapered and rounded,
    # with a rim of pixels beside it unexplained. Summarised from its pixels and those it
    # answers for, the seat comes back bent; from its explained pixels alone, flat, and
    # the chair at the truth's E.
    seat, back = [0.2807, -0.93841, -0.14363], [1.71501, -0.87756, 0.64458]
    truth = np.array(
        [
            [0.0, 0.0, 1.8, *seat, 0.2, 0.02, 0.2, 0.15, 0.15, 0, 0, 0],
            [-0.14599, -0.26051, 1.82869, *seat, 0.2, 0.22, 0.02, 0.15, 0.15, 0, 0, 0],
            [0.03843, 0.28091, 1.63934, *back, 0.02, 0.02, 0.2, 0.2, 0.2, 0, 0, 0],
            [0.23733, 0.19843, 1.90247, *back, 0.02, 0.02, 0.2, 0.2, 0.2, 0, 0, 0],
        ],
        np.float32,
    )
    camera = sqparts.OrthographicCamera(width=140, height=120, pixel_size=0.46 / 33, cx=69.5, cy=59.5)
    depth = np.asarray(sqparts.render_range_image(sqparts.Part.from_vector(truth), camera))
    returns = np.isfinite(depth)
    data = sqparts.prepare(depth, camera, figure=returns | sqparts.missing_returns(depth, camera, returns))
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    start = truth.copy()
    start[0] = [0.031, 0.01, 1.828, 0.193, 0.944, 0.176, 0.194, 0.038, 0.256, 0.457, 0.732, -0.146, -0.977, 0.512]
    exact, bent = _cost(truth, data, costs).total, _cost(start, data, costs)
    assert bent.total > exact + 100
    move = sqparts.MergeParts(passes=1, alone=True)
    parts, cost, _ = sqparts.refine_moves(sqparts.Part.from_vector(start), data, costs, [move])
    assert len(parts.size) == 4 and cost.total <= exact + 4 * costs.omission
    out = part_vectors(parts)[0]
    np.testing.assert_allclose(out[:3], truth[0, :3], atol=2 * camera.pixel_size)
    assert abs(out[12]) < 0.2  # flat (it was bent by -0.98)
    # The starts from the seat's pixels with those it answers for (all that MergeParts
    # proposes without ``alone``): none as short.
    edits = [e for e in move.propose(start, bent, data, costs, 0)[0] if e.remove == (0,)]
    totals = sqparts.edit_totals(bent, edits, data, costs)
    assert len(edits) == 2 * 2 * 13  # as they are and fitted, from both sets of pixels
    assert totals[:13].min() > cost.total + 50 and totals[26:39].min() > cost.total + 50
    plain = sqparts.MergeParts(passes=1).propose(start, bent, data, costs, 0)[0]
    assert len([e for e in plain if e.remove == (0,)]) == 2 * 13


def test_stretched_over_moves_the_face_toward_the_points_to_the_farthest():
    # A bar along its own z, turned; points beyond its +z end (and some beside it): its
    # +z face moves out to the farthest point's z, its -z face stays.
    rot = Rotation.from_rotvec([0.3, -0.7, 0.2])
    bar = np.r_[0.1, -0.05, 2.0, rot.as_rotvec(), 0.03, 0.04, 0.2, 0.5, 0.5, 0, 0, 0].astype(np.float32)
    rng = np.random.default_rng(0)
    local = np.c_[rng.uniform(-0.03, 0.03, 50), rng.uniform(-0.04, 0.04, 50), rng.uniform(0.15, 0.31, 50)]
    out = _stretched_over(bar, bar[:3] + rot.apply(local))
    axis = rot.as_matrix()[:, 2]
    ends = lambda v: (np.dot(v[:3] - bar[:3], axis) - v[8], np.dot(v[:3] - bar[:3], axis) + v[8])  # noqa: E731
    np.testing.assert_allclose(ends(out), [-0.2, local[:, 2].max()], atol=1e-5)
    np.testing.assert_allclose(np.cross(out[:3] - bar[:3], axis), 0.0, atol=1e-6)  # moved along z only
    np.testing.assert_array_equal(np.delete(out, [0, 1, 2, 8]), np.delete(bar, [0, 1, 2, 8]))
    # No point beyond the face: the part as it was.
    np.testing.assert_array_equal(_stretched_over(bar, bar[:3] + rot.apply(local * [1, 1, 0.5])), bar)


def test_stretch_parts_alone_takes_a_part_to_the_pixels_it_stopped_short_of(image):
    # The two parts side by side; the one lying across the view (its long axis along the
    # image's y) is a third of its length, one face moved in and the other held, its
    # pixels beyond unexplained. Growing takes a few pixels a round; stretched over
    # them first, the part is whole.
    data, costs = image
    short = TRUTH.copy()
    axis = Rotation.from_rotvec(TRUTH[1, 3:6]).as_matrix()[:, 2]
    assert abs(axis[1]) > 0.99
    cut = TRUTH[1, 8] * 2 / 3
    short[1, 8] -= cut
    short[1, 0:3] -= cut * axis
    exact, start = _cost(TRUTH, data, costs).total, _cost(short, data, costs)
    assert start.total > exact + 200 * costs.omission
    _, grown, _ = sqparts.refine_moves(sqparts.Part.from_vector(short), data, costs, [sqparts.GrowParts(passes=3)])
    assert grown.total > exact + 20 * costs.omission
    parts, cost, history = sqparts.refine_moves(sqparts.Part.from_vector(short), data, costs, [sqparts.StretchParts()])
    assert [s for s, _ in history] == ["initial", "stretch"]
    assert cost.total <= exact + 4 * costs.omission
    np.testing.assert_allclose(part_vectors(parts)[0], TRUTH[0])  # the whole part is left alone


def test_straighten_parts_alone_takes_a_noisy_fits_bend_off():
    # A straight part seen with sensor noise, started bent as a least-squares fit can
    # leave it (bend and taper, the pose and size moved with them): refitted with bend
    # and taper held at zero, it comes back to the truth's pose and size, and E falls.
    truth = sqparts.Part(
        size=[0.05, 0.04, 0.1], squareness=[1.0, 1.0], position=[0.0, 0.0, 1.2], orientation=[0.3, -0.5, 0.4]
    )
    depth = np.asarray(sqparts.render_range_image(truth, CAM))
    depth = depth + np.random.default_rng(5).normal(0.0, 0.002, depth.shape).astype(np.float32)
    data = sqparts.prepare(depth, CAM)
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    bent = part_vectors(truth).copy()
    bent[0, [2, 8, 11, 12, 13]] = [1.19, 0.09, -0.1, -0.25, 0.05]  # 1 cm nearer, 10% shorter, bent, tapered
    start = _cost(bent, data, costs)
    parts, cost, history = sqparts.refine_moves(
        sqparts.Part.from_vector(bent), data, costs, [sqparts.StraightenParts()]
    )
    assert [s for s, _ in history] == ["initial", "straighten"] and cost.total < start.total
    out = part_vectors(parts)[0]
    np.testing.assert_array_equal(out[11:], 0.0)  # held at zero, not merely small
    np.testing.assert_allclose(out[:3], part_vectors(truth)[0, :3], atol=1.2 / CAM.fx)  # within a pixel
    np.testing.assert_allclose(out[6:9], [0.05, 0.04, 0.1], rtol=0.05)
    assert cost.total <= _cost(part_vectors(truth), data, costs).total + 8 * costs.omission
    # A straight part is not proposed again.
    again, same, _ = sqparts.refine_moves(parts, data, costs, [sqparts.StraightenParts()])
    assert same.total == cost.total and np.array_equal(part_vectors(again), part_vectors(parts))


@pytest.mark.parametrize("e2", [1.2, 1.6, 1.9])
def test_turned_twin_reaches_the_pinched_cross_sections_distances(e2):
    # Closed form: the cross-section (z = 0) of a part with squareness ε2 reaches a along
    # its axes and a * 2^((1 - ε2) / 2) along its diagonals; its twin, turned 45 degrees
    # with 2 - ε2, reaches the same points the other way round.
    from sqparts._part import inside_outside

    v = np.array([0.1, -0.05, 1.3, 0.4, -0.3, 0.7, 0.05, 0.05, 0.12, 0.6, e2, 0.0, 0.0, 0.0], np.float32)
    twin = _turned_twin(v)
    rot = Rotation.from_rotvec(v[3:6]).as_matrix()
    d = 0.05 * 2.0 ** ((1.0 - e2) / 2)
    local = [(0.05, 0, 0), (0, -0.05, 0), (d / np.sqrt(2), d / np.sqrt(2), 0), (-d / np.sqrt(2), d / np.sqrt(2), 0)]
    part = sqparts.Part.from_vector(twin)
    for q in local:
        assert float(inside_outside(part, v[0:3] + rot @ np.asarray(q, np.float32))) == pytest.approx(1.0, abs=2e-4)
    np.testing.assert_allclose(twin[[0, 1, 2, 8, 9]], v[[0, 1, 2, 8, 9]])  # the centre, length and profile stay
    np.testing.assert_allclose(twin[10], 2.0 - e2, rtol=1e-6)
    twin_rot = Rotation.from_rotvec(twin[3:6]).as_matrix()
    np.testing.assert_allclose(twin_rot[:, 2], rot[:, 2], atol=1e-6)  # turned about the part's own axis
    np.testing.assert_allclose(twin_rot[:, 0] @ rot[:, 0], np.cos(np.pi / 4), atol=1e-6)
    # Twice: the part itself turned 90 degrees (the same solid for a1 = a2).
    again = _turned_twin(twin)
    np.testing.assert_allclose(again[6:11], v[6:11], rtol=1e-5)


def test_unpinch_parts_takes_a_pinched_fit_of_a_box_to_the_box():
    # A rounded box seen with sensor noise, fitted as its pinched twin (a rhombus
    # cross-section turned 45 degrees, which a search grid's orientation about 45 degrees
    # off leads polishing to): settling alone stays far above the truth's E; its twin,
    # settled, is the box.
    truth = sqparts.Part(
        size=[0.05, 0.05, 0.07], squareness=[0.2, 0.2], position=[0.0, 0.0, 1.2], orientation=[0.6, 0.2, -0.3]
    )
    depth = np.asarray(sqparts.render_range_image(truth, CAM))
    depth = depth + np.random.default_rng(6).normal(0.0, 0.002, depth.shape).astype(np.float32)
    data = sqparts.prepare(depth, CAM)
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    pinched = _turned_twin(part_vectors(truth)[0])[None]
    assert pinched[0, 10] == pytest.approx(1.8)
    target = _cost(part_vectors(truth), data, costs).total
    settle = [sqparts.SettleParts(scale=s) for s in (1.0, 0.5, 0.25)]
    settled, cost, _ = sqparts.refine_moves(sqparts.Part.from_vector(pinched), data, costs, settle)
    assert cost.total > target + 20 * costs.omission
    parts, final, history = sqparts.refine_moves(settled, data, costs, [sqparts.UnpinchParts()])
    assert [s for s, _ in history] == ["initial", "unpinch"]
    assert final.total <= target + 4 * costs.omission
    out = part_vectors(parts)[0]
    assert out[10] < 0.5 and np.allclose(out[6:9], [0.05, 0.05, 0.07], rtol=0.1)
    # A part that is not pinched is not proposed.
    again, same, _ = sqparts.refine_moves(parts, data, costs, [sqparts.UnpinchParts()])
    assert same.total == final.total and np.array_equal(part_vectors(again), out[None])


def test_settling_moves_only_the_parts_it_is_given(image):
    data, costs = image
    start = TRUTH + SHIFT
    parts, cost, _ = sqparts.refine_moves(
        sqparts.Part.from_vector(start), data, costs, [sqparts.SettleParts(which=(1,))]
    )
    out = part_vectors(parts)
    np.testing.assert_array_equal(out[0], start[0])
    assert not np.array_equal(out[1], start[1]) and cost.total < _cost(start, data, costs).total


def test_polishing_moves_only_the_free_numbers():
    from sqparts._polish import RIGID, figure_points, polish_parts

    depth = np.asarray(sqparts.render_range_image(SCENE, CAM))
    data = sqparts.prepare(depth, CAM)
    pts, _ = figure_points(data)
    start = TRUTH + np.r_[0.004, -0.003, 0.01, np.zeros(8), 0.1, -0.1, 0.1].astype(np.float32)
    weights = np.ones((2, len(pts)), np.float32)
    no_rays = ((np.zeros((1, 3), np.float32), np.array([[0.0, 0.0, 1.0]], np.float32)), np.zeros((2, 1), np.float32))
    free = part_vectors(polish_parts(sqparts.Part.from_vector(start), pts, weights, 20, *no_rays))  # all: default
    rigid = part_vectors(polish_parts(sqparts.Part.from_vector(start), pts, weights, 20, *no_rays, RIGID))
    assert np.abs(free[:, 11:] - start[:, 11:]).max() > 1e-3  # free: the deformations move
    np.testing.assert_allclose(rigid[:, 11:], start[:, 11:], atol=1e-6)  # held: they stay
    assert np.abs(rigid[:, :3] - start[:, :3]).max() > 1e-4  # while the pose moves


def test_grow_parts_alone_pulls_shifted_parts_back(image):
    data, costs = image
    start = TRUTH + SHIFT / 4
    parts, cost, history = sqparts.refine_moves(
        sqparts.Part.from_vector(start), data, costs, [sqparts.GrowParts(passes=3)]
    )
    assert [s for s, _ in history][:2] == ["initial", "polish 1"]
    assert cost.total < history[0][1]
    moved = np.abs(part_vectors(parts)[:, :3] - TRUTH[:, :3]).max()
    assert moved < 0.1 * np.abs(SHIFT[:3]).max() / 4  # from 5 mm off to within 0.5 mm
    # The pass that keeps nothing ends the move: 2 of the 3 passes asked for.
    assert [s for s, _ in history] == ["initial", "polish 1", "polish 2"]


@dataclasses.dataclass(frozen=True, kw_only=True)
class _Alternatives(sqparts.Move):
    """Two alternative batches: part 1 replaced by the truth, or by a shifted copy."""

    name: ClassVar[str] = "alternatives"

    def propose(self, vectors, cost, data, costs, step):
        return [[sqparts.Edit((1,), (TRUTH[1] + SHIFT)[None])], [sqparts.Edit((1,), TRUTH[1:2])]]


@dataclasses.dataclass(frozen=True, kw_only=True)
class _Count(sqparts.Move):
    """Records each pass it is asked for; proposes nothing."""

    name: ClassVar[str] = "count"
    calls: list = dataclasses.field(default_factory=list)

    def propose(self, vectors, cost, data, costs, step):
        self.calls.append(len(vectors))
        return [[]]


def test_the_loop_finishes_each_alternative_and_keeps_the_shorter(image):
    data, costs = image
    start = TRUTH + np.stack([np.zeros(14, np.float32), 2 * SHIFT])
    count = _Count(passes=5)
    parts, cost, history = sqparts.refine_moves(sqparts.Part.from_vector(start), data, costs, [_Alternatives(), count])
    np.testing.assert_array_equal(part_vectors(parts), TRUTH)
    assert cost.total == _cost(TRUTH, data, costs).total
    # Both ends were finished by the rest (one pass each: it keeps nothing).
    assert count.calls == [2, 2]
    assert [s for s, _ in history] == ["initial", "alternatives", "count"]


@dataclasses.dataclass(frozen=True, kw_only=True)
class _AlternativesThenCount(sqparts.Move):
    """Pass 1: the two alternatives of :class:`_Alternatives`; later passes: recorded,
    nothing proposed."""

    name: ClassVar[str] = "alternatives"
    calls: list = dataclasses.field(default_factory=list)

    def propose(self, vectors, cost, data, costs, step):
        self.calls.append(step)
        if len(self.calls) == 1:
            return _Alternatives().propose(vectors, cost, data, costs, step)
        return [[]]


def test_alternatives_are_finished_by_the_moves_own_passes_left(image):
    """A move of three passes whose first proposes alternatives: each alternative is
    finished by the move's second pass (which keeps nothing, ending the move), then the
    rest."""
    data, costs = image
    start = TRUTH + np.stack([np.zeros(14, np.float32), 2 * SHIFT])
    move, count = _AlternativesThenCount(passes=3), _Count(passes=5)
    parts, cost, history = sqparts.refine_moves(sqparts.Part.from_vector(start), data, costs, [move, count])
    np.testing.assert_array_equal(part_vectors(parts), TRUTH)
    assert move.calls == [0, 0, 0]  # the first pass, then one more in each of the two finishes
    assert count.calls == [2, 2]
    assert [s for s, _ in history] == ["initial", "alternatives", "alternatives", "count"]


@dataclasses.dataclass(frozen=True, kw_only=True)
class _AlternativesEveryPass(sqparts.Move):
    """Every pass: the two alternatives of :class:`_Alternatives` (recorded)."""

    name: ClassVar[str] = "alternatives"
    calls: list = dataclasses.field(default_factory=list)

    def propose(self, vectors, cost, data, costs, step):
        self.calls.append(step)
        return _Alternatives().propose(vectors, cost, data, costs, step)


def test_only_the_first_pass_with_alternatives_branches(image):
    """A move whose every pass proposes two alternatives: the first pass's two are
    finished, and within each finish a pass keeps its alternative of lowest E (the
    truth), so the rest runs twice, not once per path through the passes (2^passes)."""
    data, costs = image
    start = TRUTH + np.stack([np.zeros(14, np.float32), 2 * SHIFT])
    move, count = _AlternativesEveryPass(passes=4), _Count(passes=5)
    parts, _, _ = sqparts.refine_moves(sqparts.Part.from_vector(start), data, costs, [move, count])
    np.testing.assert_array_equal(part_vectors(parts), TRUTH)
    assert count.calls == [2, 2]
    # The shifted start's finish keeps the truth on its first pass and nothing on its
    # second; the truth's finish keeps nothing on its first.
    assert move.calls == [0, 0, 1, 0]


def test_on_gain_runs_its_moves_only_after_a_gain(image):
    data, costs = image
    stray = TRUTH[0] + np.r_[0.0, 0.15, 0.0, np.zeros(11)].astype(np.float32)
    after, never = _Count(), _Count()
    moves = [sqparts.OnGain(sqparts.DropParts(), then=(after,)), sqparts.OnGain(sqparts.DropParts(), then=(never,))]
    start = sqparts.Part.from_vector(np.concatenate([TRUTH, stray[None]]))
    _, _, history = sqparts.refine_moves(start, data, costs, moves)
    assert after.calls == [2] and never.calls == []
    assert [s for s, _ in history] == ["initial", "drop", "count after drop", "drop"]
    # Repeated: again after each gain, until the move no longer gains.
    again = _Count()
    _, _, history = sqparts.refine_moves(
        start, data, costs, [sqparts.OnGain(sqparts.DropParts(), then=(again,), repeat=5)]
    )
    assert again.calls == [2] and [s for s, _ in history] == ["initial", "drop", "count after drop", "drop"]


def test_move_settings_are_checked():
    with pytest.raises(ValueError, match=r"passes: got 0, expected an integer in \[1, 1000\]"):
        sqparts.GrowParts(passes=0)
    with pytest.raises(ValueError, match=r"repeat: got 0, expected an integer in \[1, 1000\]"):
        sqparts.OnGain(sqparts.DropParts(), repeat=0)
    moves = sqparts.RefineSettings(rounds=2, split=False, fill=True, merge=True).moves(search=None)
    assert [type(m).__name__ for m in moves] == (
        ["GrowParts", "DropParts", "OnGain", "StraightenParts"]
        + ["SettleParts"] * 3
        + ["OnGain"] * 3
        + ["SettleFaces"] * 3
        + ["OnGain"]
    )
    # Last of all: stretching, then settling and settling by faces again on a gain.
    assert type(moves[-1].move).__name__ == "StretchParts" and moves[-1].then == moves[4:7] + moves[10:13]
    assert sqparts.RefineSettings(faces=False).moves()[-1].then == moves[4:7]
    moves = moves[:-1]
    assert [m.scale for m in moves[-3:]] == [1.0, 0.5, 0.25]  # faces settled at each step scale
    assert [m.scale for m in sqparts.RefineSettings(settle=(2.0,), stretch=False).moves()[-1:]] == [2.0]
    moves = moves[:-3]
    # After settling: the pinched parts' twins, settled alone, then all settled again on a gain.
    unpinch = moves[7]
    assert type(unpinch.move).__name__ == "UnpinchParts" and unpinch.then == moves[4:7]
    assert unpinch.move.settle == (1.0, 0.5, 0.25) and unpinch.move.least == 1.5
    assert "UnpinchParts" not in [
        type(getattr(m, "move", m)).__name__ for m in sqparts.RefineSettings(unpinch=False).moves()
    ]
    assert "UnpinchParts" not in [
        type(getattr(m, "move", m)).__name__ for m in sqparts.RefineSettings(settle=()).moves()
    ]
    moves = moves[:7] + moves[8:]
    assert [m.scale for m in moves[-5:-2]] == [1.0, 0.5, 0.25]  # the steps halved, twice
    assert "StraightenParts" not in [type(m).__name__ for m in sqparts.RefineSettings(straighten=False).moves()]
    assert type(moves[-2].move).__name__ == "AbsorbParts" and moves[-2].then == moves[-5:-2]  # settled again
    # Merging once more: the settled parts grown, dropped, straightened and settled again
    # on a gain.
    merges = [m for m in moves if isinstance(m, sqparts.OnGain) and type(m.move).__name__ == "MergeParts"]
    assert merges == [moves[2], moves[-1]] and moves[2].then == moves[-1].then[:2]
    assert moves[-1].repeat == 1 and moves[-1].then[2:] == (moves[3], *moves[-5:-2])
    assert moves[-1].move.alone and not moves[2].move.alone  # the single parts' own pixels: once settled
    assert moves[-1].move.disc and not moves[2].move.disc  # discs among the starts: once settled
    assert [type(m).__name__ for m in moves[-1].then[:3]] == ["GrowParts", "DropParts", "StraightenParts"]
    plain = [m for m in sqparts.RefineSettings(straighten=False).moves() if getattr(m, "move", None) == merges[1].move]
    assert [type(m).__name__ for m in plain[0].then] == ["GrowParts", "DropParts"] + ["SettleParts"] * 3
    no_merge = sqparts.RefineSettings(merge=False, faces=False, stretch=False).moves()
    assert type(no_merge[-1].move).__name__ == "AbsorbParts"
    assert not any(isinstance(m, sqparts.OnGain) and type(m.move).__name__ == "MergeParts" for m in no_merge)
    last = sqparts.RefineSettings(absorb=False, merge=False, faces=False, stretch=False, unpinch=False).moves()
    assert [type(m).__name__ for m in last][-1] == "SettleParts"
    scales = sqparts.RefineSettings(
        settle=[1, 0.5], absorb=False, merge=False, faces=False, stretch=False, unpinch=False
    ).moves()[-2:]
    assert [type(m).__name__ for m in scales] == ["SettleParts"] * 2 and [m.scale for m in scales] == [1.0, 0.5]
    with pytest.raises(ValueError, match=r"faces: got 1, expected True or False"):
        sqparts.RefineSettings(faces=1)
    with pytest.raises(ValueError, match=r"stretch: got 'no', expected True or False"):
        sqparts.RefineSettings(stretch="no")
    with pytest.raises(ValueError, match=r"unpinch: got None, expected True or False"):
        sqparts.RefineSettings(unpinch=None)
    with pytest.raises(ValueError, match=r"which: got \[0\], expected a tuple of part indices or None"):
        sqparts.SettleParts(which=[0])
    with pytest.raises(ValueError, match=r"which: got \(True,\), expected a tuple of part indices or None"):
        sqparts.SettleParts(which=(True,))
    assert sqparts.SettleParts(which=(np.int64(2),)).which == (2,)
    with pytest.raises(ValueError, match=r"least: got 2.5, expected a squareness in \[1, 2\)"):
        sqparts.UnpinchParts(least=2.5)
    with pytest.raises(ValueError, match=r"settle: got \(\), expected a non-empty tuple of step scales"):
        sqparts.UnpinchParts(settle=())
    assert dataclasses.replace(sqparts.RefineSettings.none(), stretch=True).active
    assert not sqparts.RefineSettings.none().active and sqparts.RefineSettings.none().settle == ()
    assert sqparts.RefineSettings(settle=[1, np.float32(0.5)]).settle == (1.0, 0.5)
    for bad in ((0.0,), (-1.0,), (float("inf"),), (6.0,), (True,), "1", 1.0, (1.0,) * 9):
        with pytest.raises(
            ValueError, match=r"settle: got .*, expected a tuple of at most 8 step scales in \(0, 5.0\]"
        ):
            sqparts.RefineSettings(settle=bad)
    for bad in (0, float("nan"), 6.0, True):
        with pytest.raises(ValueError, match=r"scale: got .*, expected a number in \(0, 5.0\]"):
            sqparts.SettleParts(scale=bad)


def _faces(vector):
    """The planes of a part's six faces (±a_k along its own axis k), as their signed
    offsets along that axis from the camera's origin, from the package's Rodrigues
    rotation."""
    axes = np.asarray(sqparts.rotation_matrix(vector[3:6]), np.float64)
    centre, size = np.asarray(vector[0:3], np.float64), np.asarray(vector[6:9], np.float64)
    return np.array([axes[:, k] @ centre + sign * size[k] for k in range(3) for sign in (1, -1)])


def test_face_neighbours_move_one_face_and_hold_the_rest():
    # Each of the 12 neighbours moves exactly one of the six face planes, by 10% of its
    # semi-axis times the scale (out or in), and changes nothing but size and centre.
    rng = np.random.default_rng(3)
    columns = [
        rng.normal(0, 0.2, (4, 3)) + [0, 0, 2],
        rng.normal(0, 1, (4, 3)),
        rng.uniform(0.02, 0.2, (4, 3)),
        rng.uniform(0.1, 1.5, (4, 2)),
        rng.uniform(-0.3, 0.3, (4, 3)),
    ]
    vectors = np.concatenate(columns, axis=1).astype(np.float32)
    for scale in (1.0, 0.5):
        out = _face_neighbours(vectors, scale)
        assert out.shape == (4, 12, 14)
        for v, trials in zip(vectors, out):
            before, moved = _faces(v), set()
            for t in trials:
                np.testing.assert_array_equal(t[3:6], v[3:6])
                np.testing.assert_array_equal(t[9:], v[9:])
                shift = _faces(t) - before
                (face,) = np.flatnonzero(np.abs(shift) > 1e-5)
                assert abs(shift[face]) == pytest.approx(0.1 * scale * v[6 + face // 2], rel=1e-3)
                moved.add((int(face), bool(shift[face] * (1 if face % 2 == 0 else -1) > 0)))
            assert moved == {(f, out_) for f in range(6) for out_ in (True, False)}  # each face out and in


def test_settle_faces_alone_takes_a_thickened_part_back():
    # A box whose face toward the camera along its thinnest axis was pushed out by 10%
    # of the semi-axis, the opposite face where it belongs: settling by faces brings E
    # most of the way back to the truth's and the faces back toward their places,
    # moving size and centre only. References: the known part, its faces and its E.
    truth = sqparts.Part(
        size=[0.1, 0.05, 0.12], squareness=[0.2, 0.2], position=[0.0, 0.0, 2.0], orientation=[0.5, -0.4, 0.2]
    )
    _, data, costs = _render_one(truth, CAM)
    v = np.asarray(truth.to_vector(), np.float32)
    axis = np.asarray(sqparts.rotation_matrix(v[3:6]))[:, 1]
    start = v.copy()
    start[7] *= 1.1
    start[0:3] -= 0.1 * v[7] * axis * np.sign(axis[2])  # the near face out, the far one held
    parts, cost, history = sqparts.refine_moves(
        sqparts.Part.from_vector(start[None]), data, costs, [sqparts.SettleFaces()]
    )
    got = np.asarray(parts.to_vector())[0]
    start_e, true_e = history[0][1], sqparts.encoding_cost(truth, data, costs).total
    assert true_e <= cost.total < true_e + 0.2 * (start_e - true_e)
    assert np.abs(_faces(got) - _faces(v)).max() < 0.5 * np.abs(_faces(start) - _faces(v)).max()
    np.testing.assert_array_equal(got[3:6], start[3:6])
    np.testing.assert_array_equal(got[9:], start[9:])
    assert history[1][0].startswith("settle faces")
    # One parameter at a time, the same start stops higher (1 896 bits against 1 684;
    # the truth's 1 668): a face moves with a semi-axis and the centre together.
    one_at_a_time = sqparts.refine_moves(sqparts.Part.from_vector(start[None]), data, costs, [sqparts.SettleParts()])
    assert cost.total < one_at_a_time[1].total
    assert sqparts.SettleFaces().propose(np.zeros((0, 14), np.float32), cost, data, costs, 0) == [[]]


def test_merge_parts_with_pieces_merges_across_the_pieces_alone():
    # A bar fitted as two halves, one in each piece of the figure (a tear between them):
    # merged into one part, shorter by about a part's bits. With both halves in one
    # piece there is nothing across a tear to merge: no edit at all.
    from sqparts._scenes import limb

    bar = limb([-0.15, 0.0, 2.0], [0.15, 0.0, 2.0], 0.03)
    depth = np.asarray(sqparts.render_range_image(bar, CAM))
    data = sqparts.prepare(depth, CAM)
    costs = sqparts.Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    halves = sqparts.stack_parts(
        [limb([-0.16, 0.0, 2.0], [0.0, 0.0, 2.0], 0.03), limb([0.0, 0.0, 2.0], [0.16, 0.0, 2.0], 0.03)]
    )
    before = _cost(part_vectors(halves), data, costs)
    columns = np.broadcast_to(np.arange(CAM.width) >= CAM.width // 2, depth.shape)
    pieces = np.where(np.isfinite(depth), columns.astype(int), -1)
    merged, cost, _ = sqparts.refine_moves(halves, data, costs, [sqparts.MergeParts(passes=1, tries=0, pieces=pieces)])
    assert len(merged.size) == 1 and cost.total < before.total - 0.5 * costs.part
    whole = _cost(part_vectors(bar), data, costs)
    assert cost.total <= whole.total + 0.05 * before.explained * costs.omission
    one_piece = np.where(np.isfinite(depth), 0, -1)
    move = sqparts.MergeParts(passes=1, tries=0, pieces=one_piece)
    assert not any(move.propose(part_vectors(halves), before, data, costs, 0)[0])
    with pytest.raises(ValueError, match=r"pieces: got shape \(8, 8\), expected the image's \(64, 64\)"):
        sqparts.MergeParts(pieces=np.zeros((8, 8), int)).propose(part_vectors(halves), before, data, costs, 0)
    with pytest.raises(ValueError, match=r"pieces: got an array of shape \(64, 64\) and dtype float64"):
        sqparts.MergeParts(pieces=np.zeros((64, 64)))
    # Without pieces the same halves are adjacent, and merging proposes their merge.
    assert any(
        e.remove == (0, 1)
        for e in sqparts.MergeParts(passes=1, tries=0).propose(part_vectors(halves), before, data, costs, 0)[0]
    )
