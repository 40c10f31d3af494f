import json

import numpy as np
import pytest
import trimesh
from conftest import DATA, random_part_kwargs

import sqparts
from sqparts._io import intrinsics_from_points


def _scene(rng, n=3):
    return sqparts.stack_parts([sqparts.Part(**random_part_kwargs(rng)) for _ in range(n)])


def test_scene_json_round_trip(tmp_path, rng):
    parts = _scene(rng)
    path = tmp_path / "scene.json"
    sqparts.save_scene(path, parts, [{"name": f"p{i}"} for i in range(3)], note="x")
    data = json.loads(path.read_text())
    assert data["note"] == "x" and data["parts"][1]["name"] == "p1"
    rot = np.asarray(data["parts"][0]["rotation"])
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-6)
    back = sqparts.load_scene(path)
    np.testing.assert_allclose(back.size, parts.size, rtol=1e-6)
    np.testing.assert_allclose(
        np.asarray(sqparts.render_range_image(back, sqparts.PinholeCamera(32, 32, 40, 40, 15.5, 15.5))),
        np.asarray(sqparts.render_range_image(parts, sqparts.PinholeCamera(32, 32, 40, 40, 15.5, 15.5))),
        rtol=1e-4,
        equal_nan=True,
    )


@pytest.mark.parametrize(
    "part, match",
    [
        (
            {"size": [1, 1, 1], "squareness": [1, 1], "position": [0, 0, 1], "colour": 3},
            r"parts\[0\]: got unknown key\(s\) \['colour'\]",
        ),
        ({"size": [1, 1, 1], "squareness": [1, 1]}, r"parts\[0\]: got no position, expected keys"),
        (
            {"size": [1, -1, 1], "squareness": [1, 1], "position": [0, 0, 1]},
            r"parts\[0\].size: got .*, expected semi-axes > 0",
        ),
        (
            {
                "size": [1, 1, 1],
                "squareness": [1, 1],
                "position": [0, 0, 1],
                "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 2]],
            },
            r"parts\[0\].rotation: got .*, expected an orthonormal",
        ),
    ],
)
def test_scene_errors(tmp_path, part, match):
    path = tmp_path / "s.json"
    path.write_text(json.dumps({"parts": [part]}))
    with pytest.raises(ValueError, match=match):
        sqparts.load_scene(path)


def test_scene_file_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"scene: got .*, expected an existing file"):
        sqparts.load_scene(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"scene: got .*, expected valid JSON"):
        sqparts.load_scene(tmp_path / "bad.json")
    (tmp_path / "empty.json").write_text('{"parts": []}')
    with pytest.raises(ValueError, match=r"scene.parts: got .*, expected a non-empty list"):
        sqparts.load_scene(tmp_path / "empty.json")


def test_open3d_camera_json(tmp_path):
    # Open3D writes intrinsic_matrix column-major: [fx, 0, 0, 0, fy, 0, cx, cy, 1].
    data = {"width": 640, "height": 480, "intrinsic_matrix": [525.0, 0, 0, 0, 520.0, 0, 319.5, 239.5, 1]}
    path = tmp_path / "cam.json"
    path.write_text(json.dumps(data))
    cam = sqparts.load_camera(path)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (525.0, 520.0, 319.5, 239.5)
    sqparts.save_camera(tmp_path / "out.json", cam)
    assert json.loads((tmp_path / "out.json").read_text()) == data


def test_orthographic_and_scanner_camera_json():
    ortho = sqparts.camera_from_json(
        {"model": "orthographic", "width": 4, "height": 3, "pixel_size": 0.5, "cx": 1.5, "cy": 1.0}
    )
    o, d = ortho.rays()
    np.testing.assert_allclose(o[2, 3], [(3 - 1.5) * 0.5, (2 - 1.0) * 0.5, 0])
    np.testing.assert_allclose(d[0, 0], [0, 0, 1])
    assert sqparts.camera_from_json(ortho.to_json()) == ortho
    scan = sqparts.ScannerCamera(8, 4, 0.01, 0.02, 3.5, 1.5)
    assert sqparts.camera_from_json(scan.to_json()) == scan
    _, d = scan.rays()
    np.testing.assert_allclose(np.linalg.norm(np.asarray(d), axis=-1), 1.0, rtol=1e-6)


@pytest.mark.parametrize(
    "data, match",
    [
        ({"model": "fisheye"}, r"camera.model: got .*, expected one of"),
        ({"width": 4, "height": 3}, r"camera: got no intrinsic_matrix, expected keys"),
        (
            {"width": 4, "height": 3, "intrinsic_matrix": [1, 2, 3]},
            r"camera.intrinsic_matrix: got .*, expected 9 numbers",
        ),
        (
            {"width": -4, "height": 3, "intrinsic_matrix": [1, 0, 0, 0, 1, 0, 0, 0, 1]},
            r"width: got .*, expected a positive integer",
        ),
        (
            {"model": "orthographic", "width": 4, "height": 3, "pixel_size": 0, "cx": 0, "cy": 0},
            r"pixel_size: got .*, expected a finite number > 0",
        ),
        (
            {"model": "orthographic", "width": 4, "height": 3, "pixel_size": 1, "cx": 0, "cy": 0, "fx": 2},
            r"camera: got unknown key\(s\) \['fx'\]",
        ),
    ],
)
def test_camera_errors(data, match):
    with pytest.raises(ValueError, match=match):
        sqparts.camera_from_json(data)


@pytest.mark.parametrize("suffix", [".npy", ".png", ".tif"])
def test_range_image_round_trip(tmp_path, suffix):
    depth = np.full((6, 5), np.nan, np.float32)
    depth[1:4, 1:4] = np.linspace(1.0, 2.0, 9).reshape(3, 3)
    path = tmp_path / f"d{suffix}"
    sqparts.write_range_image(path, depth)
    back, cam = sqparts.read_range_image(path)
    assert cam is None and back.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(back), np.isnan(depth))
    np.testing.assert_allclose(back, depth, atol=6e-4, equal_nan=True)  # png: 1 mm steps


def test_kinect_png_zero_is_no_return(tmp_path):
    from PIL import Image

    raw = np.array([[0, 1000], [2500, 0]], np.uint16)
    Image.fromarray(raw).save(tmp_path / "k.png")
    depth, _ = sqparts.read_range_image(tmp_path / "k.png", depth_scale=0.001)
    np.testing.assert_allclose(depth, [[np.nan, 1.0], [2.5, np.nan]], equal_nan=True)


def test_png_that_is_not_16_bit_depth_is_refused(tmp_path):
    """An 8-bit grey PNG (a picture of depth) was read as 1..255 sensor units; palette
    and RGB PNGs were refused already. Each is one input error naming the file."""
    from PIL import Image

    depth = np.array([[0, 100], [200, 255]], np.uint8)
    Image.fromarray(depth).save(tmp_path / "grey8.png")
    with pytest.raises(ValueError, match=r"input: got an 8-bit PNG \(mode L\) in '.*grey8.png', expected a 16-bit"):
        sqparts.read_range_image(tmp_path / "grey8.png")
    Image.fromarray(depth).convert("P").save(tmp_path / "palette.png")
    Image.fromarray(np.stack([depth] * 3, -1)).save(tmp_path / "rgb.png")
    for name in ("palette.png", "rgb.png"):
        with pytest.raises(
            ValueError, match=r"input: got a PNG \(mode (P|RGB)\).*expected a single-channel 16-bit PNG"
        ):
            sqparts.read_range_image(tmp_path / name)


def test_range_image_errors(tmp_path):
    with pytest.raises(ValueError, match=r"input: got .*, expected a range image ending in"):
        sqparts.read_range_image(tmp_path / "x.jpg")
    with pytest.raises(FileNotFoundError, match=r"input: got .*, expected an existing file"):
        sqparts.read_range_image(tmp_path / "x.npy")
    np.save(tmp_path / "bad.npy", np.zeros((2, 3, 4)))
    with pytest.raises(ValueError, match=r"input: got .*, expected a 2-D numeric range image"):
        sqparts.read_range_image(tmp_path / "bad.npy")
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match=r"input: got .*, expected a readable range image"):
        sqparts.read_range_image(tmp_path / "bad.png")
    with pytest.raises(ValueError, match=r"depth_scale: got .*, expected a number > 0"):
        sqparts.read_range_image(tmp_path / "bad.png", depth_scale=-1)


@pytest.mark.skipif(not (DATA / "grabber_frame0.pcd").exists(), reason="shared data not present")
def test_real_kinect_pcd_recovers_intrinsics():
    depth, cam = sqparts.read_range_image(DATA / "grabber_frame0.pcd")
    assert depth.shape == (480, 640)
    assert 0.08 < np.isnan(depth).mean() < 0.16
    np.testing.assert_allclose([cam.fx, cam.fy, cam.cx, cam.cy], [525, 525, 320, 240], atol=0.05)


def test_intrinsics_from_points_synthetic(rng):
    cam = sqparts.PinholeCamera(40, 30, 50.0, 55.0, 20.3, 14.1)
    depth = rng.uniform(1, 3, (30, 40))
    pts = cam.points(depth)
    got = intrinsics_from_points(pts)
    np.testing.assert_allclose([got.fx, got.fy, got.cx, got.cy], [50, 55, 20.3, 14.1], atol=1e-4)


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".stl", ".glb"])
def test_mesh_export_each_part_watertight(tmp_path, rng, suffix):
    parts = _scene(rng, 2)
    mesh = sqparts.scene_mesh(parts, resolution=8)
    for body in mesh.split(only_watertight=False):
        assert body.is_watertight and body.volume > 0
    sqparts.save_mesh(tmp_path / f"m{suffix}", mesh)
    back = trimesh.load(tmp_path / f"m{suffix}", force="mesh")
    assert len(back.faces) == len(mesh.faces)


def test_part_mesh_volume_matches_closed_form():
    # Ellipsoid volume 4/3 π abc; a box (ε -> small) approaches 8abc.
    ell = sqparts.part_mesh(sqparts.Part(size=[0.1, 0.2, 0.3], position=[0, 0, 1]), resolution=32)
    np.testing.assert_allclose(ell.volume, 4 / 3 * np.pi * 0.006, rtol=5e-3)
    box = sqparts.part_mesh(sqparts.Part(size=[0.1, 0.2, 0.3], squareness=[0.1, 0.1]), resolution=32)
    np.testing.assert_allclose(box.volume, 8 * 0.006, rtol=0.03)


def test_union_mesh_is_one_watertight_body():
    a = sqparts.Part(size=[0.2, 0.2, 0.2], position=[0, 0, 1])
    b = sqparts.Part(size=[0.2, 0.2, 0.2], position=[0.15, 0, 1])
    mesh = sqparts.scene_mesh(sqparts.stack_parts([a, b]), resolution=12, union=True)
    assert mesh.is_watertight
    single = sqparts.part_mesh(a, resolution=12).volume
    assert single < mesh.volume < 2 * single


@pytest.mark.skipif(not (DATA / "teapot.obj").exists(), reason="shared data not present")
def test_render_teapot_mesh():
    mesh = sqparts.load_mesh(DATA / "teapot.obj")
    center = mesh.bounds.mean(0)
    extent = np.ptp(mesh.bounds, axis=0).max()
    mesh = mesh.copy()
    mesh.apply_translation(-center + [0, 0, 2 * extent])
    cam = sqparts.PinholeCamera(48, 48, 60, 60, 23.5, 23.5)
    depth = sqparts.render_mesh(mesh, cam)
    assert 0.1 < np.isfinite(depth).mean() < 0.9
    assert np.nanmin(depth) > 1.4 * extent and np.nanmax(depth) < 2.6 * extent


def test_writing_a_range_image_checks_it(tmp_path):
    """write_range_image wrote 3-D and empty arrays (unreadable back) and depths float32
    cannot hold (as inf); pixels without a return are written as reading gives them."""
    for bad in (np.ones((4, 4, 3)), np.zeros((0, 0)), np.array([["a"]])):
        with pytest.raises(ValueError, match=r"depth: got .* with shape .*, expected a 2-D range image with pixels"):
            sqparts.write_range_image(tmp_path / "w.npy", bad)
    with pytest.raises(ValueError, match=r"depth: got depths up to 1e\+39, expected depths that float32 holds"):
        sqparts.write_range_image(tmp_path / "w.npy", np.full((4, 4), 1e39))
    with pytest.raises(TypeError, match=r"path: got int, expected a file path"):
        sqparts.write_range_image(3, np.ones((4, 4)))
    assert not list(tmp_path.iterdir())
    depth = np.array([[1.0, np.inf], [-2.0, 0.0]])
    sqparts.write_range_image(tmp_path / "w.npy", depth)
    back, _ = sqparts.read_range_image(tmp_path / "w.npy")
    np.testing.assert_array_equal(np.load(tmp_path / "w.npy"), back)
    np.testing.assert_array_equal(back, [[1.0, np.nan], [np.nan, np.nan]])
