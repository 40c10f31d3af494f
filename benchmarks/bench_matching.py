"""Seconds to match a recognition benchmark view, this checkout against another, in the
same run.

Each side matches the same cached 128 x 128 test views (one of each object by default)
in its own process, against the database of the learnt views (both built from
``results/recognition_cache_128.json``); the sides alternate, a few views at a time, so
that both see the same machine. Saves per-view seconds and every object's score for both
sides, so that the scores can be compared too::

    git worktree add --detach /tmp/wt-base <commit>
    JAX_PLATFORMS=cpu python benchmarks/bench_matching.py --base /tmp/wt-base
    JAX_PLATFORMS=cpu python benchmarks/bench_matching.py --lattice   # verification, 640 x 480
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
VIEWS = (
    "spot/test1 fish/test2 penguin/test3 wingnut/test4 koala/test5 scorpion/test0 "
    "goathead/test1 cat/test2 boot/test3 hammer/test4 teapot/test5 human/test0"
).split()


def worker(out: Path, keys: list[str]) -> None:
    """Match ``keys`` with the sqparts this script's checkout imports (the benchmark's own
    ``recognise_view``, against the uncalibrated database); write the rows."""
    sys.path.insert(0, str(HERE))
    import bench_recognition as B

    import sqparts

    print(f"matching with {sqparts.__file__}", flush=True)
    cache = json.loads(Path(os.environ["SQPARTS_MATCH_CACHE"]).read_text())
    views = B.plan()
    folder = Path(tempfile.mkdtemp(prefix="sqparts-bench-db-"))
    db = B.learnt_database(views, cache, folder)
    spec = {k: (n, s) for k, n, _, s in views}
    rows = {}
    for key in keys:
        name, s = spec[key]
        row = B.recognise_view((str(folder), 128, db.threshold, sqparts.MatchSettings(), key, name, s, cache[key]))
        rows[key] = {"seconds": row["matching_s"], "scores": row["scores"]}
    out.write_text(json.dumps(rows))


def lattice(repeats: int = 3) -> None:
    """verify_poses on a 640 x 480 frame, on its lattice and on every pixel, same process:
    the built-in chair 2.4 m away and 48 poses about it (normal, 1.5 degrees and 1.5 cm
    standard deviations)."""
    import numpy as np
    from _common import save
    from scipy.spatial.transform import Rotation

    import sqparts
    import sqparts._compile
    import sqparts._recognize as R
    from sqparts import Observation
    from sqparts._database import transform_parts
    from sqparts._encoding import _LAYERS

    sqparts._compile.enable_caches()
    camera = sqparts.PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
    parts = sqparts.builtin_scene("chair").parts
    centre = np.asarray(parts.position, float).mean(0)
    to_camera = np.eye(4)
    to_camera[:3, 3] = [0.0, 0.0, 2.4] - centre
    parts = transform_parts(parts, to_camera)
    depth = np.asarray(sqparts.render_range_image(parts, camera))
    observation = Observation(depth, camera, np.isfinite(depth)[None])
    rng = np.random.default_rng(0)
    solids = []
    for _ in range(48):
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_rotvec(rng.normal(0, np.radians(1.5), 3)).as_matrix()
        c = np.asarray(parts.position, float).mean(0)
        pose[:3, 3] = c - pose[:3, :3] @ c + rng.normal(0, 0.015, 3)
        solids.append(transform_parts(parts, pose))
    figure = observation.figures[0]
    out = {"figure_pixels": int(figure.sum()), "solids": len(solids)}
    for label, pixels in (("lattice", R.VERIFY_PIXELS), ("every pixel", figure.size + 1)):
        R.VERIFY_PIXELS = pixels
        out[label] = {"step": R.verification_lattice(camera, figure)[0][0].step or 1}
        times = []
        for _ in range(repeats + 1):  # the first compiles
            _LAYERS.clear()  # nothing looked up from the previous repeat
            t0 = time.perf_counter()
            scores = R.verify_poses(solids, observation, figure, 0.02)
            times.append(time.perf_counter() - t0)
        out[label].update(seconds=times[1:], median_s=float(np.median(times[1:])), scores=scores.tolist())
        print(label, out[label]["step"], f"{out[label]['median_s']:.2f} s", flush=True)
    diff = np.abs(np.array(out["lattice"]["scores"]) - np.array(out["every pixel"]["scores"]))
    out["largest_score_difference"] = float(diff.max())
    out["ratio"] = out["every pixel"]["median_s"] / out["lattice"]["median_s"]
    print(f"ratio {out['ratio']:.1f}x, largest score difference {diff.max():.4f}")
    save("verification_lattice", out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", help="the other checkout (a git worktree)")
    ap.add_argument("--views", nargs="+", default=VIEWS, help="cached test views to match")
    ap.add_argument("--group", type=int, default=4, help="views per process before the sides alternate")
    ap.add_argument("--worker", nargs=2, metavar=("OUT", "KEYS"), help=argparse.SUPPRESS)
    ap.add_argument(
        "--lattice",
        action="store_true",
        help="instead: verification of 48 poses on a 640 x 480 frame, lattice vs every pixel",
    )
    args = ap.parse_args()
    if args.lattice:
        lattice()
        return
    if not args.base:
        ap.error("--base: got nothing, expected the other checkout's folder (or --lattice)")
    if args.worker:
        worker(Path(args.worker[0]), args.worker[1].split(","))
        return
    from _common import save

    env = {**os.environ, "SQPARTS_MATCH_CACHE": str(HERE / "results" / "recognition_cache_128.json")}
    sides = {"base": Path(args.base).resolve(), "new": HERE.parent}
    rows: dict[str, dict] = {"base": {}, "new": {}}
    tmp = Path(tempfile.mkdtemp(prefix="sqparts-bench-match-"))
    for g in range(0, len(args.views), args.group):
        keys = ",".join(args.views[g : g + args.group])
        for side, root in sides.items():
            out = tmp / f"{side}{g}.json"
            script = root / "benchmarks" / "bench_matching.py"
            if not script.exists():  # a base from before this script: run this one with its package
                script = HERE / "bench_matching.py"
            subprocess.run(
                [sys.executable, str(script), "--base", "-", "--worker", str(out), keys],
                check=True,
                env={**env, "PYTHONPATH": str(root)},
                cwd=root,
            )
            rows[side].update(json.loads(out.read_text()))
    import numpy as np

    keys = [k for k in args.views if k in rows["base"] and k in rows["new"]]
    base = np.array([rows["base"][k]["seconds"] for k in keys])
    new = np.array([rows["new"][k]["seconds"] for k in keys])
    diff = max(
        abs(rows["base"][k]["scores"][n] - rows["new"][k]["scores"].get(n, np.nan))
        for k in keys
        for n in rows["base"][k]["scores"]
    )
    summary = {
        "views": len(keys),
        "median_s_base": float(np.median(base)),
        "median_s_new": float(np.median(new)),
        "total_ratio_base_over_new": float(base.sum() / new.sum()),
        "largest_score_difference": float(diff),
        "same_top_object": all(
            max(rows["base"][k]["scores"], key=rows["base"][k]["scores"].get)
            == max(rows["new"][k]["scores"], key=rows["new"][k]["scores"].get)
            for k in keys
        ),
    }
    print(json.dumps(summary, indent=1))
    save("matching", {"base": str(sides["base"]), "summary": summary, "rows": rows})


if __name__ == "__main__":
    main()
