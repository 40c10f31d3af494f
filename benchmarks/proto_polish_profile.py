"""Where one Levenberg-Marquardt polish spends its time (prototype, session 38; see
benchmarks/README.md, "Session 38: where polishing's time goes").

Eight parts of the built-in human, started 2 cm and 15% off and fitted to 512 noisy
points of their own surfaces (and 256 background rays of weight 0, as a part with no
background in view gets), exactly as ``_polish_bucket`` fits them. Prints, in one
process, medians over repeated calls: the residuals and their Jacobian (forward mode, as
optimistix's solver takes it) inside a loop of 10 (so no dispatch is counted), the solve
for 1 / 5 / 20 / 40 steps, a bucket of 8 parts by ``lax.map`` (the package) and by
``vmap``, and, from a human recovery, how full the polishing rows are.

    JAX_PLATFORMS=cpu python benchmarks/proto_polish_profile.py
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from _common import time_call

import sqparts
from sqparts._encoding import host_parts, part_vectors
from sqparts._part import Part, from_unconstrained, surface_distance, surface_point, to_unconstrained
from sqparts._polish import _POINTS, _RAYS, _levenberg_marquardt, polish_part, ray_penetration


def median_ms(fn, *args, repeats: int = 30) -> float:
    return 1e3 * time_call(fn, *args, repeats=repeats)[1]


def inputs():
    rng = np.random.default_rng(0)
    truth = part_vectors(sqparts.builtin_scene("human").parts)[:8]
    points = []
    for v in truth:
        p = Part.from_vector(jnp.asarray(v))
        eta, omega = rng.uniform(-1.5, 1.5, _POINTS), rng.uniform(-3.1, 3.1, _POINTS)
        x = np.asarray(jax.vmap(lambda e, o, p=p: surface_point(p, e, o))(eta, omega))
        points.append(x + rng.normal(0.0, 0.003, x.shape))
    start = truth.copy()
    start[:, :3] += rng.normal(0.0, 0.02, (8, 3))
    start[:, 6:9] *= 1.15
    weights = np.ones((8, _POINTS), np.float32)
    origins = np.zeros((8, _RAYS, 3), np.float32)
    directions = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (8, _RAYS, 1))
    return start, np.asarray(points, np.float32), weights, origins, directions, np.zeros((8, _RAYS), np.float32)


def main():
    start, points, weights, origins, directions, ray_weights = inputs()
    u0 = to_unconstrained(Part.from_vector(jnp.asarray(start[0])))
    x, o, d = jnp.asarray(points[0]), jnp.asarray(origins[0]), jnp.asarray(directions[0])

    def residuals(u):
        p = from_unconstrained(u)
        r = jax.vmap(lambda q: surface_distance(p, q))(x)
        pen = jax.vmap(ray_penetration, in_axes=(None, 0, 0, None))(p, o, d, jnp.inf)
        return jnp.concatenate([r, pen])

    def ten(step):  # ten evaluations in one compiled loop: no dispatch counted
        return jax.jit(lambda u: jax.lax.fori_loop(0, 10, lambda i, v: v + 1e-9 * step(v), u))

    print(
        f"residuals ({_POINTS} points + {_RAYS} rays), one part: {median_ms(ten(lambda v: residuals(v).sum()), u0) / 10:.3f} ms"
    )
    jac = ten(lambda v: jax.jacfwd(residuals)(v).sum(0))
    print(f"their 768 x 14 Jacobian (jacfwd), one part: {median_ms(jac, u0) / 10:.3f} ms")

    def r2(u, _):
        return residuals(u), 1e-3 * (u - u0)

    import optimistix as optx

    for steps in (1, 5, 20, 40):
        solve = jax.jit(
            lambda u, s=steps: optx.least_squares(r2, _levenberg_marquardt(), u, max_steps=s, throw=False).value
        )
        print(f"Levenberg-Marquardt, {steps:2d} steps, one part: {median_ms(solve, u0, repeats=20):.2f} ms")

    def one(p, xs, w, os_, ds, wr):
        return polish_part(p, xs, w, rays=(os_, ds, wr), steps=20)

    args = (host_parts(start), points, weights, origins, directions, ray_weights)
    for label, fn in (
        ("lax.map (the package)", jax.jit(lambda *a: jax.lax.map(lambda b: one(*b), a))),
        ("vmap", jax.jit(jax.vmap(one))),
    ):
        first, median, _ = time_call(fn, *args, repeats=7)
        print(f"bucket of 8 parts, 20 steps, {label}: {1e3 * median:.1f} ms (first call {first:.1f} s)")

    import sqparts._polish as P

    filled = {"points": [], "rays": []}
    gather = P._gather

    def counting(w, size, seed=0):
        index, out = gather(w, size, seed)
        filled["points" if size == _POINTS else "rays"] += (out > 0).sum(1).tolist()
        return index, out

    P._gather = counting
    scene = sqparts.builtin_scene("human")
    sqparts.recover(np.asarray(sqparts.render_range_image(scene.parts, scene.camera)), scene.camera)
    P._gather = gather
    for k, size in (("points", _POINTS), ("rays", _RAYS)):
        a = np.asarray(filled[k])
        q = np.quantile(a, [0.1, 0.5, 0.9])
        print(f"human recovery, {len(a)} polished rows: {k} with weight, of {size}: mean {a.mean():.0f}, 10/50/90% {q}")


if __name__ == "__main__":
    main()
