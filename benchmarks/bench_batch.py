"""Batches (issue 29): frames per minute of ``recover_many`` in this process and on 1 and
2 Dask workers, and the 500-input run with one failing input.

Throughput (default): the same ``--frames`` synthetic frames (48x48 renders of random
single deformed parts, ``resolution=0``) recovered three ways: in this process, on a
``LocalCluster`` of one worker process, and of two (one thread each). Every way is warmed
up first on one frame per process (the compile, reported separately as ``warmup_s``);
the frames per minute are of the timed batch alone, whose outputs and results.jsonl are
written as by ``sqparts recover``. A ratio is measured in the same run.

Resume (``--resume-check``): ``sqparts recover`` over a folder of ``--inputs`` tiny frames
(24x24, each part covering at least 64 pixels; ``--resolution 0 --refine-rounds 0
--no-figure-ground``), one of them a broken file: exit 1, results.jsonl with a whole line per input
and the failure recorded; then ``--resume`` (redoes the failed one only: the others'
outputs untouched), the broken file repaired and ``--resume`` again (exit 0), and a last
``--resume`` that redoes nothing. Each command's wall time is recorded.

    JAX_PLATFORMS=cpu python benchmarks/bench_batch.py [--frames 64]
    JAX_PLATFORMS=cpu python benchmarks/bench_batch.py --resume-check [--inputs 500]
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

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import save

import sqparts

OPTIONS = dict(resolution=0)


def make_frames(folder: Path, n: int, side: int, *, seed: int = 0, min_returns: int = 0) -> sqparts.PinholeCamera:
    """``n`` renders of random single parts (sizes 0.08-0.3 m at 2 m) into ``folder``;
    a part covering fewer than ``min_returns`` pixels is drawn again."""
    rng = np.random.default_rng(seed)
    focal = side * 5 / 3  # a 0.6 m part at 2 m spans half the image
    camera = sqparts.PinholeCamera(side, side, focal, focal, (side - 1) / 2, (side - 1) / 2)
    folder.mkdir(parents=True, exist_ok=True)
    (folder.parent / "cam.json").write_text(json.dumps(camera.to_json()))
    i = 0
    while i < n:
        part = sqparts.Part(
            size=rng.uniform(0.08, 0.3, 3),
            squareness=rng.uniform(0.2, 1.8, 2),
            position=np.r_[rng.uniform(-0.1, 0.1, 2), 2.0],
            orientation=rng.normal(size=3),
            bend=rng.uniform(-0.3, 0.3, 2),
            taper=rng.uniform(-0.4, 0.4),
        )
        depth = np.asarray(sqparts.render_range_image(part, camera))
        if np.isfinite(depth).sum() >= min_returns:
            np.save(folder / f"frame{i:04d}.npy", depth)
            i += 1
    return camera


def _warm(path, camera, out):
    """One recovery, to compile (runs in this process or on every worker)."""
    from sqparts._batch import enable_compilation_cache, recover_file

    enable_compilation_cache()
    t0 = time.perf_counter()
    recover_file(path, f"{out}-{os.getpid()}", camera=camera, overwrite=True, **OPTIONS)
    return time.perf_counter() - t0


def timed_batch(inputs, camera, out: Path, client=None) -> dict:
    t0 = time.perf_counter()
    records = list(sqparts.recover_many(inputs, out=out, camera=camera, client=client, **OPTIONS))
    seconds = time.perf_counter() - t0
    ok = [r for r in records if r["status"] == "ok"]
    assert len(records) == len(inputs) and len(ok) == len(inputs), [r["error"] for r in records if r["error"]]
    return {
        "seconds": seconds,
        "frames_per_minute": 60 * len(records) / seconds,
        "parts": {r["output"]: r["parts"] for r in records},
        "median_seconds_per_frame": float(np.median([r["seconds"] for r in records])),
    }


def throughput(frames: int) -> dict:
    from distributed import Client, LocalCluster

    with tempfile.TemporaryDirectory(prefix="sqparts-bench-") as tmp:
        tmp = Path(tmp)
        camera = make_frames(tmp / "frames", frames, 48)
        inputs = sorted((tmp / "frames").glob("*.npy"))
        warm = tmp / "warm" / "frame"
        rows = []
        warmup = _warm(inputs[0], camera, warm)
        row = {"how": "one process", "workers": 0, "warmup_s": warmup, **timed_batch(inputs, camera, tmp / "one")}
        rows.append(row)
        print(f"one process: {row['frames_per_minute']:.1f} frames/min (warm-up {warmup:.1f} s)", flush=True)
        for workers in (1, 2):
            t0 = time.perf_counter()
            with (
                LocalCluster(
                    n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None
                ) as cluster,
                Client(cluster) as client,
            ):
                start = time.perf_counter() - t0
                t1 = time.perf_counter()
                client.run(_warm, str(inputs[0]), camera, str(warm))
                warmup = time.perf_counter() - t1
                row = {
                    "how": f"Dask, {workers} worker(s)",
                    "workers": workers,
                    "cluster_start_s": start,
                    "warmup_s": warmup,
                    **timed_batch(inputs, camera, tmp / f"dask{workers}", client),
                }
            rows.append(row)
            print(
                f"{workers} Dask worker(s): {row['frames_per_minute']:.1f} frames/min "
                f"(cluster start {start:.1f} s, warm-up {warmup:.1f} s)",
                flush=True,
            )
        same = all(r["parts"] == rows[0]["parts"] for r in rows)
        print(f"parts counts identical across the three: {same}", flush=True)
        for r in rows:
            r["ratio_to_one_process"] = r["frames_per_minute"] / rows[0]["frames_per_minute"]
            counts = list(r.pop("parts").values())
            r["parts_histogram"] = {str(k): counts.count(k) for k in sorted(set(counts))}
        return {
            "frames": frames,
            "image": "48x48",
            "dtype": "float32",
            "options": OPTIONS,
            "grid": "coarse",
            "refine_rounds": 2,
            "parts_identical": same,
            "rows": rows,
        }


def _cli(args, cwd) -> tuple[int, float, str]:
    env = dict(os.environ, JAX_PLATFORMS=os.environ.get("JAX_PLATFORMS", "cpu"))
    t0 = time.perf_counter()
    res = subprocess.run(
        [sys.executable, "-m", "sqparts", "recover", *args], cwd=cwd, env=env, capture_output=True, text=True
    )
    return res.returncode, time.perf_counter() - t0, (res.stderr.strip().splitlines() or [""])[-1]


def resume_check(n: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="sqparts-bench-") as tmp:
        tmp = Path(tmp)
        make_frames(tmp / "frames", n - 1, 24, min_returns=64)  # recovery wants >= 16 returns
        broken = tmp / "frames" / "frame_broken.npy"
        broken.write_bytes(b"not a range image")
        # Synthetic frames have no background: figure/ground (which may take a flat part
        # for a background plane and leave no figure) is off.
        base = [
            "frames",
            "--camera",
            "cam.json",
            "--out",
            "out",
            "--resolution",
            "0",
            "--refine-rounds",
            "0",
            "--no-figure-ground",
            "--quiet",
        ]
        results = tmp / "out" / "results.jsonl"
        steps = []

        def stamps():
            return {p: p.stat().st_mtime_ns for p in (tmp / "out").rglob("parts.json")}

        def step(name, extra, want):
            before = stamps() if results.exists() else {}
            code, seconds, err = _cli(base + extra, tmp)
            lines = results.read_text().splitlines()
            records = [json.loads(line) for line in lines]
            after = stamps()
            row = {
                "step": name,
                "exit": code,
                "expected_exit": want,
                "seconds": seconds,
                "lines": len(lines),
                "ok": sum(r["status"] == "ok" for r in records),
                "errors": [r["input"] for r in records if r["status"] != "ok"],
                "messages": [r["error"] for r in records if r["status"] != "ok"],
                "outputs_rewritten": sum(after.get(p) != t for p, t in before.items()),
                "outputs_new": len(set(after) - set(before)),
                "stderr_last_line": err,
            }
            steps.append(row)
            print(
                f"{name}: exit {code} in {seconds:.1f} s, {row['lines']} lines ({row['ok']} ok, errors "
                f"{row['errors']}), {row['outputs_rewritten']} outputs rewritten, {row['outputs_new']} new",
                flush=True,
            )
            assert code == want, err
            return row

        first = step("first run", [], 1)
        assert first["lines"] == n and first["errors"] == ["frames/frame_broken.npy"]
        again = step("--resume (broken file still broken)", ["--resume"], 1)
        assert again["outputs_rewritten"] == 0 and again["outputs_new"] == 0 and again["lines"] == n
        np.save(broken, np.load(tmp / "frames" / "frame0000.npy"))
        fixed = step("--resume (broken file repaired)", ["--resume"], 0)
        assert fixed["outputs_rewritten"] == 0 and fixed["outputs_new"] == 1 and fixed["ok"] == n
        nothing = step("--resume (complete)", ["--resume"], 0)
        assert nothing["outputs_rewritten"] == 0 and nothing["outputs_new"] == 0 and nothing["lines"] == n
        return {
            "inputs": n,
            "image": "24x24",
            "options": {"resolution": 0, "refine_rounds": 0, "figure_ground": False},
            "steps": steps,
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--resume-check", action="store_true", help="the 500-input run with one failing input")
    ap.add_argument("--inputs", type=int, default=500)
    args = ap.parse_args()
    if args.resume_check:
        save("batch_resume", resume_check(args.inputs))
    else:
        save("batch", throughput(args.frames))


if __name__ == "__main__":
    main()
