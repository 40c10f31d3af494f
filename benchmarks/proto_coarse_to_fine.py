"""Prototype (not recovery's default): does the coarse-to-fine orientation search, which
takes a single region's fit on the coarse grid from 88% to 96% on ``bench_search.py``'s
48 cases, make multi-part recovery better?

Every scene of a family is recovered through :func:`sqparts.recover` with the ``fast``
search preset as it is (``refine_orientations=0``) and with its ``refine`` best distinct
survivors refined in orientation, in one process (one cold recovery of each first, not
timed); per scene the parts, E, the fraction explained and the warm seconds of each,
saved in ``results/coarse_to_fine.json``. The family: the built-in scenes (single-part
image of ``bench_cli.py``, person, chair, castings, gate, thin chair), the castings heap
drawn from six other seeds, the chair turned three other ways and the person in five
poses. None of them were looked at to choose the mechanism's constants.

    JAX_PLATFORMS=cpu python benchmarks/proto_coarse_to_fine.py [--refine 16]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import save
from bench_cli import CAMERA, SCENE

import sqparts
from sqparts._scenes import HUMAN_POSES, castings, chair, posed_human


def scenes():
    parts, cam = sqparts.scene_from_dict(SCENE)[0], sqparts.camera_from_json(CAMERA)
    yield "single", parts, cam
    for name in ("human", "chair", "castings", "gate", "thin-chair"):
        s = sqparts.builtin_scene(name)
        yield name, s.parts, s.camera
    for seed in (0, 1, 2, 4, 5, 6):
        s = castings(seed=seed)
        yield f"castings seed {seed}", s.parts, s.camera
    for k, turn in enumerate((0.2, 0.9, 1.4)):
        s = chair(tilt=2.2 + 0.2 * k, turn=turn)
        yield f"chair turn {turn}", s.parts, s.camera
    for pose in [p for p in HUMAN_POSES if p != "standing"][:5]:
        s = posed_human(pose)
        yield f"person {pose}", s.parts, s.camera


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--refine", type=int, default=16, help="refine_orientations of the second recovery")
    args = ap.parse_args()
    settings = {r: dataclasses.replace(sqparts.SEARCH_PRESETS["fast"], refine_orientations=r) for r in (0, args.refine)}
    rows = []
    for name, parts, cam in scenes():
        depth = np.asarray(sqparts.render_range_image(parts, cam))
        row = {"scene": name}
        for r, search in settings.items():
            sqparts.recover(depth, cam, search=search)  # compiles what this image's shapes need
            t = time.perf_counter()
            rec = sqparts.recover(depth, cam, search=search)
            row[str(r)] = {
                "parts": len(rec.parts),
                "E": rec.cost.total,
                "explained": rec.fraction_explained,
                "warm_s": time.perf_counter() - t,
            }
        rows.append(row)
        a, b = row["0"], row[str(args.refine)]
        print(
            f"{name}: {a['parts']} -> {b['parts']} parts, E {a['E']:.0f} -> {b['E']:.0f} bits, "
            f"explained {a['explained']:.3f} -> {b['explained']:.3f}, {a['warm_s']:.1f} -> {b['warm_s']:.1f} s",
            flush=True,
        )
    diff = np.array([r[str(args.refine)]["E"] - r["0"]["E"] for r in rows])
    summary = {
        "shorter": int((diff < -0.5).sum()),
        "longer": int((diff > 0.5).sum()),
        "same": int((np.abs(diff) <= 0.5).sum()),
        "sum_of_E_changes_bits": float(diff.sum()),
        "median_E_change_bits": float(np.median(diff)),
    }
    print(summary)
    save("coarse_to_fine", {"refine_orientations": args.refine, "rows": rows, "summary": summary})


if __name__ == "__main__":
    main()
