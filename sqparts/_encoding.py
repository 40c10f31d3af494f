"""The encoding: what a description of the range data costs, locally and globally.

*Local* (sections 3.2-3.3): the goodness of fit Γ = μ - λε (Eq. 4) and bits saved (Eq. 5)
of one hypothesis over a window. *Global* (section 3.5): the costs κ0..κ3 (:class:`Costs`),
the area matrices and E(X) of Eq. (6), and E counted by direct pixel count in the chosen
parts' joint rendering (:func:`encoding_cost`, :class:`EncodingCost`), and after each of a
batch of changes to them (:class:`Edit`, :func:`edit_costs`): the one evaluator of E that
selection, refinement and post-processing share.

Local encoding:

For a hypothesised part rendered over a window, R*(x, y), and the measured range data
R(x, y):

1. histogram R* - R over pixels where both exist (and the pixel is on the figure);
2. the peak p is the depth offset that aligns the part with the data, so depth need not
   be sampled; μ = number of pixels within ±σ/2 of p;
3. ε = rendered pixels that fall off the figure (errors of commission), except where
   the data shows a surface in front of the part (nearer than the window of width σ at
   p): there the part is hidden, not contradicted, so a part occluded by another figure
   (an object in front, the supporting table) pays nothing for its hidden pixels, just
   as it pays nothing where its own figure hides it (:func:`commission_mask`);
4. Γ = μ - λ ε.

**Exact peak.** Fixed bins of width σ split a peak that straddles a bin edge. We use
bins of width σ/2 and take the best *adjacent pair* (a window of width σ at any
multiple of σ/2), anchored at one pixel's own difference so that moving a part in depth
leaves Γ unchanged. A peak narrower than σ/2 is always wholly inside one pair.

**Encoding (Eq. 5).** With depth quantum q and depth range D, a raw pixel costs
b = log2(D / q) bits (8 for 8-bit data); a pixel explained within ±σ/2 costs
κ1 = log2(σ / q); a part costs κ0 = 14 parameters × ``bits_per_parameter``. Bits saved
s = -κ0 + (b - κ1) Γ, and λ = (cost of a commission error) / (b - κ1).
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from ._camera import PinholeCamera, bucket_camera, fits_float32
from ._compile import RowMemo, concurrently, persistent_jit
from ._part import Part
from ._render import DEFAULT_NEWTON_STEPS, cast_part
from ._typing import Array, Bool, Float, freeze_fields

if TYPE_CHECKING:
    from ._data import RangeData

PARAMETERS_PER_PART = 14
EDGE_FOOTPRINTS = 0.5
"""Least σ, in pixel footprints at the figure's depth (:func:`encoding_for`)."""
MIN_SAVED = 0.5
"""Least bits a part saves on each pixel it explains (:attr:`Encoding.pixel_bits`)."""


@dataclasses.dataclass(frozen=True)
class Encoding:
    """Noise model and bit costs of the minimal-length encoding (Eqs. 4-7).

    Attributes
    ----------
    sigma : float
        σ, the match tolerance: a pixel is explained if within ±σ/2 (depth units).
    quantum : float
        q, the depth resolution of the data (depth units).
    depth_range : float
        D, the depth range of the data; a raw pixel costs log2(D / q) bits.
    commission_weight : float
        λ of Eq. (4), commission cost in units of the bits an explained pixel saves.
    bits_per_parameter : float
        bits to encode one of a part's 14 parameters; κ0 = 14 × this (8 here, as for
        8-bit data; :func:`encoding_for` derives it from the pixel count).
    """

    sigma: float
    quantum: float
    depth_range: float
    commission_weight: float = 4.0
    bits_per_parameter: float = 8.0

    def __post_init__(self):
        for name in ("sigma", "quantum", "depth_range", "commission_weight", "bits_per_parameter"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.floating)) and math.isfinite(v) and v > 0 and fits_float32(v)):
                raise ValueError(f"{name}: got {v!r}, expected a finite number > 0 that float32 holds")
        if self.sigma < self.quantum:
            raise ValueError(f"sigma: got {self.sigma:.3g}, expected at least the quantum {self.quantum:.3g}")

    @property
    def pixel_bits(self) -> float:
        """b: bits of one raw range pixel, log2(D / q), but at least κ1 + ½: a figure
        shallower than σ (a plate facing the camera) would otherwise price a pixel that
        a part explains above the raw pixel, and its shortest description would be no
        part at all (the parts recovered there explained nothing)."""
        return max(math.log2(self.depth_range / self.quantum), self.noise_bits + MIN_SAVED, 1.0)

    @property
    def part_bits(self) -> float:
        """κ0: bits to describe one part."""
        return PARAMETERS_PER_PART * self.bits_per_parameter

    @property
    def noise_bits(self) -> float:
        """κ1: bits to encode a pixel's deviation from a part within ±σ/2."""
        return math.log2(self.sigma / self.quantum)

    @property
    def saved_per_pixel(self) -> float:
        """b - κ1: bits saved by each pixel a part explains (at least ½)."""
        return self.pixel_bits - self.noise_bits

    @property
    def commission_bits(self) -> float:
        """Bits charged for one error of commission: λ (b - κ1)."""
        return self.commission_weight * self.saved_per_pixel

    def bits_saved(self, gamma):
        """Eq. (5): s = -κ0 + (b - κ1) Γ."""
        return -self.part_bits + self.saved_per_pixel * gamma


def encoding_for(
    depth,
    *,
    sigma: float | None = None,
    quantum: float | None = None,
    commission_weight: float = 4.0,
    bits_per_parameter: float | None = None,
    footprint: float | None = None,
) -> Encoding:
    """The default :class:`Encoding` for a range image.

    The quantum q is the data's own depth step when it is quantised (fewer distinct
    values than a quarter of the pixels: the median gap between consecutive distinct
    depths), but never finer than D / 64: float data is treated as 6-bit data, the
    resolution of the paper's synthetic example (section 4.1). σ defaults to 4 q, the
    paper's σ = 4. Both can be given explicitly; σ bounds how far a pixel may lie from a
    part and still count as explained, so noisy sensors want a larger σ.

    **σ at edges.** Given the metric width of one pixel at the figure's depth
    (``footprint``, :meth:`~sqparts.PinholeCamera.pixel_size_at`), the default σ is at
    least ``EDGE_FOOTPRINTS`` (half) of it: where a surface turns away from the ray, at
    every silhouette, its depth changes by about a footprint across one pixel (a 45°
    slope), so a part whose outline is right to a quarter of a pixel there is within
    ±σ/2 of the data, and what a pixel reports there (its centre's depth, or a mixed one)
    is known no better. A member one or two pixels across is all edge; a nearly flat
    figure far away (the built-in gate at 20 m: depth range 0.24 m, 6-bit σ 15 mm,
    footprint 87 mm) would otherwise ask its parts for depths a sixth of a pixel's width
    apart. The built-in human, chair and castings have 6-bit σ of 1.4-4.9 footprints and
    are unchanged.

    ``bits_per_parameter`` defaults to ½ log2 N for N valid pixels (at least 2 bits): N
    pixels determine a parameter to about 1/√N of its range, and a parameter sent to
    that precision costs ½ log2 N bits (Rissanen's two-part minimum description length,
    the BIC penalty). So κ0 grows slowly with the image: 75 bits for the 1 717-pixel
    built-in human, 100 bits for a 20 000-pixel figure; 8 bits (κ0 = 112, 8-bit
    parameters for 8-bit data) is reached at 65 536 pixels.
    """
    d = np.asarray(depth, np.float64)
    d = d[np.isfinite(d)]
    if d.size < 2:
        raise ValueError(f"depth: got {d.size} valid pixels, expected at least 2")
    depth_range = float(d.max() - d.min())
    if depth_range <= 0:
        depth_range = float(abs(d.max())) * 1e-3 or 1.0
    if quantum is None:
        values = np.unique(d)
        gaps = np.diff(values)
        quantum = depth_range / 64.0
        if len(values) < d.size / 4 and gaps.size:
            quantum = max(float(np.median(gaps)), quantum)
    if sigma is None:
        sigma = 4.0 * quantum
        if footprint is not None and math.isfinite(footprint):
            sigma = max(sigma, EDGE_FOOTPRINTS * float(footprint))
    if bits_per_parameter is None:
        bits_per_parameter = max(0.5 * math.log2(d.size), 2.0)
    return Encoding(float(sigma), float(quantum), depth_range, float(commission_weight), float(bits_per_parameter))


def commission_mask(hit, rendered, measured, figure, behind):
    """Errors of commission: rendered pixels ``hit`` off the ``figure``, except where the
    data lies in front of the part, hiding it (``rendered - measured > behind``); a pixel
    with no return (NaN) hides nothing. numpy or jnp arrays."""
    xp = np if all(isinstance(a, np.ndarray) for a in (hit, rendered, measured, figure)) else jnp
    finite = xp.isfinite(measured)
    hidden = finite & (rendered - xp.where(finite, measured, 0.0) > behind)
    return hit & ~figure & ~hidden


def gamma_terms(
    rendered: Float[Array, "*pixels"],
    hit: Bool[Array, "*pixels"],
    measured: Float[Array, "*pixels"],
    figure: Bool[Array, "*pixels"],
    *,
    sigma: float,
    num_bins: int,
    weight: Float[Array, "*pixels"] | None = None,
):
    """μ, ε, the peak offset p and the explained mask for one hypothesis (Eq. 4).

    ``measured`` may hold NaN (no return); ``figure`` marks the pixels of the figure of
    interest. ``weight`` (default 1) lets a pixel subsample stand for its neighbours.
    Never raises: a hypothesis that hits nothing gets μ = 0.
    """
    hit = hit.reshape(-1)
    figure = figure.reshape(-1)
    measured = measured.reshape(-1)
    rendered = rendered.reshape(-1)
    w = jnp.ones_like(rendered) if weight is None else jnp.broadcast_to(weight, rendered.shape).reshape(-1)
    both = hit & figure & jnp.isfinite(measured)
    diff = jnp.where(both, rendered - jnp.where(both, measured, 0.0), 0.0)
    anchor = diff[jnp.argmax(both)]
    half = sigma / 2
    centre = num_bins // 2
    index = jnp.floor((diff - anchor) / half).astype(jnp.int32) + centre
    ok = both & (index >= 0) & (index < num_bins)
    counts = jnp.zeros(num_bins, rendered.dtype).at[jnp.where(ok, index, 0)].add(jnp.where(ok, w, 0.0))
    pairs = counts[:-1] + counts[1:]
    best = jnp.argmax(pairs)
    mu = pairs[best]
    lo = anchor + (best - centre) * half
    offset = lo + half  # centre of the width-σ window [lo, lo + σ)
    explained = both & (diff >= lo) & (diff < lo + sigma)
    commission = jnp.sum(jnp.where(commission_mask(hit, rendered, measured, figure, lo + sigma), w, 0.0))
    return mu, commission, offset, explained


def gamma(
    rendered,
    hit,
    measured,
    figure,
    *,
    sigma: float,
    commission_weight: float,
    num_bins: int,
    weight=None,
):
    """Γ = μ - λε (Eq. 4) for one hypothesis; see :func:`gamma_terms`."""
    mu, eps, _, _ = gamma_terms(rendered, hit, measured, figure, sigma=sigma, num_bins=num_bins, weight=weight)
    return mu - commission_weight * eps


def smooth_gamma(rendered, hit, measured, figure, offset, *, sigma: float, commission_weight: float):
    """A differentiable Γ for polishing: each pixel counts k((R* - R - p) / σ) with the
    smooth window k(x) = 1 / (1 + (2x)^8) (≈1 within ±σ/2, ≈0 beyond), at a given peak
    offset p; commission as in :func:`gamma_terms`. Differentiable in the rendered depths and p."""
    both = hit & figure & jnp.isfinite(measured)
    x = jnp.where(both, rendered - jnp.where(both, measured, 0.0) - offset, 0.0) / sigma
    k = jnp.where(both, 1.0 / (1.0 + (2.0 * x) ** 8), 0.0)
    return jnp.sum(k) - commission_weight * jnp.sum(
        commission_mask(hit, rendered, measured, figure, offset + sigma / 2)
    )


# --- the global encoding: E of a set of parts (Eq. 6) ---------------------------------


@dataclasses.dataclass(frozen=True)
class Costs:
    """κ0..κ3 of Eq. (6) in bits, and N."""

    part: float
    explained: float
    commission: float
    omission: float
    figure_pixels: int

    @classmethod
    def from_encoding(cls, encoding: Encoding, figure_pixels: int) -> "Costs":
        return cls(
            part=encoding.part_bits,
            explained=encoding.noise_bits,
            commission=encoding.commission_bits,
            omission=encoding.pixel_bits,
            figure_pixels=int(figure_pixels),
        )

    def total(self, parts, explained, commission):
        """E of Eq. (6) from counts: ``parts`` parts, ``explained`` pixels explained
        within ±σ/2 and ``commission`` pixels rendered off the figure (numbers or arrays)."""
        return (
            self.part * parts
            + self.explained * explained
            + self.commission * commission
            + self.omission * (self.figure_pixels - explained)
        )


def area_matrix(masks) -> np.ndarray:
    """M (n, n): diagonal = pixels in each mask, off-diagonal = -1/2 the shared pixels.
    Counted over the pixels some mask holds, in float32 where every count is exact
    (fewer than 2^24 of them)."""
    masks = np.asarray(masks, bool)
    m = masks.reshape(len(masks), int(np.prod(masks.shape[1:])))
    m = m[:, m.any(0)]
    m = m.astype(np.float32 if m.shape[1] < 1 << 24 else np.float64)
    overlap = (m @ m.T).astype(np.float64)
    out = -0.5 * overlap
    np.fill_diagonal(out, np.diag(overlap))
    return out


def description_length(explained, commission, costs: Costs) -> float:
    """E by direct pixel count: parts, then the union of explained and commission pixels."""
    explained = np.asarray(explained, bool)
    commission = np.asarray(commission, bool)
    n = len(explained)
    e = int(explained.any(0).sum()) if n else 0
    c = int(commission.any(0).sum()) if n else 0
    return costs.total(n, e, c)


# --- E counted in the parts' joint rendering: the one evaluator of the package -----------

PART_BUCKET = 8
"""Compiled calls over parts (rendering, polishing) take batches of this many parts."""


_PART_TREE = jax.tree_util.tree_structure(Part(size=np.ones(3, np.float32)))


def host_parts(vectors) -> Part:
    """A batch of parts with host (numpy) leaves from valid (n, 14) vectors (the order of
    :meth:`~sqparts.Part.to_vector`), built without dispatching JAX operations: slicing,
    stacking and editing them is plain numpy, and they enter compiled calls as they are."""
    v = np.asarray(vectors, np.float32)
    return jax.tree_util.tree_unflatten(
        _PART_TREE, [v[:, 0:3], v[:, 3:6], v[:, 6:9], v[:, 9:11], v[:, 11:13], v[:, 13]]
    )


def part_vectors(parts: Part) -> np.ndarray:
    """(n, 14) host copy of ``parts.to_vector()``, concatenated on the host (no round trip
    through the device: refinement calls this on every trial)."""
    *head, taper = (np.asarray(a, np.float32) for a in jax.tree_util.tree_leaves(parts))
    return np.concatenate([*head, taper[..., None]], axis=-1).reshape(-1, 14)


def pad_parts(parts: Part) -> tuple[Part, int]:
    """Pad a batch to a multiple of ``PART_BUCKET`` with parts behind the camera (never hit),
    so the compiled renderer and solver only ever see batches of ``PART_BUCKET`` parts."""
    n = len(parts)
    return host_parts(pad_vectors(part_vectors(parts), -(-n // PART_BUCKET) * PART_BUCKET)), n


def pad_vectors(vectors: np.ndarray, m: int) -> np.ndarray:
    """(n, 14) part vectors padded to ``m`` rows with a tiny part behind the camera (no
    ray ever hits it)."""
    dummy = np.array([0, 0, -1e3, 0, 0, 0, 1e-3, 1e-3, 1e-3, 1, 1, 0, 0, 0], np.float32)
    return np.concatenate([vectors, np.broadcast_to(dummy, (m - len(vectors), 14))])


TILE = 16
"""Side in pixels of the square tiles :func:`render_layers` renders a part in."""
TILE_BATCH = 64
"""Tiles per compiled call of :func:`render_layers` (64 tiles: 16 384 rays)."""


@persistent_jit(static_argnames=("newton_steps",))
def _render_tiles(parts, corners, camera, newton_steps=DEFAULT_NEWTON_STEPS):
    """Part i rendered in the ``TILE`` x ``TILE`` tile of the image whose top left pixel
    is ``corners[i]`` (row, col): the same rays as those pixels of the whole image
    (``camera`` a :class:`~sqparts._camera.CompiledCamera`)."""

    def one(part, corner):
        o, d = camera.rays((corner[0], corner[1], TILE, TILE))
        t, hit = cast_part(part, o, d, newton_steps)
        return jnp.where(hit, t, jnp.inf)

    return jax.vmap(one)(parts, corners)


def silhouette_boxes(vectors: np.ndarray, camera) -> np.ndarray:
    """(n, 4) pixel rectangles (row0, col0, row1, col1), ends exclusive, that hold the
    silhouettes of the parts with (n, 14) ``vectors``, or the whole image. A silhouette
    lies in the projection of the part's bounding box
    (:func:`~sqparts._part.bounding_half_extent`: no ray that misses the box can hit the
    part, :func:`~sqparts.cast_ray`'s first test), so in the bounding rectangle of the
    box's eight projected corners, widened by a pixel for rounding. A box that reaches
    behind a pinhole camera, or a camera without :meth:`project` (a scanner), gives the
    whole image."""
    from scipy.spatial.transform import Rotation

    from ._part import bounding_half_extent

    v = np.asarray(vectors, np.float64).reshape(-1, 14)
    n, h, w = len(v), camera.height, camera.width
    whole = np.tile(np.array([0, 0, h, w], np.int64), (n, 1))
    if n == 0 or not hasattr(camera, "project"):
        return whole
    signs = np.array([(i, j, k) for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], np.float64)
    half = np.asarray(bounding_half_extent(host_parts(v)), np.float64)
    rot = Rotation.from_rotvec(v[:, 3:6]).as_matrix()
    corners = v[:, None, 0:3] + np.einsum("nij,nkj->nki", rot, signs[None] * half[:, None])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        uv = camera.project(corners)
        ok = np.isfinite(uv).all((1, 2)) & (np.abs(uv) < 1e7).all((1, 2))
        if isinstance(camera, PinholeCamera):  # its rays start at the centre: the box in front of it
            ok &= (corners[..., 2] > 1e-6).all(1)
        uv = np.where(ok[:, None, None], uv, 0.0)
    lo = np.floor(uv.min(1)).astype(np.int64) - 1  # (n, 2): (u, v)
    hi = np.ceil(uv.max(1)).astype(np.int64) + 2
    box = np.stack(
        [np.clip(lo[:, 1], 0, h), np.clip(lo[:, 0], 0, w), np.clip(hi[:, 1], 0, h), np.clip(hi[:, 0], 0, w)], 1
    )
    return np.where(ok[:, None], box, whole)


_LAYERS = RowMemo(256 << 20)
"""Rendered depth layers by part and camera (see :class:`~sqparts._compile.RowMemo`)."""


def render_layers(vectors, camera) -> np.ndarray:
    """(k, H, W) depth of each of the (k, 14) part vectors rendered on its own (inf =
    miss); a part this camera has rendered before is looked up (:data:`_LAYERS`). A
    scene's rendering is their nearest hit (:func:`_compose`), so a trial that adds,
    replaces or removes parts re-renders only the parts it changes.

    Each part is rendered only in the ``TILE`` x ``TILE`` tiles of the image that meet
    the rectangle holding its silhouette (:func:`silhouette_boxes`), and missed
    everywhere else: the whole image's rays and depths, for work in proportion to the
    part's size in the image rather than the image's. ``TILE_BATCH`` tiles, of any
    parts, per compiled call: one program for every image and part."""
    vectors = part_vectors(host_parts(vectors))
    out = np.full((len(vectors), camera.height, camera.width), np.inf, np.float32)
    big = bucket_camera(camera)  # its image a multiple of IMAGE_BUCKET, so of TILE

    def render(todo):
        return _rendered_tiles(vectors[todo], np.arange(len(todo)), len(todo), camera, big)

    return _LAYERS.rows([RowMemo.key(camera, v) for v in vectors], out, render)


def render_nearest(vectors, owner, count: int, camera) -> np.ndarray:
    """(count, H, W) the nearest depth of each group of parts (inf = miss): group g is
    the (k, 14) part ``vectors`` whose ``owner`` is g, rendered together (a solid of
    several parts, many solids at once). The same depths as :func:`render_layers`' layers
    of a group's parts, nearest first, without holding a layer per part (a few hundred
    posed solids of ten parts each are verified at once: :func:`~sqparts._recognize.verify_poses`).
    Not looked up: posed solids seldom repeat."""
    vectors = part_vectors(host_parts(vectors))
    return _rendered_tiles(vectors, np.asarray(owner, np.int64), int(count), camera, bucket_camera(camera))


def _rendered_tiles(v: np.ndarray, owner: np.ndarray, count: int, camera, big) -> np.ndarray:
    """(count, H, W): the parts ``v`` rendered in the tiles their silhouettes meet
    (``TILE_BATCH`` tiles a compiled call, on a thread per core), each tile kept at the
    nearest of the parts of its ``owner`` that meet it; inf elsewhere."""
    box = silhouette_boxes(v, camera)
    t0, t1 = box[:, :2] // TILE, -(-box[:, 2:] // TILE)  # tile index ranges, rows and columns
    counts = np.maximum(t1 - t0, 0).prod(1)
    part = np.repeat(np.arange(len(v)), counts)
    first = np.repeat(np.cumsum(counts) - counts, counts)
    k = np.arange(len(part)) - first
    span = np.maximum(t1 - t0, 1)[part, 1]
    row, col = t0[part, 0] + k // span, t0[part, 1] + k % span
    m = -(-len(part) // TILE_BATCH) * TILE_BATCH
    parts_of_tiles = host_parts(pad_vectors(v[part], m))
    corners = pad_rows(np.stack([row, col], 1).astype(np.int32) * TILE, m)
    rows_t, cols_t = big.height // TILE, big.width // TILE
    tiles = np.empty((m, TILE, TILE), np.float32)
    compiled = camera.compiled()

    def batch(j):
        b = slice(j, j + TILE_BATCH)
        tiles[b] = np.asarray(_render_tiles(parts_of_tiles[b], corners[b], compiled))

    concurrently(batch, range(0, m, TILE_BATCH))
    tiles = tiles[: len(part)]  # the rest is padding
    key = (owner[part] * rows_t + row) * cols_t + col
    canvas = np.full((count * rows_t * cols_t, TILE, TILE), np.inf, np.float32)
    if len(key) and np.bincount(owner, minlength=count).max() > 1:  # tiles of one group meet: the nearest
        order = np.argsort(key, kind="stable")
        key, tiles = key[order], tiles[order]
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        key, tiles = key[starts], np.minimum.reduceat(tiles, starts, axis=0)
    canvas[key] = tiles
    canvas = canvas.reshape(count, rows_t, cols_t, TILE, TILE)
    return canvas.transpose(0, 1, 3, 2, 4).reshape(count, big.height, big.width)[:, : camera.height, : camera.width]


def pad_rows(a: np.ndarray, m: int) -> np.ndarray:
    """``a`` with zero rows appended up to ``m`` rows."""
    return np.concatenate([a, np.zeros((m - len(a),) + a.shape[1:], a.dtype)])


def _nearest(layers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest depth of per-part depth layers (inf = none) and the index of its layer
    (ties go to the earlier part, as in :func:`~sqparts.cast_scene`)."""
    index = np.argmin(layers, axis=0)
    return np.take_along_axis(layers, index[None], axis=0)[0], index


def _visible(depth: np.ndarray, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A nearest hit as a rendering: depth (NaN = none) and the visible part (-1 = none)."""
    hit = np.isfinite(depth)
    return np.where(hit, depth, np.nan).astype(np.float32), np.where(hit, index, -1)


def _compose(layers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of per-part depth layers: depth (NaN = none) and the visible part's
    index (-1 = none; ties go to the earlier part)."""
    return _visible(*_nearest(layers))


def render_labels(parts: Part, camera) -> tuple[np.ndarray, np.ndarray]:
    """The parts rendered together (nearest hit wins): depth (NaN = none) and the
    visible part's index (-1 = none)."""
    return _compose(render_layers(part_vectors(parts), camera))


@dataclasses.dataclass(frozen=True)
class EncodingCost:
    """E by direct pixel count for a set of parts rendered together."""

    total: float
    parts: int
    explained: int
    commission: int
    omission: int
    rendered: np.ndarray  # (H, W) float32 depth of the model, NaN = none
    labels: np.ndarray  # (H, W) visible part, -1 = none
    explained_mask: np.ndarray  # (H, W) bool
    commission_mask: np.ndarray  # (H, W) bool
    layers: np.ndarray | None = dataclasses.field(default=None, repr=False)  # (n, H, W) per-part depth, inf = miss

    def __post_init__(self):
        freeze_fields(self)


def encoding_cost(parts: Part | None, data: RangeData, costs: Costs) -> EncodingCost:
    """Render ``parts`` together and count E (Eq. 6 evaluated on the joint rendering)."""
    vectors = np.zeros((0, 14), np.float32) if parts is None else part_vectors(parts)
    return layers_cost(render_layers(vectors, data.camera), data, costs)


def layers_cost(layers: np.ndarray, data: RangeData, costs: Costs) -> EncodingCost:
    """E of the scene whose parts have the per-part depth ``layers`` (:func:`render_layers`)."""
    if len(layers) == 0:
        shape = data.image.shape
        return _count(0, np.full(shape, np.nan, np.float32), np.full(shape, -1), data, costs, layers)
    return _count(len(layers), *_compose(layers), data, costs, layers)


class Composition:
    """The nearest hit of a fixed stack of per-part depth layers (m, H, W), composed once,
    onto which one more layer at a time is put (:meth:`adding`): a trial that adds one part,
    or replaces a group of parts by one, composes one layer instead of m + 1 (the nearest
    hit's ``argmin`` over the stack is most of :func:`layers_cost`'s time)."""

    def __init__(self, layers: np.ndarray):
        self.layers = layers
        if len(layers):
            self.depth, self.index = _nearest(layers)
        else:
            self.depth, self.index = np.full(layers.shape[1:], np.inf, np.float32), np.zeros(layers.shape[1:], np.int64)

    def adding(self, layer: np.ndarray, data: RangeData, costs: Costs) -> EncodingCost:
        """:func:`layers_cost` of the stack with ``layer`` (H, W) after it: the same
        rendering, labels (ties go to the earlier part) and E."""
        m = len(self.layers)
        nearer = layer < self.depth
        visible = _visible(np.where(nearer, layer, self.depth), np.where(nearer, m, self.index))
        return _count(m + 1, *visible, data, costs, np.concatenate([self.layers, layer[None]]))


@dataclasses.dataclass(frozen=True, eq=False)
class Edit:
    """A change to a set of parts: the parts at indices ``remove`` replaced by the parts
    with (k, 14) vectors ``add``. A one-for-one replacement keeps its place; otherwise the
    other parts keep their order and the new ones follow them. ``layers``: the new parts'
    depth (k, H, W; :func:`render_layers`), once rendered (:func:`render_edits`)."""

    remove: tuple[int, ...] = ()
    add: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 14), np.float32))
    layers: np.ndarray | None = dataclasses.field(default=None, repr=False)

    def __post_init__(self):
        # Any sequence of integers (a list, a numpy array) is the same edit as its tuple.
        remove = self.remove
        items: list = np.asarray(remove, dtype=object).reshape(-1).tolist()
        if any(isinstance(i, (bool, np.bool_)) or not isinstance(i, (int, np.integer)) for i in items):
            raise ValueError(f"remove: got {remove!r}, expected a sequence of part indices (integers)")
        object.__setattr__(self, "remove", tuple(int(i) for i in items))
        add = np.asarray(self.add, np.float32)
        if add.ndim not in (1, 2) or add.shape[-1] != 14:
            raise ValueError(f"add: got shape {add.shape}, expected (k, 14) part vectors")
        object.__setattr__(self, "add", add.reshape(-1, 14))

    @property
    def in_place(self) -> bool:
        """A one-for-one replacement (parts removed and added alike): its new parts take
        the removed parts' places."""
        return len(self.remove) == len(self.add) and bool(self.remove)

    def apply(self, rows: np.ndarray, new: np.ndarray) -> np.ndarray:
        """``rows`` (one per current part: vectors or depth layers) with the edit made,
        ``new`` the added parts' rows (as many as ``add``)."""
        remove = list(self.remove)
        if self.in_place:
            out = rows.copy()
            out[remove] = new
            return out
        return np.concatenate([np.delete(rows, remove, 0), np.asarray(new, rows.dtype)])


def render_edits(edits, camera) -> list[Edit]:
    """The edits with their new parts' depth layers, all of them rendered together (one
    :func:`render_layers` call, ``TILE_BATCH`` tiles a compiled call)."""
    edits = list(edits)
    todo = [e for e in edits if e.layers is None]
    if todo:
        vectors = np.concatenate([e.add for e in todo])
        layers = render_layers(vectors, camera)
        ends = np.cumsum([0] + [len(e.add) for e in todo])
        done = {id(e): layers[a:b] for e, a, b in zip(todo, ends[:-1], ends[1:])}
        edits = [e if e.layers is not None else dataclasses.replace(e, layers=done[id(e)]) for e in edits]
    return edits


def edit_costs(cost: EncodingCost, edits, data: RangeData, costs: Costs) -> list[EncodingCost]:
    """E of the parts behind ``cost`` after each of ``edits`` in turn (Eq. 6 on the joint
    rendering): the one evaluator of every change refinement and post-processing try. Only
    the new parts are rendered, all edits' together (:func:`render_edits`); an edit that
    adds one part on top of others composes the others' nearest hit once for all edits
    that remove the same parts (:class:`Composition`)."""
    layers = layers_of(cost)
    rests: dict[tuple[int, ...], Composition] = {}
    out = []
    for e in render_edits(edits, data.camera):
        new = e.layers
        assert new is not None  # rendered above
        if len(new) == 1 and len(e.remove) != 1:
            if e.remove not in rests:
                rests[e.remove] = Composition(np.delete(layers, list(e.remove), 0))
            out.append(rests[e.remove].adding(new[0], data, costs))
        else:
            out.append(layers_cost(e.apply(layers, new), data, costs))
    return out


COUNT_PIXELS = 1 << 22
"""Most pixels :func:`edit_totals` counts in one numpy call (edits times their rectangle)."""


def edit_totals(cost: EncodingCost, edits, data: RangeData, costs: Costs) -> np.ndarray:
    """(len(edits),) E of each of ``edits`` as :func:`edit_costs` counts it, without
    keeping each edit's rendering and masks: what an accept rule ranks many edits by.
    E depends only on the nearest hit, so the edits that put one part in place of the
    same others (many steps of one part: 28 edits) are counted together on the others'
    nearest depth, taken once; and since each pixel's count depends on that pixel alone,
    only in the rectangle that their new parts cover (:func:`layer_counts`)."""
    layers = layers_of(cost)
    n = len(layers)
    edits = render_edits(edits, data.camera)
    out = np.empty(len(edits))
    groups: dict[tuple[int, ...], list[tuple[int, np.ndarray]]] = {}
    for k, e in enumerate(edits):
        assert e.layers is not None  # rendered above
        if len(e.layers) == 1:
            gone = tuple(sorted({int(i) % n for i in e.remove})) if n else ()
            groups.setdefault(gone, []).append((k, e.layers[0]))
        else:
            out[k] = layers_cost(e.apply(layers, e.layers), data, costs).total
    for gone, group in groups.items():
        ks, new = [k for k, _ in group], [layer for _, layer in group]
        rest = np.delete(layers, list(gone), 0)
        depth = rest.min(0) if len(rest) else np.full(layers.shape[1:], np.inf, np.float32)
        masks = layer_errors(depth, data)
        counts = np.array([m.sum() for m in masks])
        hit = [np.isfinite(layer) for layer in new]
        rows = np.flatnonzero(np.any([h.any(1) for h in hit], axis=0))
        cols = np.flatnonzero(np.any([h.any(0) for h in hit], axis=0))
        if len(rows) == 0:  # no new part shows: the others' counts
            out[ks] = costs.total(n - len(gone) + 1, *counts)
            continue
        box = np.s_[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
        outside = counts - np.array([m[box].sum() for m in masks])
        step = max(1, COUNT_PIXELS // depth[box].size)
        for a in range(0, len(ks), step):
            stack = np.stack([layer[box] for layer in new[a : a + step]])
            inside = np.stack(layer_counts(np.minimum(depth[box], stack), data, box), 1)
            out[ks[a : a + step]] = costs.total(n - len(gone) + 1, *(outside + inside).T)
    return out


def least_pixels(costs: Costs) -> float:
    """Explained pixels a part needs to pay for its κ0 bits."""
    return costs.part / max(costs.omission - costs.explained, 1e-9)


def pixel_errors(hit, rendered, measured, figure, sigma):
    """Explained (on the figure, within ±σ/2 of the measured depth) and commission
    (rendered off the figure and not hidden by data in front: :func:`~sqparts.commission_mask`)
    masks of rendered pixels ``hit``; numpy or jnp arrays."""
    return hit & figure & (abs(rendered - measured) <= sigma / 2), commission_mask(
        hit, rendered, measured, figure, sigma / 2
    )


def layers_of(cost: EncodingCost) -> np.ndarray:
    """``cost.layers``, which every cost from :func:`layers_cost` has."""
    if cost.layers is None:
        raise ValueError(
            "cost: got an EncodingCost without per-part layers, expected one from encoding_cost or layers_cost"
        )
    return cost.layers


def _count(n: int, rendered, labels, data: RangeData, costs: Costs, layers=None) -> EncodingCost:
    with np.errstate(invalid="ignore"):
        explained, commission = pixel_errors(labels >= 0, rendered, data.image, data.figure_region, data.encoding.sigma)
    e, c = int(explained.sum()), int(commission.sum())
    return EncodingCost(
        float(costs.total(n, e, c)),
        n,
        e,
        c,
        costs.figure_pixels - e,
        rendered.astype(np.float32),
        labels,
        explained,
        commission,
        layers,
    )


def layer_errors(depth: np.ndarray, data: RangeData, box=np.s_[:, :]) -> tuple[np.ndarray, np.ndarray]:
    """Explained and commission masks (:func:`pixel_errors`) of rendered depth
    (..., H, W) (inf = miss): one part's layer, a stack of them, or a scene's; or of the
    rectangle ``box`` (a pair of slices) of the image, ``depth`` its pixels."""
    with np.errstate(invalid="ignore"):
        return pixel_errors(np.isfinite(depth), depth, data.image[box], data.figure_region[box], data.encoding.sigma)


def layer_counts(depth: np.ndarray, data: RangeData, box=np.s_[:, :]) -> tuple[np.ndarray, np.ndarray]:
    """Explained and commission pixel counts of rendered depth (..., H, W) (inf = miss),
    or of the rectangle ``box`` of the image (:func:`layer_errors`)."""
    e, c = layer_errors(depth, data, box)
    return e.sum((-2, -1)), c.sum((-2, -1))


def part_statistics(parts: Part, data: RangeData, cost: EncodingCost) -> list[dict]:
    """Per part, in the joint rendering: visible pixels, μ (explained), ε (commission),
    Γ = μ - λε and bits saved (Eq. 5)."""
    enc = data.encoding
    out = []
    for i in range(len(parts)):
        mine = cost.labels == i
        mu = int((mine & cost.explained_mask).sum())
        eps = int((mine & cost.commission_mask).sum())
        g = mu - enc.commission_weight * eps
        out.append({"pixels": int(mine.sum()), "gamma": float(g), "bits_saved": float(enc.bits_saved(g))})
    return out
