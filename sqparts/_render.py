"""Differentiable ray casting of parts into range images (paper section 3.4, steps 1-2).

The kernel is :func:`cast_ray`: one ray against one part. The ray is moved into the
part's local frame, clipped to the deformed part's bounding box, and Newton's method is
run on the gauge ``g(t) = F(D^{-1}(o + t d))^(ε1/2) - 1`` from the box entry. For an
undeformed part ``g`` is a norm minus one, convex along the ray for ε <= 2, so Newton
from outside converges monotonically to the first hit; for bent and tapered parts (not
convex) the steps are safeguarded by a bracket and fall back to bisection. The last Newton step is taken
with gradients (earlier ones under ``stop_gradient``), which gives exactly the implicit
derivative ``dt/dθ = -(∂g/∂θ) / (∂g/∂t)`` at the hit.

``vmap`` is applied in one place per axis: over pixels in :func:`cast_part`, over parts
in :func:`cast_scene` and :func:`cast_batch` (the latter chunked with
``jax.lax.map(..., batch_size=...)`` to bound memory).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ._camera import Camera, _Camera
from ._part import Part, bounding_half_extent, gauge, matmul, rotation_matrix
from ._typing import Array, Bool, Float

DEFAULT_NEWTON_STEPS = 8
"""Newton steps for rendering: meets IoU >= 0.99 against meshes on near-tangent rays of
bent parts. The hypothesis search uses fewer (see ``sqparts._search``)."""
HIT_TOLERANCE = 1e-3
"""A ray hits when it found a point inside the part, or when the gauge at the final
Newton iterate is below this (relative units; catches grazing rays)."""


def cast_ray(
    part: Part,
    origin: Float[Array, "3"],
    direction: Float[Array, "3"],
    newton_steps: int = DEFAULT_NEWTON_STEPS,
) -> tuple[Float[Array, ""], Bool[Array, ""]]:
    """First intersection of one ray with one part.

    Returns ``(t, hit)``: the ray parameter of the first hit (0 where ``hit`` is False).
    ``t`` is differentiable in all 14 part parameters and in the ray.
    """
    rot = rotation_matrix(part.orientation)
    o = matmul(rot.T, origin - part.position)
    d = matmul(rot.T, direction)
    half = bounding_half_extent(part)
    d_safe = jnp.where(jnp.abs(d) < 1e-12, 1e-12, d)
    t1 = (-half - o) / d_safe
    t2 = (half - o) / d_safe
    t_in = jnp.max(jnp.minimum(t1, t2))
    t_out = jnp.min(jnp.maximum(t1, t2))
    box_hit = (t_out > t_in) & (t_out > 0)
    t_start = jnp.maximum(t_in, 0.0)

    part_sg, o_sg, d_sg = jax.lax.stop_gradient((part, o, d))
    t_start_sg, t_out_sg = jax.lax.stop_gradient((t_start, t_out))

    def g_and_slope(t, prt, oo, dd):
        return jax.jvp(lambda s: gauge(prt, oo + s * dd), (t,), (jnp.ones_like(t),))

    def newton(carry, _):
        # Safeguarded Newton. [lo, hi] always holds the first crossing if there is one:
        # lo is outside and before it; hi is inside (bracketed) or past the gauge's
        # minimum along the ray. Steps that leave [lo, hi] become bisections, so a bent or
        # tapered part (not convex) cannot be jumped over. Near-tangent rays give a
        # near-double root where plain Newton only halves g per step; the ratio of
        # successive values estimates the root's multiplicity m = 1 / (1 - ratio) and
        # the step is stretched by m (clipped to [1, 3]).
        t, lo, hi, found, val_prev = carry
        val, slope = g_and_slope(t, part_sg, o_sg, d_sg)
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
    (t_sg, _, _, found, _), _ = jax.lax.scan(newton, init, None, length=max(newton_steps - 1, 0))
    t_sg = jax.lax.stop_gradient(t_sg)
    val_sg, slope_sg = g_and_slope(t_sg, part_sg, o_sg, d_sg)
    hit = box_hit & (found | (val_sg < HIT_TOLERANCE)) & (t_sg > 0)
    step_sg = -val_sg / jnp.where(slope_sg < 0, slope_sg, -1.0)
    # At a tangent (grazing) point the slope is ~0 and the step explodes: keep the iterate.
    small = hit & (slope_sg < 0) & (jnp.abs(step_sg) <= 0.01 * (t_out_sg - t_start_sg))
    # The final step carries the gradient: t = t* - g(t*; θ) / g'(t*), where g is taken
    # with gradients and g' is not (no second derivatives). Where the step is not taken
    # (a miss, or a grazing ray), g is evaluated at the part's centre instead: reverse
    # mode multiplies the untaken branch's partials by a zero cotangent, and at a miss
    # they can be infinite (F overflows far outside a boxy part), which gives NaN.
    point = jnp.where(small, o + t_sg * d, jnp.zeros_like(o))
    val = gauge(part, point)
    step = -val / jnp.where(small, slope_sg, -1.0)
    t = jnp.where(small, t_sg + step, t_sg)
    hit = hit & (t > 0)
    return jnp.where(hit, t, 0.0), hit


def cast_part(
    part: Part,
    origins: Float[Array, "*pixels 3"],
    directions: Float[Array, "*pixels 3"],
    newton_steps: int = DEFAULT_NEWTON_STEPS,
) -> tuple[Float[Array, "*pixels"], Bool[Array, "*pixels"]]:
    """One part against every ray (the pixel axis's one ``vmap``)."""
    shape = origins.shape[:-1]
    dtype = part.size.dtype
    o = origins.reshape(-1, 3).astype(dtype)
    d = directions.reshape(-1, 3).astype(dtype)
    t, hit = jax.vmap(cast_ray, in_axes=(None, 0, 0, None))(part, o, d, newton_steps)
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
    t, hit = jax.vmap(cast_part, in_axes=(0, None, None, None))(
        parts, origins, directions, newton_steps
    )
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
) -> tuple[Float[Array, "n *pixels"], Bool[Array, "n *pixels"]]:
    """Each part of a batch rendered alone, in chunks of ``batch_size`` parts."""
    return jax.lax.map(
        lambda p: cast_part(p, origins, directions, newton_steps), parts, batch_size=batch_size
    )


MIN_NEWTON_STEPS = 5
"""Fewest Newton steps a rendering may use: with 4 or fewer, rays of deformed parts are
left unconverged (IoU 0.86 at 4 steps, 0.77 at 3, 0 at 1, measured against 24 steps)."""
MAX_NEWTON_STEPS = 64


def _check_newton_steps(newton_steps) -> int:
    if isinstance(newton_steps, bool) or not isinstance(newton_steps, (int, np.integer)) or not (
        MIN_NEWTON_STEPS <= newton_steps <= MAX_NEWTON_STEPS
    ):
        raise ValueError(
            f"newton_steps: got {newton_steps!r}, expected an integer in [{MIN_NEWTON_STEPS}, {MAX_NEWTON_STEPS}]"
        )
    return int(newton_steps)


def _check_camera(camera) -> None:
    if not isinstance(camera, _Camera):
        raise TypeError(
            f"camera: got {type(camera).__name__}, expected a PinholeCamera, OrthographicCamera "
            "or ScannerCamera"
        )


def _as_scene(parts) -> Part:
    if not isinstance(parts, Part):
        raise TypeError(f"parts: got {type(parts).__name__}, expected a Part (single or batched)")
    if parts.batch_shape == ():
        return jax.tree_util.tree_map(lambda x: x[None], parts)
    if len(parts.batch_shape) != 1:
        raise ValueError(f"parts: got batch shape {parts.batch_shape}, expected one batch axis")
    return parts


@functools.partial(jax.jit, static_argnames=("camera", "window_shape", "newton_steps"))
def _render_scene(parts, camera, corner, window_shape, newton_steps):
    window = None if window_shape is None else (corner[0], corner[1], *window_shape)
    origins, directions = camera.rays(window)
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
        corner, shape = jnp.zeros(2, jnp.float32), None
    else:
        if len(window) != 4:
            raise ValueError(f"window: got {window!r}, expected (row0, col0, rows, cols)")
        corner = jnp.asarray(window[:2], jnp.float32)
        shape = (int(window[2]), int(window[3]))
    depth, labels = _render_scene(scene, camera, corner, shape, newton_steps)
    return (depth, labels.astype(jnp.int32)) if return_labels else depth


@functools.partial(jax.jit, static_argnames=("camera", "batch_size", "newton_steps"))
def _render_batch(parts, camera, batch_size, newton_steps):
    origins, directions = camera.rays()
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
    return _render_batch(scene, camera, batch_size, newton_steps)


def depth_to_numpy(depth) -> np.ndarray:
    """float32 numpy copy of a range image (NaN = no return)."""
    return np.asarray(depth, dtype=np.float32)
