"""The massively parallel local search (paper sections 3.3-3.4, 3.6 and the Appendix).

At each region of the image, every hypothesis of a :class:`~sqparts.Grid` is posed at
the region (its orientation taken relative to the viewing ray through the region centre,
its centre on that ray behind the measured surface), rendered over the region's window
and scored with Γ (Eq. 4): one jit-compiled computation for all regions' hypotheses
together (:func:`score_regions`), vmapped over the pixels and the hypotheses of a chunk,
a loop over a call's regions (up to :data:`REGION_BUCKET`, the loop as long as the live
ones), each a loop over its chunks of hypotheses (each chunk carrying its window),
sharded over ``jax.devices()`` with ``jax.shard_map``. It is compiled once per (lattice
sizes, camera), never per region, number of regions, stride or image.

**Pruning** (section 3.6): every hypothesis is first scored on a pixel subsample
(``stride``: every stride-th row and column, each pixel standing for stride² pixels);
only the best ``survivors`` are scored again at full resolution. ``stride=1`` is the
brute force. The subsample scores each length of hypothesis on the window that covers
it, every window in the same compiled call (:func:`_by_window`, :func:`_score_passes`),
on the pass of the fewest lattice points that holds its lattice (:class:`_Program`): an
image's figures, whose windows and strides differ, share one pruning program.

**Candidates** (:func:`fit_regions`): every region's best distinct hypotheses are posed,
scored at full resolution, polished and scored again together, ``PART_BUCKET`` per
compiled call whatever their region: polishing is region growing with optimistix
Levenberg-Marquardt on the distances (footnote 6) of the measured 3-D points each
one explains (:func:`~sqparts._polish.grow_parts`, the program the refinement polishes
with), and a polished part is kept only if it stays at its region and its Γ improves.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P

from ._camera import Camera, camera_rays
from ._compile import RowMemo, balanced_groups, concurrently, persistent_jit
from ._data import RangeData, prepare
from ._encoding import (
    PART_BUCKET,
    Encoding,
    commission_mask,
    gamma_terms,
    host_parts,
    pad_parts,
    pad_rows,
    part_vectors,
)
from ._grid import Grid, grid_preset, lookup_preset
from ._part import (
    Part,
    matmul,
    matrix_to_rotation_vector,
    rotation_matrix,
)
from ._polish import grow_parts, once_per_image
from ._render import DEFAULT_NEWTON_STEPS, _check_newton_steps, cast_part

SEARCH_NEWTON_STEPS = 6
"""Newton steps when scoring hypotheses (grazing silhouette pixels barely move Γ)."""
NUM_BINS = 1024
"""Histogram bins of width σ/2 (offsets of ±256 σ around the anchor pixel's own)."""
CHUNK_RAYS = 2**16
"""Rays per chunk of hypotheses: ``batch_size`` is capped at CHUNK_RAYS / window pixels."""


# --- the image as the search sees it --------------------------------------------------


DEFAULT_STRIDE = 4
"""The pruning lattice of a search whose stride is not given (see :class:`SearchSettings`)."""


@dataclasses.dataclass(frozen=True)
class SearchSettings:
    """How the local search runs (sections 3.3-3.4, 3.6): the settings object of
    :func:`fit_image` and :func:`~sqparts.recover`; named presets in
    :data:`SEARCH_PRESETS`.

    ``grid`` is a :class:`~sqparts.Grid` or a preset name (``"coarse"``, ``"default"``,
    ``"fine"``). ``max_size`` is the largest semi-axis searched (None: a quarter of the
    figure's largest extent) and ``window`` the region's side in pixels (None: the
    projected diameter of a ``max_size`` part); :meth:`resolve` fills both from the data.
    ``top_k`` candidates are returned per region; hypotheses are first scored on every
    ``stride``-th pixel (None: 4 here; :func:`~sqparts.recover_scene` gives each figure the
    widest lattice, at most 4, that still sees every member able to pay for a part,
    :func:`~sqparts._preprocess.pruning_stride`; where none does, thin members, a
    ``centred`` lattice of stride 2) and the best ``survivors`` rescored at full
    resolution (``prune=False``: every hypothesis at full resolution), together with
    the orientation neighbours of the ``refine_orientations`` best distinct survivors
    (coarse to fine, :func:`_orientation_neighbours`: each turned by half the grid's
    orientation step about each of its own axes, both ways); the ``polish_candidates``
    best distinct survivors are polished (``polish_rounds`` of region growing ×
    ``polish_steps`` Levenberg-Marquardt steps, rounded up to a multiple of
    :data:`~sqparts._polish.POLISH_CALL_STEPS`: all regions' candidates together,
    :func:`fit_regions`); the best polished part is restarted from
    3 · ``restarts``² starts (axis labellings × squareness values; 0: none) and polished
    again. Regions are centred on the figure's skeleton (``region_method``, see
    :func:`region_centers`) no two closer than ``spacing`` pixels (None: a seventh of the
    window). ``frame`` (None: the window) is the side of the array in which the
    full-resolution pass and the candidates' scoring compute a window, its pixels beyond
    the window masked (the same Γ as the window alone): searches whose windows differ
    but whose frames agree share those compiled programs (:func:`~sqparts.recover_scene`
    gives an image's figures one frame). ``lattices`` (None: the windows' own) are the
    pruning program's passes, in lattice points a side: each window's lattice goes to the
    pass of the fewest points that holds it, the points beyond it masked (the same Γ as
    on its own), so that searches whose windows and strides differ share the pruning
    program (:func:`~sqparts.recover_scene` gives an image's figures the widest window's
    lattices, :meth:`own_lattices`, where theirs fit in them). ``centred``: each
    region's lattice passes through its centre (:func:`_region_inputs`), so that a
    member narrower than the stride is sampled along the rows and columns of the region
    on it wherever the figure lies; otherwise (the default) the lattice is the window's
    own, every stride-th pixel from stride // 2. The resolved settings are part of the
    compiled computation's key.
    """

    grid: Grid | str = "coarse"
    max_size: float | None = None
    window: int | None = None
    top_k: int = 3
    stride: int | None = None
    survivors: int = 64
    batch_size: int = 256
    newton_steps: int = SEARCH_NEWTON_STEPS
    polish_steps: int = 20
    polish_rounds: int = 3
    polish_candidates: int = 3
    restarts: int = 0
    refine_orientations: int = 0
    region_method: str = "skeleton"
    spacing: float | None = None
    prune: bool = True
    frame: int | None = None
    lattices: tuple[int, ...] | None = None
    centred: bool = False

    def __post_init__(self):
        object.__setattr__(self, "grid", grid_preset(self.grid))
        object.__setattr__(self, "newton_steps", _check_newton_steps(self.newton_steps))  # as the renderer's
        for name in ("top_k", "stride", "survivors", "batch_size"):
            v = getattr(self, name)
            if name == "stride" and v is None:
                continue
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v <= 0:
                raise ValueError(f"{name}: got {v!r}, expected a positive integer")
        for name in ("polish_steps", "polish_rounds", "polish_candidates", "restarts", "refine_orientations"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 0):
                raise ValueError(f"{name}: got {v!r}, expected an integer >= 0")
        if self.max_size is not None:
            object.__setattr__(self, "max_size", check_max_size(self.max_size))
        for name in ("window", "frame"):
            v = getattr(self, name)
            if v is not None and (not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v <= 0):
                raise ValueError(f"{name}: got {v!r}, expected a positive integer or None")
        if self.lattices is not None:
            v = self.lattices
            if not (
                isinstance(v, (tuple, list))
                and 0 < len(v) <= 16
                and all(isinstance(x, (int, np.integer)) and not isinstance(x, bool) and x > 0 for x in v)
            ):
                raise ValueError(f"lattices: got {v!r:.60}, expected a tuple of positive integers or None")
            object.__setattr__(self, "lattices", tuple(int(x) for x in v))
        for name in ("prune", "centred"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name}: got {getattr(self, name)!r}, expected True or False")
        if self.region_method not in ("skeleton", "grid", "both"):
            raise ValueError(f"region_method: got {self.region_method!r}, expected 'skeleton', 'grid' or 'both'")
        if self.spacing is not None and not (
            isinstance(self.spacing, (int, float, np.number)) and math.isfinite(self.spacing) and self.spacing > 0
        ):
            raise ValueError(f"spacing: got {self.spacing!r}, expected a finite number > 0 or None")

    def resolve(self, data: RangeData) -> SearchSettings:
        """These settings with ``max_size``, ``window`` and ``stride`` derived from
        ``data`` where they are None."""
        max_size = self.max_size if self.max_size is not None else default_max_size(data)
        window = int(self.window) if self.window is not None else window_for(data, max_size)
        if window > 2 * data.pad:
            raise ValueError(f"window: got {window}, expected at most {2 * data.pad} pixels (twice the padding)")
        stride = DEFAULT_STRIDE if self.stride is None else self.stride
        if stride // 2 >= window:  # the lattice would hold no pixel of the window
            raise ValueError(f"stride: got {stride}, expected at most {2 * window - 1} (the window is {window} pixels)")
        if self.frame is not None and not window <= self.frame <= largest_frame(window, data.pad):
            raise ValueError(
                f"frame: got {self.frame}, expected {window} to {largest_frame(window, data.pad)} pixels "
                f"(the window, {window}, to half of it plus the padding, {data.pad})"
            )
        resolved = dataclasses.replace(self, max_size=max_size, window=window, stride=stride)
        resolved.pruning_program()  # lattices that hold the windows', or an error
        return resolved

    @property
    def side(self) -> int:
        """The window's side in pixels, of settings resolved on the data."""
        if self.window is None:
            raise ValueError("window: got None, expected settings resolved on the data (SearchSettings.resolve)")
        return int(self.window)

    @property
    def frame_side(self) -> int:
        """The side of the array the full-resolution scoring computes a window in."""
        return self.side if self.frame is None else int(self.frame)

    @property
    def lattice(self) -> int:
        """The pruning stride, of settings resolved on the data."""
        if self.stride is None:
            raise ValueError("stride: got None, expected settings resolved on the data (SearchSettings.resolve)")
        return int(self.stride)

    def own_lattices(self) -> tuple[int, ...]:
        """The pruning passes' own lattices (points a side, distinct, ascending: one per
        window of :func:`_by_window` at the stride), of settings resolved on the data."""
        grid: Grid = self.grid  # pyright: ignore[reportAssignmentType]  # resolved in __post_init__
        return tuple(sorted({_lattice_side(side, self.lattice) for side, _ in _by_window(grid, self.side)}))

    def pruning_program(self) -> _Program | None:
        """The pruning passes' compiled layout given by :attr:`lattices` (None: the windows'
        own, :meth:`_Program.exact`), of settings resolved on the data."""
        if self.lattices is None:
            return None
        need = max(self.own_lattices())
        if max(self.lattices) < need:
            raise ValueError(
                f"lattices: got {self.lattices}, expected one of at least {need} points "
                f"(the {self.side}-pixel window's lattice at stride {self.lattice})"
            )
        grid: Grid = self.grid  # pyright: ignore[reportAssignmentType]  # resolved in __post_init__
        return _Program.shared(self.lattices, grid, self.batch_size, len(jax.devices()))

    def to_json(self) -> dict:
        """The settings as JSON (the grid by its fields)."""
        out = dataclasses.asdict(self)
        out["hypotheses_per_region"] = self.grid.size  # type: ignore[union-attr]
        return out


def largest_frame(window: int, pad: int) -> int:
    """The widest frame a ``window`` can be computed in (:attr:`SearchSettings.frame`):
    a frame is cut from the corner of a window centred anywhere on the image, so it must
    stay within the ``pad`` pixels beyond the image's last row and column."""
    return int(window) // 2 + int(pad)


SEARCH_PRESETS = types.MappingProxyType(
    {
        "fast": SearchSettings(),
        "paper": SearchSettings(grid="default"),
        "region": SearchSettings(
            grid="default",
            top_k=4,
            polish_steps=20,
            polish_rounds=6,
            polish_candidates=24,
            restarts=3,
            refine_orientations=16,
        ),
    }
)
"""Named search settings. ``"fast"`` (recovery's default): the coarse grid (3 168
hypotheses), the few best starts per region polished lightly and without restarts, since
selection and joint refinement follow. ``"paper"``: the same on the paper's ~2^16 grid
(70 848 hypotheses). ``"region"``: one region on its own (:func:`fit_region`), its 16
best distinct survivors refined in orientation (``refine_orientations``), polished long
and restarted: boxy, rigid objects come back with ε ≈ 0.1 rather than as rounded blobs.
Refined orientations make a single region's fit better (of ``bench_search.py``'s 48
parts within 2% Chamfer: on the paper's grid 92% -> 96%, on the coarse grid 88% -> 96%)
but not a multi-part recovery, whose E moved both ways on a family of scenes and got
worse in sum, so ``"fast"`` does not refine (figures in ``benchmarks/README.md``)."""


def search_preset(name_or_settings) -> SearchSettings:
    """:class:`SearchSettings` from a preset name or a SearchSettings (returned as is)."""
    return lookup_preset(name_or_settings, SearchSettings, SEARCH_PRESETS, "search")


def default_max_size(data: RangeData) -> float:
    """Largest semi-axis searched: a quarter of the figure's largest metric extent."""
    pts = data.camera.points(data.image)[data.figure_mask]
    extent = float(np.max(np.ptp(pts, axis=0)))
    return max(extent / 4.0, 1e-6)


def check_max_size(max_size) -> float:
    """``max_size`` as a float, checked: a finite number > 0 (a string or a bool is none)."""
    number = isinstance(max_size, (int, float, np.integer, np.floating)) and not isinstance(max_size, (bool, np.bool_))
    value = float(max_size) if number else math.nan
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"max_size: got {max_size!r}, expected a finite number > 0")
    return value


def window_for(data: RangeData, max_size: float, *, multiple: int = 8) -> int:
    """Window side (pixels) covering the projected diameter of the largest part."""
    max_size = check_max_size(max_size)
    depth = float(np.nanmedian(data.image[data.figure_mask]))
    pixel = float(np.asarray(data.camera.pixel_size_at(np.float32(depth))))
    limit = min(2 * data.pad, max(data.camera.width, data.camera.height) + multiple)
    side = 2.0 * max_size / pixel * 1.1
    if not side < limit:  # also a max_size so large that the side overflows to inf
        return int(limit)
    side = int(math.ceil(side / multiple) * multiple)
    return int(min(max(side, 16), limit))


# --- regions --------------------------------------------------------------------------


def region_centers(figure, *, spacing: float, method: str = "skeleton", grid_shape=(10, 10)) -> np.ndarray:
    """Region centres (n, 2) as (row, col).

    ``method="skeleton"``: points on the figure's 2-D skeleton (grassfire / medial axis,
    section 4.1, without its thin spurs), thickest first, no two closer than ``spacing``
    pixels. ``"grid"``: a
    ``grid_shape`` lattice over the figure's bounding box (the paper's 10x10), keeping
    points on the figure. ``"both"``: the union.
    """
    from skimage.morphology import medial_axis

    fig = np.asarray(figure, bool)
    if method not in ("skeleton", "grid", "both"):
        raise ValueError(f"method: got {method!r}, expected 'skeleton', 'grid' or 'both'")
    if not (spacing > 0):
        raise ValueError(f"spacing: got {spacing!r}, expected a number > 0")
    centres: list = []
    if method in ("skeleton", "both"):
        from scipy.ndimage import maximum_filter

        # The image's edge bounds the figure: without that border a figure covering the
        # whole image has no background to measure distances from, and no skeleton.
        skel, dist = (a[1:-1, 1:-1] for a in medial_axis(np.pad(fig, 1), return_distance=True, rng=0))
        # Drop spurs (e.g. into corners): keep skeleton pixels at least half as thick as
        # the thickest skeleton pixel within ``spacing``.
        thick = maximum_filter(np.where(skel, dist, 0.0), size=max(int(spacing), 1))
        skel &= dist >= 0.5 * thick
        rows, cols = np.nonzero(skel)
        order = np.argsort(-dist[rows, cols], kind="stable")
        for r, c in zip(rows[order], cols[order]):
            if all((r - a) ** 2 + (c - b) ** 2 >= spacing**2 for a, b in centres):
                centres.append((int(r), int(c)))
    if method in ("grid", "both"):
        rows, cols = np.nonzero(fig)
        for r in np.linspace(rows.min(), rows.max(), grid_shape[0]).round().astype(int):
            for c in np.linspace(cols.min(), cols.max(), grid_shape[1]).round().astype(int):
                if fig[r, c] and all((r - a) ** 2 + (c - b) ** 2 >= (spacing / 2) ** 2 for a, b in centres):
                    centres.append((int(r), int(c)))
    return np.asarray(centres, np.int32).reshape(-1, 2)


# --- posing and scoring ---------------------------------------------------------------


def _frame_from_z(direction):
    """Rotation matrix taking +z onto the unit ``direction`` (JAX, smooth except at -z)."""
    d = direction / jnp.linalg.norm(direction)
    c = jnp.cross(jnp.array([0.0, 0.0, 1.0], d.dtype), d)
    cos = d[2]  # z · d
    k = jnp.array([[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]], [-c[1], c[0], 0.0]], d.dtype)
    return jnp.eye(3, dtype=d.dtype) + k + matmul(k, k) / (1.0 + cos)


def pose_hypothesis(orientation_rel, shape, max_size, ray_origin, ray_direction, surface_t) -> Part:
    """Place one grid hypothesis at a region: orientation relative to the viewing ray,
    centre on the ray behind the measured surface (at ``surface_t``) by the part's own
    half-depth along the ray."""
    view = _frame_from_z(ray_direction)
    rot = matmul(view, rotation_matrix(orientation_rel))
    size = shape[:3] * max_size
    u = matmul(rot.T, ray_direction / jnp.linalg.norm(ray_direction))
    half_depth = 1.0 / jnp.sqrt(jnp.sum((u / size) ** 2))
    t_centre = surface_t + half_depth / jnp.linalg.norm(ray_direction)
    return Part.from_vector(
        jnp.concatenate([ray_origin + t_centre * ray_direction, matrix_to_rotation_vector(rot), size, shape[3:]])
    )


def _region_inputs(depth, figure, camera, pad, corner, centre, frame: int, side, stride=1, centred=False):
    """A region's window: its ``side`` × ``side`` pixels from ``corner`` in a ``frame`` ×
    ``frame`` array (``frame`` >= ``side``; ``side`` may be traced). The frame's pixels
    beyond the window are ``valid`` False and off the figure: windows of several sides
    share one compiled program, each scoring as if cut to its own side. With ``stride``
    (may be traced; a pruning lattice), the array holds the window's pixels at every
    stride-th row and column from stride // 2, ``frame`` of them a side: lattices of
    several strides and sides share one program too, each scoring as its own. With
    ``centred`` (may be traced), the lattice's rows and columns pass through the region's
    ``centre`` instead, a point of the figure's skeleton: the member the region lies on
    is sampled there and along them, however thin it is."""
    p = pad
    if isinstance(stride, int) and stride == 1:
        at_r = at_c = jnp.arange(frame)
        measured = jax.lax.dynamic_slice(depth, (corner[0] + p, corner[1] + p), (frame, frame))
        fig = jax.lax.dynamic_slice(figure, (corner[0] + p, corner[1] + p), (frame, frame))
        start = corner
    else:  # lattice points past the padded image are masked as the frame's are
        phase = jnp.where(centred, (centre - corner) % stride, stride // 2)  # (2,) rows, columns
        at_r, at_c = (phase[k] + stride * jnp.arange(frame) for k in (0, 1))
        rows, cols = (corner[0] + p + at_r)[:, None], (corner[1] + p + at_c)[None, :]
        measured = depth.at[rows, cols].get(mode="fill", fill_value=jnp.nan)
        fig = figure.at[rows, cols].get(mode="fill", fill_value=False)
        start = corner + phase - stride // 2  # camera.rays' lattice starts at stride // 2
    valid = (at_r < side)[:, None] & (at_c < side)[None, :]
    fig = fig & valid
    window = (start[0].astype(jnp.float32), start[1].astype(jnp.float32), frame, frame)
    origins, directions = camera.rays(window, stride=stride)
    c_o, c_d = camera.rays((centre[0].astype(jnp.float32), centre[1].astype(jnp.float32), 1, 1))
    # Depth at the centre: the nearest figure pixel in a 5x5 neighbourhood.
    nb = jax.lax.dynamic_slice(depth, (centre[0] + p - 2, centre[1] + p - 2), (5, 5))
    nbf = jax.lax.dynamic_slice(figure, (centre[0] + p - 2, centre[1] + p - 2), (5, 5))
    surface_t = jnp.nanmin(jnp.where(nbf, nb, jnp.nan))
    return measured, fig, valid, origins, directions, c_o[0, 0], c_d[0, 0], surface_t


def _score_one(part, origins, directions, measured, figure, weight, *, sigma, lam, num_bins, newton_steps, valid=None):
    # The grid search's kernel, run for every hypothesis (``valid``: the rays that count).
    t, hit = cast_part(part, origins, directions, newton_steps)
    if valid is not None:
        hit = hit & valid
    mu, eps, offset, _ = gamma_terms(t, hit, measured, figure, sigma=sigma, num_bins=num_bins, weight=weight)
    return mu - lam * eps, offset


REGION_BUCKET = 16
"""Regions per compiled call of the grid search (:func:`score_regions`): one program
serves any number of regions, and a call's padding regions cost nothing (the loop over
regions stops at the last live one)."""


def _map_regions(fn, region, starts, replicated, out_shape):
    """``fn(r, starts_r, *replicated)`` for each live region ``r`` of ``region`` (R,)
    (-1: padding, which comes last and is not run; zeros there), ``starts`` a tree of (R,
    c) arrays, its chunks' first rows: a loop as long as the live regions, each mapping
    ``fn``'s chunk loops over its own rows of ``starts``. ``out_shape(starts_r)``: the
    tree of ``jax.ShapeDtypeStruct`` that ``fn`` returns (given, not found by tracing
    ``fn`` a second time: that doubled the search programs' tracing). With several
    devices the chunks (axis 1, a multiple of the devices) are sharded over them with
    ``shard_map``."""
    devices = jax.devices()

    def run(starts, region, *r):
        def row(k):
            return jax.tree_util.tree_map(lambda s: s[k], starts)

        one = out_shape(row(0))

        def body(k, out):
            y = fn(region[k], row(k), *r)
            got, want = (jax.tree_util.tree_map(lambda a: (a.shape, a.dtype), t) for t in (y, one))
            if got != want:
                raise TypeError(f"_map_regions: fn returned {got}, expected {want}")
            return jax.tree_util.tree_map(lambda o, y: o.at[k].set(y), out, y)

        out = jax.tree_util.tree_map(lambda s: jnp.zeros((len(region), *s.shape), s.dtype), one)
        return jax.lax.fori_loop(0, jnp.sum(region >= 0), body, out)  # a traced trip count: live regions only

    if len(devices) == 1:
        return run(starts, region, *replicated)
    mesh = Mesh(np.asarray(devices), ("hypotheses",))
    spec_r = jax.tree_util.tree_map(lambda _: P(), replicated)
    return jax.shard_map(
        run,
        mesh=mesh,
        in_specs=(jax.tree_util.tree_map(lambda _: P(None, "hypotheses"), starts), P(), *spec_r),
        out_specs=P(None, "hypotheses"),
        check_vma=False,
    )(starts, region, *replicated)


@persistent_jit(static_argnames=("pad", "lattices", "batches", "newton_steps"))
def _score_hypotheses(
    arrays,
    table,
    region,
    chunks,
    centre,
    max_size,
    stride,
    centred,
    *,
    camera,
    pad,
    lattices,
    batches,
    newton_steps,
):
    """Γ and depth offset p of hypotheses at several regions (the one parallel
    operation), in one or more passes. Pass q is a loop over chunks: ``chunks[q]`` =
    (``first``, ``side``, ``live``), each (R, c): chunk j of region ``region[k]``
    (``centre``: (R, 2); ``max_size``: (R,)) scores ``batches[q]`` rows of ``table`` =
    (``orientation_rel`` (m, 3), ``shape`` (m, 8)) from ``first[k, j]`` on the
    ``side[k, j]`` window centred at the region, at every ``stride``-th pixel (through
    the region's centre when ``centred``), a ``lattices[q]`` × ``lattices[q]`` array of
    them (:func:`_region_inputs`); chunks
    not ``live`` are not scored (zeros). Regions of ``region`` -1 are padding, after the
    live ones, not scored (Γ -inf). The stride, the sides and the chunks are traced:
    searches whose lattices, batches and numbers of chunks agree share the program,
    however their windows and hypotheses fall into its passes. Returns one (Γ, p) pair of
    (R, c, batch) arrays per pass."""
    depth, fig, sigma, lam = arrays
    weight = (stride * stride).astype(jnp.float32)  # each lattice point stands for stride² pixels

    def at_region(r, chunks, table, centre, sigma, lam, max_size, stride, centred):
        orientation_rel, shape = table
        out = []
        for (first, side, live), lattice, batch in zip(chunks, lattices, batches):
            # Each chunk's window, rays and depths cut before the loop over chunks, all at
            # once: cut inside it, XLA fused them into the kernel, recomputing them for
            # every hypothesis (the human's grid search took 2.0 s instead of 1.2-1.6 s).
            inputs = jax.vmap(
                lambda s, lattice=lattice: _region_inputs(
                    depth, fig, camera, pad, centre[r] - s // 2, centre[r], lattice, s, stride, centred
                )
            )(side)

            def body(j, acc, first=first, inputs=inputs, batch=batch):
                measured, figure, valid, origins, directions, c_o, c_d, surface_t = (a[j] for a in inputs)

                def one(o, shp):
                    part = pose_hypothesis(o, shp, max_size[r], c_o, c_d, surface_t)
                    return _score_one(
                        part,
                        origins,
                        directions,
                        measured,
                        figure,
                        weight,
                        sigma=sigma,
                        lam=lam,
                        num_bins=NUM_BINS,
                        newton_steps=newton_steps,
                        valid=valid,
                    )

                def score():
                    rows = (jax.lax.dynamic_slice_in_dim(a, first[j], batch) for a in (orientation_rel, shape))
                    return jax.vmap(one)(*rows)

                g, p = jax.lax.cond(live[j], score, lambda: (jnp.zeros(batch, depth.dtype),) * 2)
                return acc[0].at[j].set(g), acc[1].at[j].set(p)

            empty = jnp.zeros((len(first), batch), depth.dtype)
            # A loop of as many steps as chunks, the dead ones skipped: a loop as long as
            # the live chunks (a traced trip count) took XLA 1-2 s longer to compile.
            out.append(jax.lax.fori_loop(0, len(first), body, (empty, empty)))
        return tuple(out)

    def out_shape(chunks):  # per pass: Γ and p of each chunk's hypotheses
        return tuple((jax.ShapeDtypeStruct((len(f), b), depth.dtype),) * 2 for (f, _, _), b in zip(chunks, batches))

    out = _map_regions(at_region, region, chunks, (table, centre, sigma, lam, max_size, stride, centred), out_shape)
    live = (region >= 0)[:, None, None]
    return tuple((jnp.where(live & jnp.isfinite(gam), gam, -jnp.inf), off) for gam, off in out)


# --- results --------------------------------------------------------------------------


class RegionFit(eqx.Module):
    """The best candidates at one region, best first.

    ``parts`` (batched, k), ``gamma`` (k) Γ of Eq. (4), ``bits_saved`` (k) Eq. (5),
    ``explained`` (k, H, W) pixels each explains within ±σ/2 (full image), ``rendered``
    (k, H, W) bool: pixels each covers, ``commission`` (k, H, W) its errors of commission
    (:func:`~sqparts.commission_mask`); ``ratio`` best Γ / runner-up Γ (the paper's
    factor-of-two test); ``centre`` (row, col); ``corner`` of the window.
    """

    parts: Part
    gamma: jax.Array
    bits_saved: jax.Array
    explained: jax.Array
    rendered: jax.Array
    commission: jax.Array
    ratio: float = eqx.field(static=True)
    centre: tuple = eqx.field(static=True)
    corner: tuple = eqx.field(static=True)


def score_regions(
    data: RangeData, settings: SearchSettings, centres, *, hypotheses=None, stride: int | None = None, max_sizes=None
) -> tuple[np.ndarray, np.ndarray]:
    """Γ and offset p of hypotheses at each region centred at ``centres`` (r, 2) (row,
    col), at ``stride`` (None: the pruning lattice): every grid hypothesis
    (``hypotheses`` None), the same set at every region (a dict of (n, 3) relative
    ``"orientation"`` and (n, 8) ``"shape"``) or one set per region ((r, n, 3) and (r,
    n, 8)); ``max_sizes`` (r,) replaces ``settings.max_size`` per region. All regions'
    hypotheses go through one compiled program, in chunks (``settings.batch_size`` at
    most, about :data:`CHUNK_RAYS` rays a chunk), :data:`REGION_BUCKET` regions a call; a
    set shared by the regions is passed once. Returns (r, n) host arrays."""
    hyp = hypotheses or _grid_arrays(settings.grid)
    return _score_passes(
        data, settings, centres, [(settings.side, hyp)], stride=stride, max_sizes=max_sizes, frame=settings.frame_side
    )[0]


def _score_passes(
    data: RangeData,
    settings: SearchSettings,
    centres,
    passes,
    *,
    stride: int | None = None,
    max_sizes=None,
    frame: int | None = None,
    program: _Program | None = None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """:func:`score_regions` of several sets of hypotheses, each on its own window:
    ``passes`` = [(window side, hypotheses)], all in the same compiled calls, each window
    at the ``stride`` on its own lattice (computed in a ``frame`` × ``frame`` array at
    stride 1; None: its own side). The windows go to the passes of ``program`` (None:
    one per distinct lattice, :meth:`_Program.exact`), each to the one of the fewest
    points that holds its lattice, the points beyond it masked: it scores as on its own.
    Returns one (Γ, p) pair of (r, n) host arrays per window."""
    centres = np.asarray(centres, np.int32).reshape(-1, 2)
    r = len(centres)
    sizes = np.full(r, settings.max_size, np.float32) if max_sizes is None else np.asarray(max_sizes, np.float32)
    stride = stride or settings.lattice
    devices = len(jax.devices())
    own = [_lattice_side(frame or side, stride) for side, _ in passes]
    counts = [int(np.shape(hyp["orientation"])[-2]) for _, hyp in passes]
    program = program or _Program.exact(own, counts, settings.batch_size, devices)
    route = [program.route(lattice) for lattice in own]
    table, chunks = program.layout(passes, route, counts, devices)
    shared = table[0].ndim == 2  # one set of hypotheses for every region
    out = [(np.empty((r, n), np.float32), np.empty((r, n), np.float32)) for n in counts]
    for start in range(0, r, REGION_BUCKET):
        rows = np.arange(start, min(r, start + REGION_BUCKET))
        m = len(rows)
        region = np.where(np.arange(REGION_BUCKET) < m, np.arange(REGION_BUCKET), -1).astype(np.int32)

        def bucket(a, fill: float = 0.0):
            out = np.full((REGION_BUCKET, *a.shape[1:]), fill, a.dtype)
            out[:m] = a[rows]
            return out

        if shared:
            sets, own_rows = table, np.zeros((REGION_BUCKET, 1), np.int32)
        else:  # region k's set at rows k·program.rows: the padding regions get the first's
            picked = np.concatenate([rows, np.full(REGION_BUCKET - m, rows[0])])
            sets = tuple(a[picked].reshape(-1, a.shape[-1]) for a in table)
            own_rows = (np.arange(REGION_BUCKET) * program.rows)[:, None].astype(np.int32)
        scored = _score_hypotheses(
            data.arrays,
            sets,
            region,
            tuple(
                (
                    first[None] + own_rows,
                    np.repeat(side[None], REGION_BUCKET, 0),
                    np.repeat(live[None], REGION_BUCKET, 0),
                )
                for first, side, live, _ in chunks
            ),
            bucket(centres),
            bucket(sizes, 1.0),
            np.int32(stride),
            np.bool_(settings.centred),
            camera=data.compiled_camera,
            pad=data.pad,
            lattices=program.lattices,
            batches=program.batches,
            newton_steps=settings.newton_steps,
        )
        results = [(np.asarray(g), np.asarray(p)) for g, p in scored]
        for k, (n, q) in enumerate(zip(counts, route)):
            g, p = results[q]
            at = chunks[q][3][k]  # this window's chunks, in order
            out[k][0][rows] = g[:m, at].reshape(m, -1)[:, :n]
            out[k][1][rows] = p[:m, at].reshape(m, -1)[:, :n]
    return out


def _lattice_side(side: int, stride: int) -> int:
    """Points a side of a ``side``-pixel window's lattice at ``stride`` (every
    stride-th pixel from stride // 2)."""
    return len(range(int(stride) // 2, int(side), int(stride)))


def _chunking(n: int, lattice: int, batch_size: int, devices: int) -> tuple[int, int]:
    """(batch, chunks) for ``n`` hypotheses on a ``lattice``² array: chunks of about
    :data:`CHUNK_RAYS` rays (temporaries stay in cache; one huge vmap is slower), at
    most ``batch_size`` hypotheses, as few as that allows with the least padding, a
    multiple of ``devices``."""
    cap = int(max(1, min(batch_size, CHUNK_RAYS // lattice**2)))
    batch = -(-n // (-(-n // (cap * devices)) * devices))
    return batch, int(math.ceil(n / (batch * devices)) * devices)


@dataclasses.dataclass(frozen=True)
class _Program:
    """The passes of a compiled call of :func:`_score_hypotheses`: each pass's lattice
    (points a side), ``batches`` (hypotheses a chunk) and ``chunks`` (per region); ``rows``
    of the table per set of hypotheses. Windows go to passes (:meth:`route`), so
    searches whose windows and hypotheses differ share a program."""

    lattices: tuple[int, ...]
    batches: tuple[int, ...]
    chunks: tuple[int, ...]
    rows: int

    @classmethod
    def exact(cls, lattices, counts, batch_size: int, devices: int) -> _Program:
        """A pass per distinct lattice of the windows (``lattices``, with ``counts``
        hypotheses each), just holding their hypotheses."""
        passes = sorted(set(lattices))
        batches, chunks, rows = [], [], 0
        for lattice in passes:
            mine = [n for own, n in zip(lattices, counts) if own == lattice]
            batch, _ = _chunking(sum(mine), lattice, batch_size, devices)
            used = sum(-(-n // batch) for n in mine)
            batches.append(batch)
            chunks.append(-(-used // devices) * devices)
            rows += used * batch
        return cls(tuple(passes), tuple(batches), tuple(chunks), rows)

    @classmethod
    def shared(cls, lattices, grid: Grid, batch_size: int, devices: int) -> _Program:
        """Passes of ``lattices``, each with room for all of ``grid``'s hypotheses
        (chunks as for one length's), whatever windows a search's lengths fall into."""
        total, lengths = grid.size, len(grid.lengths)
        batches = [_chunking(total // lengths, lattice, batch_size, devices)[0] for lattice in lattices]
        chunks = [-(-(-(-total // b) + lengths) // devices) * devices for b in batches]
        return cls(tuple(int(x) for x in lattices), tuple(batches), tuple(chunks), total + lengths * max(batches))

    def route(self, lattice: int) -> int:
        """The pass of the fewest points that holds a window's ``lattice``."""
        fits = [q for q, points in enumerate(self.lattices) if points >= lattice]
        if not fits:
            raise ValueError(
                f"lattices: got {self.lattices}, expected one of at least {lattice} points (a window's own)"
            )
        return min(fits, key=lambda q: self.lattices[q])

    def layout(self, passes, route, counts, devices: int):
        """The table ((sets, rows, 3) and (sets, rows, 8); sets = 1 when the regions share
        the hypotheses, (rows, ...) then) and, per pass, (first row, side, live) of each
        of its chunks, and for each window its chunks' places: a window's hypotheses in
        consecutive chunks, the live chunks spread evenly over the devices' shares."""
        blocks, logical, at = ([], []), [[] for _ in self.lattices], 0
        for k, ((side, hyp), q, n) in enumerate(zip(passes, route, counts)):
            batch = self.batches[q]
            padded = -(-n // batch) * batch
            for out, name in zip(blocks, ("orientation", "shape")):
                a = np.asarray(hyp[name], np.float32)
                a = a.reshape(-1, n, a.shape[-1])
                out.append(np.concatenate([a, np.repeat(a[:, :1], padded - n, axis=1)], axis=1))
            logical[q] += [(at + i * batch, int(side), k) for i in range(padded // batch)]
            at += padded
        if at > self.rows or any(len(c) > n for c, n in zip(logical, self.chunks)):
            raise ValueError(
                f"passes: got {at} rows in {[len(c) for c in logical]} chunks, expected at most {self.rows} in {self.chunks}"
            )
        table = []
        for parts in blocks:
            a = np.concatenate(parts, axis=1)
            a = np.concatenate([a, np.repeat(a[:, :1], self.rows - at, axis=1)], axis=1)
            table.append(a[0] if np.ndim(passes[0][1]["orientation"]) == 2 else a)
        chunks = []
        for c, todo in zip(self.chunks, logical):
            per = c // devices
            place = np.array([(j % devices) * per + j // devices for j in range(len(todo))], np.int64)
            first, side, live = np.zeros(c, np.int32), np.full(c, 16, np.int32), np.zeros(c, bool)
            first[place] = [f for f, _, _ in todo]
            side[place] = [s for _, s, _ in todo]
            live[place] = True
            owner = np.array([k for _, _, k in todo], np.int64)
            chunks.append((first, side, live, {k: place[owner == k] for k in set(owner.tolist())}))
        return tuple(table), chunks


def score_region(data: RangeData, settings: SearchSettings, centre, *, hypotheses=None, stride: int | None = None):
    """Γ and offset p of every grid hypothesis (or of ``hypotheses``) at ``centre`` (row,
    col), at ``stride``: :func:`score_regions` of one region."""
    gam, off = score_regions(data, settings, [centre], hypotheses=hypotheses, stride=stride)
    return jax.device_put(gam[0]), jax.device_put(off[0])


@functools.lru_cache(maxsize=8)
def _grid_arrays(grid: Grid) -> dict:
    return grid.hypotheses()


@functools.lru_cache(maxsize=8)
def _by_window(grid: Grid, window: int, *, multiple: int = 8) -> list[tuple[int, np.ndarray]]:
    """The grid's hypotheses grouped by the window side that covers them: length (a3 as a
    fraction of ``max_size``) × ``window``, rounded up to a multiple of 8 (at least 16,
    at most ``window``); lengths whose sides agree form one group. A part posed at a
    region projects around the region's centre, so the pruning pass scores a short
    hypothesis on a smaller window with the same Γ (human, coarse grid: 24, 40 and 64
    pixels; half the rays), all the windows in one compiled call (:func:`_score_passes`),
    a pass per side."""
    rel = _grid_arrays(grid)["shape"][:, 2]
    sides = np.array([int(min(window, max(16, math.ceil(x * window / multiple) * multiple))) for x in rel])
    return [(int(side), np.flatnonzero(sides == side)) for side in np.unique(sides)]


def _restart_starts(part: Part, levels: int) -> Part:
    """Restarts for a polished part: its three cyclic relabellings of the local axes
    (which axis is z decides which squareness is ε1 and where a bend can act) times a
    ``levels`` × ``levels`` grid of squareness values ((i + ½) · 2 / levels), with bend and
    taper reset to zero. Polishing converges to the nearest minimum; these starts reach
    the minima a near-symmetric part or a wrong squareness hides. Returns a batch of
    ``3 levels²`` parts (host arrays)."""
    from scipy.spatial.transform import Rotation

    v = part_vectors(part)[0]
    rot = Rotation.from_rotvec(v[3:6].astype(np.float64)).as_matrix()  # = rotation_matrix, on the host
    sq = (np.arange(levels) + 0.5) * 2.0 / levels
    sq = np.stack(np.meshgrid(sq, sq, indexing="ij"), -1).reshape(-1, 2)
    starts = []
    for k in range(3):
        idx = [(k + i) % 3 for i in range(3)]
        relabelled = np.concatenate(
            [v[:3], Rotation.from_matrix(rot[:, idx]).as_rotvec(), v[6:9][idx], [0, 0, 0, 0, 0]]
        )
        out = np.tile(relabelled, (len(sq), 1))
        out[:, 9:11] = sq
        starts.append(out)
    return host_parts(np.concatenate(starts))


@persistent_jit(static_argnames=("pad", "frame", "newton_steps"))
def _score_candidates(
    arrays,
    vectors,
    orientation_rel,
    shape,
    offsets,
    posed,
    corner,
    centre,
    max_size,
    side,
    *,
    camera,
    pad,
    frame,
    newton_steps,
):
    """Score a batch of candidates at full resolution, each over its own region's
    ``side`` × ``side`` window (``corner``, ``centre``: (n, 2)), computed in a ``frame`` ×
    ``frame`` array (:func:`_region_inputs`; the masks returned are the frame's). Where
    ``posed``, candidate i is the hypothesis (``orientation_rel``, ``shape``) posed at its
    region and moved by -``offsets`` in depth along the region's centre ray (the peak of
    its Γ histogram); elsewhere it is the part ``vectors[i]``.

    Returns the parts' vectors, Γ, the window masks explained/rendered/commission, and
    ``anchored``: whether the part explains a pixel within one of the region's centre. A
    part belongs to the region it was posed at (the paper's hypotheses pass through the
    region's centre), so a polish that walks onto a neighbour is not kept, and
    unanchored candidates rank last.
    """
    depth, fig, sigma, lam = arrays
    c = side // 2

    def one(vector, o, s, p, posed, corner, centre, max_size):
        measured, figure, valid, origins, directions, c_o, c_d, surface_t = _region_inputs(
            depth, fig, camera, pad, corner, centre, frame, side
        )
        hypothesis = pose_hypothesis(o, s, max_size, c_o, c_d, surface_t).to_vector().at[:3].add(-p * c_d)
        part = Part.from_vector(jnp.where(posed, hypothesis, vector))
        t, hit = cast_part(part, origins, directions, newton_steps)
        hit = hit & valid
        mu, eps, off, explained = gamma_terms(t, hit, measured, figure, sigma=sigma, num_bins=NUM_BINS)
        explained = explained.reshape(hit.shape)
        commission = commission_mask(hit, t, measured, figure, off + sigma / 2)
        anchored = jnp.any(jax.lax.dynamic_slice(explained, (c - 1, c - 1), (3, 3)))
        return part.to_vector(), mu - lam * eps, explained, hit, commission, anchored

    return jax.vmap(one)(vectors, orientation_rel, shape, offsets, posed, corner, centre, max_size)


class _Chosen(eqx.Module):
    """A region's hypotheses worth a full-resolution look, best first (host arrays)."""

    orientation: np.ndarray  # (k, 3) relative to the viewing ray
    shape: np.ndarray  # (k, 8): the grid's shape columns
    offset: np.ndarray  # (k,) Γ's peak offset p
    ratio: float  # best Γ / runner-up Γ
    max_size: float


_CHOSEN = RowMemo(4 << 20)
"""Each region's chosen hypotheses by image, settings and centre (see
:class:`~sqparts._compile.RowMemo`): filling gaps searches a blob again on each pass and
in each alternative while the blob is unchanged."""


@once_per_image
def _image_key(data: RangeData) -> bytes:
    """Digest of what a region's search reads of the image (hashed once per image)."""
    return RowMemo.key(np.asarray(data.depth), np.asarray(data.figure), data.pad, data.camera, data.encoding)


def _choose_all(data: RangeData, settings: SearchSettings, centres, sizes, *, progress=None) -> list[_Chosen]:
    """Score every hypothesis at each region (centres (r, 2), largest semi-axes ``sizes``
    (r,); on a subsample when ``prune``), rescore the survivors and their orientation
    neighbours at full resolution and keep each region's ``max(top_k,
    polish_candidates)`` best distinct ones (:func:`_choose_rows`): the regions in
    :func:`~sqparts._compile.balanced_groups` of at most :data:`REGION_BUCKET`, run
    :func:`~sqparts._compile.concurrently` (``progress`` wraps the regions, each counted
    when its group is done). A region chosen
    before in this recovery is looked up (:data:`_CHOSEN`)."""
    per_region = [dataclasses.replace(settings, max_size=float(m)) for m in sizes]
    keys = [RowMemo.key(_image_key(data), st, tuple(int(c) for c in centre)) for st, centre in zip(per_region, centres)]
    known = {i: row for i, k in enumerate(keys) if (row := _CHOSEN.get(k)) is not None}
    todo = np.array([i for i in range(len(keys)) if i not in known], np.int64)
    groups = [todo[g] for g in balanced_groups(len(todo), REGION_BUCKET)]

    wrap = progress or (lambda it: it)

    def by_region(calls):
        """The groups' calls as :func:`concurrently` waits for them, ``progress``
        ticking once per region of each call done."""
        ticks = iter(wrap(range(len(todo))))
        for group, call in zip(groups, calls):
            yield call
            for _ in group:
                next(ticks, None)
        for _ in ticks:
            pass

    done = concurrently(
        lambda g: _choose_rows(data, settings, centres[g], sizes[g]), groups, progress=by_region if progress else None
    )
    for group, out in zip(groups, done):
        for i, row in zip(group, out):
            known[int(i)] = row
            _CHOSEN.put(keys[i], row)
    chosen = []
    for i, size in enumerate(sizes):
        row = known[i]
        table = row[:-1].reshape(-1, 12)
        chosen.append(
            _Chosen(
                table[:, :3].astype(np.float32),
                table[:, 3:11].astype(np.float32),
                table[:, 11].astype(np.float32),
                float(row[-1]),
                float(size),
            )
        )
    return chosen


def _orientation_neighbours(orientation: np.ndarray, step: float) -> np.ndarray:
    """(6n, 3): each of the (n, 3) relative orientations (rotation vectors) turned by
    ``step`` radians about each of its own three axes, one way (x, y, z) then the other
    (tilting the longest axis two ways, and rolling about it): the next finer orientations
    around a coarse grid's hypothesis, and refinement's steps in orientation
    (:class:`~sqparts._refine.SettleParts`). Section 3.3.2 finds Γ relatively sensitive
    to orientation (10-15 degrees take it to two-thirds of its peak, where sizes may
    change by 50%), so this is where a coarse grid's next level pays."""
    from scipy.spatial.transform import Rotation

    base = np.repeat(np.asarray(orientation, np.float64).reshape(-1, 3), 6, axis=0)
    turns = np.tile(np.concatenate([np.eye(3), -np.eye(3)]) * step, (len(base) // 6, 1))
    return (Rotation.from_rotvec(base) * Rotation.from_rotvec(turns)).as_rotvec()


def _choose_rows(data: RangeData, settings: SearchSettings, centres, sizes) -> list[np.ndarray]:
    """:func:`_choose_all`'s work for some regions, each region's result as one row
    (float64): per chosen hypothesis its orientation (3), shape (8) and offset (1), then
    the ratio. Every stage scores all the regions together (:func:`score_regions`)."""
    hyp = _grid_arrays(settings.grid)
    n = len(hyp["orientation"])
    r = len(centres)
    grid: Grid = settings.grid  # pyright: ignore[reportAssignmentType]  # resolved in __post_init__
    step = min(grid.axis_step, grid.roll_step) / 2
    more = 6 * settings.refine_orientations  # most orientation neighbours a region gets

    def with_neighbours(pool: dict, order: np.ndarray) -> dict:
        """The pool and, after it, its ``refine_orientations`` best distinct members
        (``order``: best first) turned by half the grid's step."""
        best = order[_distinct(pool["orientation"][order], pool["shape"][order], settings.refine_orientations)]
        turned = {
            "orientation": _orientation_neighbours(pool["orientation"][best], math.radians(step)).astype(np.float32),
            "shape": np.repeat(pool["shape"][best], 6, axis=0),
        }
        return {k: np.concatenate([pool[k], turned[k]]) for k in pool}

    def stacked(pools: list[dict], size: int) -> dict:
        """The regions' pools as (r, size, ...) arrays, each padded with its first row:
        every call has the same shapes (one program), and the padding is not read."""
        return {
            k: np.stack([np.concatenate([p[k], np.repeat(p[k][:1], size - len(p[k]), 0)]) for p in pools]) for k in hyp
        }

    grid_hypotheses = n  # the pools' first rows: the ratio is the grid's own
    if settings.prune and settings.lattice > 1 and settings.survivors < n:
        gam = np.empty((r, n), np.float32)
        windows = _by_window(settings.grid, settings.window)
        passes = [(side, {k: v[sel] for k, v in hyp.items()}) for side, sel in windows]
        scored = _score_passes(data, settings, centres, passes, max_sizes=sizes, program=settings.pruning_program())
        for (_, sel), (g, _) in zip(windows, scored):
            gam[:, sel] = g
        keep = np.argsort(-gam, axis=1, kind="stable")[:, : settings.survivors]
        pools = [{k: v[kept] for k, v in hyp.items()} for kept in keep]
        grid_hypotheses = keep.shape[1]
        if settings.refine_orientations:  # scored in the same full-resolution call
            pools = [with_neighbours(p, np.arange(grid_hypotheses)) for p in pools]
        gam_full, off_full = score_regions(
            data, settings, centres, hypotheses=stacked(pools, grid_hypotheses + more), stride=1, max_sizes=sizes
        )
    else:
        gam_full, off_full = score_regions(data, settings, centres, stride=1, max_sizes=sizes)
        pools = [hyp] * r
        if settings.refine_orientations:
            pools = [with_neighbours(hyp, np.argsort(-g, kind="stable")) for g in gam_full]
            g, o = score_regions(
                data,
                settings,
                centres,
                hypotheses=stacked([{k: v[n:] for k, v in p.items()} for p in pools], more),
                stride=1,
                max_sizes=sizes,
            )
            gam_full, off_full = np.concatenate([gam_full, g], axis=1), np.concatenate([off_full, o], axis=1)
    rows = []
    for pool, gam_all, off_all in zip(pools, gam_full, off_full):
        gam_r, off_r = gam_all[: len(pool["orientation"])], off_all[: len(pool["orientation"])]
        k = min(settings.top_k, len(gam_r))
        ranked = np.argsort(-gam_r, kind="stable")
        # Best Γ over the runner-up among the grid's hypotheses (a refined neighbour of
        # the best is not a rival to it).
        g_sorted = np.sort(gam_r[:grid_hypotheses])[::-1]
        ratio = float(g_sorted[0] / g_sorted[1]) if k > 1 and g_sorted[1] > 0 else float("inf")
        best = ranked[_distinct(pool["orientation"][ranked], pool["shape"][ranked], max(k, settings.polish_candidates))]
        table = np.concatenate([pool["orientation"][best], pool["shape"][best], off_r[best, None]], axis=1)
        rows.append(np.concatenate([table.reshape(-1), [ratio]]).astype(np.float64))
    return rows


class _Scored(eqx.Module):
    """Candidates scored over their regions' windows (host arrays, see
    :func:`_score_candidates`); ``region`` (n,) indexes the regions."""

    vectors: np.ndarray
    gamma: np.ndarray
    explained: np.ndarray
    rendered: np.ndarray
    commission: np.ndarray
    anchored: np.ndarray
    region: np.ndarray

    def take(self, index) -> _Scored:
        return jax.tree_util.tree_map(lambda a: a[index], self)

    def where(self, better, other: _Scored) -> _Scored:
        pick = lambda a, b: np.where(better.reshape((-1,) + (1,) * (a.ndim - 1)), a, b)  # noqa: E731
        return jax.tree_util.tree_map(pick, self, other)

    def seeds(self, corners, shape) -> np.ndarray:
        """(n, H, W): each candidate's explained pixels in the image."""
        return np.concatenate([_to_image(m[None], corners[r], shape) for m, r in zip(self.explained, self.region)])


def _score(
    data: RangeData, settings: SearchSettings, corners, centres, region, *, vectors=None, chosen=None
) -> _Scored:
    """:func:`_score_candidates` on the host: the parts ``vectors`` (n, 14), or the chosen
    hypotheses (a list of :class:`_Chosen`, one per region), ``region`` (n,) giving each
    candidate's region; ``PART_BUCKET`` candidates per compiled call, so one compilation
    serves any number of regions and candidates."""
    n = len(region)
    m = -(-n // PART_BUCKET) * PART_BUCKET
    rows = np.concatenate([region, np.full(m - n, region[0] if n else 0)]).astype(np.int64)
    if chosen is not None:
        hyp = [np.concatenate([getattr(c, name) for c in chosen]) for name in ("orientation", "shape", "offset")]
        hyp = [pad_rows(a.astype(np.float32), m) for a in hyp]
        hyp[1][n:] = hyp[1][0] if n else 1.0  # padding stays a valid hypothesis
        vec, posed = np.zeros((m, 14), np.float32), np.ones(m, bool)
        max_size = np.array([c.max_size for c in chosen], np.float32)[rows]
    else:
        vec = part_vectors(pad_parts(host_parts(vectors))[0])
        hyp = [
            np.zeros((m, 3), np.float32),
            np.tile(_grid_arrays(settings.grid)["shape"][:1], (m, 1)),
            np.zeros(m, np.float32),
        ]
        posed, max_size = np.zeros(m, bool), np.ones(m, np.float32)
    corner, centre = np.asarray(corners, np.int32)[rows], np.asarray(centres, np.int32)[rows]

    def bucket(k):
        b = slice(k, k + PART_BUCKET)
        orientation, shp, offset = (a[b] for a in hyp)
        out = _score_candidates(
            data.arrays,
            vec[b],
            orientation,
            shp,
            offset,
            posed[b],
            corner[b],
            centre[b],
            max_size[b],
            np.int32(settings.side),
            camera=data.compiled_camera,
            pad=data.pad,
            frame=settings.frame_side,
            newton_steps=SEARCH_NEWTON_STEPS + 2,
        )
        return [np.asarray(a) for a in out]

    w = settings.side
    vectors, gam, explained, rendered, commission, anchored = (
        np.concatenate(a)[:n] for a in zip(*concurrently(bucket, range(0, m, PART_BUCKET)))
    )
    explained, rendered, commission = (np.ascontiguousarray(a[:, :w, :w]) for a in (explained, rendered, commission))
    return _Scored(vectors, gam, explained, rendered, commission, anchored, np.asarray(region, np.int64))


def fit_regions(
    data: RangeData, settings: SearchSettings, centres, *, max_sizes=None, progress=None
) -> list[RegionFit]:
    """The best ``top_k`` parts at each region (``centres`` (n, 2) row, col), every
    region's candidates batched together after the grid search.

    At each region the grid is scored (:func:`_choose_all`, all regions together);
    then all regions' chosen
    hypotheses are posed and scored at full resolution together, polished together by
    region growing (:func:`~sqparts._polish.grow_parts`, ``polish_rounds`` ×
    ``polish_steps``), and each polished part is kept where it stays at its region and its
    Γ improves; with ``restarts``, each region's best polished part is restarted
    (:func:`_restart_starts`) and polished again. ``max_sizes`` (n,) replaces
    ``settings.max_size`` per region (the window stays ``settings.window``); ``progress``
    wraps the regions' grid searches (e.g. ``tqdm.tqdm``)."""
    centres = np.asarray(centres, np.int32).reshape(-1, 2)
    if max_sizes is None:
        sizes = [settings.max_size] * len(centres)
    else:
        sizes = [check_max_size(float(s)) for s in max_sizes]
    if len(sizes) != len(centres):
        raise ValueError(f"max_sizes: got {len(sizes)} sizes, expected {len(centres)} (one per centre)")
    if not len(centres):
        return []
    corners = centres - np.int32(settings.side // 2)
    chosen = _choose_all(data, settings, centres, np.asarray(sizes, np.float64), progress=progress)
    region = np.concatenate([np.full(len(c.offset), i) for i, c in enumerate(chosen)]).astype(np.int64)
    shape = (data.camera.height, data.camera.width)
    scored = _score(data, settings, corners, centres, region, chosen=chosen)
    if settings.polish_steps > 0 and settings.polish_rounds > 0 and len(region):

        def polished(candidates: _Scored) -> _Scored:
            grown = grow_parts(
                host_parts(candidates.vectors),
                data,
                candidates.seeds(corners, shape),
                rounds=settings.polish_rounds,
                steps=settings.polish_steps,
            )
            return _score(data, settings, corners, centres, candidates.region, vectors=part_vectors(grown))

        new = polished(scored)
        # A polished part is kept only if it stays at its region and its Γ improves.
        better = new.anchored & ((new.gamma > scored.gamma) | ~scored.anchored)
        scored = new.where(better, scored)
        if settings.restarts > 0:
            key = np.where(scored.anchored, scored.gamma, -np.inf)  # each region's best anchored part
            best = [
                int(i[np.argmax(key[i])]) for i in (np.flatnonzero(scored.region == r) for r in range(len(centres)))
            ]
            starts = [_restart_starts(host_parts(scored.vectors[b : b + 1]), settings.restarts) for b in best]
            seeds = scored.take(np.repeat(best, [len(s) for s in starts]))
            seeds = dataclasses.replace(seeds, vectors=np.concatenate([part_vectors(s) for s in starts]))
            more = polished(seeds)
            scored = jax.tree_util.tree_map(lambda a, b: np.concatenate([a, b]), scored, more)
    fits = []
    for r, (centre, corner) in enumerate(zip(centres, corners)):
        mine = scored.take(np.flatnonzero(scored.region == r))
        k = min(settings.top_k, len(mine.gamma))
        order = np.lexsort((-mine.gamma, ~mine.anchored))[:k]  # anchored first, then by Γ
        mine = mine.take(order)
        gam = mine.gamma
        fits.append(
            RegionFit(
                parts=host_parts(mine.vectors),
                gamma=jax.device_put(gam),
                bits_saved=jax.device_put(np.asarray(data.encoding.bits_saved(gam))),
                explained=jax.device_put(_to_image(mine.explained, corner, shape)),
                rendered=jax.device_put(_to_image(mine.rendered, corner, shape)),
                commission=jax.device_put(_to_image(mine.commission, corner, shape)),
                ratio=chosen[r].ratio,
                centre=tuple(int(x) for x in centre),
                corner=tuple(int(x) for x in corner),
            )
        )
    return fits


def fit_region(data: RangeData, settings: SearchSettings, centre) -> RegionFit:
    """The best ``top_k`` parts at one region (:func:`fit_regions` of one centre)."""
    return fit_regions(data, settings, [centre])[0]


def _distinct(
    orientation, shape, n: int, *, angle: float = 30.0, log_size: float = 0.3, squareness: float = 0.5
) -> np.ndarray:
    """Indices of up to ``n`` of the (best-first) hypotheses, skipping near-duplicates of
    those already taken (axes within ``angle`` degrees, every size within a factor
    e^``log_size`` and both squareness values within ``squareness``), so the polished
    starts are diverse; padded with the best skipped ones if too few are distinct."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_rotvec(np.asarray(orientation, np.float64)).as_matrix()  # = rotation_matrix, on the host
    logs, sq = np.log(shape[:, :3]), shape[:, 3:5]
    cos_max = math.cos(math.radians(angle))
    taken: list[int] = []
    for i in range(len(shape)):
        if len(taken) == n:
            break
        dup = any(
            (np.trace(rot[i].T @ rot[j]) - 1) / 2 > cos_max
            and np.max(np.abs(logs[i] - logs[j])) < log_size
            and np.max(np.abs(sq[i] - sq[j])) < squareness
            for j in taken
        )
        if not dup:
            taken.append(i)
    rest = [i for i in range(len(shape)) if i not in taken]
    return np.asarray((taken + rest)[:n], np.int64)


def _to_image(masks, corner, shape) -> np.ndarray:
    """Paste (k, win, win) window masks into (k, H, W) image masks."""
    k, win = masks.shape[0], masks.shape[1]
    out = np.zeros((k,) + tuple(shape), bool)
    r0, c0 = int(corner[0]), int(corner[1])
    rs, cs = max(r0, 0), max(c0, 0)
    re, ce = min(r0 + win, shape[0]), min(c0 + win, shape[1])
    if re > rs and ce > cs:
        out[:, rs:re, cs:ce] = masks[:, rs - r0 : re - r0, cs - c0 : ce - c0]
    return out


def make_settings(data: RangeData, base="region", **fields) -> SearchSettings:
    """The preset (or settings) ``base`` with ``fields`` replaced, resolved on ``data``
    (:meth:`SearchSettings.resolve`)."""
    return dataclasses.replace(search_preset(base), **fields).resolve(data)


def fit_image(
    depth,
    camera: Camera,
    search: SearchSettings | str = "region",
    *,
    figure=None,
    encoding: Encoding | None = None,
    centres=None,
    progress=None,
) -> tuple[list[RegionFit], RangeData, SearchSettings]:
    """Fit every region of a range image (section 3.3) with ``search`` (a
    :class:`SearchSettings` or preset name): returns the region fits, the prepared data and
    the resolved settings. ``centres`` (n, 2) replaces the regions' centres;
    ``progress`` wraps the region iterator (e.g. ``tqdm.tqdm``)."""
    if progress is not None and not callable(progress):
        raise TypeError(f"progress: got {type(progress).__name__}, expected a callable wrapping an iterable or None")
    data = prepare(depth, camera, figure=figure, encoding=encoding)
    settings = search_preset(search).resolve(data)
    if centres is not None:
        given = np.asarray(centres)
        if given.ndim != 2 or given.shape[1] != 2 or not np.issubdtype(given.dtype, np.number):
            raise ValueError(f"centres: got shape {given.shape} of {given.dtype}, expected (n, 2) pixel (row, col)")
        h, w = data.figure_mask.shape
        inside = np.isfinite(given).all(1) & (given >= 0).all(1) & (given[:, 0] < h) & (given[:, 1] < w)
        if not len(given) or not inside.all():
            bad = given[~inside][:1].tolist() if len(given) else "none"
            raise ValueError(f"centres: got {bad}, expected at least one (row, col) inside the {w}x{h} image")
    if centres is None:
        px = settings.side / 2.2
        spacing = settings.spacing or max(3.0, px / 3)
        centres = region_centers(data.figure_region, spacing=spacing, method=settings.region_method)
    return fit_regions(data, settings, centres, progress=progress), data, settings


# --- the expanding grid method (Appendix) ----------------------------------------------


@functools.partial(jax.jit, static_argnames=("num_bins",))
def _gamma_of_vectors(vecs, origins, directions, measured, figure, sigma, lam, *, num_bins):
    """Γ over the whole image for each 14-vector of ``vecs``: one program for every
    profile of the same length (the image and encoding are arguments, not constants)."""

    def one(v):
        g, _ = _score_one(
            Part.from_vector(v),
            origins,
            directions,
            measured,
            figure,
            None,
            sigma=sigma,
            lam=lam,
            num_bins=num_bins,
            newton_steps=DEFAULT_NEWTON_STEPS,
        )
        return g

    return jax.lax.map(one, vecs, batch_size=16)


def gamma_profile(data: RangeData, part: Part, parameter: int, offsets, *, num_bins: int | None = None) -> np.ndarray:
    """Γ over the whole image as parameter ``parameter`` (index into the 14-vector) of
    ``part`` moves by each of ``offsets`` (Figure 6c). Invalid parts get -inf."""
    o, d = camera_rays(data.camera)
    p = data.pad
    h, w = data.camera.height, data.camera.width
    measured, figure = data.depth[p : p + h, p : p + w], data.figure[p : p + h, p : p + w]
    enc = data.encoding
    vecs = np.asarray(part.to_vector(), np.float32)[None].repeat(len(offsets), 0)
    vecs[:, parameter] += np.asarray(offsets, np.float32)
    out = _gamma_of_vectors(
        jnp.asarray(vecs),
        o,
        d,
        measured,
        figure,
        jnp.float32(enc.sigma),
        jnp.float32(enc.commission_weight),
        num_bins=num_bins or NUM_BINS,
    )
    return np.where(_valid_vectors(vecs), np.asarray(out, np.float64), -np.inf)


def _valid_vectors(vecs: np.ndarray) -> np.ndarray:
    from ._part import BEND_RANGE, SQUARENESS_RANGE, TAPER_RANGE

    return (
        np.all(vecs[:, 6:9] > 0, 1)
        & np.all((vecs[:, 9:11] >= SQUARENESS_RANGE[0]) & (vecs[:, 9:11] <= SQUARENESS_RANGE[1]), 1)
        & np.all((vecs[:, 11:13] >= BEND_RANGE[0]) & (vecs[:, 11:13] <= BEND_RANGE[1]), 1)
        & (vecs[:, 13] >= TAPER_RANGE[0])
        & (vecs[:, 13] <= TAPER_RANGE[1])
    )


def convex_width(offsets, profile, *, fraction: float = 2.0 / 3.0) -> tuple[float, float]:
    """(left, right) distance from the best offset to where Γ first falls below
    ``fraction`` of its best (linear interpolation); inf if it never does."""
    x, g = np.asarray(offsets, float), np.asarray(profile, float)
    i = int(np.argmax(g))
    level = fraction * g[i]
    out = []
    for direction in (-1, 1):
        j = i
        width = math.inf
        while 0 <= j + direction < len(x):
            k = j + direction
            if g[k] < level:
                frac = (g[j] - level) / (g[j] - g[k]) if g[j] != g[k] else 0.0
                width = abs(x[j] + frac * (x[k] - x[j]) - x[i])
                break
            j = k
        out.append(width)
    return out[0], out[1]


def expanding_grid(data: RangeData, part: Part, *, parameters=None, steps=None, fraction: float = 2.0 / 3.0) -> dict:
    """The Appendix's expanding grid method as a tool: for each parameter, how far it can
    move from ``part`` (the truth or the best fit) before Γ falls to ``fraction`` of its
    best, and the grid spacing (twice the smaller of the two widths) that therefore
    guarantees a sample inside the convex region.

    Returns ``{index: {"left": w, "right": w, "spacing": s}}``.
    """
    names = ["x", "y", "z", "rx", "ry", "rz", "a1", "a2", "a3", "e1", "e2", "bend0", "bend1", "taper"]
    parameters = range(14) if parameters is None else parameters
    size = float(jnp.max(part.size))
    default_steps = {
        0: size,
        1: size,
        2: size,
        3: 1.2,
        4: 1.2,
        5: 1.2,
        6: None,
        7: None,
        8: None,
        9: 0.9,
        10: 0.9,
        11: 0.9,
        12: 0.9,
        13: 0.9,
    }
    result = {}
    for i in parameters:
        span = (steps or {}).get(i, default_steps[i])
        if span is None:
            span = 0.95 * float(part.to_vector()[i])
        offsets = np.linspace(-span, span, 41)
        prof = gamma_profile(data, part, i, offsets)
        left, right = convex_width(offsets, prof, fraction=fraction)
        result[names[i]] = {"left": left, "right": right, "spacing": 2 * min(left, right)}
    return result
