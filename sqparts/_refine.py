"""Joint refinement of the chosen parts (paper sections 3.5 and 4.1).

All chosen parts are rendered together (so occlusion is fully accounted for) and the
encoding cost of the whole image is computed by direct pixel count,

    E = κ0 n + κ1 |explained| + κ2 |commission| + κ3 (N - |explained|),

with the costs of :class:`~sqparts._select.Costs`. Each round is one step of region
growing over all parts at once: every part takes the figure pixels where it is visible
plus the unexplained pixels next to them that lie near its surface, and is polished on
them (optimistix Levenberg-Marquardt on radial surface distances, batched over parts)
while the background rays around it must miss it; a change is kept only if E falls, like
the paper's accept-if-improved descent. Then a part that no longer pays
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

from ._part import Part, surface_distance
from ._render import DEFAULT_NEWTON_STEPS, cast_scene
from ._search import RangeData, polish_part
from ._select import Costs

_BUCKET = 8


_PART_TREE = jax.tree_util.tree_structure(Part(size=np.ones(3, np.float32)))


def _host_parts(vectors) -> Part:
    """A batch of parts with host (numpy) leaves from valid (n, 14) vectors (the order of
    :meth:`~sqparts.Part.to_vector`), built without dispatching JAX operations: slicing,
    stacking and editing them is plain numpy, and they enter compiled calls as they are."""
    v = np.asarray(vectors, np.float32)
    return jax.tree_util.tree_unflatten(_PART_TREE, [v[:, 0:3], v[:, 3:6], v[:, 6:9], v[:, 9:11], v[:, 11:13], v[:, 13]])


def _vectors(parts: Part) -> np.ndarray:
    """(n, 14) host copy of ``parts.to_vector()``."""
    return np.asarray(parts.to_vector(), np.float32).reshape(-1, 14)


def _pad_parts(parts: Part) -> tuple[Part, int]:
    """Pad a batch to a multiple of ``_BUCKET`` with parts behind the camera (never hit),
    so the compiled renderer and solver only ever see batches of ``_BUCKET`` parts."""
    n = len(parts)
    m = -(-n // _BUCKET) * _BUCKET
    dummy = np.array([0, 0, -1e3, 0, 0, 0, 1e-3, 1e-3, 1e-3, 1, 1, 0, 0, 0], np.float32)
    return _host_parts(np.concatenate([_vectors(parts), np.broadcast_to(dummy, (m - n, 14))])), n


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


_POINTS = 1024
_RAYS = 512


@functools.partial(jax.jit, static_argnames=("steps",))
def _polish_bucket(parts, points, weights, origins, directions, ray_weights, steps):
    def one(p, x, w, o, d, wr):
        return polish_part(p, x, w, rays=(o, d, wr), steps=steps)

    return jax.vmap(one)(parts, points, weights, origins, directions, ray_weights)


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


def _polish_all(parts: Part, points, weights, steps: int, rays, ray_weights) -> Part:
    """Each part polished on its own points (non-zero ``weights[i]`` over ``points``,
    at most ``_POINTS`` of them) while missing its background rays (non-zero
    ``ray_weights[i]`` over ``rays`` = (origins, directions), at most ``_RAYS``);
    ``_BUCKET`` parts per compiled call, so one compilation serves any number of parts
    and any image."""
    padded, n = _pad_parts(parts)
    m = len(padded)
    pi, pw = _gather(np.asarray(weights)[:n], _POINTS)
    ri, rw = _gather(np.asarray(ray_weights)[:n], _RAYS)
    pi, pw, ri, rw = (np.concatenate([a, np.zeros((m - n,) + a.shape[1:], a.dtype)]) for a in (pi, pw, ri, rw))
    x = np.asarray(points, np.float32)[pi]
    if len(rays[0]) == 0:  # no background in view: nothing to miss
        rays = (np.zeros((1, 3), np.float32), np.float32([[0.0, 0.0, 1.0]]))
    o, d = (np.asarray(a, np.float32)[ri] for a in rays)
    d[rw == 0] = (0.0, 0.0, 1.0)  # padding rays stay finite
    out = [_polish_bucket(padded[k : k + _BUCKET], *(jnp.asarray(a[k : k + _BUCKET]) for a in (x, pw, o, d, rw)), steps)
           for k in range(0, m, _BUCKET)]
    return _host_parts(np.concatenate([_vectors(p) for p in out])[:n])


def _pad_rows(a: np.ndarray, m: int) -> np.ndarray:
    return np.concatenate([a, np.zeros((m - len(a),) + a.shape[1:], a.dtype)])


def _figure_points(data: RangeData, max_points: int = 20000, seed: int = 0):
    """Figure pixels' 3-D points and their flat indices (subsampled to ``max_points``),
    padded to a multiple of 1024."""
    figure = data.figure_mask
    idx = np.flatnonzero(figure)
    if len(idx) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_points, replace=False))
    pts = data.camera.points(data.image).reshape(-1, 3)[idx]
    m = int(math.ceil(len(idx) / 1024) * 1024)
    return _pad_rows(pts.astype(np.float32), m), np.concatenate([idx, np.full(m - len(idx), -1)])


def _background_rays(data: RangeData):
    """Rays through background pixels (no return, off the figure) within 3 pixels of the
    figure, where a part that swells past its silhouette shows first: (origins,
    directions, flat pixel indices)."""
    from scipy.ndimage import binary_dilation

    figure = data.figure_region
    idx = np.flatnonzero(binary_dilation(figure, iterations=3) & ~figure & ~np.isfinite(data.image))
    o, d = (np.asarray(a).reshape(-1, 3)[idx].astype(np.float32) for a in data.camera.rays())
    return (o, d), idx


def _rays_near(mask: np.ndarray, ray_index: np.ndarray, margin: int) -> np.ndarray:
    """1 for each background ray within ``margin`` pixels of ``mask``, else 0."""
    from scipy.ndimage import binary_dilation

    return binary_dilation(mask, iterations=margin).reshape(-1)[ray_index].astype(np.float32)


def polish_jointly(parts: Part, data: RangeData, costs: Costs, *, steps: int = 20, tolerance: float = 2.0, grow: int = 2):
    """One round of region growing over all parts at once: each part is fitted to the
    figure pixels where it is visible (within ``tolerance`` σ) and to the unexplained
    figure pixels within ``grow`` pixels of them that lie within 3 scale of its surface
    (scale = max(σ, 5% of its largest semi-axis); Cauchy weights of that width), while
    background rays near the silhouette must miss it. A part's change is accepted only
    if the joint E falls. Returns (parts, cost)."""
    from scipy.ndimage import binary_dilation

    cost = encoding_cost(parts, data, costs)
    pts, idx = _figure_points(data)
    valid = idx >= 0
    at = np.maximum(idx, 0)
    flat_labels = cost.labels.reshape(-1)[at]
    with np.errstate(invalid="ignore"):
        close = np.abs(cost.rendered - data.image).reshape(-1)[at] <= tolerance * data.encoding.sigma
    free = ~cost.explained_mask.reshape(-1)[at] & valid
    dist = np.abs(_distances(parts, pts))
    scale = np.maximum(0.05 * np.asarray(parts.size).max(1), data.encoding.sigma)[:, None]
    weights = []
    for i in range(len(parts)):
        near = binary_dilation(cost.labels == i, iterations=grow).reshape(-1)[at]
        support = ((flat_labels == i) & close & valid) | (free & near & (dist[i] < 3 * scale[i]))
        weights.append(np.where(support, 1.0 / np.sqrt(1.0 + (dist[i] / scale[i]) ** 2), 0.0))
    weights = np.stack(weights).astype(np.float32)
    rays, ray_index = _background_rays(data)
    ray_weights = np.stack([_rays_near(cost.labels == i, ray_index, grow + 3) for i in range(len(parts))])
    polished = _polish_all(parts, pts, weights, steps, rays, ray_weights)
    current, new = _vectors(parts), _vectors(polished)
    for i in np.argsort(-weights.sum(1)):
        trial = current.copy()
        trial[i] = new[i]
        c = encoding_cost(_host_parts(trial), data, costs)
        if c.total < cost.total - 1e-9:
            current, cost = trial, c
    return _host_parts(current), cost


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


def _merge_candidates(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(6, 14) vectors of single parts spanning the parts with vectors ``a`` and ``b``
    from end to end: straight and bent both ways, at two rolls (none if they coincide)."""
    from scipy.spatial.transform import Rotation

    from ._scenes import _frame_from_z

    pa, pb = a[0:3].astype(np.float64), b[0:3].astype(np.float64)
    length = np.linalg.norm(pb - pa)
    if length < 1e-9:
        return np.zeros((0, 14), np.float32)
    axis = (pb - pa) * (1.0 + (a[6:9].max() + b[6:9].max()) / length)  # ends past the centres by the mean half-length
    width = max(np.sort(a[6:9])[1], np.sort(b[6:9])[1])
    depth = max(a[6:9].min(), b[6:9].min())
    frame = Rotation.from_rotvec(_frame_from_z(axis))
    rows = []
    for roll in (0.0, np.pi / 2):
        rv = (frame * Rotation.from_rotvec([0.0, 0.0, roll])).as_rotvec()
        for bend in (-0.3, 0.0, 0.3):
            rows.append([*(pa + pb) / 2, *rv, width, depth, np.linalg.norm(axis) / 2, 1.0, 1.0, bend, 0.0, 0.0])
    return np.asarray(rows, np.float32)


@jax.jit
def _surface_distance(parts, points):
    return jax.vmap(lambda p: jax.vmap(lambda x: surface_distance(p, x))(points))(parts)


def _distances(parts: Part, points) -> np.ndarray:
    """(n, m) radial distance (:func:`~sqparts.surface_distance`) of every point to every
    part, ``_BUCKET`` parts per compiled call."""
    padded, n = _pad_parts(parts)
    pts = jnp.asarray(points)
    return np.concatenate([np.asarray(_surface_distance(padded[k : k + _BUCKET], pts))
                           for k in range(0, len(padded), _BUCKET)])[:n]


def merge_adjacent(parts: Part, data: RangeData, costs: Costs, *, steps: int = 20, tries: int = 3):
    """Replace two adjacent parts by one bent part when that lowers E (section 4.1).

    Every adjacent pair gets bent single-part starts, all fitted by batched LM calls
    to the pair's explained pixels; the ``tries`` best fits (by the share of the pair's
    points within σ/2 of their surface) are tried in the joint rendering."""
    from scipy.ndimage import binary_dilation

    cost = encoding_cost(parts, data, costs)
    pts, idx = _figure_points(data)
    rays, ray_index = _background_rays(data)
    merged = True
    while merged and len(parts) > 1:
        merged = False
        n = len(parts)
        grown = [binary_dilation(cost.labels == i, iterations=2) for i in range(n)]
        vec = _vectors(parts)
        inits, weights, ray_weights, pairs = [], [], [], []
        for i in range(n):
            for j in range(i + 1, n):
                if not (grown[i] & (cost.labels == j)).any():
                    continue
                union = ((cost.labels == i) | (cost.labels == j)) & cost.explained_mask
                w = np.where(idx >= 0, union.reshape(-1)[np.maximum(idx, 0)], False).astype(np.float32)
                if w.sum() < 8:
                    continue
                wr = _rays_near((cost.labels == i) | (cost.labels == j), ray_index, 5)
                for init in _merge_candidates(vec[i], vec[j]):
                    inits.append(init)
                    weights.append(w)
                    ray_weights.append(wr)
                    pairs.append((i, j))
        if not inits:
            break
        w_all = np.stack(weights)
        fitted = _polish_all(_host_parts(np.stack(inits)), pts, w_all, steps, rays, np.stack(ray_weights))
        fitted_vec = _vectors(fitted)
        # Share of each pair's points within σ/2 of the fitted surface (no rendering).
        dist = _distances(fitted, pts)
        close = (np.abs(np.asarray(dist)) <= data.encoding.sigma / 2) * w_all
        share = close.sum(1) / np.maximum(w_all.sum(1), 1)
        for k in np.argsort(-share)[:tries]:
            i, j = pairs[k]
            keep = [q for q in range(n) if q not in (i, j)]
            trial = _host_parts(np.concatenate([vec[keep], fitted_vec[k : k + 1]]))
            c = encoding_cost(trial, data, costs)
            if c.total < cost.total - 1e-9:
                parts, cost, merged = trial, c, True
                break
    return parts, cost


def refine_parts(parts: Part, data: RangeData, costs: Costs, *, rounds: int = 3, steps: int = 20, merge: bool = True):
    """Joint refinement: ``rounds`` of :func:`polish_jointly`, then drop and merge.
    Returns (parts, final cost, history of E after each stage)."""
    parts = _host_parts(_vectors(parts))
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
    return Part.from_vector(_vectors(parts)), cost, history
