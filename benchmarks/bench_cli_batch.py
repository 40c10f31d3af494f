"""A batch through the command line: N single-part images in one ``sqparts recover`` call
against N separate calls, one per image (what a user's shell loop does), in new processes
with a warm cache (issue #25: ">= 3x the throughput of 32 separate recoveries").

The images: N random single parts (sizes 0.05-0.12 m, squareness 0.3-1.7, any
orientation, 1 m away; ``default_rng(2000 + i)``) rendered by the 96x96 pinhole camera of
``bench_cli.py``. One call on the first image fills the cache first. Both ways run the
same recovery per image (``recover_scene``'s defaults), so their parts must agree; the
largest parameter difference is reported.

    JAX_PLATFORMS=cpu python benchmarks/bench_cli_batch.py [--images 32]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import save
from bench_cli import CAMERA, max_difference, parts_of, run

import sqparts

ROOT = Path(__file__).resolve().parents[1]


def images(folder: Path, count: int) -> list[Path]:
    camera = sqparts.camera_from_json(CAMERA)
    paths = []
    for i in range(count):
        rng = np.random.default_rng(2000 + i)
        part = sqparts.Part(
            size=rng.uniform(0.05, 0.12, 3).astype(np.float32),
            squareness=rng.uniform(0.3, 1.7, 2).astype(np.float32),
            position=np.array([0.0, 0.0, 1.0], np.float32),
            orientation=rng.normal(size=3).astype(np.float32),
        )
        path = folder / f"part{i:03d}.npy"
        np.save(path, np.asarray(sqparts.render_range_image(part, camera), np.float32))
        paths.append(path)
    return paths


def call(cache: Path, args) -> float:
    """Wall seconds of one ``python -m sqparts ARGS`` in a new process (:func:`bench_cli.run`)."""
    return run(ROOT, cache, args)[0]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--images", type=int, default=32)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench-cli-batch-"))
    (work / "cam.json").write_text(json.dumps(CAMERA))
    paths = images(work, args.images)
    cache = work / "cache"
    camera = ["--camera", str(work / "cam.json"), "--quiet"]
    warm_up = call(cache, ["recover", str(paths[0]), *camera, "--out", str(work / "warm-up")])
    print(f"warm-up call {warm_up:.1f} s", flush=True)
    separate = []
    for k, path in enumerate(paths):
        separate.append(call(cache, ["recover", str(path), *camera, "--out", str(work / "separate" / path.stem)]))
        print(f"separate call {k + 1}/{len(paths)}: {separate[-1]:.1f} s", flush=True)
    batch = call(cache, ["recover", *map(str, paths), *camera, "--out", str(work / "batch")])
    print(f"one call, {len(paths)} images: {batch:.1f} s", flush=True)
    difference = max(
        max_difference(parts_of(work / "separate" / p.stem), parts_of(work / "batch" / p.stem)) for p in paths
    )
    payload = {
        "images": len(paths),
        "image": "96x96 pinhole, one random part each",
        "camera": CAMERA,
        "warm_up_s": warm_up,
        "separate_calls_s": separate,
        "separate_total_s": float(np.sum(separate)),
        "separate_median_s": float(np.median(separate)),
        "one_call_s": batch,
        "throughput_ratio": float(np.sum(separate)) / batch,
        "max_parameter_difference": difference,
    }
    save("cli_batch", payload)
    print(
        f"{len(paths)} separate calls {payload['separate_total_s']:.1f} s (median {payload['separate_median_s']:.1f} s); "
        f"one call {batch:.1f} s; throughput x{payload['throughput_ratio']:.1f}; max parameter difference {difference:.2g}"
    )
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
