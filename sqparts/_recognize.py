"""Matching part-structure descriptions (section 1: recognition by matching stable descriptions).

A query :class:`~sqparts.Description` (one figure of a recovered scene) is matched to a
stored one by an assignment of query parts to model parts that maximises a score in
[0, 1]: each matched pair contributes its volume weight sqrt(v_query · v_model) times
its unary similarity (sizes, squareness, taper, bend) times the mean similarity of its
relations to the other matched pairs (gap, distance, offsets, axis angle). Unmatched
parts on either side contribute nothing, so a model with a part hidden (occlusion) or a
query with an extra part still matches, with a somewhat lower score. Optionally
(``MatchSettings.shape_tolerance``) the part match's score is then multiplied by the similarity of the two whole objects' shape distributions
(:func:`shape_similarity`), a term derived from the parts that does not depend on how
the solid was cut into them.

The assignment is solved by ``scipy.optimize.linear_sum_assignment``: first on the
unary similarities, then a few times on the unary similarities weighted by the pairwise
consistency with the previous assignment (the linearisation step of integer projected
fixed point, IPFP, Leordeanu et al. 2009); the best-scoring assignment is kept.
Sizes and relations are compared in scene units (a range image is metric), each
difference divided by a tolerance that is a fraction of the model's scale.

The model's pose in the query's frame is estimated from the matched parts' centres by
weighted Kabsch (``scipy.spatial.transform.Rotation.align_vectors``), or from the axes
of the best matched pair when fewer than three parts match.

Beside the part match, the two whole solids are aligned (:func:`align_descriptions`):
each pair of similar parts, one in the query and one in the model, proposes poses that
put one part's axes on the other's (the 24 ways a part's axes can be relabelled and
flipped: a superquadric's axes are known only up to that), the proposals are scored
all at once by how much of the model's outer surface lands near the query's, and the
best few are refined by iterative closest points (weighted Kabsch on both directions'
nearest neighbours). Its score, the share of each surface lying within a tolerance of
the other, does not depend on how either solid was cut into parts; the database
scores a stored view by the geometric mean of the two (``MatchSettings.alignment_tolerance``).

Hypothesise, then verify: when the query's range image is known (:class:`Observation`),
each refined alignment is fitted to the figure's observed points by ICP
(:func:`fit_pose`), then the stored parts at that pose are rendered into the query's
camera (:func:`verify_poses`, one batched call of the package's renderer for every pose
of every stored view) and compared with the observed depth pixel by pixel. Both steps
work on the data, not on the query's recovered parts, which change from view to view
more than the object does. A view then scores the verification of its best pose
(``MatchSettings.verification_tolerance``): the alignment proposes poses, the image
judges them; the part match still gives the correspondences.

Configuration (section 1: a person learnt standing is seen walking): each fitted pose is
also verified with the stored parts articulated (:func:`articulate`) about the joints of
a kinematic tree over the parts that touch (:func:`kinematic_tree`, made once per stored
view), and scores the better of its rigid and its articulated rendering
(``MatchSettings.articulated``).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import KDTree
from scipy.spatial.transform import Rotation

from ._camera import Camera
from ._describe import ATTRIBUTES, RELATIONS, SHAPE_BINS, SHAPE_RANGE, Description, part_volume, surface_samples


@dataclasses.dataclass(frozen=True)
class MatchSettings:
    """Tolerances of :func:`match_descriptions` and :func:`align_descriptions`.

    Attributes
    ----------
    size_tolerance : sigma of the log of a semi-axis (the semi-axes compared in scene
        units); the unary similarity is exp(-d²/2), d the RMS over the seven features of
        their differences divided by their sigmas.
    squareness_tolerance, deformation_tolerance : sigma of ε and of |taper|, |bend|.
    distance_tolerance : sigma of gaps, distances and offsets, a fraction of the model's scale.
    angle_tolerance : sigma of the angle between longest axes (radians).
    min_similarity : a pair less similar than this is left unmatched.
    iterations : IPFP re-assignments after the first.
    shape_tolerance : the whole-object term: the part match's score is multiplied by
        max(0, 1 - W / shape_tolerance), W the earth mover's distance between the two
        descriptions' shape distributions (in object scales: 0.5 = the typical distance
        between surface points moved by half the object's scale); None (the default): the
        parts alone. Off by default: a whole-object term punishes a query with parts hidden
        (occlusion), which the part match by itself tolerates.
    alignment_tolerance : the whole-solid alignment (:func:`align_descriptions`): the
        tolerance σ of a surface point's distance to the other surface, a fraction of the
        larger object's scale; a point at distance d counts exp(-d²/2σ²). The database
        scores a view by the geometric mean of the part match's score and the
        alignment's. None: parts alone.
    alignment_pairs : how many (query part, model part) pairs, most similar and largest
        first, propose poses (24 each).
    alignment_starts : how many of the best proposals are refined.
    verification_tolerance : verifying poses by rendering (:func:`verify_poses`), when
        the query's range image is known: the tolerance τ of a rendered depth's
        difference from the observed one, a fraction of the query's scale (one
        tolerance for every stored object a query is compared with, so that a larger
        model is not judged more leniently). Each refined alignment is first fitted to
        the observed points (:func:`fit_pose`); a view then scores the verification of
        its best pose (the alignment proposed it; the image judges it). None: no
        verification.
    verification_levels : the verification is the mean of its scores at τ, τ/2, ...,
        τ/2^(levels-1): a pose that puts the surface within τ/4 of the data scores
        higher than one within τ, so that the object whose shape fits closely stands out
        from those that merely cover the figure.
    articulated : also verify each fitted pose with the stored parts articulated about
        their joints (:func:`articulate`; section 1's stability under configuration: a
        person learnt standing, seen walking), the pose scoring the better of its rigid
        and its articulated rendering. False: rigid poses alone.
    pose_rotations, pose_starts : with the range image known, each stored view is also
        posed from the observed points alone (:func:`propose_poses`): ``pose_rotations``
        rotations spread over all of them are ranked by how close the points come to the
        model's surface, and the ``pose_starts`` best distinct ones are fitted and
        verified beside the alignment's starts. The alignment of two recoveries proposes
        poses only where the query was cut into parts like the stored view's; on the
        recognition benchmark the true object's best verified pose was found at 0.2-0.6
        where its pose from the benchmark's ground truth verified at 0.6-0.9 (run 11 in
        ``benchmarks/README.md``). 0: the alignment's starts alone (about half the
        matching time).
    weighting : a matched pair's weight: ``"fraction"``, sqrt(v_query v_model) of the two
        parts' volume fractions; ``"volume"``, min(V_query, V_model) / max(ΣV_query,
        ΣV_model) of their volumes in scene units, so that a query explaining only a small
        piece of a model (or a model only a small piece of the query) scores low.
    """

    size_tolerance: float = 0.3
    squareness_tolerance: float = 0.45
    deformation_tolerance: float = 0.4
    distance_tolerance: float = 0.25
    angle_tolerance: float = 0.6
    min_similarity: float = 0.05
    iterations: int = 4
    weighting: str = "volume"
    shape_tolerance: float | None = None
    alignment_tolerance: float | None = 0.08
    alignment_pairs: int = 12
    alignment_starts: int = 4
    verification_tolerance: float | None = 0.1
    verification_levels: int = 3
    articulated: bool = True
    pose_rotations: int = 512
    pose_starts: int = 4

    def __post_init__(self):
        def number(v) -> bool:
            return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and np.isfinite(v)

        for name in ("size_tolerance", "squareness_tolerance", "deformation_tolerance", "distance_tolerance"):
            if not (number(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name}: got {getattr(self, name)!r}, expected a finite number > 0")
        if not (number(self.angle_tolerance) and self.angle_tolerance > 0):
            raise ValueError(f"angle_tolerance: got {self.angle_tolerance!r}, expected radians > 0")
        if not (number(self.min_similarity) and 0 <= self.min_similarity <= 1):
            raise ValueError(f"min_similarity: got {self.min_similarity!r}, expected a number in [0, 1]")
        k = self.iterations
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 0:
            raise ValueError(f"iterations: got {k!r}, expected an integer >= 0")
        if not isinstance(self.articulated, (bool, np.bool_)):
            raise ValueError(f"articulated: got {self.articulated!r}, expected True or False")
        if self.weighting not in ("fraction", "volume"):
            raise ValueError(f"weighting: got {self.weighting!r}, expected 'fraction' or 'volume'")
        t = self.shape_tolerance
        if t is not None and not (isinstance(t, (int, float)) and np.isfinite(t) and t > 0):
            raise ValueError(f"shape_tolerance: got {t!r}, expected a number > 0 or None")
        for name in ("alignment_tolerance", "verification_tolerance"):
            t = getattr(self, name)
            if t is not None and not (isinstance(t, (int, float)) and np.isfinite(t) and t > 0):
                raise ValueError(f"{name}: got {t!r}, expected a number > 0 or None")
        for name, least in [
            ("alignment_pairs", 1),
            ("alignment_starts", 1),
            ("verification_levels", 1),
            ("pose_rotations", 1),
            ("pose_starts", 0),
        ]:
            k = getattr(self, name)
            if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < least:
                raise ValueError(f"{name}: got {k!r}, expected an integer >= {least}")


@dataclasses.dataclass(frozen=True)
class Match:
    """One query description matched to one stored description.

    Attributes
    ----------
    score : float in [0, 1].
    pairs : (k, 2) int array of (query part, model part) indices.
    pose : (4, 4) array taking model-frame points to the query's frame.
    articulation : (n, 4, 4) array or None: per part of the stored view's main
        description, the model-frame motion (applied before ``pose``) that articulated it
        about its joints (:func:`articulate`), when that verified better than the rigid
        pose; None: rigid.
    """

    score: float
    pairs: np.ndarray
    pose: np.ndarray
    articulation: np.ndarray | None = None


_SIZE = slice(0, 3)
_SQ = slice(3, 5)
_DEF = slice(5, 7)
_REL = [RELATIONS.index(k) for k in ("gap", "distance", "offset_1", "offset_2", "offset_3")]
_ANGLE = RELATIONS.index("axis_angle")
_VOLUME = ATTRIBUTES.index("volume")


def _unary_features(d: Description) -> np.ndarray:
    a = d.attributes
    return np.column_stack([np.log(a[:, _SIZE] * d.scale), np.sort(a[:, _SQ], axis=1), a[:, _DEF]])


def unary_similarity(query: Description, model: Description, settings: MatchSettings = MatchSettings()) -> np.ndarray:
    """(n_query, n_model) similarity exp(-d²/2) of each pair of parts' attributes, d the
    RMS of the differences over their tolerances."""
    s = settings
    sigma = np.array([s.size_tolerance] * 3 + [s.squareness_tolerance] * 2 + [s.deformation_tolerance] * 2)
    diff = (_unary_features(query)[:, None, :] - _unary_features(model)[None, :, :]) / sigma
    return np.exp(-0.5 * np.mean(diff**2, -1))


def _relation_features(d: Description) -> tuple[np.ndarray, np.ndarray]:
    return d.relations[..., _REL] * d.scale, d.relations[..., _ANGLE]


def _pairwise_similarity(qr, mr, pairs, settings: MatchSettings, model_scale: float) -> np.ndarray:
    """(k, k) similarity of the relations of matched pairs a=(i, j), b=(k, l): query
    relation (i, k) against model relation (j, l)."""
    if len(pairs) < 2:
        return np.ones((len(pairs), len(pairs)))
    qi, mj = pairs[:, 0], pairs[:, 1]
    qd, qa = qr[0][np.ix_(qi, qi)], qr[1][np.ix_(qi, qi)]
    md, ma = mr[0][np.ix_(mj, mj)], mr[1][np.ix_(mj, mj)]
    dd = (qd - md) / (settings.distance_tolerance * model_scale)
    da = (qa - ma) / settings.angle_tolerance
    d2 = (np.sum(dd**2, -1) + da**2) / (dd.shape[-1] + 1)
    return np.exp(-0.5 * d2)


def _consistency(qr, mr, query_n, model_n, pairs, settings, model_scale) -> np.ndarray:
    """(n_query, n_model) mean relation similarity of each candidate pair to the pairs of
    the current assignment (1 where the assignment has no other pair)."""
    out = np.ones((query_n, model_n))
    if len(pairs) == 0:
        return out
    qi, mj = pairs[:, 0], pairs[:, 1]
    qd, qa = qr[0][:, qi], qr[1][:, qi]  # (nq, k, 5), (nq, k)
    md, ma = mr[0][:, mj], mr[1][:, mj]  # (nm, k, 5)
    dd = (qd[:, None] - md[None]) / (settings.distance_tolerance * model_scale)
    da = (qa[:, None] - ma[None]) / settings.angle_tolerance
    sim = np.exp(-0.5 * (np.sum(dd**2, -1) + da**2) / (dd.shape[-1] + 1))  # (nq, nm, k)
    # A candidate pair is not compared with an assigned pair sharing its query or model part.
    other = (np.arange(query_n)[:, None, None] != qi[None, None, :]) & (
        np.arange(model_n)[None, :, None] != mj[None, None, :]
    )
    count = other.sum(-1)
    return np.where(count > 0, (sim * other).sum(-1) / np.maximum(count, 1), 1.0)


def _score(unary, weight, pairwise, pairs) -> float:
    if len(pairs) == 0:
        return 0.0
    u = unary[pairs[:, 0], pairs[:, 1]] * weight[pairs[:, 0], pairs[:, 1]]
    if len(pairs) == 1:
        return float(u.sum())
    k = len(pairs)
    consistency = (pairwise.sum(1) - np.diag(pairwise)) / (k - 1)
    return float((u * consistency).sum())


def _assign(benefit, unary, min_similarity) -> np.ndarray:
    rows, cols = linear_sum_assignment(-benefit)
    keep = unary[rows, cols] >= min_similarity
    return np.stack([rows[keep], cols[keep]], -1).astype(np.int64).reshape(-1, 2)


def estimate_pose(query: Description, model: Description, pairs, weights=None) -> np.ndarray:
    """(4, 4) rigid transform taking the model's frame to the query's from matched parts:
    weighted Kabsch on their centres (three or more pairs spread in space), else the
    rotation taking the best pair's axes onto each other (a part's axes are defined up to
    sign; the sign nearest the centres' alignment is not resolved here)."""
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    pose = np.eye(4)
    if len(pairs) == 0:
        return pose
    w = np.ones(len(pairs)) if weights is None else np.asarray(weights, float)
    q, m = query.positions[pairs[:, 0]], model.positions[pairs[:, 1]]
    qc, mc = np.average(q, 0, w), np.average(m, 0, w)
    spread = np.linalg.svd(m - mc, compute_uv=False) if len(pairs) >= 3 else np.zeros(3)
    if len(pairs) >= 3 and spread[1] > 1e-3 * model.scale:
        rot = Rotation.align_vectors(q - qc, m - mc, weights=w)[0]
        r = rot.as_matrix()
    else:
        best = int(np.argmax(w))
        rq, rm = query.rotations[pairs[best, 0]], model.rotations[pairs[best, 1]]
        r = rq @ rm.T
        if np.linalg.det(r) < 0:
            r = rq @ np.diag([1, 1, -1]) @ rm.T
    pose[:3, :3] = r
    pose[:3, 3] = qc - r @ mc
    return pose


def match_descriptions(query: Description, model: Description, settings: MatchSettings = MatchSettings()) -> Match:
    """Match a query description to a model description (see the module docstring).

    Missing and extra parts are allowed on both sides; the score counts only the matched
    parts, weighted by their volume fractions, so it is 1 for identical descriptions and
    falls as parts go unmatched or differ.
    """
    if not isinstance(query, Description) or not isinstance(model, Description):
        raise TypeError(f"query, model: got {type(query).__name__}, {type(model).__name__}, expected two Descriptions")
    if not isinstance(settings, MatchSettings):
        raise TypeError(f"settings: got {type(settings).__name__}, expected a MatchSettings")
    unary = unary_similarity(query, model, settings)
    if settings.weighting == "volume":
        vq, vm = query.attributes[:, _VOLUME] * query.scale**3, model.attributes[:, _VOLUME] * model.scale**3
        weight = np.minimum(vq[:, None], vm[None, :]) / max(vq.sum(), vm.sum())
    else:
        weight = np.sqrt(query.attributes[:, _VOLUME][:, None] * model.attributes[:, _VOLUME][None, :])
    qr, mr = _relation_features(query), _relation_features(model)
    benefit = unary * weight
    pairs = _assign(benefit, unary, settings.min_similarity)
    best_pairs, best_score = (
        pairs,
        _score(unary, weight, _pairwise_similarity(qr, mr, pairs, settings, model.scale), pairs),
    )
    for _ in range(settings.iterations):
        consistency = _consistency(qr, mr, len(query), len(model), pairs, settings, model.scale)
        new = _assign(benefit * consistency, unary, settings.min_similarity)
        score = _score(unary, weight, _pairwise_similarity(qr, mr, new, settings, model.scale), new)
        if score > best_score + 1e-12:
            best_pairs, best_score = new, score
        if np.array_equal(new, pairs):
            break
        pairs = new
    # Drop matched pairs whose relations contradict the rest (they lower the score).
    while len(best_pairs) > 2:
        pw = _pairwise_similarity(qr, mr, best_pairs, settings, model.scale)
        scores = [
            _score(unary, weight, np.delete(np.delete(pw, k, 0), k, 1), np.delete(best_pairs, k, 0))
            for k in range(len(best_pairs))
        ]
        k = int(np.argmax(scores))
        if scores[k] <= best_score:
            break
        best_pairs, best_score = np.delete(best_pairs, k, 0), scores[k]
    w = weight[best_pairs[:, 0], best_pairs[:, 1]] if len(best_pairs) else None
    score = best_score * shape_similarity(query, model, settings.shape_tolerance)
    return Match(score, best_pairs, estimate_pose(query, model, best_pairs, w))


@dataclasses.dataclass(frozen=True)
class Alignment:
    """Two whole solids aligned (:func:`align_descriptions`).

    Attributes
    ----------
    score : float in [0, 1], the mean over both surfaces of exp(-d²/2σ²), d a surface
        point's distance to the other surface.
    pose : (4, 4) array taking model-frame points to the query's frame.
    """

    score: float
    pose: np.ndarray


_RELABEL = np.round(Rotation.create_group("O").as_matrix())
"""The 24 rotations of a box (the octahedral group): the signed permutation matrices with
determinant +1, rounded to exact 0 and ±1."""
_ICP_ITERATIONS = 15
_GATE = 8.0
"""Nearest neighbours farther than this many σ are no correspondence in :func:`_refine_pose`:
their weight would be exp(-8) ≈ 3e-4 of a coincident pair's, and a k-d tree stops
searching for a point at that distance (on the benchmark's views about 6% of a match's
CPU time is saved; most points are near a surface)."""
_SPARSE = 5
"""Moved points are every fifth of a surface's (itself an area-proportional draw, of 400
of the 2000); the distances are to all the other surface's points."""
_COARSE = 4
_SHORTLIST = 64
"""Proposed poses are ranked coarse to fine: all of them on every :data:`_COARSE`-th
moved point, then the :data:`_SHORTLIST` best of those again on all of them (a third of
the distances brute force takes; with every 8th point and 32 poses one benchmark view in
96 lost its best start)."""


def _similarity(tree: KDTree, points: np.ndarray, sigma: float) -> np.ndarray:
    """exp(-d²/2σ²) of each point's distance d to the tree's points (0 beyond 3σ)."""
    d, _ = tree.query(points, distance_upper_bound=3 * sigma)
    return np.exp(-0.5 * (d / sigma) ** 2)


def _mean_similarity(tree: KDTree, moved: np.ndarray, sigma: float) -> np.ndarray:
    """(s,) mean :func:`_similarity` of each set of moved points (s, n, 3)."""
    return _similarity(tree, moved.reshape(-1, 3), sigma).reshape(len(moved), -1).mean(1)


def _rank_poses(tree: KDTree, rot: np.ndarray, trans: np.ndarray, points: np.ndarray, sigma: float) -> np.ndarray:
    """(s,) ranking of proposed poses (rotations (s, 3, 3), translations (s, 3)) by the
    mean :func:`_similarity` of the moved ``points`` (n, 3) to the tree's surface, coarse
    to fine: every proposal on every :data:`_COARSE`-th point, then the
    :data:`_SHORTLIST` best again on all points. The shortlist's values are exact; the
    rest rank below them, in their coarse order."""

    def moved(k, p):
        return np.einsum("sab,nb->sna", rot[k], p) + trans[k][:, None]

    everyone = np.arange(len(rot))
    coarse = _mean_similarity(tree, moved(everyone, points[::_COARSE]), sigma)
    rank = coarse - 2.0
    shortlist = np.argsort(-coarse, kind="stable")[:_SHORTLIST]
    rank[shortlist] = _mean_similarity(tree, moved(shortlist, points), sigma)
    return rank


def _distinct(rank, rot, trans, count: int, reach: float) -> list[int]:
    """Up to ``count`` poses best ``rank`` first, each differing from every one kept by
    more than 0.3 in its rotation matrix (Frobenius) or more than ``reach`` in its
    translation."""
    kept: list[int] = []
    for k in np.argsort(-np.asarray(rank), kind="stable"):
        if len(kept) == count:
            break
        if all(np.linalg.norm(rot[k] - rot[o]) > 0.3 or np.linalg.norm(trans[k] - trans[o]) > reach for o in kept):
            kept.append(int(k))
    return kept


def _refine_pose(q, m, mtree, r, t, sigma, qtree=None):
    """Iterative closest points from (r, t), the pose taking the model's frame to the
    query's: each step a weighted Kabsch on the nearest neighbours of the query's points
    ``q`` among the model's surface (``mtree``) and, given the query's surface
    (``qtree``), of the model's points ``m`` among it; weights fall with distance
    (exp(-d²/8σ²)), so that surface one side has and the other lacks (an occluded or
    extra part) pulls little; pairs farther apart than :data:`_GATE` σ are left out.
    Without ``qtree`` the query's points are data (an observed range image's), which the
    model's surface is brought onto."""
    gate = _GATE * sigma
    for _ in range(_ICP_ITERATIONS):
        d2, i2 = mtree.query((q - t) @ r, distance_upper_bound=gate)
        near = np.isfinite(d2)
        src, dst, d = mtree.data[i2[near]], q[near], d2[near]
        if qtree is not None:
            d1, i1 = qtree.query(m @ r.T + t, distance_upper_bound=gate)
            near = np.isfinite(d1)
            src = np.concatenate([m[near], src])
            dst, d = np.concatenate([qtree.data[i1[near]], dst]), np.concatenate([d1[near], d])
        if len(d) < 3:  # nothing within reach: the pose stays as it is
            break
        w = np.exp(-0.125 * (d / sigma) ** 2) + 1e-12
        r, t = _kabsch(src, dst, w)
    return r, t


def _kabsch(src, dst, w, centre=None):
    """The rotation r and translation t (p -> r p + t) taking points ``src`` onto ``dst``
    in weighted least squares (weights ``w``): free, or a turn about a fixed ``centre``
    (a joint: then t = centre - r centre)."""
    if centre is None:
        sc, dc = np.average(src, 0, w), np.average(dst, 0, w)
    else:
        sc = dc = centre
    u, _, vt = np.linalg.svd(((src - sc) * w[:, None]).T @ (dst - dc))
    r = vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
    return r, dc - r @ sc


def align_candidates(
    query: Description, model: Description, settings: MatchSettings = MatchSettings()
) -> list[Alignment]:
    """Every refined start of :func:`align_descriptions`, best first (empty when either
    description lacks its ``surface`` or ``settings.alignment_tolerance`` is None).

    Poses are proposed by the ``settings.alignment_pairs`` pairs of parts with the
    largest unary similarity times the geometric mean of their volume fractions: the
    model part's sorted axes put on the query part's in each of the 24 proper
    relabellings, its centre on the query part's centre and, separately, the model's
    volume-weighted centre on the query's. All proposals are scored by the mean
    similarity of the model's surface points to the query's surface (coarse to fine,
    :func:`_rank_poses`); the
    ``settings.alignment_starts`` best distinct ones are refined by :func:`_refine_pose`
    and scored on both surfaces. Several are kept because the surfaces alone can prefer a
    pose that the range image rules out (:func:`verify_poses`)."""
    if query.surface is None or model.surface is None or settings.alignment_tolerance is None:
        return []
    qtree, mtree = KDTree(query.surface), KDTree(model.surface)
    q, m = query.surface[::_SPARSE], model.surface[::_SPARSE]
    sigma = settings.alignment_tolerance * max(query.scale, model.scale)
    unary = unary_similarity(query, model, settings)
    benefit = unary * np.sqrt(query.volumes[:, None] * model.volumes[None, :])
    pairs = np.argsort(-benefit, axis=None, kind="stable")[: settings.alignment_pairs]
    qi, mj = np.unravel_index(pairs, benefit.shape)

    rq, rm = query.rotations[qi].copy(), model.rotations[mj].copy()
    for r in (rq, rm):  # sorted axes as rotations: a left-handed triple's last axis flipped
        r[np.linalg.det(r) < 0, :, 2] *= -1
    rot = np.einsum("pab,sbc,pdc->psad", rq, _RELABEL, rm).reshape(-1, 3, 3)
    cq = np.average(query.positions, 0, query.volumes)
    cm = np.average(model.positions, 0, model.volumes)
    anchors_q = np.concatenate([np.repeat(query.positions[qi], len(_RELABEL), 0), np.repeat(cq[None], len(rot), 0)])
    anchors_m = np.concatenate([np.repeat(model.positions[mj], len(_RELABEL), 0), np.repeat(cm[None], len(rot), 0)])
    rot = np.concatenate([rot, rot])
    trans = anchors_q - np.einsum("sab,sb->sa", rot, anchors_m)
    starts = _distinct(_rank_poses(qtree, rot, trans, m, sigma), rot, trans, settings.alignment_starts, sigma)
    out = []
    for s in starts:
        r, t = _refine_pose(q, m, mtree, rot[s], trans[s], sigma, qtree)
        score = 0.5 * (_similarity(qtree, m @ r.T + t, sigma).mean() + _similarity(mtree, (q - t) @ r, sigma).mean())
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = r, t
        out.append(Alignment(float(score), pose))
    return sorted(out, key=lambda a: -a.score)


def align_descriptions(query: Description, model: Description, settings: MatchSettings = MatchSettings()) -> Alignment:
    """Align the model's whole solid to the query's (see the module docstring): the best
    of :func:`align_candidates`. Needs both descriptions' ``surface`` (score 1 and the
    identity when either lacks it)."""
    if query.surface is None or model.surface is None or settings.alignment_tolerance is None:
        return Alignment(1.0, np.eye(4))
    return next(iter(align_candidates(query, model, settings)), Alignment(-1.0, np.eye(4)))


@dataclasses.dataclass(frozen=True, eq=False)
class Observation:
    """The range image a query was recovered from, to verify poses on
    (:func:`verify_poses`).

    Attributes
    ----------
    depth : (H, W) z-depth, NaN where there is no return.
    camera : the camera that took it.
    figures : (F, H, W) bool, the pixels of each figure of the query (what its parts are
        to explain).
    """

    depth: np.ndarray
    camera: Camera
    figures: np.ndarray

    def __post_init__(self):
        depth, figures = np.asarray(self.depth, np.float32), np.asarray(self.figures, bool)
        if figures.ndim == 2:
            figures = figures[None]
        if depth.shape != (self.camera.height, self.camera.width) or figures.shape[1:] != depth.shape:
            raise ValueError(
                f"observation: got depth {depth.shape} and figures {figures.shape}, expected "
                f"({self.camera.height}, {self.camera.width}) and (F, {self.camera.height}, {self.camera.width})"
            )
        object.__setattr__(self, "depth", depth)
        object.__setattr__(self, "figures", figures)


_OBSERVED_POINTS = 800
"""Observed points a pose is fitted to (:func:`fit_pose`): a fixed draw of the figure's."""


def observed_points(observation: Observation, figure) -> np.ndarray:
    """(n, 3) camera-frame points of the ``figure`` mask's pixels, at most
    :data:`_OBSERVED_POINTS` of them (a fixed draw)."""
    points = np.asarray(observation.camera.points(observation.depth))[np.asarray(figure, bool)]
    points = points[np.isfinite(points).all(-1)]
    if len(points) > _OBSERVED_POINTS:
        points = points[np.sort(np.random.default_rng(0).choice(len(points), _OBSERVED_POINTS, replace=False))]
    return points


def rotation_lattice(count: int) -> np.ndarray:
    """(count, 3, 3) rotations spread evenly over all of them: the super-Fibonacci spiral
    of unit quaternions (Alexa, "Super-Fibonacci Spirals", CVPR 2022), deterministic."""
    s = np.arange(count) + 0.5
    r, big_r = np.sqrt(s / count), np.sqrt(1.0 - s / count)
    alpha, beta = 2.0 * np.pi * s / np.sqrt(2.0), 2.0 * np.pi * s / 1.533751168755204288118041
    quaternions = np.stack([r * np.sin(alpha), r * np.cos(alpha), big_r * np.sin(beta), big_r * np.cos(beta)], -1)
    return Rotation.from_quat(quaternions).as_matrix()


_PROPOSAL_STEPS = 5
"""Translation-only closest-point steps each proposed rotation of :func:`propose_poses`
takes before the rotations are ranked (on the chair turned 12 random ways, the best of
four fitted proposals verified 0.50 on average with none, 0.69 with 3, 0.81 with 5)."""


def propose_poses(
    points, model: Description, sigma: float, *, rotations: int, count: int, sight=None
) -> list[np.ndarray]:
    """The ``count`` best distinct 4x4 poses (model frame to camera) of ``rotations``
    proposed from the observed ``points`` alone, for :func:`fit_pose` to refine.

    Each rotation of :func:`rotation_lattice` is placed with the centroid of the model's
    near half (its surface points nearer than their median along the line of ``sight``,
    default: from the origin to the points' centroid, a pinhole camera's) on the points'
    centroid, then moved by :data:`_PROPOSAL_STEPS` translation-only closest-point steps
    (weighted and gated as :func:`_refine_pose`), all rotations at once; they are ranked
    by the mean similarity of the points to the model's surface so placed
    (:func:`_rank_poses`). The alignment of two recoveries proposes poses from the parts
    the query happens to have been cut into; these need nothing of the query's recovery,
    so a view whose recovered parts resemble none of the stored ones is still posed.
    Empty when the model has no surface or there are fewer than 3 points."""
    points = np.asarray(points, float)
    if model.surface is None or len(points) < 3 or count < 1 or rotations < 1:
        return []
    rot = rotation_lattice(rotations)
    centroid = points.mean(0)
    sight = centroid if sight is None else np.asarray(sight, float)
    sight = sight / max(float(np.linalg.norm(sight)), 1e-12)
    turned = np.einsum("sab,nb->sna", rot, model.surface[::_SPARSE])
    along = turned @ sight
    near = along <= np.median(along, 1, keepdims=True)
    trans = centroid[None] - (turned * near[..., None]).sum(1) / near.sum(1)[:, None]
    tree, few = KDTree(model.surface), points[::_COARSE]
    inverse = np.transpose(rot, (0, 2, 1))  # the points into each pose's model frame: rᵀ(x - t)
    for _ in range(_PROPOSAL_STEPS):
        local = np.einsum("sab,snb->sna", inverse, few[None] - trans[:, None])
        d, i = tree.query(local.reshape(-1, 3), distance_upper_bound=_GATE * sigma)
        d, i = d.reshape(len(rot), -1), i.reshape(len(rot), -1)
        found = np.isfinite(d)
        w = np.where(found, np.exp(-0.125 * (np.where(found, d, 0.0) / sigma) ** 2), 0.0)
        nearest = np.einsum("sab,snb->sna", rot, tree.data[np.where(found, i, 0)]) + trans[:, None]
        trans = trans + ((few[None] - nearest) * w[..., None]).sum(1) / np.maximum(w.sum(1), 1e-12)[:, None]
    rank = _rank_poses(tree, inverse, -np.einsum("sab,sb->sa", inverse, trans), points, sigma)
    out = []
    for k in _distinct(rank, rot, trans, count, np.inf):
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rot[k], trans[k]
        out.append(pose)
    return out


def fit_pose(points, model: Description, pose, sigma: float) -> np.ndarray:
    """``pose`` (4x4, the model's frame to the camera's) refined by iterative closest
    points bringing the model's outer surface onto observed ``points`` (:func:`_refine_pose`
    without a query surface: the data, not the query's recovered parts, which are cut
    differently from view to view). The pose as given when the model has no surface,
    there are fewer than 3 points or none of them is within reach of the model's surface
    (:data:`_GATE`)."""
    pose = np.asarray(pose, float)
    if model.surface is None or len(points) < 3:
        return pose
    r, t = _refine_pose(np.asarray(points, float), None, KDTree(model.surface), pose[:3, :3], pose[:3, 3], sigma)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = r, t
    return out


_ARTICULATION_STEPS = 15
"""Most steps of :func:`articulate`."""

_ARTICULATION_SETTLED = 0.01
""":func:`articulate` stops when a step moves no surface sample farther than this many σ."""

_JOINT_SAMPLES = 10
"""Latitudes of each part's surface samples (:func:`~sqparts._describe.surface_samples`)
that joints are placed on and articulation is fitted with."""


@dataclasses.dataclass(frozen=True, eq=False)
class KinematicTree:
    """A stored solid's parts as a tree of joints, in the model's frame
    (:func:`kinematic_tree`).

    Attributes
    ----------
    parent : (n,) int, each part's parent (-1: the root, and parts touching none of the
        tree, which move with the root).
    order : the tree's parts breadth first, the root first.
    joints : (n, 3) each part's joint with its parent (the root's: its centre).
    samples : (m, 3) points on the parts' surfaces; ``owner`` (m,) their parts.
    subtree : (n, n) bool, ``subtree[c, i]``: part i moves when c turns about its joint.
    """

    parent: np.ndarray
    order: tuple[int, ...]
    joints: np.ndarray
    samples: np.ndarray
    owner: np.ndarray
    subtree: np.ndarray


def kinematic_tree(parts, touching) -> KinematicTree:
    """The joints of batched ``parts`` (model frame) given which touch (``touching``,
    (n, n) bool: :attr:`~sqparts.Description.touching`): the largest part is the root, the
    parts touching a part already in the tree are its children (breadth first), and a
    child's joint is the midpoint of the closest pair of surface samples, one on the
    child and one on its parent."""
    size = np.asarray(parts.size, float).reshape(-1, 3)
    n = len(size)
    squareness = np.asarray(parts.squareness, float).reshape(n, 2)
    bend, taper = np.asarray(parts.bend, float).reshape(n, 2), np.asarray(parts.taper, float).reshape(n)
    rot = Rotation.from_rotvec(np.asarray(parts.orientation, float).reshape(n, 3)).as_matrix()
    pos = np.asarray(parts.position, float).reshape(n, 3)
    local = [
        surface_samples(size[i], squareness[i], bend[i], taper[i], rot[i], pos[i], count=_JOINT_SAMPLES)
        for i in range(n)
    ]
    owner = np.repeat(np.arange(n), [len(s) for s in local])
    samples = np.concatenate(local)
    touching = np.asarray(touching, bool)
    order, parent = [int(np.argmax(part_volume(size, squareness)))], np.full(n, -1)
    for p in order:  # grows while it is walked: breadth first
        for c in np.flatnonzero(touching[p]):
            if int(c) not in order:
                parent[c] = p
                order.append(int(c))
    joints = pos.copy()
    subtree = np.eye(n, dtype=bool)
    for c in reversed(order[1:]):
        a, b = samples[owner == c], samples[owner == parent[c]]
        d, j = map(np.asarray, KDTree(b).query(a))
        k = int(np.argmin(d))
        joints[c] = 0.5 * (a[k] + b[j[k]])
        subtree[parent[c]] |= subtree[c]
    return KinematicTree(parent, tuple(order), joints, samples, owner, subtree)


def articulate(tree: KinematicTree, points, pose, sigma: float) -> np.ndarray:
    """(n, 4, 4) per part, the motion taking the model's frame to the query's camera
    frame after the stored solid at ``pose`` is articulated onto observed ``points``
    (section 1: the same object in another configuration).

    Starting from the rigid ``pose``, each of :data:`_ARTICULATION_STEPS` steps pairs
    every observed point with its nearest surface sample (within :data:`_GATE` σ,
    weighted exp(-d²/8σ²) as :func:`fit_pose` does), moves the whole solid by the
    weighted Kabsch motion of all pairs, then, down the tree, turns each part with its
    subtree about its joint by the weighted Kabsch rotation of the subtree's pairs (at
    least 8 pairs each). A solid of one part, or whose parts touch none, stays at
    ``pose``."""
    pose = np.asarray(pose, float)
    n = len(tree.parent)
    rot, trans = np.repeat(pose[None, :3, :3], n, 0), np.repeat(pose[None, :3, 3], n, 0)
    points = np.asarray(points, float)
    gate = _GATE * sigma
    surface = np.einsum("mab,mb->ma", rot[tree.owner], tree.samples) + trans[tree.owner]
    for _ in range(_ARTICULATION_STEPS if len(tree.order) > 1 and len(points) >= 3 else 0):
        d, j = map(np.asarray, KDTree(surface).query(points, distance_upper_bound=gate))
        near = np.isfinite(d)
        d, j, dst = d[near], j[near], points[near]
        w = np.exp(-0.125 * (d / sigma) ** 2) + 1e-12
        for c in tree.order:
            root = tree.parent[c] < 0  # the first in order: the others have a parent
            moved = np.ones(n, bool) if root else tree.subtree[c]
            sel = moved[tree.owner[j]]
            if sel.sum() < 8:
                continue
            src = np.einsum("mab,mb->ma", rot[tree.owner[j[sel]]], tree.samples[j[sel]]) + trans[tree.owner[j[sel]]]
            # the whole solid free; a subtree about its joint
            r, t = _kabsch(src, dst[sel], w[sel], None if root else rot[c] @ tree.joints[c] + trans[c])
            rot[moved] = np.einsum("ab,mbc->mac", r, rot[moved])
            trans[moved] = trans[moved] @ r.T + t
        before, surface = surface, np.einsum("mab,mb->ma", rot[tree.owner], tree.samples) + trans[tree.owner]
        if np.abs(surface - before).max() < _ARTICULATION_SETTLED * sigma:
            break
    out = np.repeat(np.eye(4)[None], n, 0)
    out[:, :3, :3], out[:, :3, 3] = rot, trans
    return out


VERIFY_PIXELS = 1024
"""Poses are verified on a lattice of the image's pixels, every s-th pixel of every s-th
row, s = floor(sqrt(figure pixels / VERIFY_PIXELS)), so that at least about this many of
the figure's pixels are compared (every pixel of a smaller figure): both of
:func:`verify_poses`'s terms are means over pixels, which the lattice samples evenly, and
the rays rendered per pose no longer grow with the image (on a 640 x 480 frame whose
object covers 20 000 pixels, s = 4)."""


def verification_lattice(camera: Camera, figure) -> tuple[tuple[slice, slice], Camera]:
    """The pixels a ``figure`` mask is verified on (:data:`VERIFY_PIXELS`): their index
    into the image and the camera of exactly those pixels' rays
    (:meth:`~sqparts.PinholeCamera.cropped`)."""
    step = max(1, min(math.isqrt(int(np.count_nonzero(figure)) // VERIFY_PIXELS), camera.width, camera.height))
    if step == 1:
        return (slice(None), slice(None)), camera
    window = (slice(None, None, step), slice(None, None, step))
    return window, camera.cropped((0, 0, camera.height, camera.width), step)


def verify_poses(solids, observation: Observation, figure, tolerance, levels: int = 1) -> np.ndarray:
    """(k,) how well each of ``solids`` (batched :class:`~sqparts.Part`, camera frame: a
    stored model at a candidate pose) explains the observed range image, in [0, 1].

    Each solid is rendered into the observation's camera (one batched call for all of
    them) and compared with the observed depth D pixel by pixel: agreement
    exp(-(R - D)²/2τ²), τ = ``tolerance`` (one per solid, scene units). ``explained`` is
    the agreement summed over the ``figure`` mask's pixels over their count; ``precision``
    the agreement summed over the rendered pixels over their count, both leaving out
    those hidden behind a nearer observed surface (an occluder). The score is
    sqrt(explained x precision): a model that covers the figure but spills far past it,
    or one that fits a piece of it, both score low. Both sums are taken over the pixels
    of :func:`verification_lattice`, which bounds the rays rendered per solid. With
    ``levels`` > 1 the score is the mean of the scores at τ, τ/2, ..., τ/2^(levels-1)
    (one rendering; ``MatchSettings.verification_levels``)."""
    from ._encoding import part_vectors, render_nearest

    if isinstance(levels, bool) or not isinstance(levels, (int, np.integer)) or levels < 1:
        raise ValueError(f"levels: got {levels!r}, expected an integer >= 1")
    solids = list(solids)
    if not solids:
        return np.zeros(0)
    window, camera = verification_lattice(observation.camera, figure)
    vectors = [part_vectors(s) for s in solids]
    owner = np.repeat(np.arange(len(vectors)), [len(v) for v in vectors])
    rendered = render_nearest(np.concatenate(vectors), owner, len(vectors), camera)  # (k, H, W), inf: miss
    tau = np.broadcast_to(np.asarray(tolerance, float), (len(solids),))[:, None, None]
    depth, figure = observation.depth[window][None], np.asarray(figure, bool)[window][None]
    seen, model = np.isfinite(depth), np.isfinite(rendered)
    both = seen & model
    difference = rendered - np.where(seen, depth, 0.0)
    scores = []
    for level in range(levels):
        t = tau / 2.0**level
        agree = np.where(both, np.exp(-0.5 * (difference / t) ** 2), 0.0)
        hidden = both & (difference > 2.0 * t)  # an observed surface well in front
        explained = (agree * figure).sum((1, 2)) / max(int(figure.sum()), 1)
        visible = model & ~hidden
        precision = (agree * visible).sum((1, 2)) / np.maximum(visible.sum((1, 2)), 1)
        scores.append(np.sqrt(explained * precision))
    return np.mean(scores, axis=0)


def shape_similarity(query: Description, model: Description, tolerance: float | None = 0.5) -> float:
    """max(0, 1 - W / tolerance), W the 1-D earth mover's distance between the two shape
    distributions (the L1 distance of their cumulative sums times the bin width, in object
    scales); 1 when either description has none or ``tolerance`` is None."""
    if tolerance is None or query.shape_distribution is None or model.shape_distribution is None:
        return 1.0
    width = SHAPE_RANGE / SHAPE_BINS
    w = float(np.abs(np.cumsum(query.shape_distribution) - np.cumsum(model.shape_distribution)).sum() * width)
    return max(0.0, 1.0 - w / tolerance)


COHORT = 6
"""Databases of at least this many objects accept a query's best object by its lead over
the others (:func:`lead`); smaller ones by its score alone. Calibration's impostor leads
are then means over at least four objects: a database of three, calibrated on leads over
one object, set its threshold at a lead of 0.07 and accepted an unknown object whose best
scored 0.18 against the 0.10 of the only other (the built-in castings against the person
and the chair)."""


def lead(score: float, others) -> float:
    """``score`` (a query's against one stored object) minus the mean of ``others`` (its
    scores against every other stored object): how far that object stands out from the
    rest of the database (cohort normalisation, as in speaker and face verification). A
    query that resembles everything a little, or whose recovery matches every object
    poorly, is judged against its own level rather than an absolute one. ``score``
    itself when there are no others."""
    top, rest = float(_scores("score", score)), _scores("others", others).ravel()
    return top - (float(rest.mean()) if len(rest) else 0.0)


def _scores(name: str, values) -> np.ndarray:
    """``values`` as float64 scores, or one line naming ``name`` (not numbers, or NaN/inf)."""
    try:
        out = np.asarray(values, float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: got {values!r:.60}, expected finite scores (numbers)") from None
    if not np.isfinite(out).all():
        raise ValueError(f"{name}: got {values!r:.60}, expected finite scores")
    return out


FALSE_ACCEPT = 0.05
"""The rate at which a view of an object the database does not know may be taken for one
it does: :func:`calibrate_threshold` bounds the chance that a new impostor like the stored
views' passes by it (by 1 / (n + 1) where n, the stored views, is below 19)."""


def calibrate_threshold(genuine, impostor, *, default: float = 0.45, false_accept: float = FALSE_ACCEPT) -> float:
    """Threshold for rejecting unknown objects, from ``impostor`` values (a stored view's
    best against the other objects: what an unknown object scores) and ``genuine``
    values (a view against its own object, the view itself left out); the values are
    scores, or their :func:`lead` over the other objects, as the database decides.

    The threshold is the split-conformal quantile of the n impostor values (the
    Neyman-Pearson choice: the unknown-object error is the one fixed): it lets
    k = floor((n + 1) x ``false_accept``) - 1 of them through (at least none), so that a
    new impostor exchangeable with them passes with probability at most (k + 1) / (n + 1):
    ``false_accept`` from 1 / ``false_accept`` - 1 values on (19 at 5%), 1 / (n + 1) below
    that, where rejecting all of them is the most the values allow. (The plain empirical
    quantile, k = floor(n x ``false_accept``) through, bounds it by 5.4% with 36 values
    at 5%.) Below 2 / ``false_accept`` - 1 values (39 at 5%) none passes. The threshold
    sits midway between the highest impostor value it must reject and the next higher
    value of either kind (0.05 above it when there is none). The genuine values do not
    move it: a view left out is farther from its object's other views than a new view
    usually is from its nearest stored one, so they understate how well known objects
    score. With no impostor values it is 0.8 x the lowest genuine value (at most
    ``default``); with none at all, ``default``.
    """
    g, i = _scores("genuine", genuine).ravel(), np.sort(_scores("impostor", impostor).ravel())[::-1]
    if len(i) == 0:
        return float(default) if len(g) == 0 else float(min(default, 0.8 * g.min()))
    k = max(int(np.floor(false_accept * (len(i) + 1) + 1e-9)) - 1, 0)  # impostors allowed through
    if k >= len(i):
        return float(i[-1] - 1e-3)
    rejected = i[k]
    above = np.concatenate([g, i])
    above = above[above > rejected]
    return float(0.5 * (rejected + above.min()) if len(above) else rejected + 0.05)
