"""The model database and the learn / recognize pipelines (the edge: files).

A database is a folder of JSON files, human-readable and diffable::

    DB/database.json   {"format": "sqparts-database/2", "threshold": t, "statistic": "lead" or "score",
                        "calibration": {...}}
    DB/NAME.json       {"format": "sqparts-model/1", "name": NAME, "views": [VIEW, ...]}

Each VIEW is one learnt range image: ``source`` (where it came from), ``main`` (the
recovered parts as scene JSON, moved so that their volume-weighted centre is the origin:
the model's frame) with its ``description`` (:meth:`sqparts.Description.to_json`), and
``variants``: the other descriptions recovery could also have given, each
``{"kind", "parts", "description"}``: ``level`` (the multiscale levels, coarse to fine,
section 4.1), ``initial`` (the selection before refinement), ``merged`` (two touching
parts as one) and ``split`` (a long part as two). Recognition matches a query against
every stored description of an object and keeps the best. ``statistic`` names what the
threshold bounds: the best object's score, or its lead over the other objects
(:func:`~sqparts.lead`; databases of :data:`~sqparts._recognize.COHORT` or more objects).
A version-1 index (no ``statistic``; its threshold bounds the score) is still read.

Every file is written atomically (``sqparts._io.atomic_write``) and read through the
same checks as scene files, so a failed write leaves the database as it was.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import re
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

if TYPE_CHECKING:
    from ._recover import Recovery, SceneRecovery

from ._camera import camera_rays, json_numbers
from ._compile import concurrently
from ._describe import Description, describe, merged_alternatives, part_volume, surface_cloud
from ._io import _load_json, atomic_write, scene_from_dict, scene_to_dict
from ._part import Part, stack_parts
from ._recognize import (
    COHORT,
    KinematicTree,
    MatchSettings,
    Observation,
    align_candidates,
    articulate,
    calibrate_threshold,
    fit_pose,
    kinematic_tree,
    lead,
    match_descriptions,
    observed_points,
    propose_poses,
    verify_poses,
)
from ._typing import freeze_fields

DATABASE_FORMAT = "sqparts-database/2"
_READ_FORMATS = ("sqparts-database/1", DATABASE_FORMAT)
STATISTICS = ("score", "lead")
MODEL_FORMAT = "sqparts-model/1"
INDEX = "database.json"
DEFAULT_THRESHOLD = 0.45
"""Score below which nothing is recognised, until the database has calibrated its own."""

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")


def check_name(name) -> str:
    if not isinstance(name, str) or not _NAME.match(name) or name == Path(INDEX).stem:
        raise ValueError(
            f"name: got {name!r}, expected 1-100 letters, digits, '.', '_' or '-', starting with a letter "
            f"or digit (not 'database')"
        )
    return name


def _round(x):
    """Numbers to 6 significant digits, so files stay small and diffs readable."""
    if isinstance(x, float):
        return float(f"{x:.6g}")
    if isinstance(x, dict):
        return {k: _round(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_round(v) for v in x]
    return x


_NUMBER_LIST = re.compile(r"\[\s+([-+0-9.eE,\s]+?)\s+\]")
_FLAT_OBJECT = re.compile(r"\{\s+((?:\"[a-z_0-9]+\": [^{}\[\]\n]+,?\s+)+)\}")


def _write_json(path: Path, data) -> None:
    """Indented JSON with lists of numbers and flat objects (edges) on one line each."""
    text = json.dumps(_round(data), indent=1)
    text = _NUMBER_LIST.sub(lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]", text)
    text = _FLAT_OBJECT.sub(
        lambda m: "{" + ", ".join(x.strip().rstrip(",") for x in m.group(1).strip().split("\n")) + "}", text
    )
    with atomic_write(path, "w") as f:
        f.write(text + "\n")


def _digest(data) -> str:
    """A fingerprint of JSON data as :func:`_write_json` writes it (numbers rounded), equal
    for the data and for what reading the file back gives."""
    return hashlib.sha256(json.dumps(_round(data), sort_keys=True).encode()).hexdigest()[:16]


@dataclasses.dataclass(frozen=True)
class StoredDescription:
    """One description of one view of a stored object, with the parts it describes."""

    kind: str
    parts: Part
    description: Description

    @functools.cached_property
    def tree(self) -> KinematicTree:
        """The parts' joints (:func:`~sqparts._recognize.kinematic_tree`), made once."""
        return kinematic_tree(self.parts, self.description.touching)


@dataclasses.dataclass(frozen=True)
class StoredView:
    source: str
    main: StoredDescription
    variants: tuple

    @property
    def descriptions(self) -> tuple:
        """The main description first, then the variants."""
        return (self.main, *self.variants)


def transform_parts(parts: Part, pose) -> Part:
    """Batched ``parts`` moved by a 4x4 rigid transform (p -> R p + t), or each part by
    its own ((n, 4, 4): an articulation), on the host."""
    pose = np.asarray(pose, float)
    r, t = pose[..., :3, :3], pose[..., :3, 3]
    moved = Rotation.from_matrix(r) * Rotation.from_rotvec(np.asarray(parts.orientation, float).reshape(-1, 3))
    return Part(
        size=parts.size,
        squareness=parts.squareness,
        position=(np.einsum("...ab,...b->...a", r, np.asarray(parts.position, float)) + t).astype(np.float32),
        orientation=moved.as_rotvec().astype(np.float32),
        bend=parts.bend,
        taper=parts.taper,
    )


def _stored(kind: str, parts: Part) -> StoredDescription:
    parts = parts if parts.batch_shape else stack_parts([parts])
    return StoredDescription(kind, parts, describe(parts))


def _stored_to_json(s: StoredDescription) -> dict:
    return {"kind": s.kind, "parts": scene_to_dict(s.parts)["parts"], "description": s.description.to_json()}


def _stored_from_json(data, where: str) -> StoredDescription:
    if not isinstance(data, dict) or "parts" not in data:
        raise ValueError(
            f"{where}: got {type(data).__name__}, expected an object with 'kind', 'parts' and 'description'"
        )
    try:
        parts, _, _ = scene_from_dict({"parts": data["parts"]})
    except ValueError as e:
        raise ValueError(f"{where}.{e}") from None
    desc = Description.from_json(data.get("description"), where=f"{where}.description")
    if len(desc) != (len(parts) if parts.batch_shape else 1):
        raise ValueError(f"{where}.description: got {len(desc)} parts, expected {len(parts)} (as in {where}.parts)")
    desc = dataclasses.replace(desc, surface=surface_cloud(parts))  # not stored: made again from the parts
    return StoredDescription(str(data.get("kind", "main")), parts, desc)


def view_from_parts(
    parts: Part, *, source: str = "", initial: Part | None = None, levels=(), merged: int = 2, split: int = 2
) -> StoredView:
    """A :class:`StoredView` from one figure's recovered parts (camera frame): the parts
    centred (the model's frame), their description and the variants (see the module
    docstring). ``levels`` are coarser recoveries' parts, ``initial`` the selection before
    refinement; ``merged`` and ``split`` bound how many of those variants are made."""
    parts = parts if parts.batch_shape else stack_parts([parts])
    pos = np.asarray(parts.position, float)
    vol = part_volume(np.asarray(parts.size, float), np.asarray(parts.squareness, float))
    centre = (pos * vol[:, None]).sum(0) / vol.sum()

    def move(p: Part) -> Part:
        p = p if p.batch_shape else stack_parts([p])
        return dataclasses.replace(p, position=(np.asarray(p.position, float) - centre).astype(np.float32))

    main = _stored("main", move(parts))
    variants = [_stored("level", move(p)) for p in levels if p is not None]
    if initial is not None and len(initial) != len(parts):
        variants.append(_stored("initial", move(initial)))
    variants += [_stored("merged", p) for p in merged_alternatives(main.parts, main.description, limit=merged)]
    variants += [_stored("split", p) for p in split_alternatives(main.parts, limit=split)]
    return StoredView(source, main, tuple(variants))


def split_alternatives(parts: Part, *, limit: int = 2, min_elongation: float = 2.0) -> list[Part]:
    """Up to ``limit`` alternatives, each with one elongated part (longest semi-axis at
    least ``min_elongation`` times the next) split in two halves along that axis."""
    sizes = np.asarray(parts.size, float)
    out = []
    order = np.argsort(-sizes.max(1))
    for i in order:
        s = np.sort(sizes[i])
        if len(out) >= limit or s[2] < min_elongation * s[1]:
            continue
        axis = int(np.argmax(sizes[i]))
        rot = np.asarray(parts[int(i)].rotation(), float)
        half = sizes[i].copy()
        half[axis] /= 2
        p = parts[int(i)]
        pieces = []
        for sign in (-1.0, 1.0):
            pos = np.asarray(p.position, float) + sign * rot[:, axis] * half[axis]
            pieces.append(
                Part(
                    size=half.astype(np.float32),
                    squareness=p.squareness,
                    position=pos.astype(np.float32),
                    orientation=p.orientation,
                )
            )
        out.append(stack_parts([parts[k] for k in range(len(parts)) if k != i] + pieces))
    return out


@dataclasses.dataclass(frozen=True)
class RecognitionMatch:
    """One stored object's best match to a query.

    ``parts``: (query part, model part) pairs, query indices into the whole recovery's
    parts (all figures, as in parts.json), model indices into ``model_parts``;
    ``pose``: 4x4, model frame to the query's camera frame; ``figure``: the query
    figure matched (-1: all figures together); ``articulation``: (n, 4, 4) per model
    part, its model-frame motion before ``pose`` when the stored parts verified better
    articulated about their joints (:func:`~sqparts._recognize.articulate`), else None.
    """

    name: str
    score: float
    parts: np.ndarray
    pose: np.ndarray
    figure: int
    view: int
    kind: str
    model_parts: Part
    articulation: np.ndarray | None = None

    def __post_init__(self):
        freeze_fields(self)

    def posed_parts(self) -> Part:
        """The matched stored parts moved into the query's camera frame by ``pose``
        (each by its own motion when articulated)."""
        if self.articulation is None:
            return transform_parts(self.model_parts, self.pose)
        return transform_parts(self.model_parts, np.einsum("ab,nbc->nac", self.pose, self.articulation))

    def to_json(self) -> dict:
        out = {
            "name": self.name,
            "score": float(self.score),
            "parts": self.parts.tolist(),
            "pose": self.pose.tolist(),
            "figure": self.figure,
            "view": self.view,
            "kind": self.kind,
        }
        if self.articulation is not None:
            out["articulation"] = self.articulation.tolist()
        return out


class ModelDatabase:
    """A folder of stored objects (see the module docstring).

    ``ModelDatabase(path)`` opens a folder, which need not exist yet (it is made on the
    first :meth:`add_view`). ``objects`` maps each name to its tuple of
    :class:`StoredView`; ``threshold`` is the calibrated value of ``statistic`` below
    which a query is not recognised (:meth:`evidence`).
    """

    def __init__(self, path):
        self.path = Path(path)
        if self.path.exists() and not self.path.is_dir():
            raise NotADirectoryError(f"--db: got {str(self.path)!r}, which is a file, expected a database folder")
        self.objects: dict[str, tuple] = {}
        self.threshold = DEFAULT_THRESHOLD
        self.statistic = "score"
        self.calibration: dict = {}
        self._digests: dict[str, str] = {}
        """Per object, a fingerprint of its file as last read or written."""
        if self.path.is_dir():
            self._read()

    def _read(self) -> None:
        index = self.path / INDEX
        if index.is_file():
            data = _load_json(index, "database")
            if not isinstance(data, dict) or data.get("format") not in _READ_FORMATS:
                raise ValueError(
                    f"database: got {str(index)!r} without format {DATABASE_FORMAT!r}, expected a sqparts database"
                )
            t = data.get("threshold", DEFAULT_THRESHOLD)
            if isinstance(t, bool) or not isinstance(t, (int, float)) or not np.isfinite(t):
                raise ValueError(f"database.threshold: got {t!r}, expected a finite number")
            statistic = data.get("statistic", "score")
            if statistic not in STATISTICS:
                raise ValueError(f"database.statistic: got {statistic!r}, expected one of {', '.join(STATISTICS)}")
            self.threshold, self.statistic = float(t), statistic
            self.calibration = _checked_calibration(data.get("calibration", {}))
        for file in sorted(self.path.glob("*.json")):
            if file.name == INDEX or file.name.startswith("."):
                continue
            data = _load_json(file, "model")
            where = file.name
            if (
                not isinstance(data, dict)
                or data.get("format") != MODEL_FORMAT
                or not isinstance(data.get("views"), list)
            ):
                raise ValueError(
                    f"{where}: got {type(data).__name__}, expected an object with format {MODEL_FORMAT!r} and views"
                )
            if not data["views"]:  # nothing to match: every recognition would quietly miss it
                raise ValueError(f"{where}.views: got none, expected at least one view of the object")
            name = check_name(data.get("name"))
            if name != file.stem:
                raise ValueError(
                    f"{where}: got name {name!r}, expected {file.stem!r} (one file per object, named by it)"
                )
            views = []
            for k, v in enumerate(data["views"]):
                w = f"{where}.views[{k}]"
                if not isinstance(v, dict) or not isinstance(v.get("variants", []), list):
                    raise ValueError(f"{w}: got {type(v).__name__}, expected an object with 'main' and 'variants'")
                views.append(
                    StoredView(
                        str(v.get("source", "")),
                        _stored_from_json(v.get("main"), f"{w}.main"),
                        tuple(_stored_from_json(s, f"{w}.variants[{i}]") for i, s in enumerate(v.get("variants", []))),
                    )
                )
            self.objects[name] = tuple(views)
            self._digests[name] = _digest(data)

    @property
    def names(self) -> list[str]:
        return sorted(self.objects)

    def _object_data(self, name: str) -> dict:
        """Object ``name``'s file as written (its fingerprint recorded as it is made)."""
        data = {
            "format": MODEL_FORMAT,
            "name": name,
            "views": [
                {
                    "source": v.source,
                    "main": _stored_to_json(v.main),
                    "variants": [_stored_to_json(s) for s in v.variants],
                }
                for v in self.objects[name]
            ],
        }
        self._digests[name] = _digest(data)
        return data

    def _write_index(self) -> None:
        _write_json(
            self.path / INDEX,
            {
                "format": DATABASE_FORMAT,
                "threshold": self.threshold,
                "statistic": self.statistic,
                "calibration": self.calibration,
                "objects": self.names,
            },
        )

    def add_view(self, name: str, view: StoredView, *, calibrate: bool = True) -> None:
        """Add one view to object ``name`` (made if new), write its file and, with
        ``calibrate``, recalibrate the threshold and write ``database.json``."""
        self.add_views(name, [view], calibrate=calibrate)

    def add_views(self, name: str, views, *, replace: bool = False, calibrate: bool = True) -> None:
        """Add views to object ``name`` (made if new; with ``replace`` its old views are
        dropped), write its file once and, with ``calibrate``, recalibrate."""
        check_name(name)
        views = tuple(views)
        if not all(isinstance(v, StoredView) for v in views):
            raise TypeError("views: got something other than StoredView, expected views from view_from_parts")
        before = (dict(self.objects), dict(self._digests), self.threshold, self.statistic, self.calibration)
        self.objects[name] = (*(() if replace else self.objects.get(name, ())), *views)
        try:
            data = self._object_data(name)
            if calibrate:  # in memory first: the files are written only once it is done
                self.calibrate(write=False)
        except BaseException:  # e.g. interrupted while calibrating: the database as it was
            self.objects, self._digests, self.threshold, self.statistic, self.calibration = before
            raise
        self.path.mkdir(parents=True, exist_ok=True)
        _write_json(self.path / f"{name}.json", data)
        if calibrate:
            self._write_index()

    def without(self, *names) -> "ModelDatabase":
        """An in-memory copy without the named objects (nothing written), calibrated as
        a database that never had them: from the calibration's scores less those of
        the named objects' views and against them (exact, as a view's score against an
        object is its best over that object's views alone; nothing is matched). A
        database whose calibration kept no scores keeps its threshold and statistic."""
        unknown = [n for n in names if not isinstance(n, str) or n not in self.objects]
        if unknown:
            raise ValueError(f"names: got {unknown[0]!r}, expected names of stored objects ({', '.join(self.names)})")
        other = ModelDatabase.__new__(ModelDatabase)
        other.path, other.threshold, other.calibration = self.path, self.threshold, dict(self.calibration)
        other.statistic = self.statistic
        other.objects = {k: v for k, v in self.objects.items() if k not in names}
        other._digests = {k: v for k, v in self._digests.items() if k not in names}
        if names and "views" in self.calibration:
            kept = [  # of the objects it has (a calibration may name files removed since)
                {**v, "scores": {n: s for n, s in v["scores"].items() if n in other.objects}}
                for v in self.calibration["views"]
                if v["object"] in other.objects
            ]
            other.calibrate_from(kept)
            if "settings" in self.calibration:
                other.calibration["settings"] = self.calibration["settings"]
            if "objects" in self.calibration:
                other.calibration["objects"] = {n: d for n, d in self.calibration["objects"].items() if n not in names}
        return other

    def match(
        self,
        query: Description,
        *,
        settings: MatchSettings = MatchSettings(),
        exclude=None,
        observation: Observation | None = None,
        figure=None,
    ):
        """Per object, its best (score, view, kind, Match, stored) against ``query``, best first.
        ``exclude``: (name, view index) to leave out.

        A view's score is the geometric mean of its best description's part match and
        the alignment of the view's main solid with the query's
        (:func:`~sqparts._recognize.align_candidates`; the variants are the same solid
        cut otherwise, so it is aligned once), and the match's pose is the alignment's
        (when ``settings.alignment_tolerance`` is set). Given the query's
        ``observation`` (and its ``figure`` mask, default: all its figures), every
        refined alignment of every view, and the ``settings.pose_starts`` poses the
        observed points propose alone (:func:`~sqparts._recognize.propose_poses`), is
        fitted to the figure's observed points
        (:func:`~sqparts._recognize.fit_pose`) and verified by rendering
        (:func:`~sqparts._recognize.verify_poses`, all in one batched call): the view
        then scores the verification of its best pose (``settings.verification_levels``
        tolerances, the largest a ``settings.verification_tolerance`` fraction of the
        query's scale, one for every object), and that pose is the match's (when
        ``settings.verification_tolerance`` is set); the part match gives the
        correspondences. With ``settings.articulated``
        each fitted pose is also verified with the main description's parts articulated
        about their joints (:func:`~sqparts._recognize.articulate`; the tree is made once
        per stored view) and scores the better of the two renderings; when the
        articulated one wins, the match's correspondences are the main description's and
        its ``articulation`` the parts' motions."""

        def candidates(item):
            """The view's part match with each of its descriptions (the main first) and
            its main solid's alignments."""
            name, k, view = item
            matches = [(match_descriptions(query, s.description, settings), s) for s in view.descriptions]
            return name, k, matches, align_candidates(query, view.main.description, settings)

        # Every stored view on its own: run on a thread per core (the k-d tree queries and
        # SVDs most of the time goes to release the GIL); the results do not depend on it.
        items = [(n, k, v) for n, views in self.objects.items() for k, v in enumerate(views) if exclude != (n, k)]
        rows = concurrently(candidates, items)
        tolerance = settings.verification_tolerance
        posed: list | None = None  # per row, its alignments fitted to the observation
        if observation is not None and tolerance is not None:
            mask = observation.figures.any(0) if figure is None else figure
            points = observed_points(observation, mask)
            directions = camera_rays(observation.camera)[1][np.asarray(mask, bool)]
            sight = directions.mean(0) if len(directions) else None  # no figure: no points, no proposals

            def fitted(row):
                """The row's alignments fitted to the points, each with its articulation
                (None: rigid only)."""
                name, k, _matches, aligned = row
                model = self.objects[name][k].main
                scale = max(query.scale, model.description.scale)
                sigma = float(settings.alignment_tolerance or 0.0) * scale  # aligned only when it is set
                starts = [a.pose for a in aligned] + propose_poses(
                    points,
                    model.description,
                    sigma,
                    rotations=settings.pose_rotations,
                    count=settings.pose_starts,
                    sight=sight,
                )
                poses = [fit_pose(points, model.description, pose, sigma) for pose in starts]
                motions = [
                    articulate(model.tree, points, pose, sigma)
                    if settings.articulated and len(model.tree.order) > 1
                    else None
                    for pose in poses
                ]
                return list(zip(poses, motions))

            posed, solids = [], []
            for row, fits in zip(rows, concurrently(fitted, rows)):
                model = self.objects[row[0]][row[1]].main
                posed.append(fits)
                # Per pose the rigid solid and, articulated about its joints, the same parts
                # moved each by its own motion.
                for pose, motion in fits:
                    solids.append(transform_parts(model.parts, pose))
                    solids += [] if motion is None else [transform_parts(model.parts, motion)]
            tau = tolerance * query.scale  # one tolerance for every object this query meets
            checks = iter(verify_poses(solids, observation, mask, tau, settings.verification_levels))
        best: dict[str, tuple] = {}
        for r, (name, k, matches, aligned) in enumerate(rows):
            m, stored = max(matches, key=lambda row: row[0].score)
            if aligned and posed is not None:
                evidence, articulation = [], []
                for pose, motion in posed[r]:
                    rigid = next(checks)
                    moved = -1.0 if motion is None else next(checks)
                    evidence.append(float(max(rigid, moved)))
                    if motion is not None and moved > rigid:
                        articulation.append(np.einsum("ab,nbc->nac", np.linalg.inv(pose), motion))
                    else:
                        articulation.append(None)
                j = int(np.argmax(evidence))
                if articulation[j] is not None:  # the main's parts were articulated: its correspondences
                    m, stored = matches[0]
                m = dataclasses.replace(m, score=evidence[j], pose=posed[r][j][0], articulation=articulation[j])
            elif aligned:
                m = dataclasses.replace(
                    m, score=float(np.sqrt(m.score * max(aligned[0].score, 0.0))), pose=aligned[0].pose
                )
            if name not in best or m.score > best[name][0]:
                best[name] = (m.score, k, stored.kind, m, stored)
        return [(name, *best[name]) for name in sorted(best, key=lambda n: -best[n][0])]

    def evidence(self, scores) -> float:
        """What :attr:`threshold` bounds, for one query's ``scores`` (one per stored
        object, any order): the best score's :func:`~sqparts.lead` over the others when
        :attr:`statistic` is ``"lead"``, else the best score (0 when there are none)."""
        s = sorted((float(x) for x in scores), reverse=True)
        if not s:
            return 0.0
        return lead(s[0], s[1:]) if self.statistic == "lead" else s[0]

    def calibrate(self, *, settings: MatchSettings = MatchSettings(), write: bool = True) -> float:
        """Set :attr:`threshold` from the stored views alone, each view matched against
        the database with itself left out: genuine values (its score against its own
        object) and impostor values (the best of the other objects: what an object the
        database does not know scores); see :func:`sqparts.calibrate_threshold`. The
        values are the scores themselves or, in a database of at least
        :data:`~sqparts._recognize.COHORT` objects, their :func:`~sqparts.lead` over the
        remaining objects (:attr:`statistic`; measured on the recognition benchmark, the
        lead separates known from unknown objects better than the score). With
        ``settings.verification_tolerance``, each view is matched as seen again: its own
        parts rendered from its viewpoint (:func:`view_observation`) are the observation
        the others' poses are verified on, so that the threshold is on the scale of
        :func:`recognize`'s verified scores. :attr:`calibration` keeps every view's
        scores, the settings and a fingerprint of each object's file.

        A view's score against an object is its best over that object's views alone, so
        the last calibration's scores stand where neither the view's own object nor the
        object matched against has changed since, under the same settings: only those
        pairs are matched again, and adding one object to a database of n views matches
        each view against the new object and the new views against all (not n x n).
        Writes ``database.json`` (with ``write``, when the folder exists)."""
        key = _round(dataclasses.asdict(settings))
        digests = {n: self._digests[n] for n in self.objects}
        old = self.calibration if self.calibration.get("settings") == key else {}
        unchanged = {n for n, d in (old.get("objects") or {}).items() if digests.get(n) == d}
        kept = {(v["object"], v["view"]): v["scores"] for v in old.get("views", []) if v["object"] in unchanged}
        changed = self.without(*unchanged)
        views_scores = []
        for name, views in self.objects.items():
            for k, view in enumerate(views):
                against = changed if (name, k) in kept else self
                scores = {n: s for n, s in kept.get((name, k), {}).items() if n in unchanged}
                if against.objects:
                    query, observation = view.main.description, None
                    if settings.verification_tolerance is not None:
                        query, observation = view_observation(view)
                    found = against.match(query, settings=settings, exclude=(name, k), observation=observation)
                    scores.update((n, s) for n, s, *_ in found)
                views_scores.append({"object": name, "view": k, "scores": scores})
        self.calibrate_from(views_scores)
        self.calibration.update(settings=key, objects=digests)
        if write and self.path.is_dir():
            self._write_index()
        return self.threshold

    def calibrated_for(self, settings: MatchSettings = MatchSettings()) -> bool:
        """Whether the threshold was calibrated for these objects, as their files now are,
        and on the scale of the scores matching with ``settings`` gives. False when the
        last calibration was made with other settings (a database calibrated before a
        matcher's setting existed, or with other tolerances) or on other objects (a
        model file removed, added or edited by hand since: the calibration keeps a
        fingerprint of each file it was made on); then :meth:`calibrate`, which matches
        only what changed. True when the calibration records neither (a format 1
        database)."""
        used = self.calibration.get("settings")
        if used is None:
            return True
        objects = self.calibration.get("objects")
        return used == _round(dataclasses.asdict(settings)) and (objects is None or objects == self._digests)

    def calibrate_from(self, views_scores, *, statistic: str | None = None) -> float:
        """Set :attr:`statistic` (given, or by the number of objects: see
        :meth:`calibrate`), :attr:`threshold` and :attr:`calibration` from stored views'
        scores as :meth:`calibrate` keeps them (:func:`calibration_values`); nothing is
        matched or written."""
        if statistic is None:
            statistic = "lead" if len(self.objects) >= COHORT else "score"
        if statistic not in STATISTICS:
            raise ValueError(f"statistic: got {statistic!r}, expected one of {', '.join(STATISTICS)}")
        genuine, impostor = calibration_values(views_scores, statistic)
        self.statistic = statistic
        self.threshold = calibrate_threshold(genuine, impostor, default=DEFAULT_THRESHOLD)
        self.calibration = {"genuine": sorted(genuine), "impostor": sorted(impostor), "views": list(views_scores)}
        return self.threshold


def _checked_calibration(data) -> dict:
    """database.json's ``calibration`` as :meth:`ModelDatabase.calibrate` writes it:
    ``{"settings": ..., "objects": {name: digest}, "views": [{"object", "view",
    "scores": {name: score}}]}`` (every key optional); anything else is refused by name."""

    def fail(what, got):
        raise ValueError(f"database.calibration{what}: got {got!r:.60}, expected what sqparts calibrate writes")

    if not isinstance(data, dict):
        fail("", data)
    objects = data.get("objects", {})
    if not isinstance(objects, dict) or not all(isinstance(v, str) for v in objects.values()):
        fail(".objects", objects)
    views = data.get("views", [])
    if not isinstance(views, list):
        fail(".views", views)
    for k, v in enumerate(views):
        if (
            not isinstance(v, dict)
            or not isinstance(v.get("object"), str)
            or isinstance(v.get("view"), bool)
            or not isinstance(v.get("view"), int)
            or not isinstance(v.get("scores"), dict)
            or not all(json_numbers(x) and not isinstance(x, list) and np.isfinite(x) for x in v["scores"].values())
        ):
            fail(f".views[{k}]", v)
    return data


def calibration_values(views_scores, statistic: str) -> tuple[list[float], list[float]]:
    """Genuine and impostor values of ``statistic`` (``"score"`` or ``"lead"``) from the
    stored views' scores as :meth:`ModelDatabase.calibrate` keeps them (each
    ``{"object", "view", "scores": {name: score}}``, the view itself left out): genuine,
    its own object's score (when the object has other views) or that score's
    :func:`~sqparts.lead` over the other objects; impostor, the best of the other objects
    or its lead over the rest of them."""
    genuine, impostor = [], []
    for v in views_scores:
        name, scores = v["object"], v["scores"]
        others = sorted((s for n, s in scores.items() if n != name), reverse=True)
        if name in scores:
            genuine.append(lead(scores[name], others) if statistic == "lead" else scores[name])
        if others:
            impostor.append(lead(others[0], others[1:]) if statistic == "lead" else others[0])
    return genuine, impostor


def view_observation(view: StoredView, *, size: int = 64) -> tuple[Description, Observation]:
    """A stored view seen again: its main parts rendered by a ``size`` x ``size`` pinhole
    camera from the side it was learnt from (the stored parts keep the learning camera's
    axes; only its centre was moved to the origin), 6 object radii away, the object
    filling about half the image. Returns the main description moved into that camera's
    frame and the rendering as an :class:`~sqparts._recognize.Observation` (one figure:
    every rendered pixel). Used to calibrate verified scores on the stored views alone."""
    from ._camera import PinholeCamera
    from ._encoding import render_labels

    parts, desc = view.main.parts, view.main.description
    radius = float(np.max(np.linalg.norm(np.asarray(parts.position), axis=-1) + np.asarray(parts.size).max(-1)))
    shift = np.array([0.0, 0.0, 6.0 * radius])
    f = 0.25 * size * 6.0
    camera = PinholeCamera(width=size, height=size, fx=f, fy=f, cx=(size - 1) / 2, cy=(size - 1) / 2)
    pose = np.eye(4)
    pose[:3, 3] = shift
    depth, _ = render_labels(transform_parts(parts, pose), camera)
    moved = dataclasses.replace(
        desc,
        positions=desc.positions + shift,
        surface=None if desc.surface is None else desc.surface + shift,
    )
    return moved, Observation(depth, camera, np.isfinite(depth)[None])


def _figure_recoveries(recovery) -> list:
    return list(getattr(recovery, "figures", None) or [recovery])


def observation_of(recovery) -> Observation:
    """The image, camera and figure masks of a :class:`~sqparts.SceneRecovery` or
    :class:`~sqparts.Recovery`, to verify its matches on."""
    figures = _figure_recoveries(recovery)
    camera = getattr(recovery, "camera", None) or figures[0].data.camera
    return Observation(recovery.depth, camera, np.stack([np.asarray(f.figure, bool) for f in figures]))


def _coarse_levels(recovery, levels: int) -> list[Part]:
    """Parts of the largest figure recovered on its image binned by 2^(levels-1) ... 2
    (section 4.1's coarser levels), each with parts up to half the figure's extent / 2^k,
    with the figure's own search settings and without refinement."""
    from ._preprocess import downsample, downsample_mask
    from ._recover import recover
    from ._refine import RefineSettings

    fig = _figure_recoveries(recovery)[0]
    depth = np.where(fig.figure, fig.depth, np.nan).astype(np.float32)
    camera = getattr(recovery, "camera", None) or fig.data.camera
    pts = camera.points(depth)[fig.figure]
    max_size = float(np.max(np.ptp(pts, axis=0))) / 2.0
    out = []
    for k in range(levels - 1):
        f = 2 ** (levels - 1 - k)
        d, cam = downsample(depth, camera, f)
        mask = downsample_mask(fig.figure, f) & np.isfinite(d)
        if mask.sum() < 16:
            continue
        # The window, frame and lattices were the full image's (one program for all its
        # figures): the binned image's are its own.
        search = dataclasses.replace(fig.search, max_size=max_size / 2**k, window=None, frame=None, lattices=None)
        rec = recover(d, cam, search=search, refine=RefineSettings.none(), figure=mask)
        out.append(rec.parts)
    return out


def view_from_recovery(recovery, *, source: str = "", levels: int = 2) -> StoredView:
    """A :class:`StoredView` from a recovery of a view that shows one object: all its
    figures together are the object (depth jumps inside an object, a fin in front of a
    body, tear it into several figures). The variants: the largest figure's selection
    before refinement and its coarser multiscale levels (``levels`` - 1 of them,
    recovered here), each with the other figures' parts, then merges and splits."""
    figures = _figure_recoveries(recovery)
    others = [p for r in figures[1:] for p in r.parts]
    parts = stack_parts([p for r in figures for p in r.parts])
    coarse = _coarse_levels(recovery, levels) if levels > 1 else []
    return view_from_parts(
        parts,
        source=source,
        initial=stack_parts([*figures[0].initial_parts, *others]),
        levels=[stack_parts([*c, *others]) for c in coarse],
    )


def learn(name: str, views, *, database, levels: int = 2, progress=None, **recover_kwargs) -> ModelDatabase:
    """Recover each view and add it to object ``name`` in ``database``.

    Parameters
    ----------
    name : the object's name (letters, digits, '.', '_', '-').
    views : sequence of (depth, camera) pairs, or of :class:`~sqparts.SceneRecovery` /
        :class:`~sqparts.Recovery` already made; the largest figure of each is the object.
    database : a :class:`ModelDatabase` or a folder path.
    levels : multiscale levels stored per view (1: only the recovery itself).
    recover_kwargs : :func:`sqparts.recover_scene`'s settings (``scene``, ``search``,
        ``select``, ``refine``).

    Returns the database, written and recalibrated.
    """
    from ._recover import Recovery, SceneRecovery, recover_scene

    check_name(name)
    if not (isinstance(levels, (int, np.integer)) and 1 <= levels <= 4):
        raise ValueError(f"levels: got {levels!r}, expected an integer in [1, 4]")
    views = list(views)
    if not views:
        raise ValueError("views: got none, expected at least one (depth, camera) pair or recovery")
    for k, view in enumerate(views):  # each checked before any work
        if not (isinstance(view, tuple) and len(view) == 2 or isinstance(view, (Recovery, SceneRecovery))):
            raise TypeError(
                f"views[{k}]: got {type(view).__name__}, expected a (depth, camera) pair or a recovery "
                "(sqparts.recover_scene's or sqparts.recover's)"
            )
    db = database if isinstance(database, ModelDatabase) else ModelDatabase(database)
    for k, view in enumerate(views):
        if isinstance(view, tuple):
            depth, camera = view
            rec = recover_scene(depth, camera, progress=progress, **recover_kwargs)
            source = f"view {k}"
        else:
            rec, source = view, f"recovery {k}"
        if not _figure_recoveries(rec):
            raise ValueError(
                f"views[{k}]: got a range image in which nothing was recovered, expected a view of the object"
            )
        db.add_view(
            name,
            view_from_recovery(rec, source=source, levels=levels),
            calibrate=k == len(views) - 1,
        )
    return db


def match_figures(
    figures, *, database, settings: MatchSettings = MatchSettings(), observation: Observation | None = None
):
    """Match each figure's parts (a list of batched :class:`~sqparts.Part`, camera frame)
    against every stored object. Returns (best name or None, list of
    :class:`RecognitionMatch`, one per object, best first); query part indices count
    through all figures in order. Each figure is matched on its own, and, when there are
    several, all of them together (an object torn at its own depth jumps; an occluder
    is then an extra part). ``observation``: the range image the figures were recovered
    from, with one mask per figure (:func:`observation_of`), to verify each pose on
    (:meth:`ModelDatabase.match`)."""
    db = database if isinstance(database, ModelDatabase) else ModelDatabase(database)
    if observation is not None and len(observation.figures) != len(figures):
        raise ValueError(
            f"observation: got {len(observation.figures)} figure masks, expected one per figure ({len(figures)})"
        )
    kept = [
        (i, f if f.batch_shape else stack_parts([f]))
        for i, f in enumerate(figures)
        if f is not None and (not f.batch_shape or len(f))
    ]
    offsets = np.cumsum([0] + [len(f) for _, f in kept])
    queries: list[tuple[int, Part, int | None]] = [(k, parts, i) for k, (i, parts) in enumerate(kept)]
    if len(kept) > 1:  # also all figures together: an object torn at its own depth jumps
        queries.append((-1, stack_parts([p for _, f in kept for p in f]), None))
    best: dict[str, tuple] = {}
    for f, parts, index in queries:
        query = describe(parts)
        mask = None if observation is None or index is None else observation.figures[index]
        for name, score, view, kind, m, stored in db.match(
            query, settings=settings, observation=observation, figure=mask
        ):
            if name not in best or score > best[name][0]:
                pairs = m.pairs.copy()
                pairs[:, 0] += offsets[f] if f >= 0 else 0
                best[name] = (
                    score,
                    RecognitionMatch(name, score, pairs, m.pose, f, view, kind, stored.parts, m.articulation),
                )
    matches = [m for _, m in sorted(best.values(), key=lambda r: -r[0])]
    top = matches[0].name if matches and db.evidence([m.score for m in matches]) >= db.threshold else None
    return top, matches


@dataclasses.dataclass(frozen=True)
class Recognition:
    """What :func:`recognize` found: ``best`` (a name, or None when ``evidence``, the
    database's :meth:`~ModelDatabase.evidence` for the matches' scores, is below
    ``threshold``), ``statistic`` (what the evidence is: ``"score"`` or ``"lead"``),
    ``matches`` (one per stored object, best first), the ``recovery`` of the input and the
    seconds taken (``timings``). Immutable, as a recovery is."""

    best: str | None
    matches: Sequence
    threshold: float
    evidence: float
    statistic: str
    recovery: Recovery | SceneRecovery
    timings: Mapping

    def __post_init__(self):
        freeze_fields(self)

    def to_json(self) -> dict:
        return {
            "best": self.best,
            "threshold": self.threshold,
            "evidence": self.evidence,
            "statistic": self.statistic,
            "matches": [m.to_json() for m in self.matches],
            "timings_s": dict(self.timings),
        }

    def summary(self) -> str:
        top = ", ".join(f"{m.name} {m.score:.2f}" for m in self.matches[:3])
        return (
            f"best: {self.best or 'none (unknown object)'} ({self.statistic} {self.evidence:.2f}, "
            f"threshold {self.threshold:.2f}; {top})"
        )


def recognize(
    depth=None,
    camera=None,
    *,
    database,
    recovery=None,
    settings: MatchSettings = MatchSettings(),
    progress=None,
    **recover_kwargs,
) -> Recognition:
    """Recover a range image (or take ``recovery``) and match each of its figures against
    every stored object; per object the best figure, view and variant is kept.

    ``best`` is the top object if the database's evidence for it (its score or, in a
    database of :data:`~sqparts._recognize.COHORT` or more objects, its lead over the
    others: :meth:`ModelDatabase.evidence`) reaches the calibrated threshold, else None
    (an object the database does not know). A database calibrated with other matching
    ``settings``, or on model files changed since, is calibrated again first
    (:meth:`ModelDatabase.calibrated_for`; this writes ``database.json``). Each match's
    ``pose`` takes the model's frame to the camera frame.
    """
    from ._recover import recover_scene

    db = database if isinstance(database, ModelDatabase) else ModelDatabase(database)
    if not db.objects:
        raise ValueError(f"--db: got {str(db.path)!r} with no objects, expected a database made by sqparts learn")
    if not db.calibrated_for(settings):  # a threshold on the scale of these settings' scores
        db.calibrate(settings=settings)
    t0 = time.perf_counter()
    if recovery is None:
        if depth is None or camera is None:
            raise ValueError("depth, camera: got none, expected a range image and its camera (or recovery=)")
        recovery = recover_scene(depth, camera, progress=progress, **recover_kwargs)
    t1 = time.perf_counter()
    top, matches = match_figures(
        [r.parts for r in _figure_recoveries(recovery)],
        database=db,
        settings=settings,
        observation=observation_of(recovery),
    )
    t2 = time.perf_counter()
    return Recognition(
        top,
        matches,
        db.threshold,
        db.evidence([m.score for m in matches]),
        db.statistic,
        recovery,
        {"recovery": t1 - t0, "matching": t2 - t1, "total": t2 - t0},
    )
