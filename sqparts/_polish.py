"""Polishing: optimistix Levenberg-Marquardt on the distances of measured points from a
part's surface along its normal (:func:`~sqparts.normal_distance`, footnote 6), while rays off the figure must miss the part.

:func:`polish_part` fits one part; :func:`polish_parts` fits a batch of parts, each on
its own points, ``PART_BUCKET`` parts and :data:`POLISH_CALL_STEPS` steps per compiled
call: the one program every stage polishes with. :func:`grow_parts` grows a batch of
parts' supports over the image by rounds of it (the search's polish of every region's
candidates at once); the refinement's moves build their own supports on the same
:func:`figure_points` and :func:`background_rays`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ._camera import camera_rays
from ._compile import RowMemo, balanced_groups, concurrently, persistent_jit
from ._data import RangeData
from ._encoding import PART_BUCKET, host_parts, pad_parts, pad_rows, pad_vectors, part_vectors
from ._part import (
    Part,
    distance_terms,
    from_unconstrained,
    matmul,
    normal_distance,
    part_tangent,
    rotation_matrix,
    surface_distance,
    to_local,
    to_unconstrained,
)
from ._typing import ArrayLike, Float


def ray_penetration(part: Part, origin, direction, far: Float[ArrayLike, ""] = jnp.inf):
    """Signed radial distance (:func:`~sqparts.surface_distance`) of the ray's point
    deepest inside the part's ellipsoid of semi-axes ``size``, among the points
    ``origin + t direction`` with t <= ``far`` (the free segment in front of a return):
    negative when the ray enters the part there (exact for ellipsoids, a smooth proxy
    for the rest). Its derivatives are a custom JVP like
    :func:`~sqparts.surface_distance`'s (:func:`_ray_penetration_jvp`)."""
    direction = jnp.asarray(direction)
    return _ray_penetration(part, jnp.asarray(origin), direction, jnp.asarray(far, direction.dtype))


def _deepest(part: Part, origin, direction, far):
    """The ray's parameter t of its point deepest inside the part's ellipsoid, before
    ``far``, and that unclipped (t = -(o.d)/(d.d), o and d in the ellipsoid's unit frame)."""
    o = to_local(part, origin) / part.size
    d = matmul(rotation_matrix(part.orientation).T, direction) / part.size
    free = -matmul(o, d) / matmul(d, d)
    return jnp.minimum(free, far), free


@jax.custom_jvp
def _ray_penetration(part: Part, origin, direction, far):
    t, _ = _deepest(part, origin, direction, far)
    return surface_distance(part, origin + t * direction)


@_ray_penetration.defjvp
def _ray_penetration_jvp(primals, tangents):
    """The distance's terms at the deepest point x = o + t d (:func:`distance_terms`)
    and the move of t. With M = R S^-2 R^T (S the semi-axes), t = -a/b for a =
    (o - c)^T M d and b = d^T M d, so b dt = -(x - c)^T dM d + (M d).(dc - do) - (M (x -
    c + t d)).dd (c the position); clipped at ``far``, dt = dfar. As for the distance,
    the part's share is one dot product of a vector of this ray with one of the tangent."""
    part, origin, direction, far = primals
    dpart, dorigin, ddirection, dfar = tangents
    t, free = _deepest(part, origin, direction, far)
    x = origin + t * direction
    value, per_point, turned = distance_terms(part, x)

    def metric(orientation, size):
        r = rotation_matrix(orientation) / size
        return matmul(r, r.T)

    m, dm = jax.jvp(metric, (part.orientation, part.size), (dpart.orientation, dpart.size))
    m_dir = matmul(m, direction)
    along = matmul(turned, direction)  # the distance's derivative along the ray
    inside = free <= far
    w = jnp.where(inside, along / matmul(direction, m_dir), 0.0)
    rel = x - part.position
    per_ray = jnp.concatenate([per_point, -w * jnp.outer(rel, direction).reshape(9), w * m_dir])
    per_tangent = jnp.concatenate([part_tangent(part, dpart), dm.reshape(9), dpart.position])
    ray = matmul(turned, dorigin + t * ddirection) - w * (
        matmul(m_dir, dorigin) + matmul(matmul(m, rel + t * direction), ddirection)
    )
    return value, matmul(per_ray, per_tangent) + ray + jnp.where(inside, 0.0, along * dfar)


@functools.cache
def _levenberg_marquardt():
    """The damped Gauss-Newton step through the normal equations (lineax >= 0.1's
    Normal: a 14x14 Cholesky) instead of optimistix's default QR of the stacked
    (residuals + 14) x 14 Jacobian. The normal equations square the condition number,
    but the damping and the prior below keep them well-posed; the steps agree to 1e-7
    and a bucket of 8 parts polishes in 79 ms instead of 112 ms on the CPU (human
    recovery warm: 8.3 -> 6.5 s). Imported on first trace: a process that loads its
    exported programs never needs optimistix (0.1 s of its start-up)."""
    import lineax as lx
    import optimistix as optx

    return optx.LevenbergMarquardt(rtol=1e-6, atol=1e-8, linear_solver=lx.Normal(lx.Cholesky()))


def polish_part(part: Part, points, weights, *, rays=None, steps: int = 20, free=None) -> Part:
    """Levenberg-Marquardt (optimistix) on the weighted distances along the surface's
    normal (:func:`~sqparts.normal_distance`) of ``points`` from the part's surface.

    ``rays`` = (origins, directions, weights[, far]), optional: rays off the figure,
    which the part must miss (up to ``far``, default: the whole ray); each adds its
    weighted penetration (:func:`ray_penetration`) so the part cannot swell past the
    silhouette while hugging the visible points. ``free``, optional (14,) bool: the
    numbers of :meth:`~sqparts.Part.to_vector` the solve may move (default: all); the
    rest keep the part's values (e.g. bend and taper held at zero: :data:`RIGID`).
    Runs a fixed number of steps and never raises; returns the input if the solve produced
    non-finite values or the weights cover fewer than 8 points.

    The solve is posed in units of :func:`_unit` (a power of two; 1 for scenes at a
    metre-like scale), so that an image in millimetres or kilometres polishes as the
    same image in metres: the prior, the damping and the tolerances are not
    scale-free.
    """
    w = weights.astype(part.size.dtype)
    unit = _unit(points, w)
    part = _scaled(part, 1 / unit)
    points = points / unit
    u0 = to_unconstrained(part)
    free = jnp.ones(u0.shape, bool) if free is None else jnp.asarray(free, bool)

    def residuals(u, _):
        p = from_unconstrained(jnp.where(free, u, u0))
        r = w * jax.vmap(lambda x: normal_distance(p, x))(points)
        if rays is not None:
            o, d, wr, *far = rays
            far = far[0] if far else jnp.full(wr.shape, jnp.inf, wr.dtype)
            pen = jax.vmap(ray_penetration, in_axes=(None, 0, 0, 0))(p, o / unit, d, far / unit)
            r = jnp.concatenate([r, wr * jnp.minimum(pen, 0.0)])
        # A weak prior on the 14 numbers keeps unobserved ones near their start.
        return r, 1e-3 * (u - u0)

    import optimistix as optx

    sol = optx.least_squares(residuals, _levenberg_marquardt(), u0, max_steps=steps, throw=False)
    ok = jnp.all(jnp.isfinite(sol.value)) & (jnp.sum(w > 0) >= 8)
    return _scaled(from_unconstrained(jnp.where(ok & free, sol.value, u0)), unit)


UNIT_RANGE = (0.125, 64.0)
"""The scene scale polishing takes as it is (:func:`_unit`): median distances of a part's
points from the camera in this range, in scene units (metres: 12.5 cm to 64 m)."""


def _unit(points, weights):
    """1 when the median distance from the camera of the ``points`` with non-zero
    ``weights`` lies in :data:`UNIT_RANGE`, else the power of two nearest it: exact in
    floating point, so a scene in other units polishes in metre-like ones."""
    r = jnp.where(weights > 0, jnp.linalg.norm(points, axis=-1), jnp.nan)
    m = jnp.nanmedian(r)
    inside = ~jnp.isfinite(m) | ((m >= UNIT_RANGE[0]) & (m < UNIT_RANGE[1]))
    return jnp.where(inside, 1.0, jnp.exp2(jnp.round(jnp.log2(jnp.where(inside, 1.0, m))))).astype(points.dtype)


def _scaled(part: Part, factor) -> Part:
    """``part`` with its position and semi-axes times ``factor``."""
    v = part.to_vector()
    return Part.from_vector(jnp.concatenate([v[..., 0:3] * factor, v[..., 3:6], v[..., 6:9] * factor, v[..., 9:]], -1))


# Points and background rays per part in one fit: a fixed random subset beyond these
# fits 14 parameters about as well as all of them at half the cost (final E of the
# human, chair and castings with 512 points: 5 468, 6 253, 9 441 bits; with 1 024:
# 5 484, 6 253, 9 452).
_POINTS = 512


_RAYS = 256

POLISH_CALL_STEPS = 20
"""Levenberg-Marquardt steps per compiled call of :func:`polish_parts`: the search's
rounds of region growing and the refinement's moves take 20 each, so one program
serves both."""


RIGID = np.arange(14) < 11
"""``free`` for :func:`polish_part` that holds bend and taper (the last three of the
14 numbers) where they are: a fit without (or with fixed) deformations."""
RIGID.setflags(write=False)


@persistent_jit(static_argnames=("steps",))
def _polish_bucket(parts, points, weights, origins, directions, ray_weights, free, steps):
    def one(p, x, w, o, d, wr, f):
        return polish_part(p, x, w, rays=(o, d, wr), steps=steps, free=f)

    # One part after another (lax.map), not vmap: vmapping optimistix's while loop
    # traces and compiles 2.5x longer (17.9 s against 7.5 s on the CPU) and is no faster.
    return jax.lax.map(lambda args: one(*args), (parts, points, weights, origins, directions, ray_weights, free))


def _gather(weights: np.ndarray, size: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Per row of ``weights`` (n, m): the indices of up to ``size`` of its non-zero
    entries (a fixed random subset when there are more, drawn by the row alone: a part's
    fit does not depend on what shares its batch) and their weights, padded with index 0
    and weight 0."""
    index = np.zeros((len(weights), size), np.int64)
    out = np.zeros((len(weights), size), np.float32)
    for i, w in enumerate(weights):
        nz = np.flatnonzero(w)
        if len(nz) > size:
            nz = np.sort(np.random.default_rng((seed, len(nz))).choice(nz, size, replace=False))
        index[i, : len(nz)] = nz
        out[i, : len(nz)] = w[nz]
    return index, out


_POLISHED = RowMemo(16 << 20)
"""Polished part vectors by their inputs (see :class:`~sqparts._compile.RowMemo`)."""


def polish_parts(parts: Part, points, weights, steps: int, rays, ray_weights, free=None) -> Part:
    """Each part polished on its own points (non-zero ``weights[i]`` over ``points``,
    at most ``_POINTS`` of them) while missing its background rays (non-zero
    ``ray_weights[i]`` over ``rays`` = (origins, directions), at most ``_RAYS``), moving
    the numbers ``free[i]`` lets it (:func:`polish_part`; (n, 14) or (14,) bool, default all);
    ``PART_BUCKET`` parts and :data:`POLISH_CALL_STEPS` solver steps per compiled call, so
    one compilation serves any number of parts, any image and any ``steps`` (rounded up to
    a multiple of :data:`POLISH_CALL_STEPS`; each call starts the solver afresh from where
    the last one stopped). A part polished before on the same points and rays is looked
    up (:data:`_POLISHED`)."""
    vectors = part_vectors(parts)
    n = len(vectors)
    pi, pw = _gather(np.asarray(weights)[:n], _POINTS)
    ri, rw = _gather(np.asarray(ray_weights)[:n], _RAYS)
    x = np.asarray(points, np.float32)[pi]
    if len(rays[0]) == 0:  # no background in view: nothing to miss
        rays = (np.zeros((1, 3), np.float32), np.array([[0.0, 0.0, 1.0]], np.float32))
    o, d = (np.asarray(a, np.float32)[ri] for a in rays)
    free = np.ones(14, bool) if free is None else np.asarray(free, bool)
    free = np.broadcast_to(free if free.ndim == 1 else free[:n], (n, 14))
    calls = -(-steps // POLISH_CALL_STEPS)
    keys = [RowMemo.key(calls, vectors[i], x[i], pw[i], o[i], d[i], rw[i], free[i]) for i in range(n)]

    def polish(todo):
        def bucket(group):
            rows = np.asarray(todo)[group]
            row = pad_vectors(vectors[rows], PART_BUCKET)
            xs, pws, os_, ds, rws, fs = (pad_rows(a[rows], PART_BUCKET) for a in (x, pw, o, d, rw, free))
            ds[rws == 0] = (0.0, 0.0, 1.0)  # padding rays stay finite
            for _ in range(calls):  # host arrays in: one program for every call
                row = part_vectors(_polish_bucket(host_parts(row), xs, pws, os_, ds, rws, fs, steps=POLISH_CALL_STEPS))
            return row[: len(rows)]

        # Each part's fit does not depend on what shares its call: the parts are spread
        # evenly over the calls that run at once.
        return np.concatenate(concurrently(bucket, balanced_groups(len(todo), PART_BUCKET)))

    return host_parts(_POLISHED.rows(keys, vectors.copy(), polish))


# --- region growing over a whole image ------------------------------------------------


POLISH_SCALE = 0.05
"""Width of region growing's Cauchy weights, as a fraction of the part's largest
semi-axis (never below σ)."""


def once_per_image(fn):
    """Compute ``fn(data)`` once per prepared image (kept in the instance's ``__dict__``;
    :class:`RangeData` is frozen and its arrays are not hashable)."""

    @functools.wraps(fn)
    def wrapper(data):
        cache = data.__dict__.setdefault("_polish_cache", {})
        if fn.__name__ not in cache:
            cache[fn.__name__] = fn(data)
        return cache[fn.__name__]

    return wrapper


@once_per_image
def figure_points(data: RangeData):
    """Figure pixels' 3-D points (float32) and their flat indices (a fixed random 20 000
    of them when there are more)."""
    max_points, seed = 20000, 0
    idx = np.flatnonzero(data.figure_mask)
    if len(idx) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_points, replace=False))
    return data.camera.points(data.image).reshape(-1, 3)[idx].astype(np.float32), idx


@once_per_image
def background_rays(data: RangeData):
    """Rays through background pixels (no return, off the figure) within 3 pixels of the
    figure, where a part that swells past its silhouette shows first: (origins,
    directions), flat pixel indices. Rays with a return off the figure (another figure,
    an occluder) do not count: a part may hide behind them."""
    from scipy.ndimage import binary_dilation

    figure = data.figure_region
    idx = np.flatnonzero(binary_dilation(figure, iterations=3) & ~figure & ~np.isfinite(data.image))
    o, d = (np.asarray(a).reshape(-1, 3)[idx].astype(np.float32) for a in camera_rays(data.camera))
    return (o, d), idx


def rays_near(mask: np.ndarray, ray_index: np.ndarray, margin: int) -> np.ndarray:
    """1 for each background ray within ``margin`` pixels of ``mask`` (H, W), else 0; a
    stack of masks (n, H, W) gives (n, rays)."""
    from scipy.ndimage import binary_dilation, generate_binary_structure

    mask = np.asarray(mask, bool)
    cross = generate_binary_structure(2, 1)
    structure = cross if mask.ndim == 2 else np.stack([np.zeros_like(cross), cross, np.zeros_like(cross)])
    near = binary_dilation(mask, structure, iterations=margin)
    return near.reshape(*mask.shape[:-2], -1)[..., ray_index].astype(np.float32)


@persistent_jit
def _surface_distance(parts, points):
    return jax.vmap(lambda p: jax.vmap(lambda x: surface_distance(p, x))(points))(parts)


POINT_CHUNK = 2048
"""Points per compiled call of :func:`surface_distances`: one program for every image's
point count (fewer points a call pay more calls' overhead; more, more padding)."""


def surface_distances(parts: Part, points) -> np.ndarray:
    """(n, m) radial distance (:func:`~sqparts.surface_distance`) of every point to every
    part, ``PART_BUCKET`` parts and :data:`POINT_CHUNK` points per compiled call."""
    padded, n = pad_parts(parts)
    pts = np.asarray(points, np.float32)
    m = len(pts)
    pts = pad_rows(pts, max(1, -(-m // POINT_CHUNK)) * POINT_CHUNK)
    buckets, chunks = range(0, len(padded), PART_BUCKET), range(0, len(pts), POINT_CHUNK)
    out = iter(
        concurrently(
            lambda c: np.asarray(_surface_distance(padded[c[0] : c[0] + PART_BUCKET], pts[c[1] : c[1] + POINT_CHUNK])),
            [(k, j) for k in buckets for j in chunks],
        )
    )
    return np.block([[next(out) for _ in chunks] for _ in buckets])[:n, :m]


def polish_scale(parts: Part, sigma: float) -> np.ndarray:
    """(n,) width of each part's Cauchy weights: :data:`POLISH_SCALE` of its largest
    semi-axis, never below σ."""
    return np.maximum(POLISH_SCALE * np.asarray(parts.size).reshape(-1, 3).max(1), sigma).astype(np.float32)


def grow_parts(parts: Part, data: RangeData, seeds, *, rounds: int, steps: int, grow: int = 2) -> Part:
    """Polish a batch of parts by region growing over the image (an ICP), all parts
    together in each round.

    ``seeds`` (n, H, W) are the figure pixels each part starts from (e.g. those its
    hypothesis explains). The first round fits each part to its seed; each later one
    grows the support by ``grow`` pixels into neighbours within 3 scale of the part's
    surface (:func:`polish_scale`). Each round fits the support with Cauchy weights of
    width scale (:func:`polish_parts`, ``steps`` Levenberg-Marquardt steps) while the
    :func:`background_rays` within ``grow`` + 3 pixels of the support must miss the part.
    So a coarse hypothesis walks onto its whole visible surface without jumping to an
    occluder or a neighbouring part, or swelling past its silhouette; it may hide behind
    an occluder.
    """
    from scipy.ndimage import binary_dilation

    seeds = np.asarray(seeds, bool)
    n = len(parts)
    if seeds.shape != (n, data.camera.height, data.camera.width):
        raise ValueError(f"seeds: got shape {seeds.shape}, expected {(n, data.camera.height, data.camera.width)}")
    if n == 0 or rounds == 0:
        return parts
    pts, idx = figure_points(data)
    rays, ray_index = background_rays(data)
    scale = polish_scale(parts, data.encoding.sigma)[:, None]
    box = np.ones((1, 2 * grow + 1, 2 * grow + 1), bool)
    support = seeds.reshape(n, -1)[:, idx]
    vec = part_vectors(parts)
    for r in range(rounds):
        dist = np.abs(surface_distances(host_parts(vec), pts))
        image = np.zeros(seeds.shape, bool)
        image.reshape(n, -1)[:, idx] = support
        if r > 0:
            near = np.asarray(binary_dilation(image, box), bool).reshape(n, -1)[:, idx]
            support = near & (dist < 3 * scale)
            image[:] = False
            image.reshape(n, -1)[:, idx] = support
        weights = np.where(support, 1.0 / np.sqrt(1.0 + (dist / scale) ** 2), 0.0)
        ray_weights = rays_near(image, ray_index, grow + 3)
        vec = part_vectors(polish_parts(host_parts(vec), pts, weights, steps, rays, ray_weights))
    return host_parts(vec)
