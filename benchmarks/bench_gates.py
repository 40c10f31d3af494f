"""Gates the built-in scenes do not hold: how far the gate's recovery (Figure 10) carries
to other gates (issue #27). Each gate has two posts, rails and one diagonal brace, bars
about two pixels across, nothing behind them; each goes through
:func:`sqparts.recover_scene`'s defaults with prettifying (up = -y), as ``sqparts recover
--prettify --up 0,-1,0`` would. Per gate: parts, which true members are found (a
recovered part with silhouette IoU >= 0.5, as in ``bench_recover.py``), explained
fraction, commission, E and wall time.

    JAX_PLATFORMS=cpu python benchmarks/bench_gates.py          # results/gates.json
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import save
from bench_recover import true_parts_found

import sqparts

GATES = {
    "four rails, other diagonal, 18 m": {"distance": 18.0, "rails": (-0.8, -0.2, 0.4, 0.9), "brace": (-0.8, 0.9)},
    "pinhole camera, 22 m": {"distance": 22.0, "pinhole": True},
    "two rails, steeper brace, 16 m": {"distance": 16.0, "rails": (-0.8, 0.9), "brace": (1.1, -0.9)},
}
"""Name: :func:`sqparts._scenes.gate`'s keywords (distance in metres, rail heights, the
brace's heights at its left and right ends, camera); the rest is the built-in gate's."""


def main() -> None:
    rows = []
    for name, spec in GATES.items():
        s = sqparts.builtin_scene("gate", **spec)
        parts, cam, names = s.parts, s.camera, s.part_names
        depth = np.asarray(sqparts.render_range_image(parts, cam))
        t0 = time.perf_counter()
        r = sqparts.recover_scene(depth, cam, scene=sqparts.SceneSettings(prettify=True, up=(0.0, -1.0, 0.0)))
        wall = time.perf_counter() - t0
        found = true_parts_found(parts, r.parts, cam, names)
        row = {
            "gate": name,
            "true_parts": len(parts),
            "found_parts": len(r.parts),
            "true_parts_found": found,
            "true_found_count": int(sum(v["found"] for v in found.values())),
            "fraction_explained": r.fraction_explained,
            "commission_fraction": r.commission_fraction,
            "description_length_bits": r.cost.total,
            "wall_s": wall,
        }
        rows.append(row)
        print(
            f"{name}: {row['found_parts']} parts for {row['true_parts']}, found "
            f"{[n for n, v in found.items() if v['found']]}, explained {row['fraction_explained']:.1%}, "
            f"commission {row['commission_fraction']:.1%}, E {row['description_length_bits']:.0f} bits, {wall:.0f} s",
            flush=True,
        )
    save("gates", {"gates": rows})


if __name__ == "__main__":
    main()
