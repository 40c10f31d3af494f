"""Start-up machinery (sqparts/_compile.py) and the shape buckets: exported programs give
the direct call's results, a bad cache entry falls back to tracing, and a recovery runs
few distinct programs, none new for another image size within a bucket."""

import contextlib
import json
import logging
import os
import subprocess
import sys
import threading
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sqparts
from sqparts import _compile
from sqparts._camera import camera_rays
from sqparts._compile import persistent_jit


def _scaled(part, points, *, factor):
    """A Part out (a pytree with a custom node) and an array: exercises both trees."""
    bigger = eqx.tree_at(lambda p: p.size, part, part.size * factor)
    return bigger, jnp.sum(points * part.position, axis=-1) * factor


scaled = persistent_jit(_scaled, static_argnames=("factor",))

PART = sqparts.Part(size=[0.1, 0.2, 0.3], squareness=[0.5, 1.0], position=[0.1, -0.2, 2.0])
POINTS = np.random.default_rng(0).normal(size=(7, 3)).astype(np.float32)


def _reference():
    # Plain numpy, not the code under test.
    return np.array([0.1, 0.2, 0.3]) * 2.0, (POINTS @ np.array([0.1, -0.2, 2.0])) * 2.0


def _check(out):
    size, dots = _reference()
    np.testing.assert_allclose(np.asarray(out[0].size), size, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(out[1]), dots, rtol=1e-5, atol=1e-6)
    assert isinstance(out[0], sqparts.Part)


@pytest.fixture
def export_dir(tmp_path):
    _compile.set_export_dir(tmp_path)
    _compile.forget_loaded()
    yield tmp_path
    _compile.set_export_dir(None)
    _compile.forget_loaded()


def _entries(directory):
    return sorted(directory.glob("*.jaxexport"))


def test_exported_program_matches_direct_call(export_dir, monkeypatch):
    _check(scaled(PART, POINTS, factor=2.0))  # traces, exports, stores
    (entry,) = _entries(export_dir)
    # A new process is simulated by forgetting what was loaded; now it must load, not trace.
    _compile.forget_loaded()
    monkeypatch.setattr(_compile, "_export", lambda *a: pytest.fail("traced again instead of loading"))
    out = scaled(PART, POINTS, factor=2.0)
    _check(out)
    direct = _scaled(PART, jnp.asarray(POINTS), factor=2.0)
    np.testing.assert_allclose(np.asarray(out[1]), np.asarray(direct[1]), rtol=1e-6)
    assert _entries(export_dir) == [entry]


def test_other_shapes_and_static_arguments_get_their_own_entries(export_dir):
    scaled(PART, POINTS, factor=2.0)
    scaled(PART, POINTS[:3], factor=2.0)
    out = scaled(PART, POINTS, factor=3.0)
    assert len(_entries(export_dir)) == 3
    np.testing.assert_allclose(np.asarray(out[0].size), [0.3, 0.6, 0.9], rtol=1e-6)


@pytest.mark.parametrize("damage", ["garbage", "truncated", "flipped", "empty"])
def test_corrupt_entry_falls_back_to_tracing(export_dir, caplog, damage):
    scaled(PART, POINTS, factor=2.0)
    (entry,) = _entries(export_dir)
    blob = entry.read_bytes()
    entry.write_bytes(
        {
            "garbage": b"not an export at all",
            "truncated": blob[: len(blob) // 2],
            "flipped": blob[:-40] + bytes(b ^ 0xFF for b in blob[-40:]),
            "empty": b"",
        }[damage]
    )
    _compile.forget_loaded()
    with caplog.at_level(logging.WARNING, logger="sqparts._compile"):
        _check(scaled(PART, POINTS, factor=2.0))
    assert "ignoring exported program" in caplog.text
    # The bad entry was replaced by a good one.
    _compile.forget_loaded()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="sqparts._compile"):
        _check(scaled(PART, POINTS, factor=2.0))
    assert caplog.text == ""


def test_entry_for_other_shapes_is_not_used(export_dir, caplog):
    """A well-formed entry under the wrong name (a stale or colliding key) is rejected by
    its own argument shapes, never run on the wrong arguments."""
    scaled(PART, POINTS[:3], factor=2.0)
    (small,) = _entries(export_dir)
    scaled(PART, POINTS, factor=2.0)
    (big,) = set(_entries(export_dir)) - {small}
    big.write_bytes(small.read_bytes())
    _compile.forget_loaded()
    with caplog.at_level(logging.WARNING, logger="sqparts._compile"):
        _check(scaled(PART, POINTS, factor=2.0))
    assert "argument shapes or dtypes differ" in caplog.text


def test_failing_exported_call_falls_back(export_dir, monkeypatch, caplog):
    def broken(exported, skeleton):
        def run(leaves):
            raise RuntimeError("cannot run this entry")

        return run

    monkeypatch.setattr(_compile, "_Runner", broken)
    with caplog.at_level(logging.WARNING, logger="sqparts._compile"):
        _check(scaled(PART, POINTS, factor=2.0))
        _check(scaled(PART, POINTS, factor=2.0))  # the plain jit from now on, warned once
    assert caplog.text.count("using jit") == 1


def test_off_by_default_and_by_environment(tmp_path, monkeypatch):
    _compile.set_export_dir(None)
    _check(scaled(PART, POINTS, factor=2.0))
    _compile.set_export_dir(tmp_path)
    try:
        monkeypatch.setenv("SQPARTS_EXPORT", "0")
        _compile.forget_loaded()
        _check(scaled(PART, POINTS, factor=2.0))
        assert _entries(tmp_path) == []
    finally:
        _compile.set_export_dir(None)


def test_inside_jit_it_is_the_plain_function(export_dir):
    out = jax.jit(lambda pts: scaled(PART, pts, factor=2.0))(POINTS)
    _check(out)
    assert _entries(export_dir) == []


def _loads_by_thread(monkeypatch):
    """Record which thread loads each entry (its file name)."""
    seen = []
    load = _compile._load

    def recording(path, avals=None):
        seen.append((threading.current_thread().name, path.name))
        return load(path, avals)

    monkeypatch.setattr(_compile, "_load", recording)
    return seen


def _wait_for_prefetch():
    for future in list(_compile._prefetched.values()):
        future.result()


def test_prefetching_loads_what_the_last_block_used_in_the_background(export_dir, monkeypatch):
    with _compile.prefetching("job"):
        scaled(PART, POINTS[:3], factor=2.0)
        scaled(PART, POINTS, factor=2.0)
        scaled(PART, POINTS[:3], factor=2.0)
    small, big = (e.name for e in sorted(_entries(export_dir), key=lambda e: e.stat().st_mtime_ns))
    assert (export_dir / "job.programs").read_text().split() == [small, big]  # in the order first used
    _compile.forget_loaded()  # a new process
    seen = _loads_by_thread(monkeypatch)
    monkeypatch.setattr(_compile, "_export", lambda *a: pytest.fail("traced again instead of loading"))
    with _compile.prefetching("job"):
        _wait_for_prefetch()
        assert sorted(name for _, name in seen) == sorted([small, big])
        assert all(thread.startswith("sqparts-prefetch") for thread, _ in seen)
        _check(scaled(PART, POINTS, factor=2.0))
        out = scaled(PART, POINTS[:3], factor=2.0)
    assert len(seen) == 2  # the calls took what the background loaded
    np.testing.assert_allclose(np.asarray(out[1]), _reference()[1][:3], rtol=1e-5, atol=1e-6)
    assert not _compile._prefetched  # nothing left behind for a later block


def test_prefetching_a_bad_list_or_entry_changes_no_result(export_dir, monkeypatch, caplog):
    """Garbage, paths outside the folder, missing entries and an entry holding another
    shape's program: each is skipped or rejected, the calls load or trace what they need,
    and the list is rewritten to what was used."""
    scaled(PART, POINTS[:3], factor=2.0)
    (small,) = _entries(export_dir)
    with _compile.prefetching("job"):
        scaled(PART, POINTS, factor=2.0)
    (big,) = set(_entries(export_dir)) - {small}
    big.write_bytes(small.read_bytes())  # the name promises one shape, the program has another
    (export_dir / "job.programs").write_text(
        f"not an entry\n../{small.name}\n{big.name}\nscaled-{'0' * 32}.jaxexport\n\x00\xff\n"
    )
    _compile.forget_loaded()
    with caplog.at_level(logging.WARNING, logger="sqparts._compile"), _compile.prefetching("job"):
        _wait_for_prefetch()
        _check(scaled(PART, POINTS, factor=2.0))
    assert "argument shapes or dtypes differ" in caplog.text
    assert (export_dir / "job.programs").read_text().split() == [big.name]
    _compile.forget_loaded()
    with _compile.prefetching("job"):  # the entry was exported again: now it loads
        _wait_for_prefetch()
        _check(scaled(PART, POINTS, factor=2.0))


def test_prefetching_is_a_plain_block_when_exporting_is_off(tmp_path):
    _compile.set_export_dir(None)
    with _compile.prefetching("job"):
        _check(scaled(PART, POINTS, factor=2.0))
    assert not list(tmp_path.iterdir()) and not _compile._prefetched


def test_the_command_exits_with_mains_status_and_all_its_output(tmp_path):
    """``python -m sqparts`` ends with os._exit: the status, the streams and the files
    must all be there as a normal exit leaves them."""
    sqparts.save_scene(tmp_path / "scene.json", sqparts.stack_parts([PART]))
    (tmp_path / "cam.json").write_text(json.dumps(sqparts.PinholeCamera(16, 12, 20.0, 20.0, 7.5, 5.5).to_json()))
    env = {**os.environ, "SQPARTS_CACHE_DIR": str(tmp_path / "cache"), "JAX_PLATFORMS": "cpu"}
    args = ["render", str(tmp_path / "scene.json"), "--camera", str(tmp_path / "cam.json"), "--out"]
    ok = subprocess.run(
        [sys.executable, "-m", "sqparts", *args, str(tmp_path / "d.npy")], env=env, capture_output=True, text=True
    )
    assert ok.returncode == 0 and "d.npy" in ok.stdout, ok.stderr
    depth = np.load(tmp_path / "d.npy")
    np.testing.assert_array_equal(
        depth, np.asarray(sqparts.render_range_image(PART, sqparts.PinholeCamera(16, 12, 20.0, 20.0, 7.5, 5.5)))
    )
    bad = subprocess.run(
        [sys.executable, "-m", "sqparts", *args, str(tmp_path / "d.npy")], env=env, capture_output=True, text=True
    )
    assert bad.returncode == 2 and bad.stderr.startswith("sqparts: error: ") and bad.stderr.count("\n") == 1


# --- distinct programs per recovery -------------------------------------------------------

_compiles = {"on": False, "n": 0}


def _count(name, seconds, **_):
    if _compiles["on"] and name == "/jax/core/compile/backend_compile_duration":
        _compiles["n"] += 1


jax.monitoring.register_event_duration_secs_listener(_count)


@contextlib.contextmanager
def count_programs():
    """Counts the XLA programs built (compiled, or loaded from the persistent cache)."""
    box = {}
    _compiles.update(on=True, n=0)
    try:
        yield box
    finally:
        box["n"] = _compiles["n"]
        _compiles.update(on=False)


CAM = sqparts.PinholeCamera(48, 48, 180.0, 180.0, 23.5, 23.5)
# Distinct programs a recovery builds (the aim: at most 12). Traced, it builds 6
# of its own and 4 that equinox makes while tracing (constants of its error enumeration);
# loaded from exported programs, only its own.
TRACED_BOUND, EXPORTED_BOUND = 10, 6
KW = dict(search=sqparts.SearchSettings(max_size=0.14, window=48), refine=sqparts.RefineSettings(rounds=1))


ONE_PART = sqparts.Part(
    size=[0.05, 0.07, 0.11], squareness=[0.6, 1.0], position=[0.0, 0.0, 1.2], orientation=[0.3, 0.2, 0.0]
)


@pytest.fixture(scope="module")
def one_part():
    return np.asarray(sqparts.render_range_image(ONE_PART, CAM))


def test_recovery_programs_bounded_and_shared_within_a_bucket(one_part):
    with count_programs() as first:
        rec = sqparts.recover(one_part, CAM, **KW)
    assert len(rec.parts) >= 1
    assert first["n"] <= TRACED_BOUND
    # The same view cropped at the bottom right: another image size, the same rays, the
    # same bucket (48 and 40 x 44 both pad to 320).
    cropped = one_part[:40, :44]
    cam = sqparts.PinholeCamera(44, 40, 180.0, 180.0, 23.5, 23.5)
    assert np.isfinite(cropped).sum() == np.isfinite(one_part).sum()  # the part is all in view
    with count_programs() as second:
        rec2 = sqparts.recover(cropped, cam, **KW)
    assert second["n"] == 0
    np.testing.assert_allclose(rec2.parts.to_vector(), rec.parts.to_vector(), rtol=1e-4, atol=1e-5)
    # Another camera (focal lengths, principal point, image size): its intrinsics are
    # an argument of the programs, not part of them, so it builds none either, and the
    # part comes back as it is.
    other = sqparts.PinholeCamera(64, 56, 204.0, 196.0, 30.2, 27.9)
    seen = np.asarray(sqparts.render_range_image(ONE_PART, other))
    with count_programs() as third:
        rec3 = sqparts.recover(seen, other, **KW)
    assert third["n"] == 0
    assert len(rec3.parts) == 1
    np.testing.assert_allclose(np.sort(np.asarray(rec3.parts.size).ravel()), np.sort(ONE_PART.size), rtol=0.1)
    np.testing.assert_allclose(np.asarray(rec3.parts.position).ravel(), ONE_PART.position, atol=0.01)


def test_a_scenes_figures_share_the_programs_of_one():
    # recover_scene's figures differ in window (32 and 16 pixels here): their
    # full-resolution scoring runs in one frame and their pruning on one set of lattices,
    # so two figures build the programs one does (each scored as on its own window:
    # tests/test_search.py); without the shared lattices they built a pruning program
    # each.
    cam = sqparts.PinholeCamera(96, 96, 180.0, 180.0, 47.5, 47.5)
    parts = sqparts.stack_parts(
        [
            sqparts.Part(
                size=[0.05, 0.07, 0.16], squareness=[0.6, 1.0], position=[-0.1, 0, 1.2], orientation=[0.3, 0.2, 0]
            ),
            sqparts.Part(size=[0.02, 0.02, 0.03], position=[0.12, 0.05, 1.2]),
        ]
    )
    depth = np.asarray(sqparts.render_range_image(parts, cam))
    with count_programs() as built:
        scene = sqparts.recover_scene(depth, cam, refine=sqparts.RefineSettings(rounds=1))
    assert len({f.search.window for f in scene.figures}) == 2
    assert built["n"] <= TRACED_BOUND  # 11 without the sharing, in a fresh process
    # The same in any process (equinox's 4 programs are built once per process, so the
    # count alone passes after another test has traced): the figures name one program.
    programs = {f.search.pruning_program() for f in scene.figures}
    assert len(programs) == 1 and None not in programs


@pytest.mark.parametrize(
    "camera",
    [
        CAM,
        sqparts.OrthographicCamera(width=48, height=48, pixel_size=0.004, cx=23.5, cy=23.5),
        sqparts.ScannerCamera(width=48, height=48, azimuth_step=0.004, elevation_step=0.005, cx=23.5, cy=23.5),
    ],
    ids=["pinhole", "orthographic", "scanner"],
)
def test_pixel_footprints_of_host_depths_compile_nothing(camera):
    # Host depths (a float, numpy) get numpy footprints without a compiled program; traced
    # ones the same values in JAX.
    depth = np.array([[0.5, 1.2], [2.0, 3.5]], np.float32)
    with count_programs() as host:
        one = camera.pixel_size_at(1.2)
        many = camera.pixel_size_at(depth)
        wide = camera.pixel_size_at(depth.astype(np.float64))
    assert host["n"] == 0
    assert isinstance(many, np.ndarray) and many.shape == depth.shape and many.dtype == np.float32
    assert wide.dtype == np.float64
    traced = np.asarray(jax.jit(camera.pixel_size_at)(jnp.asarray(depth)))
    np.testing.assert_allclose(many, traced, rtol=1e-6)
    assert float(one) == pytest.approx(float(traced[0, 1]), rel=1e-6)


@pytest.mark.parametrize(
    "camera",
    [
        sqparts.PinholeCamera(70, 50, 232.72727272727272, 240.0, 34.3, 24.9),
        sqparts.OrthographicCamera(width=48, height=40, pixel_size=0.013, cx=23.5, cy=19.2),
        sqparts.ScannerCamera(width=48, height=40, azimuth_step=0.0123, elevation_step=0.011, cx=23.5, cy=19.5),
    ],
    ids=["pinhole", "orthographic", "scanner"],
)
def test_host_rays_and_points_compile_nothing_and_agree_with_the_compiled_rays(camera):
    # Back-projection on the host (the search's size prior, polishing's points) builds no
    # program; its rays are the compiled programs' rays, bit for bit where no
    # transcendental function enters (the scanner's sines may differ by an ulp).
    depth = np.random.default_rng(0).uniform(0.5, 2.0, (camera.height, camera.width)).astype(np.float32)
    with count_programs() as host:
        origins, directions = camera_rays(camera)
        points = camera.points(depth)
    assert host["n"] == 0
    traced = [np.asarray(a) for a in jax.jit(lambda: camera.rays())()]
    # As the compiled stages take it: the intrinsics an argument, the same rays.
    window = (0, 0, camera.height, camera.width)
    compiled = camera.compiled()
    argument = [np.asarray(a) for a in jax.jit(lambda c: c.rays(window))(compiled)]
    for got, want in zip(argument, traced):
        np.testing.assert_array_equal(got, want)
    assert origins.dtype == directions.dtype == np.float32 and points.dtype == np.float64
    exact = not isinstance(camera, sqparts.ScannerCamera)
    for got, want in zip((origins, directions), traced):
        if exact:
            np.testing.assert_array_equal(got, want)
        else:
            np.testing.assert_allclose(got, want, rtol=0, atol=2e-7)
    np.testing.assert_allclose(points, traced[0] + depth[..., None].astype(np.float64) * traced[1], rtol=1e-6)


@pytest.mark.slow
def test_recovery_from_exported_programs(one_part, tmp_path):
    """A recovery run from exported programs in a "new process" (nothing loaded, JAX's
    in-memory caches cleared) builds only its own programs and recovers the same parts
    as the plain jit."""
    _compile.set_export_dir(None)  # whatever an earlier test (a CLI run in this process) loaded
    _compile.forget_loaded()
    plain = sqparts.recover(one_part, CAM, **KW)
    _compile.set_export_dir(tmp_path)
    try:
        exporting = sqparts.recover(one_part, CAM, **KW)
        assert len(_entries(tmp_path)) >= 5
        _compile.forget_loaded()
        jax.clear_caches()
        with count_programs() as loaded:
            again = sqparts.recover(one_part, CAM, **KW)
    finally:
        _compile.set_export_dir(None)
        _compile.forget_loaded()
    assert loaded["n"] <= EXPORTED_BOUND
    for rec in (exporting, again):
        np.testing.assert_allclose(rec.parts.to_vector(), plain.parts.to_vector(), rtol=1e-4, atol=1e-5)
        assert rec.description_length == pytest.approx(plain.description_length, rel=1e-6)


def test_crowded_processes_release_their_programs():
    """Past the given share of the kernel's mapping limit the compiled programs are dropped
    (and compiled again on the next call); below it nothing is touched."""
    f = jax.jit(lambda x: jnp.sin(x) * 3.0)
    x = jnp.arange(4.0)
    f(x)
    assert f._cache_size() == 1
    assert not _compile.release_if_crowded(fraction=1.0)
    assert f._cache_size() == 1
    if not Path("/proc/self/maps").exists():
        pytest.skip("no /proc: nothing to measure")
    assert _compile.release_if_crowded(fraction=0.0)
    assert f._cache_size() == 0
    np.testing.assert_allclose(np.asarray(f(x)), np.sin(np.arange(4.0)) * 3.0, rtol=1e-6)


def test_the_command_line_leaves_the_callers_caches_as_it_found_them(tmp_path, monkeypatch):
    """main() called from Python turns the caches on for its run only."""
    monkeypatch.setenv("SQPARTS_CACHE_DIR", str(tmp_path / "cache"))
    names = (
        "jax_compilation_cache_dir",
        "jax_persistent_cache_min_compile_time_secs",
        "jax_compilation_cache_max_size",
    )
    before = {n: getattr(jax.config, n) for n in names}
    _compile.set_export_dir(None)
    with _compile.caches_enabled():
        assert _compile._state["dir"] == tmp_path / "cache" / "exported"
        assert jax.config.jax_persistent_cache_min_compile_time_secs == 0.0
        assert jax.config.jax_compilation_cache_max_size == _compile.CACHE_MAX_BYTES
    assert _compile._state["dir"] is None
    assert {n: getattr(jax.config, n) for n in names} == before
    from sqparts.cli import main

    sqparts.save_scene(tmp_path / "scene.json", sqparts.stack_parts([PART]))
    (tmp_path / "cam.json").write_text(json.dumps(sqparts.PinholeCamera(16, 12, 20.0, 20.0, 7.5, 5.5).to_json()))
    argv = ["render", str(tmp_path / "scene.json"), "--camera", str(tmp_path / "cam.json")]
    assert main([*argv, "--out", str(tmp_path / "d.npy"), "--quiet"]) == 0
    assert _compile._state["dir"] is None
    assert {n: getattr(jax.config, n) for n in names} == before


def test_processes_share_the_compilation_cache_under_a_lock(tmp_path):
    """Two processes with the command line's caches on, one after the other: the second
    loads the first's program instead of compiling it, and every entry went through JAX's
    file lock (its ``.lockfile`` and per-entry access times exist only when entries are
    written and read under the lock)."""
    code = (
        "import jax, jax.numpy as jnp\n"
        "from jax._src import monitoring\n"
        "from sqparts._compile import enable_caches\n"
        "seen = []\n"
        "monitoring.register_event_listener(lambda e, **k: seen.append(e.rsplit('/', 1)[-1]))\n"
        "enable_caches()\n"
        "jax.jit(lambda x: jnp.sin(x) * 3)(jnp.arange(5.0)).block_until_ready()\n"
        "print(seen.count('cache_hits'), seen.count('cache_misses'))\n"
    )
    env = {**os.environ, "SQPARTS_CACHE_DIR": str(tmp_path / "cache"), "JAX_PLATFORMS": "cpu"}
    runs = [subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True) for _ in range(2)]
    assert [r.returncode for r in runs] == [0, 0], [r.stderr for r in runs]
    (hits0, misses0), (hits1, misses1) = [map(int, r.stdout.split()[-2:]) for r in runs]
    assert hits0 == 0 and misses0 >= 1  # the first compiles (the arange and the sine)
    assert hits1 == misses0 and misses1 == 0  # the second loads them all
    assert (tmp_path / "cache" / ".lockfile").exists()
    assert list((tmp_path / "cache").glob("*-atime"))


def test_an_entry_left_by_a_killed_process_does_not_stop_the_cache(tmp_path):
    """A process killed between writing a cache entry and its access time leaves an entry
    without one; JAX's eviction then fails on every later write (with a warning: nothing
    new is kept). The command line's caches mend it first, so the next program is kept."""
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "jit_f-0123abcd-cache").write_bytes(b"\0" * 64)  # no jit_f-0123abcd-atime
    code = (
        "import jax, jax.numpy as jnp\n"
        "from sqparts._compile import enable_caches\n"
        "enable_caches()\n"
        "jax.jit(lambda x: jnp.cos(x) + 2)(jnp.arange(3.0)).block_until_ready()\n"
    )
    env = {**os.environ, "SQPARTS_CACHE_DIR": str(cache), "JAX_PLATFORMS": "cpu"}
    run = subprocess.run(
        [sys.executable, "-W", "error::UserWarning", "-c", code], env=env, capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr
    assert "Error writing persistent compilation cache" not in run.stderr
    written = {p.name for p in cache.glob("*-cache")} - {"jit_f-0123abcd-cache"}
    assert written  # the new program was kept
    for entry in cache.glob("*-cache"):
        assert entry.with_name(entry.name.removesuffix("-cache") + "-atime").exists()


def test_concurrently_is_the_loop_in_order(monkeypatch):
    """The threads' results are the loop's, in the items' order, whatever the thread
    count; an exception reaches the caller; ``progress`` sees every call."""
    import time as _time

    def slow_square(x):
        _time.sleep(0.01 * (5 - x))  # later items finish first
        return x * x

    seen = []

    def progress(it):
        for f in it:
            seen.append(f)
            yield f

    for threads in ("1", "3"):
        monkeypatch.setenv("SQPARTS_THREADS", threads)
        seen.clear()
        assert _compile.concurrently(slow_square, range(5), progress=progress) == [0, 1, 4, 9, 16]
        assert len(seen) == 5

        def fails(x):
            if x == 2:
                raise ValueError("item 2")
            return x

        with pytest.raises(ValueError, match="item 2"):
            _compile.concurrently(fails, range(4))


def test_bucketed_polishing_on_threads_equals_one_after_another(monkeypatch):
    """Three buckets of parts polished on two threads: bit for bit what one thread gives."""
    from sqparts._polish import polish_parts

    rng = np.random.default_rng(4)
    parts = sqparts.stack_parts(
        [
            sqparts.Part(size=rng.uniform(0.1, 0.3, 3), position=[0, 0, 2.0], orientation=rng.normal(size=3))
            for _ in range(20)
        ]
    )
    points = (rng.normal(size=(600, 3)) * 0.2 + [0, 0, 2.0]).astype(np.float32)
    weights = (rng.random((20, 600)) < 0.3).astype(np.float32)
    rays = (np.zeros((100, 3), np.float32), np.tile(np.float32([[0, 0, 1]]), (100, 1)))
    ray_weights = (rng.random((20, 100)) < 0.5).astype(np.float32)
    out = {}
    for threads in ("1", "2"):
        monkeypatch.setenv("SQPARTS_THREADS", threads)
        out[threads] = np.asarray(polish_parts(parts, points, weights, 4, rays, ray_weights).to_vector())
    np.testing.assert_array_equal(out["1"], out["2"])
    assert not np.array_equal(out["1"], np.asarray(parts.to_vector()))  # it did polish
    # Two threads split the 20 parts into four calls of five, one thread into three of
    # 7, 7 and 6; a part alone in its call (the rest padding) gets the same fit too.
    for i in (0, 13):
        alone = polish_parts(parts[i : i + 1], points, weights[i : i + 1], 4, rays, ray_weights[i : i + 1])
        np.testing.assert_array_equal(np.asarray(alone.to_vector())[0], out["1"][i])


def test_balanced_groups_cover_the_items_evenly_over_the_threads(monkeypatch):
    for threads, n, sizes in (
        (2, 12, [6, 6]),
        (2, 2, [1, 1]),
        (2, 1, [1]),
        (2, 17, [5, 4, 4, 4]),
        (1, 12, [6, 6]),
        (1, 5, [5]),
        (3, 20, [7, 7, 6]),
        (2, 0, []),
    ):
        monkeypatch.setenv("SQPARTS_THREADS", str(threads))
        groups = _compile.balanced_groups(n, 8)
        assert [len(g) for g in groups] == sizes
        assert np.array_equal(np.concatenate(groups) if groups else np.zeros(0), np.arange(n))
    # On an accelerator the threads do not multiply the device: as few calls as there can be.
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert [len(g) for g in _compile.balanced_groups(17, 8)] == [6, 6, 5]
    assert [len(g) for g in _compile.balanced_groups(2, 8)] == [2]


def test_row_memo_looks_up_what_it_computed_and_forgets_the_oldest():
    memo = _compile.RowMemo(max_bytes=3 * 8)
    memo.put(b"outside", np.float64([0]))
    assert memo.get(b"outside") is None  # outside every scope nothing is kept
    with _compile.memo_scope():
        _row_memo_inside(memo)
    assert memo.get(b"k") is None and memo._bytes == 0  # forgotten when the scope closes


def _row_memo_inside(memo):
    keys = [_compile.RowMemo.key("f", np.float32([i]), i) for i in range(4)]
    assert len(set(keys)) == 4 and keys[0] == _compile.RowMemo.key("f", np.float32([0]), 0)
    assert _compile.RowMemo.key(np.float32([1, 2])) != _compile.RowMemo.key(np.float32([[1, 2]]))
    for i, k in enumerate(keys):
        memo.put(k, np.float64([i]))
    assert memo.get(keys[0]) is None  # the oldest went out: 4 rows of 8 bytes over 24
    assert [float(memo.get(k)[0]) for k in keys[1:]] == [1.0, 2.0, 3.0]
    assert memo.hits == 3
    memo.put(b"k", np.float64([5]))


def test_rendering_and_polishing_look_up_repeats_bit_for_bit():
    """Within a recovery's memo scope a part rendered or polished before is looked up: the
    same bits as computing it afresh, and the lookups happen."""
    rng = np.random.default_rng(6)
    cam = sqparts.PinholeCamera(40, 40, 160.0, 160.0, 19.5, 19.5)
    vectors = np.stack(
        [
            np.asarray(
                sqparts.Part(
                    size=rng.uniform(0.1, 0.3, 3), position=[0, 0, 2.0], orientation=rng.normal(size=3)
                ).to_vector()
            )
            for _ in range(5)
        ]
    ).astype(np.float32)
    points = (rng.normal(size=(300, 3)) * 0.2 + [0, 0, 2.0]).astype(np.float32)
    weights = (rng.random((5, 300)) < 0.3).astype(np.float32)
    rays = (np.zeros((50, 3), np.float32), np.tile(np.float32([[0, 0, 1]]), (50, 1)))
    ray_weights = (rng.random((5, 50)) < 0.5).astype(np.float32)
    with _compile.memo_scope():
        _repeats_inside(vectors, cam, points, weights, rays, ray_weights)


def _repeats_inside(vectors, cam, points, weights, rays, ray_weights):
    from sqparts._encoding import _LAYERS, render_layers
    from sqparts._polish import _POLISHED, polish_parts

    fresh_layers = render_layers(vectors, cam)
    fresh = np.asarray(
        polish_parts(sqparts.Part.from_vector(vectors), points, weights, 20, rays, ray_weights).to_vector()
    )
    hits = _LAYERS.hits, _POLISHED.hits
    order = [3, 0, 3, 4]
    again_layers = render_layers(vectors[order], cam)
    again = polish_parts(sqparts.Part.from_vector(vectors[order]), points, weights[order], 20, rays, ray_weights[order])
    assert _LAYERS.hits - hits[0] == 4 and _POLISHED.hits - hits[1] == 4
    np.testing.assert_array_equal(again_layers, fresh_layers[order])
    np.testing.assert_array_equal(np.asarray(again.to_vector()), fresh[order])
    # Other inputs are not confused with them: other steps, other weights.
    longer = polish_parts(sqparts.Part.from_vector(vectors[:1]), points, weights[:1], 40, rays, ray_weights[:1])
    other = polish_parts(sqparts.Part.from_vector(vectors[:1]), points, weights[1:2], 20, rays, ray_weights[:1])
    assert not np.array_equal(np.asarray(longer.to_vector())[0], fresh[0])
    assert not np.array_equal(np.asarray(other.to_vector())[0], fresh[0])


def test_best_first_selection_builds_no_program():
    """Selection by groups solves problems of several sizes in one recovery: best-first
    runs on the host for every size (no XLA program), and each answer passes a
    brute-force check that no single flip lowers E (best-first's fixed point)."""
    costs = sqparts.Costs(part=112.0, explained=2.0, commission=24.0, omission=6.0, figure_pixels=600)
    rng = np.random.default_rng(5)
    problems = []
    for n in (5, 23, 64):
        explained = np.zeros((n, 600), bool)
        for i in range(n):
            s = rng.integers(0, 540)
            explained[i, s : s + rng.integers(20, 150)] = True
        problems.append(sqparts.SelectionProblem.from_masks(explained, rng.random((n, 600)) < 0.02, costs))
    with count_programs() as built:
        chosen = [sqparts.select_best_first(p) for p in problems]
    assert built["n"] == 0
    for p, x in zip(problems, chosen):
        e = p.energy(x)
        for i in range(p.size):
            flipped = x.copy()
            flipped[i] = ~flipped[i]
            assert p.energy(flipped) >= e - 1e-3


def test_surface_distances_build_one_program_for_any_point_count():
    # Images differ in their figure's point count: the distances go through one program
    # in fixed chunks of points, and equal one unchunked computation.
    from sqparts._polish import POINT_CHUNK, surface_distances

    rng = np.random.default_rng(3)
    parts = sqparts.Part.from_vector(
        np.concatenate(
            [
                rng.uniform(-0.2, 0.2, (3, 3)) + [0.0, 0.0, 1.5],
                rng.uniform(-1.0, 1.0, (3, 3)),
                rng.uniform(0.05, 0.2, (3, 3)),
                rng.uniform(0.3, 1.5, (3, 2)),
                rng.uniform(-0.2, 0.2, (3, 3)),
            ],
            axis=1,
        ).astype(np.float32)
    )
    few, many = (
        rng.uniform(-0.4, 0.4, (k, 3)).astype(np.float32) + [0.0, 0.0, 1.5] for k in (700, 2 * POINT_CHUNK + 300)
    )
    surface_distances(parts, few)
    with count_programs() as later:
        got = surface_distances(parts, many.astype(np.float32))
    assert later["n"] == 0
    assert got.shape == (3, len(many))
    whole = jax.jit(
        jax.vmap(lambda p: jax.vmap(lambda x: sqparts.surface_distance(p, x))(jnp.asarray(many, jnp.float32)))
    )
    np.testing.assert_allclose(got, np.asarray(whole(parts)), rtol=1e-6, atol=1e-7)
