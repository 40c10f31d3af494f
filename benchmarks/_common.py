"""Shared benchmark helpers: timing with warm-up, machine description, JSON output."""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import time
from pathlib import Path

import jax

RESULTS = Path(__file__).resolve().parent / "results"


def machine() -> dict:
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    gpu = None
    try:
        gpu = (
            subprocess.run(
                ["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True, text=True, timeout=10
            ).stdout.strip()
            or None
        )
    except (OSError, subprocess.SubprocessError):
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "gpu": gpu,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "devices": [str(d) for d in jax.devices()],
    }


def time_call(fn, *args, repeats: int = 5):
    """(compile_plus_first_call_s, median_s, all_s) of ``fn(*args)`` with block_until_ready."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return first, statistics.median(times), times


def result_path(name: str, ext: str = "json") -> Path:
    """``results/<name><$SQPARTS_BENCH_SUFFIX>.<ext>``: a partial or off-machine run given a
    suffix leaves the committed results (JSON and figures alike) untouched."""
    RESULTS.mkdir(exist_ok=True)
    return RESULTS / f"{name}{os.environ.get('SQPARTS_BENCH_SUFFIX', '')}.{ext}"


def save(name: str, payload: dict) -> Path:
    path = result_path(name)
    payload = {"machine": machine(), "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), **payload}
    path.write_text(json.dumps(payload, indent=2) + "\n")
    print(f"saved {path}")
    return path
