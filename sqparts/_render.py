"""Differentiable ray casting of parts into range images (paper section 3.4, steps 1-2).

The kernel is :func:`cast_ray`: one ray against one part. The ray is moved into the
part's local frame, clipped to the deformed part's bounding box, and Newton's method is
run on the gauge ``g(t) = F(D^{-1}(o + t d))^(ε1/2) - 1`` from the box entry. For an
undeformed part ``g`` is a norm minus one, convex along the ray for ε <= 2, so Newton
from outside converges monotonically to the first hit; for bent and tapered parts (not
convex) the steps are safeguarded by a bracket and fall back to bisection. Inside the
loop ``g`` and its slope along the ray are computed in closed form, in log space (no
``jvp``, shared logarithms). The last Newton step is taken with gradients (earlier ones
under ``stop_gradient``): its custom JVP differentiates :func:`~sqparts._part.gauge`
itself, which gives exactly the implicit derivative ``dt/dθ = -(∂g/∂θ) / (∂g/∂t)`` at the
hit, while the forward pass reuses the loop's last value and slope.

``vmap`` is applied in one place per axis: over pixels in :func:`cast_part` (optionally
in tiles of rays, ``ray_batch_size``), over parts in :func:`cast_scene` and
:func:`cast_batch` (the latter chunked with ``jax.lax.map(..., batch_size=...)`` to bound
memory, and on CPUs casting each chunk's rays in cache-sized tiles, ``CPU_TILE``).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._camera import MAX_PIXELS, MAX_SIDE, Camera, _Camera
from ._part import Part, bounding_half_extent, gauge, matmul, rotation_matrix
from ._typing import Array, Bool, Float

DEFAULT_NEWTON_STEPS = 8
"""Newton steps for rendering: meets IoU >= 0.99 against meshes on near-tangent rays of
bent parts. The hypothesis search uses fewer (see ``sqparts._search``)."""
HIT_TOLERANCE = 1e-3
"""A ray hits when it found a point inside the part, or when the gauge at the final
Newton iterate is below this (relative units; catches grazing rays)."""
CPU_TILE = 8192
"""Rays x parts per vectorised pass of :func:`cast_batch` on CPUs (see there)."""


class _RayGauge(NamedTuple):
    """Per-part constants of :func:`_gauge_along_ray` (computed once, shared by every ray)."""

    inv_size: Array  # 1 / (a1, a2, a3)
    bend_x: Array  # bend[0] / a3
    bend_z: Array  # bend[1] / a1
    taper: Array  # taper / a3
    power_xy: Array  # 2 / ε2
    power_section: Array  # ε2 / ε1
    power_z: Array  # 2 / ε1
    power_gauge: Array  # ε1 / 2
    tiny: Array  # smallest normalised coordinate whose log is taken


def _ray_gauge(part: Part) -> _RayGauge:
    e1, e2 = part.squareness[0], part.squareness[1]
    a1, a3 = part.size[0], part.size[2]
    dtype = part.size.dtype
    return _RayGauge(
        inv_size=1.0 / part.size,
        bend_x=part.bend[0] / a3,
        bend_z=part.bend[1] / a1,
        taper=part.taper / a3,
        power_xy=2.0 / e2,
        power_section=e2 / e1,
        power_z=2.0 / e1,
        power_gauge=e1 / 2.0,
        tiny=jnp.asarray(np.sqrt(np.finfo(dtype).tiny), dtype),
    )


def _log_add(u, v):
    """``log(exp(u) + exp(v))`` and the weight ``exp(u) / (exp(u) + exp(v))``."""
    big = jnp.maximum(u, v)
    small_share = jnp.exp(-jnp.abs(u - v))
    total = 1.0 + small_share
    weight_big = 1.0 / total
    weight_u = jnp.where(u >= v, weight_big, small_share * weight_big)
    return big + jnp.log(total), weight_u


def _gauge_along_ray(k: _RayGauge, o, d, t):
    """Value and slope ``(g(t), g'(t))`` of the gauge of :func:`~sqparts._part.gauge` at
    ``o + t d`` (local frame), in closed form and in log space.

    With ``u = log|q / a|`` for the undeformed point ``q``: ``log A = log(e^(2 ux/ε2) +
    e^(2 uy/ε2))``, ``log F = log(e^(ε2/ε1 log A) + e^(2 uz/ε1))`` and ``g + 1 = e^(ε1/2 log F)``;
    each log-sum gives its weight, and ``g' = (g + 1) (w_A (w_x qx'/qx + w_y qy'/qy) + (1 - w_A)
    qz'/qz)`` (the exponents cancel: (ε1/2)(ε2/ε1)(2/ε2) = (ε1/2)(2/ε1) = 1). Forward only (no
    gradients are taken through it); 8 transcendental functions instead of 10, and no overflow
    far outside a boxy part.
    """
    x, y, z = o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]
    dx, dy, dz = d[0], d[1], d[2]
    # Undeform (see sqparts._part.undeform) with the derivative along the ray.
    z = z - k.bend_z * x * x
    dz = dz - 2.0 * k.bend_z * x * dx
    x = x - k.bend_x * z * z
    dx = dx - 2.0 * k.bend_x * z * dz
    scale = 1.0 + k.taper * z
    scale = jnp.where(jnp.abs(scale) < 1e-6, 1e-6, scale)
    inv_scale = 1.0 / scale
    dscale = k.taper * dz * inv_scale
    qx, qy, qz = x * inv_scale * k.inv_size[0], y * inv_scale * k.inv_size[1], z * k.inv_size[2]
    dqx = (dx * inv_scale * k.inv_size[0]) - qx * dscale
    dqy = (dy * inv_scale * k.inv_size[1]) - qy * dscale
    dqz = dz * k.inv_size[2]
    ax, ay, az = (jnp.maximum(jnp.abs(c), k.tiny) for c in (qx, qy, qz))
    log_a, wx = _log_add(k.power_xy * jnp.log(ax), k.power_xy * jnp.log(ay))
    log_f, w_section = _log_add(k.power_section * log_a, k.power_z * jnp.log(az))
    norm = jnp.exp(k.power_gauge * log_f)
    sx = jnp.where(qx < 0, -1.0, 1.0)
    sy = jnp.where(qy < 0, -1.0, 1.0)
    sz = jnp.where(qz < 0, -1.0, 1.0)
    rate = w_section * (wx * sx * dqx / ax + (1.0 - wx) * sy * dqy / ay) + (1.0 - w_section) * sz * dqz / az
    return norm - 1.0, norm * rate


@jax.custom_jvp
def _final_step(part, o, d, t, val, slope, take):
    """``t - g(t; θ) / g'(t)`` where ``take``, else ``t``: the final Newton step, whose
    derivative is the implicit one, ``-(∂g/∂θ) / g'`` (``t``, ``val`` and ``slope`` carry none)."""
    return jnp.where(take, t - val / jnp.where(take, slope, -1.0), t)


@_final_step.defjvp
def _final_step_jvp(primals, tangents):
    part, o, d, t, val, slope, take = primals
    dpart, do, dd = tangents[:3]
    # Where the step is not taken (a miss, or a grazing ray) the gauge is linearised at the
    # part's centre instead: reverse mode multiplies that branch by a zero cotangent, and at
    # a miss its partials can be infinite (F overflows far outside a boxy part): NaN.
    point = jnp.where(take, o + t * d, jnp.zeros_like(o))
    dpoint = jnp.where(take, do + t * dd, jnp.zeros_like(do))
    _, dval = jax.jvp(gauge, (part, point), (dpart, dpoint))
    return _final_step(*primals), jnp.where(take, -dval / jnp.where(take, slope, -1.0), 0.0)


def cast_ray(
    part: Part,
    origin: Float[Array, "3"],
    direction: Float[Array, "3"],
    newton_steps: int = DEFAULT_NEWTON_STEPS,
    *,
    unroll: bool = False,
) -> tuple[Float[Array, ""], Bool[Array, ""]]:
    """First intersection of one ray with one part.

    Returns ``(t, hit)``: the ray parameter of the first hit (0 where ``hit`` is False).
    ``t`` is differentiable in all 14 part parameters and in the ray. ``unroll``: the
    Newton loop unrolled, the same results; XLA then fuses its steps, at a cost in
    compile time (the grid search's pruning program on a 2-core CPU: 5.2 s instead of
    4.2 s) and, measured there, no gain in speed: the search does not unroll.
    """
    rot = rotation_matrix(part.orientation)
    o = matmul(rot.T, origin - part.position)
    d = matmul(rot.T, direction)
    return _cast_local_ray(part, o, d, newton_steps, unroll)


def _cast_local_ray(part: Part, o, d, newton_steps, unroll: bool):
    """:func:`cast_ray` for a ray already in the part's local frame."""
    half = bounding_half_extent(part)
    d_safe = jnp.where(jnp.abs(d) < 1e-12, 1e-12, d)
    t1 = (-half - o) / d_safe
    t2 = (half - o) / d_safe
    t_in = jnp.max(jnp.minimum(t1, t2))
    t_out = jnp.min(jnp.maximum(t1, t2))
    box_hit = (t_out > t_in) & (t_out > 0)
    t_start = jnp.maximum(t_in, 0.0)

    k = jax.lax.stop_gradient(_ray_gauge(part))
    o_sg, d_sg = jax.lax.stop_gradient((o, d))
    t_start_sg, t_out_sg = jax.lax.stop_gradient((t_start, t_out))

    def newton(carry, _):
        # Safeguarded Newton. [lo, hi] always holds the first crossing if there is one:
        # lo is outside and before it; hi is inside (bracketed) or past the gauge's
        # minimum along the ray. Steps that leave [lo, hi] become bisections, so a bent or
        # tapered part (not convex) cannot be jumped over. Near-tangent rays give a
        # near-double root where plain Newton only halves g per step; the ratio of
        # successive values estimates the root's multiplicity m = 1 / (1 - ratio) and
        # the step is stretched by m (clipped to [1, 3]).
        t, lo, hi, found, val_prev = carry
        val, slope = _gauge_along_ray(k, o_sg, d_sg, t)
        descending = slope < 0
        outside = val > 0
        lo = jnp.where(outside & (descending | found), t, lo)
        hi = jnp.where(~outside | (~found & ~descending), t, hi)
        found = found | ~outside
        ratio = jnp.clip(val / jnp.where(val_prev > 0, val_prev, jnp.inf), 0.0, 2.0 / 3.0)
        multiplicity = jnp.where(outside, 1.0 / (1.0 - ratio), 1.0)
        t_newton = t - multiplicity * val / jnp.where(descending, slope, -1.0)
        ok = descending & (t_newton >= lo) & (t_newton <= hi)
        t_next = jnp.where(ok, t_newton, 0.5 * (lo + hi))
        return (t_next, lo, hi, found, val), None

    init = (t_start_sg, t_start_sg, t_out_sg, jnp.zeros((), bool), jnp.zeros_like(t_start_sg))
    (t_sg, _, _, found, _), _ = jax.lax.scan(newton, init, None, length=max(newton_steps - 1, 0), unroll=unroll)
    val_sg, slope_sg = _gauge_along_ray(k, o_sg, d_sg, t_sg)
    hit = box_hit & (found | (val_sg < HIT_TOLERANCE)) & (t_sg > 0)
    step_sg = -val_sg / jnp.where(slope_sg < 0, slope_sg, -1.0)
    # At a tangent (grazing) point the slope is ~0 and the step explodes: keep the iterate.
    small = hit & (slope_sg < 0) & (jnp.abs(step_sg) <= 0.01 * (t_out_sg - t_start_sg))
    t = _final_step(part, o, d, t_sg, val_sg, slope_sg, small)
    hit = hit & (t > 0)
    return jnp.where(hit, t, 0.0), hit


def cast_part(
    part: Part,
    origins: Float[Array, "*pixels 3"],
    directions: Float[Array, "*pixels 3"],
    newton_steps: int = DEFAULT_NEWTON_STEPS,
    *,
    ray_batch_size: int | None = None,
    unroll: bool = False,
) -> tuple[Float[Array, "*pixels"], Bool[Array, "*pixels"]]:
    """One part against every ray (the pixel axis's one ``vmap``).

    With ``ray_batch_size`` the rays are cast that many at a time
    (``jax.lax.map(..., batch_size=ray_batch_size)``); the results are the same.
    ``unroll``: as :func:`cast_ray`'s.
    """
    if ray_batch_size is not None and (not isinstance(ray_batch_size, int) or ray_batch_size <= 0):
        raise ValueError(f"ray_batch_size: got {ray_batch_size!r}, expected a positive integer or None")
    shape = origins.shape[:-1]
    dtype = part.size.dtype
    o = origins.reshape(-1, 3).astype(dtype)
    d = directions.reshape(-1, 3).astype(dtype)
    if ray_batch_size is None or ray_batch_size >= o.shape[0]:
        t, hit = jax.vmap(lambda oi, di: cast_ray(part, oi, di, newton_steps, unroll=unroll))(o, d)
    else:
        t, hit = jax.lax.map(
            lambda od: cast_ray(part, od[0], od[1], newton_steps, unroll=unroll), (o, d), batch_size=ray_batch_size
        )
    return t.reshape(shape), hit.reshape(shape)


def cast_scene(
    parts: Part,
    origins: Float[Array, "*pixels 3"],
    directions: Float[Array, "*pixels 3"],
    newton_steps: int = DEFAULT_NEWTON_STEPS,
) -> tuple[Float[Array, "*pixels"], Bool[Array, "*pixels"], Array]:
    """Boolean union of a batch of parts: the nearest hit wins (occlusion).

    Returns ``(t, hit, index)`` where ``index`` is the visible part per pixel (-1 = none).
    """
    t, hit = jax.vmap(cast_part, in_axes=(0, None, None, None))(parts, origins, directions, newton_steps)
    t_masked = jnp.where(hit, t, jnp.inf)
    index = jnp.argmin(t_masked, axis=0)
    any_hit = jnp.any(hit, axis=0)
    t_near = jnp.take_along_axis(t, index[None], axis=0)[0]
    return jnp.where(any_hit, t_near, 0.0), any_hit, jnp.where(any_hit, index, -1)


def cast_batch(
    parts: Part,
    origins: Float[Array, "*pixels 3"],
    directions: Float[Array, "*pixels 3"],
    *,
    batch_size: int = 64,
    newton_steps: int = DEFAULT_NEWTON_STEPS,
) -> tuple[Float[Array, " n *pixels"], Bool[Array, " n *pixels"]]:
    """Each part of a batch rendered alone, in chunks of ``batch_size`` parts.

    On CPUs the rays of a chunk are cast in tiles of ``CPU_TILE // batch_size`` rays (at
    least one; ``batch_size`` capped at the number of parts): XLA:CPU runs the Newton loop as a chain of element-wise passes, each
    writing one array of rays x parts, and arrays of ``CPU_TILE`` elements stay in cache.
    Other backends want every ray at once and get no tiles.
    """
    ray_batch_size = None
    if jax.default_backend() == "cpu":
        ray_batch_size = max(1, CPU_TILE // min(batch_size, parts.size.shape[0]))
    return jax.lax.map(
        lambda p: cast_part(p, origins, directions, newton_steps, ray_batch_size=ray_batch_size),
        parts,
        batch_size=batch_size,
    )


MIN_NEWTON_STEPS = 5
"""Fewest Newton steps a rendering may use: with 4 or fewer, rays of deformed parts are
left unconverged (IoU 0.86 at 4 steps, 0.77 at 3, 0 at 1, measured against 24 steps)."""
MAX_NEWTON_STEPS = 64


def _check_window(window) -> tuple[jax.Array, tuple[int, int]]:
    """(corner, (rows, cols)) of a ``window`` (row0, col0, rows, cols): integers, at
    least one row and column, and no more pixels than a camera may have (the window's
    rays are allocated)."""
    values = list(window) if isinstance(window, (tuple, list, np.ndarray)) else []
    ok = len(values) == 4 and all(
        not isinstance(v, bool) and isinstance(v, (int, np.integer)) and abs(int(v)) <= MAX_SIDE for v in values
    )
    rows, cols = (int(values[2]), int(values[3])) if ok else (0, 0)
    if min(rows, cols) < 1 or rows * cols > MAX_PIXELS:
        raise ValueError(
            f"window: got {window!r:.80}, expected (row0, col0, rows, cols): integers with rows, cols >= 1, "
            f"at most {MAX_SIDE} each and {MAX_PIXELS} pixels"
        )
    return jnp.asarray(values[:2], jnp.float32), (rows, cols)


def _check_newton_steps(newton_steps) -> int:
    if (
        isinstance(newton_steps, bool)
        or not isinstance(newton_steps, (int, np.integer))
        or not (MIN_NEWTON_STEPS <= newton_steps <= MAX_NEWTON_STEPS)
    ):
        raise ValueError(
            f"newton_steps: got {newton_steps!r}, expected an integer in [{MIN_NEWTON_STEPS}, {MAX_NEWTON_STEPS}]"
        )
    return int(newton_steps)


def _check_camera(camera) -> None:
    if not isinstance(camera, _Camera):
        raise TypeError(
            f"camera: got {type(camera).__name__}, expected a PinholeCamera, OrthographicCamera or ScannerCamera"
        )


def _as_scene(parts) -> Part:
    if not isinstance(parts, Part):
        raise TypeError(f"parts: got {type(parts).__name__}, expected a Part (single or batched)")
    if parts.batch_shape == ():
        return jax.tree_util.tree_map(lambda x: x[None], parts)
    if len(parts.batch_shape) != 1:
        raise ValueError(f"parts: got batch shape {parts.batch_shape}, expected one batch axis")
    if parts.batch_shape[0] == 0:
        raise ValueError("parts: got 0 parts, expected at least one")
    return parts


@functools.partial(jax.jit, static_argnames=("window_shape", "newton_steps"))
def _render_scene(parts, camera, corner, window_shape, newton_steps):
    origins, directions = camera.rays((corner[0], corner[1], *window_shape))
    t, hit, index = cast_scene(parts, origins, directions, newton_steps)
    return jnp.where(hit, t, jnp.nan).astype(jnp.float32), index


def render_range_image(
    parts: Part,
    camera: Camera,
    *,
    window: tuple[int, int, int, int] | None = None,
    newton_steps: int = DEFAULT_NEWTON_STEPS,
    return_labels: bool = False,
):
    """Render a part or a scene (batched :class:`Part`) into a float32 range image.

    Parameters
    ----------
    parts : Part
        One part, or a batch (leading axis) combined by Boolean union.
    camera : PinholeCamera | OrthographicCamera | ScannerCamera
        Gives one ray per pixel; the image stores z-depth (range for a scanner).
    window : (row0, col0, rows, cols), optional
        Render only this window; compiled once per (rows, cols).
    return_labels : bool
        Also return the int32 index of the visible part per pixel (-1 where none).

    Returns
    -------
    depth : float32 array, shape (height, width) or (rows, cols); NaN where no return.
    """
    _check_camera(camera)
    newton_steps = _check_newton_steps(newton_steps)
    scene = _as_scene(parts)
    if window is None:
        corner, shape = np.zeros(2, np.float32), (camera.height, camera.width)
    else:
        corner, shape = _check_window(window)
        row0, col0 = (int(v) for v in window[:2])
        if row0 < 0 or col0 < 0 or row0 + shape[0] > camera.height or col0 + shape[1] > camera.width:
            raise ValueError(
                f"window: got {tuple(int(v) for v in window)}, expected (row0, col0, rows, cols) inside the "
                f"{camera.width}x{camera.height} image (camera.cropped's rule)"
            )
    depth, labels = _render_scene(scene, camera.compiled(), corner, shape, newton_steps)
    return (depth, labels.astype(jnp.int32)) if return_labels else depth


@functools.partial(jax.jit, static_argnames=("shape", "batch_size", "newton_steps"))
def _render_batch(parts, camera, shape, batch_size, newton_steps):
    origins, directions = camera.rays((0, 0, *shape))
    t, hit = cast_batch(parts, origins, directions, batch_size=batch_size, newton_steps=newton_steps)
    return jnp.where(hit, t, jnp.nan).astype(jnp.float32)


def render_each(
    parts: Part,
    camera: Camera,
    *,
    batch_size: int = 64,
    newton_steps: int = DEFAULT_NEWTON_STEPS,
) -> Float[Array, "n h w"]:
    """Render every part of a batch on its own (no occlusion), chunked by ``batch_size``."""
    _check_camera(camera)
    newton_steps = _check_newton_steps(newton_steps)
    scene = _as_scene(parts)
    if not isinstance(batch_size, int) or batch_size <= 0:
        raise ValueError(f"batch_size: got {batch_size!r}, expected a positive integer")
    return _render_batch(scene, camera.compiled(), (camera.height, camera.width), batch_size, newton_steps)


def depth_to_numpy(depth) -> np.ndarray:
    """float32 numpy copy of a range image (NaN = no return)."""
    return np.asarray(depth, dtype=np.float32)
