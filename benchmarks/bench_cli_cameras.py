"""A stream of images from other cameras through the CLI: each image made by another
camera (focal lengths, principal point, image size; a few orthographic) and recovered by
``sqparts recover`` in a new process, the cache starting empty and kept from one call to
the next, as a user with a folder of images from several sensors (or a dataset of
renders) meets it. Wall time per call, and the number of XLA programs each call built
(compiled or loaded from JAX's cache, not from sqparts' exported programs).

The baseline is another checkout (``--base``); its calls alternate with this one's,
image by image, each checkout with its own cache. The recovered parts of the two are
compared.

    JAX_PLATFORMS=cpu python benchmarks/bench_cli_cameras.py --base /tmp/wt-base [--images 10]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import save
from bench_cli import max_difference, parts_of, run

ROOT = Path(__file__).resolve().parents[1]


def stream(n: int, seed: int = 0):
    """(scene, camera) JSON pairs: one or two random parts, each image from its own
    camera, the object filling a random share of it."""
    rng = np.random.default_rng(seed)
    for i in range(n):
        width, height = (int(x) for x in rng.integers(64, 201, 2))
        depth = float(rng.uniform(0.8, 3.0))
        parts = []
        for k in range(1 + i % 2):
            size = rng.uniform(0.04, 0.12, 3)
            parts.append(
                {
                    "size": size.round(4).tolist(),
                    "squareness": rng.uniform(0.2, 1.6, 2).round(3).tolist(),
                    "position": [round(0.12 * k - 0.06 * (i % 2), 4), 0.0, depth],
                    "rotation": _rotation(rng),
                }
            )
        extent = 0.3 if i % 2 else 0.2  # metres the object spans, about
        share = float(rng.uniform(0.35, 0.8))  # of the image's shorter side
        if i % 4 == 3:
            camera = {
                "model": "orthographic",
                "width": width,
                "height": height,
                "pixel_size": round(extent / (share * min(width, height)), 6),
                "cx": round((width - 1) / 2 + float(rng.uniform(-3, 3)), 3),
                "cy": round((height - 1) / 2 + float(rng.uniform(-3, 3)), 3),
            }
        else:
            f = share * min(width, height) * depth / extent
            fx, fy = f * float(rng.uniform(0.97, 1.03)), f * float(rng.uniform(0.97, 1.03))
            cx, cy = (width - 1) / 2 + float(rng.uniform(-4, 4)), (height - 1) / 2 + float(rng.uniform(-4, 4))
            camera = {"width": width, "height": height, "intrinsic_matrix": [fx, 0, 0, 0, fy, 0, cx, cy, 1]}
        yield {"parts": parts}, camera


def _rotation(rng) -> list:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q.round(6).tolist()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--base", required=True, type=Path, help="checkout of the baseline")
    ap.add_argument("--images", type=int, default=10)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench-cli-cameras-"))
    images = []
    for i, (scene, camera) in enumerate(stream(args.images)):
        (work / f"scene{i}.json").write_text(json.dumps(scene))
        (work / f"cam{i}.json").write_text(json.dumps(camera))
        image = work / f"image{i}.npy"
        render = ["render", str(work / f"scene{i}.json"), "--camera", str(work / f"cam{i}.json")]
        run(ROOT, work / "render-cache", [*render, "--out", str(image), "--quiet"])
        images.append((image, work / f"cam{i}.json", camera))
    variants = {"base": args.base.resolve(), "new": ROOT}
    rows = []
    for i, (image, cam, camera) in enumerate(images):
        row = {"image": i, "camera": camera}
        for v, checkout in variants.items():
            out = work / f"out-{v}-{i}"
            command = ["recover", str(image), "--camera", str(cam), "--out", str(out), "--quiet"]
            wall, counts = run(checkout, work / f"cache-{v}", command, count=True)
            row[v] = {"wall_s": wall, **counts, "parts": len(parts_of(out))}
            print(f"image {i} {v}: {wall:.1f} s, {counts.get('programs')} programs", flush=True)
        row["max_parameter_difference"] = max_difference(
            parts_of(work / f"out-base-{i}"), parts_of(work / f"out-new-{i}")
        )
        rows.append(row)
    summary = {}
    for v in variants:
        walls = [r[v]["wall_s"] for r in rows]
        summary[v] = {
            "first_s": walls[0],
            "median_after_first_s": statistics.median(walls[1:]) if len(walls) > 1 else None,
            "total_s": sum(walls),
            "programs_after_first": sum(r[v].get("programs", 0) for r in rows[1:]),
        }
    payload = {
        "what": "sqparts recover on a stream of images, each from another camera, new process per call, one cache",
        "dtype": "float32",
        "base": str(variants["base"]),
        "images": rows,
        "summary": summary,
        "speedup_total_base_over_new": summary["base"]["total_s"] / summary["new"]["total_s"],
    }
    save("cli_cameras", payload)
    for v, s in summary.items():
        print(
            f"{v}: first {s['first_s']:.1f} s, median after {s['median_after_first_s']:.1f} s, "
            f"total {s['total_s']:.1f} s, programs after the first {s['programs_after_first']}"
        )
    print("max parameter difference", [r["max_parameter_difference"] for r in rows])
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
