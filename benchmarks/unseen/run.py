"""Recover every scene dir through sqparts.recover_scene (defaults) in one process.

    JAX_PLATFORMS=cpu python benchmarks/unseen/run.py OUT.json DIR...

A DIR is one scene folder (depth.npy, camera.json, truth.json) or a folder of them
(e.g. the scenes folder make.py wrote).  The first scene is recovered once first as a warm-up
(compile time is then excluded from `seconds`).  Per scene:
  name, figures, parts_per_figure, parts, truth_parts, truth_objects,
  E (first = largest figure's bits), E_sum (all figures), explained (first figure),
  explained_all (scene), seconds,
  E_truth: the true parts' E under the first figure's encoding (one-object scenes only;
    all true parts when there is one figure, else per_figure[0]'s), E_truth_all: all
    true parts under the first figure's encoding (one-object scenes),
  per_figure: [{E, parts, explained, pixels, truth_parts, truth_objects, E_truth}]: each
    true part is assigned to the figure showing most of its pixels; E_truth is the E of a
    figure's assigned true parts under that figure's encoding (all scenes),
  truth_unassigned: true parts no figure shows,
  error (message, or null).
Set SQPARTS_PKG=/path/to/checkout to import sqparts from another checkout, and
SQPARTS_SCENE=PRESET (e.g. synthetic) to pass scene=PRESET (default: recover_scene's own),
SQPARTS_JOIN=never|always|auto to recover with that preset's settings and that join.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
import traceback
from pathlib import Path

if os.environ.get("SQPARTS_PKG"):
    sys.path.insert(0, os.environ["SQPARTS_PKG"])

import numpy as np

import sqparts
from sqparts import scene_from_dict

KW = {"scene": os.environ["SQPARTS_SCENE"]} if os.environ.get("SQPARTS_SCENE") else {}
if os.environ.get("SQPARTS_JOIN"):  # never, always or auto (sqparts.cli.JOIN_MODES; spelt out: SQPARTS_PKG may lack it)
    KW["scene"] = dataclasses.replace(
        sqparts.scene_preset(KW.get("scene", "real")),
        join={"never": False, "always": True}.get(os.environ["SQPARTS_JOIN"], os.environ["SQPARTS_JOIN"]),
    )


def scene_dirs(args):
    out = []
    for a in map(Path, args):
        if (a / "depth.npy").exists():
            out.append(a)
        else:
            found = sorted(p.parent for p in a.glob("*/depth.npy"))
            if (a / "index.json").exists():  # keep the generator's order
                order = {m["name"]: i for i, m in enumerate(json.loads((a / "index.json").read_text()))}
                found.sort(key=lambda p: order.get(p.name, len(order)))
            out.extend(found)
    return out


def load(d: Path):
    depth = np.load(d / "depth.npy")
    cam = sqparts.load_camera(d / "camera.json")
    parts, ann, _ = scene_from_dict(json.loads((d / "truth.json").read_text()))
    objs = np.array([a.get("figure", 0) for a in ann])
    return depth, cam, parts, objs


def subset(parts, idx):
    return sqparts.stack_parts([parts[int(i)] for i in idx])


def run_one(d: Path) -> dict:
    depth, cam, truth, objs = load(d)
    nobj = int(objs.max()) + 1
    row = {
        "name": d.name,
        "truth_parts": len(truth),
        "truth_objects": nobj,
        "truth_parts_per_object": [int((objs == k).sum()) for k in range(nobj)],
    }
    t = time.perf_counter()
    scene = sqparts.recover_scene(depth, cam, **KW)
    row["seconds"] = time.perf_counter() - t
    figs = list(scene.figures)
    row["figures"] = len(figs)
    row["parts_per_figure"] = [len(f.parts) for f in figs]
    row["parts"] = int(sum(row["parts_per_figure"]))
    row["E"] = float(figs[0].cost.total) if figs else None
    row["E_sum"] = float(sum(f.cost.total for f in figs))
    row["explained"] = float(figs[0].fraction_explained) if figs else None
    row["explained_all"] = float(scene.fraction_explained) if figs else None
    # Each true part goes to the figure that shows most of its pixels (parts shown by no
    # figure go nowhere); a figure's E_truth is the E of its true parts under its encoding.
    _, labels = sqparts.render_range_image(truth, scene.camera, return_labels=True)
    labels = np.asarray(labels)
    owner = []
    for i in range(len(truth)):
        counts = [int(((labels == i) & np.asarray(f.figure)).sum()) for f in figs]
        owner.append(int(np.argmax(counts)) if counts and max(counts) > 0 else -1)
    owner = np.array(owner)
    per = []
    for k, f in enumerate(figs):
        mine = np.flatnonzero(owner == k)
        e = float(sqparts.encoding_cost(subset(truth, mine), f.data, f.costs).total) if len(mine) else None
        objs_k = sorted({int(objs[i]) for i in mine})
        per.append(
            {
                "E": float(f.cost.total),
                "parts": len(f.parts),
                "explained": float(f.fraction_explained),
                "pixels": int(np.asarray(f.figure).sum()),
                "truth_parts": int(len(mine)),
                "truth_objects": objs_k,
                "E_truth": e,
            }
        )
    row["truth_unassigned"] = int((owner < 0).sum())
    # The truth's E under the first figure's encoding, one-object scenes only: all true
    # parts (as bench_objects.py) where the object came out as one figure; where it was
    # torn into several, the first figure's assigned true parts (per_figure[0]).
    row["E_truth_all"] = (
        float(sqparts.encoding_cost(truth, figs[0].data, figs[0].costs).total) if figs and nobj == 1 else None
    )
    row["E_truth"] = (row["E_truth_all"] if len(figs) == 1 else per[0]["E_truth"]) if figs and nobj == 1 else None
    row["per_figure"] = per
    row["error"] = None
    return row


def main():
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    out = Path(sys.argv[1])
    dirs = scene_dirs(sys.argv[2:])
    if not dirs:
        sys.exit("no scene dirs")
    t0 = time.perf_counter()
    try:
        depth, cam, _, _ = load(dirs[0])
        sqparts.recover_scene(depth, cam, **KW)
    except Exception as e:  # the scene's own run records it
        print(f"warm-up failed: {e!r}", flush=True)
    print(f"warm-up {time.perf_counter() - t0:.1f} s; {len(dirs)} scenes", flush=True)
    rows = []
    for d in dirs:
        try:
            r = run_one(d)
        except Exception as e:
            r = {"name": d.name, "error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc()}
            print(f"{d.name:22s} ERROR {r['error']}", flush=True)
            rows.append(r)
            continue
        rows.append(r)
        truth = "" if r["E_truth"] is None else f" truth {r['E_truth']:8.1f} ({r['E'] - r['E_truth']:+7.1f})"
        figs = (
            ""
            if r["figures"] == 1
            else " ["
            + "; ".join(
                f"E {p['E']:.1f} {p['parts']}p truth {p['truth_parts']}p obj{p['truth_objects']} "
                + ("-" if p["E_truth"] is None else f"{p['E_truth']:.1f}")
                for p in r["per_figure"]
            )
            + "]"
        )
        print(
            f"{r['name']:22s} parts {r['parts']}/{r['truth_parts']} figs {r['figures']} "
            f"{r['parts_per_figure']} E {r['E']:8.1f}{truth} expl {r['explained']:.3f} {r['seconds']:5.1f}s{figs}",
            flush=True,
        )
    meta = {
        "sqparts": getattr(sqparts, "__file__", None),
        "dirs": [str(d) for d in dirs],
        "wall_s": time.perf_counter() - t0,
        "kwargs": {k: v if isinstance(v, str) else repr(v) for k, v in KW.items()},
    }
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    os.replace(tmp, out)
    print(
        f"saved {out} ({len(rows)} scenes, {sum(1 for r in rows if r.get('error'))} errors, "
        f"{sum(r.get('seconds', 0) for r in rows):.0f} s recovering)"
    )


if __name__ == "__main__":
    main()
