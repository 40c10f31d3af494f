"""Part-structure descriptions: what a recovery says about an object, independent of the camera.

Section 1 of the paper asks for a description that is *stable* and can be matched against
stored ones: a handful of parts, each with a few shape numbers, and how the parts sit
together. A :class:`Description` holds, per part, pose-free attributes in the object's
own scale (sorted semi-axes, squareness ε1 ε2, |taper|, |bend|, volume fraction) and,
per ordered pair of parts, relations (whether they touch, relative size, where one's
centre sits in the other's frame, the angle between their longest axes). None of these
change under a rigid motion of the camera or a change of units; the camera-frame
positions and rotations are kept beside them (``positions``, ``rotations``) only to
estimate the pose once parts are matched.

Beside the parts, a whole-object term derived from them: the D2 shape distribution of
points on the parts' surfaces (:func:`shape_distribution`), which one part recovered as
two, or two as one, barely moves.

The graph form (:meth:`Description.graph`) is a ``networkx.DiGraph``: nodes are parts,
edges ordered pairs; :meth:`Description.to_json` is its node-link JSON.

Pure numpy: no file I/O, no JAX tracing.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import KDTree
from scipy.spatial.distance import pdist
from scipy.special import beta

from ._camera import json_numbers
from ._part import Part, matrix_to_rotation_vector, stack_parts

ATTRIBUTES = ("size_1", "size_2", "size_3", "squareness_1", "squareness_2", "taper", "bend", "volume")
"""Columns of :attr:`Description.attributes`: semi-axes sorted largest first and divided by
the object's scale, ε1, ε2 (Eq. 1), |taper|, the bends' magnitude sqrt(b0² + b1²), and the
part's share of the object's volume."""

RELATIONS = ("touch", "gap", "distance", "offset_1", "offset_2", "offset_3", "axis_angle", "log_volume_ratio")
"""Columns of :attr:`Description.relations` for the ordered pair (i, j): 1 if the parts touch,
the gap between their surfaces and the distance between their centres (object scale),
|offset| of j's centre along i's axes (i's sorted axes, object scale), the angle in [0, π/2]
between their longest axes (radians), and log(volume_j / volume_i)."""

TOUCH_GAP = 0.08
"""Parts whose surfaces come closer than this (a fraction of the object's scale) touch."""

SHAPE_BINS = 24
SHAPE_RANGE = 4.0
"""The whole-object shape distribution (:func:`shape_distribution`): ``SHAPE_BINS`` bins of
the distance between two surface points over [0, ``SHAPE_RANGE``] object scales (a solid
of scale s fits well inside 4 s unless it is a thin rod more than 4 s long; longer distances
fall in the last bin)."""


def part_volume(size, squareness) -> np.ndarray:
    """Volume of undeformed superquadrics, 2 a1 a2 a3 ε1 ε2 B(ε1/2 + 1, ε1) B(ε2/2, ε2/2).

    ``size`` (..., 3), ``squareness`` (..., 2); tapering and bending are ignored.
    """
    size, sq = np.asarray(size, float), np.asarray(squareness, float)
    e1, e2 = sq[..., 0], sq[..., 1]
    return 2.0 * np.prod(size, -1) * e1 * e2 * beta(e1 / 2 + 1, e1) * beta(e2 / 2, e2 / 2)


def _signed_pow(x, e):
    return np.sign(x) * np.abs(x) ** e


def _rotation_matrices(orientation) -> np.ndarray:
    """Rodrigues' formula for rotation vectors (n, 3) -> (n, 3, 3)."""
    rv = np.asarray(orientation, float).reshape(-1, 3)
    theta = np.linalg.norm(rv, axis=1)
    safe = np.where(theta < 1e-12, 1.0, theta)
    k = rv / safe[:, None]
    kx = np.zeros((len(rv), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx = kx - kx.transpose(0, 2, 1)
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    return np.eye(3) + s * kx + (1 - c) * kx @ kx


def surface_samples(size, squareness, bend, taper, rotation, position, *, count: int = 12) -> np.ndarray:
    """Camera-frame points on one deformed part (Eq. 1, then taper and bends as
    :func:`sqparts._part.deform`): ``count`` latitudes x 2 ``count`` longitudes."""
    eta = np.linspace(-np.pi / 2, np.pi / 2, count)
    omega = np.linspace(-np.pi, np.pi, 2 * count, endpoint=False)
    ee, ww = np.meshgrid(eta, omega, indexing="ij")
    e1, e2 = squareness
    a1, a2, a3 = size
    ce, se = _signed_pow(np.cos(ee), e1), _signed_pow(np.sin(ee), e1)
    x = a1 * ce * _signed_pow(np.cos(ww), e2)
    y = a2 * ce * _signed_pow(np.sin(ww), e2)
    z = a3 * se
    scale = 1.0 + taper * z / a3
    x, y = x * scale, y * scale
    x = x + bend[0] * z * z / a3
    z = z + bend[1] * x * x / a1
    q = np.stack([x.ravel(), y.ravel(), z.ravel()], -1)
    return q @ np.asarray(rotation).T + np.asarray(position)


def _eq1(scaled, squareness):
    """Eq. 1's inside-outside function F of part-frame coordinates already divided by the
    semi-axes and made non-negative (|x|/a1, |y|/a2, |z|/a3), shape (..., 3)."""
    e1, e2 = squareness
    return (scaled[..., 0] ** (2 / e2) + scaled[..., 1] ** (2 / e2)) ** (e2 / e1) + scaled[..., 2] ** (2 / e1)


def _radial_surface(theta, phi, size, squareness, bend, taper):
    """Part-frame points of a deformed superquadric in the directions (θ latitude, φ
    longitude): the direction d projected radially, r = F(d)^(-ε1/2) for the
    inside-outside function F of Eq. 1, then tapered and bent as :func:`surface_samples`."""
    d = np.stack([np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi), np.sin(theta)], -1)
    a1, _, a3 = size
    with np.errstate(divide="ignore"):
        f = _eq1(np.abs(d) / np.asarray(size), squareness)
    q = d * (f ** (-squareness[0] / 2))[..., None]
    x, y, z = q[..., 0], q[..., 1], q[..., 2]
    scale = 1.0 + taper * z / a3
    x, y = x * scale, y * scale
    x = x + bend[0] * z * z / a3
    z = z + bend[1] * x * x / a1
    return np.stack([x, y, z], -1)


def area_samples(size, squareness, bend, taper, rotation, position, *, count: int = 12):
    """Points on one deformed part and the surface area each stands for.

    The directions of a (latitude, longitude) grid of ``count`` x 2 ``count`` cells are
    projected radially onto the part (:func:`_radial_surface`), which spreads points over
    the flat faces of a boxy part where Eq. 1's own (η, ω) grid crowds them onto its
    edges. Each cell's centre stands for the cell's area, half the cross product of its
    diagonals (exact for a planar cell). Returns ((2 count², 3) points, (2 count²,) areas)
    in the frame given by ``rotation`` and ``position``.
    """
    edges_t = np.linspace(-np.pi / 2, np.pi / 2, count + 1)
    edges_p = np.linspace(-np.pi, np.pi, 2 * count + 1)
    centres = _radial_surface(
        *np.meshgrid((edges_t[1:] + edges_t[:-1]) / 2, (edges_p[1:] + edges_p[:-1]) / 2, indexing="ij"),
        size,
        squareness,
        bend,
        taper,
    )
    c = _radial_surface(*np.meshgrid(edges_t, edges_p, indexing="ij"), size, squareness, bend, taper)
    area = 0.5 * np.linalg.norm(np.cross(c[1:, 1:] - c[:-1, :-1], c[1:, :-1] - c[:-1, 1:]), axis=-1)
    p = centres.reshape(-1, 3) @ np.asarray(rotation).T + np.asarray(position)
    return p, area.ravel()


def shape_distribution(parts: Part, *, count: int = 12) -> np.ndarray:
    """The whole object's D2 shape distribution (Osada et al. 2002) computed from its parts:
    the area-weighted histogram of the distance between two points of the parts' surfaces,
    in units of the object's scale (cube root of the parts' total volume), ``SHAPE_BINS``
    bins over [0, ``SHAPE_RANGE``], summing to 1 (distances beyond the range in the last bin).

    A description of the solid as a whole that does not depend on how it was cut into
    parts: one part recovered as two, or two as one, moves it little, where the part graph
    changes. Unchanged by a rigid motion of all the parts and by a change of units.
    """
    size, sq, bend, taper, position, orientation = _as_arrays(parts)
    rot = _rotation_matrices(orientation)
    samples = [
        area_samples(size[i], sq[i], bend[i], taper[i], rot[i], position[i], count=count) for i in range(len(size))
    ]
    pts = np.concatenate([p for p, _ in samples])
    area = np.concatenate([a for _, a in samples])
    scale = float(np.cbrt(part_volume(size, sq).sum()))
    i, j = np.triu_indices(len(pts), 1)
    d = pdist(pts) / scale
    h, _ = np.histogram(
        np.minimum(d, SHAPE_RANGE * (1 - 1e-9)), bins=SHAPE_BINS, range=(0, SHAPE_RANGE), weights=area[i] * area[j]
    )
    return h / h.sum()


SURFACE_SAMPLES = 2000
"""Points of a :class:`Description`'s :attr:`~Description.surface` (the solid's outer
surface): dense enough that two draws of the same surface lie well within the alignment's
tolerance of each other, so that distances to them stand for distances to the surface."""


def _inside(points: np.ndarray, size, squareness, rotation, position) -> np.ndarray:
    """(n,) bool: ``points`` strictly inside the undeformed superquadric (F < 1, Eq. 1)."""
    return _eq1(np.abs((points - position) @ rotation) / size + 1e-12, squareness) < 1.0 - 1e-6


def surface_cloud(parts: Part, *, samples: int = SURFACE_SAMPLES, count: int = 32) -> np.ndarray:
    """(samples, 3) points spread by area over the outer surface of the solid the parts
    make together: each part's :func:`area_samples`, less those inside another part,
    drawn in proportion to the area each stands for (systematic resampling: sample k is
    the cell where the cumulative area passes (k + 1/2) / samples of the total, so a
    large cell may be drawn more than once and the same parts always give the same
    points). The inside test ignores taper and bend (the other part's undeformed Eq. 1).
    The solid as a whole, however it was cut into parts: what
    :func:`sqparts._recognize.align_descriptions` aligns."""
    size, sq, bend, taper, position, orientation = _as_arrays(parts)
    rot = _rotation_matrices(orientation)
    pts, areas = [], []
    for k in range(len(size)):
        p, a = area_samples(size[k], sq[k], bend[k], taper[k], rot[k], position[k], count=count)
        hidden = np.zeros(len(p), bool)
        for j in range(len(size)):
            if j != k:
                hidden |= _inside(p, size[j], sq[j], rot[j], position[j])
        pts.append(p)
        areas.append(np.where(hidden, 0.0, a))
    p, a = np.concatenate(pts), np.concatenate(areas)
    if not a.sum() > 0:  # every sample inside another part (parts wholly inside others): all of them
        a = np.ones(len(a))
    cumulative = np.cumsum(a)
    pick = np.searchsorted(cumulative, (np.arange(samples) + 0.5) / samples * cumulative[-1])
    return p[np.minimum(pick, len(p) - 1)]


@dataclasses.dataclass(frozen=True, eq=False)
class Description:
    """The part structure of one figure (section 1: a stable description to match).

    Attributes
    ----------
    scale : float
        The object's scale, the cube root of its parts' total volume (scene units).
    attributes : (n, 8) array
        Per part, the pose-free :data:`ATTRIBUTES`.
    relations : (n, n, 8) array
        Per ordered pair (i, j), the :data:`RELATIONS` (zeros on the diagonal).
    positions : (n, 3) array
        Part centres in the frame the parts were given in (for pose estimation only).
    rotations : (n, 3, 3) array
        Part-to-frame rotations, columns in the order of the sorted axes (for pose only).
    names : tuple of str
        Optional part names ("" where none).
    shape_distribution : (SHAPE_BINS,) array or None
        The whole object's :func:`shape_distribution` (None: not known, e.g. a description
        read from a file written before it existed; matching then uses the parts alone).
    surface : (SURFACE_SAMPLES, 3) array or None
        Points on the solid's outer surface in the frame of ``positions``
        (:func:`surface_cloud`), for aligning whole solids; not part of the JSON form (a
        stored view recomputes it from its parts). None: matching uses the parts alone.
    """

    scale: float
    attributes: np.ndarray
    relations: np.ndarray
    positions: np.ndarray
    rotations: np.ndarray
    names: tuple = ()
    shape_distribution: np.ndarray | None = None
    surface: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.attributes)

    @property
    def touching(self) -> np.ndarray:
        """(n, n) bool: which parts touch."""
        return self.relations[..., 0] > 0.5

    @property
    def volumes(self) -> np.ndarray:
        return self.attributes[:, ATTRIBUTES.index("volume")]

    def transformed(self, rotation, translation) -> "Description":
        """The same description with the pose data moved by a rigid motion (p -> R p + t)."""
        r, t = np.asarray(rotation, float), np.asarray(translation, float)
        return dataclasses.replace(
            self,
            positions=self.positions @ r.T + t,
            rotations=r @ self.rotations,
            surface=None if self.surface is None else self.surface @ r.T + t,
        )

    def to_json(self) -> dict:
        """Node-link JSON: ``{"scale", "nodes": [...], "edges": [...]}``, every number a float."""
        nodes = []
        for i in range(len(self)):
            node = {
                "id": i,
                **{k: float(v) for k, v in zip(ATTRIBUTES, self.attributes[i])},
                "position": self.positions[i].tolist(),
                "rotation": self.rotations[i].tolist(),
            }
            if self.names and self.names[i]:
                node["name"] = self.names[i]
            nodes.append(node)
        edges = [
            {"source": i, "target": j, **{k: float(v) for k, v in zip(RELATIONS, self.relations[i, j])}}
            for i in range(len(self))
            for j in range(len(self))
            if i != j
        ]
        for e in edges:
            e["touch"] = bool(e["touch"])
        out = {"scale": float(self.scale), "nodes": nodes, "edges": edges}
        if self.shape_distribution is not None:
            out["shape_distribution"] = [float(v) for v in self.shape_distribution]
        return out

    @classmethod
    def from_json(cls, data, *, where: str = "description") -> "Description":
        """Inverse of :meth:`to_json`; raises ``ValueError`` naming ``where`` and the field."""
        if not isinstance(data, dict) or "nodes" not in data or "scale" not in data:
            raise ValueError(
                f"{where}: got {type(data).__name__}, expected an object with 'scale', 'nodes' and 'edges'"
            )
        nodes, edges = data["nodes"], data.get("edges", [])
        if not isinstance(nodes, list) or not nodes or not isinstance(edges, list):
            raise ValueError(f"{where}.nodes: got {type(nodes).__name__}, expected a non-empty list of parts")
        n = len(nodes)

        def number(value, field, shape=()):
            try:
                flag = isinstance(value, bool) and field.endswith(".touch")  # written as true/false
                a = np.asarray(value, float) if json_numbers(value) or flag else None
            except (TypeError, ValueError):
                a = None
            if a is None or a.shape != shape or not np.all(np.isfinite(a)):
                raise ValueError(
                    f"{where}.{field}: got {value!r:.60}, expected {'a finite number' if not shape else f'finite numbers of shape {shape}'}"
                )
            return a

        scale = float(number(data["scale"], "scale"))
        if scale <= 0:
            raise ValueError(f"{where}.scale: got {scale}, expected a number > 0")
        attributes = np.zeros((n, len(ATTRIBUTES)))
        positions, rotations, names = np.zeros((n, 3)), np.zeros((n, 3, 3)), []
        for i, node in enumerate(nodes):
            if not isinstance(node, dict):
                raise ValueError(f"{where}.nodes[{i}]: got {type(node).__name__}, expected an object")
            for k, key in enumerate(ATTRIBUTES):
                attributes[i, k] = number(node.get(key), f"nodes[{i}].{key}")
                positive = key.startswith(("size", "squareness"))
                if attributes[i, k] < 0 or (positive and attributes[i, k] == 0):
                    raise ValueError(
                        f"{where}.nodes[{i}].{key}: got {node.get(key)!r:.60}, expected a number {'>' if positive else '>='} 0"
                    )
            positions[i] = number(node.get("position"), f"nodes[{i}].position", (3,))
            rotations[i] = number(node.get("rotation"), f"nodes[{i}].rotation", (3, 3))
            names.append(str(node.get("name", "")))
        relations = np.zeros((n, n, len(RELATIONS)))
        for k, edge in enumerate(edges):
            if not isinstance(edge, dict):
                raise ValueError(f"{where}.edges[{k}]: got {type(edge).__name__}, expected an object")
            i, j = edge.get("source"), edge.get("target")
            if not (isinstance(i, int) and isinstance(j, int) and 0 <= i < n and 0 <= j < n and i != j):
                raise ValueError(
                    f"{where}.edges[{k}]: got source {i!r}, target {j!r}, expected two different part ids in [0, {n})"
                )
            for c, key in enumerate(RELATIONS):
                relations[i, j, c] = number(edge.get(key), f"edges[{k}].{key}")
        shape = None
        if "shape_distribution" in data:
            shape = number(data["shape_distribution"], "shape_distribution", (SHAPE_BINS,))
            if np.any(shape < 0) or not np.isclose(shape.sum(), 1.0, atol=1e-4):
                raise ValueError(
                    f"{where}.shape_distribution: got values summing to {shape.sum():.4g}, expected {SHAPE_BINS} numbers >= 0 summing to 1"
                )
            shape = shape / shape.sum()
        return cls(scale, attributes, relations, positions, rotations, tuple(names) if any(names) else (), shape)

    def graph(self):
        """The description as a ``networkx.DiGraph`` (node and edge attributes as in :meth:`to_json`)."""
        import networkx as nx

        return nx.node_link_graph(
            dict(
                self.to_json(),
                directed=True,
                multigraph=False,
                graph={
                    "scale": self.scale,
                    "shape_distribution": None if self.shape_distribution is None else self.shape_distribution.tolist(),
                },
            ),
            edges="edges",
        )


def _as_arrays(parts: Part):
    single = parts.batch_shape == ()
    get = (lambda x: np.asarray(x, float)[None]) if single else (lambda x: np.asarray(x, float))
    return (
        get(parts.size),
        get(parts.squareness),
        get(parts.bend),
        get(parts.taper).reshape(-1),
        get(parts.position),
        get(parts.orientation),
    )


def describe(parts: Part, *, names=None, touch_gap: float = TOUCH_GAP) -> Description:
    """The part-structure :class:`Description` of one figure's parts.

    Parameters
    ----------
    parts : Part
        One figure's parts (batched or single), in any frame (usually the camera's).
    names : optional sequence of str, one per part.
    touch_gap : surfaces closer than this fraction of the object's scale touch.

    Every attribute and relation is unchanged by a rigid motion of all the parts and by a
    change of units; the axes of each part are sorted by size (largest first), so that
    the same shape labelled differently by the search is described the same way.
    """
    if not isinstance(parts, Part):
        raise TypeError(f"parts: got {type(parts).__name__}, expected a sqparts.Part")
    if not (isinstance(touch_gap, (int, float)) and np.isfinite(touch_gap) and touch_gap >= 0):
        raise ValueError(f"touch_gap: got {touch_gap!r}, expected a finite number >= 0")
    size, sq, bend, taper, position, orientation = _as_arrays(parts)
    n = len(size)
    if names is not None and len(names) != n:
        raise ValueError(f"names: got {len(names)} names, expected {n} (one per part)")
    rot = _rotation_matrices(orientation)
    volume = part_volume(size, sq)
    scale = float(np.cbrt(volume.sum()))
    order = np.argsort(-size, axis=1, kind="stable")
    sorted_size = np.take_along_axis(size, order, 1)
    sorted_rot = np.take_along_axis(rot, order[:, None, :], 2)  # columns = axes, largest first
    attributes = np.column_stack(
        [
            sorted_size / scale,
            sq,
            np.abs(taper),
            np.hypot(bend[:, 0], bend[:, 1]),
            volume / volume.sum(),
        ]
    )
    samples = [surface_samples(size[i], sq[i], bend[i], taper[i], rot[i], position[i]) for i in range(n)]
    trees = [KDTree(p) for p in samples]
    relations = np.zeros((n, n, len(RELATIONS)))
    for i in range(n):
        for j in range(n):
            if i == j:
                continue
            if j < i:
                gap = relations[j, i, 1]
            else:
                gap = float(trees[i].query(samples[j], k=1)[0].min()) / scale
            offset = np.abs(sorted_rot[i].T @ (position[j] - position[i])) / scale
            cos = abs(float(sorted_rot[i][:, 0] @ sorted_rot[j][:, 0]))
            relations[i, j] = [
                float(gap < touch_gap),
                gap,
                np.linalg.norm(position[j] - position[i]) / scale,
                *offset,
                np.arccos(min(cos, 1.0)),
                np.log(volume[j] / volume[i]),
            ]
    return Description(
        scale,
        attributes,
        relations,
        position.copy(),
        sorted_rot,
        tuple(names) if names is not None else (),
        shape_distribution(parts),
        surface_cloud(parts),
    )


def describe_figures(recovery, *, names=None) -> list[Description]:
    """One :class:`Description` per figure of a :class:`~sqparts.SceneRecovery` (largest
    first), or a one-element list for a :class:`~sqparts.Recovery`."""
    figures = getattr(recovery, "figures", None) or [recovery]
    return [describe(r.parts, names=names if len(figures) == 1 else None) for r in figures]


def merged_alternatives(parts: Part, description: Description | None = None, *, limit: int = 3) -> list[Part]:
    """Other part structures recovery could also have given: each of up to ``limit``
    pairs of touching parts (smallest combined volume first) merged into one part.

    The merged part is fitted to both parts' surface samples by their moments: centre
    and axes from the samples' principal directions, semi-axes from their extents,
    squareness of the larger part, no taper or bend. Returns one batched Part per
    alternative (one part fewer than ``parts``).
    """
    d = description if description is not None else describe(parts)
    n = len(d)
    if n < 2:
        return []
    size, sq, bend, taper, position, orientation = _as_arrays(parts)
    rot = _rotation_matrices(orientation)
    pairs = [(d.volumes[i] + d.volumes[j], i, j) for i in range(n) for j in range(i + 1, n) if d.touching[i, j]]
    out = []
    for _, i, j in sorted(pairs)[:limit]:
        pts = np.concatenate([surface_samples(size[k], sq[k], bend[k], taper[k], rot[k], position[k]) for k in (i, j)])
        centre = pts.mean(0)
        _, _, vt = np.linalg.svd(pts - centre, full_matrices=False)
        axes = vt[::-1].T  # smallest variance first: largest extent on local z
        if np.linalg.det(axes) < 0:
            axes[:, 0] *= -1
        local = (pts - centre) @ axes
        lo, hi = local.min(0), local.max(0)
        centre = centre + axes @ ((lo + hi) / 2)
        half = np.maximum((hi - lo) / 2, 1e-6)
        big = i if d.volumes[i] >= d.volumes[j] else j
        merged = Part(
            size=half.astype(np.float32),
            squareness=sq[big].astype(np.float32),
            position=centre.astype(np.float32),
            orientation=np.asarray(matrix_to_rotation_vector(axes.astype(np.float32)), np.float32),
        )
        keep = [parts[k] for k in range(n) if k not in (i, j)]
        out.append(stack_parts(keep + [merged]))
    return out
