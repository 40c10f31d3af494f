"""Real range data, before the search: sensor clean-up and figure/ground (paper sections 3, 4).

The stages, in order:

1. :func:`downsample`: bin a sensor-sized image (640×480) to the resolution the search
   needs, with a NaN-aware median, and the matching camera;
2. :func:`clean_range_image`: missing returns (NaN, 0, negative, inf) become NaN,
   mixed-range ("flying") pixels at depth edges and isolated outliers are removed, and
   the depth quantum is estimated;
3. :func:`figure_ground`: the paper's recipe (section 3, ref. [23]): "chop out a cube
   of data, locate the ground plane, and the remaining data is figure". Large planes that
   run off the image (table, floor, wall) are found by RANSAC and removed; what is left is
   a *rubber sheet* spanning neighbouring pixels that **tears** wherever depth jumps by
   more than ``tear`` pixel footprints, and each piece of the torn sheet is a figure.

Depth jumps are measured in *pixel footprints* (the metric width of a pixel at that
depth, :meth:`~sqparts.PinholeCamera.pixel_size_at`): a jump of ``tear`` footprints
between neighbours is a surface at atan(tear) from face-on (83° for the default 8),
steeper than any surface a sensor measures reliably, so the threshold needs no tuning per
sensor or resolution.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ._camera import Camera
from ._camera import check_range_image as _check_depth
from ._typing import freeze_fields

DEFAULT_TEAR = 8.0
"""Depth jump, in pixel footprints, that tears the rubber sheet."""


def check_positive(name: str, value, *, integer: bool = False):
    """``value``, a finite number > 0 (an integer with ``integer``; never a bool), or
    ``ValueError`` naming ``name``."""
    ok = isinstance(value, (int, np.integer)) if integer else isinstance(value, (int, float, np.number))
    ok = ok and not isinstance(value, (bool, np.bool_))
    if not ok or not math.isfinite(value) or value <= 0:
        kind = "an integer" if integer else "a finite number"
        raise ValueError(f"{name}: got {value!r}, expected {kind} > 0")
    return value


def footprint(depth, camera: Camera) -> np.ndarray:
    """Metric width of each pixel at its depth (NaN where there is no return)."""
    return np.asarray(camera.pixel_size_at(np.asarray(depth, np.float32)), np.float64)


# --- 1. resolution -------------------------------------------------------------------


def _measured_box(valid: np.ndarray) -> tuple[int, int, int, int] | None:
    """The bounding box (r0, r1, c0, c1) of the returns when they fill at least half of
    it and of the image (a sensor's image, often with a dead frame); None when they do
    not (objects rendered against nothing)."""
    rows, cols = np.nonzero(valid)
    if rows.size == 0:
        return None
    r0, r1, c0, c1 = int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1
    if valid.mean() < 0.5 or valid[r0:r1, c0:c1].mean() < 0.5:
        return None
    return r0, r1, c0, c1


def downsample(depth, camera: Camera, factor: int) -> tuple[np.ndarray, Camera]:
    """Bin ``factor`` × ``factor`` blocks to their median valid depth, cropping the image
    to a multiple of ``factor``; returns (depth, camera).

    A sensor's image (its returns fill a measured area, :func:`_measured_box`): a block
    holds a return when any of its pixels does, its dropouts filled. Objects against
    nothing (a render): a binned pixel looks along its block's central ray, which meets
    the object where it covers most of the block, so a block holds a return when at
    least half of it does (as :func:`downsample_mask`), or when it holds any and so do
    its four neighbours (dropouts inside a surface are not its outline), or when it
    holds any and no block around it is mostly covered (a member thinner than half a
    block, which would otherwise vanish). There, keeping every block with any return
    widened each silhouette by half a binned pixel a side (a box in a 640x480 render came
    back 15-20% too thick). In a sensor's image most holes are dropouts, and growing them
    changed the shared stereo mug's description for the worse (5 parts explaining 61% of
    its returns at full resolution, where 8 explain 71%).
    """
    check_positive("factor", factor, integer=True)
    d = _check_depth(depth, camera)
    cam = camera.downsampled(int(factor))
    f = int(factor)
    h, w = cam.height, cam.width
    blocks = d[: h * f, : w * f].reshape(h, f, w, f).transpose(0, 2, 1, 3).reshape(h, w, f * f)
    count = np.isfinite(blocks).sum(axis=-1)
    keep = count > 0
    if _measured_box(np.isfinite(d)) is None:
        most = 2 * count >= f * f
        cross = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], bool)
        inside = np.asarray(ndimage.binary_erosion(keep, structure=cross, border_value=1), bool)
        thin = ~np.asarray(ndimage.binary_dilation(most, structure=np.ones((3, 3), bool)), bool)
        keep = most | (keep & (inside | thin))
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            out = np.nanmedian(blocks, axis=-1)
    return np.where(keep, out, np.nan).astype(np.float32), cam


def downsample_mask(mask, factor: int) -> np.ndarray:
    """Bin a boolean mask: a block is set when at least half of it is."""
    m = np.asarray(mask, bool)
    f = int(factor)
    h, w = m.shape[0] // f, m.shape[1] // f
    return m[: h * f, : w * f].reshape(h, f, w, f).mean(axis=(1, 3)) >= 0.5


def auto_factor(shape, target: int = 160) -> int:
    """The binning factor that brings an image's longest side to about ``target``, at
    most its shortest side (a long strip keeps one row)."""
    return max(1, min(int(max(shape)) // int(target), int(min(shape))))


# --- 2. sensor clean-up --------------------------------------------------------------


def _shifted(a: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """out[i, j] = a[i + dy, j + dx], NaN outside the image."""
    out = np.full_like(a, np.nan)
    h, w = a.shape
    ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
    xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
    out[yd, xd] = a[ys, xs]
    return out


def flying_pixels(depth, camera: Camera, *, tear: float = DEFAULT_TEAR) -> np.ndarray:
    """Mixed-range ("flying") pixels: a return that lies *between* two surfaces across a
    depth edge, as sensors report where a pixel sees both. A pixel is flagged when, along
    a row, column or diagonal, its two neighbours straddle it, each more than ``tear``/2
    footprints away, and each of those gaps is more than twice the step between that
    neighbour and the next one out: the surfaces either side are continuous and the pixel
    belongs to neither (a steep ramp, where every step is alike, is not flagged)."""
    check_positive("tear", tear)
    d = _check_depth(depth, camera)
    thr = footprint(d, camera) * tear
    out = np.zeros(d.shape, bool)
    with np.errstate(invalid="ignore"):
        for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
            a, b = _shifted(d, -dy, -dx), _shifted(d, dy, dx)
            a2, b2 = _shifted(d, -2 * dy, -2 * dx), _shifted(d, 2 * dy, 2 * dx)
            ga, gb = np.abs(d - a), np.abs(b - d)
            sa, sb = np.nan_to_num(np.abs(a - a2)), np.nan_to_num(np.abs(b2 - b))
            between = (d - np.fmin(a, b) > 0) & (np.fmax(a, b) - d > 0)
            out |= between & (ga > thr / 2) & (gb > thr / 2) & (ga > 2 * sa) & (gb > 2 * sb)
    return out & np.isfinite(d)


def torn_components(depth, camera: Camera, mask=None, *, tear: float = DEFAULT_TEAR) -> np.ndarray:
    """The rubber sheet: 4-neighbours in ``mask`` (default: every return) are joined
    unless their depths differ by more than ``tear`` footprints; returns the labels of
    the pieces (0, 1, ... by decreasing size; -1 outside the mask)."""
    check_positive("tear", tear)
    d = _check_depth(depth, camera)
    m = np.isfinite(d) if mask is None else (np.asarray(mask, bool) & np.isfinite(d))
    h, w = d.shape
    thr = footprint(d, camera) * tear
    idx = np.arange(h * w).reshape(h, w)
    rows, cols = [], []
    with np.errstate(invalid="ignore"):
        for sa, sb in (
            ((slice(None), slice(0, -1)), (slice(None), slice(1, None))),
            ((slice(0, -1), slice(None)), (slice(1, None), slice(None))),
        ):
            joined = m[sa] & m[sb] & (np.abs(d[sa] - d[sb]) <= np.fmin(thr[sa], thr[sb]))
            rows.append(idx[sa][joined])
            cols.append(idx[sb][joined])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(h * w, h * w))
    _, lab = connected_components(graph, directed=False)
    lab = lab.reshape(h, w)
    out = np.full((h, w), -1, np.int64)
    if m.any():
        ids, counts = np.unique(lab[m], return_counts=True)
        order = ids[np.argsort(-counts, kind="stable")]
        remap = np.full(lab.max() + 1, -1)
        remap[order] = np.arange(len(order))
        out[m] = remap[lab[m]]
    return out


JOIN_GAP = 2
"""Widest run of pixels without a return across which :func:`joined_pieces` still finds
two pieces touching (the flying pixels that clean-up removes along an occluding edge)."""


def joined_pieces(pieces: np.ndarray, depth, camera: Camera, *, apart=()) -> np.ndarray:
    """Pieces of the rubber sheet (``pieces``: :func:`torn_components` labels) that one
    object's own occlusions tore apart, joined again: two pieces that touch in the image
    (4-neighbours, or across at most :data:`JOIN_GAP` pixels without a return along a
    row or column) are one when the least depth jump between them is less than the 3-D
    extent of the smaller of them (the diagonal of its points' bounding box): an arm in
    front of the torso, a mug's handle before its body, a plate seen so nearly edge-on
    that its surface tears. An object that stands farther behind another than its own
    size stays apart; one beside another, nearer than that, does not (the Kinect frame's
    laptop and box: a jump of a fifth of the box's size, as a mug's handle or a plate's
    torn strips show), so it is for views of one object. Joins chain: a piece joined
    to two others joins them. The pieces ``apart`` (labels) are never joined
    (background running off the image). Returns the labels of the joined pieces (0, 1,
    ... by decreasing size; -1 where ``pieces`` is)."""
    d = _check_depth(depth, camera).astype(np.float64)
    pieces = np.array(pieces, np.int64)
    if pieces.shape != d.shape:
        raise ValueError(f"pieces: got shape {pieces.shape}, expected the depth's {d.shape}")
    n = int(pieces.max()) + 1 if pieces.size else 0
    if n < 2:
        return pieces
    pts = np.asarray(camera.points(d.astype(np.float32)), np.float64)
    flat = pieces.reshape(-1)
    inside = flat >= 0
    lo = np.full((n, 3), np.inf)
    hi = np.full((n, 3), -np.inf)
    np.minimum.at(lo, flat[inside], pts.reshape(-1, 3)[inside])
    np.maximum.at(hi, flat[inside], pts.reshape(-1, 3)[inside])
    extent = np.linalg.norm(hi - lo, axis=1)
    extent[[int(i) for i in apart]] = -np.inf
    empty = ~np.isfinite(d)
    a_all, b_all, j_all = [], [], []
    for axis in (0, 1):
        lab, dep = (pieces, d) if axis == 1 else (pieces.T, d.T)
        gap: np.ndarray = empty if axis == 1 else empty.T
        between = np.ones(lab[:, :-1].shape, bool)  # every pixel between the pair has no return
        for k in range(1, JOIN_GAP + 2):
            a, b = lab[:, :-k], lab[:, k:]
            if k > 1:
                between = between[:, :-1] & gap[:, k - 1 : -1]
            m = (a >= 0) & (b >= 0) & (a != b) & between
            a_all.append(np.minimum(a[m], b[m]))
            b_all.append(np.maximum(a[m], b[m]))
            j_all.append(np.abs(dep[:, :-k] - dep[:, k:])[m])
    a, b, jump = np.concatenate(a_all), np.concatenate(b_all), np.concatenate(j_all)
    parent = np.arange(n)

    def root(k):
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    if len(a):
        key = a * n + b
        order = np.lexsort((jump, key))
        first = np.ones(len(order), bool)
        first[1:] = key[order][1:] != key[order][:-1]
        for i, k, j in zip(a[order][first], b[order][first], jump[order][first]):  # each touching pair's least jump
            if j < min(extent[i], extent[k]):
                parent[root(i)] = root(k)
    groups = np.array([root(k) for k in range(n)])
    out = np.full(pieces.shape, -1, np.int64)
    ids, counts = np.unique(groups[flat[inside]], return_counts=True)
    rank = np.full(n, -1)
    rank[ids[np.argsort(-counts, kind="stable")]] = np.arange(len(ids))
    out.reshape(-1)[inside] = rank[groups[flat[inside]]]
    return out


def estimate_quantum(depth) -> float | None:
    """The depth step of quantised data (median gap between consecutive distinct depths
    when they are fewer than a quarter of the returns), or None for continuous data."""
    v = np.asarray(depth, np.float64)
    v = v[np.isfinite(v)]
    values = np.unique(v)
    if v.size < 8 or len(values) >= v.size / 4 or len(values) < 2:
        return None
    return float(np.median(np.diff(values)))


def estimate_noise(depth) -> float:
    """Robust standard deviation of the sensor's depth noise: the median absolute
    deviation of d[i] - (d[i-1] + d[i+1]) / 2 along rows and columns (zero on any plane
    seen face-on or not), scaled by 1.4826 / sqrt(1.5) for Gaussian noise. Depth edges are
    rare enough not to move the median."""
    d = np.asarray(depth, np.float64)
    second = np.concatenate(
        [(d[:, 1:-1] - 0.5 * (d[:, :-2] + d[:, 2:])).ravel(), (d[1:-1] - 0.5 * (d[:-2] + d[2:])).ravel()]
    )
    second = second[np.isfinite(second)]
    if second.size < 16:
        return 0.0
    return float(1.4826 * np.median(np.abs(second - np.median(second))) / math.sqrt(1.5))


@dataclasses.dataclass(frozen=True)
class CleanedRange:
    """What :func:`clean_range_image` did.

    Attributes
    ----------
    depth : (H, W) float32, NaN where there is no (trusted) return.
    missing : pixels that had no return on input (NaN, 0, negative or inf).
    flying : mask of mixed-range pixels removed.
    outliers : mask of isolated returns removed (pieces of the rubber sheet smaller than
        ``min_pixels``).
    quantum : the data's depth step, or None when continuous.
    noise : robust standard deviation of the depth noise (:func:`estimate_noise`).
    """

    depth: np.ndarray
    missing: int
    flying: np.ndarray
    outliers: np.ndarray
    quantum: float | None
    noise: float = 0.0

    def __post_init__(self):
        freeze_fields(self)

    def summary(self) -> str:
        q = "continuous" if self.quantum is None else f"quantum {self.quantum:.3g}"
        return (
            f"{self.missing} missing, {int(self.flying.sum())} flying and {int(self.outliers.sum())} "
            f"outlier pixels removed; {q}; noise {self.noise:.3g}"
        )


def check_depth_range(depth_range) -> tuple[float, float]:
    """``depth_range`` as (near, far) floats, finite (settings are written to
    ``parts.json``), with 0 <= near < far."""
    try:
        near, far = (float(x) for x in depth_range)
    except (TypeError, ValueError):
        near = far = np.nan
    if not (0 <= near < far < np.inf):
        raise ValueError(f"depth_range: got {depth_range!r}, expected (near, far), finite, with 0 <= near < far")
    return near, far


def crop_depth_range(depth, depth_range: tuple[float, float] | None) -> np.ndarray:
    """Drop returns outside ``depth_range`` (near, far; the paper's "cube of data")."""
    d = np.asarray(depth)
    if depth_range is None:
        return d
    near, far = check_depth_range(depth_range)
    with np.errstate(invalid="ignore"):
        return np.where((d >= near) & (d <= far), d, np.nan).astype(d.dtype)


def clean_range_image(
    depth,
    camera: Camera,
    *,
    tear: float = DEFAULT_TEAR,
    min_pixels: int = 4,
    depth_range: tuple[float, float] | None = None,
) -> CleanedRange:
    """Clean a sensor's range image: missing returns to NaN, drop returns outside
    ``depth_range`` (near, far), remove flying pixels (:func:`flying_pixels`) and
    isolated outliers (pieces of the rubber sheet under ``min_pixels``)."""
    check_positive("min_pixels", min_pixels, integer=True)
    raw = np.asarray(depth, np.float64)
    d = _check_depth(raw, camera)
    missing = int((~np.isfinite(d)).sum())
    d = crop_depth_range(d, depth_range)
    quantum = estimate_quantum(d)
    flying = flying_pixels(d, camera, tear=tear)
    d = np.where(flying, np.nan, d)
    labels = torn_components(d, camera, tear=tear)
    sizes = np.bincount(labels[labels >= 0], minlength=1)
    small = (labels >= 0) & (sizes[np.maximum(labels, 0)] < min_pixels)
    d = np.where(small, np.nan, d)
    return CleanedRange(d.astype(np.float32), missing, flying, small, quantum, estimate_noise(d))


# --- holes: free space or missing data -----------------------------------------------


HOLE_POLICIES = ("auto", "free", "missing")
"""What a pixel with no return means (:func:`missing_returns`)."""
DROPOUT_WIDTH = 3
"""Widest sensor dropout, in pixel footprints: a no-return hole that holds a disc wider
than this is free space under the ``"auto"`` hole policy."""


def check_holes(holes) -> str:
    """``holes`` checked: one of :data:`HOLE_POLICIES`."""
    if not (isinstance(holes, str) and holes in HOLE_POLICIES):
        raise ValueError(f"holes: got {holes!r}, expected one of {', '.join(map(repr, HOLE_POLICIES))}")
    return holes


def missing_returns(depth, camera: Camera, figure, *, holes: str = "auto", tear: float = DEFAULT_TEAR) -> np.ndarray:
    """The pixels without a return that are *missing data* for ``figure`` (its pixels
    with a return); every other pixel without a return is *free space*.

    A pixel with no return says something: on a synthetic render, or where a scanner
    sees the sky, there is nothing along its ray, and a part drawn there is an error of
    commission; on a real sensor a small hole may be a dropout (a specular spot, a dark
    patch), which says nothing, and a part drawn there is neither explained nor an error.
    Only no-return pixels inside the figure's outline (enclosed by its returns,
    4-connected) can be missing; a no-return region that reaches the image border, or
    the image frame's no-return area beyond the outline, is free space under every policy.

    ``holes``:

    - ``"free"``: every pixel without a return is free space (nothing is missing);
    - ``"missing"``: every enclosed no-return pixel is missing data;
    - ``"auto"``: each enclosed hole (a 4-connected piece of the outline's interior that
      is not the figure) is free space when a return farther than the figure around it
      (by more than ``tear`` pixel footprints) is seen through it, or when its no-return
      pixels hold a disc more than :data:`DROPOUT_WIDTH` footprints wide (a pixel is one
      footprint at its own depth, so this needs no metric threshold); the rest, small
      interior holes, are missing data.

    **Mixed pixels.** Except under ``"free"``, the pixels without a return that touch
    the figure's returns (8-neighbours) are missing data too: a sensor's pixel is a
    footprint, not a point, and one that the silhouette crosses sees the figure and what
    lies beyond at once (it reports nothing, or a mixed depth that clean-up removes), so
    the silhouette is known to a pixel and a part that overlaps it by less than one
    pays nothing for that. A member two pixels across is all edge: without this, a part
    a fraction of a pixel too wide would pay commission along its whole length.

    Returns an (H, W) bool mask of pixels without a return.
    """
    check_holes(holes)
    d = _check_depth(depth, camera)
    valid = np.isfinite(d)
    piece = np.asarray(figure, bool) & valid
    if piece.shape != d.shape:
        raise ValueError(f"figure: got shape {piece.shape}, expected {d.shape}")
    if holes == "free":
        return np.zeros(d.shape, bool)
    rim = np.asarray(ndimage.binary_dilation(piece, structure=np.ones((3, 3), bool)), bool) & ~valid
    inside = np.asarray(ndimage.binary_fill_holes(piece), bool) & ~piece
    if holes == "missing":
        return (inside & ~valid) | rim
    if not inside.any():
        return rim
    labels, count = ndimage.label(inside)  # pyright: ignore[reportGeneralTypeIssues]
    width = np.asarray(ndimage.distance_transform_edt(inside & ~valid))  # to the nearest return or edge
    size = footprint(d, camera)
    missing = np.zeros(d.shape, bool)
    for k in range(1, count + 1):
        hole = labels == k
        gap = hole & ~valid
        if not gap.any():
            continue
        if 2 * float(width[gap].max()) - 1 > DROPOUT_WIDTH:
            continue  # too wide for a dropout: free space
        seen = hole & valid
        if seen.any():
            around = np.asarray(ndimage.binary_dilation(hole, structure=np.ones((3, 3), bool)), bool) & piece
            near = float(np.median(d[around])) if around.any() else float(np.median(d[piece]))
            if np.any(d[seen] - near > tear * size[seen]):
                continue  # a farther surface is seen through it: free space
        missing |= gap
    return missing | rim


def pruning_stride(figure, least_pixels: float, *, largest: int = 4) -> int:
    """The largest pruning stride (every stride-th row and column scored first, at most
    ``largest``) that still sees every member of ``figure`` able to pay for a part: the
    largest s such that fewer than ``least_pixels`` (the pixels a part needs to pay for
    its κ0 bits) of the figure's pixels go unseen by an s-lattice. A pixel is seen when,
    wherever the lattice lies, one of its points falls on the figure within s - 1 steps
    of it through the figure (8-connected): the figure's pixels that near hold all s²
    residues of (row, column) modulo s. A member s pixels across is always seen (an s ×
    s square holds every residue), and so is a slanted bar narrower than that (a bar
    3.6 pixels across at 45° meets every 4-lattice) and the staircase edge of a slanted
    outline, which an opening by the square would trim; a bar of fewer rows than s
    along the rows is not (some offsets of the lattice miss it), nor is a thin member
    beside a wider one across the background."""
    fig = np.asarray(figure, bool)
    rows, cols = np.indices(fig.shape)
    step = np.ones((3, 3), bool)
    for s in range(int(largest), 1, -1):
        seen, row_res, col_res = fig.copy(), rows % s, cols % s
        for residue in range(s * s):
            on = fig & (row_res == residue // s) & (col_res == residue % s)
            seen &= np.asarray(ndimage.binary_dilation(on, structure=step, iterations=s - 1, mask=fig), bool)
        if (fig & ~seen).sum() < least_pixels:
            return s
    return 1


# --- 3. figure / ground --------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Plane:
    """The plane n·x + offset = 0 with unit normal n on the camera's side (the camera
    centre has positive distance)."""

    normal: np.ndarray
    offset: float

    def distance(self, points) -> np.ndarray:
        """Signed distance of points (..., 3), positive on the camera's side."""
        return np.asarray(points, np.float64) @ self.normal + self.offset

    def to_json(self) -> dict:
        return {"normal": [float(x) for x in self.normal], "offset": float(self.offset)}


def fit_plane(
    points, *, threshold: float, iterations: int = 256, sample: int = 4096, seed: int = 0, triples=None
) -> tuple[Plane, np.ndarray]:
    """RANSAC plane through points (N, 3), refitted by least squares to its inliers
    (distance ≤ ``threshold``); returns (plane, inlier mask). Deterministic for a seed.
    The candidate planes pass through ``iterations`` random triples of the points, or
    through the given ``triples`` (k, 3) of indices into them."""
    check_positive("threshold", threshold)
    p = np.asarray(points, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 3:
        raise ValueError(f"points: got {p.shape}, expected at least 3 points of shape (N, 3)")
    rng = np.random.default_rng(seed)
    test = p if len(p) <= sample else p[rng.choice(len(p), sample, replace=False)]
    n, off = _planes_through(p[rng.integers(0, len(p), (iterations, 3)) if triples is None else np.asarray(triples)])
    if len(n) == 0:
        raise ValueError("points: got collinear samples, expected points spanning a plane")
    score = (np.abs(test @ n.T + off) <= threshold).sum(axis=0)
    best = int(np.argmax(score))
    normal, offset = n[best], off[best]
    for _ in range(2):  # least-squares refit on the inliers
        inl = np.abs(p @ normal + offset) <= threshold
        if inl.sum() < 3:
            break
        c = p[inl].mean(axis=0)
        _, _, vt = np.linalg.svd(p[inl] - c, full_matrices=False)
        normal = vt[-1]
        offset = -normal @ c
    if offset < 0:  # the camera centre (origin) on the positive side
        normal, offset = -normal, -offset
    plane = Plane(normal / np.linalg.norm(normal), float(offset))
    return plane, np.abs(plane.distance(p)) <= threshold


def _planes_through(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals and offsets of the planes through point triples (k, 3, 3), leaving
    out collinear ones."""
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12
    n = n[ok] / norm[ok, None]
    return n, -np.einsum("ij,ij->i", n, tri[ok, 0])


def _frame_triples(rest: np.ndarray, frame: np.ndarray, *, iterations: int = 256, seed: int = 0) -> np.ndarray | None:
    """(k, 3) indices into the returns ``rest`` (in ``np.nonzero`` order) of local
    triples, each a pixel on the ``frame`` and two more within a sixth of the image of it:
    a background plane's candidates run off the image, and local triples lie on one
    surface far more often than random ones (a frame alone, nearly a line along one
    edge, would leave the plane's tilt to chance)."""
    index = np.full(rest.shape, -1, np.int64)
    index[rest] = np.arange(int(rest.sum()))
    seeds = np.argwhere(rest & frame)
    if len(seeds) == 0:
        return None
    h, w = rest.shape
    radius = max(3, min(h, w) // 6)
    rng = np.random.default_rng(seed)
    out = []
    for r, c in seeds[rng.integers(0, len(seeds), iterations)]:
        rr = np.clip(r + rng.integers(-radius, radius + 1, 32), 0, h - 1)
        cc = np.clip(c + rng.integers(-radius, radius + 1, 32), 0, w - 1)
        near = np.unique(index[rr, cc])
        near = near[(near >= 0) & (near != index[r, c])]
        if len(near) >= 2:
            out.append([index[r, c], *rng.choice(near, 2, replace=False)])
    return np.asarray(out, np.int64) if out else None


def _outer_frame(valid: np.ndarray, width: int = 3) -> np.ndarray:
    """Returns within ``width`` pixels of the edge of the measured area
    (:func:`_measured_box`), or of the image when there is none (an object rendered
    against nothing touches no frame)."""
    out = np.zeros(valid.shape, bool)
    if not valid.any():
        return out
    r0, r1, c0, c1 = _measured_box(valid) or (0, valid.shape[0], 0, valid.shape[1])
    out[r0:r1, c0:c1] = True
    out[r0 + width : r1 - width, c0 + width : c1 - width] = False
    return out & valid


def _object_face(
    dist: np.ndarray,
    inliers: np.ndarray,
    rest: np.ndarray,
    depth: np.ndarray,
    camera: Camera,
    *,
    threshold: float,
    least: int,
    tear: float,
    against_nothing: bool,
) -> bool:
    """Whether a plane through ``inliers`` (``dist``: every pixel's signed distance from
    it, positive on the camera's side) is the face of an object rather than background.
    Background carries or stands behind the figures: at least ``least``/2 of the returns
    ``rest`` within 3 pixels of it lie in front of it (more than ``threshold``; the
    camera sees the inside of a room, a table or a floor, whose other surfaces stand in
    front). Without those, the plane is a face when as many lie behind it on the same
    piece of the rubber sheet (:func:`torn_components`; the camera sees the outside of a
    convex body, whose other faces turn away behind the face it shows), or when the
    returns are objects ``against_nothing`` (no measured area, :func:`_measured_box`):
    there no plane is needed to part a figure from its surroundings. A face cut by the
    image's edge runs off the image as a table does; taken for the ground, it would drop
    its object and everything beyond it."""
    ring = rest & ~inliers & np.asarray(ndimage.binary_dilation(inliers, iterations=3), bool)
    if 2 * int((ring & (dist > threshold)).sum()) >= least:
        return False
    if against_nothing:
        return True
    sheet = torn_components(depth, camera, rest, tear=tear)
    joined = np.isin(sheet, np.unique(sheet[inliers & (sheet >= 0)])) & (sheet >= 0)
    return 2 * int((ring & joined & (dist < -threshold)).sum()) >= least


@dataclasses.dataclass(frozen=True)
class FigureGround:
    """What :func:`figure_ground` found.

    Attributes
    ----------
    figures : tuple of (H, W) bool masks, largest first. A mask may include pixels with no
        return inside the figure's outline that the hole policy calls missing data
        (:func:`missing_returns`): those are neither explained nor errors of commission.
    planes : the background planes removed (table, floor, wall), largest first.
    ground : the supporting plane (the removed plane whose normal points most nearly up
        in the image, -y), or None.
    background : (H, W) bool, returns assigned to planes or behind them.
    labels : (H, W) int, figure index per pixel, -1 = none.
    joinable : pieces that :func:`joined_pieces` would join, where ``join`` did not: per
        group that holds two or more figures, (the indices of those figures, the union
        of their masks), for :func:`~sqparts.recover_scene` to decide by description
        length whether they are one object.
    """

    figures: Sequence
    planes: Sequence
    ground: Plane | None
    background: np.ndarray
    labels: np.ndarray
    joinable: Sequence = ()

    def __post_init__(self):
        freeze_fields(self)

    @property
    def up(self) -> np.ndarray | None:
        """Gravity's "up" in the camera frame: the ground plane's normal, or None."""
        return None if self.ground is None else self.ground.normal


def figure_ground(
    depth,
    camera: Camera,
    *,
    planes: int = 3,
    plane_threshold: float | None = None,
    min_plane_fraction: float = 0.1,
    tear: float = DEFAULT_TEAR,
    min_pixels: int | None = None,
    max_figures: int | None = None,
    max_height: float | None = None,
    max_border_fraction: float = 0.15,
    holes: str = "auto",
    join: bool = False,
    seed: int = 0,
) -> FigureGround:
    """Separate figures from ground.

    Up to ``planes`` background planes are removed (a table or floor and the two walls
    of a corner): each is the RANSAC plane of the remaining returns through local triples
    that start on the outer frame of the measured area (a table, floor or wall runs off
    the image), kept if it holds at least ``min_plane_fraction`` of the remaining returns
    and 5% of the frame, and is not an object's face (:func:`_object_face`: the returns
    it joins turn away behind it, none stand in front). Returns within
    ``plane_threshold`` (default: 1% of the median depth, at least 3 depth quanta) of a
    plane, or below the ground plane, are background; with ``max_height`` so is everything farther than that above the ground
    (the paper's "cube of data"). The rest is torn into pieces at depth discontinuities
    (:func:`torn_components`), with ``join`` the pieces one object's own occlusions tore
    apart joined again (:func:`joined_pieces`; two objects side by side, a laptop and
    a box on a table, pass the same test, so it is for a view of one object; without
    it, the groups it would join are named in ``joinable``, for
    :func:`~sqparts.recover_scene` to decide by description length), and the pieces of
    at least ``min_pixels`` (default: 0.25% of the returns, at least 16) are the
    figures, except, once a plane is removed, a piece with more than
    ``max_border_fraction`` of its returns on the outer frame of the measured area (a
    band 1/40 of the image's shorter side wide, at least 3 pixels): that is background
    running off the image, like the planes (a wall's edge where two planes meet, a
    cable, the end of a shelf), not an object; 1 keeps such pieces. ``max_figures``
    keeps the largest figures. Each figure's mask also holds the pixels without a return
    that ``holes`` (:func:`missing_returns`) calls missing data: neither explained nor
    errors of commission; a part drawn on any other pixel without a return pays
    commission there.
    """
    d = _check_depth(depth, camera)
    check_holes(holes)
    if not (isinstance(planes, (int, np.integer)) and planes >= 0):
        raise ValueError(f"planes: got {planes!r}, expected an integer >= 0")
    if not isinstance(join, bool):
        raise ValueError(f"join: got {join!r}, expected True or False")
    if not (0 < min_plane_fraction <= 1):
        raise ValueError(f"min_plane_fraction: got {min_plane_fraction!r}, expected a number in (0, 1]")
    valid = np.isfinite(d)
    if valid.sum() < 16:
        raise ValueError(f"depth: got {int(valid.sum())} returns, expected at least 16")
    if plane_threshold is None:
        q = estimate_quantum(d) or 0.0
        plane_threshold = max(0.01 * float(np.median(d[valid])), 3 * q)
    check_positive("plane_threshold", plane_threshold)
    if min_pixels is None:
        min_pixels = max(16, int(0.0025 * valid.sum()))
    check_positive("min_pixels", min_pixels, integer=True)
    if not (isinstance(max_border_fraction, (int, float, np.integer, np.floating)) and 0 <= max_border_fraction <= 1):
        raise ValueError(f"max_border_fraction: got {max_border_fraction!r}, expected a number in [0, 1]")
    pts = camera.points(d)
    frame = _outer_frame(valid)
    sparse = _measured_box(valid) is None  # objects against nothing
    background = np.zeros(d.shape, bool)
    found = []
    for _ in range(int(planes)):
        rest = valid & ~background
        if rest.sum() < 16:
            break
        if (rest & frame).sum() < 3:
            break
        triples = _frame_triples(rest, frame, seed=seed + len(found))
        if triples is None or len(_planes_through(pts[rest][triples])[0]) == 0:  # e.g. one row: no plane
            break
        plane, _ = fit_plane(pts[rest], threshold=plane_threshold, seed=seed + len(found), triples=triples)
        with np.errstate(invalid="ignore"):
            dist = plane.distance(pts)
            inl = rest & (np.abs(dist) <= plane_threshold)
        if inl.sum() < min_plane_fraction * rest.sum() or (inl & frame).sum() < 0.05 * frame.sum():
            break
        if _object_face(
            dist, inl, rest, d, camera, threshold=plane_threshold, least=min_pixels, tear=tear, against_nothing=sparse
        ):
            break
        found.append(plane)
        background |= inl
        ground = max(found, key=lambda p: -p.normal[1])
        with np.errstate(invalid="ignore"):  # what lies below the ground is not figure either
            background |= valid & (ground.distance(pts) <= plane_threshold)
    ground = max(found, key=lambda p: -p.normal[1]) if found else None
    if ground is not None and max_height is not None:
        check_positive("max_height", max_height)
        with np.errstate(invalid="ignore"):
            background |= valid & (ground.distance(pts) > max_height)
    keep = valid & ~background
    if found:  # one-pixel slivers the planes leave along the objects' bases go; a dropout's neighbours stay
        opened = np.asarray(ndimage.binary_opening(keep, structure=np.ones((2, 2), bool)), bool)
        keep &= opened | ~np.asarray(ndimage.binary_dilation(background, structure=np.ones((3, 3), bool)), bool)
    pieces = torn_components(d, camera, keep, tear=tear)
    border = _outer_frame(valid, width=max(3, min(d.shape) // 40)) if found and max_border_fraction < 1 else None

    def running_off(pieces, sizes):  # the pieces that are background running off the image
        if border is None:
            return np.zeros(len(sizes), bool)
        on = np.bincount(pieces[(pieces >= 0) & border], minlength=len(sizes))
        return on > max_border_fraction * sizes

    sizes = np.bincount(pieces[pieces >= 0], minlength=1)
    # background running off the image is judged alone, not joined to what it touches
    joined = joined_pieces(pieces, d, camera, apart=np.flatnonzero(running_off(pieces, sizes)))
    if join:
        pieces = joined
        sizes = np.bincount(pieces[pieces >= 0], minlength=1)
    off = running_off(pieces, sizes)
    figures, kept = [], []
    labels = np.full(d.shape, -1, np.int64)
    for i in np.flatnonzero(sizes >= min_pixels):
        if max_figures is not None and len(figures) >= max_figures:
            break
        if off[i]:
            continue
        piece = pieces == i
        mask = piece | missing_returns(d, camera, piece, holes=holes, tear=tear)
        labels[mask & (labels < 0)] = len(figures)
        figures.append(mask)
        kept.append(i)
    joinable = []
    if not join:  # each group of joined pieces that holds two figures or more
        group = np.full(len(sizes), -1, np.int64)
        group[pieces[pieces >= 0]] = joined[pieces >= 0]
        for g in np.unique(group[kept]) if kept else ():
            members = tuple(k for k, i in enumerate(kept) if group[i] == g)
            if len(members) > 1:  # the figures' own pixels: smaller pieces joined to them are not
                joinable.append((members, np.any([figures[k] for k in members], 0)))
    return FigureGround(figures, found, ground, background, labels, tuple(joinable))
