"""Warm recovery time and results of this checkout against another (``--base``), each
scene in new processes, the two checkouts' processes interleaved, and whether the
recovered parts are bit-for-bit the same.

Per scene and checkout: one process that recovers the scene once cold (compiling, and
counting the XLA programs it builds) and ``--runs`` times warm with
:func:`sqparts.recover`'s defaults; the warm runs' median is the figure. ``single`` is
``bench_cli.py``'s 96x96 one-part image, ``kinect`` the Kinect frame of
``../shared/data``, a path (holding a ``/``) a folder of ``depth.npy`` and
``camera.json`` (``benchmarks/unseen/make.py``'s); the others are built-in scenes. ``scene:NAME`` recovers NAME through
:func:`sqparts.recover_scene` instead (clean-up, figure/ground, a recovery per
figure; e.g. ``scene:kinect``, ``scene:human``). Several
``--rounds`` repeat the whole interleaving (the machines are shared and noisy: compare
medians taken in the same run).

    git worktree add --detach /tmp/wt-base <commit>
    JAX_PLATFORMS=cpu python benchmarks/bench_against.py --base /tmp/wt-base [--scenes single human chair castings]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import CHILD_PREAMBLE, interleaved, run_in_checkout, save, warm_fields
from bench_cli import CAMERA, SCENE

ROOT = Path(__file__).resolve().parents[1]

CHILD = (
    CHILD_PREAMBLE
    + r"""
name, runs, scene, camera = sys.argv[1], int(sys.argv[2]), json.loads(sys.argv[3]), json.loads(sys.argv[4])
whole = name.startswith("scene:")  # through recover_scene (clean-up, figure/ground, a recovery per figure)
name = name.removeprefix("scene:")
if name == "kinect":
    depth, cam = sqparts.read_range_image(sys.argv[5])
elif "/" in name:  # a folder of depth.npy and camera.json (benchmarks/unseen/make.py's)
    import pathlib
    folder = pathlib.Path(name)
    depth = np.load(folder / "depth.npy")
    cam = sqparts.camera_from_json(json.loads((folder / "camera.json").read_text()))
else:
    if name == "single":
        parts, cam = sqparts.scene_from_dict(scene)[0], sqparts.camera_from_json(camera)
    else:
        s = sqparts.builtin_scene(name)
        parts, cam = s.parts, s.camera
    depth = np.asarray(sqparts.render_range_image(parts, cam))
recover = sqparts.recover_scene if whole else sqparts.recover
built[0] = 0
t = time.perf_counter()
r = recover(depth, cam)
cold = time.perf_counter() - t
programs = built[0]
times, stages = [], []
for _ in range(runs):
    t = time.perf_counter()
    r = recover(depth, cam)
    times.append(time.perf_counter() - t)
    stages.append(dict(r.timings))
print("RESULT " + json.dumps({"parts": len(r.parts), "E": r.cost.total, "explained": r.fraction_explained,
    "cold_s": cold, "programs": programs, "warm_programs": built[0] - programs, "warm_s": times, "stages": stages, "vectors": np.asarray(r.parts.to_vector()).tolist()}))
"""
)


KINECT = ROOT.parent / "shared" / "data" / "grabber_frame0.pcd"


def run(checkout: Path, scene: str, runs: int) -> dict:
    name = scene.removeprefix("scene:")
    if "/" in name:  # a folder: absolute, for the children run elsewhere
        scene = scene.removesuffix(name) + str(Path(name).resolve())
    return run_in_checkout(checkout, CHILD, scene, str(runs), json.dumps(SCENE), json.dumps(CAMERA), str(KINECT))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--base", required=True, type=Path, help="checkout of the baseline")
    ap.add_argument("--scenes", nargs="+", default=["single", "human", "chair", "castings"])
    ap.add_argument("--runs", type=int, default=5, help="warm runs per process")
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    checkouts = {"base": args.base.resolve(), "new": ROOT}
    rows = []
    for scene in args.scenes:

        def one(v, checkout):
            r = run(checkout, scene, args.runs)
            print(
                f"{scene} {v}: {r['parts']} parts, E {r['E']:.3f}, warm median {statistics.median(r['warm_s']):.2f} s",
                flush=True,
            )
            return r

        got = interleaved(checkouts, args.rounds, one)
        timing = warm_fields(got)
        warm = timing["warm_median_s"]
        base, new = got["base"][-1], got["new"][-1]
        row = {
            "scene": scene,
            "parts": {v: got[v][-1]["parts"] for v in checkouts},
            "E": {v: got[v][-1]["E"] for v in checkouts},
            "explained": {v: got[v][-1]["explained"] for v in checkouts},
            "identical_parts": base["vectors"] == new["vectors"],
            **timing,
            "programs_first_recovery": {v: got[v][-1]["programs"] for v in checkouts},
            "programs_warm_runs": {v: got[v][-1]["warm_programs"] for v in checkouts},
            "stages_last_run": {v: got[v][-1]["stages"][-1] for v in checkouts},
        }
        rows.append(row)
        print(
            f"{scene}: base {warm['base']:.2f} s, new {warm['new']:.2f} s (x{row['speedup']:.2f}); "
            f"identical parts: {row['identical_parts']}",
            flush=True,
        )
    save("against", {"base": str(checkouts["base"]), "runs": args.runs, "rounds": args.rounds, "rows": rows})


if __name__ == "__main__":
    main()
