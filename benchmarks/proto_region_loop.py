"""Prototype measurement (session 53): the grid search at full resolution (stride 1, no
pruning: the path of a small figure's regions) for a few regions, in the checkout on
``PYTHONPATH`` (this one by default): ``score_regions`` where it exists (one call for
all the regions), else ``score_region`` once per region. The paper's grid, a 32-pixel
window, the human's image; the second of two runs is the figure.

    JAX_PLATFORMS=cpu SQPARTS_BENCH_SUFFIX=_new python benchmarks/proto_region_loop.py
    cd /tmp/wt-base && JAX_PLATFORMS=cpu PYTHONPATH=/tmp/wt-base SQPARTS_BENCH_SUFFIX=_base \\
        python /work/main/benchmarks/proto_region_loop.py

Writes ``benchmarks/results/region_loop<suffix>.json`` (next to this script).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import save

import sqparts
from sqparts import _search


def main(regions: int = 4):
    s = sqparts.builtin_scene("human")
    data = sqparts.prepare(np.asarray(sqparts.render_range_image(s.parts, s.camera)), s.camera)
    settings = sqparts.make_settings(data, grid="default", max_size=0.2, window=32)
    centres = np.argwhere(data.figure_mask)[::400][:regions]
    times, gamma = [], None
    for _ in range(2):
        t = time.perf_counter()
        if hasattr(_search, "score_regions"):
            gamma = _search.score_regions(data, settings, centres, stride=1)[0]
        else:
            gamma = np.stack([np.asarray(_search.score_region(data, settings, c, stride=1)[0]) for c in centres])
        times.append(time.perf_counter() - t)
    hypotheses = len(_search._grid_arrays(settings.grid)["orientation"])
    print(f"{regions} regions x {hypotheses} hypotheses at stride 1, window {settings.window}: {times[-1]:.2f} s")
    save(
        "region_loop",
        {
            "sqparts": str(Path(sqparts.__file__).resolve().parent),
            "one_call": hasattr(_search, "score_regions"),
            "regions": regions,
            "hypotheses": hypotheses,
            "window": settings.window,
            "times_s": times,
            "gamma_sum": float(np.sum(gamma)),
        },
    )


if __name__ == "__main__":
    main()
