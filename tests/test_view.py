"""The 3-D views (issue 29, item 3): ``sqparts view`` (viser, driven in headless Chromium)
and ``sqparts recover --rerun`` (a Rerun recording read back with rerun's own reader);
``recover`` writes what they need (range.npy, camera.json, pixels.npz)."""

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import cli_error

import sqparts
from sqparts._io import load_view_data, save_view_data
from sqparts._view import STATUS, build_view, view_layers
from sqparts.cli import main

ROOT = Path(__file__).resolve().parents[1]
CAMERA = {"width": 32, "height": 24, "intrinsic_matrix": [40.0, 0, 0, 0, 40.0, 0, 15.5, 11.5, 1]}
SCENE = {
    "parts": [
        {
            "size": [0.2, 0.15, 0.3],
            "squareness": [0.5, 1.0],
            "position": [-0.22, 0, 2.0],
            "rotation": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
            "gamma": 40.0,
            "figure": 0,
            "name": "torso",
        },
        {"size": [0.12, 0.12, 0.2], "squareness": [1.0, 1.0], "position": [0.22, 0.05, 2.0], "figure": 1},
    ]
}
FAST = ["--resolution", "0", "--refine-rounds", "0", "--quiet"]


@pytest.fixture
def out_dir(tmp_path):
    """A recover-like output folder without running a recovery: the scene as parts.json,
    its rendering as range.npy, and every measured pixel explained but one row omitted."""
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "parts.json").write_text(json.dumps({**SCENE, "figures": [{"pixels": 10, "parts": 1}]}))
    parts, camera = sqparts.load_scene(folder / "parts.json"), sqparts.camera_from_json(CAMERA)
    model, labels = (np.asarray(a) for a in sqparts.render_range_image(parts, camera, return_labels=True))
    depth = model.copy()
    depth[12] = np.nan  # a row the sensor missed: commission there
    status = np.where(np.isfinite(model), STATUS["explained"], 0)
    status[12][np.isfinite(model[12])] = STATUS["commission"]
    status[10][np.isfinite(model[10])] = STATUS["omitted"]
    save_view_data(folder, depth, camera, status=status, model=model, labels=labels)
    return folder


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_view_data_round_trip(out_dir):
    data = load_view_data(out_dir)
    assert data["camera"] == sqparts.camera_from_json(CAMERA)
    assert data["depth"].shape == data["status"].shape == data["model"].shape == (24, 32)
    layers = view_layers(data, resolution=6)
    assert [name for name, *_ in layers["parts"]] == ["part_0", "part_1"]
    assert [label for *_, label in layers["parts"]] == ["part_0 · torso · figure 0 · Γ 40", "part_1 · figure 1"]
    assert set(layers["points"]) == {"measured", *STATUS}
    measured, _ = layers["points"]["measured"]
    assert len(measured) == int(np.isfinite(data["depth"]).sum())
    # the measured points lie on the parts' surfaces: z of a point is its depth
    np.testing.assert_allclose(np.sort(measured[:, 2]), np.sort(data["depth"][np.isfinite(data["depth"])]), rtol=1e-6)
    commission, colors = layers["points"]["commission"]
    assert len(commission) == int((data["status"] == STATUS["commission"]).sum()) > 0  # at the model's depth
    assert (colors == [51, 102, 230]).all()


def test_view_data_errors(out_dir, tmp_path):
    with pytest.raises(FileNotFoundError, match=r"folder: got .*, expected a sqparts recover output folder"):
        load_view_data(tmp_path / "nothing")
    with pytest.raises(FileNotFoundError, match=r"folder: got .* without parts.json, expected"):
        load_view_data(tmp_path)
    np.save(out_dir / "range.npy", np.ones((5, 5), np.float32))
    with pytest.raises(ValueError, match=r"range.npy: got shape \(5, 5\), expected \(24, 32\)"):
        load_view_data(out_dir)


def test_view_cli_errors(tmp_path, capsys):
    assert main(["view", str(tmp_path / "nothing")]) == 2
    assert capsys.readouterr().err.startswith("sqparts: error: folder: got ")
    assert main(["view", str(tmp_path), "--port", "70000"]) == 2
    assert "--port: got '70000', expected an integer in [1, 65535]" in capsys.readouterr().err


def test_build_view(out_dir):
    viser = pytest.importorskip("viser")
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        handles = build_view(server, load_view_data(out_dir))
    finally:
        server.stop()
    assert {"parts/part_0", "parts/part_1", "points/measured", "points/explained"} <= set(handles)
    assert handles["parts/part_0"].visible and handles["points/measured"].visible
    assert not handles["points/omitted"].visible


def _chromium():
    """Chromium and its driver from the system (Debian: chromium, chromium-driver)."""
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not (browser and driver):
        pytest.skip("Chromium or chromedriver not installed (.ci/run installs Debian's chromium, chromium-driver)")
    webdriver = pytest.importorskip("selenium.webdriver")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for a in (
        "--headless=new",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        "--window-size=1024,720",
        "--use-gl=angle",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--ignore-gpu-blocklist",
    ):
        options.add_argument(a)
    try:
        return webdriver.Chrome(service=Service(driver), options=options)
    except Exception as e:  # no display libraries, a sandbox that cannot start...
        pytest.skip(f"Chromium cannot start here ({type(e).__name__}: {str(e).splitlines()[0]})")


def color_pixels(image: np.ndarray, color, tolerance: float = 0.03) -> int:
    """Pixels whose chromaticity (RGB direction) is within ``tolerance`` of ``color``'s:
    a part's pixels, however the lights shade it."""
    rgb = image.astype(float)
    unit = rgb / np.maximum(np.linalg.norm(rgb, axis=-1, keepdims=True), 1.0)
    c = np.asarray(color, float)[:3]
    return int((np.linalg.norm(unit - c / np.linalg.norm(c), axis=-1) < tolerance).sum())


CLICK_CHECKBOX = """
for (const box of document.querySelectorAll("input[type=checkbox]")) {
    let row = box.parentElement;  // the smallest element around it holding the label
    while (row && !(row.innerText || "").includes(arguments[0])) row = row.parentElement;
    if (row && row.querySelectorAll("input[type=checkbox]").length === 1) { box.click(); return true; }
}
return false;
"""
"""Click the checkbox whose row's text contains ``arguments[0]``."""


@pytest.mark.slow
def test_viewer_in_headless_chromium(out_dir, tmp_path):
    from PIL import Image

    port = free_port()
    env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
    server = subprocess.Popen(
        [sys.executable, "-m", "sqparts", "view", str(out_dir), "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        cwd=tmp_path,
    )
    try:
        url = None
        for line in server.stdout:  # the viewer announces its address once it serves
            if line.startswith("viewing "):
                url = line.split(" at ")[1].split()[0]
                break
        assert url is not None, "the viewer stopped before serving"
        assert url == f"http://127.0.0.1:{port}"
        browser = _chromium()
        try:
            browser.get(url)
            colors = sqparts.part_colors(2)
            deadline = time.monotonic() + 90
            while True:  # until the scene has arrived over the websocket and been drawn
                time.sleep(2)
                browser.save_screenshot(str(tmp_path / "viewer.png"))
                image = np.asarray(Image.open(tmp_path / "viewer.png").convert("RGB"))
                canvas = image[:, : int(image.shape[1] * 0.6)]  # left of the control panel
                counts = [color_pixels(canvas, c) for c in colors]
                if min(counts) >= 50 or time.monotonic() > deadline:
                    break
            page = " ".join(browser.find_element("tag name", "body").text.split())
            # part_0's checkbox hides it
            assert browser.execute_script(CLICK_CHECKBOX, "part_0 ·")
            hidden = counts[0]
            for _ in range(10):
                time.sleep(1)
                browser.save_screenshot(str(tmp_path / "hidden.png"))
                shown = np.asarray(Image.open(tmp_path / "hidden.png").convert("RGB"))
                hidden = color_pixels(shown[:, : int(shown.shape[1] * 0.6)], colors[0])
                if hidden < counts[0] / 5:
                    break
        finally:
            browser.quit()
        assert min(counts) >= 50, f"part colours' pixels in the screenshot: {counts}"
        assert hidden < counts[0] / 5, f"part_0's pixels after hiding it: {hidden} of {counts[0]}"
        # the control panel lists the parts (toggles), the point layers and the figures
        for text in ("part_0 · torso · figure 0 · Γ 40", "part_1 · figure 1", "measured", "commission", "Figures"):
            assert text in page, text
    finally:
        server.terminate()
        server.wait(timeout=30)


@pytest.mark.slow
def test_recover_writes_view_files_and_rerun(tmp_path):
    pytest.importorskip("rerun")
    (tmp_path / "cam.json").write_text(json.dumps(CAMERA))
    (tmp_path / "scene.json").write_text(
        json.dumps({"parts": [{k: v for k, v in SCENE["parts"][0].items() if k not in ("gamma", "figure", "name")}]})
    )
    depth = np.asarray(
        sqparts.render_range_image(
            sqparts.load_scene(tmp_path / "scene.json"), sqparts.load_camera(tmp_path / "cam.json")
        )
    )
    np.save(tmp_path / "x.npy", depth)
    np.save(tmp_path / "y.npy", depth)
    out, rrd = tmp_path / "out", tmp_path / "run.rrd"
    assert (
        main(
            [
                "recover",
                str(tmp_path / "x.npy"),
                str(tmp_path / "y.npy"),
                "--camera",
                str(tmp_path / "cam.json"),
                "--out",
                str(out),
                "--rerun",
                str(rrd),
                *FAST,
            ]
        )
        == 0
    )
    for name in ("x", "y"):
        assert {"parts.json", "model.ply", "report.png", "range.npy", "camera.json", "pixels.npz"} <= {
            p.name for p in (out / name).iterdir()
        }
        data = load_view_data(out / name)
        assert data["camera"] == sqparts.camera_from_json(CAMERA)
        assert data["status"].max() >= STATUS["explained"]
        jsonschema = pytest.importorskip("jsonschema")
        jsonschema.validate(json.loads((out / name / "parts.json").read_text()), sqparts.parts_schema())
    assert rrd.stat().st_size > 0 and not list(tmp_path.glob(".sqparts-*"))
    from rerun.chunk import RrdReader

    entities = set(RrdReader(rrd).store().schema().entity_paths())
    for name in ("x", "y"):
        assert {f"/{name}/points/measured", f"/{name}/parts/part_0", f"/{name}/camera/depth"} <= entities
    # --rerun: an existing recording is kept unless --overwrite
    assert (
        main(
            [
                "recover",
                str(tmp_path / "x.npy"),
                "--camera",
                str(tmp_path / "cam.json"),
                "--out",
                str(tmp_path / "out2"),
                "--rerun",
                str(rrd),
                *FAST,
            ]
        )
        == 2
    )
    assert not (tmp_path / "out2").exists()


def test_rerun_option_errors(tmp_path, capsys):
    (tmp_path / "cam.json").write_text(json.dumps(CAMERA))
    np.save(tmp_path / "x.npy", np.ones((24, 32), np.float32))
    recover = ["recover", str(tmp_path / "x.npy"), "--camera", str(tmp_path / "cam.json"), "--out", str(tmp_path / "o")]
    assert cli_error(capsys, [*recover, "--rerun", str(tmp_path / "r.txt")]).startswith("sqparts: error: --rerun: got ")
    (tmp_path / "r.rrd").write_bytes(b"x")  # an existing recording is never overwritten
    assert cli_error(capsys, [*recover, "--rerun", str(tmp_path / "r.rrd")]).startswith("sqparts: error: --rerun: got ")
    assert (tmp_path / "r.rrd").read_bytes() == b"x" and not (tmp_path / "o").exists()


def test_view_files_errors(out_dir):
    np.savez(out_dir / "pixels.npz", status=np.zeros((24, 32), np.uint8))
    with pytest.raises(ValueError, match=r"pixels.npz: got .*, expected status, model and labels arrays"):
        load_view_data(out_dir)
    np.savez(out_dir / "pixels.npz", status=np.zeros((2, 2)), model=np.zeros((2, 2)), labels=np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"pixels.npz: got shapes \[\(2, 2\), .*\], expected \(24, 32\)"):
        load_view_data(out_dir)


def test_missing_packages_are_one_line_errors(out_dir, tmp_path, monkeypatch, capsys):
    (tmp_path / "cam.json").write_text(json.dumps(CAMERA))
    np.save(tmp_path / "x.npy", np.ones((24, 32), np.float32))
    recover = ["recover", str(tmp_path / "x.npy"), "--camera", str(tmp_path / "cam.json"), "--out", str(tmp_path / "o")]
    assert main([*recover, "--rerun", str(tmp_path / "no" / "r.rrd")]) == 2
    assert "--rerun: got " in capsys.readouterr().err and not (tmp_path / "o").exists()
    monkeypatch.setitem(sys.modules, "rerun", None)
    assert main([*recover, "--rerun", str(tmp_path / "r.rrd")]) == 2
    assert "--rerun: got no rerun-sdk installed, expected pip install 'sqparts[view]'" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "viser", None)
    assert main(["view", str(out_dir)]) == 2
    assert "view: got no viser, expected it installed (pip install 'sqparts[view]')" in capsys.readouterr().err


def test_parts_only_folder(tmp_path):
    """A folder with parts.json alone (``sqparts demo``'s has no camera): parts, no points."""
    (tmp_path / "parts.json").write_text(json.dumps(SCENE))
    layers = view_layers(load_view_data(tmp_path), resolution=6)
    assert len(layers["parts"]) == 2 and layers["points"] == {}
