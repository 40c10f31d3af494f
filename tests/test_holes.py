"""The hole policy: which pixels without a return are free space and which are missing
data, against masks written down from the scene's construction."""

import numpy as np
import pytest

import sqparts
from sqparts._preprocess import DROPOUT_WIDTH, missing_returns

CAM = sqparts.OrthographicCamera(64, 64, 0.01, 31.5, 31.5)
PLATE = (slice(8, 56), slice(8, 56))  # a fronto-parallel plate 2 m away


def box(r0, r1, c0, c1):
    m = np.zeros((64, 64), bool)
    m[r0:r1, c0:c1] = True
    return m


# The plate's holes, by construction.
DROPOUT = box(15, 17, 15, 17)  # 2x2: a sensor dropout
SLIT = box(40, 41, 12, 18)  # 1x6: a crack, one footprint wide
WINDOW = box(30, 38, 30, 38)  # 8x8: an opening far wider than a dropout
SEE_THROUGH = box(15, 18, 40, 43)  # 3x3 whose centre shows a wall behind
SEEN = box(16, 17, 41, 42)
OCCLUDED = box(45, 48, 40, 43)  # 3x3 whose centre shows something in front
NEAR = box(46, 47, 41, 42)
NOTCH = box(8, 12, 25, 28)  # cut into the plate's edge: open to the outside


@pytest.fixture(scope="module")
def plate():
    depth = np.full((64, 64), np.nan, np.float32)
    depth[PLATE] = 2.0
    for hole in (DROPOUT, SLIT, WINDOW, SEE_THROUGH, OCCLUDED, NOTCH):
        depth[hole] = np.nan
    depth[SEEN] = 3.0  # a wall a metre behind, seen through the hole
    depth[NEAR] = 1.5  # a twig half a metre in front
    figure = depth == 2.0
    return depth, figure


def test_constants_make_the_construction_unambiguous():
    # The window is far wider than a dropout, the others no wider than one.
    assert 8 > DROPOUT_WIDTH >= 3


@pytest.mark.parametrize(
    "policy, expected",
    [
        ("auto", DROPOUT | SLIT | (OCCLUDED & ~NEAR)),
        ("missing", DROPOUT | SLIT | WINDOW | (SEE_THROUGH & ~SEEN) | (OCCLUDED & ~NEAR)),
        ("free", np.zeros((64, 64), bool)),
    ],
)
def test_missing_returns_by_policy(plate, policy, expected):
    depth, figure = plate
    got = missing_returns(depth, CAM, figure, holes=policy)
    np.testing.assert_array_equal(got, expected)
    assert not (got & NOTCH).any()  # open to the outside: free under every policy


@pytest.mark.parametrize("policy, commission", [("auto", 64 + 9 + 12), ("missing", 1 + 12), ("free", 103)])
def test_a_part_over_free_space_pays_commission(plate, policy, commission):
    """A part covering the whole plate, holes and notch included, pays commission on the
    free pixels it covers and where it stands in front of the wall, not on missing data
    nor where the twig hides it."""
    depth, figure = plate
    fig = figure | missing_returns(depth, CAM, figure, holes=policy)
    hit = box(8, 56, 8, 56)
    rendered = np.where(hit, 2.0, np.inf)
    got = sqparts.commission_mask(hit, rendered, depth.astype(np.float64), fig, 0.01)
    free = (DROPOUT | SLIT | WINDOW | (SEE_THROUGH & ~SEEN) | (OCCLUDED & ~NEAR) | NOTCH) & ~fig
    assert int(got.sum()) == commission == int(free.sum()) + 1  # + the wall pixel
    assert not got[NEAR].any() and got[SEEN].all()


def test_figure_ground_keeps_only_missing_holes(plate):
    depth, figure = plate
    for policy in ("auto", "missing", "free"):
        fg = sqparts.figure_ground(depth, CAM, planes=0, holes=policy)
        main = fg.figures[0]
        np.testing.assert_array_equal(main, figure | missing_returns(depth, CAM, figure, holes=policy))


def test_hole_policy_is_checked():
    depth = np.full((8, 8), 2.0, np.float32)
    cam = sqparts.OrthographicCamera(8, 8, 0.01, 3.5, 3.5)
    with pytest.raises(ValueError, match=r"holes: got 'maybe', expected one of 'auto', 'free', 'missing'"):
        missing_returns(depth, cam, np.isfinite(depth), holes="maybe")
    with pytest.raises(ValueError, match=r"holes: got 'maybe'"):
        sqparts.recover_scene(depth, cam, holes="maybe")
    from sqparts.cli import build_parser

    args = build_parser().parse_args(["recover", "x.npy", "--out", "o", "--holes", "free"])
    assert args.holes == "free"
