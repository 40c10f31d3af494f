"""Independent compiled calls on threads (``sqparts._compile.concurrently``): warm
recovery of built-in scenes with one thread per core against ``SQPARTS_THREADS=1`` (one
call after another, the code before threads), interleaved in one process, and whether the
two give bit-for-bit the same parts.

    python benchmarks/bench_threads.py [--scenes human chair castings] [--runs 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import save

import sqparts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["human", "chair", "castings"])
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    from sqparts._compile import _cores

    rows = []
    for name in args.scenes:
        scene = sqparts.builtin_scene(name)
        depth = np.asarray(sqparts.render_range_image(scene.parts, scene.camera))
        sqparts.recover(depth, scene.camera)  # compile
        times: dict[str, list[float]] = {"serial": [], "threads": []}
        results = {}
        for _ in range(args.runs):
            for mode, value in (("serial", "1"), ("threads", "0")):
                os.environ["SQPARTS_THREADS"] = value
                t = time.perf_counter()
                rec = sqparts.recover(depth, scene.camera)
                times[mode].append(time.perf_counter() - t)
                results[mode] = (len(rec.parts), float(rec.cost.total), np.asarray(rec.parts.to_vector()))
        os.environ.pop("SQPARTS_THREADS")
        serial, threads = (statistics.median(times[m]) for m in ("serial", "threads"))
        same = results["serial"][:2] == results["threads"][:2] and np.array_equal(
            results["serial"][2], results["threads"][2]
        )
        row = dict(
            scene=name,
            parts=results["threads"][0],
            description_length_bits=results["threads"][1],
            serial_s=times["serial"],
            threads_s=times["threads"],
            median_serial_s=serial,
            median_threads_s=threads,
            speed_up=serial / threads,
            identical=bool(same),
        )
        rows.append(row)
        print(
            f"{name}: {serial:.2f} s one after another, {threads:.2f} s on {_cores()} threads "
            f"({serial / threads:.2f}x), identical: {same}",
            flush=True,
        )
    save("threads", {"threads": _cores(), "scenes": rows})


if __name__ == "__main__":
    main()
