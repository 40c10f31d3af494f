"""Local encoding: the goodness of fit Γ = μ - λε (Eq. 4) and bits saved (Eq. 5).

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

import jax.numpy as jnp
import numpy as np

from ._typing import Array, Bool, Float

PARAMETERS_PER_PART = 14
EDGE_FOOTPRINTS = 0.5
"""Least σ, in pixel footprints at the figure's depth (:func:`encoding_for`)."""


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
            if not (isinstance(v, (int, float, np.floating)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: got {v!r}, expected a finite number > 0")
        if self.sigma < self.quantum:
            raise ValueError(f"sigma: got {self.sigma:.3g}, expected at least the quantum {self.quantum:.3g}")

    @property
    def pixel_bits(self) -> float:
        """b: bits of one raw range pixel."""
        return max(math.log2(self.depth_range / self.quantum), 1.0)

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
        """b - κ1: bits saved by each pixel a part explains."""
        return max(self.pixel_bits - self.noise_bits, 0.5)

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
