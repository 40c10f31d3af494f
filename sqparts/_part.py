"""The 14-parameter part: a deformed superquadric (paper section 2.1, Eq. 1, footnote 4).

Conventions
-----------
A part lives in its own *local* frame: the superquadric of Eq. (1) is centred at the
origin with semi-axes ``size = (a1, a2, a3)`` along local x, y and z. Local z is the axis
that tapering and the main bend act on; by convention it is the longest axis (footnote 4),
but this is not enforced so that any shape can be written.

The 14 numbers (footnote 4), in the order of :meth:`Part.to_vector`:

====================  =====  ===================================================
field                 count  meaning
====================  =====  ===================================================
``position``          3      local origin in camera coordinates (metres, or the
                             unit of the range image)
``orientation``       3      rotation vector (axis * angle, radians) of the matrix
                             R taking local to camera coordinates: p_cam = R p + c
``size``              3      semi-axes a1, a2, a3 > 0, same unit as position
``squareness``        2      ε1 (along z / latitude), ε2 (in the x-y section);
                             1 = round, 0.1 = box-like, 2 = diamond-like
``bend``              2      dimensionless. ``bend[0]`` bends the longest (z) axis
                             toward +x: x += bend[0] * z**2 / a3 (tip deflection
                             bend[0] * a3). ``bend[1]`` bends the x axis toward
                             +z: z += bend[1] * x**2 / a1 (tip deflection
                             bend[1] * a1). Range [-1, 1]; 0 = straight.
``taper``             1      dimensionless, along the longest (z) axis: x and y are
                             scaled by (1 + taper * z / a3). Range [-1, 1]; positive
                             widens the +z end.
====================  =====  ===================================================

The deformation maps undeformed local points ``q`` to deformed local points ``p`` by
taper, then ``bend[0]``, then ``bend[1]``; each step is exactly invertible, so the
inside-outside function of the deformed part is ``F(D^{-1}(p))`` in closed form
(footnote 6: it remains the distance measure).
"""

from __future__ import annotations

from typing import Any, cast

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np

from ._typing import Array, ArrayLike, Float

SQUARENESS_RANGE = (0.1, 2.0)
"""Allowed range of ε1 and ε2 (inclusive)."""
BEND_RANGE = (-1.0, 1.0)
"""Allowed range of each bend coefficient (inclusive)."""
TAPER_RANGE = (-1.0, 1.0)
"""Allowed range of the taper coefficient (inclusive)."""

_TINY = 1e-30


def abs_pow(x: ArrayLike, p: ArrayLike) -> Array:
    """``|x| ** p`` written as ``exp(p log|x|)``, NaN-safe (value and gradient) at 0.

    XLA:CPU compiles ``pow`` to a slow scalar call and its gradient is NaN at 0; this is
    vectorised and returns 0 with gradient 0 where ``x == 0``.
    """
    x = jnp.asarray(x)
    ax = jnp.abs(x)
    small = ax < _TINY
    safe = jnp.where(small, 1.0, ax)
    return jnp.where(small, 0.0, jnp.exp(p * jnp.log(safe)))


def signed_pow(x: ArrayLike, p: ArrayLike) -> Array:
    """``sign(x) |x| ** p``, NaN-safe at 0 (see :func:`abs_pow`)."""
    return jnp.sign(x) * abs_pow(x, p)


def matmul(a: ArrayLike, b: ArrayLike) -> Array:
    """``a @ b`` at full float32 precision. On NVIDIA GPUs JAX's default float32 product is
    TF32 (a 10-bit mantissa), which moves rotated points by about 1e-3 of their depth:
    enough to change Γ by hundreds of pixels and the recovered model (11 parts instead of
    14 on the human). On CPUs the two are the same."""
    return jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)


@jax.jit
def rotation_matrix(rotation_vector: Float[ArrayLike, "3"]) -> Float[Array, "3 3"]:
    """Rodrigues' formula: rotation vector (axis * angle) to a 3x3 matrix.

    Uses a Taylor expansion below 1e-4 rad so that value and gradient are finite at 0.
    """
    w = jnp.asarray(rotation_vector)
    theta2 = jnp.sum(w * w)
    small = theta2 < 1e-8
    theta2_safe = jnp.where(small, 1.0, theta2)
    theta = jnp.sqrt(theta2_safe)
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / theta2_safe)
    zero = jnp.zeros((), w.dtype)
    k = jnp.array([[zero, -w[2], w[1]], [w[2], zero, -w[0]], [-w[1], w[0], zero]], dtype=w.dtype)
    return jnp.eye(3, dtype=w.dtype) + a * k + b * matmul(k, k)


def rotation_vector(matrix: Float[ArrayLike, "3 3"]) -> np.ndarray:
    """Checked inverse of :func:`rotation_matrix` for I/O: matrix to rotation vector
    (numpy, float64), via :func:`matrix_to_rotation_vector`.

    Raises ``ValueError`` unless ``matrix`` is a proper rotation (orthonormal, det +1,
    to 1e-4).
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (3, 3):
        raise ValueError(f"rotation: got shape {m.shape}, expected a finite 3x3 matrix")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"rotation: got {m.tolist()}, expected a finite 3x3 matrix")
    err = np.abs(m @ m.T - np.eye(3)).max()
    if err > 1e-4 or np.linalg.det(m) < 0:
        raise ValueError(
            f"rotation: got |R R^T - I| = {err:.2g}, det = {np.linalg.det(m):.3g}, expected an "
            "orthonormal matrix with determinant +1"
        )
    with jax.enable_x64(True):
        return np.array(matrix_to_rotation_vector(jnp.asarray(m, jnp.float64)), np.float64)


class Part(eqx.Module):
    """One deformed superquadric part, or a batch of them (leading axes on every field).

    Construct with keywords; ``orientation`` (rotation vector), ``bend`` and ``taper``
    default to zero. Concrete inputs are validated (finite, ``size > 0``, squareness,
    bend and taper in range) and raise ``ValueError`` naming the field; traced inputs
    (inside ``jit``/``vmap``) are not checked.

    Examples
    --------
    >>> part = Part(size=[0.1, 0.1, 0.3], squareness=[0.5, 1.0], position=[0, 0, 2.0])
    """

    position: Float[Array, "*batch 3"]
    orientation: Float[Array, "*batch 3"]
    size: Float[Array, "*batch 3"]
    squareness: Float[Array, "*batch 2"]
    bend: Float[Array, "*batch 2"]
    taper: Float[Array, "*batch"]

    def __init__(
        self,
        *,
        size,
        squareness=(1.0, 1.0),
        position=(0.0, 0.0, 0.0),
        orientation=None,
        bend=None,
        taper=None,
    ):
        size = _as_float_array(size)
        dtype = size.dtype
        batch = size.shape[:-1]

        def field(name, x, default_shape):
            try:
                return _host_op(lambda xp, a: xp.asarray(a, dtype), np.zeros(default_shape, dtype) if x is None else x)
            except (TypeError, ValueError):  # strings, objects, ragged lists
                raise ValueError(f"{name}: got {x!r:.60}, expected numbers") from None

        position = field("position", position, None)
        squareness = field("squareness", squareness, None)
        orientation = field("orientation", orientation, batch + (3,))
        bend = field("bend", bend, batch + (2,))
        taper = field("taper", taper, batch)
        fields = dict(
            position=position,
            orientation=orientation,
            size=size,
            squareness=squareness,
            bend=bend,
            taper=taper,
        )
        if not _traced(*fields.values()):
            _validate(fields, batch)
        self.position = position
        self.orientation = orientation
        self.size = size
        self.squareness = squareness
        self.bend = bend
        self.taper = taper

    # --- the 14-vector -----------------------------------------------------------
    def to_vector(self) -> Float[Array, "*batch 14"]:
        """The 14 parameters (footnote 4) as one vector, in the module docstring's order."""
        return _host_op(
            lambda xp, *f: xp.concatenate([*f[:-1], f[-1][..., None]], axis=-1),
            self.position,
            self.orientation,
            self.size,
            self.squareness,
            self.bend,
            self.taper,
        )

    @classmethod
    def from_vector(cls, vector: Float[ArrayLike, "*batch 14"]) -> "Part":
        """Inverse of :meth:`to_vector`; validated when concrete."""
        # Concrete vectors are sliced on the host (see _host_op).
        v = cast(Array, vector) if _traced(vector) else np.asarray(vector)
        if v.shape[-1:] != (14,):
            raise ValueError(f"vector: got shape {v.shape}, expected a trailing axis of 14")
        return cls(
            position=v[..., 0:3],
            orientation=v[..., 3:6],
            size=v[..., 6:9],
            squareness=v[..., 9:11],
            bend=v[..., 11:13],
            taper=v[..., 13],
        )

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return self.size.shape[:-1]

    def __len__(self) -> int:
        if not self.batch_shape:
            raise TypeError("part: got a single Part, expected a batch (only a batch of parts has a length)")
        return self.batch_shape[0]

    def __iter__(self):
        # Python's fallback iteration calls __getitem__ until IndexError, which JAX's
        # clamped indexing never raises: iterate over the leading batch axis explicitly.
        return (self[i] for i in range(len(self)))

    def __getitem__(self, index) -> "Part":
        if isinstance(index, (int, np.integer)) and self.batch_shape and not -len(self) <= index < len(self):
            raise IndexError(f"index: got {index}, expected an index into a batch of {len(self)} parts")
        return jax.tree_util.tree_map(lambda x: _host_op(lambda _, a: a[index], x), self)

    def rotation(self) -> Float[Array, "*batch 3 3"]:
        """Local-to-camera rotation matrix R (p_cam = R p_local + position)."""
        flat = self.orientation.reshape(-1, 3)
        mats = jax.vmap(rotation_matrix)(flat)
        return mats.reshape(self.batch_shape + (3, 3))


def _as_float_array(x) -> Array:
    dtype = getattr(x, "dtype", None)  # an array's, read without a transfer; else a host probe
    try:
        dtype = np.asarray(x).dtype if dtype is None else dtype
    except (TypeError, ValueError):  # a ragged list
        dtype = np.dtype(object)
    if not (jnp.issubdtype(dtype, jnp.number) or jnp.issubdtype(dtype, jnp.bool_)):
        raise ValueError(f"size: got {x!r:.60}, expected numbers")

    def convert(xp, a):
        a = xp.asarray(a)
        if xp.issubdtype(a.dtype, xp.complexfloating):
            raise ValueError(f"size: got {a.dtype}, expected real numbers")
        if xp.issubdtype(a.dtype, xp.floating) and a.dtype.itemsize >= 4:
            return a
        # Integers, and float16/bfloat16 (whose rays would miss every part): float32 or wider.
        return a.astype(jnp.result_type(float))

    return _host_op(convert, x)


def _traced(*arrays) -> bool:
    """Whether any of ``arrays`` is a JAX tracer (inside ``jit``, ``vmap``, ``grad``)."""
    return any(isinstance(a, jax.core.Tracer) for a in arrays)


def _validate(fields: dict, batch: tuple[int, ...]) -> None:
    want = {
        "position": batch + (3,),
        "orientation": batch + (3,),
        "size": batch + (3,),
        "squareness": batch + (2,),
        "bend": batch + (2,),
        "taper": batch,
    }
    if fields["size"].ndim == 0 or fields["size"].shape[-1] != 3:
        raise ValueError(f"size: got shape {fields['size'].shape}, expected 3 semi-axes (a1, a2, a3)")
    for name, shape in want.items():
        got = fields[name].shape
        if got != shape:
            raise ValueError(f"{name}: got shape {got}, expected {shape}")
        values = np.asarray(fields[name])
        if not np.all(np.isfinite(values)):
            raise ValueError(f"{name}: got {values.tolist()}, expected finite values")
    size = np.asarray(fields["size"])
    if np.any(size <= 0):
        raise ValueError(f"size: got {size.tolist()}, expected semi-axes > 0")
    for name, (lo, hi) in (
        ("squareness", SQUARENESS_RANGE),
        ("bend", BEND_RANGE),
        ("taper", TAPER_RANGE),
    ):
        values = np.asarray(fields[name])
        if np.any(values < lo) or np.any(values > hi):
            raise ValueError(f"{name}: got {values.tolist()}, expected values in [{lo}, {hi}]")


# --- geometry of one part -----------------------------------------------------------


def bounding_half_extent(part: Part) -> Float[Array, "*batch 3"] | np.ndarray:
    """Half-extent of an axis-aligned box in the local frame containing the deformed part
    (batched parts: one box each; parts with host leaves (:func:`~sqparts._encoding.host_parts`)
    give a numpy array, on the host)."""
    xp = np if isinstance(part.size, np.ndarray) else jnp
    a1, a2, a3 = part.size[..., 0], part.size[..., 1], part.size[..., 2]
    grow = 1.0 + abs(part.taper)
    hx = a1 * grow + abs(part.bend[..., 0]) * a3
    hy = a2 * grow
    hz = a3 + abs(part.bend[..., 1]) * hx * hx / a1
    return xp.stack([hx, hy, hz], -1)


def deform(part: Part, q: Float[Array, "3"]) -> Float[Array, "3"]:
    """Apply taper, then bend[0], then bend[1] to an undeformed local point ``q``."""
    a1, a3 = part.size[0], part.size[2]
    x, y, z = q[0], q[1], q[2]
    scale = 1.0 + part.taper * z / a3
    x, y = x * scale, y * scale
    x = x + part.bend[0] * z * z / a3
    z = z + part.bend[1] * x * x / a1
    return jnp.stack([x, y, z])


def undeform(part: Part, p: Float[Array, "3"]) -> Float[Array, "3"]:
    """Exact inverse of :func:`deform` (bend[1], then bend[0], then taper)."""
    a1, a3 = part.size[0], part.size[2]
    x, y, z = p[0], p[1], p[2]
    z = z - part.bend[1] * x * x / a1
    x = x - part.bend[0] * z * z / a3
    scale = 1.0 + part.taper * z / a3
    scale = jnp.where(jnp.abs(scale) < 1e-6, 1e-6, scale)
    return jnp.stack([x / scale, y / scale, z])


def superquadric_function(part: Part, q: Float[Array, "3"]) -> Float[Array, ""]:
    """The undeformed inside-outside function F(q) of Eq. (1): < 1 inside, 1 on the surface.

    F = ((|x/a1|^(2/ε2) + |y/a2|^(2/ε2))^(ε2/ε1) + |z/a3|^(2/ε1)
    """
    e1, e2 = part.squareness[0], part.squareness[1]
    fx = abs_pow(q[0] / part.size[0], 2.0 / e2)
    fy = abs_pow(q[1] / part.size[1], 2.0 / e2)
    fz = abs_pow(q[2] / part.size[2], 2.0 / e1)
    return abs_pow(fx + fy, e2 / e1) + fz


def to_local(part: Part, point: Float[ArrayLike, "3"]) -> Float[Array, "3"]:
    """Camera point to the part's (deformed) local frame: R^T (p - position)."""
    return matmul(rotation_matrix(part.orientation).T, jnp.asarray(point) - part.position)


def inside_outside(part: Part, point: Float[ArrayLike, "3"]) -> Float[Array, ""]:
    """Inside-outside function of the posed, deformed part at a camera-frame point.

    < 1 inside, 1 on the surface, > 1 outside; the distance measure of footnote 6. For a
    single part; ``vmap`` over points or parts.
    """
    return superquadric_function(part, undeform(part, to_local(part, point)))


def gauge(part: Part, local_point: Float[Array, "3"]) -> Float[Array, ""]:
    """``F(D^{-1}(p))^(ε1/2) - 1`` at a local point: 0 on the surface, degree-1 homogeneous.

    For an undeformed part this is a norm minus one (convex for ε <= 2), the form the ray
    caster runs Newton's method on.
    """
    f = superquadric_function(part, undeform(part, local_point))
    return abs_pow(f, part.squareness[0] / 2.0) - 1.0


@jax.custom_jvp
def surface_distance(part: Part, point: Float[ArrayLike, "3"]) -> Float[Array, ""]:
    """Signed radial distance of a camera-frame point from the part's surface (< 0 inside).

    ``|q| (1 - F(q)^(-ε1/2))`` with ``q`` the undeformed local point: the distance along
    the ray from the part's centre through the point (exact for spheres; Gross & Boult's
    radial Euclidean distance). Unlike the algebraic inside-outside value it hardly
    favours small parts or points near the ends of long axes.

    Its derivatives (a custom JVP, the same in every mode): the gradient of the distance
    in the part's frame with respect to the local point and the part's shape, taken once
    per point in reverse mode, then applied to the tangents of the pose, the shape and the
    point. Forward mode through the formula carries every tangent through every step of
    it; polishing's Jacobians (14 tangents per point) cost about 4x less this way. The
    tangent is one dot product of a vector per point with a vector per tangent
    (:func:`distance_terms`, :func:`part_tangent`).
    """
    return _local_distance(part, to_local(part, point))


_FAR = 8.0
"""Largest |q_i / a_i| at which :func:`_local_distance` evaluates F as it is (F is then at
most 2^20 8^20 = 1e24, its derivatives finite in float32)."""


def _undeformed(part: Part, local: Float[Array, "3"]) -> Float[Array, "3"]:
    """The undeformed local point (:func:`undeform`), stepped off the centre by a
    millionth of a1 when it lies there (where the direction is undefined)."""
    q = undeform(part, local)
    tiny = 1e-6 * part.size[0]
    return jnp.where(jnp.sum(q * q) < tiny * tiny, q + jnp.stack([tiny, 0.0 * tiny, 0.0 * tiny]), q)


def _local_distance(part: Part, local: Float[Array, "3"]) -> Float[Array, ""]:
    """:func:`surface_distance` of a point already in the part's (deformed) local frame.

    Far outside a boxy part the terms |q_i / a_i|^(2/ε) of F overflow float32 (ε 0.1: a
    point 90 semi-axes out, or nearer where a bend or taper stretches the undeformed
    frame): the value stayed finite, its gradients were NaN. The norm F^(ε1/2) is degree-1
    homogeneous in q, so beyond :data:`_FAR` semi-axes it is taken at q / λ and times λ, λ
    the power of two at or above the largest |q_i / a_i| (exact in floating point; λ = 1
    nearer, the computation as it always was)."""
    q = _undeformed(part, local)
    ratio = jax.lax.stop_gradient(jnp.max(jnp.abs(q / part.size)))
    # Near the centre of a boxy part F underflows to 0 (|q/a|^(2/ε), ε 0.1, below 3% of every
    # semi-axis) and the distance was -inf: there too q is taken at q / λ, λ < 1.
    rescale = (ratio > _FAR) | (ratio < 1.0 / _FAR)
    lam = jnp.where(rescale, jnp.exp2(jnp.ceil(jnp.log2(jnp.where(rescale, ratio, 1.0)))), 1.0)
    norm = lam * abs_pow(superquadric_function(part, q / lam), part.squareness[0] / 2.0)
    length = jnp.sqrt(jnp.sum(q * q))
    return length - length / norm


def _local_normal_distance(part: Part, local: Float[Array, "3"]) -> Float[Array, ""]:
    """:func:`normal_distance` of a point already in the part's (deformed) local frame:
    :func:`_local_distance` times the cosine between the ray from the centre and the
    surface's normal there, n / (|q| |grad n|) (Euler: q . grad n = n for the
    degree-1 homogeneous norm n); grad n in closed form at the surface point q / n,
    where F = 1: (A^(ε2/ε1 - 1) sgn|x/a1|^(2/ε2 - 1) / a1, the same in y,
    sgn|z/a3|^(2/ε1 - 1) / a3), A = |x/a1|^(2/ε2) + |y/a2|^(2/ε2)."""
    e1, e2 = part.squareness[0], part.squareness[1]
    radial = _local_distance(part, local)
    q = _undeformed(part, local)
    length = jnp.sqrt(jnp.sum(q * q))
    p = q * ((length - radial) / length) / part.size  # the surface point q / n (|q| / n = |q| - radial), per semi-axis
    across = abs_pow(abs_pow(p[0], 2.0 / e2) + abs_pow(p[1], 2.0 / e2), e2 / e1 - 1.0)
    grad = (
        jnp.stack(
            [
                across * signed_pow(p[0], 2.0 / e2 - 1.0),
                across * signed_pow(p[1], 2.0 / e2 - 1.0),
                signed_pow(p[2], 2.0 / e1 - 1.0),
            ]
        )
        / part.size
    )
    return radial / jnp.maximum((length - radial) * jnp.sqrt(jnp.sum(grad * grad)), 1.0)


def _distance_jvp(normal: bool):
    """The custom JVP of :func:`surface_distance` (or, ``normal``, :func:`normal_distance`):
    :func:`distance_terms` applied to the part's and the point's tangents."""

    def jvp(primals, tangents):
        part, point = primals
        dpart, dpoint = tangents
        value, per_point, turned = distance_terms(part, point, normal=normal)
        return value, matmul(per_point, part_tangent(part, dpart)) + matmul(turned, jnp.asarray(dpoint))

    return jvp


surface_distance.defjvp(_distance_jvp(False))


@jax.custom_jvp
def normal_distance(part: Part, point: Float[ArrayLike, "3"]) -> Float[Array, ""]:
    """Signed distance of a camera-frame point from the part's surface (< 0 inside), to
    first order along the surface's normal: :func:`surface_distance` times the cosine
    between the ray from the part's centre through the point and the normal where it
    meets the surface, ``(n - 1) / |grad n|`` for the norm ``n = F^(ε1/2)``. A point moved
    off the surface along its normal is that far from it wherever it lies (section 2.1:
    measurement error normal to the surface), where the radial distance counts it 1/cos θ
    times: least squares on radial distances of a noisy surface buys residual by moving
    the part's centre away from the faces it sees (a noisy box's hidden side swelled by
    several noise widths). Polishing fits these; selecting a part's pixels and the rays
    it must miss keeps the radial distance, which, unlike this, does not shrink beyond a
    boxy part's edges. Derivatives as :func:`surface_distance`'s."""
    return _local_normal_distance(part, to_local(part, point))


normal_distance.defjvp(_distance_jvp(True))


def distance_terms(part: Part, point: Float[ArrayLike, "3"], *, normal: bool = False):
    """:func:`surface_distance` at a camera-frame point with what its derivatives need:
    (value, a (20,) vector whose dot product with :func:`part_tangent` is the
    derivative along a change of the part, R g: the gradient in the camera frame
    (the derivative along a move of the point is its dot product with the move)).

    With the local point l = R^T (x - t) and g the distance's gradient there,
    g.dl = Σ_ij g_i (x - t)_j dR_ji + (R g).(dx - dt), and position and orientation enter
    through l alone. So a Jacobian over many points and tangents (vmapped) is one
    matrix product, not 3-vector products of shape (tangents, points, 3), which
    XLA:CPU runs about 4x slower (polishing's Jacobian: 3.5x faster in all)."""
    rotation = rotation_matrix(part.orientation)
    offset = jnp.asarray(point) - part.position
    local = _local_normal_distance if normal else _local_distance
    value, (g_part, g) = jax.value_and_grad(local, argnums=(0, 1))(part, matmul(rotation.T, offset))
    turned = matmul(rotation, g)
    per_point = jnp.concatenate(
        [g_part.size, g_part.squareness, g_part.bend, g_part.taper[None], jnp.outer(offset, g).reshape(9), turned]
    )
    return value, per_point, turned


def part_tangent(part: Part, dpart: Part) -> Float[Array, "20"]:
    """A change ``dpart`` of a single part as :func:`distance_terms`' (20,) vector:
    shape, the rotation matrix's change, minus the position's."""
    d_rotation = jax.jvp(rotation_matrix, (part.orientation,), (dpart.orientation,))[1]
    return jnp.concatenate(
        [dpart.size, dpart.squareness, dpart.bend, dpart.taper[None], d_rotation.reshape(9), -dpart.position]
    )


def surface_point(part: Part, eta: ArrayLike, omega: ArrayLike) -> Float[Array, "3"]:
    """Camera-frame point of Eq. (1) at latitude η in [-π/2, π/2], longitude ω in [-π, π].

    X(η, ω) = (a1 C_η^ε1 C_ω^ε2, a2 C_η^ε1 S_ω^ε2, a3 S_η^ε1), then deformed and posed.
    """
    e1, e2 = part.squareness[0], part.squareness[1]
    ce, se = signed_pow(jnp.cos(eta), e1), signed_pow(jnp.sin(eta), e1)
    cw, sw = signed_pow(jnp.cos(omega), e2), signed_pow(jnp.sin(omega), e2)
    q = jnp.stack([part.size[0] * ce * cw, part.size[1] * ce * sw, part.size[2] * se])
    p = deform(part, q)
    return matmul(rotation_matrix(part.orientation), p) + part.position


def stack_parts(parts) -> Part:
    """Stack a sequence of single parts into one batched :class:`Part` (a scene)."""
    parts = list(parts)
    if not parts:
        raise ValueError("parts: got an empty sequence, expected at least one part")
    return jax.tree_util.tree_map(lambda *xs: _host_op(lambda xp, *a: xp.stack(a), *xs), *parts)


def _host_op(fn, *arrays) -> Any:
    """``fn(xp, *arrays)`` with ``xp = numpy`` on host copies of concrete ``arrays``
    (placed on the device with ``jax.device_put``), or ``xp = jax.numpy`` when any is
    traced. Building, indexing and stacking parts outside ``jit`` with ``jax.numpy`` would
    compile one small XLA program per operation and new shape (``jnp.asarray`` of a
    numpy array included)."""
    if _traced(*arrays):
        return fn(jnp, *arrays)
    return jax.device_put(fn(np, *(np.asarray(a) for a in arrays)))


@jax.jit
def matrix_to_rotation_vector(matrix: Float[ArrayLike, "3 3"]) -> Float[Array, "3"]:
    """JAX inverse of :func:`rotation_matrix` (via the quaternion; all four Shepperd
    branches computed and the best-conditioned one selected, so it is jit/vmap safe)."""
    m = jnp.asarray(matrix)
    tr = jnp.trace(m)
    d = jnp.diagonal(m)
    cands = jnp.stack([tr, d[0], d[1], d[2]])
    i = jnp.argmax(cands)
    eps = 1e-12
    w0 = jnp.sqrt(jnp.maximum(1.0 + tr, eps)) / 2
    q0 = jnp.stack([w0, (m[2, 1] - m[1, 2]) / (4 * w0), (m[0, 2] - m[2, 0]) / (4 * w0), (m[1, 0] - m[0, 1]) / (4 * w0)])
    x1 = jnp.sqrt(jnp.maximum(1.0 + 2 * d[0] - tr, eps)) / 2
    q1 = jnp.stack([(m[2, 1] - m[1, 2]) / (4 * x1), x1, (m[1, 0] + m[0, 1]) / (4 * x1), (m[2, 0] + m[0, 2]) / (4 * x1)])
    y2 = jnp.sqrt(jnp.maximum(1.0 + 2 * d[1] - tr, eps)) / 2
    q2 = jnp.stack([(m[0, 2] - m[2, 0]) / (4 * y2), (m[1, 0] + m[0, 1]) / (4 * y2), y2, (m[2, 1] + m[1, 2]) / (4 * y2)])
    z3 = jnp.sqrt(jnp.maximum(1.0 + 2 * d[2] - tr, eps)) / 2
    q3 = jnp.stack([(m[1, 0] - m[0, 1]) / (4 * z3), (m[2, 0] + m[0, 2]) / (4 * z3), (m[2, 1] + m[1, 2]) / (4 * z3), z3])
    q = jnp.stack([q0, q1, q2, q3])[i]
    q = jnp.where(q[0] < 0, -q, q)
    v = q[1:]
    s = jnp.sqrt(jnp.sum(v * v))
    small = s < 1e-9
    s_safe = jnp.where(small, 1.0, s)
    angle = 2 * jnp.arctan2(s_safe, q[0])
    return jnp.where(small, 2 * v / jnp.maximum(q[0], eps), v / s_safe * angle)


def _logit(x):
    return jnp.log(x) - jnp.log1p(-x)


@jax.jit
def to_unconstrained(part: Part) -> Float[Array, "*batch 14"]:
    """14-vector in an unconstrained space for optimisers: log sizes, squareness through a
    logistic onto [0.1, 2], bend and taper through tanh onto [-1, 1]."""
    lo, hi = SQUARENESS_RANGE
    sq = jnp.clip((part.squareness - lo) / (hi - lo), 1e-4, 1 - 1e-4)
    return jnp.concatenate(
        [
            part.position,
            part.orientation,
            jnp.log(part.size),
            _logit(sq),
            jnp.arctanh(jnp.clip(part.bend, -0.999, 0.999)),
            jnp.arctanh(jnp.clip(part.taper, -0.999, 0.999))[..., None],
        ],
        axis=-1,
    )


@jax.jit
def from_unconstrained(u: Float[ArrayLike, "*batch 14"]) -> Part:
    """Inverse of :func:`to_unconstrained` (always a valid part)."""
    u = jnp.asarray(u)
    lo, hi = SQUARENESS_RANGE
    return Part.from_vector(
        jnp.concatenate(
            [
                u[..., 0:6],
                jnp.exp(u[..., 6:9]),
                lo + (hi - lo) * jax.nn.sigmoid(u[..., 9:11]),
                jnp.tanh(u[..., 11:14]),
            ],
            axis=-1,
        )
    )
