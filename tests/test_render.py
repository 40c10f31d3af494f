import functools
from unittest import mock

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_part_kwargs
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

import sqparts
from sqparts._render import cast_batch, cast_part

PINHOLE = sqparts.PinholeCamera(64, 64, 100.0, 100.0, 31.5, 31.5)
ORTHO = sqparts.OrthographicCamera(64, 64, 0.011, 31.5, 31.5)


def _ellipsoid_depth(camera, center, rot, size):
    """Closed-form first hit of every camera ray with an ellipsoid."""
    o, d = (np.asarray(a, np.float64) for a in camera.rays())
    m = rot.T / np.asarray(size)[:, None]  # maps camera offsets to the unit sphere
    oo = (o - center) @ m.T
    dd = d @ m.T
    a = (dd * dd).sum(-1)
    b = (oo * dd).sum(-1)
    c = (oo * oo).sum(-1) - 1
    disc = b * b - a * c
    t = (-b - np.sqrt(np.maximum(disc, 0))) / a
    return np.where(disc > 0, t, np.nan)


def _compare(ref, ours, camera):
    a, b = np.isfinite(ref), np.isfinite(ours)
    iou = (a & b).sum() / max((a | b).sum(), 1)
    both = a & b
    px = np.asarray(camera.pixel_size_at(jnp.asarray(ref[both])))
    err = np.abs(ref[both] - ours[both]) / px
    return iou, float(np.median(err)) if err.size else np.inf


@pytest.mark.parametrize("camera", [PINHOLE, ORTHO], ids=["pinhole", "orthographic"])
def test_ellipsoids_match_closed_form(camera, rng):
    for _ in range(10):
        kw = random_part_kwargs(rng, deform=False)
        kw["squareness"] = [1.0, 1.0]
        part = sqparts.Part(**kw)
        ref = _ellipsoid_depth(
            camera, kw["position"], np.asarray(sqparts.rotation_matrix(part.orientation)), kw["size"]
        )
        ours = np.asarray(sqparts.render_range_image(part, camera))
        iou, med = _compare(ref, ours, camera)
        assert iou >= 0.99 and med <= 0.05, (iou, med)
        assert ours.dtype == np.float32


@pytest.mark.slow
@pytest.mark.parametrize("camera", [PINHOLE, ORTHO], ids=["pinhole", "orthographic"])
def test_random_deformed_parts_match_trimesh(camera):
    rng = np.random.default_rng(1 if camera is PINHOLE else 2)
    ious, meds = [], []
    for _ in range(30):
        part = sqparts.Part(**random_part_kwargs(rng))
        ref = sqparts.render_mesh(sqparts.part_mesh(part, resolution=20), camera)
        ours = np.asarray(sqparts.render_range_image(part, camera))
        iou, med = _compare(ref, ours, camera)
        ious.append(iou)
        meds.append(med)
    assert min(ious) >= 0.99, ious
    assert max(meds) <= 0.05, meds


def test_scanner_stores_range_along_ray():
    cam = sqparts.ScannerCamera(64, 32, np.radians(1.0), np.radians(1.0), 31.5, 15.5)
    center = np.array([1.0, -0.3, 8.0])
    part = sqparts.Part(size=[1.5, 1.5, 1.5], position=center)
    ours = np.asarray(sqparts.render_range_image(part, cam), np.float64)
    _, d = (np.asarray(a, np.float64) for a in cam.rays())
    b = d @ center
    disc = b * b - (center @ center - 2.25)
    ref = np.where(disc > 0, b - np.sqrt(np.maximum(disc, 0)), np.nan)
    iou, _ = _compare(ref, ours, cam)
    assert iou >= 0.99
    both = np.isfinite(ref) & np.isfinite(ours)
    np.testing.assert_allclose(ours[both], ref[both], atol=1e-4)


def test_scene_nearest_hit_wins(rng):
    a = sqparts.Part(**random_part_kwargs(rng, distance=2.0))
    b = sqparts.Part(**random_part_kwargs(rng, distance=2.15))
    scene = sqparts.stack_parts([a, b])
    depth, labels = sqparts.render_range_image(scene, PINHOLE, return_labels=True)
    each = np.asarray(sqparts.render_each(scene, PINHOLE))
    expected = np.fmin(each[0], each[1])
    np.testing.assert_array_equal(np.isnan(depth), np.isnan(expected))
    np.testing.assert_allclose(depth, expected, rtol=1e-6, equal_nan=True)
    lab = np.asarray(labels)
    hit = np.isfinite(expected)
    np.testing.assert_array_equal(lab[~hit], -1)
    np.testing.assert_array_equal(np.nanargmin(np.where(np.isnan(each), np.inf, each), 0)[hit], lab[hit])


def test_moving_a_part_moves_its_rendering(rng):
    part = sqparts.Part(**random_part_kwargs(rng, deform=False))
    moved = sqparts.Part.from_vector(part.to_vector().at[2].add(0.25))
    d0 = np.asarray(sqparts.render_range_image(part, ORTHO))
    d1 = np.asarray(sqparts.render_range_image(moved, ORTHO))
    np.testing.assert_allclose(d1, d0 + 0.25, atol=1e-5)  # orthographic: pure depth shift
    shifted = sqparts.Part.from_vector(part.to_vector().at[0].add(5 * ORTHO.pixel_size))
    d2 = np.asarray(sqparts.render_range_image(shifted, ORTHO))
    np.testing.assert_allclose(d2[:, 5:], d0[:, :-5], atol=1e-4)


def test_window_equals_crop(rng):
    part = sqparts.Part(**random_part_kwargs(rng))
    full = np.asarray(sqparts.render_range_image(part, PINHOLE))
    win = np.asarray(sqparts.render_range_image(part, PINHOLE, window=(10, 7, 20, 30)))
    np.testing.assert_allclose(win, full[10:30, 7:37], rtol=1e-6, equal_nan=True)


def test_jit_equals_no_jit_and_chunked_equals_unchunked(rng):
    cam = sqparts.PinholeCamera(12, 12, 15.0, 15.0, 5.5, 5.5)
    o, d = cam.rays()
    parts = sqparts.stack_parts([sqparts.Part(**random_part_kwargs(rng)) for _ in range(7)])
    t_jit, h_jit = jax.jit(cast_part)(parts[0], o, d)
    with jax.disable_jit():
        t_eager, h_eager = cast_part(parts[0], o, d)
    np.testing.assert_array_equal(h_jit, h_eager)
    np.testing.assert_allclose(t_jit, t_eager, rtol=1e-5)
    full_t, full_h = jax.jit(jax.vmap(cast_part, in_axes=(0, None, None)))(parts, o, d)
    for bs in (1, 3, 7):
        t, h = jax.jit(lambda p: cast_batch(p, o, d, batch_size=bs))(parts)
        np.testing.assert_array_equal(h, full_h)
        np.testing.assert_allclose(t, full_t, rtol=1e-6)


def test_unrolled_newton_loop_gives_the_same_rays(rng):
    # The grid search unrolls the Newton loop (fused steps), everything else rolls it
    # (less to compile): the same hits and depths either way, and the same gradients.
    cam = sqparts.PinholeCamera(24, 24, 30.0, 30.0, 11.5, 11.5)
    o, d = cam.rays()
    parts = sqparts.stack_parts([sqparts.Part(**random_part_kwargs(rng)) for _ in range(6)])
    for unroll_steps in (6, 8):
        rolled = jax.jit(jax.vmap(lambda p: cast_part(p, o, d, unroll_steps)))(parts)
        unrolled = jax.jit(jax.vmap(lambda p: cast_part(p, o, d, unroll_steps, unroll=True)))(parts)
        assert np.asarray(rolled[1]).sum() > 100  # the parts are in view
        np.testing.assert_array_equal(unrolled[1], rolled[1])
        np.testing.assert_allclose(unrolled[0], rolled[0], rtol=1e-6)

    def depth_sum(p, unroll):
        t, hit = cast_part(p, o, d, unroll=unroll)
        return jnp.sum(jnp.where(hit, t, 0.0))

    grads = [jax.grad(depth_sum)(parts[0], u) for u in (False, True)]
    np.testing.assert_allclose(grads[1].to_vector(), grads[0].to_vector(), rtol=1e-5, atol=1e-6)


def test_ray_tiles_equal_one_pass(rng):
    # cast_part in tiles of rays (the last one short) and cast_batch's CPU tiles give the
    # same rays as one vectorised pass, with the same gradients.
    cam = sqparts.PinholeCamera(12, 12, 15.0, 15.0, 5.5, 5.5)
    o, d = cam.rays()
    parts = sqparts.stack_parts([sqparts.Part(**random_part_kwargs(rng)) for _ in range(5)])
    t, h = jax.jit(cast_part)(parts[0], o, d)
    t_tiled, h_tiled = jax.jit(lambda p: cast_part(p, o, d, ray_batch_size=10))(parts[0])
    np.testing.assert_array_equal(h_tiled, h)
    np.testing.assert_allclose(t_tiled, t, rtol=1e-6)
    grad = jax.jit(jax.grad(lambda v: cast_part(sqparts.Part.from_vector(v), o, d)[0].sum()))(parts[0].to_vector())
    grad_tiled = jax.jit(jax.grad(lambda v: cast_part(sqparts.Part.from_vector(v), o, d, ray_batch_size=10)[0].sum()))(
        parts[0].to_vector()
    )
    np.testing.assert_allclose(grad_tiled, grad, rtol=1e-5, atol=1e-6)
    full_t, full_h = jax.jit(jax.vmap(cast_part, in_axes=(0, None, None)))(parts, o, d)
    with mock.patch("sqparts._render.CPU_TILE", 64):  # tiles of 64 // 3 = 21 rays
        batch_t, batch_h = jax.jit(functools.partial(cast_batch, batch_size=3))(parts, o, d)
    np.testing.assert_array_equal(batch_h, full_h)
    np.testing.assert_allclose(batch_t, full_t, rtol=1e-6)


def _interior_rays(part, camera, n=6):
    """Rays that hit the part away from its silhouette (stable under small changes)."""
    depth = np.asarray(sqparts.render_range_image(part, camera))
    from scipy.ndimage import binary_erosion

    inner = binary_erosion(np.isfinite(depth), iterations=3)
    rows, cols = np.nonzero(inner)
    pick = np.linspace(0, len(rows) - 1, n).astype(int)
    o, d = camera.rays()
    return o[rows[pick], cols[pick]], d[rows[pick], cols[pick]]


@pytest.mark.parametrize("deformed", [False, True])
def test_depth_gradients_match_finite_differences(x64, rng, deformed):
    kw = random_part_kwargs(rng, deform=deformed)
    kw["squareness"] = [0.7, 1.2]
    part = sqparts.Part(**{k: np.asarray(v, np.float64) for k, v in kw.items()})
    o, d = _interior_rays(part, PINHOLE)
    o, d = jnp.asarray(o, jnp.float64), jnp.asarray(d, jnp.float64)

    @jax.jit
    def depth_sum(v):
        t, hit = cast_part(sqparts.Part.from_vector(v), o, d, 12)
        return jnp.sum(t * jnp.arange(1, len(t) + 1))

    v = part.to_vector()
    assert v.dtype == jnp.float64
    check_grads(depth_sum, (v,), order=1, modes=["rev", "fwd"], eps=1e-6, atol=1e-4, rtol=1e-4)
    np.testing.assert_allclose(jax.jacfwd(depth_sum)(v), jax.jacrev(depth_sum)(v), rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize(
    "kw",
    [
        dict(squareness=[0.1, 0.1]),
        dict(squareness=[2.0, 2.0]),
        dict(squareness=[1.0, 1.0]),
        dict(squareness=[0.3, 1.0], bend=[0.0, 0.0], taper=0.0),
    ],
)
def test_gradients_finite_on_axis_and_at_limits(x64, kw):
    # The central ray runs exactly along the part's local z axis (x = y = 0 everywhere).
    part = sqparts.Part(size=[0.2, 0.3, 0.4], position=[0.0, 0.0, 2.0], **kw)
    o = jnp.zeros((1, 3), jnp.float64)
    d = jnp.array([[0.0, 0.0, 1.0]], jnp.float64)

    def depth(v):
        t, hit = cast_part(sqparts.Part.from_vector(v), o, d)
        return t[0]

    v = part.to_vector()
    value, g = jax.jit(jax.value_and_grad(depth))(v)
    np.testing.assert_allclose(value, 1.6, atol=1e-9)
    assert np.all(np.isfinite(g)), g
    np.testing.assert_allclose(g[2], 1.0, atol=1e-9)  # moving the part in z moves the hit
    np.testing.assert_allclose(g[8], -1.0, atol=1e-9)  # a3 grows toward the camera


def test_render_errors():
    part = sqparts.Part(size=[0.1, 0.1, 0.1], position=[0, 0, 1.0])
    with pytest.raises(TypeError, match=r"camera: got .*, expected a PinholeCamera"):
        sqparts.render_range_image(part, {"width": 3})
    with pytest.raises(TypeError, match=r"parts: got .*, expected a Part"):
        sqparts.render_range_image([part], PINHOLE)
    with pytest.raises(ValueError, match=r"window: got .*, expected \(row0, col0, rows, cols\)"):
        sqparts.render_range_image(part, PINHOLE, window=(1, 2))
    # A window past the pixel limit aborted the process in XLA; an empty one returned (0, 5).
    for window in [(0, 0, 100000, 100000), (0, 0, 0, 5), (0, 0, -3, 5), 5, "abcd", (0, 0, 2.5, 4), (0, 0, True, 4)]:
        with pytest.raises(ValueError, match=r"window: got .*, expected \(row0, col0, rows, cols\): integers"):
            sqparts.render_range_image(part, PINHOLE, window=window)
    # A window past the image's edge rendered rays the camera does not have.
    for window in [(0, 0, 100, 100), (-1, 0, 4, 4), (60, 60, 5, 5)]:
        with pytest.raises(ValueError, match=r"window: got .*, expected \(row0, col0, rows, cols\) inside the 64x64"):
            sqparts.render_range_image(part, PINHOLE, window=window)
    with pytest.raises(ValueError, match=r"batch_size: got .*, expected a positive integer"):
        sqparts.render_each(part, PINHOLE, batch_size=0)
    o, d = PINHOLE.rays()
    with pytest.raises(ValueError, match=r"ray_batch_size: got 0, expected a positive integer or None"):
        cast_part(part, o, d, ray_batch_size=0)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_gauge_along_ray_matches_gauge_and_its_derivative(dtype, rng):
    # The Newton loop's closed-form value and slope against the plain gauge and autodiff,
    # near the surface, far outside a boxy part, on the local axes and at the centre.
    from sqparts._part import gauge
    from sqparts._render import _gauge_along_ray, _ray_gauge

    with jax.enable_x64(dtype == "float64"):
        kws = [random_part_kwargs(rng) for _ in range(6)]
        kws += [
            dict(size=[0.2, 0.1, 0.3], squareness=[0.1, 0.1], position=[0, 0, 2.0], bend=[0.3, -0.2], taper=0.4),
            dict(size=[0.2, 0.1, 0.3], squareness=[2.0, 2.0], position=[0, 0, 2.0]),
        ]
        for kw in kws:
            part = sqparts.Part(**{k: np.asarray(v, dtype) for k, v in kw.items()})
            o = jnp.asarray(np.r_[rng.normal(size=(40, 3)) * 0.4, np.zeros((2, 3)), [[0, 0, 0.6], [3.0, 0, 0]]], dtype)
            d = rng.normal(size=(44, 3))
            d[-4:] = [[0, 0, 1], [1, 0, 0], [0, 0, -1], [-1, 0, 0]]
            d = jnp.asarray(d / np.linalg.norm(d, axis=1, keepdims=True), dtype)
            t = jnp.asarray(rng.uniform(0.0, 0.3, 44), dtype)
            val, slope = jax.vmap(_gauge_along_ray, in_axes=(None, 0, 0, 0))(_ray_gauge(part), o, d, t)
            ref_val, ref_slope = jax.vmap(
                lambda oo, dd, tt: jax.jvp(lambda s: gauge(part, oo + s * dd), (tt,), (jnp.ones_like(tt),))
            )(o, d, t)
            val, slope, ref_val, ref_slope = (np.asarray(a) for a in (val, slope, ref_val, ref_slope))
            # The plain gauge overflows far outside a boxy part, and autodiff is NaN on some
            # axes; the log-space form is finite everywhere.
            assert np.all(np.isfinite(val)) and np.all(np.isfinite(slope))
            ok = np.isfinite(ref_val) & np.isfinite(ref_slope)
            assert ok.sum() >= 40
            rtol = 2e-4 if dtype == "float32" else 1e-9
            np.testing.assert_allclose(val[ok], ref_val[ok], rtol=rtol, atol=rtol)
            scale = np.abs(ref_val[ok]) + 1
            np.testing.assert_allclose(slope[ok] / scale, ref_slope[ok] / scale, rtol=rtol, atol=rtol)


@settings(deadline=None, max_examples=25)
@given(seed=st.integers(0, 2**31 - 1))
def test_reverse_mode_equals_forward_mode_at_hits_misses_and_grazing_rays(seed):
    # A small camera sees each part whole: hits, misses and grazing silhouette rays.
    rng = np.random.default_rng(seed)
    kw = random_part_kwargs(rng)
    if seed % 3 == 0:
        kw["squareness"] = rng.choice([0.1, 2.0], 2)
    vector = sqparts.Part(**kw).to_vector()
    np.testing.assert_allclose(_JACREV(vector), _JACFWD(vector), rtol=1e-4, atol=1e-4)
    assert np.all(np.isfinite(np.asarray(_JACREV(vector))))


def _cast_small(vector):
    o, d = sqparts.PinholeCamera(10, 10, 12.0, 12.0, 4.5, 4.5).rays()
    t, _ = cast_part(sqparts.Part.from_vector(vector), o.reshape(-1, 3), d.reshape(-1, 3))
    return t


_JACFWD = jax.jit(jax.jacfwd(_cast_small))
_JACREV = jax.jit(jax.jacrev(_cast_small))


@pytest.mark.parametrize(
    "camera",
    [
        sqparts.PinholeCamera(50, 37, 60.0, 60.0, 24.5, 18.0),
        sqparts.OrthographicCamera(50, 37, 0.012, 24.5, 18.0),
        sqparts.ScannerCamera(50, 37, 0.02, 0.02, 24.5, 18.0),
    ],
    ids=["pinhole", "orthographic", "scanner"],
)
def test_tiled_layers_equal_whole_image_rendering(camera, rng):
    """render_layers renders each part only in the tiles around its silhouette's box:
    the depths equal every ray of the image cast against the part, for small, large,
    deformed, off-image, border-straddling parts and parts reaching behind the camera,
    on an image whose size is no multiple of the tile."""
    from sqparts._encoding import render_layers, silhouette_boxes

    parts = [sqparts.Part(**random_part_kwargs(rng)) for _ in range(10)]
    vectors = np.stack([np.asarray(p.to_vector()) for p in parts])
    vectors[0, 6:9] *= 6.0  # larger than the image
    vectors[1, 0] += 0.35  # across the right border
    vectors[2, 0:2] += 3.0  # out of view
    vectors[3, 2] = 0.05  # reaching behind the camera plane
    vectors[4, 6:9] = [0.004, 0.004, 0.004]  # a pixel or two
    o, d = camera.rays()
    cast = jax.jit(lambda v: cast_part(sqparts.Part.from_vector(v), o, d))
    whole = np.stack([np.where(h, t, np.inf) for t, h in map(cast, vectors)])
    tiled = render_layers(vectors, camera)
    assert tiled.shape == whole.shape and np.isfinite(whole).any(axis=(1, 2)).sum() >= 6
    np.testing.assert_array_equal(np.isfinite(tiled), np.isfinite(whole))
    np.testing.assert_allclose(tiled[np.isfinite(tiled)], whole[np.isfinite(whole)], rtol=1e-6, atol=1e-5)
    box = silhouette_boxes(vectors, camera)
    area = (box[:, 2] - box[:, 0]) * (box[:, 3] - box[:, 1])
    if isinstance(camera, sqparts.ScannerCamera):
        assert (area == camera.width * camera.height).all()  # no projection: the whole image
    else:
        assert area[4] < 36 and area[2] == 0  # a tiny part's box is small, an unseen one's empty


@pytest.mark.parametrize(
    "camera",
    [sqparts.PinholeCamera(50, 37, 60.0, 60.0, 24.5, 18.0), sqparts.ScannerCamera(50, 37, 0.02, 0.02, 24.5, 18.0)],
    ids=["pinhole", "scanner"],
)
def test_groups_rendered_together_equal_their_parts_nearest_hit(camera, rng):
    """render_nearest (posed solids verified at once) gives each group of parts the
    nearest of every ray of the image cast against each of its parts: groups of one and
    of several overlapping parts, listed out of order, an empty group and one out of view."""
    from sqparts._encoding import render_layers, render_nearest

    vectors = np.stack([np.asarray(sqparts.Part(**random_part_kwargs(rng)).to_vector()) for _ in range(9)])
    vectors[3, 0:2] += 3.0  # out of view: its group (of one) misses everywhere
    vectors[7, 0:3] = vectors[6, 0:3] + 0.02  # two parts of one group overlapping
    owner = np.array([2, 0, 2, 4, 0, 2, 1, 1, 0])  # group 3 is empty
    o, d = camera.rays()
    cast = jax.jit(lambda v: cast_part(sqparts.Part.from_vector(v), o, d))
    whole = np.stack([np.where(h, t, np.inf) for t, h in map(cast, vectors)])
    expected = np.stack(
        [whole[owner == g].min(0) if (owner == g).any() else np.full(whole.shape[1:], np.inf) for g in range(5)]
    )
    together = render_nearest(vectors, owner, 5, camera)
    assert together.shape == expected.shape and np.isfinite(expected[[0, 1, 2]]).any(axis=(1, 2)).all()
    assert not np.isfinite(together[[3, 4]]).any()
    np.testing.assert_array_equal(np.isfinite(together), np.isfinite(expected))
    np.testing.assert_allclose(together[np.isfinite(together)], expected[np.isfinite(expected)], rtol=1e-6, atol=1e-5)
    # The same depths, bit for bit, as the parts' own layers (what verification used before).
    layers = render_layers(vectors, camera)
    for g in range(3):
        np.testing.assert_array_equal(together[g], layers[owner == g].min(0))
    # Nothing in view at all: every group misses everywhere.
    assert not np.isfinite(render_nearest(vectors[[3, 3]], [0, 0], 2, camera)).any()
