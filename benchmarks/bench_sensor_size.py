"""Sensor-sized renders through ``recover_scene``, scored against the truth at full
resolution: does binning a 640x480 image keep the parts' size, and does figure/ground
keep every object?

Each scene is a few known parts rendered at the camera's full resolution (the package's
renderer, which the tests hold to trimesh's ray casting); :func:`sqparts.recover_scene`
with its defaults bins the image (4x for 640x480), separates the figures and recovers
them; the recovered parts are rendered back at full resolution. Per scene: parts, the
IoU of the model's silhouette with the truth's, the median |depth difference| where both
are seen, every true part's share of pixels the model covers (an object dropped scores
0), and for one-part scenes the sorted semi-axes' largest relative error. Both checkouts
run the same scenes, each in one process.

    git worktree add --detach /tmp/wt-base <commit>
    JAX_PLATFORMS=cpu python benchmarks/bench_sensor_size.py --base /tmp/wt-base
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import CHILD_PREAMBLE, run_in_checkout, save

ROOT = Path(__file__).resolve().parents[1]

CHILD = (
    CHILD_PREAMBLE
    + r"""
from scipy.spatial.transform import Rotation

def part(size, position, turn=(0.0, 0.0, 0.0), squareness=(0.3, 0.3)):
    return sqparts.Part(size=list(size), squareness=list(squareness), position=list(position),
                        orientation=Rotation.from_euler("xyz", turn, degrees=True).as_rotvec().tolist())

box = part((0.15, 0.08, 0.05), (0.0, 0.0, 1.0), (30, 30, 20))
pin = sqparts.PinholeCamera(640, 480, 600.0, 600.0, 319.5, 239.5)
scenes = [
    ("box, pinhole 640x480", [box], pin),
    ("box, fx != fy, off-centre", [part((0.15, 0.08, 0.05), (0.05, 0.03, 1.0), (30, 30, 20))],
     sqparts.PinholeCamera(640, 480, 700.0, 560.0, 250.0, 300.0)),
    ("box, 643x479", [box], sqparts.PinholeCamera(643, 479, 600.0, 600.0, 321.0, 239.0)),
    ("box, orthographic 640x480", [box], sqparts.OrthographicCamera(640, 480, 0.0006, 319.5, 239.5)),
    ("cylinder, pinhole 640x480", [part((0.05, 0.05, 0.14), (0.02, -0.01, 0.9), (70, 10, 0), (1.0, 0.2))], pin),
    ("three parts, one cut by the edge", [
        part((0.15, 0.08, 0.05), (0.38, 0.0, 1.0), (0, 25, 0)),
        part((0.05, 0.05, 0.08), (-0.15, 0.05, 0.7), (17, 29, 0), (1.0, 1.0)),
        part((0.06, 0.04, 0.12), (-0.05, -0.15, 1.4), (0, 0, 0), (0.5, 1.0)),
    ], sqparts.PinholeCamera(640, 480, 600.0, 600.0, 319.5, 239.5)),
]
rows = []
for name, parts, cam in scenes:
    truth, labels = (np.asarray(a) for a in sqparts.render_range_image(sqparts.stack_parts(parts), cam, return_labels=True))
    t = time.perf_counter()
    r = sqparts.recover_scene(truth, cam)
    seconds = time.perf_counter() - t
    model = np.asarray(sqparts.render_range_image(r.parts, cam))
    m, s = np.isfinite(model), np.isfinite(truth)
    both = m & s
    row = {"scene": name, "true_parts": len(parts), "parts": len(r.parts), "seconds": seconds,
           "iou": float(both.sum() / (m | s).sum()),
           "median_dz_mm": float(1000 * np.median(np.abs(model[both] - truth[both]))) if both.any() else None,
           "covered": [float((m & (labels == i)).sum() / max(1, (labels == i).sum())) for i in range(len(parts))]}
    if len(parts) == 1 and len(r.parts) == 1:
        got, want = np.sort(np.asarray(r.parts.size).reshape(-1)), np.sort(np.asarray(parts[0].size))
        row["size_error"] = float(np.max(np.abs(got - want) / want))
    rows.append(row)
    print(name, json.dumps(row), file=sys.stderr, flush=True)
print("RESULT " + json.dumps(rows))
"""
)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--base", type=Path, required=True, help="a checkout (git worktree) to compare against")
    args = ap.parse_args()
    got = {v: run_in_checkout(checkout, CHILD) for v, checkout in (("base", args.base.resolve()), ("new", ROOT))}
    for a, b in zip(got["base"], got["new"]):
        size = (
            f", size error {a.get('size_error', float('nan')):.3f} -> {b.get('size_error', float('nan')):.3f}"
            if "size_error" in a or "size_error" in b
            else ""
        )
        print(
            f"{a['scene']:34s} parts {a['parts']} -> {b['parts']} (true {a['true_parts']}), IoU {a['iou']:.3f} -> "
            f"{b['iou']:.3f}, median |dz| {a['median_dz_mm']} -> {b['median_dz_mm']} mm, covered "
            f"{[round(c, 2) for c in a['covered']]} -> {[round(c, 2) for c in b['covered']]}{size}"
        )
    save("sensor_size", {"base": str(args.base), "rows": got})


if __name__ == "__main__":
    main()
