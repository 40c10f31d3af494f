"""The pipeline: range image -> regions -> local search -> selection -> refinement.

:func:`recover` strings the stages together (paper sections 3.3-3.5 and 4):

1. :func:`~sqparts.prepare` the data (figure mask, encoding: σ, λ and the bit costs);
2. :func:`~sqparts.fit_image`: the parallel search at every region on the figure's
   skeleton, keeping the best few candidates per region;
3. area matrices and :func:`~sqparts.select_parts` (exact by HiGHS, or best-first);
4. :func:`~sqparts.refine_parts`: all chosen parts rendered together and refined.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import numpy as np

from ._camera import Camera
from ._fit import Encoding
from ._part import Part, stack_parts
from ._refine import EncodingCost, encoding_cost, part_statistics, refine_parts
from ._search import RangeData, fit_image
from ._select import Costs, SelectionProblem, select_parts


@dataclasses.dataclass
class Recovery:
    """What :func:`recover` found.

    Attributes
    ----------
    parts : Part
        The recovered parts (batched), in the camera frame.
    part_stats : list of dict
        Per part: visible ``pixels``, ``gamma`` (Eq. 4) and ``bits_saved`` (Eq. 5) in
        the joint rendering.
    cost : EncodingCost
        Final description length E (bits) and its pixel counts; ``cost.rendered`` is the
        model's range image, ``cost.labels`` its part labels.
    initial_parts, initial_cost :
        The selection before refinement (Figure 7c's "initial explanation").
    candidates : int
        Candidates found by the local search (regions × top_k).
    selection_method : str
    timings : dict
        Seconds per stage: ``search``, ``selection``, ``refinement``, ``total``.
    settings : dict
        The settings used (grid, max_size, window, σ, λ, bit costs...).
    depth, figure :
        The input range image and figure mask.
    history : list of (stage, E)
    """

    parts: Part
    part_stats: list
    cost: EncodingCost
    initial_parts: Part
    initial_cost: EncodingCost
    candidates: int
    selection_method: str
    timings: dict
    settings: dict
    depth: np.ndarray
    figure: np.ndarray
    history: list

    @property
    def description_length(self) -> float:
        return self.cost.total

    @property
    def fraction_explained(self) -> float:
        return self.cost.explained / max(int(self.figure.sum()), 1)

    @property
    def commission_fraction(self) -> float:
        """Commission pixels as a fraction of the figure's pixels."""
        return self.cost.commission / max(int(self.figure.sum()), 1)

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


def recover(
    depth,
    camera: Camera,
    *,
    figure=None,
    grid="coarse",
    max_size: float | None = None,
    window: int | None = None,
    encoding: Encoding | None = None,
    top_k: int = 3,
    selection: str = "auto",
    refine_rounds: int = 2,
    merge: bool = True,
    centres=None,
    progress=None,
    **search_kwargs,
) -> Recovery:
    """Recover a part model from a range image.

    Parameters
    ----------
    depth : (H, W) float array, NaN where there is no return.
    camera : the camera that took it (``depth.shape == (camera.height, camera.width)``).
    figure : optional (H, W) bool mask of the figure (default: every return).
    grid : a :class:`~sqparts.Grid` or preset name (``"coarse"``, ``"default"``, ``"fine"``).
    max_size : largest semi-axis searched (default: a third of the figure's extent).
    selection : ``"auto"``, ``"exact"`` or ``"best-first"``.
    refine_rounds : rounds of joint polishing (0 = none); ``merge`` allows bent merges.
    progress : optional wrapper for the region loop (e.g. ``tqdm.tqdm``).
    """
    t0 = time.perf_counter()
    fits, data, settings = fit_image(
        depth, camera, grid=grid, figure=figure, encoding=encoding, max_size=max_size, window=window,
        top_k=top_k, centres=centres, progress=progress, **search_kwargs,
    )
    jax.block_until_ready([f.gamma for f in fits])
    t1 = time.perf_counter()
    costs = Costs.from_encoding(data.encoding, int(data.figure_mask.sum()))
    parts, explained, commission = _candidates(fits, data)
    if parts is None:
        raise ValueError("depth: the search found no part that explains any pixel")
    problem = SelectionProblem.from_masks(explained, commission, costs)
    chosen, method = select_parts(problem, method=selection)
    if not chosen.any():
        chosen[int(np.argmax([f.sum() for f in explained]))] = True
    initial = jax.tree_util.tree_map(lambda x: x[np.flatnonzero(chosen)], parts)
    t2 = time.perf_counter()
    initial_cost = encoding_cost(initial, data, costs)
    if refine_rounds > 0 or merge:
        final, cost, history = refine_parts(initial, data, costs, rounds=refine_rounds, merge=merge)
    else:
        final, cost, history = initial, initial_cost, [("initial", initial_cost.total)]
    t3 = time.perf_counter()
    enc = data.encoding
    return Recovery(
        parts=final,
        part_stats=part_statistics(final, data, cost),
        cost=cost,
        initial_parts=initial,
        initial_cost=initial_cost,
        candidates=len(parts),
        selection_method=method,
        timings={"search": t1 - t0, "selection": t2 - t1, "refinement": t3 - t2, "total": t3 - t0},
        settings={
            "grid": dataclasses.asdict(settings.grid),
            "hypotheses_per_region": settings.grid.size,
            "regions": len(fits),
            "max_size": settings.max_size,
            "window": settings.window,
            "top_k": settings.top_k,
            "stride": settings.stride,
            "survivors": settings.survivors,
            "sigma": enc.sigma,
            "quantum": enc.quantum,
            "commission_weight": enc.commission_weight,
            "bits": {"part": costs.part, "explained_pixel": costs.explained,
                     "commission_pixel": costs.commission, "omitted_pixel": costs.omission},
            "raw_bits": costs.omission * costs.figure_pixels,
        },
        depth=np.asarray(data.image),
        figure=np.asarray(data.figure_mask),
        history=history,
    )


def _candidates(fits, data: RangeData):
    """All regions' candidates with Γ > 0 as one batch, their explained and commission masks."""
    parts, explained, commission = [], [], []
    figure = data.figure_mask
    for f in fits:
        for i in range(len(f.gamma)):
            if float(f.gamma[i]) <= 0:
                continue
            parts.append(f.parts[i])
            explained.append(np.asarray(f.explained[i]))
            commission.append(np.asarray(f.rendered[i]) & ~figure)
    if not parts:
        return None, None, None
    return stack_parts(parts), np.stack(explained), np.stack(commission)
