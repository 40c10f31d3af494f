"""Sensor clean-up and figure/ground on synthetic scenes with known answers."""

import dataclasses

import numpy as np
import pytest
from scipy import ndimage

import sqparts
from sqparts._preprocess import auto_factor, downsample_mask
from sqparts._scenes import limb

CAM = sqparts.PinholeCamera(160, 120, 150.0, 150.0, 79.5, 59.5)
# A table seen from above at an angle: unit normal toward the camera, 1.2 m away.
TABLE_N = np.array([0.0, -np.cos(np.radians(40)), -np.sin(np.radians(40))])
TABLE_D = 1.2


def plane_depth(camera, normal, offset):
    """Closed-form z-depth of the plane n·x + offset = 0 along each pixel's ray."""
    o, d = (np.asarray(a, np.float64) for a in camera.rays())
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -(o @ normal + offset) / (d @ normal)
    return np.where(t > 0, t, np.nan)


def on_table(centre_2d, half_height, width):
    """A vertical part standing on the table (local z along the table normal; the camera
    is on the +n side, since n·0 + d > 0)."""
    up = TABLE_N
    e1 = np.array([1.0, 0.0, 0.0])
    e2 = np.cross(up, e1)
    middle = np.array([0.0, 0.0, TABLE_D / np.sin(np.radians(40))])  # the table at the image centre
    base = middle + centre_2d[0] * e1 + centre_2d[1] * e2
    return limb(base, base + 2 * half_height * up, width, width, (0.3, 1.0))


@pytest.fixture(scope="module")
def table_scene():
    parts = sqparts.stack_parts([on_table((-0.25, 0.05), 0.12, 0.07), on_table((0.2, -0.05), 0.09, 0.1)])
    depth_parts, labels = (np.asarray(a) for a in sqparts.render_range_image(parts, CAM, return_labels=True))
    table = plane_depth(CAM, TABLE_N, TABLE_D)
    depth = np.fmin(depth_parts, table)
    truth = [np.isfinite(depth_parts) & (labels == i) & (depth_parts <= table) for i in range(2)]
    return depth.astype(np.float32), truth


def test_plane_depth_reference_is_on_plane():
    d = plane_depth(CAM, TABLE_N, TABLE_D)
    pts = CAM.points(d)
    ok = np.isfinite(d)
    assert ok.mean() > 0.9
    np.testing.assert_allclose(pts[ok] @ TABLE_N + TABLE_D, 0, atol=1e-9)


def test_downsample_keeps_geometry():
    # The binned image seen through the binned camera lies on the same 3-D plane.
    d = plane_depth(CAM, TABLE_N, TABLE_D)
    for f in (2, 3, 4):
        small, cam = sqparts.downsample(d, CAM, f)
        assert small.shape == (CAM.height // f, CAM.width // f) == (cam.height, cam.width)
        pts = cam.points(small)
        ok = np.isfinite(small)
        assert ok.mean() > 0.9
        assert np.max(np.abs(pts[ok] @ TABLE_N + TABLE_D)) < 2e-4 * TABLE_D
    with pytest.raises(ValueError, match="factor"):
        sqparts.downsample(d, CAM, 0)
    assert auto_factor((480, 640), 160) == 4 and auto_factor((100, 120), 160) == 1
    assert auto_factor((4, 5000), 32) == 4  # a strip is binned by at most its shortest side (was 156: an error)
    m = np.zeros((4, 4), bool)
    m[:2, :2] = True
    m[2, 2] = True
    np.testing.assert_array_equal(downsample_mask(m, 2), [[True, False], [False, False]])


def test_downsample_does_not_widen_a_silhouette_against_nothing(rng):
    """A part against nothing (a render), binned 4x: the binned image's returns are the
    pixels the binned camera sees the part at (rendered at that camera: the reference),
    give or take its outline; keeping every block with any return widened the silhouette
    by half a binned pixel a side (a recovered box came back 15-20% too thick). Dropouts
    inside the part are not its outline, and a bar thinner than half a block stays. A
    sensor's image (its returns fill the frame) keeps every block with a return: its
    holes are mostly dropouts."""
    fine = sqparts.PinholeCamera(640, 480, 600.0, 600.0, 319.5, 239.5)
    part = sqparts.Part(size=[0.15, 0.08, 0.05], squareness=[0.3, 0.3], position=[0.0, 0.0, 1.0])
    depth = np.asarray(sqparts.render_range_image(part, fine))
    small, cam = sqparts.downsample(depth, fine, 4)
    seen = np.isfinite(np.asarray(sqparts.render_range_image(part, cam)))
    got = np.isfinite(small)
    outline = seen.sum() - ndimage.binary_erosion(seen).sum()
    assert (got & ~seen).sum() <= 0.25 * outline and (seen & ~got).sum() <= 0.25 * outline, (
        (got & ~seen).sum(),
        (seen & ~got).sum(),
        outline,
    )
    holes = np.where(rng.random(depth.shape) < 0.6, np.nan, depth)
    inner = ndimage.binary_erosion(seen, iterations=2)
    assert np.isfinite(sqparts.downsample(holes, fine, 4)[0])[inner].mean() > 0.98  # a block left empty loses its rim
    for cols in (slice(43, 45), slice(41, 43)):  # two pixels wide: a quarter of two blocks, or half of one
        bar = np.full((CAM.height, CAM.width), np.nan)
        bar[8:112, cols] = 1.0
        binned, _ = sqparts.downsample(bar, CAM, 4)
        assert set(np.isfinite(binned).sum(axis=1)[2:28].tolist()) <= {1, 2} and np.nanmax(np.abs(binned - 1.0)) == 0
    plane = plane_depth(CAM, TABLE_N, TABLE_D)
    rows, cols = np.mgrid[: CAM.height, : CAM.width]
    sensor = np.where((rows - 60.3) ** 2 + (cols - 80.5) ** 2 < 30**2, np.nan, plane)  # a round hole, not on blocks
    h, w = CAM.height // 4, CAM.width // 4
    anything = np.isfinite(sensor).reshape(h, 4, w, 4).any(axis=(1, 3))
    np.testing.assert_array_equal(np.isfinite(sqparts.downsample(sensor, CAM, 4)[0]), anything)


def test_downsample_other_cameras():
    for cam in (
        sqparts.OrthographicCamera(64, 48, 0.01, 31.5, 23.5),
        sqparts.ScannerCamera(64, 48, 0.004, 0.004, 31.5, 23.5),
    ):
        small = cam.downsampled(4)
        # The centre of binned pixel (i, j) looks along the mean ray of its 4x4 block.
        o, d = (np.asarray(a) for a in cam.rays())
        o2, d2 = (np.asarray(a) for a in small.rays())
        block_o = o.reshape(12, 4, 16, 4, 3).mean(axis=(1, 3))
        np.testing.assert_allclose(o2, block_o, atol=1e-6)
        block_d = d.reshape(12, 4, 16, 4, 3).mean(axis=(1, 3))
        block_d /= np.linalg.norm(block_d, axis=-1, keepdims=True)
        np.testing.assert_allclose(d2 / np.linalg.norm(d2, axis=-1, keepdims=True), block_d, atol=2e-5)


@pytest.mark.parametrize("step", [1, 2, 3])
def test_cropped_camera_has_the_rays_of_those_pixels(step):
    """A cropped, strided camera's rays are the original camera's at the same pixels
    (``image[row0 : row0 + rows : step, col0 : col0 + cols : step]``)."""
    for cam in (
        CAM,
        sqparts.OrthographicCamera(64, 48, 0.01, 31.5, 23.5),
        sqparts.ScannerCamera(64, 48, 0.004, 0.004, 31.5, 23.5),
    ):
        window = (5, 7, 31, 26)
        small = cam.cropped(window, step)
        o, d = (np.asarray(a) for a in cam.rays())
        o2, d2 = (np.asarray(a) for a in small.rays())
        crop = (slice(5, 36, step), slice(7, 33, step))
        assert o2.shape == o[crop].shape
        np.testing.assert_allclose(o2, o[crop], atol=1e-6)
        np.testing.assert_allclose(d2, d[crop], atol=1e-6)
    for bad in ((0, 0, 0, 4), (-1, 0, 4, 4), (0, 0, CAM.height + 1, 4)):
        with pytest.raises(ValueError, match="window"):
            CAM.cropped(bad)
    with pytest.raises(ValueError, match="step"):
        CAM.cropped((0, 0, 4, 4), 0)


def test_fit_plane_ransac(rng):
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    u = np.cross(n, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    ab = rng.uniform(-1, 1, (700, 2))
    inliers = -0.8 * n + ab[:, :1] * u + ab[:, 1:] * v + rng.normal(0, 0.002, (700, 1)) * n
    outliers = rng.uniform(-1, 1, (300, 3))
    plane, mask = sqparts.fit_plane(np.concatenate([inliers, outliers]), threshold=0.01)
    assert abs(abs(plane.normal @ n) - 1) < 1e-4
    assert plane.offset > 0 and abs(plane.offset - 0.8) < 2e-3
    assert mask[:700].mean() > 0.99
    # Outliers that happen to lie within the threshold are few.
    assert mask[700:].mean() < 0.05


def test_estimate_noise(rng):
    yy, xx = np.mgrid[:120, :160]
    for sd in (0.001, 0.004):
        d = 1.0 + 0.004 * xx + 0.002 * yy + rng.normal(0, sd, xx.shape)
        assert abs(sqparts.estimate_noise(d) / sd - 1) < 0.1


def test_figure_ground_plane_plus_parts(table_scene):
    depth, truth = table_scene
    fg = sqparts.figure_ground(depth, CAM)
    assert fg.ground is not None
    angle = np.degrees(np.arccos(min(1.0, fg.ground.normal @ TABLE_N)))
    assert angle < 0.5, angle
    assert abs(fg.ground.offset - TABLE_D) < 0.01
    np.testing.assert_allclose(fg.up, TABLE_N, atol=1e-2)
    assert len(fg.figures) == 2
    for mask in fg.figures:
        ious = [(mask & t).sum() / (mask | t).sum() for t in truth]
        assert max(ious) > 0.9, ious
    # No table pixel is figure.
    table_only = np.isfinite(depth) & ~truth[0] & ~truth[1]
    assert (fg.labels[table_only] >= 0).mean() < 0.005


def test_figure_ground_keeps_parts_with_scattered_dropouts(table_scene, rng):
    """A fifth of the pixels without a return, at random (a sensor's dropouts): the two
    parts on the table are still two figures with their returns. Removing every return
    outside a complete 2x2 block of returns (meant for the slivers a plane leaves along
    an object's base) broke them into pieces and dropped some."""
    depth, truth = table_scene
    holes = np.where(rng.random(depth.shape) < 0.2, np.nan, depth).astype(np.float32)
    fg = sqparts.figure_ground(holes, CAM)
    returns = np.isfinite(holes)
    assert len(fg.figures) == 2
    for mask in fg.figures:
        ious = [(mask & t & returns).sum() / ((mask | t) & returns).sum() for t in truth]
        assert max(ious) > 0.8, ious  # 0.83-0.93 over three draws of the holes


def test_figure_ground_room_corner():
    # Two parts on a table in the corner of two walls: each background plane meets the
    # image frame along one edge only (nearly a line), and all three are removed.
    e1 = np.array([1.0, 0.0, 0.0])
    e2 = np.cross(TABLE_N, e1)
    middle = np.array([0.0, 0.0, TABLE_D / np.sin(np.radians(40))])
    walls = []
    for normal, point in ((e2, middle + 0.3 * e2), (e1, middle + 0.38 * e1)):
        offset = -normal @ point  # the camera inside the room: on every plane's + side
        walls.append((normal, offset) if offset > 0 else (-normal, -offset))
    parts = sqparts.stack_parts([on_table((-0.2, 0.0), 0.12, 0.07), on_table((0.15, -0.1), 0.09, 0.1)])
    depth_parts, labels = (np.asarray(a) for a in sqparts.render_range_image(parts, CAM, return_labels=True))
    room = np.fmin.reduce([plane_depth(CAM, TABLE_N, TABLE_D)] + [plane_depth(CAM, n, d) for n, d in walls])
    depth = np.fmin(depth_parts, room).astype(np.float32)
    truth = [(labels == i) & (depth_parts <= room) for i in range(2)]
    fg = sqparts.figure_ground(depth, CAM)
    assert len(fg.planes) == 3
    for normal, offset in [(TABLE_N, TABLE_D)] + walls:
        found = [p for p in fg.planes if p.normal @ normal > np.cos(np.radians(1.0))]
        assert len(found) == 1 and abs(found[0].offset - offset) < 0.01, ([p.to_json() for p in fg.planes], normal)
    np.testing.assert_allclose(fg.up, TABLE_N, atol=1e-2)
    assert len(fg.figures) == 2
    for mask in fg.figures:
        ious = [(mask & t).sum() / (mask | t).sum() for t in truth]
        assert max(ious) > 0.9, ious


def test_figure_ground_drops_background_running_off_the_image():
    # A part in the middle, a large part cut by the left edge (10% of it on the frame) and
    # a scrap of a thin one at the right edge (over 40% on the frame): the scrap is dropped.
    parts = sqparts.stack_parts(
        [on_table((0.0, 0.05), 0.12, 0.07), on_table((-0.8, 0.0), 0.15, 0.16), on_table((0.95, 0.0), 0.1, 0.07)]
    )
    depth_parts, labels = (np.asarray(a) for a in sqparts.render_range_image(parts, CAM, return_labels=True))
    table = plane_depth(CAM, TABLE_N, TABLE_D)
    depth = np.fmin(depth_parts, table).astype(np.float32)
    truth = [(labels == i) & (depth_parts <= table) for i in range(3)]
    frame = np.zeros(depth.shape, bool)
    frame[:3], frame[-3:], frame[:, :3], frame[:, -3:] = True, True, True, True
    on_frame = [(t & frame).sum() / t.sum() for t in truth]
    assert on_frame[0] == 0 and 0.05 < on_frame[1] < 0.15 and on_frame[2] > 0.3, on_frame
    fg = sqparts.figure_ground(depth, CAM)
    assert len(fg.figures) == 2
    for mask, t in zip(fg.figures, truth[:2][::-1]):  # largest first: the cut part, the middle one
        assert (mask & t).sum() / (mask | t).sum() > 0.9
    kept = sqparts.figure_ground(depth, CAM, max_border_fraction=1.0)
    assert len(kept.figures) == 3 and (kept.figures[2] & truth[2]).sum() / (kept.figures[2] | truth[2]).sum() > 0.9
    with pytest.raises(ValueError, match=r"max_border_fraction: got 1.5, expected a number in \[0, 1\]"):
        sqparts.figure_ground(depth, CAM, max_border_fraction=1.5)


@pytest.mark.parametrize("turn", [0.0, 25.0])
def test_a_face_cut_by_the_image_edge_is_not_ground(turn):
    """A box's flat face running off the image's right edge, against nothing, beside a
    part in front of its plane and one behind it: the face is not a background plane
    (its object's other returns turn away behind it, and nothing stands on it), so all
    three parts are figures. It was taken for the ground: the box and the part behind it
    were dropped (turned) or no figure was left (face-on), with exit 0 in the first case."""
    box = sqparts.Part(
        size=[0.15, 0.08, 0.05],
        squareness=[0.3, 0.3],
        position=[0.38, 0.0, 1.0],
        orientation=[0.0, np.radians(turn), 0.0],
    )
    front = sqparts.Part(size=[0.05, 0.05, 0.08], position=[-0.15, 0.05, 0.7], orientation=[0.3, 0.5, 0.0])
    behind = sqparts.Part(size=[0.06, 0.04, 0.12], squareness=[0.5, 1.0], position=[-0.05, -0.15, 1.4])
    depth, labels = (
        np.asarray(a)
        for a in sqparts.render_range_image(sqparts.stack_parts([box, front, behind]), CAM, return_labels=True)
    )
    assert np.isfinite(depth[:, -1]).sum() >= 8  # the box runs off the image
    fg = sqparts.figure_ground(depth, CAM)
    assert fg.planes == () and len(fg.figures) == 3
    returns = [m & np.isfinite(depth) for m in fg.figures]  # a figure's mask also holds its rim's missing data
    for i in range(3):
        truth = (labels == i) & np.isfinite(depth)
        assert max((m & truth).sum() / (m | truth).sum() for m in returns) > 0.95


def test_figure_ground_without_ground_keeps_everything(table_scene):
    depth, truth = table_scene
    parts_only = np.where(truth[0] | truth[1], depth, np.nan)
    fg = sqparts.figure_ground(parts_only, CAM)
    assert fg.ground is None and fg.planes == ()
    assert len(fg.figures) == 2
    returns = np.isfinite(parts_only)
    assert sum(int((m & returns).sum()) for m in fg.figures) == int((truth[0] | truth[1]).sum())
    # Beyond its returns a figure holds only pixels without one on its one-pixel rim
    # (mixed pixels, missing data under the default hole policy).
    for m in fg.figures:
        grown = np.zeros_like(m)
        core = np.pad(m & returns, 1)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                grown |= core[1 + dy : core.shape[0] - 1 + dy, 1 + dx : core.shape[1] - 1 + dx]
        assert not (m & ~returns & ~grown).any()


def test_rubber_sheet_tears_only_at_jumps():
    # A steep but continuous surface (60 degrees) stays in one piece; a step splits it.
    cam = sqparts.OrthographicCamera(40, 30, 0.01, 19.5, 14.5)
    xx = np.arange(40)[None, :].repeat(30, 0)
    slope = 1.0 + np.tan(np.radians(60)) * 0.01 * xx
    assert np.unique(sqparts.torn_components(slope, cam)).tolist() == [0]
    step = slope + np.where(xx >= 25, 0.2, 0.0)
    lab = sqparts.torn_components(step, cam)
    assert np.unique(lab).tolist() == [0, 1]
    assert (lab[:, :25] == 0).all() and (lab[:, 25:] == 1).all()


def test_pieces_one_object_tore_are_joined_and_objects_stay_apart():
    # Against nothing (no planes), 1 cm pixels, tears at 8 cm. A body 30 cm square; a
    # handle 10 cm before its right side (torn off by the jump, but the jump is less
    # than the handle's own 12 cm); a small block 50 cm before its top edge (touching it
    # in the image, farther off than its 11 cm); a block beside it, touching nothing.
    cam = sqparts.OrthographicCamera(70, 50, 0.01, 34.5, 24.5)
    depth = np.full((50, 70), np.nan)
    depth[10:40, 10:40] = 2.0
    depth[20:26, 40:52] = 1.9
    depth[2:10, 15:23] = 1.5
    depth[30:45, 55:65] = 2.0
    torn = sqparts.torn_components(depth, cam)
    assert torn.max() == 3  # four pieces
    joined = sqparts.joined_pieces(torn, depth, cam)
    assert joined.max() == 2
    assert (joined[10:40, 10:40] == 0).all() and (joined[20:26, 40:52] == 0).all()  # the largest: body and handle
    assert (joined[30:45, 55:65] == 1).all() and (joined[2:10, 15:23] == 2).all()
    assert (joined[np.isnan(depth)] == -1).all()
    # The handle farther out (15 cm before the body: more than its size) stays apart.
    farther = np.where(np.isclose(depth, 1.9), 1.85, depth)
    assert sqparts.joined_pieces(sqparts.torn_components(farther, cam), farther, cam).max() == 3
    # Across a seam of pixels without a return (the flying pixels clean-up removes
    # along an occluding edge): two pixels wide, still touching; three, apart.
    for width, joined_up in ((2, True), (3, False)):
        seam = depth.copy()
        seam[20:26, 40 : 40 + width] = np.nan
        lab = sqparts.joined_pieces(sqparts.torn_components(seam, cam), seam, cam)
        assert bool(lab[22, 39] == lab[22, 45]) is joined_up, width
    # Pieces kept apart (background running off the image) are not joined.
    kept = sqparts.joined_pieces(torn, depth, cam, apart=[int(torn[22, 45])])
    assert kept[22, 45] != kept[22, 20]
    # figure_ground joins them when asked; by default it names them joinable: the body
    # (figure 0) and the handle (figure 2; the block beside is figure 1), as one mask.
    assert len(sqparts.figure_ground(depth, cam, join=True).figures) == 3
    assert sqparts.figure_ground(depth, cam, join=True).joinable == ()
    fg = sqparts.figure_ground(depth, cam)
    assert len(fg.figures) == 4
    assert [k for k, _ in fg.joinable] == [(0, 2)]
    np.testing.assert_array_equal(fg.joinable[0][1], fg.figures[0] | fg.figures[2])
    with pytest.raises(ValueError, match=r"join: got 1, expected True or False"):
        sqparts.figure_ground(depth, cam, join=1)
    # Through recover_scene's settings and the command line's flag.
    from sqparts.cli import _recover_options, build_parser

    assert sqparts.SceneSettings(join=True).join is True and sqparts.SceneSettings().join == "auto"
    with pytest.raises(ValueError, match=r"join: got 'no', expected True, False or 'auto'"):
        sqparts.SceneSettings(join="no")
    for flags, want in (([], "auto"), (["--join"], True), (["--join", "auto"], "auto"), (["--join", "never"], False)):
        args = build_parser().parse_args(["recover", "x.npy", "--out", "o", *flags])
        assert _recover_options(args)["scene"].join == want


def _plate_edge_on():
    """A plate 40 x 2 x 50 cm seen nearly edge-on (its face 6.6 degrees off the line of
    sight) at 1.5 m, 80 x 60 pixels: its depth jumps tear it into pieces."""
    rotation = np.array(
        [[0.96692, 0.0, -0.25508], [-0.02945, 0.99331, -0.11165], [0.25338, 0.11547, 0.96045]], np.float64
    )
    from scipy.spatial.transform import Rotation

    plate = sqparts.Part(
        size=(0.2, 0.01, 0.25),
        squareness=(0.15, 0.15),
        position=(0.0, 0.0, 1.5),
        orientation=Rotation.from_matrix(rotation).as_rotvec(),
    )
    cam = sqparts.PinholeCamera(80, 60, 124.1, 124.1, 39.5, 29.5)
    return plate, cam, np.asarray(sqparts.render_range_image(plate, cam))


@pytest.mark.slow
def test_recover_scene_joins_a_torn_object_where_that_is_the_shorter_description():
    """Figure/ground tears the plate into figures that joined_pieces would join. Apart
    two of them take a part each (the third, 40 pixels, none); recover_scene with join
    "auto" (the default) merges those across the tear, recovers the figures as one too,
    and keeps one part across the tear: the shorter description of their pixels. The
    separate description's bits are its parts' E on the joined figure; a joined
    description as long or longer is not kept, nor a shorter one whose parts all stay
    within the pieces (objects side by side)."""
    from types import SimpleNamespace

    from sqparts._recover import _joined

    plate, cam, depth = _plate_edge_on()
    apart = sqparts.recover_scene(depth, cam, scene=sqparts.SceneSettings(join=False))
    assert [len(r.parts) for r in apart.figures] == [1, 1] and apart.joins == ()
    auto = sqparts.recover_scene(depth, cam, scene=sqparts.SceneSettings(join="auto"))
    fg = auto.figure_ground  # on the cleaned image
    assert len(fg.figures) >= 2 and [k for k, _ in fg.joinable] == [tuple(range(len(fg.figures)))]
    assert len(auto.figures) == 1 and len(auto.parts) == 1
    (join,) = auto.joins
    one = auto.figures[0]
    assert join["joined"] and join["spans"] and join["figures"] == (0,) and join["joined_bits"] == one.cost.total
    assert not (np.any([r.figure for r in apart.figures], 0) & ~one.figure).any()
    separate = sqparts.encoding_cost(apart.parts, one.data, one.costs).total
    assert join["separate_bits"] == pytest.approx(separate, abs=1e-3)
    assert join["joined_bits"] < join["separate_bits"] - 100  # a part's bits and more
    shown = np.isfinite(depth)
    drawn = np.isfinite(np.asarray(sqparts.render_range_image(auto.parts, cam)))
    assert (shown & drawn).sum() / (shown | drawn).sum() > 0.9  # the one part is the plate
    # The rule itself: a joined description longer than the separate one, or as long, is
    # not kept; a shorter one is, unless its part explains pixels in one figure only.
    masks = [r.figure for r in apart.figures]
    cost = one.cost
    for extra, within, joined in ((1.0, False, False), (0.0, False, False), (-0.5, False, True), (-0.5, True, False)):
        explained = cost.explained_mask & (masks[0] if within else True)
        stand_in = SimpleNamespace(
            cost=SimpleNamespace(total=join["separate_bits"] + extra, labels=cost.labels, explained_mask=explained),
            data=one.data,
            costs=one.costs,
            figure=one.figure,
            parts=one.parts,
        )
        kept, (report,) = _joined(list(apart.figures), [(0, 1)], [stand_in], masks)
        assert report["joined"] is joined and report["spans"] is not within
        assert report["separate_bits"] == pytest.approx(join["separate_bits"], abs=1e-3)
        assert len(kept) == (1 if joined else 2) and report["figures"] == ([0] if joined else [0, 1])
        if joined:
            assert kept == [stand_in]
        else:  # apart, each figure as it was or shorter with the joined part
            assert all(k.cost.total <= a.cost.total for k, a in zip(kept, apart.figures))
    # A figure kept apart takes the joined recovery's parts within it only where they are
    # the shorter description of it.
    from sqparts._encoding import part_vectors
    from sqparts._recover import _shorter

    first = apart.figures[0]
    mine = part_vectors(first.parts)
    swollen = mine.copy()
    swollen[:, 6:9] *= 1.3
    assert _shorter(first, swollen) is first
    worse = dataclasses.replace(
        first, parts=sqparts.Part.from_vector(swollen), cost=sqparts.encoding_cost(swollen, first.data, first.costs)
    )
    better = _shorter(worse, mine)
    assert better.cost.total == pytest.approx(first.cost.total, abs=1e-3)
    assert better.cost.total < worse.cost.total
    np.testing.assert_array_equal(part_vectors(better.parts), mine)
    assert better.history[-1] == ("joined figure's parts", better.cost.total)
    # parts.json says so, and the schema holds it.
    import jsonschema

    data = auto.scene_dict()
    jsonschema.validate(data, sqparts.parts_schema())
    assert data["figure_joins"][0]["joined"] is True


@pytest.mark.slow
def test_recover_scene_keeps_two_objects_side_by_side_apart():
    """A box and a ball before it, torn apart by the depth jump (15 cm) but joinable (it
    is less than the ball's size): with join "auto", recovered as one figure, their parts stay each within
    its piece, no part spans the tear, and the figures stay apart, a part each."""
    box = sqparts.Part(size=(0.1, 0.1, 0.1), squareness=(0.2, 0.2), position=(-0.1, 0.0, 1.5), orientation=(0, 0.5, 0))
    ball = sqparts.Part(size=(0.09, 0.09, 0.09), position=(0.08, 0.0, 1.25))
    cam = sqparts.PinholeCamera(80, 60, 124.1, 124.1, 39.5, 29.5)
    depth = np.asarray(sqparts.render_range_image(sqparts.stack_parts([box, ball]), cam))
    scene = sqparts.recover_scene(depth, cam, scene=sqparts.SceneSettings(join="auto"))
    assert [k for k, _ in scene.figure_ground.joinable] == [(0, 1)]
    assert [len(r.parts) for r in scene.figures] == [1, 1]
    (join,) = scene.joins
    assert not join["spans"] and not join["joined"] and join["figures"] == (0, 1)


def _box_on_wall(rng):
    cam = sqparts.OrthographicCamera(80, 60, 0.01, 39.5, 29.5)
    depth = np.full((60, 80), 2.0)
    depth[15:45, 20:60] = 1.5  # a box face 0.5 m in front of a wall
    fg = np.zeros(depth.shape, bool)
    fg[15:45, 20:60] = True
    edge = ~fg & (np.roll(fg, 1, 0) | np.roll(fg, -1, 0) | np.roll(fg, 1, 1) | np.roll(fg, -1, 1))
    inject = edge & (rng.random(depth.shape) < 0.6)
    mixed = depth.copy()
    mixed[inject] = 1.5 + rng.uniform(0.25, 0.75, inject.sum()) * 0.5
    return cam, depth, mixed, inject


def test_flying_pixels_found_and_removed(rng):
    cam, clean, mixed, inject = _box_on_wall(rng)
    found = sqparts.flying_pixels(mixed, cam)
    assert found[inject].mean() > 0.95
    assert found[~inject].mean() < 0.002
    assert not sqparts.flying_pixels(clean, cam).any()
    out = sqparts.clean_range_image(mixed, cam)
    assert np.isnan(out.depth[inject]).mean() > 0.95
    # With the flying pixels gone, the rubber sheet separates box from wall exactly.
    lab = sqparts.torn_components(out.depth, cam)
    box = lab[15:45, 20:60]
    assert len(np.unique(box[box >= 0])) == 1


def test_clean_missing_and_outliers():
    cam = sqparts.OrthographicCamera(30, 20, 0.01, 14.5, 9.5)
    d = np.full((20, 30), 1.0, np.float64)
    d[0, 0], d[0, 1], d[0, 2], d[0, 3] = 0.0, -1.0, np.inf, np.nan
    d[10, 10] = 0.2  # a lone return far in front of the surface
    out = sqparts.clean_range_image(d, cam)
    assert out.missing == 4
    assert np.isnan(out.depth[10, 10]) and out.outliers[10, 10]
    assert np.isfinite(out.depth).sum() == 20 * 30 - 5
    assert out.depth.dtype == np.float32
    near = sqparts.clean_range_image(d, cam, depth_range=(0.1, 0.5))
    assert np.isfinite(near.depth).sum() == 0 or np.nanmax(near.depth) <= 0.5
    with pytest.raises(ValueError, match="depth_range"):
        sqparts.clean_range_image(d, cam, depth_range=(2, 1))
    with pytest.raises(ValueError, match="tear"):
        sqparts.flying_pixels(d, cam, tear=-1)
    with pytest.raises(ValueError, match="depth: got shape"):
        sqparts.clean_range_image(d[:5], cam)


def test_quantised_data():
    yy, xx = np.mgrid[:60, :80]
    d = np.round((1.0 + 0.003 * xx) / 0.004) * 0.004  # 4 mm steps, like a 16-bit PNG in mm
    from sqparts._preprocess import estimate_quantum

    assert abs(estimate_quantum(d) - 0.004) < 1e-9
    assert estimate_quantum(d + 1e-4 * np.random.default_rng(0).random(d.shape)) is None


def test_recover_scene_gives_its_figures_one_frame(monkeypatch):
    # Figures of different sizes get different windows; their full-resolution scoring is
    # computed in one frame, the widest window's, so they share its compiled programs
    # (each scored as on its own window: tests/test_search.py). A frame beyond a window's
    # padding is not shared.
    from sqparts import _recover
    from sqparts._data import PAD

    parts = sqparts.stack_parts([on_table((-0.25, 0.05), 0.25, 0.08), on_table((0.2, -0.05), 0.06, 0.06)])
    depth = np.fmin(np.asarray(sqparts.render_range_image(parts, CAM)), plane_depth(CAM, TABLE_N, TABLE_D))
    seen = []

    def spy(depth, camera, *, search, **kwargs):
        seen.append(search)
        raise ValueError("found no part")

    monkeypatch.setattr(_recover, "recover", spy)
    with pytest.raises(ValueError, match="found no part"):
        sqparts.recover_scene(depth.astype(np.float32), CAM)
    assert len(seen) == 2 and seen[0].window != seen[1].window
    widest = max(s.window for s in seen)
    assert [s.frame_side for s in seen] == [widest, widest]
    small, large = (sqparts.SearchSettings(window=w) for w in (16, 16 + 2 * PAD))
    assert _recover._shared_frame(small, [small, large]) == small
    assert _recover._shared_frame(large, [small, large]) == large
    # A search pruned on no lattice (stride 1, brute force) scores the whole grid at
    # full resolution: on its own window, not the widest one's frame.
    narrow = next(s for s in seen if s.window != widest)
    alone = dataclasses.replace(narrow, stride=1, frame=None)
    assert _recover._shared_frame(alone, seen).frame is None
    assert _recover._shared_frame(dataclasses.replace(alone, stride=2), seen).frame == widest
    # Their pruning passes run on the widest window's lattices, where theirs fit in them
    # (each scored as on its own lattice: tests/test_search.py); a figure whose lattice is
    # finer than any of the widest one's keeps its own.
    wide = next(s for s in seen if s.window == widest)
    assert [s.lattices for s in seen] == [wide.own_lattices()] * 2
    fine = dataclasses.replace(narrow, stride=1, lattices=None)
    assert _recover._shared_lattices(fine, [fine, wide]) == fine
    with pytest.raises(ValueError, match=r"lattices: got \(1,\), expected one of at least"):
        dataclasses.replace(narrow, lattices=(1,)).pruning_program()


def test_prettifying_without_a_ground_plane_or_up_is_refused_before_recovering(monkeypatch):
    # The missing gravity direction was reported after every figure had been recovered.
    from sqparts import _recover

    part = sqparts.Part(size=[0.1, 0.08, 0.2], squareness=[0.5, 1.0], position=[0.0, 0.0, 1.5])
    depth = np.asarray(sqparts.render_range_image(part, CAM))
    called = []
    monkeypatch.setattr(_recover, "recover", lambda *a, **k: called.append(1))
    with pytest.raises(ValueError, match=r"^up: got nothing and no ground plane was found, .*\(--up X,Y,Z\)$"):
        sqparts.recover_scene(depth, CAM, scene=sqparts.SceneSettings(prettify=True))
    assert called == []
