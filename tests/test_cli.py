import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import cli_error

import sqparts
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


@pytest.fixture
def files(tmp_path):
    (tmp_path / "cam.json").write_text(json.dumps(CAMERA))
    (tmp_path / "scene.json").write_text(json.dumps(SCENE))
    return tmp_path


def test_render_mesh_show(files, capsys):
    assert (
        main(["render", str(files / "scene.json"), "--camera", str(files / "cam.json"), "--out", str(files / "d.npy")])
        == 0
    )
    depth = np.load(files / "d.npy")
    assert depth.shape == (24, 32) and depth.dtype == np.float32
    expected = sqparts.render_range_image(
        sqparts.load_scene(files / "scene.json"), sqparts.load_camera(files / "cam.json")
    )
    np.testing.assert_array_equal(depth, np.asarray(expected))
    assert (
        main(["render", str(files / "scene.json"), "--camera", str(files / "cam.json"), "--out", str(files / "d.png")])
        == 0
    )
    assert main(["mesh", str(files / "scene.json"), "--out", str(files / "m.ply")]) == 0
    assert main(["show", str(files / "d.png"), "--out", str(files / "pic.png")]) == 0
    assert (files / "pic.png").stat().st_size > 1000


def test_bad_inputs_give_one_line_and_no_file(files, capsys):
    out = files / "o.npy"
    base = ["render", str(files / "scene.json"), "--camera", str(files / "cam.json"), "--out", str(out)]
    assert "expected an existing file" in cli_error(capsys, ["render", str(files / "nope.json")] + base[2:])
    bad = dict(SCENE, parts=[dict(SCENE["parts"][0], size=[0.2, -1, 0.3])])
    (files / "neg.json").write_text(json.dumps(bad))
    assert "expected semi-axes > 0" in cli_error(capsys, ["render", str(files / "neg.json")] + base[2:])
    unk = dict(SCENE, parts=[dict(SCENE["parts"][0], colour="red")])
    (files / "unk.json").write_text(json.dumps(unk))
    assert "got unknown key(s) ['colour']" in cli_error(capsys, ["render", str(files / "unk.json")] + base[2:])
    (files / "garbage.json").write_text("{]")
    assert "expected valid JSON" in cli_error(
        capsys, ["render", str(files / "scene.json"), "--camera", str(files / "garbage.json"), "--out", str(out)]
    )
    assert "--out: got" in cli_error(capsys, base[:-1] + [str(files / "o.jpg")])
    assert "expected a path in an existing directory" in cli_error(
        capsys, base[:-1] + [str(files / "no" / "dir" / "o.npy")]
    )
    np.save(files / "cube.npy", np.zeros((2, 2, 2)))
    assert "expected a 2-D numeric range image" in cli_error(
        capsys, ["show", str(files / "cube.npy"), "--out", str(files / "p.png")]
    )
    assert "--resolution: got '2', expected an integer in [4, 512]" in cli_error(
        capsys, ["mesh", str(files / "scene.json"), "--out", str(files / "m.ply"), "--resolution", "2"]
    )
    assert not out.exists() and not (files / "p.png").exists() and not (files / "m.ply").exists()
    assert not list(files.glob(".*.tmp"))


def test_python_dash_m_help():
    res = subprocess.run([sys.executable, "-m", "sqparts", "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "render" in res.stdout and "demo" in res.stdout
    res = subprocess.run([sys.executable, "-m", "sqparts", "render"], capture_output=True, text=True)
    assert res.returncode == 2 and "Traceback" not in res.stderr
