import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_part_kwargs
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import sqparts
from sqparts._part import deform, rotation_vector, undeform


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(size=[0.1, -0.2, 0.3]), r"size: got .*, expected semi-axes > 0"),
        (dict(size=[0.1, 0.2]), r"size: got .*, expected 3 semi-axes"),
        (dict(size=[0.1, 0.2, 0.3], squareness=[0.05, 1.0]), r"squareness: got .*, expected values in \[0.1, 2.0\]"),
        (dict(size=[0.1, 0.2, 0.3], squareness=[1.0, 2.5]), r"squareness: got .*, expected values in"),
        (dict(size=[0.1, np.nan, 0.3]), r"size: got .*, expected finite values"),
        (dict(size=[0.1, 0.2, 0.3], position=[0, 0]), r"position: got shape \(2,\), expected \(3,\)"),
        (dict(size=[0.1, 0.2, 0.3], bend=[1.5, 0]), r"bend: got .*, expected values in \[-1.0, 1.0\]"),
        (dict(size=[0.1, 0.2, 0.3], taper=-1.2), r"taper: got .*, expected values in"),
        (dict(size=[0.1, 0.2, 0.3], orientation=[0, np.inf, 0]), r"orientation: got .*, expected finite"),
    ],
)
def test_part_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        sqparts.Part(**kwargs)


def test_from_vector_checks_length():
    with pytest.raises(ValueError, match=r"vector: got .*, expected a trailing axis of 14"):
        sqparts.Part.from_vector(np.ones(13))


def test_vector_round_trip(rng):
    part = sqparts.Part(**random_part_kwargs(rng))
    v = part.to_vector()
    assert v.shape == (14,)
    np.testing.assert_array_equal(sqparts.Part.from_vector(v).to_vector(), v)


def test_batch_iterates_and_indexes_within_range(rng):
    parts = [sqparts.Part(**random_part_kwargs(rng)) for _ in range(3)]
    batch = sqparts.stack_parts(parts)
    got = list(batch)  # would never end if iteration fell back to clamped indexing
    assert len(got) == 3
    for a, b in zip(got, parts):
        np.testing.assert_array_equal(a.to_vector(), b.to_vector())
    np.testing.assert_array_equal(batch[-1].to_vector(), parts[2].to_vector())
    with pytest.raises(IndexError, match=r"index: got 3, expected an index into a batch of 3"):
        batch[3]
    with pytest.raises(IndexError, match=r"index: got -4, expected an index"):
        batch[np.int64(-4)]
    with pytest.raises(TypeError, match=r"part: got a single Part, expected a batch"):
        list(parts[0])


def test_stacking_and_indexing_agree_inside_and_outside_jit(rng):
    """Concrete parts are stacked and indexed on the host, traced ones in JAX: both give
    numpy's stack and fancy indexing of the 14-vectors, as JAX arrays."""
    vecs = np.stack([np.asarray(sqparts.Part(**random_part_kwargs(rng)).to_vector()) for _ in range(5)])
    parts = [sqparts.Part.from_vector(v) for v in vecs]
    index = np.array([4, 0, 2])

    def pick(*ps):
        return sqparts.stack_parts(ps)[index].to_vector()

    host = pick(*parts)
    assert isinstance(host, jax.Array) and isinstance(sqparts.stack_parts(parts).size, jax.Array)
    np.testing.assert_array_equal(host, vecs[index])
    np.testing.assert_array_equal(jax.jit(pick)(*parts), vecs[index])
    batch = sqparts.Part.from_vector(jnp.asarray(vecs))
    np.testing.assert_array_equal(jax.vmap(lambda p: p.to_vector())(batch), vecs)


def test_rotation_matches_scipy(rng):
    for _ in range(10):
        rv = rng.normal(size=3) * 2
        np.testing.assert_allclose(
            sqparts.rotation_matrix(jnp.asarray(rv)), Rotation.from_rotvec(rv).as_matrix(), atol=2e-6
        )
        m = Rotation.from_rotvec(rv).as_matrix()
        np.testing.assert_allclose(Rotation.from_rotvec(rotation_vector(m)).as_matrix(), m, atol=1e-9)
    np.testing.assert_allclose(sqparts.rotation_matrix(jnp.zeros(3)), np.eye(3))
    with pytest.raises(ValueError, match=r"rotation: got .*, expected an orthonormal matrix"):
        rotation_vector(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(
        ValueError, match=r"rotation: got \[\[1\.0, 0\.0, 0\.0\], \[0\.0, inf, 0\.0\], .*\], expected a finite 3x3"
    ):
        rotation_vector(np.diag([1.0, np.inf, 1.0]))
    with pytest.raises(ValueError, match=r"rotation: got shape \(2, 2\), expected a finite 3x3"):
        rotation_vector(np.eye(2))


@settings(deadline=None, max_examples=15)
@given(seed=st.integers(0, 2**31 - 1))
def test_surface_points_have_inside_outside_one(seed):
    rng = np.random.default_rng(seed)
    part = sqparts.Part(**random_part_kwargs(rng))
    eta = rng.uniform(-1.5, 1.5, 64)
    omega = rng.uniform(-np.pi, np.pi, 64)
    pts = jax.vmap(sqparts.surface_point, in_axes=(None, 0, 0))(part, eta, omega)
    f = jax.vmap(sqparts.inside_outside, in_axes=(None, 0))(part, pts)
    np.testing.assert_allclose(f, 1.0, rtol=2e-3)


def test_inside_outside_closed_form_ellipsoid():
    part = sqparts.Part(size=[1.0, 2.0, 3.0], position=[1.0, 0.0, 0.0])
    p = jnp.array([1.5, 1.0, 1.0])
    expected = 0.5**2 + 0.5**2 + (1 / 3) ** 2
    np.testing.assert_allclose(sqparts.inside_outside(part, p), expected, rtol=1e-5)


def test_deform_inverts(rng):
    part = sqparts.Part(**random_part_kwargs(rng))
    q = jnp.asarray(rng.uniform(-0.1, 0.1, (20, 3)), jnp.float32)
    back = jax.vmap(lambda x: undeform(part, deform(part, x)))(q)
    np.testing.assert_allclose(back, q, atol=1e-5)


@pytest.mark.parametrize("squareness", [(0.1, 0.1), (2.0, 2.0), (0.1, 2.0), (1.0, 1.0)])
def test_inside_outside_gradients_finite_at_singular_places(x64, squareness):
    # On the axes (x = y = 0 etc.), at squareness limits, with zero bend and taper.
    part = sqparts.Part(size=[0.3, 0.2, 0.5], squareness=squareness, position=[0.0, 0.0, 2.0])
    vec = part.to_vector()

    def f(v, p):
        return sqparts.inside_outside(sqparts.Part.from_vector(v), p)

    for p in ([0.0, 0.0, 2.0], [0.0, 0.0, 2.3], [0.1, 0.0, 2.0], [0.0, 0.1, 2.0]):
        g_v, g_p = jax.grad(f, argnums=(0, 1))(vec, jnp.asarray(p))
        assert np.all(np.isfinite(g_v)) and np.all(np.isfinite(g_p)), (squareness, p)


def _distance_f64(v, x):
    """numpy float64 reference of surface_distance (Eq. 1, the paper's deformations
    undone as :func:`~sqparts._part.undeform` documents, the radial distance)."""
    v, x = np.asarray(v, np.float64), np.asarray(x, np.float64)
    local = Rotation.from_rotvec(v[3:6]).as_matrix().T @ (x - v[0:3])
    a1, a2, a3, e1, e2 = v[6], v[7], v[8], v[9], v[10]
    px, py, pz = local
    pz = pz - v[12] * px * px / a1
    px = px - v[11] * pz * pz / a3
    k = 1.0 + v[13] * pz / a3
    q = np.array([px / k, py / k, pz])
    # F in logarithms: float64 itself overflows beyond |q/a|^(2/ε) ~ 1e308.
    lx, ly, lz = (np.log(abs(q[i] / a)) * (2 / e) for i, a, e in ((0, a1, e2), (1, a2, e2), (2, a3, e1)))
    log_f = np.logaddexp((e2 / e1) * np.logaddexp(lx, ly), lz)
    length = np.linalg.norm(q)
    return length - length / np.exp(0.5 * e1 * log_f)


def test_surface_distance_gradients_finite_far_from_boxy_and_deformed_parts(rng):
    """|q/a|^(2/ε) overflowed float32 away from boxy parts (ε 0.1: 90 semi-axes out, or
    one semi-axis out where a bend stretches the undeformed frame): the value stayed
    finite, every gradient was NaN (18% of boxy, deformed parts at four semi-axes). The
    value and its gradient in the point against float64 numpy (central differences)."""
    v0 = np.array([0.0, 0.0, 0.0, 0.3, -0.2, 0.5, 0.07, 0.403, 0.117, 0.1, 0.1, 0.294, -0.668, -0.035])
    cases = [(v0, [-0.401, 0.033, -0.03])]  # the fuzzed case: NaN 1.4 semi-axes out
    cases.append((np.r_[0, 0, 0, 0, 0, 0, 1.0, 0.5, 0.8, 0.1, 0.1, 0, 0, 0], [100.0, 30.0, 20.0]))
    for _ in range(40):
        v = np.r_[rng.normal(0, 0.1, 3), rng.normal(0, 1, 3), rng.uniform(0.05, 0.4, 3), 0.1, rng.uniform(0.1, 0.4)]
        v = np.r_[v, rng.uniform(-0.9, 0.9, 2), rng.uniform(-0.9, 0.9)]
        d = rng.normal(size=3)
        cases.append((v, v[0:3] + rng.choice([1.5, 4.0, 30.0]) * v[6:9].max() * d / np.linalg.norm(d)))
    grad = jax.jit(jax.grad(lambda v, x: sqparts.surface_distance(sqparts.Part.from_vector(v), x), argnums=(0, 1)))
    for v, x in cases:
        x = np.asarray(x, np.float64)
        g_v, g_x = (np.asarray(g) for g in grad(jnp.asarray(v, jnp.float32), jnp.asarray(x, jnp.float32)))
        assert np.isfinite(g_v).all() and np.isfinite(g_x).all(), (v, x)
        value = float(sqparts.surface_distance(sqparts.Part.from_vector(jnp.asarray(v, jnp.float32)), jnp.asarray(x)))
        ref = _distance_f64(v, x)
        np.testing.assert_allclose(value, ref, rtol=1e-3, atol=1e-4)
        h = 1e-5 * max(1.0, np.linalg.norm(x))
        fd = [(_distance_f64(v, x + h * e) - _distance_f64(v, x - h * e)) / (2 * h) for e in np.eye(3)]
        np.testing.assert_allclose(g_x, fd, rtol=2e-2, atol=2e-3)


def test_surface_distance_closed_forms():
    # A sphere: the radial distance is the Euclidean distance, |x - c| - r.
    c = np.array([0.1, -0.2, 2.0])
    sphere = sqparts.Part(size=[0.3, 0.3, 0.3], squareness=[1.0, 1.0], position=c, orientation=[0.3, -1.0, 0.5])
    rng = np.random.default_rng(0)
    x = c + rng.normal(size=(50, 3)) * 0.4
    got = np.asarray(jax.vmap(lambda p: sqparts.surface_distance(sphere, p))(jnp.asarray(x)))
    np.testing.assert_allclose(got, np.linalg.norm(x - c, axis=1) - 0.3, atol=2e-6)
    # Any superquadric: along the ray from the centre the distance is (s - 1) r(direction),
    # with r found here by bisection of the inside-outside function.
    part = sqparts.Part(
        size=[0.2, 0.1, 0.35], squareness=[0.4, 1.6], position=[0.0, 0.1, 1.5], orientation=[1.0, 0.2, -0.4]
    )
    rot = np.asarray(sqparts.rotation_matrix(part.orientation))
    for u in rng.normal(size=(10, 3)):
        u /= np.linalg.norm(u)
        lo, hi = 0.0, 1.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            inside = float(sqparts.inside_outside(part, jnp.asarray(np.asarray(part.position) + rot @ (mid * u)))) < 1
            lo, hi = (mid, hi) if inside else (lo, mid)
        r = lo
        for s in (0.5, 1.0, 1.7):
            x = np.asarray(part.position) + rot @ (s * r * u)
            assert float(sqparts.surface_distance(part, jnp.asarray(x, jnp.float32))) == pytest.approx(
                (s - 1) * r, abs=3e-5
            )
    # Finite value and gradient at the centre itself, and near the centre of boxy parts
    # (where F underflowed and the distance was -inf).
    g = jax.grad(lambda p: sqparts.surface_distance(sphere, p))(jnp.asarray(c, jnp.float32))
    assert np.all(np.isfinite(np.asarray(g)))
    for squareness in ([0.1, 0.1], [0.1, 2.0], [2.0, 0.1]):
        box = sqparts.Part(size=[0.2, 0.1, 0.3], squareness=squareness, position=c, orientation=[0.3, -1.0, 0.5])
        for offset in ([0.0, 0.0, 0.0], [0.002, -0.001, 0.001]):
            x = jnp.asarray(c + np.asarray(offset), jnp.float32)
            for distance in (sqparts.surface_distance, sqparts.normal_distance):
                value, grad = jax.value_and_grad(lambda p: distance(box, p))(x)
                assert np.isfinite(float(value)) and np.all(np.isfinite(np.asarray(grad))), (squareness, offset)
                assert -0.3 <= float(value) <= -0.05  # inside, by about the nearest semi-axis


def _custom_jvp_matches_the_formula(distance, local_distance, squareness, seed=3, count=12, atol=2e-5) -> int:
    """``distance``'s custom JVP against plain forward and reverse mode through
    ``local_distance``, every part parameter and the point, at 16 points about each of
    ``count`` random parts (a third with ``squareness``), to ``atol`` of each row's
    largest entry; the values themselves equal. Returns the rows compared."""
    from sqparts._part import to_local

    def custom(v, x):
        return distance(sqparts.Part.from_vector(v), x)

    def plain(v, x):
        part = sqparts.Part.from_vector(v)
        return local_distance(part, to_local(part, x))

    rng = np.random.default_rng(seed)
    checked = 0
    for i in range(count):
        kw = random_part_kwargs(rng, deform=i % 2 == 1)
        if i % 3 == 0:
            kw["squareness"] = squareness
        v = sqparts.Part(**kw).to_vector()
        c = np.asarray(v[:3])
        x = jnp.asarray(c + rng.normal(size=(16, 3)) * 0.2, jnp.float32)
        want_v, want_x = jax.vmap(jax.jacfwd(plain, argnums=(0, 1)), (None, 0))(v, x)
        for mode in (jax.jacfwd, jax.jacrev):
            got_v, got_x = jax.vmap(mode(custom, argnums=(0, 1)), (None, 0))(v, x)
            for got, want in ((got_v, want_v), (got_x, want_x)):
                got, want = np.asarray(got), np.asarray(want)
                assert np.all(np.isfinite(got))
                # Plain forward mode overflows on some points of boxy parts (|q|^(2/ε) far
                # out): compare where it is finite, which must be most points.
                ok = np.isfinite(want).all(-1)
                checked += ok.sum()
                scale = np.abs(want[ok]).max(axis=-1, keepdims=True) + 1e-3
                np.testing.assert_allclose(got[ok] / scale, want[ok] / scale, atol=atol)
        np.testing.assert_array_equal(jax.vmap(custom, (None, 0))(v, x), jax.vmap(plain, (None, 0))(v, x))
    return checked


def test_normal_distance_derivatives_equal_autodiff_through_the_formula():
    from sqparts._part import _local_normal_distance

    assert (
        _custom_jvp_matches_the_formula(sqparts.normal_distance, _local_normal_distance, [0.3, 0.4], 4, 8, 5e-5)
        >= 0.8 * 8 * 16 * 2 * 2
    )


def test_surface_distance_derivatives_equal_autodiff_through_the_formula():
    """surface_distance's custom JVP (local reverse-mode gradients applied to the local
    point's tangents) against plain forward and reverse mode through the formula, and a
    sphere's closed form: every part parameter and the point, forward and reverse."""
    from sqparts._part import _local_distance

    def custom(v, x):
        return sqparts.surface_distance(sqparts.Part.from_vector(v), x)

    assert (
        _custom_jvp_matches_the_formula(sqparts.surface_distance, _local_distance, [0.15, 0.2]) >= 0.8 * 12 * 16 * 2 * 2
    )
    # A sphere: the distance |x - c| - r; its gradient is u = (x - c)/|x - c| in the
    # point, -u in the position, and -u_i² in semi-axis a_i (u_i in the part's frame: the
    # radius along u of an ellipsoid is (Σ u_i²/a_i²)^(-1/2)).
    sphere = sqparts.Part(size=[0.3, 0.3, 0.3], position=[0.1, -0.2, 2.0], orientation=[0.3, -1.0, 0.5]).to_vector()
    x = jnp.asarray([0.5, 0.1, 2.3], jnp.float32)
    unit = np.asarray(x - sphere[:3]) / np.linalg.norm(np.asarray(x - sphere[:3]))
    g_v, g_x = jax.grad(custom, argnums=(0, 1))(sphere, x)
    np.testing.assert_allclose(np.asarray(g_x), unit, atol=1e-5)
    np.testing.assert_allclose(np.asarray(g_v[:3]), -unit, atol=1e-5)
    local = np.asarray(sqparts.rotation_matrix(sphere[3:6])).T @ unit
    np.testing.assert_allclose(np.asarray(g_v[6:9]), -(local**2), atol=1e-5)
    np.testing.assert_allclose(np.asarray(g_v[3:6]), 0.0, atol=1e-5)  # turning a sphere moves nothing


def _norm_f64(q, a, e1, e2):
    """The superquadric norm F^(ε1/2) of an undeformed local point, float64, F in
    logarithms."""
    with np.errstate(divide="ignore"):
        lx, ly, lz = (np.log(abs(q[i] / a[i])) * (2 / e) for i, e in ((0, e2), (1, e2), (2, e1)))
    return np.exp(0.5 * e1 * np.logaddexp((e2 / e1) * np.logaddexp(lx, ly), lz))


def test_normal_distance_counts_an_error_along_the_normal_as_it_is():
    # A point moved off a box's surface along its normal by d is d from it (to first
    # order) wherever it lies, near the face's edges too, where the ray from the centre
    # meets the face obliquely and the radial distance counts d / cos θ; the normal from
    # float64 central differences of the norm.
    box = sqparts.Part(
        size=[0.2, 0.1, 0.05], squareness=[0.2, 0.2], position=[0.0, 0.0, 1.5], orientation=[0.3, -0.2, 0.1]
    )
    rot = np.asarray(sqparts.rotation_matrix(box.orientation))
    centre, a = np.asarray(box.position, np.float64), np.asarray(box.size, np.float64)
    rng = np.random.default_rng(2)
    ratios = []
    for eta, omega in rng.uniform([-1.4, -3.1], [1.4, 3.1], (30, 2)):
        p = np.asarray(sqparts.surface_point(box, eta, omega), np.float64)
        s = rot.T @ (p - centre)
        h = 1e-7
        g = [(_norm_f64(s + h * u, a, 0.2, 0.2) - _norm_f64(s - h * u, a, 0.2, 0.2)) / (2 * h) for u in np.eye(3)]
        normal = rot @ (np.asarray(g) / np.linalg.norm(g))
        for d in (-0.002, 0.002):
            x = jnp.asarray(p + d * normal, jnp.float32)
            assert float(sqparts.normal_distance(box, x)) == pytest.approx(d, abs=3e-4), (eta, omega, d)
            ratios.append(float(sqparts.surface_distance(box, x)) / d)
    assert max(ratios) > 1.5  # the radial distance does not (cos θ < 2/3 somewhere)
    # A sphere: both are |x - c| - r; along a part's axes (squareness up to 1): |x_i| - a_i.
    sphere = sqparts.Part(size=[0.3, 0.3, 0.3], position=[0.1, -0.2, 2.0], orientation=[0.3, -1.0, 0.5])
    x = np.asarray(sphere.position) + rng.normal(size=(20, 3)) * 0.4
    got = np.asarray(jax.vmap(lambda p: sqparts.normal_distance(sphere, p))(jnp.asarray(x, jnp.float32)))
    np.testing.assert_allclose(got, np.linalg.norm(x - np.asarray(sphere.position), axis=1) - 0.3, atol=3e-6)
    part = sqparts.Part(
        size=[0.2, 0.1, 0.35], squareness=[0.4, 0.7], position=[0.0, 0.1, 1.5], orientation=[1.0, 0.2, -0.4]
    )
    rot = np.asarray(sqparts.rotation_matrix(part.orientation))
    for axis, length in enumerate([0.2, 0.1, 0.35]):
        for t in (-0.5, 0.3, 1.2, 3.0):
            x = jnp.asarray(np.asarray(part.position) + rot[:, axis] * t * length, jnp.float32)
            assert float(sqparts.normal_distance(part, x)) == pytest.approx((abs(t) - 1) * length, abs=3e-6)


def test_half_precision_fields_are_widened_and_complex_refused():
    """A float16 part kept float16 fields, and its rays missed it: no pixel rendered."""
    cam = sqparts.OrthographicCamera(width=16, height=16, pixel_size=0.05, cx=7.5, cy=7.5)
    want = np.isfinite(np.asarray(sqparts.render_range_image(sqparts.Part(size=[0.3] * 3, position=[0, 0, 3.0]), cam)))
    assert want.sum() > 50
    for dtype in (np.float16, jnp.bfloat16):
        part = sqparts.Part(size=np.full(3, 0.3, dtype), position=np.array([0, 0, 3.0], dtype))
        assert part.size.dtype == np.float32 and part.position.dtype == np.float32
        np.testing.assert_array_equal(np.isfinite(np.asarray(sqparts.render_range_image(part, cam))), want)
    with pytest.raises(ValueError, match=r"size: got complex128, expected real numbers"):
        sqparts.Part(size=[1 + 1j, 1, 1])


def test_fields_that_are_not_numbers_are_named():
    """Strings, objects and ragged lists gave numpy's own messages, naming no field."""
    for kwargs, field in [
        (dict(size="abc"), "size"),
        (dict(size=[object(), 1, 1]), "size"),
        (dict(size=[[1, 1, 1], [1, 1]]), "size"),
        (dict(size=[1, 1, 1], position="xyz"), "position"),
        (dict(size=[1, 1, 1], bend=[[1], [1, 2]]), "bend"),
    ]:
        with pytest.raises(ValueError, match=rf"^{field}: got .*, expected numbers$"):
            sqparts.Part(**kwargs)
