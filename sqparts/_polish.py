"""Polishing: optimistix Levenberg-Marquardt on the radial distances of measured points
from a part's surface (footnote 6), while rays off the figure must miss the part.

:func:`polish_part` fits one part; :func:`grow_polish` grows a hypothesis's support
over its window by rounds of it (the search's polish); :func:`polish_parts` fits a
batch of parts, each on its own points, ``PART_BUCKET`` parts per compiled call (the
refinement's moves).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from ._compile import concurrently, persistent_jit
from ._encoding import PART_BUCKET, host_parts, pad_parts, part_vectors
from ._part import Part, from_unconstrained, matmul, rotation_matrix, surface_distance, to_local, to_unconstrained
from ._typing import ArrayLike, Float


def ray_penetration(part: Part, origin, direction, far: Float[ArrayLike, ""] = jnp.inf):
    """Signed radial distance (:func:`~sqparts.surface_distance`) of the ray's point
    deepest inside the part's ellipsoid of semi-axes ``size``, among the points
    ``origin + t direction`` with t <= ``far`` (the free segment in front of a return):
    negative when the ray enters the part there (exact for ellipsoids, a smooth proxy
    for the rest)."""
    o = to_local(part, origin) / part.size
    d = matmul(rotation_matrix(part.orientation).T, direction) / part.size
    t = jnp.minimum(-matmul(o, d) / matmul(d, d), far)
    return surface_distance(part, origin + t * direction)


# The damped Gauss-Newton step through the normal equations (lineax >= 0.1's Normal: a
# 14x14 Cholesky) instead of optimistix's default QR of the stacked (residuals + 14) x 14
# Jacobian. The normal equations square the condition number, but the damping and the
# prior below keep them well-posed; the steps agree to 1e-7 and a bucket of 8 parts
# polishes in 79 ms instead of 112 ms on the CPU (human recovery warm: 8.3 -> 6.5 s).
_LM = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-8, linear_solver=lx.Normal(lx.Cholesky()))


def polish_part(part: Part, points, weights, *, rays=None, steps: int = 20) -> Part:
    """Levenberg-Marquardt (optimistix) on the weighted radial distances
    (:func:`~sqparts.surface_distance`) of ``points`` from the part's surface.

    ``rays`` = (origins, directions, weights[, far]), optional: rays off the figure,
    which the part must miss (up to ``far``, default: the whole ray); each adds its
    weighted penetration (:func:`ray_penetration`) so the part cannot swell past the
    silhouette while hugging the visible points.
    Runs a fixed number of steps and never raises; returns the input if the solve produced
    non-finite values or the weights cover fewer than 8 points.
    """
    u0 = to_unconstrained(part)
    w = weights.astype(u0.dtype)

    def residuals(u, _):
        p = from_unconstrained(u)
        r = w * jax.vmap(lambda x: surface_distance(p, x))(points)
        if rays is not None:
            o, d, wr, *far = rays
            far = far[0] if far else jnp.full(wr.shape, jnp.inf, wr.dtype)
            pen = jax.vmap(ray_penetration, in_axes=(None, 0, 0, 0))(p, o, d, far)
            r = jnp.concatenate([r, wr * jnp.minimum(pen, 0.0)])
        # A weak prior on the 14 numbers keeps unobserved ones near their start.
        return r, 1e-3 * (u - u0)

    sol = optx.least_squares(residuals, _LM, u0, max_steps=steps, throw=False)
    ok = jnp.all(jnp.isfinite(sol.value)) & (jnp.sum(w > 0) >= 8)
    return from_unconstrained(jnp.where(ok, sol.value, u0))


def grow_polish(
    part: Part, origins, directions, depth, figure, seed, *, scale, rounds: int, steps: int, grow: int = 2
) -> Part:
    """Polish a hypothesis on a window of the image by region growing (an ICP).

    ``origins``, ``directions`` (H, W, 3) are the window's rays, ``depth`` (H, W) its
    measured depth (NaN: no return), ``figure`` (H, W) its figure pixels and ``seed`` (H, W)
    the pixels the hypothesis explains. Each round grows the support by ``grow`` pixels
    into neighbours within ``3 scale`` of the surface and fits the support with Cauchy
    weights of width ``scale`` (:func:`polish_part`), while rays off the figure must miss
    the part in front of their return (all along when there is none: a part may hide
    behind an occluding figure). So a coarse hypothesis walks onto its whole visible
    surface without jumping to an occluder or a neighbouring part, or swelling past its
    silhouette.
    """
    valid = figure & jnp.isfinite(depth)
    flat = (origins + jnp.where(valid, depth, 0.0)[..., None] * directions).reshape(-1, 3)
    # Every other off-figure ray is enough to keep the part inside its silhouette.
    r = slice(0, None, 2)
    far = jnp.where(jnp.isfinite(depth[r, r]), depth[r, r] - scale, jnp.inf).reshape(-1)
    rays = (
        origins[r, r].reshape(-1, 3),
        directions[r, r].reshape(-1, 3),
        (~figure[r, r]).reshape(-1).astype(flat.dtype),
        far,
    )
    size = 2 * grow + 1

    def one_round(carry, first):
        p, support = carry
        d = jnp.abs(jax.vmap(lambda x: surface_distance(p, x))(flat)).reshape(valid.shape)
        grown = jax.lax.reduce_window(support.astype(jnp.float32), 0.0, jax.lax.max, (size, size), (1, 1), "SAME") > 0
        support = jnp.where(first, support & valid, grown & valid & (d < 3 * scale))
        w = jnp.where(support, jax.lax.rsqrt(1 + (d / scale) ** 2), 0.0)
        return (polish_part(p, flat, w.reshape(-1), rays=rays, steps=steps), support), None

    first = jnp.arange(rounds) == 0
    (part, _), _ = jax.lax.scan(one_round, (part, seed), first)
    return part


# Points and background rays per part in one fit: a fixed random subset beyond these
# fits 14 parameters about as well as all of them at half the cost (final E of the
# human, chair and castings with 512 points: 5 468, 6 253, 9 441 bits; with 1 024:
# 5 484, 6 253, 9 452).
_POINTS = 512


_RAYS = 256


@persistent_jit(static_argnames=("steps",))
def _polish_bucket(parts, points, weights, origins, directions, ray_weights, steps):
    def one(p, x, w, o, d, wr):
        return polish_part(p, x, w, rays=(o, d, wr), steps=steps)

    # One part after another (lax.map), not vmap: vmapping optimistix's while loop
    # traces and compiles 2.5x longer (17.9 s against 7.5 s on the CPU) and is no faster.
    return jax.lax.map(lambda args: one(*args), (parts, points, weights, origins, directions, ray_weights))


def _gather(weights: np.ndarray, size: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Per row of ``weights`` (n, m): the indices of up to ``size`` of its non-zero
    entries (a fixed random subset when there are more) and their weights, padded with
    index 0 and weight 0."""
    rng = np.random.default_rng(seed)
    index = np.zeros((len(weights), size), np.int64)
    out = np.zeros((len(weights), size), np.float32)
    for i, w in enumerate(weights):
        nz = np.flatnonzero(w)
        if len(nz) > size:
            nz = np.sort(rng.choice(nz, size, replace=False))
        index[i, : len(nz)] = nz
        out[i, : len(nz)] = w[nz]
    return index, out


def polish_parts(parts: Part, points, weights, steps: int, rays, ray_weights) -> Part:
    """Each part polished on its own points (non-zero ``weights[i]`` over ``points``,
    at most ``_POINTS`` of them) while missing its background rays (non-zero
    ``ray_weights[i]`` over ``rays`` = (origins, directions), at most ``_RAYS``);
    ``PART_BUCKET`` parts per compiled call, so one compilation serves any number of parts
    and any image."""
    padded, n = pad_parts(parts)
    m = len(padded)
    pi, pw = _gather(np.asarray(weights)[:n], _POINTS)
    ri, rw = _gather(np.asarray(ray_weights)[:n], _RAYS)
    pi, pw, ri, rw = (np.concatenate([a, np.zeros((m - n,) + a.shape[1:], a.dtype)]) for a in (pi, pw, ri, rw))
    x = np.asarray(points, np.float32)[pi]
    if len(rays[0]) == 0:  # no background in view: nothing to miss
        rays = (np.zeros((1, 3), np.float32), np.array([[0.0, 0.0, 1.0]], np.float32))
    o, d = (np.asarray(a, np.float32)[ri] for a in rays)
    d[rw == 0] = (0.0, 0.0, 1.0)  # padding rays stay finite

    def bucket(k):
        return part_vectors(
            _polish_bucket(
                padded[k : k + PART_BUCKET], *(a[k : k + PART_BUCKET] for a in (x, pw, o, d, rw)), steps=steps
            )
        )

    return host_parts(np.concatenate(concurrently(bucket, range(0, m, PART_BUCKET)))[:n])


def pad_rows(a: np.ndarray, m: int) -> np.ndarray:
    return np.concatenate([a, np.zeros((m - len(a),) + a.shape[1:], a.dtype)])
