"""Many inputs, one command (issue 29): folders and glob patterns, results.jsonl with a
line per input, a failing input recorded while the batch goes on (exit 1), --resume
redoing nothing on a complete run and tolerating a torn last line, signals, and the
same batch on a two-worker Dask LocalCluster."""

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import no_staging_left, spawn_cli

import sqparts
from sqparts import _batch
from sqparts.cli import main

CAMERA = {"width": 32, "height": 24, "intrinsic_matrix": [40.0, 0, 0, 0, 40.0, 0, 15.5, 11.5, 1]}
SCENE = {
    "parts": [
        {
            "size": [0.2, 0.15, 0.3],
            "squareness": [0.5, 1.0],
            "position": [0, 0, 2.0],
            "rotation": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
            "taper": 0.2,
        }
    ]
}
FAST = ["--resolution", "0", "--refine-rounds", "0", "--quiet"]
OUTPUTS = {"parts.json", "model.ply", "report.png", "range.npy", "camera.json", "pixels.npz"}
KEYS = {"input", "output", "status", "parts", "E", "fraction_explained", "seconds", "error"}


@pytest.fixture
def batch(tmp_path):
    """Three renders of one part at three distances in ``in/``, and ``cam.json``."""
    (tmp_path / "cam.json").write_text(json.dumps(CAMERA))
    (tmp_path / "scene.json").write_text(json.dumps(SCENE))
    depth = np.asarray(
        sqparts.render_range_image(
            sqparts.load_scene(tmp_path / "scene.json"), sqparts.load_camera(tmp_path / "cam.json")
        )
    )
    (tmp_path / "in").mkdir()
    for i in range(3):
        np.save(tmp_path / "in" / f"f{i}.npy", depth + 0.1 * i)
    return tmp_path


def recover_argv(tmp, *inputs, out="out"):
    return ["recover", *map(str, inputs), "--camera", str(tmp / "cam.json"), "--out", str(tmp / out), *FAST]


def lines(path: Path) -> list[dict]:
    text = path.read_text()
    assert text.endswith("\n")
    return [json.loads(line) for line in text.splitlines()]


def stamps(folder: Path) -> dict:
    return {p: p.stat().st_mtime_ns for p in folder.rglob("*")}


def test_a_failing_input_is_recorded_and_the_batch_goes_on(batch, capsys):
    (batch / "in" / "f1.npy").write_bytes(b"not a range image")
    assert main(recover_argv(batch, batch / "in")) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("sqparts: error: input: got 1 of 3 inputs failing") and "f1.npy" in err
    records = lines(batch / "out" / "results.jsonl")
    assert [r["output"] for r in records] == ["f0", "f1", "f2"]
    assert all(set(r) == KEYS for r in records)
    bad, good = records[1], [records[0], records[2]]
    assert bad["status"] == "error" and "f1.npy" in bad["error"] and bad["parts"] is None
    assert not (batch / "out" / "f1").exists()
    for r in good:
        assert r["status"] == "ok" and r["error"] is None and r["parts"] >= 1 and r["seconds"] > 0
        assert 0 < r["fraction_explained"] <= 1 and r["E"] > 0
        assert {p.name for p in (batch / "out" / r["output"]).iterdir()} == OUTPUTS
        saved = json.loads((batch / "out" / r["output"] / "parts.json").read_text())
        assert len(saved["parts"]) == r["parts"] and saved["description_length_bits"] == pytest.approx(r["E"])
    assert no_staging_left(batch)

    # --resume redoes only the failed input, once it is fixed; one line per input.
    np.save(batch / "in" / "f1.npy", np.load(batch / "in" / "f0.npy") + 0.05)
    before = stamps(batch / "out" / "f0")
    assert main(recover_argv(batch, batch / "in") + ["--resume"]) == 0
    assert stamps(batch / "out" / "f0") == before
    records = lines(batch / "out" / "results.jsonl")
    assert sorted(r["output"] for r in records) == ["f0", "f1", "f2"]
    assert all(r["status"] == "ok" for r in records)


def test_resume_redoes_nothing_on_a_complete_run(batch, capsys, monkeypatch):
    argv = recover_argv(batch, batch / "in" / "*.npy")  # a glob pattern
    assert main(argv) == 0
    before = stamps(batch / "out")
    assert len(lines(batch / "out" / "results.jsonl")) == 3

    def must_not_run(*args, **kwargs):
        raise AssertionError("recomputed")

    monkeypatch.setattr(_batch, "recover_file", must_not_run)
    assert main(argv + ["--resume"]) == 0
    assert stamps(batch / "out") == before  # results.jsonl included: not even rewritten
    # Without --resume (or --overwrite) the earlier run is never replaced silently.
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("sqparts: error: --out: got") and "--resume" in err and "\n" not in err
    assert stamps(batch / "out") == before


def test_resume_refuses_a_single_recoverys_folder(batch, capsys, monkeypatch):
    """--resume into the folder of one input's recovery (its three files, no
    results.jsonl) wrote a batch's sub-folder and results.jsonl beside them; it is
    refused before any work, the folder as it was."""
    out = batch / "out"
    out.mkdir()
    for name in _batch.OUTPUT_FILES:
        (out / name).write_text("")
    before = stamps(out)
    monkeypatch.setattr(_batch, "recover_file", lambda *a, **k: pytest.fail("recovery ran"))
    assert main(recover_argv(batch, batch / "in" / "f0.npy") + ["--resume"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("sqparts: error: --out: got") and "one recovery's outputs" in err and "\n" not in err
    assert stamps(out) == before


def test_resume_refuses_a_folder_of_no_earlier_run(batch, capsys, monkeypatch):
    """--resume into a folder of the user's own files (no results.jsonl) wrote a batch
    layout among them; it is refused before any work, the folder as it was. A folder
    holding only an interrupted run's staging folders is resumed."""
    out = batch / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    before = stamps(out)
    monkeypatch.setattr(_batch, "recover_file", lambda *a, **k: pytest.fail("recovery ran"))
    assert main(recover_argv(batch, batch / "in") + ["--resume"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("sqparts: error: --resume: got --out") and "no results.jsonl" in err and "\n" not in err
    assert stamps(out) == before
    (out / "notes.txt").unlink()
    (out / ".sqparts-0123.tmp").mkdir()
    plan = _batch.plan_batch([batch / "in"], out=out, camera=batch / "cam.json", resume=True)
    assert len(plan.tasks) == len(list((batch / "in").iterdir()))


def test_resume_ignores_a_torn_last_line(batch):
    argv = recover_argv(batch, batch / "in")
    assert main(argv) == 0
    results = batch / "out" / "results.jsonl"
    complete = results.read_text().splitlines(keepends=True)
    # A crash while f2's line was being written: its outputs are there, its line torn.
    results.write_text("".join(complete[:2]) + complete[2][:25])
    before = stamps(batch / "out" / "f0")
    assert main(argv + ["--resume"]) == 0
    records = lines(results)  # every line whole again
    assert [r["output"] for r in records] == ["f0", "f1", "f2"] and all(r["status"] == "ok" for r in records)
    assert stamps(batch / "out" / "f0") == before
    assert no_staging_left(batch)


def test_resume_after_a_crash_that_tore_the_only_line(batch, capsys):
    # The first input's line torn by a crash: the folder is still a batch's, so --resume
    # finishes it (it said the folder held no results.jsonl), and a run without --resume
    # or --overwrite refuses it.
    argv = recover_argv(batch, batch / "in")
    assert main(argv) == 0
    results = batch / "out" / "results.jsonl"
    results.write_text(results.read_text()[:25])
    assert main(argv) == 2
    assert "holds the results.jsonl of an earlier run" in capsys.readouterr().err
    assert main(argv + ["--resume"]) == 0
    records = lines(results)
    assert [r["output"] for r in records] == ["f0", "f1", "f2"] and all(r["status"] == "ok" for r in records)
    assert no_staging_left(batch)


def test_glob_patterns_folders_and_recursive(batch, tmp_path):
    sub = batch / "in" / "deeper" / "more"
    sub.mkdir(parents=True)
    np.save(sub / "g.npy", np.zeros((24, 32), np.float32))
    (batch / "in" / "notes.txt").write_text("not an image")
    (batch / "in" / ".hidden").mkdir()
    np.save(batch / "in" / ".hidden" / "h.npy", np.zeros((2, 2)))

    def names(paths):
        return [str(p.relative_to(batch / "in")) for p in paths]

    expand = _batch.expand_inputs
    assert names(expand([batch / "in"])) == ["f0.npy", "f1.npy", "f2.npy"]
    assert names(expand([batch / "in"], recursive=True)) == ["deeper/more/g.npy", "f0.npy", "f1.npy", "f2.npy"]
    assert names(expand([str(batch / "in" / "f[12].npy")])) == ["f1.npy", "f2.npy"]
    assert names(expand([str(batch / "in" / "**" / "*.npy")])) == ["deeper/more/g.npy", "f0.npy", "f1.npy", "f2.npy"]
    (sub / "parts.json").write_text("{}")  # an output folder inside the inputs: its report is no input
    (sub / "report.png").write_bytes(b"")
    np.save(sub / "range.npy", np.zeros((2, 2)))  # nor the range image it keeps for `view`
    assert names(expand([batch / "in"], recursive=True)) == ["deeper/more/g.npy", "f0.npy", "f1.npy", "f2.npy"]
    # Nor anything in a batch's --out: a resumed batch took its own outputs for new inputs.
    assert names(expand([batch / "in"], recursive=True, exclude=batch / "in" / "deeper")) == [
        "f0.npy",
        "f1.npy",
        "f2.npy",
    ]
    assert names(expand([str(batch / "in" / "**" / "*.npy")], exclude=sub)) == ["f0.npy", "f1.npy", "f2.npy"]
    with pytest.raises(ValueError, match="input: got pattern .*, which matches no range images"):
        expand([str(batch / "in" / "*.tif")])
    with pytest.raises(ValueError, match="input: got .* twice"):
        expand([batch / "in", str(batch / "in" / "f0.*")])
    with pytest.raises(FileNotFoundError, match="input: got .*, expected an existing file or folder"):
        expand([batch / "nope.npy"])
    with pytest.raises(ValueError, match="input: got folder .*--recursive"):
        expand([batch / "in" / "deeper"])
    assert _batch.output_names([Path("a/x.npy"), Path("b/x.npy"), Path("b/y.npy")]) == ["a/x", "b/x", "y"]


@pytest.mark.parametrize(
    "argv_tail, start",
    [
        (["--resume", "--overwrite"], "--resume: got it with --overwrite"),
        (["--jobs", "2", "--scheduler", "tcp://127.0.0.1:1"], "--jobs: got 2 with --scheduler"),
        (["--jobs", "0"], "--jobs: got '0', expected an integer >= 1"),
    ],
)
def test_batch_command_line_errors_come_before_any_work(batch, capsys, argv_tail, start):
    assert main(recover_argv(batch, batch / "in") + argv_tail) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"sqparts: error: {start}") and "\n" not in err, err
    assert not (batch / "out").exists()


def test_recover_many_in_python(batch):
    records = list(
        sqparts.recover_many(
            [batch / "in" / "f0.npy", batch / "in" / "f2.npy"],
            out=batch / "py",
            camera=batch / "cam.json",
            scene=sqparts.SceneSettings(resolution=0),
            refine=sqparts.RefineSettings.none(),
        )
    )
    assert [r["output"] for r in records] == ["f0", "f2"] and all(r["status"] == "ok" for r in records)
    assert lines(batch / "py" / "results.jsonl") == records
    with pytest.raises(FileExistsError, match="--out: got .*results.jsonl of an earlier run"):
        sqparts.recover_many([batch / "in"], out=batch / "py", camera=batch / "cam.json")
    assert (
        list(
            sqparts.recover_many(
                [batch / "in" / "f0.npy", batch / "in" / "f2.npy"],
                out=batch / "py",
                camera=batch / "cam.json",
                resume=True,
            )
        )
        == []
    )


@pytest.mark.slow
@pytest.mark.parametrize("signum, jobs", [(signal.SIGTERM, []), (signal.SIGINT, ["--jobs", "2"])])
def test_a_signal_stops_the_batch_keeping_finished_inputs_and_whole_lines(batch, signum, jobs):
    for i in range(3, 6):
        np.save(batch / "in" / f"f{i:02d}.npy", np.load(batch / "in" / "f0.npy") + 0.01 * i)
    results = batch / "out" / "results.jsonl"
    proc = spawn_cli(recover_argv(batch, batch / "in") + jobs)
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        if results.exists() and results.read_text().count("\n") >= 1:
            break
        time.sleep(0.2)
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=180)
    assert proc.returncode in (0, 128 + signum), err  # 0: it finished before the signal
    assert "Traceback" not in err
    records = lines(results)  # whole lines only
    assert 1 <= len(records) <= 6 and (len(records) == 6 or proc.returncode != 0)
    for r in records:
        assert r["status"] == "ok" and {p.name for p in (batch / "out" / r["output"]).iterdir()} == OUTPUTS
    assert no_staging_left(batch)
    # Finishing the batch redoes none of what was done.
    done = {r["output"]: (batch / "out" / r["output"] / "parts.json").stat().st_mtime_ns for r in records}
    assert main(recover_argv(batch, batch / "in") + ["--resume"]) == 0
    assert {k: (batch / "out" / k / "parts.json").stat().st_mtime_ns for k in done} == done
    assert len(lines(results)) == 6


@pytest.mark.slow
def test_two_dask_workers_give_the_single_process_results(batch):
    from distributed import Client, LocalCluster

    (batch / "in" / "f9.npy").write_bytes(b"broken")
    inputs = [batch / "in"]
    here = {
        r["output"]: r
        for r in sqparts.recover_many(
            inputs,
            out=batch / "one",
            camera=batch / "cam.json",
            scene=sqparts.SceneSettings(resolution=0),
            refine=sqparts.RefineSettings.none(),
        )
    }
    with (
        LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        records = list(
            sqparts.recover_many(
                inputs,
                out=batch / "two",
                camera=batch / "cam.json",
                client=client,
                scene=sqparts.SceneSettings(resolution=0),
                refine=sqparts.RefineSettings.none(),
            )
        )
        workers = client.run(lambda: os.getpid())
    assert len(workers) == 2
    assert sorted(r["output"] for r in records) == ["f0", "f1", "f2", "f9"]
    assert sorted(r["output"] for r in lines(batch / "two" / "results.jsonl")) == ["f0", "f1", "f2", "f9"]
    for r in records:
        assert r["status"] == here[r["output"]]["status"]
        assert r["parts"] == here[r["output"]]["parts"]
        if r["status"] == "ok":
            assert {p.name for p in (batch / "two" / r["output"]).iterdir()} == OUTPUTS
    assert records_by(records)["f9"]["status"] == "error" and "f9.npy" in records_by(records)["f9"]["error"]
    assert no_staging_left(batch)


def records_by(records):
    return {r["output"]: r for r in records}


@pytest.mark.slow
def test_the_local_cluster_prints_none_of_distributed_s_own_errors(capfd):
    """--jobs reports every failure as an error record. What distributed logs besides, in the
    workers and here, is its own shutdown races: a worker's heartbeat to a closing scheduler
    printed a traceback after Ctrl-C. Its errors are logged, in each process, and not printed."""
    import logging

    from sqparts._dask import local_cluster

    with local_cluster(1) as client:
        client.run(lambda: logging.getLogger("distributed.worker").error("heartbeat failed (worker)"))
        logging.getLogger("distributed.scheduler").error("heartbeat failed (here)")
    err = capfd.readouterr().err
    assert "heartbeat failed" not in err, err
