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
SEE_THROUGH = box(15, 18, 38, 45)  # 3x7 whose centre shows a wall behind
SEEN = box(16, 17, 41, 42)
OCCLUDED = box(45, 48, 38, 45)  # 3x7 whose centre shows something in front
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


def rim_of(returns):
    """No-return pixels with a return among their 8 neighbours (explicit shifts)."""
    padded = np.pad(returns, 1)
    near = np.zeros_like(returns)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            near |= padded[1 + dy : 65 + dy, 1 + dx : 65 + dx]
    return near & ~returns


def test_constants_make_the_construction_unambiguous(plate):
    # The window is far wider than a dropout, the others no wider than one.
    assert 8 > DROPOUT_WIDTH >= 3
    depth, figure = plate
    rim = rim_of(figure) & ~np.isfinite(depth)
    # Each 3x7 hole keeps four pixels off the rim (its middle row, but for its ends and
    # the return in its centre), the notch three (its middle column but for its foot).
    for hole, middle in ((SEE_THROUGH, SEEN), (OCCLUDED, NEAR)):
        assert int((hole & ~rim & ~middle).sum()) == 4
    assert int((NOTCH & ~rim).sum()) == 3


def expected_missing(policy, depth, figure):
    """From the construction: which holes each policy calls missing data, and, except
    under "free", the one-pixel rim of no-return pixels around the plate's returns."""
    if policy == "free":
        return np.zeros((64, 64), bool)
    rim = rim_of(figure) & ~np.isfinite(depth)
    holes = DROPOUT | SLIT | (OCCLUDED & ~NEAR)  # "auto": the narrow ones nothing shows through
    if policy == "missing":
        holes = holes | WINDOW | (SEE_THROUGH & ~SEEN)
    return holes | rim


@pytest.mark.parametrize("policy", ["auto", "missing", "free"])
def test_missing_returns_by_policy(plate, policy):
    depth, figure = plate
    got = missing_returns(depth, CAM, figure, holes=policy)
    np.testing.assert_array_equal(got, expected_missing(policy, depth, figure))
    assert not (got & NOTCH & ~rim_of(figure)).any()  # open to the outside: free under every policy


# A part covering the plate's square: commission on the free pixels it covers (by count
# from the construction) and on the wall pixel it stands in front of.
ALL_HOLES = 4 + 6 + 64 + (21 - 1) + (21 - 1) + 12
WINDOW_OFF_RIM = 36  # its 6x6 middle
COMMISSION = {
    "auto": WINDOW_OFF_RIM + 4 + 3 + 1,  # window, the see-through hole's middle, the notch's, the wall
    "missing": 3 + 1,  # the notch's middle column, the wall
    "free": ALL_HOLES + 1,
}


@pytest.mark.parametrize("policy", ["auto", "missing", "free"])
def test_a_part_over_free_space_pays_commission(plate, policy):
    """A part covering the whole plate, holes and notch included, pays commission on the
    free pixels it covers and where it stands in front of the wall, not on missing data
    nor where the twig hides it."""
    depth, figure = plate
    fig = figure | missing_returns(depth, CAM, figure, holes=policy)
    hit = box(8, 56, 8, 56)
    rendered = np.where(hit, 2.0, np.inf)
    got = sqparts.commission_mask(hit, rendered, depth.astype(np.float64), fig, 0.01)
    free = hit & ~np.isfinite(depth) & ~expected_missing(policy, depth, figure)
    assert int(got.sum()) == COMMISSION[policy] == int(free.sum()) + 1  # + the wall pixel
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
        sqparts.SceneSettings(holes="maybe")
    from sqparts.cli import build_parser

    args = build_parser().parse_args(["recover", "x.npy", "--out", "o", "--holes", "free"])
    assert args.holes == "free"


# --- thin parts ---------------------------------------------------------------------


def test_sigma_at_edges_is_half_a_footprint():
    """σ defaults to 4 quanta of 6-bit data, but never under half a pixel footprint: a
    flat figure's depth range says nothing about how well its rims can be matched."""
    flat = np.full(100, 20.0) + np.linspace(0.0, 0.24, 100)  # the gate's depth range
    plain = sqparts.encoding_for(flat)
    assert plain.sigma == pytest.approx(4 * 0.24 / 64)
    assert sqparts.encoding_for(flat, footprint=0.087).sigma == pytest.approx(0.0435)
    assert sqparts.encoding_for(flat, footprint=0.01).sigma == pytest.approx(plain.sigma)  # 4q is more
    assert sqparts.encoding_for(flat, sigma=0.005, footprint=0.087).sigma == 0.005  # given: as given
    cam = sqparts.ScannerCamera(64, 32, np.radians(0.25), np.radians(0.25), 31.5, 15.5)
    depth = np.full((32, 64), np.nan, np.float32)
    depth[10:12, 5:60] = 20.0 + np.linspace(0.0, 0.24, 55)
    data = prepare_data(depth, cam)
    assert data.encoding.sigma == pytest.approx(0.5 * 20.0 * np.radians(0.25), rel=0.01)


def prepare_data(depth, cam):
    from sqparts._data import prepare

    return prepare(depth, cam)


@pytest.mark.slow
def test_one_pixel_wide_bar():
    """A bar one pixel across and 40 long, receding in depth, seen against nothing:
    recovered by recover_scene's defaults as a part along its axis, of its length."""
    from sqparts._scenes import limb

    cam = sqparts.OrthographicCamera(64, 32, 0.01, 31.5, 16.0)  # row 16's centre on the axis
    start, end = np.array([-0.2, 0.0, 1.0]), np.array([0.2, 0.0, 1.25])
    truth = limb(start, end, 0.006, 0.006, (0.3, 0.3))  # 1.2 pixels across
    depth = np.asarray(sqparts.render_range_image(truth, cam))
    assert set(np.nonzero(np.isfinite(depth))[0]) == {16} and np.isfinite(depth).sum() >= 38
    rec = sqparts.recover_scene(depth, cam)
    # No lattice of a window sees the bar wherever it lies: it is pruned on a 2-lattice
    # through each region's centre.
    assert [(f.search.stride, f.search.centred) for f in rec.figures] == [(2, True)]
    assert rec.fraction_explained > 0.8
    sizes, rot = np.asarray(rec.parts.size), np.asarray(rec.parts.rotation())
    best = int(np.argmax([s["pixels"] for s in rec.part_stats]))
    axis = rot[best][:, int(np.argmax(sizes[best]))]
    true_axis = (end - start) / np.linalg.norm(end - start)
    in_image = lambda v: v[:2] / np.linalg.norm(v[:2])  # noqa: E731 (the axis as seen)
    assert np.degrees(np.arccos(min(1.0, abs(in_image(axis) @ in_image(true_axis))))) < 3.0
    seen_length = 2 * sizes[best].max() * np.linalg.norm(axis[:2])  # projected on the image
    assert seen_length == pytest.approx(0.4, rel=0.15)


@pytest.mark.parametrize("width, stride", [(1, 1), (2, 2), (3, 3), (5, 4)])
def test_pruning_stride_sees_every_member(width, stride):
    """A blob with a bar ``width`` pixels across and 30 long: the stride is the bar's
    width (at most 4), and a lattice of that stride has a pixel on the bar wherever it
    lies; a bar too short to pay for a part does not lower the stride."""
    from sqparts._preprocess import pruning_stride

    fig = box(20, 44, 4, 28)
    fig[30 : 30 + width, 28:58] = True
    assert pruning_stride(fig, least_pixels=20) == stride
    for r0 in range(stride):  # every offset of the lattice sees the bar
        for c0 in range(stride):
            assert fig[30 : 30 + width, 28:58][(r0 - 30) % stride :: stride, (c0 - 28) % stride :: stride].any()
    short = box(20, 44, 4, 28)
    short[30 : 30 + width, 28:31] = True  # 3 pixels long: fewer than a part needs
    assert pruning_stride(short, least_pixels=4 * width) == 4


@pytest.mark.parametrize("across, stride", [(2.2, 3), (3.7, 4)])
def test_pruning_stride_sees_a_slanted_bar_every_lattice_meets(across, stride):
    """A bar at 45° off a blob, ``across`` pixels wide: its pixels lie on 3 (or 5)
    diagonals, so row - column takes every residue modulo 3 (or 4) along it and every
    3-lattice (4-lattice) has points on it, though no 3 x 3 (4 x 4 for the wider)
    square fits inside it; the narrower one misses some offsets of a 4-lattice. Checked
    by brute force over every offset of the chosen lattice: points on the bar all along
    it."""
    from sqparts._preprocess import pruning_stride

    rows, cols = np.indices((64, 64))
    bar = (np.abs(rows - cols) <= across / np.sqrt(2.0)) & (rows >= 14) & (rows < 56)
    fig = box(4, 16, 4, 16) | bar
    assert pruning_stride(fig, least_pixels=20) == stride
    for r0 in range(stride):
        for c0 in range(stride):
            hit = bar & (rows % stride == r0) & (cols % stride == c0)
            along = np.unique(rows[hit])
            assert along.min() <= 14 + stride and along.max() >= 55 - stride and np.diff(along).max() <= stride


def test_pruning_stride_does_not_see_a_bar_through_the_background():
    """A bar one pixel across, parallel to a blob's edge two pixels away: the blob's
    pixels near it hold every residue of a 4-lattice, but most offsets of any lattice
    wider than 1 put no point on the bar itself."""
    from sqparts._preprocess import pruning_stride

    fig = box(10, 50, 10, 40)
    fig[10:50, 42] = True  # the gap: columns 40 and 41
    assert pruning_stride(fig, least_pixels=20) == 1
