"""Start-up of the CLI: wall time of ``sqparts recover`` and ``sqparts demo`` in new
processes, with an empty cache (cold) and with the cache the previous run left (warm),
and the number of XLA programs a warm call builds.

The baseline is another checkout of the package (``--base``, e.g. made with
``git worktree add /tmp/wt-base 894eee1``); both are run in the same session, their
calls interleaved, so the ratio is honest on a shared machine. Each call is a fresh
``python -m sqparts ...`` with ``PYTHONPATH`` pointing at the checkout and its own
``SQPARTS_CACHE_DIR``. The recovered parts of the two checkouts are compared.

    JAX_PLATFORMS=cpu python benchmarks/bench_cli.py --base /tmp/wt-base [--repeats 5 --demo-repeats 3]

``--demo-repeats 0`` times ``recover`` alone.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import save

ROOT = Path(__file__).resolve().parents[1]
SCENE = {"parts": [{"size": [0.12, 0.08, 0.06], "squareness": [0.5, 0.8], "position": [0.0, 0.0, 1.0]}]}
CAMERA = {"width": 96, "height": 96, "intrinsic_matrix": [110, 0, 0, 0, 110, 0, 47.5, 47.5, 1]}

# Run inside the child: the CLI's main with a counter of XLA programs built (compiled or
# loaded from the persistent cache) and of the tracing/lowering/compiling seconds.
COUNTING = r"""
import sys, json, collections
from jax import monitoring
ev = collections.defaultdict(lambda: [0, 0.0])
def on(name, secs, **kw):
    ev[name][0] += 1; ev[name][1] += secs
monitoring.register_event_duration_secs_listener(on)
from sqparts.cli import main
rc = main(sys.argv[1:])
get = lambda k: ev.get("/jax/core/compile/" + k, [0, 0.0])
print("COUNTS " + json.dumps({"programs": get("backend_compile_duration")[0],
      "trace_s": get("jaxpr_trace_duration")[1], "lower_s": get("jaxpr_to_mlir_module_duration")[1],
      "backend_compile_or_load_s": get("backend_compile_duration")[1]}))
sys.exit(rc)
"""


def run(checkout: Path, cache: Path, args, *, count=False) -> tuple[float, dict]:
    env = dict(os.environ, PYTHONPATH=str(checkout), SQPARTS_CACHE_DIR=str(cache), JAX_PLATFORMS="cpu")
    cmd = [sys.executable, "-c", COUNTING, *args] if count else [sys.executable, "-m", "sqparts", *args]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=tempfile.gettempdir())
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise RuntimeError(f"{checkout}: {' '.join(args)} failed:\n{p.stderr[-3000:]}")
    counts = {}
    for line in p.stdout.splitlines():
        if line.startswith("COUNTS "):
            counts = json.loads(line[7:])
    return wall, counts


def parts_of(out: Path):
    return json.loads((out / "parts.json").read_text())["parts"]


def max_difference(a, b) -> float:
    if len(a) != len(b):
        return float("inf")
    worst = 0.0
    for p, q in zip(a, b):
        for k in set(p) | set(q):
            if isinstance(p.get(k), (list, float, int)) and not isinstance(p.get(k), bool):
                import numpy as np

                worst = max(worst, float(np.max(np.abs(np.asarray(p[k], float) - np.asarray(q[k], float)))))
    return worst


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--base", required=True, type=Path, help="checkout of the baseline")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--demo-repeats", type=int, default=3)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench-cli-"))
    (work / "parts.json").write_text(json.dumps(SCENE))
    (work / "cam.json").write_text(json.dumps(CAMERA))
    run(
        ROOT,
        work / "render-cache",
        [
            "render",
            str(work / "parts.json"),
            "--camera",
            str(work / "cam.json"),
            "--out",
            str(work / "part.npy"),
            "--quiet",
        ],
    )
    variants = {"base": args.base.resolve(), "new": ROOT}
    recover = lambda out: [  # noqa: E731
        "recover",
        str(work / "part.npy"),
        "--camera",
        str(work / "cam.json"),  # noqa: E731
        "--out",
        str(out),
        "--quiet",
        "--overwrite",  # the same output folder every run
    ]
    demo = lambda out: ["demo", "--out", str(out), "--quiet", "--overwrite"]  # noqa: E731
    times = {v: {"recover_cold": [], "recover_warm": [], "demo_cold": [], "demo_warm": []} for v in variants}
    counts = {}
    commands = [(c, m, r) for c, m, r in (("recover", recover, args.repeats), ("demo", demo, args.demo_repeats)) if r]
    for command, make, repeats in commands:
        for _ in range(repeats):  # cold: an empty cache each time, base and new interleaved
            for v, checkout in variants.items():
                cache = work / f"cache-{v}-{command}-cold"
                shutil.rmtree(cache, ignore_errors=True)
                wall, _ = run(checkout, cache, make(work / f"out-{v}-{command}"))
                times[v][f"{command}_cold"].append(wall)
                print(f"{v} {command} cold {wall:.1f} s", flush=True)
        for _ in range(repeats):  # warm: the cache the last cold run left
            for v, checkout in variants.items():
                wall, _ = run(checkout, work / f"cache-{v}-{command}-cold", make(work / f"out-{v}-{command}"))
                times[v][f"{command}_warm"].append(wall)
                print(f"{v} {command} warm {wall:.1f} s", flush=True)
        for v, checkout in variants.items():
            _, c = run(checkout, work / f"cache-{v}-{command}-cold", make(work / f"out-{v}-{command}"), count=True)
            counts.setdefault(v, {})[command] = c
            print(f"{v} {command} warm counts {c}", flush=True)
    same = {
        c: max_difference(parts_of(work / f"out-base-{c}"), parts_of(work / f"out-new-{c}")) for c, _, _ in commands
    }
    summary = {
        v: {k: {"median_s": statistics.median(t), "all_s": t} for k, t in d.items() if t} for v, d in times.items()
    }
    ratios = {k: summary["base"][k]["median_s"] / summary["new"][k]["median_s"] for k in summary["new"]}
    payload = {
        "image": "96x96 pinhole, one part (sqparts render of the scene below)",
        "scene": SCENE,
        "camera": CAMERA,
        "demo": "sqparts demo (built-in human, 128x128)",
        "dtype": "float32",
        "base": str(variants["base"]),
        "repeats": args.repeats,
        "demo_repeats": args.demo_repeats,
        "times": summary,
        "speedup_base_over_new": ratios,
        "warm_counts": counts,
        "max_parameter_difference_base_vs_new": same,
    }
    save("cli", payload)
    for k in summary["new"]:
        print(
            f"{k:14s} base {summary['base'][k]['median_s']:6.1f} s  new {summary['new'][k]['median_s']:6.1f} s  x{ratios[k]:.1f}"
        )
    print("warm counts", counts)
    print("max parameter difference", same)
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
