"""Joint refinement of the chosen parts (paper sections 3.5 and 4.1).

All chosen parts are rendered together (so occlusion is fully accounted for) and the
encoding cost of the whole image is computed by direct pixel count,

    E = κ0 n + κ1 |explained| + κ2 |commission| + κ3 (N - |explained|),

with the costs of :class:`~sqparts._select.Costs`. Each round assigns every figure pixel
to the part visible there, polishes all parts at once (optimistix Levenberg-Marquardt on
the inside-outside residuals of their pixels, batched over parts) and keeps a change only
if E falls, like the paper's accept-if-improved descent. Then a part that no longer pays
for its bits is dropped, and two adjacent parts are merged when one bent part encodes
them more cheaply.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._part import Part, stack_parts, surface_distance
from ._render import DEFAULT_NEWTON_STEPS, cast_scene
from ._search import RangeData, polish_part
from ._select import Costs

_BUCKET = 8


def _pad_parts(parts: Part) -> tuple[Part, int]:
    """Pad a batch to a multiple of ``_BUCKET`` with parts behind the camera (never hit),
    so the compiled renderer and solver only ever see batches of ``_BUCKET`` parts."""
    n = len(parts)
    m = -(-n // _BUCKET) * _BUCKET
    dummy = np.array([0, 0, -1e3, 0, 0, 0, 1e-3, 1e-3, 1e-3, 1, 1, 0, 0, 0], parts.size.dtype)
    vectors = np.concatenate([np.asarray(parts.to_vector()), np.broadcast_to(dummy, (m - n, 14))])
    # Host (numpy) leaves: slicing buckets off them compiles nothing.
    return jax.tree_util.tree_map(np.asarray, Part.from_vector(vectors)), n


@functools.partial(jax.jit, static_argnames=("camera", "newton_steps"))
def _render_labels(parts, camera, newton_steps=DEFAULT_NEWTON_STEPS):
    o, d = camera.rays()
    t, hit, index = cast_scene(parts, o, d, newton_steps)
    return jnp.where(hit, t, jnp.inf), index


def render_labels(parts: Part, camera) -> tuple[np.ndarray, np.ndarray]:
    """The parts rendered together (nearest hit wins): depth (NaN = none) and the
    visible part's index (-1 = none). Rendered ``_BUCKET`` parts at a time (one
    compilation for any number of parts) and merged by depth."""
    padded, _ = _pad_parts(parts)
    t, labels = None, None
    for k in range(0, len(padded), _BUCKET):
        tk, lk = (np.asarray(a) for a in _render_labels(padded[k : k + _BUCKET], camera))
        if t is None:
            t, labels = tk, lk
        else:
            nearer = tk < t  # ties keep the earlier part, as within a chunk
            t, labels = np.where(nearer, tk, t), np.where(nearer, lk + k, labels)
    return np.where(np.isfinite(t), t, np.nan).astype(np.float32), labels


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


def encoding_cost(parts: Part | None, data: RangeData, costs: Costs) -> EncodingCost:
    """Render ``parts`` together and count E (Eq. 6 evaluated on the joint rendering)."""
    measured, figure = data.image, data.figure_region
    if parts is None or len(parts) == 0:
        n, rendered, labels = 0, np.full(measured.shape, np.nan, np.float32), np.full(measured.shape, -1)
    else:
        n = len(parts)
        rendered, labels = render_labels(parts, data.camera)
    hit = labels >= 0
    with np.errstate(invalid="ignore"):
        explained = hit & figure & (np.abs(rendered - measured) <= data.encoding.sigma / 2)
    commission = hit & ~figure
    e, c = int(explained.sum()), int(commission.sum())
    total = costs.part * n + costs.explained * e + costs.commission * c + costs.omission * (costs.figure_pixels - e)
    return EncodingCost(float(total), n, e, c, costs.figure_pixels - e, rendered.astype(np.float32), labels, explained, commission)


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


@functools.partial(jax.jit, static_argnames=("steps",))
def _polish_bucket(parts, points, weights, steps):
    return jax.vmap(lambda p, w: polish_part(p, points, w, steps=steps))(parts, weights)


def _polish_all(parts: Part, points, weights, steps: int) -> Part:
    """Each part polished on its own point weights (``weights[i]``), ``_BUCKET`` parts
    per compiled call (one compilation for any number of parts)."""
    padded, n = _pad_parts(parts)
    w = np.zeros((len(padded), points.shape[0]), np.float32)
    w[:n] = np.asarray(weights)[:n]
    out = [_polish_bucket(padded[k : k + _BUCKET], points, jnp.asarray(w[k : k + _BUCKET]), steps)
           for k in range(0, len(padded), _BUCKET)]
    return jax.tree_util.tree_map(lambda *a: jnp.concatenate(a)[:n], *out)


def _figure_points(data: RangeData, max_points: int = 20000, seed: int = 0):
    """Figure pixels' 3-D points and their flat indices (subsampled to ``max_points``),
    padded to a multiple of 1024."""
    figure = data.figure_mask
    idx = np.flatnonzero(figure)
    if len(idx) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_points, replace=False))
    pts = data.camera.points(data.image).reshape(-1, 3)[idx]
    m = int(math.ceil(len(idx) / 1024) * 1024)
    pad = m - len(idx)
    return np.concatenate([pts, np.zeros((pad, 3))]).astype(np.float32), np.concatenate([idx, np.full(pad, -1)])


def polish_jointly(parts: Part, data: RangeData, costs: Costs, *, steps: int = 20, tolerance: float = 2.0):
    """One round: assign each figure pixel to the part visible there (if within
    ``tolerance`` σ), polish every part on its pixels at once, and accept each part's
    change only if the joint E falls. Returns (parts, cost)."""
    cost = encoding_cost(parts, data, costs)
    pts, idx = _figure_points(data)
    valid = idx >= 0
    flat_labels = cost.labels.reshape(-1)[np.maximum(idx, 0)]
    with np.errstate(invalid="ignore"):
        close = np.abs(cost.rendered - data.image).reshape(-1)[np.maximum(idx, 0)] <= tolerance * data.encoding.sigma
    weights = np.stack([(flat_labels == i) & close & valid for i in range(len(parts))]).astype(np.float32)
    polished = _polish_all(parts, jnp.asarray(pts), weights, steps)
    current = parts
    for i in np.argsort(-weights.sum(1)):
        trial = jax.tree_util.tree_map(lambda a, b: a.at[i].set(b[i]), current, polished)
        c = encoding_cost(trial, data, costs)
        if c.total < cost.total - 1e-9:
            current, cost = trial, c
    return current, cost


def drop_unprofitable(parts: Part, data: RangeData, costs: Costs):
    """Remove parts, one at a time, while removing one lowers E."""
    cost = encoding_cost(parts, data, costs)
    improved = True
    while improved and len(parts) > 1:
        improved = False
        best = None
        # Only parts whose own explained pixels could not pay for two part descriptions
        # can be worth dropping; the others are not re-rendered.
        own = np.array([(cost.labels == i)[cost.explained_mask].sum() for i in range(len(parts))])
        gain = own * (costs.omission - costs.explained)
        for i in np.flatnonzero(gain < 2 * costs.part + costs.commission * cost.commission):
            keep = np.delete(np.arange(len(parts)), i)
            trial = jax.tree_util.tree_map(lambda x: x[keep], parts)
            c = encoding_cost(trial, data, costs)
            if c.total < cost.total - 1e-9 and (best is None or c.total < best[1].total):
                best = (trial, c)
        if best is not None:
            parts, cost = best
            improved = True
    return parts, cost


def _merge_candidate(a: Part, b: Part) -> list[Part]:
    """Initial single parts spanning two parts: straight and bent both ways, at two rolls."""
    from ._scenes import limb

    pa, pb = np.asarray(a.position, np.float64), np.asarray(b.position, np.float64)
    length = np.linalg.norm(pb - pa)
    if length < 1e-9:
        return []
    reach = 0.5 * (float(jnp.max(a.size)) + float(jnp.max(b.size))) * (pb - pa) / length
    width = max(float(jnp.sort(a.size)[1]), float(jnp.sort(b.size)[1]))
    depth = max(float(jnp.min(a.size)), float(jnp.min(b.size)))
    return [
        limb(pa - reach, pb + reach, width, depth, roll=roll, bend=(bend, 0.0))
        for roll in (0.0, np.pi / 2)
        for bend in (-0.3, 0.0, 0.3)
    ]


@jax.jit
def _surface_distance(parts, points):
    """Radial distance (:func:`~sqparts.surface_distance`) of every point to every part."""
    return jax.vmap(lambda p: jax.vmap(lambda x: surface_distance(p, x))(points))(parts)


def merge_adjacent(parts: Part, data: RangeData, costs: Costs, *, steps: int = 20, tries: int = 3):
    """Replace two adjacent parts by one bent part when that lowers E (section 4.1).

    Every adjacent pair gets bent single-part starts, all fitted by batched LM calls
    to the pair's explained pixels; the ``tries`` best fits (by the share of the pair's
    points within σ/2 of their surface) are tried in the joint rendering."""
    from scipy.ndimage import binary_dilation

    cost = encoding_cost(parts, data, costs)
    pts, idx = _figure_points(data)
    merged = True
    while merged and len(parts) > 1:
        merged = False
        n = len(parts)
        grown = [binary_dilation(cost.labels == i, iterations=2) for i in range(n)]
        inits, weights, pairs = [], [], []
        for i in range(n):
            for j in range(i + 1, n):
                if not (grown[i] & (cost.labels == j)).any():
                    continue
                union = ((cost.labels == i) | (cost.labels == j)) & cost.explained_mask
                w = np.where(idx >= 0, union.reshape(-1)[np.maximum(idx, 0)], False).astype(np.float32)
                if w.sum() < 8:
                    continue
                for init in _merge_candidate(parts[i], parts[j]):
                    inits.append(init)
                    weights.append(w)
                    pairs.append((i, j))
        if not inits:
            break
        w_all = np.stack(weights)
        fitted = _polish_all(stack_parts(inits), jnp.asarray(pts), w_all, steps)
        # Share of each pair's points within σ/2 of the fitted surface (no rendering).
        padded, m = _pad_parts(fitted)
        dist = np.concatenate([np.asarray(_surface_distance(padded[k : k + _BUCKET], jnp.asarray(pts)))
                               for k in range(0, len(padded), _BUCKET)])[:m]
        close = (np.abs(np.asarray(dist)) <= data.encoding.sigma / 2) * w_all
        share = close.sum(1) / np.maximum(w_all.sum(1), 1)
        for k in np.argsort(-share)[:tries]:
            i, j = pairs[k]
            keep = [q for q in range(n) if q not in (i, j)]
            trial = stack_parts([parts[q] for q in keep] + [fitted[int(k)]])
            c = encoding_cost(trial, data, costs)
            if c.total < cost.total - 1e-9:
                parts, cost, merged = trial, c, True
                break
    return parts, cost


def refine_parts(parts: Part, data: RangeData, costs: Costs, *, rounds: int = 3, steps: int = 20, merge: bool = True):
    """Joint refinement: ``rounds`` of :func:`polish_jointly`, then drop and merge.
    Returns (parts, final cost, history of E after each stage)."""
    cost = encoding_cost(parts, data, costs)
    history = [("initial", cost.total)]
    for r in range(rounds):
        parts, cost = polish_jointly(parts, data, costs, steps=steps)
        history.append((f"polish {r + 1}", cost.total))
    parts, cost = drop_unprofitable(parts, data, costs)
    history.append(("drop", cost.total))
    if merge:
        parts, cost = merge_adjacent(parts, data, costs)
        history.append(("merge", cost.total))
    return parts, cost, history
