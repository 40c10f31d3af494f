"""Objects nobody tuned on: fourteen scenes of one to four parts (a box, an ellipsoid, a
bent rod, a tapered column; a T, an L, a bench, a mallet, a lamp, a small far object, a
box with a knob, a noisy ellipsoid, a quantised stool, a chair), each at its own
distance, camera (pinhole or orthographic, 64x64 to 200x160, principal point off
centre), turn and tilt, some with depth noise or 8-bit quantisation, drawn from one seed
(written for session 63 by a reviewer who had not seen the built-in scenes). Each is
recovered through :func:`sqparts.recover_scene` (the command line's path) by this
checkout and by the baseline (``--base``), in one process each, the scenes one after
another; recorded per scene: parts against the truth's count, E of the recovery and of
the true parts under the recovery's own encoding (E above the truth's: the search or
the refinement stopped short; below it: the criterion prefers another description),
and the seconds.

    JAX_PLATFORMS=cpu python benchmarks/bench_objects.py --base /tmp/wt-base
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import CHILD_PREAMBLE, run_in_checkout, save

ROOT = Path(__file__).resolve().parents[1]
SEED = 20261207

# name, parts (semi-axes, squareness, position, turn (a matrix, or (axis, degrees) pairs
# applied in order), bend, taper) in the object's frame (y down), distance, camera, image
# size, noise (m), quantisation step (m)
VERT = [("x", 90)]
SCENES = [
    ("box", [([0.10, 0.075, 0.15], [0.15, 0.15], [0, 0, 0], [], None, None)], 1.5, "pinhole", (128, 128), 0, 0),
    ("ellipsoid", [([0.30, 0.20, 0.15], [1, 1], [0, 0, 0], [], None, None)], 3.0, "pinhole", (96, 96), 0, 0),
    (
        "bent rod",
        [([0.04, 0.04, 0.25], [0.3, 1.0], [0, 0, 0], [[0, 0, 1], [1, 0, 0], [0, 1, 0]], [0.5, 0.0], None)],
        1.0,
        "pinhole",
        (160, 120),
        0,
        0,
    ),
    ("tapered", [([0.10, 0.10, 0.30], [0.5, 1.0], [0, 0, 0], VERT, None, -0.6)], 2.0, "orthographic", (100, 100), 0, 0),
    (
        "T",
        [
            ([0.20, 0.04, 0.04], [0.2, 0.2], [0, -0.20, 0], [], None, None),
            ([0.04, 0.04, 0.18], [0.2, 0.2], [0, 0, 0], VERT, None, None),
        ],
        1.2,
        "pinhole",
        (128, 96),
        0,
        0,
    ),
    (
        "L",
        [
            ([0.04, 0.04, 0.20], [0.2, 0.2], [0, -0.16, 0], VERT, None, None),
            ([0.16, 0.04, 0.04], [0.2, 0.2], [0.12, 0, 0], [], None, None),
        ],
        1.0,
        "orthographic",
        (120, 80),
        0,
        0,
    ),
    (
        "bench",
        [
            ([0.40, 0.025, 0.15], [0.15, 0.15], [0, -0.20, 0], [], None, None),
            ([0.02, 0.18, 0.13], [0.15, 0.15], [-0.33, 0, 0], [], None, None),
            ([0.02, 0.18, 0.13], [0.15, 0.15], [0.33, 0, 0], [], None, None),
        ],
        2.5,
        "pinhole",
        (160, 120),
        0,
        0,
    ),
    (
        "mallet",
        [
            ([0.015, 0.015, 0.15], [1, 1], [0, 0, 0], VERT, None, None),
            ([0.035, 0.035, 0.07], [0.3, 1.0], [0, -0.17, 0], [("y", 90)], None, None),
        ],
        0.5,
        "pinhole",
        (200, 160),
        0,
        0,
    ),
    (
        "lamp",
        [
            ([0.15, 0.15, 0.03], [0.3, 1.0], [0, 0.45, 0], VERT, None, None),
            ([0.02, 0.02, 0.40], [1, 1], [0, 0.02, 0], VERT, None, None),
            ([0.15, 0.15, 0.15], [0.3, 1.0], [0, -0.45, 0], VERT, None, -0.5),
        ],
        4.0,
        "pinhole",
        (160, 120),
        0,
        0,
    ),
    (
        "small far object",
        [
            ([0.12, 0.08, 0.08], [0.2, 0.2], [0, -0.14, 0], [], None, None),
            ([0.05, 0.05, 0.10], [0.3, 1.0], [0, 0.04, 0], VERT, None, None),
        ],
        5.0,
        "pinhole",
        (64, 64),
        0,
        0,
    ),
    (
        "box and knob, noisy",
        [
            ([0.12, 0.05, 0.09], [0.2, 0.2], [0, 0, 0], [], None, None),
            ([0.04, 0.04, 0.04], [1, 1], [0, -0.08, 0], [], None, None),
        ],
        1.0,
        "pinhole",
        (128, 128),
        0.001,
        0,
    ),
    (
        "noisy ellipsoid",
        [([0.08, 0.05, 0.12], [1, 1], [0, 0, 0], [("z", 30)], None, None)],
        0.8,
        "pinhole",
        (96, 80),
        0.002,
        0,
    ),
    (
        "quantised stool",
        [
            ([0.18, 0.03, 0.18], [0.5, 1.0], [0, -0.22, 0], VERT, None, None),
            ([0.03, 0.03, 0.20], [1, 1], [0, 0, 0], VERT, None, None),
            ([0.12, 0.03, 0.12], [0.5, 1.0], [0, 0.22, 0], VERT, None, None),
        ],
        2.0,
        "pinhole",
        (128, 96),
        0,
        4.5 / 255,
    ),
    (
        "chair",
        [
            ([0.20, 0.02, 0.20], [0.15, 0.15], [0, 0, 0], [], None, None),
            ([0.20, 0.22, 0.02], [0.15, 0.15], [0, -0.24, 0.18], [], None, None),
            ([0.02, 0.02, 0.20], [0.2, 0.2], [-0.17, 0.22, -0.17], VERT, None, None),
            ([0.02, 0.02, 0.20], [0.2, 0.2], [0.17, 0.22, -0.17], VERT, None, None),
        ],
        1.8,
        "orthographic",
        (140, 120),
        0.0005,
        0,
    ),
]

CHILD = (
    CHILD_PREAMBLE
    + r"""
from scipy.spatial.transform import Rotation as R
scenes, seed = json.loads(sys.argv[1]), int(sys.argv[2])
rng = np.random.default_rng(seed)
rows = []
for name, specs, z, model, (w, h), noise, step in scenes:
    yaw, pitch = rng.uniform(-60, 60), rng.uniform(15, 35)  # the object turned, the camera looking down on it
    turn = R.from_euler("x", pitch, degrees=True) * R.from_euler("y", yaw, degrees=True)
    parts = []
    for size, eps, pos, rot, bend, taper in specs:
        local = R.identity()
        if rot and not isinstance(rot[0][0], str):
            local = R.from_matrix(rot)
        for axis, deg in rot if rot and isinstance(rot[0][0], str) else []:
            local = R.from_euler(axis, deg, degrees=True) * local
        extra = {k: v for k, v in (("bend", bend), ("taper", taper)) if v is not None}
        parts.append(sqparts.Part(size=size, squareness=eps, position=turn.apply(pos) + [0, 0, z],
                                  orientation=(turn * local).as_rotvec(), **extra))
    parts = sqparts.stack_parts(parts)
    extent = 2 * max(max(abs(c) for c in pos) + max(size) for size, _, pos, *_ in specs)
    share = 0.95 if name in ("T", "L") else 0.55  # of the shorter side the object spans
    if model == "pinhole":
        f = share * min(w, h) * z / extent
        cam = sqparts.PinholeCamera(w, h, f, f, (w - 1) / 2 + rng.uniform(-2, 2), (h - 1) / 2 + rng.uniform(-2, 2))
    else:
        cam = sqparts.OrthographicCamera(w, h, extent / (share * min(w, h)), (w - 1) / 2, (h - 1) / 2)
    depth = np.asarray(sqparts.render_range_image(parts, cam), np.float32)
    if noise:
        depth = depth + rng.normal(0, noise, depth.shape).astype(np.float32)
    if step:
        depth = (np.round(depth / step) * step).astype(np.float32)
    t = time.perf_counter()
    scene = sqparts.recover_scene(depth, cam)
    seconds = time.perf_counter() - t
    got = [f for f in scene.figures]
    fig = max(got, key=lambda f: len(f.parts)) if got else None
    # The true parts' E under the recovery's encoding: for an object seen as one figure.
    truth_E = float(sqparts.encoding_cost(parts, fig.data, fig.costs).total) if len(got) == 1 else None
    rows.append({"scene": name, "true_parts": len(specs), "parts": len(scene.parts), "figures": len(got),
                 "E": float(fig.cost.total) if fig is not None else None, "E_truth": truth_E,
                 "explained": fig.fraction_explained if fig is not None else None, "pixels": int(np.isfinite(depth).sum()), "s": seconds})
    print(name, rows[-1], file=sys.stderr, flush=True)
print("RESULT " + json.dumps(rows))
"""
)


def _row(r: dict) -> str:
    truth = "n/a" if r["E_truth"] is None else f"{r['E_truth']:.1f}"
    return f"{r['parts']} parts in {r['figures']} figure(s), E {r['E']:.1f} (truth's {truth}), {r['s']:.1f} s"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--base", required=True, type=Path, help="checkout of the baseline")
    args = ap.parse_args()
    checkouts = {"base": args.base.resolve(), "new": ROOT}
    got = {}
    for v, checkout in checkouts.items():
        got[v] = run_in_checkout(checkout, CHILD, json.dumps(SCENES), str(SEED))
    rows = []
    for b, n in zip(got["base"], got["new"]):
        rows.append({"scene": b["scene"], "true_parts": b["true_parts"], "base": b, "new": n})
        print(
            f"{b['scene']:22s} truth {b['true_parts']}: "
            + "; ".join(f"{v} {_row(r)}" for v, r in (("base", b), ("new", n)))
        )
    right = {v: sum(r[v]["parts"] == r["true_parts"] for r in rows) for v in checkouts}
    print(f"part count right: base {right['base']} of {len(rows)}, new {right['new']} of {len(rows)}")
    save("objects", {"base": str(checkouts["base"]), "seed": SEED, "rows": rows, "part_count_right": right})


if __name__ == "__main__":
    main()
