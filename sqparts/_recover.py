"""The pipeline: range image -> regions -> local search -> selection -> refinement.

:func:`recover` strings the stages together (paper sections 3.3-3.5 and 4):

1. :func:`~sqparts.prepare` the data (figure mask, encoding: σ, λ and the bit costs);
2. :func:`~sqparts.fit_image`: the parallel search at every region on the figure's
   skeleton, keeping the best few candidates per region;
3. area matrices and :func:`~sqparts.select_parts` (exact by HiGHS, or best-first);
4. :func:`~sqparts.refine_parts`: all chosen parts rendered together and refined.

:func:`recover_scene` runs it on real data: binning, clean-up and figure/ground
(:mod:`sqparts._preprocess`), then :func:`recover` per figure, then optional prettifying
(:mod:`sqparts._postprocess`). :func:`recover_multiscale` runs it at several scales.
"""

from __future__ import annotations

import dataclasses
import time
import types
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import jax
import numpy as np

from ._camera import Camera, fits_float32
from ._compile import memo_scope
from ._data import PAD, RangeData, figure_footprint, prepare
from ._encoding import (
    Costs,
    Encoding,
    EncodingCost,
    encoding_cost,
    host_parts,
    layer_errors,
    least_pixels,
    part_statistics,
    part_vectors,
    render_layers,
)
from ._grid import lookup_preset
from ._part import Part, stack_parts
from ._refine import MAX_PASSES, MergeParts, OnGain, RefineSettings, run_moves
from ._render import render_range_image
from ._search import SearchSettings, fit_image, largest_frame, search_preset
from ._select import SelectionProblem, SelectSettings, select_rendered
from ._typing import freeze_fields

if TYPE_CHECKING:
    from ._preprocess import CleanedRange, FigureGround


class _Fractions:
    """Explained and commission pixels as fractions of the figure's pixels with a return
    (for any result with ``cost`` and ``figure``)."""

    if TYPE_CHECKING:
        cost: EncodingCost
        figure: np.ndarray

    @property
    def fraction_explained(self) -> float:
        return self.cost.explained / max(int(self.figure.sum()), 1)

    @property
    def commission_fraction(self) -> float:
        return self.cost.commission / max(int(self.figure.sum()), 1)


class _Meshes:
    """The parts as meshes for other tools (for any result with ``parts``); trimesh and
    Open3D are imported only here, at the edge (:mod:`sqparts._mesh`)."""

    if TYPE_CHECKING:
        parts: Part

    def to_trimesh(self, *, resolution: int = 32):
        """A ``trimesh.Scene``, one geometry ``part_<i>`` per part in ``report.png``'s
        colours; ``.export("model.glb")`` writes glTF for Blender and three.js."""
        from ._mesh import scene_trimesh

        return scene_trimesh(self.parts, resolution=resolution)

    def to_open3d(self, *, resolution: int = 32) -> list:
        """A list of coloured ``open3d.geometry.TriangleMesh``, one per part."""
        from ._mesh import scene_open3d

        return scene_open3d(self.parts, resolution=resolution)


@dataclasses.dataclass(frozen=True)
class Recovery(_Fractions, _Meshes):
    """What :func:`recover` found (immutable: later stages derive a new one with
    ``dataclasses.replace``).

    Attributes
    ----------
    parts : Part
        The recovered parts (batched), in the camera frame.
    part_stats : tuple of mappings
        Per part: visible ``pixels``, ``gamma`` (Eq. 4) and ``bits_saved`` (Eq. 5) in
        the joint rendering.
    cost : EncodingCost
        Final description length E (bits) and its pixel counts; ``cost.rendered`` is the
        model's range image, ``cost.labels`` its part labels.
    initial_parts, initial_cost :
        The selection before refinement (Figure 7c's "initial explanation").
    candidates : int
        Candidates found by the local search (regions × top_k).
    regions : int
        Regions searched.
    selection_method : str
    timings : mapping
        Seconds per stage: ``search``, ``selection``, ``refinement``, ``total``.
    search, select, refine :
        The settings objects it ran with (``search`` resolved on the data: its
        ``max_size`` and ``window``); :attr:`settings` is their JSON form with σ, λ and
        the bit costs.
    depth, figure :
        The input range image and figure mask (pixels with a return).
    history : tuple of (stage, E)
    data, costs :
        The prepared data and bit costs, for later stages (prettifying, residuals).
    """

    parts: Part
    part_stats: Sequence
    cost: EncodingCost
    initial_parts: Part
    initial_cost: EncodingCost
    candidates: int
    regions: int
    selection_method: str
    timings: Mapping
    search: SearchSettings
    select: SelectSettings
    refine: RefineSettings
    depth: np.ndarray
    figure: np.ndarray
    history: tuple
    data: RangeData
    costs: Costs

    def __post_init__(self):
        freeze_fields(self)

    @property
    def settings(self) -> dict:
        """The settings as JSON: ``search``, ``select``, ``refine``, σ, quantum, λ, the
        bit costs and the raw data's bits (what parts.json records)."""
        enc, costs = self.data.encoding, self.costs
        return {
            "search": self.search.to_json(),
            "select": dataclasses.asdict(self.select),
            "refine": dataclasses.asdict(self.refine),
            "regions": self.regions,
            "sigma": enc.sigma,
            "quantum": enc.quantum,
            "commission_weight": enc.commission_weight,
            "bits": {
                "part": costs.part,
                "explained_pixel": costs.explained,
                "commission_pixel": costs.commission,
                "omitted_pixel": costs.omission,
            },
            "raw_bits": costs.omission * costs.figure_pixels,
        }

    @property
    def description_length(self) -> float:
        return self.cost.total

    def summary(self) -> str:
        n = len(self.parts)
        t = self.timings
        return (
            f"{n} parts ({14 * n} parameters), E = {self.cost.total:.0f} bits "
            f"(initial {self.initial_cost.total:.0f}; raw data {self.settings['raw_bits']:.0f}), "
            f"{self.fraction_explained:.1%} of {int(self.figure.sum())} figure pixels explained within ±σ/2, "
            f"commission {self.commission_fraction:.1%}; "
            f"search {t['search']:.1f} s, selection {t['selection']:.2f} s, refinement {t['refinement']:.1f} s, "
            f"total {t['total']:.1f} s"
        )

    def scene_dict(self, names=None) -> dict:
        """The scene JSON of the result (see :mod:`sqparts._io`), with per-part Γ and bits,
        description length, timings and settings."""
        from ._io import scene_to_dict

        ann = []
        for i, s in enumerate(self.part_stats):
            a = dict(s)
            if names:
                a["name"] = names[i]
            ann.append(a)
        return scene_to_dict(
            self.parts,
            ann,
            description_length_bits=self.cost.total,
            initial_description_length_bits=self.initial_cost.total,
            fraction_explained=self.fraction_explained,
            commission_fraction=self.commission_fraction,
            candidates=self.candidates,
            selection=self.selection_method,
            timings_s=self.timings,
            settings=self.settings,
        )


def _settings(value, kind, name: str):
    if value is None:
        return kind()
    if not isinstance(value, kind):
        raise TypeError(f"{name}: got {value!r:.60} ({type(value).__name__}), expected a sqparts.{kind.__name__}")
    return value


@memo_scope()  # a recovery looks up its own repeated renderings and fits
def recover(
    depth,
    camera: Camera,
    *,
    search: SearchSettings | str = "fast",
    select: SelectSettings | None = None,
    refine: RefineSettings | None = None,
    figure=None,
    encoding: Encoding | None = None,
    centres=None,
    progress=None,
) -> Recovery:
    """Recover a part model from a range image (sections 3.3-3.5).

    Parameters
    ----------
    depth : (H, W) float array, NaN where there is no return.
    camera : the camera that took it (``depth.shape == (camera.height, camera.width)``).
    search : a :class:`~sqparts.SearchSettings` or a preset name of
        :data:`~sqparts.SEARCH_PRESETS` (``"fast"``: the coarse grid, light polishing;
        ``"paper"``: the paper's ~2^16 grid; ``"region"``: one region's long polishing
        and restarts, for boxy, rigid objects).
    select : how Eq. (7) is minimised (:class:`~sqparts.SelectSettings`).
    refine : joint refinement (:class:`~sqparts.RefineSettings`; ``RefineSettings.none()``
        to stop after selection).
    figure : optional (H, W) bool mask of the figure (default: every return).
    encoding : σ, λ and the bit costs (default: :func:`~sqparts.encoding_for` the figure).
    centres : optional (n, 2) region centres (row, col) replacing the skeleton's.
    progress : optional wrapper for the region loop (e.g. ``tqdm.tqdm``).
    """
    search = search_preset(search)
    select = _settings(select, SelectSettings, "select")
    refine = _settings(refine, RefineSettings, "refine")
    t0 = time.perf_counter()
    fits, data, resolved = fit_image(
        depth, camera, search, figure=figure, encoding=encoding, centres=centres, progress=progress
    )
    jax.block_until_ready([f.gamma for f in fits])
    t1 = time.perf_counter()
    costs = Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    parts, layers, explained, commission = _candidates(fits, data)
    if parts is None:
        raise ValueError(
            "depth: got an image where the search found no part that explains any pixel, expected a figure the grid can fit"
            + _max_size_hint(search)
        )
    assert layers is not None and explained is not None  # None only together with parts
    problem = SelectionProblem.from_masks(explained, commission, costs)
    chosen, method = select.select(problem)
    chosen = select_rendered(layers, data, costs, start=chosen)
    if not chosen.any():
        chosen[int(np.argmax([f.sum() for f in explained]))] = True
    initial = parts[np.flatnonzero(chosen)]
    t2 = time.perf_counter()
    initial_cost = encoding_cost(initial, data, costs)
    if refine.active:
        final, cost, history = refine.refine(initial, data, costs, search=resolved)
    else:
        final, cost, history = initial, initial_cost, [("initial", initial_cost.total)]
    t3 = time.perf_counter()
    return Recovery(
        parts=final,
        part_stats=part_statistics(final, data, cost),
        cost=cost,
        initial_parts=initial,
        initial_cost=initial_cost,
        candidates=len(parts),
        regions=len(fits),
        selection_method=method,
        timings={"search": t1 - t0, "selection": t2 - t1, "refinement": t3 - t2, "total": t3 - t0},
        search=resolved,
        select=select,
        refine=refine,
        depth=np.asarray(data.image),
        figure=np.asarray(data.figure_mask),
        history=tuple(history),
        data=data,
        costs=costs,
    )


def _candidates(fits, data: RangeData):
    """All regions' candidates with Γ > 0 as one batch: the parts, their depth layers
    over the whole image (:func:`~sqparts._encoding.render_layers`) and their explained and
    commission masks by the joint encoding's rule (:func:`~sqparts._encoding.layer_errors`):
    a polished part may outgrow the window it was searched in, and its commission
    outside the window counts in E all the same."""
    parts = [f.parts[i] for f in fits for i, g in enumerate(np.asarray(f.gamma)) if g > 0]
    if not parts:
        return None, None, None, None
    parts = stack_parts(parts)
    layers = render_layers(parts.to_vector(), data.camera)
    return parts, layers, *layer_errors(layers, data)


# --- real scenes: clean-up, figure/ground, one recovery per figure ----------------------


WINDOW_SIZES = (16, 32, 48, 64, 96, 128)
"""Windows are rounded up to one of these so that figures of different sizes share
compiled searches."""


def _composite_cost(recoveries, shape) -> EncodingCost:
    """One :class:`EncodingCost` for several figures' recoveries: nearest surface wins,
    labels numbered across figures, totals summed."""
    rendered = np.full(shape, np.nan, np.float32)
    labels = np.full(shape, -1, np.int64)
    explained = np.zeros(shape, bool)
    commission = np.zeros(shape, bool)
    offset = 0
    totals = np.zeros(5)
    for rec, cost in recoveries:
        nearer = np.isfinite(cost.rendered) & ~(cost.rendered >= rendered)
        rendered = np.where(nearer, cost.rendered, rendered)
        labels = np.where(nearer, cost.labels + offset, labels)
        explained |= cost.explained_mask
        commission |= cost.commission_mask
        offset += len(rec.parts)
        totals += [cost.total, cost.parts, cost.explained, cost.commission, cost.omission]
    t, n, e, c, o = totals
    return EncodingCost(float(t), int(n), int(e), int(c), int(o), rendered, labels, explained, commission)


@dataclasses.dataclass(frozen=True)
class SceneSettings:
    """How :func:`recover_scene` prepares real data and finishes its parts; presets in
    :data:`SCENE_PRESETS`.

    Binning: ``resolution`` (bin the image, NaN-aware median, so its longest side is
    about this; None or 0: full resolution). The cube of data: ``depth_range`` (near,
    far): returns outside are dropped. Clean-up (``clean``): missing returns, flying
    pixels and outliers (:func:`~sqparts.clean_range_image`, with ``tear``). Pixels
    without a return (``holes``, :func:`~sqparts.missing_returns`): ``"auto"`` (small
    interior holes are missing data, wide ones and those a farther surface shows through
    are free space), ``"free"`` (every one is free space: a part drawn there pays
    commission) or ``"missing"`` (every enclosed one is missing data).
    Figure/ground (``figure_ground``): up to ``planes`` background planes removed
    (``plane_threshold``) and the rest split into figures (``min_figure_pixels``,
    ``max_figures``, ``max_height``, ``max_border_fraction``: see
    :func:`~sqparts.figure_ground`); off: the whole image is one figure. Pieces that one
    object's own occlusions may have torn apart (``join``; :func:`~sqparts.joined_pieces`:
    they touch, and the depth jump between them is less than the smaller one's size):
    ``"auto"`` (the default) takes each such group's figures' parts together on the
    group's pixels, merged across the tears (:func:`_merged_across`), searches and
    refines the group as one figure as well only where a part of that spans a tear, and
    joins the figures where a part of the joined description spans the tear and it
    describes their pixels in fewer bits than the figures' parts together (under the
    joined figure's encoding); True always joins them, False never. Prettifying
    (``prettify``): near-vertical and near-horizontal parts snapped to gravity ``up``
    (default: the ground plane's normal) within ``max_angle`` degrees when E rises by at
    most ``max_bits`` (:func:`~sqparts.prettify`).
    """

    resolution: int | None = 160
    depth_range: tuple[float, float] | None = None
    clean: bool = True
    tear: float | None = None
    holes: str = "auto"
    figure_ground: bool = True
    planes: int = 3
    plane_threshold: float | None = None
    min_figure_pixels: int | None = None
    max_figures: int | None = None
    max_height: float | None = None
    max_border_fraction: float = 0.15
    join: bool | str = "auto"
    prettify: bool = False
    up: tuple[float, float, float] | None = None
    max_angle: float = 15.0
    max_bits: float = 56.0

    def __post_init__(self):
        from ._preprocess import check_depth_range, check_holes, check_positive

        check_holes(self.holes)
        for name, integer in (
            ("tear", False),
            ("plane_threshold", False),
            ("min_figure_pixels", True),
            ("max_figures", True),
            ("max_height", False),
        ):
            if getattr(self, name) is not None:
                check_positive(name, getattr(self, name), integer=integer)
        p = self.planes
        if isinstance(p, bool) or not isinstance(p, (int, np.integer)) or p < 0:
            raise ValueError(f"planes: got {p!r}, expected an integer >= 0")
        r = self.resolution
        if r is not None and (isinstance(r, bool) or not isinstance(r, (int, np.integer)) or r < 0):
            raise ValueError(f"resolution: got {r!r}, expected an integer >= 0 or None")
        for name in ("clean", "figure_ground", "prettify"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}: got {getattr(self, name)!r}, expected True or False")
        if not (isinstance(self.join, bool) or self.join == "auto"):
            raise ValueError(f"join: got {self.join!r}, expected True, False or 'auto'")
        if self.depth_range is not None:
            object.__setattr__(self, "depth_range", check_depth_range(self.depth_range))
        if self.up is not None:
            try:
                up = tuple(float(x) for x in self.up)
            except (TypeError, ValueError):
                up = ()
            if len(up) != 3 or not all(np.isfinite(x) and fits_float32(x) for x in up) or not any(up):
                raise ValueError(
                    f"up: got {self.up!r}, expected three finite numbers (x, y, z) that float32 holds, not all 0"
                )
            object.__setattr__(self, "up", up)
        if isinstance(self.max_angle, bool) or not (
            isinstance(self.max_angle, (int, float)) and 0 < self.max_angle <= 90
        ):
            raise ValueError(f"max_angle: got {self.max_angle!r}, expected degrees in (0, 90]")
        if isinstance(self.max_bits, bool) or not (
            isinstance(self.max_bits, (int, float)) and np.isfinite(self.max_bits) and self.max_bits >= 0
        ):
            raise ValueError(f"max_bits: got {self.max_bits!r}, expected a finite number >= 0")
        if not (isinstance(self.max_border_fraction, (int, float)) and 0 <= self.max_border_fraction <= 1):
            raise ValueError(f"max_border_fraction: got {self.max_border_fraction!r}, expected a number in [0, 1]")


SCENE_PRESETS = types.MappingProxyType(
    {
        "real": SceneSettings(),
        "prettified": SceneSettings(prettify=True),
        "synthetic": SceneSettings(resolution=None, clean=False, figure_ground=False),
    }
)
"""Named scene settings: ``"real"`` (recover_scene's default: binned to ~160 pixels,
cleaned, figure/ground), ``"prettified"`` (the same, then prettified), ``"synthetic"``
(a clean render: full resolution, no clean-up, the whole image one figure)."""


def scene_preset(name_or_settings) -> SceneSettings:
    """:class:`SceneSettings` from a preset name or a SceneSettings (returned as is)."""
    return lookup_preset(name_or_settings, SceneSettings, SCENE_PRESETS, "scene")


@dataclasses.dataclass(frozen=True)
class SceneRecovery(_Fractions, _Meshes):
    """What :func:`recover_scene` found: one :class:`Recovery` per figure (immutable).

    Attributes
    ----------
    figures : tuple of Recovery, largest figure first.
    camera : the camera of the (possibly binned) image the search ran on.
    depth : that image after clean-up, NaN = no return.
    factor : the binning factor applied to the input.
    cleaned : the :class:`~sqparts.CleanedRange` report, or None.
    figure_ground : the :class:`~sqparts.FigureGround` result, or None.
    prettify : per figure, per part: what prettifying tried and kept (or None).
    timings : seconds: ``preprocess``, ``recovery`` (all figures), ``total``.
    scene : the :class:`SceneSettings` it ran with (each figure's :class:`Recovery`
        records its search, select and refine settings).
    joins : per group of figure/ground's figures that may be one object (``join``
        "auto"): ``figures`` (indices into ``figures``: the joined one, or those kept
        apart), ``separate_bits`` and ``joined_bits`` (the two descriptions of the
        group's pixels; the joined one: the figures' parts merged across the tears, or,
        where a part of those spans a tear, the shorter of that and the group's own
        recovery), ``spans`` (a part of the joined one across the tear),
        ``joined``. ``figure_ground.figures`` are the figures before joining.
    """

    figures: Sequence
    camera: Camera
    depth: np.ndarray
    factor: int
    cleaned: CleanedRange | None
    figure_ground: FigureGround | None
    prettify: Sequence | None
    timings: Mapping
    scene: SceneSettings
    joins: Sequence = ()

    def __post_init__(self):
        freeze_fields(self)

    @property
    def parts(self) -> Part:
        return stack_parts([r.parts[i] for r in self.figures for i in range(len(r.parts))])

    @property
    def part_stats(self) -> list:
        return [dict(s, figure=k) for k, r in enumerate(self.figures) for s in r.part_stats]

    @property
    def figure(self) -> np.ndarray:
        out = np.zeros(self.depth.shape, bool)
        for r in self.figures:
            out |= r.figure
        return out

    @property
    def cost(self) -> EncodingCost:
        return _composite_cost([(r, r.cost) for r in self.figures], self.depth.shape)

    @property
    def initial_cost(self) -> EncodingCost:
        return _composite_cost([(r, r.initial_cost) for r in self.figures], self.depth.shape)

    @property
    def initial_parts(self) -> Part:
        return stack_parts([r.initial_parts[i] for r in self.figures for i in range(len(r.initial_parts))])

    @property
    def settings(self) -> dict:
        return {
            "scene": dataclasses.asdict(self.scene),
            "sigma": max(r.settings["sigma"] for r in self.figures),
            "figures": [r.settings for r in self.figures],
        }

    def summary(self) -> str:
        n = len(self.parts)
        fg = self.figure_ground
        ground = "" if fg is None else f"{len(fg.planes)} background plane(s) removed, "
        per = ", ".join(str(len(r.parts)) for r in self.figures)
        joined = sum(j["joined"] for j in self.joins)
        joins = f" ({joined} of {len(self.joins)} touching group(s) joined)" if self.joins else ""
        return (
            f"{ground}{len(self.figures)} figure(s){joins} at {self.camera.width}x{self.camera.height}; "
            f"{n} parts ({per}), E = {self.cost.total:.0f} bits, {self.fraction_explained:.1%} of "
            f"{int(self.figure.sum())} figure pixels explained, commission {self.commission_fraction:.1%}; "
            f"total {self.timings['total']:.1f} s"
        )

    def scene_dict(self, names=None) -> dict:
        from ._io import scene_to_dict

        fg = self.figure_ground
        ann = self.part_stats
        if self.prettify:
            flat = [e for rep in self.prettify for e in rep]
            ann = [dict(a, prettify=e) for a, e in zip(ann, flat)]
        return scene_to_dict(
            self.parts,
            ann,
            description_length_bits=self.cost.total,
            fraction_explained=self.fraction_explained,
            commission_fraction=self.commission_fraction,
            camera=self.camera.to_json(),
            binning=self.factor,
            clean_up=None if self.cleaned is None else self.cleaned.summary(),
            ground_plane=None if fg is None or fg.ground is None else fg.ground.to_json(),
            background_planes=[] if fg is None else [p.to_json() for p in fg.planes],
            figures=[
                {
                    "pixels": int(r.figure.sum()),
                    "parts": len(r.parts),
                    "description_length_bits": r.cost.total,
                    "fraction_explained": r.fraction_explained,
                    "timings_s": r.timings,
                }
                for r in self.figures
            ],
            figure_joins=list(self.joins),
            timings_s=self.timings,
            settings=self.settings,
        )


def _max_size_hint(search: SearchSettings) -> str:
    """What to try when a search given its own ``max_size`` found no part."""
    if search.max_size is None:
        return ""
    return f" (parts were searched with semi-axes up to max_size {search.max_size:g}: try another --max-size, or none)"


def _snap_window(window: int) -> int:
    return next((w for w in WINDOW_SIZES if w >= window), int(window))


def _shared_frame(search: SearchSettings, searches) -> SearchSettings:
    """``search`` with the frame of the widest window among ``searches`` (one image's
    figures), where that frame fits its window's padding (:meth:`SearchSettings.resolve`):
    the figures' full-resolution passes and candidates then share their compiled
    programs, each scored as on its own window. Not a search pruned on no lattice
    (``stride`` 1, brute force): its full-resolution pass scores the whole grid, and a
    frame pixel beyond its window costs as much there as one inside it (a 52-pixel
    sliver's 32-pixel window in a 64-pixel frame: 8.5 s of search warm, 2.2 s on its own
    window), more than the compiling of its own programs."""
    if search.window is None or search.stride == 1:
        return search
    frame = max(int(s.window) for s in searches if s.window is not None)
    if frame <= search.window or frame > largest_frame(search.window, PAD):
        return search
    return dataclasses.replace(search, frame=frame)


def _shared_lattices(search: SearchSettings, searches) -> SearchSettings:
    """``search`` with the pruning lattices of the widest window's search among
    ``searches`` (one image's figures) where they hold its own: the figures' pruning
    passes then share one compiled program, each window scored as on its own lattice,
    on the pass of the fewest points that holds it. A figure pruned on a finer lattice
    than any of the widest one's keeps its own."""
    widest = max((s for s in searches if s.window is not None), key=lambda s: s.window, default=None)
    if widest is None or None in (widest.stride, search.window, search.stride):
        return search
    shared = widest.own_lattices()
    if max(search.own_lattices()) > max(shared):
        return search
    return dataclasses.replace(search, lattices=shared)


def recover_scene(
    depth,
    camera: Camera,
    *,
    scene: SceneSettings | str = "real",
    search: SearchSettings | str = "fast",
    select: SelectSettings | None = None,
    refine: RefineSettings | None = None,
    encoding: Encoding | None = None,
    progress=None,
) -> SceneRecovery:
    """Recover a real scene: bin, clean, separate figures from ground (``scene``, a
    :class:`SceneSettings` or preset name), recover each figure on its own with
    ``search``, ``select`` and ``refine`` as for :func:`recover` (the searches compiled
    once, shared by all figures), optionally prettify. Unless ``search`` (and ``encoding``)
    fix them, each figure's σ covers the sensor's noise (:func:`~sqparts.estimate_noise`)
    and half a pixel footprint, its pruning stride is the widest lattice (at most 4) that
    still sees every member able to pay for a part (2 for the built-in gate's two-pixel
    bars, 1 for a one-pixel one), and its window is snapped to a few sizes so that figures
    share compiled programs; the figures' full-resolution scoring runs in one frame, the
    widest window's (``SearchSettings.frame``), and their pruning passes on the widest
    window's lattices where theirs fit in them (``SearchSettings.lattices``), so that they
    share those programs too.
    """
    from ._encoding import encoding_for
    from ._postprocess import prettify as _prettify
    from ._preprocess import (
        DEFAULT_TEAR,
        auto_factor,
        clean_range_image,
        crop_depth_range,
        downsample,
        estimate_noise,
        missing_returns,
        pruning_stride,
    )
    from ._preprocess import figure_ground as _figure_ground
    from ._search import default_max_size, window_for

    st = scene_preset(scene)
    search = search_preset(search)
    select = _settings(select, SelectSettings, "select")
    refine = _settings(refine, RefineSettings, "refine")
    t0 = time.perf_counter()
    tear = DEFAULT_TEAR if st.tear is None else st.tear
    d = np.asarray(depth, np.float32)
    if d.ndim != 2:
        raise ValueError(f"depth: got shape {d.shape}, expected a 2-D range image")
    given = int(np.isfinite(d).sum())  # returns in the input, before binning and clean-up
    factor = auto_factor(d.shape, st.resolution) if st.resolution else 1
    if factor > 1:
        d, camera = downsample(d, camera, factor)
    binned = d
    if st.clean:
        cleaned = clean_range_image(d, camera, tear=tear, depth_range=st.depth_range)
        d = cleaned.depth
    else:
        cleaned = None
        d = crop_depth_range(d, st.depth_range)
    left = int(np.isfinite(d).sum())
    if st.figure_ground and left < 16 and left != given:  # too few once binned and cleaned: say so
        # The depth range alone leaves too few: name it, not the clean-up.
        ranged = st.depth_range is not None and np.isfinite(crop_depth_range(binned, st.depth_range)).sum() < 16
        steps = [f"binning to {d.shape[1]}x{d.shape[0]}"] * (factor > 1) + [
            "clean-up" if st.clean and not ranged else "the depth range"
        ]
        hints = (
            ["a finer --resolution"] * (factor > 1)
            + (["a wider --depth-range"] if ranged else ["--no-clean"] * st.clean)
        ) * (given >= 16)
        raise ValueError(
            f"depth: got {left} of {given} returns left after {' and '.join(steps)}, expected at least 16"
            + (f" ({' or '.join(hints)})" if hints else "")
        )
    fg = None
    if st.figure_ground:
        fg = _figure_ground(
            d,
            camera,
            planes=st.planes,
            plane_threshold=st.plane_threshold,
            tear=tear,
            min_pixels=st.min_figure_pixels,
            max_figures=st.max_figures,
            max_height=st.max_height,
            max_border_fraction=st.max_border_fraction,
            holes=st.holes,
            join=st.join is True,
        )
        masks = fg.figures
        if not masks:
            raise ValueError(
                "depth: got no figure left after removing the background, expected at least one (try --no-figure-ground or a smaller --min-figure-pixels; in Python figure_ground=False or min_figure_pixels)"
            )
    else:
        masks = [np.isfinite(d) | missing_returns(d, camera, np.isfinite(d), holes=st.holes, tear=tear)]
    gravity = st.up if st.up is not None else (fg.up if fg is not None else None)
    if st.prettify and gravity is None:  # said before the figures' recoveries, not after
        raise ValueError(
            "up: got nothing and no ground plane was found, expected the gravity direction up=(x, y, z) "
            "for prettifying (--up X,Y,Z)"
        )
    t1 = time.perf_counter()
    reports = []
    noise = estimate_noise(d)
    joinable: Sequence[tuple[tuple[int, ...], np.ndarray]] = fg.joinable if fg is not None and st.join == "auto" else ()
    figures = []
    for mask in [*masks, *(m for _, m in joinable)]:  # each group that may be one object, too
        enc = encoding
        if enc is None:  # σ covers the sensor's noise (±σ/2 is ±2 sd) and half a pixel footprint
            base = encoding_for(d[mask & np.isfinite(d)], footprint=figure_footprint(d, mask, camera))
            enc = encoding_for(d[mask & np.isfinite(d)], sigma=max(base.sigma, 4.0 * noise))
        figure_search = search
        if search.stride is None:  # thin members: a lattice that sees them
            stride = pruning_stride(mask & np.isfinite(d), enc.part_bits / enc.saved_per_pixel)
            # No lattice of the window sees them wherever it lies: one through each
            # region's centre does (the regions lie on the figure's skeleton, a region on
            # each member), at a quarter of the full resolution's cost.
            figure_search = dataclasses.replace(figure_search, stride=max(stride, 2), centred=stride == 1)
        if search.window is None:
            data = prepare(d, camera, figure=mask, encoding=enc)
            size = search.max_size or default_max_size(data)
            figure_search = dataclasses.replace(figure_search, window=_snap_window(window_for(data, size)))
        figures.append((mask, enc, figure_search))
    if search.frame is None:  # the figures' full-resolution scoring in one frame: one program
        figures = [(mask, enc, _shared_frame(s, [f[2] for f in figures])) for mask, enc, s in figures]
        if search.lattices is None:  # and their pruning on one set of lattices: one program
            figures = [(mask, enc, _shared_lattices(s, [f[2] for f in figures])) for mask, enc, s in figures]

    def figure_recovery(mask, enc, figure_search, refine):  # None: the search found no part
        try:
            return recover(
                d,
                camera,
                search=figure_search,
                select=select,
                refine=refine,
                figure=mask,
                encoding=enc,
                progress=progress,
            )
        except ValueError as e:
            if "found no part" not in str(e):
                raise
            return None

    separate = [figure_recovery(*f, refine) for f in figures[: len(masks)]]
    joint = []
    for (members, _), f in zip(joinable, figures[len(masks) :]):
        # Searched and refined as one figure only where the pieces' parts, merged across the
        # tears, already span one: a join needs a part that does.
        pieces = [masks[k] for k in members]
        apart = [separate[k] for k in members if separate[k] is not None]
        rec = _merged_across(apart, d, camera, f[0], f[1], pieces, refine) if apart and refine.active else None
        if rec is None or _spanning(_shown(rec, pieces), rec.costs).any():
            whole = figure_recovery(*f, refine)
            rec = min((r for r in (rec, whole) if r is not None), key=lambda r: r.cost.total, default=None)
        joint.append(rec)
    recoveries, joins = _joined(separate, [k for k, _ in joinable], joint, masks)
    if not recoveries:
        raise ValueError(
            "depth: got figures on which the search found no part, expected at least one part" + _max_size_hint(search)
        )
    if st.prettify:
        finished = []
        for rec in recoveries:
            parts, cost, report = _prettify(
                rec.parts, rec.data, rec.costs, up=gravity, max_angle=st.max_angle, max_bits=st.max_bits
            )
            finished.append(
                dataclasses.replace(
                    rec,
                    parts=parts,
                    cost=cost,
                    part_stats=part_statistics(parts, rec.data, cost),
                    history=(*rec.history, ("prettify", cost.total)),
                )
            )
            reports.append(report)
        recoveries = finished
    t2 = time.perf_counter()
    return SceneRecovery(
        recoveries,
        camera,
        d,
        factor,
        cleaned,
        fg,
        reports if st.prettify else None,
        {"preprocess": t1 - t0, "recovery": t2 - t1, "total": t2 - t0},
        st,
        joins,
    )


@memo_scope()
def _merged_across(apart, depth, camera: Camera, mask, encoding: Encoding, pieces, refine: RefineSettings) -> Recovery:
    """The figures' recoveries ``apart`` (of the figures ``pieces``) as one recovery of
    their union ``mask``, under its ``encoding``: their parts together, grown over its
    pixels (a part may now take pixels of another piece that its own figure lacked)
    and merged across the tears (:class:`~sqparts._refine.MergeParts` with
    ``pieces``), each merge followed by growing and dropping as in refinement, while
    merging lowers E. What :func:`recover_scene` tries first for a group of figures
    that may be one object (join "auto"): no search."""
    t0 = time.perf_counter()
    data = prepare(depth, camera, figure=mask, encoding=encoding)
    costs = Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    label = np.full(np.shape(mask), -1)
    for k, piece in enumerate(pieces):
        label[np.asarray(piece, bool)] = k
    grow = refine.regrow()
    merge = OnGain(MergeParts(passes=1, steps=refine.steps, tries=0, pieces=label), then=grow, repeat=MAX_PASSES)
    start = np.concatenate([part_vectors(r.parts) for r in apart])
    initial_cost = encoding_cost(host_parts(start), data, costs)
    vectors, cost, history = run_moves((*grow, merge), start, initial_cost, data, costs)
    final = Part.from_vector(vectors)
    t = time.perf_counter() - t0
    return dataclasses.replace(
        apart[0],
        parts=final,
        part_stats=part_statistics(final, data, cost),
        cost=cost,
        initial_parts=Part.from_vector(start),
        initial_cost=initial_cost,
        candidates=sum(r.candidates for r in apart),
        regions=sum(r.regions for r in apart),
        timings={"search": 0.0, "selection": 0.0, "refinement": t, "total": t},
        depth=np.asarray(data.image),
        figure=np.asarray(data.figure_mask),
        history=(("figures' parts", initial_cost.total), *history),
        data=data,
        costs=costs,
    )


def _joined(separate, groups, joint, masks):
    """The figures' recoveries (``separate``, of the figures ``masks``; None: no part
    found), each group of them (``groups``: their indices) that ``joint`` recovered as
    one figure replaced by that recovery where one of its parts spans the tear (it
    explains, in two of the group's figures, at least the pixels that pay for a part:
    :func:`~sqparts._encoding.least_pixels`) and it describes the group's pixels in
    fewer bits than the figures' parts together (under the joined figure's encoding).
    A group is searched and refined as one figure only where the figures' parts,
    merged across the tears (:func:`_merged_across`), already span one
    (:func:`recover_scene`). Without a part across the tear a shorter joined
    description only rearranges parts within the pieces (or their interplay: two
    objects side by side), and the figures stay apart; each of them then takes the
    joined recovery's parts that explain most of their pixels within it where those
    describe it in fewer bits (another search's answer for the piece: :func:`_shorter`).
    Returns (recoveries, largest figure first; per group, a dict: ``figures`` (their
    indices: the joined one, or those kept apart), ``separate_bits`` (None: no part
    found apart), ``joined_bits``, ``spans`` (a part across the tear), ``joined``)."""
    keep = list(separate)
    found = []
    for members, rec in zip(groups, joint):
        apart = [separate[k] for k in members if separate[k] is not None]
        if rec is None:
            continue
        joined_bits = float(rec.cost.total)
        separate_bits = None
        if apart:
            vectors = np.concatenate([part_vectors(r.parts) for r in apart])
            separate_bits = float(encoding_cost(host_parts(vectors), rec.data, rec.costs).total)
        shown = _shown(rec, [masks[k] for k in members])
        spans = bool(_spanning(shown, rec.costs).any())
        join = spans and (separate_bits is None or joined_bits < separate_bits)
        if join:
            for k in members:
                keep[k] = None
            keep.append(rec)
        else:  # apart: each figure takes the joined recovery's parts within it where they are the shorter
            owner, seen = np.argmax(shown, 1), np.max(shown, 1)
            for j, k in enumerate(members):
                if keep[k] is not None and ((owner == j) & (seen > 0)).any():
                    keep[k] = _shorter(keep[k], part_vectors(rec.parts)[(owner == j) & (seen > 0)])
        recs = (rec,) if join else tuple(keep[k] for k in members if keep[k] is not None)
        found.append((recs, separate_bits, joined_bits, spans, join))
    out = sorted((r for r in keep if r is not None), key=lambda r: -int(np.asarray(r.figure).sum()))
    index = {id(r): k for k, r in enumerate(out)}
    joins = [
        {"figures": [index[id(r)] for r in recs], "separate_bits": s, "joined_bits": j, "spans": spans, "joined": join}
        for recs, s, j, spans, join in found
    ]
    return out, joins


def _shown(rec: Recovery, masks) -> np.ndarray:
    """(parts, masks): the pixels of each mask that each of ``rec``'s parts explains."""
    labels, explained = np.asarray(rec.cost.labels), np.asarray(rec.cost.explained_mask)
    return np.array(
        [[int((explained & (labels == i) & m).sum()) for m in masks] for i in range(len(rec.parts))], np.int64
    ).reshape(len(rec.parts), len(masks))


def _spanning(shown: np.ndarray, costs: Costs) -> np.ndarray:
    """Per part (a row of :func:`_shown`): whether it spans a tear between the figures:
    it explains, in two of them, at least the pixels that pay for a part
    (:func:`~sqparts._encoding.least_pixels`)."""
    return (shown >= least_pixels(costs)).sum(1) >= 2


def _shorter(rec: Recovery, vectors: np.ndarray) -> Recovery:
    """``rec`` with the parts of (k, 14) ``vectors`` instead where they describe its figure
    in fewer bits (another recovery's parts within it: a joined figure's)."""
    cost = encoding_cost(host_parts(vectors), rec.data, rec.costs)
    if not cost.total < rec.cost.total:
        return rec
    parts = Part.from_vector(vectors)
    return dataclasses.replace(
        rec,
        parts=parts,
        cost=cost,
        part_stats=part_statistics(parts, rec.data, cost),
        history=(*rec.history, ("joined figure's parts", cost.total)),
    )


# --- multiscale ---------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class MultiscaleRecovery:
    """Recoveries at several scales, coarse to fine (paper sections 1 and 4.1).

    Attributes
    ----------
    levels : tuple of Recovery, coarsest first.
    factors : the binning factor of each level's image.
    cameras : each level's camera.
    max_sizes : each level's largest semi-axis searched.
    parents : per level, per part, the index of the part one level coarser that covers
        most of its pixels (-1: none, and every part of level 0).
    """

    levels: Sequence
    factors: Sequence
    cameras: Sequence
    max_sizes: Sequence
    parents: Sequence

    def __post_init__(self):
        freeze_fields(self)

    def summary(self) -> str:
        return "; ".join(
            f"level {i} ({c.width}x{c.height}, parts up to {s:.3g}): {len(r.parts)} parts, {r.fraction_explained:.0%} explained"
            for i, (r, c, s) in enumerate(zip(self.levels, self.cameras, self.max_sizes))
        )

    def tree(self) -> dict:
        """The hierarchy as JSON: per level, its parts (scene format) with ``parent``."""
        from ._io import part_to_dict

        return {
            "levels": [
                {
                    "binning": f,
                    "max_size": s,
                    "camera": c.to_json(),
                    "parts": [
                        part_to_dict(r.parts[j], parent=int(p[j]), **r.part_stats[j]) for j in range(len(r.parts))
                    ],
                }
                for r, f, c, s, p in zip(self.levels, self.factors, self.cameras, self.max_sizes, self.parents)
            ]
        }


def recover_multiscale(
    depth,
    camera: Camera,
    *,
    levels: int = 3,
    search: SearchSettings | str = "fast",
    select: SelectSettings | None = None,
    refine: RefineSettings | None = None,
    figure=None,
    progress=None,
) -> MultiscaleRecovery:
    """Recover a coarse-to-fine hierarchy of part models.

    Level k of ``levels`` (0 = coarsest) searches parts up to ``max_size`` / 2^k
    (``search.max_size``, default: half the figure's largest extent; ``search``,
    ``select`` and ``refine`` as for :func:`recover`) on the image binned by
    2^(levels-1-k). Small images give "summarizing" descriptions, since each part must
    still pay its κ0 bits from fewer pixels: a person as one blob; as head, torso and
    limbs; with hands and feet. Each part is linked to its parent one level up.
    """
    from ._preprocess import downsample, downsample_mask

    if not (isinstance(levels, (int, np.integer)) and 1 <= levels <= 6):
        raise ValueError(f"levels: got {levels!r}, expected an integer in [1, 6]")
    search = search_preset(search)
    d0 = np.asarray(depth, np.float32)
    data0 = prepare(d0, camera, figure=figure)
    max_size = search.max_size
    if max_size is None:
        pts = camera.points(data0.image)[data0.figure_mask]
        max_size = float(np.max(np.ptp(pts, axis=0))) / 2.0
    fig0 = data0.figure_region
    out_levels, factors, cameras, sizes, parents = [], [], [], [], []
    for k in range(levels):
        f = 2 ** (levels - 1 - k)
        if f > 1:
            d, cam = downsample(d0, camera, f)
            fig = downsample_mask(fig0, f)
        else:
            d, cam, fig = d0, camera, fig0
        size = max_size / 2**k
        level = dataclasses.replace(search, max_size=size, window=None)
        rec = recover(d, cam, search=level, select=select, refine=refine, figure=fig, progress=progress)
        if out_levels:
            _, coarse = render_range_image(out_levels[-1].parts, cam, return_labels=True)
            coarse = np.asarray(coarse)
            par = []
            for j in range(len(rec.parts)):
                under = coarse[(rec.cost.labels == j) & (coarse >= 0)]
                par.append(int(np.bincount(under).argmax()) if under.size else -1)
            parents.append(np.asarray(par, np.int64))
        else:
            parents.append(np.full(len(rec.parts), -1, np.int64))
        out_levels.append(rec)
        factors.append(f)
        cameras.append(cam)
        sizes.append(size)
    return MultiscaleRecovery(out_levels, factors, cameras, sizes, parents)
