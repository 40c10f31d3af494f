"""Shared benchmark helpers: timing with warm-up, machine description, JSON output, and the
synthetic single-part cases with their whole-surface Chamfer score."""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

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


CHILD_PREAMBLE = r"""
import json, sys, time
import jax
import numpy as np
import sqparts
built = [0]
jax.monitoring.register_event_duration_secs_listener(
    lambda name, secs, **kw: built.__setitem__(0, built[0] + (name == "/jax/core/compile/backend_compile_duration")))
"""
"""The start of a child script for :func:`run_in_checkout`: imports, and ``built[0]``
counting the XLA programs built."""


def run_in_checkout(checkout: Path, child: str, *args: str) -> dict:
    """Run the script ``child`` with ``args`` in a new process importing ``sqparts`` from
    ``checkout`` (on the CPU, from a folder holding no other checkout); returns the JSON
    it prints after ``RESULT ``."""
    env = dict(os.environ, PYTHONPATH=str(checkout), JAX_PLATFORMS="cpu")
    p = subprocess.run(
        [sys.executable, "-c", child, *args], env=env, capture_output=True, text=True, cwd=tempfile.gettempdir()
    )
    if p.returncode != 0:
        raise RuntimeError(f"{checkout}: {' '.join(args)} failed:\n{p.stderr[-3000:]}")
    return json.loads(next(line[7:] for line in p.stdout.splitlines() if line.startswith("RESULT ")))


def interleaved(checkouts: dict, rounds: int, run) -> dict:
    """``run(name, checkout)`` for every checkout (name -> path), ``rounds`` times, the
    checkouts' processes interleaved so that the host's drift loads them alike; returns
    name -> the list of results."""
    got = {v: [] for v in checkouts}
    for _ in range(rounds):
        for v, checkout in checkouts.items():
            got[v].append(run(v, checkout))
    return got


def warm_fields(got: dict) -> dict:
    """Row fields of :func:`interleaved` results that record ``warm_s`` and ``cold_s``:
    every run's times, the warm medians and the base's over the new's (``speedup``)."""
    warm_s = {v: [t for r in runs for t in r["warm_s"]] for v, runs in got.items()}
    median = {v: statistics.median(t) for v, t in warm_s.items()}
    return {
        "warm_median_s": median,
        "warm_s": warm_s,
        "cold_s": {v: [r["cold_s"] for r in runs] for v, runs in got.items()},
        "speedup": median["base"] / median["new"],
    }


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


def make_case(i: int, variants, *, seed: int = 1000, pixels: int = 64):
    """Synthetic single-part case ``i``: a random part (sizes 0.08-0.25 m, squareness
    0.2-1.8, any orientation, 2 m away), half of them bent and tapered, rendered by a
    pinhole or an orthographic camera of ``pixels``² and then left clean, given 2 mm of
    Gaussian noise, quantised to 6 bits or half occluded by a plate in front (``variants``
    names which). Case i cycles through the combinations (camera fastest, then variant,
    then deformed), each drawn from ``default_rng(seed + i)``. The region's centre is the
    visible pixel deepest inside the part's outline (on its skeleton, as region_centers
    picks) and the figure its piece of the rubber sheet (:func:`sqparts.torn_components`)."""
    from scipy.ndimage import distance_transform_edt

    import sqparts

    rng = np.random.default_rng(seed + i)
    pinhole = i % 2 == 0
    variant = variants[(i // 2) % len(variants)]
    deformed = (i // (2 * len(variants))) % 2 == 1
    a = np.sort(rng.uniform(0.08, 0.25, 3))[[1, 0, 2]]
    kw = dict(
        size=a,
        squareness=rng.uniform(0.2, 1.8, 2),
        position=np.r_[rng.uniform(-0.03, 0.03, 2), 2.0],
        orientation=rng.normal(size=3),
    )
    if deformed:
        kw["bend"] = [rng.uniform(-0.3, 0.3), 0.0]
        kw["taper"] = rng.uniform(-0.3, 0.3)
    truth = sqparts.Part(**{k: np.asarray(v, np.float32) for k, v in kw.items()})
    scale = pixels / 64.0  # the same field of view at any resolution
    c = (pixels - 1) / 2.0
    cam = (
        sqparts.PinholeCamera(pixels, pixels, 190.0 * scale, 190.0 * scale, c, c)
        if pinhole
        else sqparts.OrthographicCamera(pixels, pixels, 0.0105 / scale, c, c)
    )
    scene = truth
    if variant == "occluded":
        box = sqparts.Part(
            size=np.array([0.4, 0.4, 0.02], np.float32),
            squareness=np.array([0.2, 0.2], np.float32),
            position=np.array([0.4 if rng.random() < 0.5 else -0.4, 0.0, 1.6], np.float32),
        )
        scene = sqparts.stack_parts([truth, box])
    depth, labels = (np.asarray(x) for x in sqparts.render_range_image(scene, cam, return_labels=True))
    if variant == "noise":
        depth = depth + rng.normal(0, 0.002, depth.shape).astype(np.float32)
    if variant == "6-bit":
        lo, hi = np.nanmin(depth), np.nanmax(depth)
        depth = (lo + np.round((depth - lo) / (hi - lo) * 63) / 63 * (hi - lo)).astype(np.float32)
    visible = labels == 0
    inside = distance_transform_edt(visible)
    centre = np.array(np.unravel_index(np.argmax(inside), inside.shape))
    pieces = sqparts.torn_components(depth, cam)
    figure = pieces == pieces[tuple(centre)]
    return dict(
        truth=truth,
        camera=cam,
        depth=depth,
        figure=figure,
        centre=centre,
        variant=variant,
        pinhole=pinhole,
        deformed=deformed,
        visible=int(visible.sum()),
        occluded_fraction=None,
    )


def chamfer(a, b, n: int = 2000, dense: int = 40000) -> float:
    """Symmetric mean distance between the whole surfaces of ``a`` and ``b`` (a part or a
    batch of parts: the union of their surfaces), hidden sides included: n samples of
    each against a dense (40 000-point) sampling of the other, so the sampling floor is
    ~0.2% of the size."""
    import trimesh
    from scipy.spatial import cKDTree

    import sqparts

    def mesh(parts):
        if parts.batch_shape == ():
            return sqparts.part_mesh(parts, resolution=24)
        return trimesh.util.concatenate([sqparts.part_mesh(parts[i], resolution=24) for i in range(len(parts))])

    ma, mb = mesh(a), mesh(b)
    pa, da = trimesh.sample.sample_surface(ma, n, seed=0)[0], trimesh.sample.sample_surface(ma, dense, seed=2)[0]
    pb, db = trimesh.sample.sample_surface(mb, n, seed=1)[0], trimesh.sample.sample_surface(mb, dense, seed=3)[0]
    return 0.5 * (cKDTree(db).query(pa)[0].mean() + cKDTree(da).query(pb)[0].mean())
