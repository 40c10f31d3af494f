"""Joint refinement of the chosen parts (paper sections 3.5 and 4.1): one loop over moves.

All chosen parts are rendered together (so occlusion is fully accounted for) and the
encoding cost of the whole image is computed by direct pixel count,

    E = κ0 n + κ1 |explained| + κ2 |commission| + κ3 (N - |explained|),

with the costs of :class:`~sqparts._encoding.Costs`. Refinement is the paper's
accept-if-improved descent on E, built from small moves (frozen dataclasses whose fields
are their knobs). Each pass of a move proposes a batch of :class:`~sqparts._encoding.Edit`
s (parts removed, parts added); their joint E is evaluated together by the package's one
evaluator, :func:`~sqparts._encoding.edit_costs` (every edit's new parts rendered in one
batched call, the other parts' depth layers reused); and one accept rule,
:func:`accept_edits`, keeps the best improving edit, then each next best that still
lowers E once the edits kept before it are made. A move runs its passes while they lower
E. The moves, in :meth:`RefineSettings.moves`'s order:

- :class:`GrowParts`: region growing over all parts at once: every part takes the figure
  pixels where it is visible plus the unexplained pixels next to them that lie near its
  surface, and is polished on them (optimistix Levenberg-Marquardt on surface
  distances, batched over parts) while the background rays around it must miss it;
- :class:`SplitParts`: a part that spans two (a torso with its pelvis) split in two along
  its axis;
- :class:`FillGaps`: blobs of unexplained pixels searched again at their own scale for the
  parts the first search missed (a long blob also at its skeleton points; a member too
  thin for a blob, a gate's two-pixel brace, started from its pixels' moments; each new
  small part settled by a pattern search on E itself). It proposes two alternative
  batches, and the rest of the moves finish each: the shorter description is kept;
- :class:`DropParts`: a part that no longer pays for its bits dropped;
- :class:`MergeParts`: adjacent parts merged when one part encodes them more cheaply: two
  into one bent part (section 4.1), or a group into one part started from its pixels'
  moments (a flat box for a laptop seen as patches); :class:`OnGain` then grows the parts
  again, drops those the merge made redundant, and merges again, until merging no
  longer lowers E: the descent runs to its fixed point;
- :class:`StraightenParts`: each bent or tapered part fitted again with bend and taper
  held at zero (a noisy surface's least-squares fit buys a little residual with a
  deformation that moves the part's rim; E may prefer the straight part);
- :class:`SettleParts`: the paper's final optimisation (section 3.5): each part's
  parameters stepped one at a time, all parts rendered together, a step kept if E falls;
- :class:`UnpinchParts`: a part whose cross-section settled pinched against its twin
  turned 45 degrees, settled on its own (a noisy box fitted as a rhombus turned 45
  degrees), then all settled again if it gains;
- :class:`AbsorbParts`: a small part dropped while the parts beside it grow over its
  pixels (a bar the search cut in two at a joint taken back whole), then settled again:
  after settling, so that it can only shorten the description the other moves give;
- :class:`MergeParts` once more, for the same reason: settled parts may merge where
  they did not before (a body split under a lid's overhang, whose lid settling moved;
  an L's arm cut in two; single parts summarised from their explained pixels alone
  too: a seat seen edge-on, fitted bent; a disc among the starts: a lid seen as two
  plates), then grown, dropped, straightened and settled again if it gains (a
  merged part's fit to noisy points bends it, as the first search's fits did);
- :class:`SettleFaces`, once per step scale of settling: settling with one face of a
  part moved at a time (a semi-axis and the centre together), which the one-parameter
  steps cannot do where each alone raises E;
- :class:`StretchParts`, last of all: each part that answers for unexplained pixels
  stretched over them and grown, then settled again (by parameters and by faces) if it
  gains (a chair's back that stops short of the seat it meets).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import TYPE_CHECKING, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from ._compile import persistent_jit
from ._data import RangeData
from ._encoding import (
    Costs,
    Edit,
    EncodingCost,
    edit_costs,
    edit_totals,
    encoding_cost,
    host_parts,
    layers_of,
    least_pixels,
    part_vectors,
    pixel_errors,
    render_edits,
)
from ._part import BEND_RANGE, SQUARENESS_RANGE, TAPER_RANGE, Part, from_unconstrained, to_unconstrained
from ._polish import (
    RIGID,
    background_rays,
    figure_points,
    polish_parts,
    polish_scale,
    rays_near,
    surface_distances,
)
from ._render import cast_part

if TYPE_CHECKING:
    from ._search import SearchSettings


def _grow_inputs(parts: Part, data: RangeData, cost: EncodingCost, which, *, tolerance: float = 2.0, grow: int = 2):
    """What one region-growing fit of the parts ``which`` (indices) needs, given their
    joint rendering ``cost``: their (k, 14) vectors, point weights and ray weights (for
    :func:`polish_parts` with :func:`figure_points` and :func:`background_rays`).

    Each part takes the figure pixels where it is visible (within ``tolerance`` σ) and
    the unexplained figure pixels within ``grow`` pixels of them that lie within 3 scale
    of its surface (scale = max(σ, 5% of its largest semi-axis); Cauchy weights of that
    width); background rays within ``grow`` + 3 pixels of it must miss it.
    """
    from scipy.ndimage import binary_dilation

    which = np.asarray(which, np.int64)
    pts, idx = figure_points(data)
    flat_labels = cost.labels.reshape(-1)[idx]
    with np.errstate(invalid="ignore"):
        close = np.abs(cost.rendered - data.image).reshape(-1)[idx] <= tolerance * data.encoding.sigma
    free = ~cost.explained_mask.reshape(-1)[idx]
    vec = part_vectors(parts)[which]
    chosen = host_parts(vec)
    dist = np.abs(surface_distances(chosen, pts))
    scale = polish_scale(chosen, data.encoding.sigma)[:, None]
    _, ray_index = background_rays(data)
    weights, ray_weights = [], []
    for k, i in enumerate(which):
        mine = cost.labels == i
        near = binary_dilation(mine, iterations=grow).reshape(-1)[idx]
        support = ((flat_labels == i) & close) | (free & near & (dist[k] < 3 * scale[k]))  # pyright: ignore[reportOperatorIssue]  # scipy is untyped: binary_dilation's inferred return includes float arrays
        weights.append(np.where(support, 1.0 / np.sqrt(1.0 + (dist[k] / scale[k]) ** 2), 0.0))
        ray_weights.append(rays_near(mine, ray_index, grow + 3))
    return vec, np.stack(weights), np.stack(ray_weights)


def _grown_edits(
    edits, vectors, cost: EncodingCost, data: RangeData, costs: Costs, *, rounds, steps, grow=2, free=None, every=False
):
    """``edits`` of the parts with (n, 14) ``vectors`` and joint cost ``cost`` with their
    new parts (in the removed parts' places for a one-for-one edit, else last) grown over
    the image as each edit leaves it: ``rounds`` rounds of region growing
    (:func:`_grow_inputs`, ``grow`` pixels; :func:`_grow`, ``steps`` solver steps,
    moving the numbers ``free`` lets them), all edits' parts in one batch a round.
    With ``every``, every round's edits are returned (rounds x edits), not the last
    round's: growing does not always lower E round after round (two parts that grow into
    a corner both take its pixels, and the next round's supports follow them), and the
    accept rule then picks the round."""
    done = []  # each round's edits, rendered once (the accept rule reuses the layers)
    for _ in range(rounds if edits else 0):
        edits = render_edits(edits, data.camera)
        if done:
            done[-1] = edits
        scores = edit_costs(cost, edits, data, costs)
        inputs = []
        for e, c in zip(edits, scores):
            m = len(vectors) - len(e.remove) + len(e.add)  # parts after the edit
            placed = list(e.remove) if e.in_place else np.arange(m - len(e.add), m)
            inputs.append(_grow_inputs(host_parts(e.apply(vectors, e.add)), data, c, placed, grow=grow))
        new = np.split(_grow(data, inputs, steps=steps, free=free), np.cumsum([len(e.add) for e in edits])[:-1])
        edits = [Edit(e.remove, v) for e, v in zip(edits, new)]
        done.append(edits)
    return [e for batch in done for e in batch] if every else edits


def _grow(data: RangeData, inputs, *, steps: int, free=None) -> np.ndarray:
    """Fit every part of a list of :func:`_grow_inputs` results in one batch (moving the
    numbers ``free`` lets them, :func:`~sqparts._polish.polish_parts`); returns their
    (Σk, 14) fitted vectors."""
    vec, weights, ray_weights = (np.concatenate(a) for a in zip(*inputs))
    pts, _ = figure_points(data)
    rays, _ = background_rays(data)
    return part_vectors(polish_parts(host_parts(vec), pts, weights, steps, rays, ray_weights, free))


def accept_edits(vectors: np.ndarray, cost: EncodingCost, edits, data: RangeData, costs: Costs):
    """The accept rule of every move: of the ``edits`` to the parts with (n, 14)
    ``vectors`` and joint cost ``cost``, ranked together by their E
    (:func:`~sqparts._encoding.edit_totals`), the best improving edit is kept; then each
    next best that improved on its own is tried again on the parts as they now are, and
    kept if it still lowers E (:func:`~sqparts._encoding.edit_costs`); an edit of a part
    that a kept edit changed is skipped.
    Returns (vectors, cost), unchanged if no edit lowers E."""
    edits = render_edits(edits, data.camera)
    totals = edit_totals(cost, edits, data, costs)
    order = sorted((k for k, t in enumerate(totals) if t < cost.total - 1e-9), key=lambda k: totals[k])
    where = np.arange(len(vectors))  # each part's index now; -1 = changed by a kept edit
    for k in order:
        e = edits[k]
        if (where[list(e.remove)] < 0).any():
            continue
        now = dataclasses.replace(e, remove=tuple(int(where[i]) for i in e.remove))
        c = edit_costs(cost, [now], data, costs)[0]
        if c.total >= cost.total - 1e-9:
            continue
        vectors, cost = now.apply(vectors, e.add), c
        where[list(e.remove)] = -1
        if not e.in_place and e.remove:
            alive = where >= 0
            where[alive] -= np.searchsorted(np.sort(now.remove), where[alive])
    return vectors, cost


MAX_PASSES = 1000
"""Most passes of one move (a bound on its work; a pass that keeps nothing ends it)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class Move:
    """A refinement move: each of at most ``passes`` passes proposes batches of edits
    (:meth:`propose`), accepted by :func:`accept_edits`; the move stops at the first pass
    that keeps nothing. ``name``: its stage in a recovery's history (with the pass number
    when ``numbered``)."""

    name: ClassVar[str] = "move"
    numbered: ClassVar[bool] = False
    passes: int = 1

    def __post_init__(self):
        p = self.passes
        if isinstance(p, bool) or not isinstance(p, (int, np.integer)) or not 1 <= p <= MAX_PASSES:
            raise ValueError(f"passes: got {p!r}, expected an integer in [1, {MAX_PASSES}]")

    def propose(
        self, vectors: np.ndarray, cost: EncodingCost, data: RangeData, costs: Costs, step: int
    ) -> list[list[Edit]]:
        """Pass ``step`` (from 0): a list of alternative batches of edits (usually one).
        With several, the rest of the moves finish each and the shorter description is
        kept."""
        raise NotImplementedError


@dataclasses.dataclass(frozen=True, kw_only=True)
class GrowParts(Move):
    """Region growing over all parts at once (:func:`_grow_inputs`, :func:`_grow`:
    ``steps`` solver steps on each part's support, which takes the unexplained pixels
    within ``grow`` pixels and ``tolerance`` σ); each part's new fit is an edit."""

    name: ClassVar[str] = "polish"
    numbered: ClassVar[bool] = True
    passes: int = 2
    steps: int = 20
    tolerance: float = 2.0
    grow: int = 2

    def propose(self, vectors, cost, data, costs, step):
        n = len(vectors)
        if n == 0:
            return [[]]
        inputs = _grow_inputs(host_parts(vectors), data, cost, np.arange(n), tolerance=self.tolerance, grow=self.grow)
        new = _grow(data, [inputs], steps=self.steps)
        return [[Edit((i,), new[i : i + 1]) for i in range(n)]]


@dataclasses.dataclass(frozen=True, kw_only=True)
class StraightenParts(Move):
    """Each deformed part (bend or taper not zero) fitted again without its deformation:
    bend and taper set to zero and held there (:data:`~sqparts._polish.RIGID`) through
    ``rounds`` rounds of region growing (``steps`` solver steps each) from its pixels.
    Least squares on a noisy surface buys a little residual with a bend or taper that
    moves the part's rim; E, which counts pixels, can prefer the straight part, and no
    step of :class:`SettleParts` reaches it from the bent one, since its pose and size
    move with it."""

    name: ClassVar[str] = "straighten"
    rounds: int = 2
    steps: int = 20

    def propose(self, vectors, cost, data, costs, step):
        straight = np.where(RIGID, vectors, 0.0).astype(np.float32)
        trials = [Edit((int(i),), straight[i : i + 1]) for i in np.flatnonzero((vectors[:, ~RIGID] != 0).any(1))]
        return [_grown_edits(trials, vectors, cost, data, costs, rounds=self.rounds, steps=self.steps, free=RIGID)]


@dataclasses.dataclass(frozen=True, kw_only=True)
class SplitParts(Move):
    """A part replaced by two, its halves along its longest axis grown by ``rounds`` of
    region growing (``steps`` solver steps each): the inverse of :class:`MergeParts`,
    for a part that spans two (a torso with its pelvis). Proposed, all in one batch, for
    the ``tries`` parts with the most unexplained figure pixels beside them, if those
    could pay for one more part."""

    name: ClassVar[str] = "split"
    steps: int = 20
    rounds: int = 4
    tries: int = 3

    def propose(self, vectors, cost, data, costs, step):
        from scipy.ndimage import binary_dilation
        from scipy.spatial.transform import Rotation

        omitted = data.figure_mask & ~cost.explained_mask
        grown = [np.asarray(binary_dilation(cost.labels == i, iterations=2), bool) for i in range(len(vectors))]
        beside = np.array([(g & omitted).sum() for g in grown])
        trials = []
        for i in [int(i) for i in np.argsort(-beside)[: self.tries] if beside[i] >= least_pixels(costs)]:
            v = vectors[i].astype(np.float64)
            axis = Rotation.from_rotvec(v[3:6]).as_matrix()[:, 2] * v[8] / 2
            halves = np.stack([v, v])
            halves[:, 0:3] = [v[0:3] - axis, v[0:3] + axis]
            halves[:, 8] = v[8] / 2
            halves[:, 11:14] = 0.0
            trials.append(Edit((i,), halves))
        return [_grown_edits(trials, vectors, cost, data, costs, rounds=self.rounds, steps=self.steps)]


def omitted_blobs(omitted: np.ndarray) -> tuple[np.ndarray, int]:
    """Label the blobs of a mask of unexplained pixels: the 8-connected sets of its
    pixels whose 3x3 neighbourhoods lie in the mask (at least 3 pixels thick), each with
    its one-pixel rim. Slivers along the parts' outlines belong to no blob and do not
    join two blobs (a teapot's lid to its handle). Returns (labels (H, W), 0 = none;
    count)."""
    from scipy.ndimage import binary_erosion, grey_dilation, label

    omitted = np.asarray(omitted, bool)
    square = np.ones((3, 3), bool)
    cores, count = label(binary_erosion(omitted, structure=square), structure=square)  # pyright: ignore[reportGeneralTypeIssues]  # scipy is untyped: label returns (labels, count) without output=
    return np.where(omitted, grey_dilation(cores, footprint=square), 0), count


def thin_members(omitted: np.ndarray, shown: np.ndarray, blob_labels: np.ndarray, points: np.ndarray, reach: float):
    """The unexplained members too thin for :func:`omitted_blobs` (a gate's two-pixel
    bars: no 3x3 neighbourhood fits in them), as masks, largest first.

    A piece is an 8-connected set of unexplained pixels outside every blob; a sliver
    along a part's outline touches that part's pixels along most of its length, so only
    pieces with at most half their pixels next to a rendered part (``shown``) count. A
    member that other members cross (a brace over the rails) is cut into collinear
    pieces: a piece joins another when all its 3-D ``points`` ((H, W, 3), camera frame)
    lie within ``reach`` (metres) of the other's principal line, and the joined pieces
    are one member."""
    from scipy.ndimage import binary_dilation, label
    from scipy.sparse.csgraph import connected_components

    square = np.ones((3, 3), bool)
    pieces, count = label(omitted & (blob_labels == 0), structure=square)  # pyright: ignore[reportGeneralTypeIssues]  # scipy is untyped: label returns (labels, count) without output=
    beside = binary_dilation(shown, structure=square)
    kept = [m for m in (pieces == k for k in range(1, count + 1)) if m.sum() >= 3 and (m & beside).sum() <= m.sum() / 2]
    if not kept:
        return []
    clouds = [points[m].astype(np.float64) for m in kept]
    lines = []
    for p in clouds:
        c = p.mean(0)
        lines.append((c, np.linalg.eigh(np.cov((p - c).T))[1][:, -1]))

    def off_line(p, line):
        c, u = line
        q = p - c
        return np.linalg.norm(q - np.outer(q @ u, u), axis=1)

    near = np.array(
        [[i == j or off_line(clouds[j], lines[i]).max() <= reach for j in range(len(kept))] for i in range(len(kept))]
    )
    _, member = connected_components(near | near.T, directed=False)
    masks = [np.any([kept[i] for i in np.flatnonzero(member == k)], axis=0) for k in np.unique(member)]
    return sorted(masks, key=lambda m: -int(m.sum()))


@dataclasses.dataclass(frozen=True, kw_only=True)
class FillGaps(Move):
    """The figure's unexplained blobs searched again for parts the first search missed (a
    hand, a foot, a teapot's lid: too small for the scales searched around the skeleton),
    with ``search``, the first search's :class:`~sqparts.SearchSettings` (None: no search).

    The ``blobs`` largest :func:`omitted_blobs` that could pay for a part are searched
    with :func:`~sqparts._search.fit_regions` at their innermost pixel, ``max_size`` 3/4 of
    the blob's extent across the image (same window and grid: nothing is recompiled). A
    blob more than two of its widest discs long may hold several things (a lid's knob on
    the lid's rim seen edge-on), so it is also searched at up to ``seeds`` more of its
    skeleton points (:func:`~sqparts._search.region_centers`, thickest first, spaced by
    the blob's inscribed radius), each at a scale of four times its own inscribed radius.
    Members too thin for a blob (:func:`thin_members`: a gate's two-pixel brace, cut into
    pieces by the rails it crosses) get the moment starts of their pixels
    (:func:`_moment_candidates`), ``blobs`` of them at most, largest first: a window
    search on a fixed grid of directions meets a two-pixel bar at a slant only where it
    crosses the window. Each candidate is grown by ``rounds`` of region growing beside the
    current parts (``steps`` solver steps), and the best one per search is settled on E
    itself (:func:`settle_part`: a pixel of commission outweighs the few a hand explains).

    Proposes the innermost searches' additions and, if the skeleton points' searches add
    to them, all additions, as alternatives: a part that pays here can still stop a
    merge that would have paid more. Up to ``passes`` passes while they lower E: the
    unexplained pixels regroup once a pass has added parts (a gate's six two-pixel
    members need more than one pass). The first pass that proposes two alternatives
    doubles the work after it; later passes keep their alternative of lowest E
    (:func:`run_moves`)."""

    name: ClassVar[str] = "fill gaps"
    passes: int = 4
    search: SearchSettings | None = None
    steps: int = 20
    rounds: int = 3
    blobs: int = 4
    seeds: int = 3

    def propose(self, vectors, cost, data, costs, step):
        from scipy.ndimage import distance_transform_edt

        from ._search import fit_regions, region_centers

        settings = self.search
        if settings is None:
            return [[]]
        least = least_pixels(costs)
        omitted = data.figure_mask & ~cost.explained_mask
        blob_labels, count = omitted_blobs(omitted)
        sizes = np.bincount(blob_labels.ravel(), minlength=count + 1)[1:]
        inner = distance_transform_edt(omitted)
        additions, seed, innermost, searches = [], [], set(), []

        def search(centre, max_size):
            searches.append((centre, float(np.clip(max_size, 1e-6, settings.max_size))))

        for b in np.argsort(-sizes, kind="stable")[: self.blobs]:
            blob = blob_labels == b + 1
            if sizes[b] < least:
                continue
            radius = np.where(blob, inner, 0.0)  # pyright: ignore[reportCallIssue, reportArgumentType]  # scipy is untyped: distance_transform_edt returns the distances array here
            centre = tuple(int(i) for i in np.unravel_index(int(np.argmax(radius)), blob.shape))
            rows, cols = np.nonzero(blob)
            pixel = float(data.camera.pixel_size_at(float(np.nanmedian(data.image[blob]))))
            length = max(np.ptp(rows), np.ptp(cols)) + 1  # across the image, not in depth
            search(centre, 0.75 * pixel * length)
            innermost.add(centre)
            if length > 4 * radius[centre]:
                spacing = max(float(radius[centre]), 1.0)
                points = [
                    (int(r), int(c))
                    for r, c in region_centers(blob, spacing=spacing)
                    if (r - centre[0]) ** 2 + (c - centre[1]) ** 2 >= spacing**2
                ]
                for r, c in points[: self.seeds]:
                    search((r, c), 4 * pixel * float(radius[r, c]))
        # Members too thin for a blob start from their pixels' moments: a window search
        # along a fixed grid of directions meets a two-pixel bar at a slant only where it
        # crosses the window.
        points = data.camera.points(data.image)
        pixel = float(data.camera.pixel_size_at(float(np.nanmedian(data.image[data.figure_mask]))))
        thin = [
            m
            for m in thin_members(omitted, cost.labels >= 0, blob_labels, points, 2 * pixel + data.encoding.sigma)
            if m.sum() >= least
        ]
        for k, member in enumerate(thin[: self.blobs]):
            starts = _moment_candidates(points[member], data.encoding.sigma)
            additions.extend(starts)
            seed.extend([("thin", k)] * len(starts))
            innermost.add(("thin", k))
        # The searches are independent: run together, their finds kept in this order.
        fits = (
            fit_regions(data, settings, [c for c, _ in searches], max_sizes=[s for _, s in searches])
            if searches
            else []
        )
        for (centre, _), fit in zip(searches, fits):
            good = part_vectors(fit.parts)[np.asarray(fit.gamma) > 0]
            additions.extend(good)
            seed.extend([centre] * len(good))
        if not additions:
            return [[]]
        n = len(vectors)
        found = render_edits([Edit((), a[None]) for a in np.asarray(additions, np.float32)], data.camera)
        scores = edit_costs(cost, found, data, costs)
        for _ in range(self.rounds):
            trials = [host_parts(e.apply(vectors, e.add)) for e in found]
            new = _grow(data, [_grow_inputs(t, data, c, [n]) for t, c in zip(trials, scores)], steps=self.steps)
            grown = render_edits([Edit((), v[None]) for v in new], data.camera)
            for k, c in enumerate(edit_costs(cost, grown, data, costs)):
                if c.total < scores[k].total:
                    found[k], scores[k] = grown[k], c
        best = {}
        for k, (s, c) in enumerate(zip(seed, scores)):
            if s not in best or c.total < scores[best[s]].total:
                best[s] = k
        rest = layers_of(cost).min(0) if n else np.full(data.image.shape, np.inf, np.float32)
        settled = {
            s: Edit((), settle_part(found[k].add[0], found[k].layers[0], rest, data, costs)[None])  # pyright: ignore[reportOptionalSubscript]  # rendered above
            for s, k in best.items()
        }
        alternatives = [[e for s, e in settled.items() if s in innermost]]
        if any(s not in innermost for s in settled):
            alternatives.append(list(settled.values()))
        return alternatives


@dataclasses.dataclass(frozen=True, kw_only=True)
class DropParts(Move):
    """A part dropped when that lowers E; only parts whose own explained pixels could not
    pay for two part descriptions are tried (the others are not re-rendered), and the
    last part is never dropped."""

    name: ClassVar[str] = "drop"
    passes: int = MAX_PASSES

    def propose(self, vectors, cost, data, costs, step):
        n = len(vectors)
        if n <= 1:
            return [[]]
        own = _explained_by_each(cost, n)
        gain = own * (costs.omission - costs.explained)
        which = np.flatnonzero(gain < 2 * costs.part + costs.commission * cost.commission)
        if len(which) == n:  # one part stays: the one that explains most
            which = which[which != int(np.argmax(own))]
        return [[Edit((int(i),)) for i in which]]


def _stretched_over(vector: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The part with 14-vector ``vector`` with its face toward ``points`` (m, 3) moved out
    to their farthest, the opposite face held: the face on the axis along which the
    points' mean lies farthest out in semi-axes. Unchanged if no point lies beyond it."""
    from scipy.spatial.transform import Rotation

    v = np.asarray(vector, np.float64).copy()
    if len(points) == 0:
        return v.astype(np.float32)
    axes = Rotation.from_rotvec(v[3:6]).as_matrix()  # columns: the part's axes in the camera frame
    local = (np.asarray(points, np.float64) - v[0:3]) @ axes
    mean = local.mean(0)
    k = int(np.argmax(np.abs(mean) / v[6:9]))
    side = 1.0 if mean[k] >= 0 else -1.0
    far, semi = float((side * local[:, k]).max()), v[6 + k]
    if far > semi:
        v[6 + k] = (semi + far) / 2
        v[0:3] += side * (far - semi) / 2 * axes[:, k]
    return v.astype(np.float32)


@dataclasses.dataclass(frozen=True, kw_only=True)
class AbsorbParts(Move):
    """A part dropped while the parts beside it grow over its pixels (``rounds`` rounds
    of region growing, ``grow`` pixels and ``steps`` solver steps each,
    :func:`_grow_inputs`), tried for the ``tries`` parts that explain fewest pixels: a
    member that the search cut in two, its piece taken back by the rest of it (the end
    of a bar, the corner of an L), where dropping the piece alone would leave its pixels
    unexplained. Each part beside the piece is tried growing over it as it is, and
    stretched over it first (:func:`_stretched_over`), alone and all together: growing
    takes a few pixels a round, and a bar cut short of an L's corner lies farther from
    it. Each round's result is an edit (one corner piece pays after one round; after
    three, both bars have grown into the corner)."""

    name: ClassVar[str] = "absorb"
    passes: int = MAX_PASSES
    tries: int = 3
    rounds: int = 3
    grow: int = 4
    steps: int = 20

    def propose(self, vectors, cost, data, costs, step):
        n = len(vectors)
        if n <= 1:
            return [[]]
        own = _explained_by_each(cost, n)
        adjacent = _adjacent_parts(cost.labels, n)
        pts, idx = figure_points(data)
        shown = np.where(cost.explained_mask, cost.labels, -1).reshape(-1)[idx]
        trials = []
        for i in [int(i) for i in np.argsort(own, kind="stable")[: self.tries] if adjacent[i].any()]:
            beside = tuple(int(j) for j in np.flatnonzero(adjacent[i]))
            stretched = np.stack([_stretched_over(vectors[j], pts[shown == i]) for j in beside])
            trials.append(Edit((i, *beside), vectors[list(beside)]))
            trials += [Edit((i, j), v[None]) for j, v in zip(beside, stretched)]
            if len(beside) > 1:
                trials.append(Edit((i, *beside), stretched))
        return [
            _grown_edits(
                trials, vectors, cost, data, costs, rounds=self.rounds, steps=self.steps, grow=self.grow, every=True
            )
        ]


@dataclasses.dataclass(frozen=True, kw_only=True)
class StretchParts(Move):
    """Each part that answers for unexplained pixels (:func:`_answered_for`) stretched
    over them (:func:`_stretched_over`), then grown (``rounds`` rounds of region
    growing, ``grow`` pixels and ``steps`` solver steps each); the stretched part and
    each round's are edits. A part that stops short of its pixels (a chair's back above
    the seat it meets, its lower edge a strip of unexplained pixels) is reached in one
    jump, where growing takes a few pixels a round and settling a few percent of a
    semi-axis a step, each while E falls."""

    name: ClassVar[str] = "stretch"
    passes: int = MAX_PASSES
    rounds: int = 2
    grow: int = 4
    steps: int = 20

    def propose(self, vectors, cost, data, costs, step):
        pts, idx = figure_points(data)
        owner = _answered_for(cost, data).reshape(-1)[idx]
        trials = render_edits(  # rendered once: growing starts from them, and they are edits too
            [Edit((i,), _stretched_over(vectors[i], pts[owner == i])[None]) for i in np.unique(owner[owner >= 0])],
            data.camera,
        )
        return [
            trials
            + _grown_edits(
                trials, vectors, cost, data, costs, rounds=self.rounds, steps=self.steps, grow=self.grow, every=True
            )
        ]


def _answered_for(cost: EncodingCost, data: RangeData) -> np.ndarray:
    """(H, W) int: for each figure pixel no part explains, the part whose visible pixels
    are nearest (the part that answers for it); -1 elsewhere."""
    from scipy.ndimage import distance_transform_edt

    shown = cost.labels >= 0
    if not shown.any():
        return np.full(cost.labels.shape, -1)
    near = np.asarray(distance_transform_edt(~shown, return_distances=False, return_indices=True))
    return np.where(data.figure_mask & ~cost.explained_mask, cost.labels[near[0], near[1]], -1)


def _explained_by_each(cost: EncodingCost, n: int) -> np.ndarray:
    """(n,) explained pixels each of the ``n`` parts of ``cost`` shows."""
    return np.array([(cost.labels == i)[cost.explained_mask].sum() for i in range(n)])


def _adjacent_parts(labels: np.ndarray, n: int) -> np.ndarray:
    """(n, n) bool: parts whose visible pixels (``labels``, -1 = none) lie within two
    pixels of each other's."""
    from scipy.ndimage import binary_dilation

    grown = [binary_dilation(labels == i, iterations=2) for i in range(n)]
    adjacent = np.array([[i != j and (grown[i] & (labels == j)).any() for j in range(n)] for i in range(n)])
    return adjacent | adjacent.T


def _coordinate_neighbours(vectors: np.ndarray, pixels: np.ndarray, scale: float) -> np.ndarray:
    """Each of the parts ``vectors`` (n, 14) with one parameter a step up and a step down
    (at ``scale`` times): the position a pixel (``pixels``, (n,): a pixel's width at each
    part's depth) along each camera axis, the orientation 0.1 rad about each of the part's
    own axes, each semi-axis 10%, each squareness a factor 1.4, bend and taper 0.1; each
    kept in its range. Returns (n, 28, 14)."""
    from ._search import _orientation_neighbours

    v = np.asarray(vectors, np.float64)
    n = len(v)
    out = np.repeat(v[:, None], 28, axis=1)
    up_down = np.array([1.0, -1.0])
    for k in range(3):
        out[:, 2 * k, k] += pixels * scale
        out[:, 2 * k + 1, k] -= pixels * scale
    out[:, 6:12, 3:6] = _orientation_neighbours(v[:, 3:6], 0.1 * scale).reshape(n, 6, 3)
    for j, (k, f) in enumerate([(k, f) for k in (6, 7, 8) for f in (1 + 0.1 * scale, 1 - 0.1 * scale)]):
        out[:, 12 + j, k] *= f
    for j, (k, f) in enumerate([(k, f) for k in (9, 10) for f in (1 + 0.4 * scale, 1 / (1 + 0.4 * scale))]):
        out[:, 18 + j, k] = np.clip(out[:, 18 + j, k] * f, *SQUARENESS_RANGE)
    for j, (k, d) in enumerate([(k, d) for k in (11, 12, 13) for d in 0.1 * scale * up_down]):
        out[:, 22 + j, k] = np.clip(out[:, 22 + j, k] + d, *BEND_RANGE if k < 13 else TAPER_RANGE)
    return out.astype(np.float32)


MAX_STEP_SCALE = 5.0
"""Largest step scale of :class:`SettleParts` (a semi-axis's step down is then half of it)."""


def _step_scale(x) -> bool:
    ok = isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, (bool, np.bool_))
    return bool(ok and 0 < x <= MAX_STEP_SCALE)


SETTLE_SCALES = (1.0, 0.5, 0.25)
"""The final optimisation's step scales (:class:`SettleParts`, one after another): once
the full steps no longer lower E, half and then a quarter of them do (the step halving
of a pattern search; each stage only ever lowers E)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class SettleParts(Move):
    """The paper's final optimisation (section 3.5): all parts rendered together, one
    part's parameter changed at a time, and the change kept if E falls. Each pass
    proposes every part with each of its 14 parameters a step up and a step down
    (:func:`_coordinate_neighbours`, steps ``scale`` times a pixel, 0.1 rad, 10% of a
    semi-axis, a factor 1.4 in squareness, 0.1 in bend and taper);
    :func:`accept_edits` keeps the best, then each other part's that still lowers E.
    Polishing fits the visible points' distances, which E only approximates: an
    outline's corners (squareness), the extent of a part's hidden side, the pixels
    within ±σ/2 at its rim are where this descent still gains. ``which``: the indices
    of the parts stepped (None: every part; the rest stay as they are)."""

    name: ClassVar[str] = "settle"
    passes: int = MAX_PASSES
    scale: float = 1.0
    which: tuple[int, ...] | None = None

    def __post_init__(self):
        super().__post_init__()
        if not _step_scale(self.scale):
            raise ValueError(f"scale: got {self.scale!r}, expected a number in (0, {MAX_STEP_SCALE}]")
        w = self.which
        index = (int, np.integer)
        if w is not None and not (
            isinstance(w, tuple) and all(isinstance(i, index) and not isinstance(i, bool) and i >= 0 for i in w)
        ):
            raise ValueError(f"which: got {w!r}, expected a tuple of part indices or None (every part)")
        if w is not None:
            object.__setattr__(self, "which", tuple(int(i) for i in w))

    def _moved(self, n: int) -> list[int]:
        """The parts this settling moves (``which``, of ``n``; None: all)."""
        return list(range(n)) if self.which is None else [i for i in self.which if i < n]

    def propose(self, vectors, cost, data, costs, step):
        if len(vectors) == 0:
            return [[]]
        pixels = np.asarray(data.camera.pixel_size_at(vectors[:, 2].astype(np.float64)), np.float64)
        trials = _coordinate_neighbours(vectors, pixels, self.scale)
        return [
            [
                Edit((i,), t[None])
                for i in self._moved(len(vectors))
                for t in trials[i]
                if not np.array_equal(t, vectors[i])
            ]
        ]


def _face_neighbours(vectors: np.ndarray, scale: float) -> np.ndarray:
    """Each of the parts ``vectors`` (n, 14) with one face moved alone: for each of its
    own axes, the semi-axis 5% (at ``scale`` times) up or down and the centre moved as
    much along that axis one way or the other, so that one of the two faces it bounds
    moves by 10% of the semi-axis and the other stays where it is. Returns (n, 12, 14)."""
    from scipy.spatial.transform import Rotation

    v = np.asarray(vectors, np.float64)
    axes = Rotation.from_rotvec(v[:, 3:6]).as_matrix()  # columns: the part's axes in the camera frame
    out = np.repeat(v[:, None], 12, axis=1)
    for j, (k, grow, side) in enumerate([(k, g, s) for k in range(3) for g in (1, -1) for s in (1, -1)]):
        step = 0.05 * scale * v[:, 6 + k]
        out[:, j, 6 + k] += grow * step
        out[:, j, 0:3] += (side * step)[:, None] * axes[:, :, k]
    return out.astype(np.float32)


@dataclasses.dataclass(frozen=True, kw_only=True)
class SettleFaces(SettleParts):
    """:class:`SettleParts` with one face of a part moved at a time
    (:func:`_face_neighbours`) instead of one parameter: a semi-axis and the centre
    stepped together, which one-parameter steps cannot do while each alone raises E (a
    lid grown too thick over the body below it; a part's hidden back face, where noise
    has swollen it in depth)."""

    name: ClassVar[str] = "settle faces"

    def propose(self, vectors, cost, data, costs, step):
        if len(vectors) == 0:
            return [[]]
        trials = _face_neighbours(vectors, self.scale)
        return [[Edit((i,), t[None]) for i in self._moved(len(vectors)) for t in trials[i]]]


def _turned_twin(vector: np.ndarray) -> np.ndarray:
    """The (14,) part ``vector`` with its cross-section's pinch traded for squareness:
    turned 45 degrees about its z axis, ε2 -> 2 - ε2 (at least the smallest squareness)
    and both cross-section semi-axes a * 2^((1 - ε2) / 2) (a their mean), unbent. A
    cross-section |x/a|^(2/ε2) + |y/a|^(2/ε2) <= 1 reaches a * 2^((1 - ε2) / 2) along its
    diagonals and a along its axes; the twin reaches the same two distances the other
    way round, so at ε2 = 2 (a rhombus, |x| + |y| <= a) it is exactly the square it is
    (ε2 = 0), and near it nearly so."""
    from scipy.spatial.transform import Rotation

    v = np.asarray(vector, np.float64).copy()
    e2 = v[10]
    turn = Rotation.from_rotvec(v[3:6]) * Rotation.from_rotvec([0.0, 0.0, math.pi / 4])
    v[3:6] = turn.as_rotvec()
    v[6:8] = (v[6] + v[7]) / 2 * 2.0 ** ((1.0 - e2) / 2)
    v[10] = max(2.0 - e2, SQUARENESS_RANGE[0])
    v[11:13] = 0.0
    return v.astype(np.float32)


@dataclasses.dataclass(frozen=True, kw_only=True)
class UnpinchParts(Move):
    """Each part with a pinched cross-section (ε2 above ``least``) replaced by its twin
    turned 45 degrees about its axis (:func:`_turned_twin`), settled on E alone
    (:class:`SettleParts` at each step scale of ``settle``, the twin's parameters only).
    A box's square cross-section is also a rhombus (ε2 = 2) turned 45 degrees, so a box
    that the grid met turned by about that much is fitted by pinching its cross-section
    instead of turning it; no step of :class:`SettleParts` crosses from one to the other
    (a squareness or an angle moved alone costs more), and the pinched fit never quite
    takes a box's rounded edges. The twin is settled, not grown: on a noisy surface
    region growing's least squares moves a box's faces by more than the pixels allow."""

    name: ClassVar[str] = "unpinch"
    least: float = 1.5
    settle: tuple[float, ...] = SETTLE_SCALES

    def __post_init__(self):
        super().__post_init__()
        if isinstance(self.least, bool) or not (isinstance(self.least, (int, float)) and 1.0 <= self.least < 2.0):
            raise ValueError(f"least: got {self.least!r}, expected a squareness in [1, 2)")
        scales = self.settle
        if not isinstance(scales, tuple) or not scales or not all(_step_scale(x) for x in scales):
            raise ValueError(
                f"settle: got {scales!r}, expected a non-empty tuple of step scales in (0, {MAX_STEP_SCALE}]"
            )

    def propose(self, vectors, cost, data, costs, step):
        edits = []
        for i in np.flatnonzero(vectors[:, 10] > self.least):
            twin = vectors.copy()
            twin[i] = _turned_twin(vectors[i])
            moves = tuple(SettleParts(scale=s, which=(int(i),)) for s in self.settle)
            settled, _, _ = run_moves(moves, twin, encoding_cost(host_parts(twin), data, costs), data, costs)
            edits.append(Edit((int(i),), settled[i][None]))
        return [edits]


_CROP = 32
_RANDOM_TRIALS = 35


@persistent_jit
def _crop_trials(start, u, first, steps, seed, step, corner, rest, measured, figure, sigma, camera):
    """The part with unconstrained vector ``u`` (when ``first``: that of the 14-vector
    ``start``, converted here rather than in a program of its own) and 63 neighbours (each
    parameter a step ``steps_i`` up and down, and ``_RANDOM_TRIALS`` random moves of the
    same scale) rendered in a ``_CROP``² crop at ``corner`` over the other parts' nearest
    depth ``rest``: per trial its unconstrained vector, its 14-vector, explained and
    commission pixel counts in the crop, and whether it reaches the crop's border."""
    u = jnp.where(first, to_unconstrained(Part.from_vector(start)), u)
    key = jax.random.fold_in(jax.random.key(seed), step)  # inside: no eager key programs
    eye = jnp.diag(steps)
    moves = jax.random.normal(key, (_RANDOM_TRIALS, len(u))) * steps / jnp.sqrt(len(u) / 2.0)
    trials = jnp.concatenate([u[None], u + eye, u - eye, u + moves])
    o, d = camera.rays((corner[0], corner[1], _CROP, _CROP))

    def one(v):
        t, hit = cast_part(from_unconstrained(v), o, d)
        z = jnp.minimum(jnp.where(hit, t, jnp.inf), rest)
        explained, commission = pixel_errors(jnp.isfinite(z), z, measured, figure, sigma)
        border = hit[0].any() | hit[-1].any() | hit[:, 0].any() | hit[:, -1].any()
        return explained.sum(), commission.sum(), border

    vectors = jax.vmap(lambda v: from_unconstrained(v).to_vector())(trials)
    return (trials, vectors, *jax.vmap(one)(trials))


def settle_part(vector, layer, rest, data: RangeData, costs: Costs, *, iterations: int = 48, seed: int = 0):
    """Pattern search on E itself for one small part (14-vector ``vector`` whose own
    depth layer is ``layer``) over the other parts' nearest depth ``rest`` (H, W; inf =
    none): each step renders the part and 63 neighbours (:func:`_crop_trials`) in a
    ``_CROP``-pixel crop around it, moves to the best if E falls, and halves the steps
    after two misses: the paper's accept-if-improved descent on the pixel counts that the
    least-squares fits only approximate (a pixel of commission costs λ explained ones).
    Returns the vector unchanged for parts that do not fit the crop."""
    rows, cols = np.nonzero(np.isfinite(layer))
    h, w = layer.shape
    if len(rows) == 0 or h < _CROP or w < _CROP or max(np.ptp(rows), np.ptp(cols)) + 9 > _CROP:
        return vector
    r0 = int(np.clip((rows.min() + rows.max() + 1 - _CROP) // 2, 0, h - _CROP))
    c0 = int(np.clip((cols.min() + cols.max() + 1 - _CROP) // 2, 0, w - _CROP))
    crop = (slice(r0, r0 + _CROP), slice(c0, c0 + _CROP))
    args = (
        np.asarray(rest[crop], np.float32),
        np.ascontiguousarray(data.image[crop]),
        np.ascontiguousarray(data.figure_region[crop]),
        np.float32(data.encoding.sigma),
    )
    pixel = float(data.camera.pixel_size_at(float(vector[2])))
    # Steps: a pixel in position, 0.1 rad, 10% in size, 0.4 in logit squareness, 0.2 in bend and taper.
    base = np.array([pixel] * 3 + [0.1] * 6 + [0.4] * 2 + [0.2] * 3, np.float32)
    start = np.asarray(vector, np.float32)
    u, current, scale, failures = np.zeros(14, np.float32), None, 1.0, 0
    for i in range(iterations):
        trials, vectors, e, c, border = (
            np.asarray(a)
            for a in _crop_trials(
                start,
                u,
                np.bool_(i == 0),
                base * scale,
                np.int32(seed),
                np.uint32(i),
                np.array([r0, c0], np.int32),
                *args,
                camera=data.compiled_camera,
            )
        )
        f = np.where(border, np.inf, costs.total(0, e, c))  # E up to the pixels outside the crop
        k = int(np.argmin(f))
        if current is None:  # trial 0 is the current part
            u, current = trials[0], vectors[0]
        if f[k] < f[0] - 1e-9:
            u, current, failures = trials[k], vectors[k], 0
        else:
            failures += 1
            if failures == 2:  # the random moves differ each time: two misses halve the steps
                scale, failures = scale / 2, 0
                if scale < 0.05:
                    break
    return vector if current is None else current


def _merge_candidates(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(4, 14) vectors of single parts spanning the parts with vectors ``a`` and ``b``
    from end to end: round, straight and bent both ways in the plane of the joint (the
    point nearest both parts' long axes), and straight from the farthest end of one to
    that of the other with their mean squareness; none if they coincide."""
    from scipy.spatial.transform import Rotation

    pa, pb = a[0:3].astype(np.float64), b[0:3].astype(np.float64)
    length = np.linalg.norm(pb - pa)
    if length < 1e-9:
        return np.zeros((0, 14), np.float32)
    axis = (pb - pa) * (1.0 + (a[6:9].max() + b[6:9].max()) / length)  # ends past the centres by the mean half-length
    z = axis / np.linalg.norm(axis)
    ua, ub = (Rotation.from_rotvec(v[3:6].astype(np.float64)).as_matrix()[:, int(np.argmax(v[6:9]))] for v in (a, b))
    # The joint: midway between the closest points of the two long axes.
    m = np.array([[ua @ ua, -ua @ ub], [ua @ ub, -ub @ ub]])
    rhs = np.array([(pb - pa) @ ua, (pb - pa) @ ub])
    s = np.linalg.lstsq(m, rhs, rcond=None)[0] if abs(np.linalg.det(m)) > 1e-6 else np.zeros(2)
    joint = (pa + s[0] * ua + pb + s[1] * ub) / 2 - (pa + pb) / 2
    x = joint - (joint @ z) * z
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    rv = Rotation.from_matrix(np.stack([x, np.cross(z, x), z], 1)).as_rotvec()
    width = max(np.sort(a[6:9])[1], np.sort(b[6:9])[1])
    depth = max(a[6:9].min(), b[6:9].min())
    round_ = [
        [*(pa + pb) / 2, *rv, width, depth, np.linalg.norm(axis) / 2, 1.0, 1.0, bend, 0.0, 0.0]
        for bend in (-0.3, 0.0, 0.3)
    ]
    # Two pieces of one straight member share its cross-section, and it runs from the
    # farthest end of one to the farthest end of the other.
    ends = [(p - pa) @ z + sign * v[6:9].max() * (u @ z) for p, u, v in ((pa, ua, a), (pb, ub, b)) for sign in (-1, 1)]
    lo, hi = min(ends), max(ends)
    straight = [*(pa + z * (lo + hi) / 2), *rv, width, depth, (hi - lo) / 2, *(a[9:11] + b[9:11]) / 2, 0.0, 0.0, 0.0]
    return np.asarray(round_ + [straight], np.float32)


def _moment_candidates(points: np.ndarray, sigma: float, *, disc: bool = False) -> np.ndarray:
    """(13, 14) vectors (with ``disc``, (14, 14)) of single parts summarising the 3-D
    surface ``points`` (n, 3) from their moments: centred on them, axes along their
    principal directions (longest = z, least = y, nearly the viewing direction of a
    visible surface), semi-axes from their 1-99% extents. The depth (y) semi-axis is
    either thin (a plate: a laptop lid, a table top) or as deep as the part is wide (a
    solid seen from one side, the symmetric interpretation of its hidden side), its
    centre then pushed back from the camera; box-like, round or a cylinder. Three of the
    solids are bent and tapered as the points' centre line and width say
    (:func:`_deformation_moments`: footnote 11's bending of the longest axis and
    tapering along it), so one limb that the search cut in two, or a bent part it fitted
    with a straight one, is summarised as one. Next, with ``disc``, a disc: local z on
    the least axis (a round plate: a lid, a cap). The last is a plate bent through
    itself (:func:`_plate_bend`: a chair's back, a curved panel), which the bent solids,
    as deep as they are wide, do not reach."""
    from scipy.spatial.transform import Rotation

    p = np.asarray(points, np.float64)
    c = p.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov((p - c).T))
    axes = vecs[:, ::-1]  # columns: longest, middle, least
    lo, hi = np.percentile((p - c) @ axes, [1, 99], axis=0)
    mid = c + axes @ ((lo + hi) / 2)
    half = np.maximum((hi - lo) / 2 / 0.98, sigma / 2)  # exact for a uniformly covered face
    z, x, y = axes[:, 0], axes[:, 1], axes[:, 2]
    if y @ mid < 0:  # y away from the camera
        y = -y

    def rotvec(x, y, z):
        frame = np.stack([x, y, z], 1)
        if np.linalg.det(frame) < 0:
            frame[:, 0] = -frame[:, 0]
        return Rotation.from_matrix(frame).as_rotvec()

    along, across = rotvec(x, y, z), rotvec(z, y, x)  # the local z axis along the longest or the middle axis
    thin, deep = sigma / 2, half[1]
    out = []
    # A plate's face on the points' mid-plane (rectangular or elliptical outline: ε1);
    # a solid's front on their nearest points: a box, an ellipsoid, a cylinder (a mug's
    # body) standing along either axis.
    for depth, front, e1, e2, rv, a1, a3 in (
        (thin, 0.0, 0.1, 0.1, along, half[1], half[0]),
        (thin, 0.0, 1.0, 0.1, along, half[1], half[0]),
        (deep, half[2], 0.1, 0.1, along, half[1], half[0]),
        (deep, half[2], 1.0, 1.0, along, half[1], half[0]),
        (deep, half[2], 0.1, 1.0, along, half[1], half[0]),
        (half[0], half[2], 0.1, 1.0, across, half[0], half[1]),
    ):
        centre = mid + y * (depth - front)
        out.append([*centre, *rv, a1, depth, a3, e1, e2, 0.0, 0.0, 0.0])
    # The deformed solids: local x along the centre line's bend, which may lie in the
    # image (x) or along the view (y); the symmetric cross-section, as deep as wide.
    local = (p - mid) @ np.stack([z, x, y], 1)
    offset, bend, taper = _deformation_moments(local, half[0])
    phi = math.atan2(bend[1], bend[0])
    bx = math.cos(phi) * x + math.sin(phi) * y
    rv = rotvec(bx, np.cross(z, bx), z)
    centre = mid + x * offset[0] + y * (deep - half[2])
    for e1, e2 in ((1.0, 1.0), (0.1, 1.0), (0.4, 0.4)):
        out.append([*centre, *rv, half[1], deep, half[0], e1, e2, float(np.hypot(*bend)), 0.0, taper])
    # The same solids as deep as their rim says (:func:`_rim_depth`): a symmetric solid's
    # rim, where its surface turns away from the view, lies on its mid-plane.
    rim = _rim_depth(local, sigma)
    front = mid - y * half[2]
    for e1, e2 in ((1.0, 1.0), (0.1, 1.0)):
        out.append([*(front + y * rim), *along, half[1], rim, half[0], e1, e2, 0.0, 0.0, 0.0])
    out.append(
        [*(front + x * offset[0] + y * rim), *rv, half[1], rim, half[0], 1.0, 1.0, float(np.hypot(*bend)), 0.0, taper]
    )
    # A disc: local z on the least axis, a round outline (ε2 = 1) over the longest and
    # middle axes, as thick as the points reach along it (a lid, a wheel, a mushroom's
    # cap seen from the side, whose visible rim spans its thickness) and its rim rounded
    # halfway (ε1 = 0.5; fitting from a flat rim, at the bound, leaves it flat): a round
    # plate, which the starts above (local z in the plate) do not reach by fitting.
    if disc:
        out.append([*mid, *rotvec(z, x, y), half[0], half[1], max(half[2], thin), 0.5, 1.0, 0.0, 0.0, 0.0])
    # A plate bent through itself (a chair's back, a curved panel): its surface's depth
    # fitted as a quadric over the plate (:func:`_plate_bend`) bends it along the
    # direction of larger principal curvature; local x then lies along the view, and the
    # plate is thin there.
    depth, curve, dirs = _plate_bend(local)
    k = int(np.argmax(np.abs(curve)))
    along = dirs[0, k] * z + dirs[1, k] * x
    s_lo, s_hi = np.percentile(local[:, :2] @ dirs, [1, 99], axis=0)
    length, width = np.maximum((s_hi - s_lo) / 2 / 0.98, sigma / 2)[[k, 1 - k]]
    at = dirs @ ((s_lo + s_hi) / 2)  # the plate's centre in (z, x)
    centre = mid + z * at[0] + x * at[1] + y * (depth(*at) + thin)
    b = float(np.clip(curve[k] * length, -0.9, 0.9))
    out.append([*centre, *rotvec(y, np.cross(along, y), along), thin, width, length, 0.1, 0.1, b, 0.0, 0.0])
    return np.asarray(out, np.float32)


def _plate_bend(local: np.ndarray):
    """A plate's bend through itself from its visible surface points ``local`` (n, 3) in
    the moment frame (columns: along the longest axis z, the middle axis x, the least
    axis y, nearly the view): the depth fitted as a quadric y = c0 + c1 z + c2 x + h_zz
    z² + 2 h_zx z x + h_xx x² by least squares. Returns (the quadric as a function of z
    and x, the eigenvalues (2,) of h, half the surface's principal curvatures (a part
    bent along a direction s deflects its tip at a3 by bend·a3 = h_s a3², so bend =
    h_s a3), and their directions (2, 2) as columns in (z, x))."""
    zz, xx, yy = local[:, 0], local[:, 1], local[:, 2]
    c = np.linalg.lstsq(np.stack([np.ones_like(zz), zz, xx, zz * zz, 2 * zz * xx, xx * xx], 1), yy, rcond=None)[0]
    curve, dirs = np.linalg.eigh(np.array([[c[3], c[4]], [c[4], c[5]]]))

    def depth(z, x):
        return float(c[0] + c[1] * z + c[2] * x + c[3] * z * z + 2 * c[4] * z * x + c[5] * x * x)

    return depth, curve, dirs


def _rim_depth(local: np.ndarray, sigma: float, *, slices: int = 8) -> float:
    """How far behind its nearest point a solid's mid-plane lies, from its visible
    surface points ``local`` (n, 3) in the moment frame (columns: along the longest axis,
    across it in the image, along the view). A solid symmetric about its mid-plane has
    its rim there, where the surface turns away from the view and its cross-section is
    widest; in each of ``slices`` slices along the axis the squared width x² is fitted as
    a parabola in the depth y (exact for an elliptical cross-section, x² = rx² (1 - (y -
    yc)² / ry²)): the rim lies at its vertex yc and the half-depth is ry, its distance
    from the front root. A slice whose width does not fall off with depth (a flat face)
    says nothing. The median over the slices that say something, at least σ/2."""
    edges = np.quantile(local[:, 0], np.linspace(0.0, 1.0, slices + 1)[1:-1])
    which = np.digitize(local[:, 0], edges)
    depths = []
    for k in range(slices):
        s = local[which == k]
        if len(s) < 8:
            continue
        # The slice's own centre line (its points' across-axis midpoint), then the fit.
        # A face at one depth says nothing (and fails numpy's fit); a nearly flat one
        # makes the fit rank-deficient: numpy warns, and the checks below drop the slice.
        y = s[:, 2] - np.median(s[:, 2])
        if not np.ptp(y) > 0:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            x = s[:, 1] - np.polyval(np.polyfit(s[:, 0], s[:, 1], 1), s[:, 0])
            c2, c1, c0 = np.polyfit(y, x * x, 2)
        disc = c1 * c1 - 4 * c2 * c0
        if c2 < 0 and disc > 0:
            depths.append(np.sqrt(disc) / (2 * -c2))
    return float(max(np.median(depths), sigma / 2)) if depths else sigma / 2


def _deformation_moments(local: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Bend and taper of a part from its surface points ``local`` (n, 3) in the moment
    frame (columns: along the longest axis z, the middle axis x, the least axis y),
    ``length`` its half-length a3. The centre line's offsets x(z), y(z) are fitted by
    least-squares parabolas c0 + c1 z + c2 z²: Part's bend moves x by bend·z²/a3, so the
    bend is c2·a3 in each direction; the taper scales the cross-section by 1 + t z/a3, so
    the points' mean distance from the line across x, fitted as r0 + r1 z, gives
    t = a3 r1 / r0. Returns (the line's offsets c0 in x and y, the bend in x and y, the
    taper), bend and taper clipped into Part's ranges."""
    z = local[:, 0] / max(length, 1e-9)
    basis = np.stack([np.ones_like(z), z, z * z], 1)
    coef = np.linalg.lstsq(basis, local[:, 1:3], rcond=None)[0]  # (3, 2): x and y parabolas
    r = np.abs(local[:, 1] - basis @ coef[:, 0])
    r0, r1 = np.linalg.lstsq(basis[:, :2], r, rcond=None)[0]
    bend = np.clip(coef[2] / max(length, 1e-9), -0.9, 0.9) if length > 0 else np.zeros(2)
    taper = float(np.clip(r1 / r0, -0.9, 0.9)) if r0 > 1e-9 else 0.0
    return coef[0], bend, taper


def _part_groups(adjacent: np.ndarray) -> list[tuple]:
    """Groups of two or more parts that one part might summarise: each part with its
    neighbours, and each connected set of adjacent parts (``adjacent``: (n, n) bool)."""
    from scipy.sparse.csgraph import connected_components

    _, comp = connected_components(adjacent, directed=False)
    groups = {tuple(np.flatnonzero(adjacent[i] | (np.arange(len(adjacent)) == i))) for i in range(len(adjacent))}
    groups |= {tuple(np.flatnonzero(comp == k)) for k in np.unique(comp)}
    return sorted(g for g in groups if len(g) >= 2)


@dataclasses.dataclass(frozen=True, kw_only=True)
class MergeParts(Move):
    """Adjacent parts replaced by one part (section 4.1).

    Every adjacent pair gets bent single-part starts (:func:`_merge_candidates`), and
    every group of adjacent parts (:func:`_part_groups`: a part with its neighbours, a
    connected set) gets starts from the moments of its pixels (:func:`_moment_candidates`:
    a laptop seen as five rounded patches is one flat box; a bent, tapered limb seen as
    two or three pieces is one bent, tapered part). On the first pass the ``tries`` single
    parts with the most bits to win back (unexplained and commission pixels they answer
    for) get the same starts from their own pixels: one part's description replaced by a
    shorter one (a polish that settled on the wrong squareness or depth, a straight fit
    of a bent part); with ``alone``, again from their explained pixels alone (the
    unexplained pixels beside a thin plate seen edge-on, fitted bent, pull its starts
    bent again); with ``disc``, a disc on the least axis among the moment starts (a
    lid, a mushroom's cap seen as two plates: a superquadric's round outline lies about
    its local z, which the other starts put in the plate). Only in the merge after
    settling, where a start can only shorten the settled description: earlier, a disc
    that summarises a round body at once (a teapot seen from above) wins a merge that
    leaves the descent in a longer end. All are fitted by batched LM calls of
    ``steps`` steps to the pixels their starts came from (the moment starts, farther
    from their answer, twice over); every start, as it is and fitted, is an edit (the
    distances that the fits minimise thicken a thin plate, and lengthen a bar whose
    ends meet other parts).
    With ``pieces`` ((H, W) int: the piece of the figure each pixel lies in, -1 none;
    figures that one object's own occlusions may have torn apart) only parts in
    different pieces (where each explains most of its pixels) count as adjacent: merges
    across the tears alone."""

    name: ClassVar[str] = "merge"
    passes: int = MAX_PASSES
    steps: int = 20
    tries: int = 3
    alone: bool = False
    disc: bool = False
    pieces: np.ndarray | None = dataclasses.field(default=None, compare=False, repr=False)

    def __post_init__(self):
        super().__post_init__()
        if self.pieces is not None:
            pieces = np.asarray(self.pieces)
            if pieces.ndim != 2 or not np.issubdtype(pieces.dtype, np.integer):
                raise ValueError(
                    f"pieces: got an array of shape {pieces.shape} and dtype {pieces.dtype}, expected (H, W) integers"
                )
            object.__setattr__(self, "pieces", pieces)

    def propose(self, vectors, cost, data, costs, step):
        n = len(vectors)
        if self.pieces is not None and self.pieces.shape != np.shape(cost.labels):
            raise ValueError(f"pieces: got shape {self.pieces.shape}, expected the image's {np.shape(cost.labels)}")
        if n == 0:
            return [[]]
        pts, idx = figure_points(data)
        rays, ray_index = background_rays(data)
        adjacent = _adjacent_parts(cost.labels, n)
        if self.pieces is not None:  # across the tears alone
            shown = cost.explained_mask & (self.pieces >= 0)
            counts = [np.bincount(self.pieces[shown & (cost.labels == i)]) for i in range(n)]
            piece = np.array([c.argmax() if len(c) else -1 for c in counts])
            adjacent &= piece[:, None] != piece[None, :]
        inits, weights, ray_weights, members = [], [], [], []
        owner = _answered_for(cost, data)

        def add(group, starts, *, whole=False):
            union = np.isin(cost.labels, group) & cost.explained_mask
            if whole:
                union = union | np.isin(owner, group)
            w = union.reshape(-1)[idx].astype(np.float32)
            if w.sum() < 8:
                return
            wr = rays_near(np.isin(cost.labels, group), ray_index, 5)
            for init in starts(w):
                inits.append(init)
                weights.append(w)
                ray_weights.append(wr)
                members.append(tuple(int(g) for g in group))

        for i, j in zip(*np.nonzero(np.triu(adjacent))):
            add((i, j), lambda w: _merge_candidates(vectors[i], vectors[j]))
        n_pairs = len(inits)
        # Single parts, on the first pass: the ``tries`` that could gain most, i.e. with
        # the most bits to win back from the pixels they answer for (unexplained: κ3 - κ1
        # each; commission: κ2 each).
        gain = np.array(
            [
                np.isin(owner, [i]).sum() * (costs.omission - costs.explained)
                + (cost.commission_mask & (cost.labels == i)).sum() * costs.commission
                for i in range(n)
            ]
        )
        singles = [(int(i),) for i in np.argsort(-gain, kind="stable")[: self.tries] if step == 0 and gain[i] > 0]

        def moments(w):
            return _moment_candidates(pts[w > 0], data.encoding.sigma, disc=self.disc)

        for group in _part_groups(adjacent) + singles:
            add(group, moments, whole=True)
        for group in singles if self.alone else []:  # and from its explained pixels alone
            if np.isin(owner, group).any():  # (where it answers for others)
                add(group, moments)
        if not inits:
            return [[]]
        w_all, wr_all, start = np.stack(weights), np.stack(ray_weights), np.stack(inits)

        def fit(rows, calls):
            # ``calls`` solves of ``steps`` each, not one longer one: the same compiled program.
            out = start[rows]
            for _ in range(calls if len(out) else 0):
                out = part_vectors(polish_parts(host_parts(out), pts, w_all[rows], self.steps, rays, wr_all[rows]))
            return out

        fitted = np.concatenate([fit(slice(0, n_pairs), 1), fit(slice(n_pairs, len(inits)), 2)])
        return [[Edit(group, v[None]) for v, group in zip(np.concatenate([fitted, start]), members * 2)]]


@dataclasses.dataclass(frozen=True)
class OnGain:
    """Run ``move``, then the moves ``then`` only if it lowered E; all of it up to
    ``repeat`` times while ``move`` lowers E (after a merge: the merged part grows onto
    its neighbourhood as the others did, parts the merge made redundant are dropped,
    and the parts as they now are may merge again)."""

    move: Move
    then: tuple = ()
    repeat: int = 1

    def __post_init__(self):
        r = self.repeat
        if isinstance(r, bool) or not isinstance(r, (int, np.integer)) or not 1 <= r <= MAX_PASSES:
            raise ValueError(f"repeat: got {r!r}, expected an integer in [1, {MAX_PASSES}]")


def run_moves(moves, vectors: np.ndarray, cost: EncodingCost, data: RangeData, costs: Costs, *, branch: bool = True):
    """The refinement loop: each of ``moves`` (:class:`Move` or :class:`OnGain`) in turn,
    pass after pass while its passes lower E, each pass's edits accepted by
    :func:`accept_edits`. The first pass that proposes alternatives (when ``branch``) has
    the rest (the move's own passes left, then the other moves) finish each, and the
    shorter description is kept; within those finishes (``branch`` False) a pass keeps
    its alternative of lowest E and goes on, so a refinement finishes at most as many
    descriptions as that one pass proposed, however many passes propose alternatives.
    Returns (vectors, cost, history of (stage, E))."""
    history = []
    for m, move in enumerate(moves):
        if isinstance(move, OnGain):
            for _ in range(move.repeat):
                before = cost.total
                vectors, cost, stages = run_moves((move.move,), vectors, cost, data, costs, branch=branch)
                history += stages
                if cost.total >= before:
                    break
                vectors, cost, stages = run_moves(move.then, vectors, cost, data, costs, branch=branch)
                history += [(f"{stage} after {move.move.name}", e) for stage, e in stages]
            continue
        for step in range(move.passes):
            ends = []
            for edits in move.propose(vectors, cost, data, costs, step):
                end = accept_edits(vectors, cost, edits, data, costs)
                if not any(np.array_equal(end[0], v) for v, _ in ends):  # False for different part counts too
                    ends.append(end)
            if len(ends) > 1 and branch:
                rest = moves[m + 1 :]
                if step + 1 < move.passes:  # the move's own passes left come first
                    rest = (dataclasses.replace(move, passes=move.passes - step - 1), *rest)
                finished = [run_moves(rest, v, c, data, costs, branch=False) for v, c in ends]
                k = min(range(len(ends)), key=lambda k: finished[k][1].total)
                vectors, cost, stages = finished[k]
                return vectors, cost, [*history, (move.name, ends[k][1].total), *stages]
            end = min(ends, key=lambda e: e[1].total)
            improved = end[1].total < cost.total
            vectors, cost = end
            if move.numbered:
                history.append((f"{move.name} {step + 1}", cost.total))
            if not improved:
                break
        if not move.numbered:
            history.append((move.name, cost.total))
    return vectors, cost, history


def refine_moves(parts: Part, data: RangeData, costs: Costs, moves):
    """Refine ``parts`` by the loop over ``moves`` (:func:`run_moves`; e.g.
    :meth:`RefineSettings.moves`). Returns (parts, final cost, history of (stage, E) from
    ``"initial"``)."""
    vectors = part_vectors(parts)
    cost = encoding_cost(host_parts(vectors), data, costs)
    vectors, final, history = run_moves(tuple(moves), vectors, cost, data, costs)
    return Part.from_vector(vectors), final, [("initial", cost.total), *history]


MERGE_POLISH_ROUNDS = 4
"""Most rounds of region growing after a merge (each kept only if E falls)."""


def refine_parts(
    parts: Part,
    data: RangeData,
    costs: Costs,
    *,
    rounds: int = 3,
    steps: int = 20,
    split: bool = True,
    merge: bool = True,
    straighten: bool = True,
    settle: tuple[float, ...] = SETTLE_SCALES,
    absorb: bool = True,
    faces: bool = True,
    stretch: bool = True,
    unpinch: bool = True,
    search=None,
):
    """Joint refinement with :class:`RefineSettings`' moves, in the order its docstring
    gives (the keywords are its fields; ``fill`` when ``search``, the first search's
    :class:`~sqparts.SearchSettings`, is given). Returns (parts, final cost, history of E
    after each stage)."""
    settings = RefineSettings(
        rounds=rounds,
        steps=steps,
        split=split,
        fill=search is not None,
        merge=merge,
        straighten=straighten,
        settle=settle,
        absorb=absorb,
        faces=faces,
        stretch=stretch,
        unpinch=unpinch,
    )
    return refine_moves(parts, data, costs, settings.moves(search))


MAX_REFINE_ROUNDS = 100
"""Most rounds of joint polishing a recovery may ask for (a bound on its work)."""


@dataclasses.dataclass(frozen=True)
class RefineSettings:
    """Joint refinement after selection (:func:`refine_moves` with :meth:`moves`):
    ``rounds`` passes of :class:`GrowParts` of ``steps`` solver steps each (rounded up to
    a multiple of :data:`~sqparts._polish.POLISH_CALL_STEPS`; 0 = none), then ``split``
    (:class:`SplitParts`), ``fill`` (:class:`FillGaps`: the blobs still unexplained
    searched again at their own scale, for small parts: hands, feet), dropping parts that
    do not pay (:class:`DropParts`), ``merge`` (:class:`MergeParts`, each merge
    followed by growing and dropping again, until merging no longer lowers E),
    ``straighten`` (:class:`StraightenParts`: bent or tapered parts fitted again
    without their deformation), the paper's final optimisation of every parameter on E
    itself (:class:`SettleParts`,
    once per step scale in ``settle``, :data:`SETTLE_SCALES` by default; () = none),
    ``unpinch`` (:class:`UnpinchParts`: a part with a pinched cross-section against its
    twin turned 45 degrees, settled; the settling again if that lowered E; none without
    ``settle``),
    ``absorb`` (:class:`AbsorbParts`: a small part dropped while its neighbours grow
    over its pixels; the settling again if that lowered E), ``merge`` once more
    (settled parts may merge where they did not before, and single parts are summarised
    from their explained pixels alone too, with discs among the starts; then grown,
    dropped, straightened and settled again),
    ``faces`` (:class:`SettleFaces`: settling with one face of a part moved at a time,
    once per step scale in ``settle``), and last ``stretch`` (:class:`StretchParts`:
    parts stretched over the unexplained pixels they answer for; then settled again, by
    parameters and by faces), each kept only when E falls: these four, after settling,
    can only shorten the description the rest gives.
    ``RefineSettings.none()``: no refinement."""

    rounds: int = 2
    steps: int = 20
    split: bool = True
    fill: bool = True
    merge: bool = True
    straighten: bool = True
    settle: tuple[float, ...] = SETTLE_SCALES
    absorb: bool = True
    faces: bool = True
    stretch: bool = True
    unpinch: bool = True

    def __post_init__(self):
        r = self.rounds
        if isinstance(r, bool) or not isinstance(r, (int, np.integer)) or not (0 <= r <= MAX_REFINE_ROUNDS):
            raise ValueError(f"rounds: got {r!r}, expected an integer in [0, {MAX_REFINE_ROUNDS}]")
        if isinstance(self.steps, bool) or not isinstance(self.steps, (int, np.integer)) or not 1 <= self.steps <= 1000:
            raise ValueError(f"steps: got {self.steps!r}, expected an integer in [1, 1000]")
        for name in ("split", "fill", "merge", "straighten", "absorb", "faces", "stretch", "unpinch"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}: got {getattr(self, name)!r}, expected True or False")
        scales = self.settle
        if not isinstance(scales, (tuple, list)) or len(scales) > 8 or not all(_step_scale(x) for x in scales):
            raise ValueError(
                f"settle: got {scales!r}, expected a tuple of at most 8 step scales in (0, {MAX_STEP_SCALE}] (() for none)"
            )
        object.__setattr__(self, "settle", tuple(float(x) for x in scales))

    @classmethod
    def none(cls) -> RefineSettings:
        return cls(
            rounds=0,
            split=False,
            fill=False,
            merge=False,
            straighten=False,
            settle=(),
            absorb=False,
            faces=False,
            stretch=False,
            unpinch=False,
        )

    @property
    def active(self) -> bool:
        return (
            self.rounds > 0
            or self.split
            or self.fill
            or self.merge
            or self.straighten
            or self.absorb
            or self.stretch
            or bool(self.settle)
        )

    def regrow(self) -> tuple:
        """What follows a merge that lowered E: the parts grown again (at most
        :data:`MERGE_POLISH_ROUNDS` rounds of :class:`GrowParts`), then those that no
        longer pay dropped."""
        return (GrowParts(passes=MERGE_POLISH_ROUNDS, steps=self.steps), DropParts())

    def moves(self, search=None) -> tuple:
        """The moves these settings ask for, in order; ``search`` (the first search's
        resolved :class:`~sqparts.SearchSettings`) is used for filling gaps."""
        moves: list = [GrowParts(passes=self.rounds, steps=self.steps)] if self.rounds else []
        if self.split:
            moves.append(SplitParts(steps=self.steps))
        if self.fill and search is not None:
            moves.append(FillGaps(search=search, steps=self.steps))
        moves.append(DropParts())
        again = self.regrow()
        if self.merge:
            moves.append(OnGain(MergeParts(passes=1, steps=self.steps), then=again, repeat=MAX_PASSES))
        straighten = (StraightenParts(steps=self.steps),) if self.straighten else ()
        moves.extend(straighten)
        settle = tuple(SettleParts(scale=s) for s in self.settle)
        moves.extend(settle)
        if self.unpinch and settle:  # the settled twin against the settled part
            moves.append(OnGain(UnpinchParts(settle=self.settle), then=settle))
        if self.absorb:  # after settling: it only ever shortens the settled description
            moves.append(OnGain(AbsorbParts(steps=self.steps), then=settle))
        if self.merge:  # after settling, likewise: the parts as settled may merge where they did not before
            # The single parts as settled, too, and discs among the starts.
            last = MergeParts(passes=1, steps=self.steps, alone=True, disc=True)
            moves.append(OnGain(last, then=again + straighten + settle))
        faces = tuple(SettleFaces(scale=s) for s in self.settle) if self.faces else ()
        moves.extend(faces)  # likewise
        if self.stretch:  # last of all, likewise
            moves.append(OnGain(StretchParts(steps=self.steps), then=settle + faces))
        return tuple(moves)

    def refine(self, parts: Part, data: RangeData, costs: Costs, search=None):
        """:func:`refine_moves` with :meth:`moves`."""
        return refine_moves(parts, data, costs, self.moves(search))
