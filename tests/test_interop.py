"""Interop with the ecosystem's own readers (issue 29, item 4): cameras read and written by
Open3D itself, RealSense intrinsics, TUM and EXR depth, parts as trimesh / glTF / Open3D
meshes, and ``parts.json`` against its JSON Schema."""

import json
import struct

import numpy as np
import pytest

import sqparts
from sqparts._io import ANNOTATION_KEYS, PART_KEYS

SCENE = {
    "parts": [
        {
            "size": [0.2, 0.15, 0.3],
            "squareness": [0.5, 1.0],
            "position": [-0.25, 0, 2.0],
            "rotation": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
            "taper": 0.2,
        },
        {"size": [0.12, 0.12, 0.25], "squareness": [1.0, 1.0], "position": [0.25, 0.05, 2.0]},
    ]
}


def _open3d():
    try:
        import open3d
    except ImportError as e:  # a wheel exists for CPython 3.8-3.12 on x86-64 Linux, macOS, Windows
        pytest.skip(f"open3d cannot be imported here ({e})")
    return open3d


@pytest.fixture
def parts(tmp_path):
    (tmp_path / "scene.json").write_text(json.dumps(SCENE))
    return sqparts.load_scene(tmp_path / "scene.json")


# --- cameras ---------------------------------------------------------------------------


def test_open3d_reads_the_camera_sqparts_writes(tmp_path):
    o3d = _open3d()
    camera = sqparts.PinholeCamera(32, 24, 40.0, 41.0, 15.5, 11.25)
    sqparts.save_camera(tmp_path / "cam.json", camera)
    intrinsic = o3d.io.read_pinhole_camera_intrinsic(str(tmp_path / "cam.json"))
    assert (intrinsic.width, intrinsic.height) == (32, 24)
    np.testing.assert_allclose(intrinsic.intrinsic_matrix, [[40, 0, 15.5], [0, 41, 11.25], [0, 0, 1]])


def test_sqparts_reads_the_camera_open3d_writes(tmp_path):
    o3d = _open3d()
    intrinsic = o3d.camera.PinholeCameraIntrinsic(640, 480, 525.0, 526.0, 319.5, 239.5)
    assert o3d.io.write_pinhole_camera_intrinsic(str(tmp_path / "o3d.json"), intrinsic)
    camera = sqparts.load_camera(tmp_path / "o3d.json")
    assert camera == sqparts.PinholeCamera(640, 480, 525.0, 526.0, 319.5, 239.5)


def test_sqparts_reads_open3ds_camera_parameters(tmp_path):
    """Open3D's camera parameters (the intrinsics under "intrinsic", beside an extrinsic
    pose) were refused with "got no height, intrinsic_matrix, width"."""
    o3d = _open3d()
    params = o3d.camera.PinholeCameraParameters()
    params.intrinsic = o3d.camera.PinholeCameraIntrinsic(64, 48, 60.0, 80.0, 30.5, 20.25)
    params.extrinsic = np.array([[1, 0, 0, 0.3], [0, 0, -1, 0.1], [0, 1, 0, 2.0], [0, 0, 0, 1.0]])
    assert o3d.io.write_pinhole_camera_parameters(str(tmp_path / "params.json"), params)
    assert sqparts.load_camera(tmp_path / "params.json") == sqparts.PinholeCamera(64, 48, 60.0, 80.0, 30.5, 20.25)


def _write_pcd(path, xyz, viewpoint="0 0 0 1 0 0 0"):
    h, w = xyz.shape[:2]
    rows = "".join(" ".join(f"{v:.9g}" for v in p) + "\n" for p in xyz.reshape(-1, 3))
    path.write_text(
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {w}\nHEIGHT {h}\nVIEWPOINT {viewpoint}\nPOINTS {w * h}\nDATA ascii\n" + rows
    )


def test_an_organized_cloud_not_in_its_cameras_frame_is_refused(tmp_path):
    """The intrinsics are fitted to the points; a cloud moved to a world frame was read
    with made-up intrinsics and a wrong depth (its z), with exit 0. Open3D's reader gives
    the reference points."""
    o3d = _open3d()
    camera = sqparts.PinholeCamera(40, 30, 40.0, 40.0, 19.5, 14.5)
    part = sqparts.Part(size=[0.4, 0.3, 0.2], position=[0.0, 0.0, 1.0])
    depth = np.asarray(sqparts.render_range_image(part, camera), np.float64)
    xyz = camera.points(np.where(np.isfinite(depth), depth, 1.5))  # a wall behind the part
    _write_pcd(tmp_path / "camera.pcd", xyz)
    np.testing.assert_allclose(
        np.asarray(o3d.io.read_point_cloud(str(tmp_path / "camera.pcd")).points), xyz.reshape(-1, 3), rtol=1e-6
    )
    back, cam = sqparts.read_range_image(tmp_path / "camera.pcd")
    np.testing.assert_allclose(back, xyz[..., 2], rtol=1e-6)
    np.testing.assert_allclose([cam.fx, cam.fy, cam.cx, cam.cy], [40, 40, 19.5, 14.5], atol=1e-3)
    a = np.radians(20)
    turn = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    _write_pcd(tmp_path / "world.pcd", xyz @ turn.T + [0.3, -0.2, 0.5])
    with pytest.raises(
        ValueError, match=r"input: got an organized cloud that a pinhole camera at its origin reprojects"
    ):
        sqparts.read_range_image(tmp_path / "world.pcd")
    # The same world points with the camera's pose as their VIEWPOINT (PCL's sensor
    # origin and orientation, qw qx qy qz): read in the camera's frame. The VIEWPOINT was
    # ignored, and such a cloud refused.
    from scipy.spatial.transform import Rotation

    qx, qy, qz, qw = Rotation.from_matrix(turn).as_quat()
    _write_pcd(tmp_path / "posed.pcd", xyz @ turn.T + [0.3, -0.2, 0.5], f"0.3 -0.2 0.5 {qw} {qx} {qy} {qz}")
    back, cam = sqparts.read_range_image(tmp_path / "posed.pcd")
    np.testing.assert_allclose(back, xyz[..., 2], rtol=1e-5)
    np.testing.assert_allclose([cam.fx, cam.fy, cam.cx, cam.cy], [40, 40, 19.5, 14.5], atol=1e-3)
    # A cloud a pinhole explains as it is is read as it is, whatever its VIEWPOINT says
    # (PCL's Kinect grabber writes its camera-frame clouds with a half turn about x).
    _write_pcd(tmp_path / "grabber.pcd", xyz, "0 0 0 0 1 0 0")
    np.testing.assert_allclose(sqparts.read_range_image(tmp_path / "grabber.pcd")[0], xyz[..., 2], rtol=1e-6)
    _write_pcd(tmp_path / "nopose.pcd", xyz @ turn.T + [0.3, -0.2, 0.5], "0 0 0 0 0 0 0")
    with pytest.raises(ValueError, match=r"input: got VIEWPOINT 0 0 0 0 0 0 0, expected tx ty tz qw qx qy qz"):
        sqparts.read_range_image(tmp_path / "nopose.pcd")


REALSENSE = {
    "width": 848,
    "height": 480,
    "ppx": 421.3,
    "ppy": 238.9,
    "fx": 425.1,
    "fy": 425.2,
    "model": "Brown Conrady",
    "coeffs": [0, 0, 0, 0, 0],
}


@pytest.mark.parametrize("wrap", [lambda d: d, lambda d: {"intrinsics": d}, lambda d: {"depth": d, "serial": "1"}])
def test_realsense_intrinsics(tmp_path, wrap):
    (tmp_path / "rs.json").write_text(json.dumps(wrap(REALSENSE)))
    camera = sqparts.load_camera(tmp_path / "rs.json")
    assert camera == sqparts.PinholeCamera(848, 480, 425.1, 425.2, 421.3, 238.9)


@pytest.mark.parametrize(
    "change, match",
    [
        ({"coeffs": [0.1, 0, 0, 0, 0]}, r"camera.coeffs: got \[0.1, .*expected zero distortion"),
        ({"coeffs": "x"}, r"camera.coeffs: got 'x', expected 5 numbers"),
        ({"fx": "a"}, r"camera.fx: got 'a', expected a number"),
        ({"fx": -1.0}, r"fx: got -1.0, expected"),
        ({"skew": 0}, r"camera: got unknown key\(s\) \['skew'\], expected only"),
    ],
)
def test_realsense_intrinsics_errors(tmp_path, change, match):
    (tmp_path / "rs.json").write_text(json.dumps({**REALSENSE, **change}))
    with pytest.raises(ValueError, match=match):
        sqparts.load_camera(tmp_path / "rs.json")


def test_realsense_intrinsics_given_twice_must_agree(tmp_path):
    other = {**REALSENSE, "width": 640, "ppx": 320.0}
    (tmp_path / "rs.json").write_text(json.dumps({"intrinsics": REALSENSE, "depth": REALSENSE}))
    assert sqparts.load_camera(tmp_path / "rs.json").width == 848
    (tmp_path / "rs.json").write_text(json.dumps({"intrinsics": other, "depth": REALSENSE}))
    with pytest.raises(ValueError, match="^camera: got RealSense intrinsics under both 'intrinsics' and 'depth'"):
        sqparts.load_camera(tmp_path / "rs.json")


def test_realsense_intrinsics_missing_a_field_name_it(tmp_path):
    """Without fy the file was read as Open3D's and refused for having no intrinsic_matrix."""
    (tmp_path / "rs.json").write_text(json.dumps({k: v for k, v in REALSENSE.items() if k not in ("fy", "ppy")}))
    with pytest.raises(ValueError, match=r"^camera: got no fy, ppy, expected RealSense intrinsics with keys"):
        sqparts.load_camera(tmp_path / "rs.json")


@pytest.mark.parametrize(
    "wrap",
    [
        lambda d: {**d, "depth_scale": 0.0001},
        lambda d: {"intrinsics": d, "depth_scale": 0.0001},
        lambda d: {"depth": {**d, "depth_scale": 0.0001}},
    ],
    ids=["flat", "beside", "inside"],
)
def test_a_realsense_dumps_depth_scale_reads_its_pngs(tmp_path, capsys, wrap):
    """A dump's depth_scale (here 0.1 mm a unit, as on a D405) was ignored: its PNGs were
    read as millimetres, every depth ten times too large. It is the default now, and a
    --depth-scale that contradicts it is an error."""
    from conftest import cli_error

    from sqparts.cli import main

    small = {**REALSENSE, "width": 32, "height": 24, "fx": 30.0, "fy": 30.0, "ppx": 15.5, "ppy": 11.5}
    (tmp_path / "rs.json").write_text(json.dumps(wrap(small)))
    assert sqparts.camera_depth_scale(tmp_path / "rs.json") == 0.0001
    scene = {
        "parts": [
            {"size": [0.1, 0.1, 0.1], "squareness": [1, 1], "position": [0, 0, 0.5], "rotation": np.eye(3).tolist()}
        ]
    }
    (tmp_path / "scene.json").write_text(json.dumps(scene))
    argv = ["render", str(tmp_path / "scene.json"), "--camera", str(tmp_path / "rs.json")]
    assert main([*argv, "--out", str(tmp_path / "d.png"), "--quiet"]) == 0
    units = np.asarray(__import__("PIL.Image").Image.open(tmp_path / "d.png"))
    assert int(units[units > 0].min()) == pytest.approx(4000, abs=20)  # the sphere's front, 0.4 m, in 0.1 mm units
    err = cli_error(capsys, [*argv, "--out", str(tmp_path / "e.png"), "--depth-scale", "0.001"])
    assert (
        err
        == "sqparts: error: --depth-scale: got 0.001, expected the camera file's depth_scale 0.0001 (or no --depth-scale)"
    )
    assert main([*argv, "--out", str(tmp_path / "f.png"), "--depth-scale", "0.0001", "--quiet"]) == 0
    # Intrinsics without one: millimetres, as before.
    (tmp_path / "mm.json").write_text(json.dumps(small))
    assert sqparts.camera_depth_scale(tmp_path / "mm.json") is None
    (tmp_path / "bad.json").write_text(json.dumps({**small, "depth_scale": -1}))
    with pytest.raises(ValueError, match=r"^camera.depth_scale: got -1, expected a finite number > 0"):
        sqparts.camera_depth_scale(tmp_path / "bad.json")


# --- depth from datasets ----------------------------------------------------------------


def test_a_depth_scale_in_units_per_metre_is_refused(tmp_path, capsys):
    """Open3D and TUM give 1000 or 5000 units per metre; sqparts' --depth-scale is metres
    per unit, so 5000 read millimetres as kilometres, with exit 0."""
    from conftest import cli_error

    line = cli_error(
        capsys, ["show", str(tmp_path / "d.png"), "--out", str(tmp_path / "s.png"), "--depth-scale", "5000"]
    )
    assert line.startswith("sqparts: error: --depth-scale: got '5000', expected a number in (0, 1]: metres per unit"), (
        line
    )


def test_tum_png_at_5000_units_per_metre(tmp_path):
    from PIL import Image

    raw = np.zeros((24, 32), np.uint16)
    raw[4:20, 6:26] = 5000 * 1.5  # 1.5 m
    raw[10, 10] = 5000 * 2 + 1
    Image.fromarray(raw).save(tmp_path / "tum.png")
    depth, camera = sqparts.read_range_image(tmp_path / "tum.png", depth_scale=1 / 5000)
    assert camera is None and np.isnan(depth[0, 0])
    np.testing.assert_allclose(depth[5, 7], 1.5)
    np.testing.assert_allclose(depth[10, 10], 2.0002, rtol=1e-6)


def _write_exr(path, channels):
    OpenEXR = pytest.importorskip("OpenEXR")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, channels).write(str(path))


@pytest.mark.parametrize("channel", ["Z", "depth", "Y", "whatever"])
def test_exr_depth(tmp_path, channel):
    depth = np.linspace(0.5, 3.0, 24 * 32, dtype=np.float32).reshape(24, 32)
    depth[0, :4] = np.inf
    depth[1, :4] = 0
    _write_exr(tmp_path / "d.exr", {channel: depth})
    back, camera = sqparts.read_range_image(tmp_path / "d.exr")
    assert camera is None and back.dtype == np.float32 and back.shape == (24, 32)
    assert np.isnan(back[:2, :4]).all()
    np.testing.assert_array_equal(back[2:], depth[2:])


def test_a_colour_exr_is_not_depth(tmp_path):
    """A colour render's red channel was read as depth; a grey image (R = G = B) still is."""
    depth = np.linspace(0.5, 3.0, 24 * 32, dtype=np.float32).reshape(24, 32)
    _write_exr(tmp_path / "grey.exr", {"R": depth, "G": depth, "B": depth})
    np.testing.assert_array_equal(sqparts.read_range_image(tmp_path / "grey.exr")[0], depth)
    _write_exr(tmp_path / "colour.exr", {"R": depth, "G": depth * 0.5, "B": depth})
    with pytest.raises(ValueError, match=r"input: got channels \['B', 'G', 'R'\] in .*\(R where R, G and B agree"):
        sqparts.read_range_image(tmp_path / "colour.exr")


def test_a_renderers_far_background_is_no_return(tmp_path):
    """Blender's Z pass marks "no hit" as 1e10: the image was refused whole ("rescale the
    image"). Beside returns within range, such depths are no return; an image of nothing
    else is still refused."""
    camera = sqparts.PinholeCamera(32, 24, 30.0, 30.0, 15.5, 11.5)
    depth = np.asarray(sqparts.render_range_image(sqparts.Part(size=[0.2, 0.2, 0.2], position=[0, 0, 1.0]), camera))
    _write_exr(tmp_path / "z.exr", {"Z": np.where(np.isfinite(depth), depth, 1e10).astype(np.float32)})
    back, _ = sqparts.read_range_image(tmp_path / "z.exr")
    data = sqparts.prepare(back, camera)
    np.testing.assert_array_equal(np.isfinite(data.image), np.isfinite(depth))
    with pytest.raises(ValueError, match=r"depth: got returns from 1e\+10 to 1e\+10, expected depths in"):
        sqparts.prepare(np.full((24, 32), 1e10), camera)


def test_exr_errors(tmp_path):
    _write_exr(tmp_path / "uv.exr", {"U": np.ones((24, 32), np.float32), "V": np.ones((24, 32), np.float32)})
    with pytest.raises(ValueError, match=r"input: got channels \['U', 'V'\] in .*, expected one of \['Z'"):
        sqparts.read_range_image(tmp_path / "uv.exr")
    (tmp_path / "bad.exr").write_bytes(b"not an exr")
    with pytest.raises(ValueError, match=r"input: got .*bad.exr', expected a readable OpenEXR file"):
        sqparts.read_range_image(tmp_path / "bad.exr")
    # A header declaring 100 000 x 100 000 pixels is refused before any pixel is decoded.
    _write_exr(tmp_path / "d.exr", {"Z": np.ones((24, 32), np.float32)})
    data = bytearray((tmp_path / "d.exr").read_bytes())
    at = data.index(b"dataWindow\x00box2i\x00") + len(b"dataWindow\x00box2i\x00") + 4
    data[at : at + 16] = struct.pack("<4i", 0, 0, 99_999, 99_999)
    (tmp_path / "big.exr").write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"input: got an image of shape \(100000, 100000\) in .*, expected at most"):
        sqparts.read_range_image(tmp_path / "big.exr")


# --- meshes -----------------------------------------------------------------------------


def test_scene_trimesh_glb_round_trip(tmp_path, parts):
    import trimesh

    scene = sqparts.scene_trimesh(parts, resolution=8)
    sqparts.save_mesh(tmp_path / "model.glb", scene)
    back = trimesh.load(tmp_path / "model.glb")
    assert isinstance(back, trimesh.Scene)
    assert sorted(back.geometry) == ["part_0", "part_1"]
    assert sorted(back.graph.nodes_geometry) == ["part_0", "part_1"]
    colors = sqparts.part_colors(2)
    for i in range(2):
        geometry = back.geometry[f"part_{i}"]
        assert geometry.is_watertight
        np.testing.assert_array_equal(np.unique(geometry.visual.vertex_attributes["color"], axis=0), colors[i : i + 1])
        np.testing.assert_array_equal(geometry.visual.material.baseColorFactor, colors[i])
    # each part where it is: its mesh's centre near the part's position
    for i, d in enumerate(SCENE["parts"]):
        np.testing.assert_allclose(back.geometry[f"part_{i}"].bounds.mean(0)[:2], d["position"][:2], atol=0.03)


def test_ply_that_recover_writes_reads_back_in_trimesh_and_open3d(tmp_path, parts):
    """model.ply is written with numpy (sqparts._mesh.save_ply); both readers must see
    exactly trimesh's own PLY export of the same mesh: same vertices (float32), same
    triangles in the same order, one watertight outward body per part."""
    import trimesh

    from sqparts._mesh import save_ply, scene_surface

    verts, faces = scene_surface(parts, resolution=8)
    save_ply(tmp_path / "ours.ply", verts, faces)
    (tmp_path / "trimesh.ply").write_bytes(trimesh.Trimesh(verts, faces, process=False).export(file_type="ply"))
    ours = trimesh.load(tmp_path / "ours.ply", process=False)
    theirs = trimesh.load(tmp_path / "trimesh.ply", process=False)
    np.testing.assert_array_equal(ours.vertices, theirs.vertices)
    np.testing.assert_array_equal(ours.faces, theirs.faces)
    np.testing.assert_allclose(ours.vertices, verts, atol=1e-6)  # float32 of the float64 surface
    bodies = ours.split(only_watertight=False)
    assert len(bodies) == 2 and all(b.is_watertight and b.volume > 0 for b in bodies)
    o3d = _open3d()
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "ours.ply"))
    np.testing.assert_array_equal(np.asarray(mesh.vertices), theirs.vertices)
    np.testing.assert_array_equal(np.asarray(mesh.triangles), faces)
    with pytest.raises(ValueError, match=r"faces: got indices outside 0\.\.2, expected indices of the vertices"):
        save_ply(tmp_path / "bad.ply", verts[:3], [[0, 1, 3]])
    assert not (tmp_path / "bad.ply").exists()


def test_part_colors_are_report_colors():
    import matplotlib

    from sqparts._plot import _label_rgb

    labels = np.arange(25)[None]
    np.testing.assert_allclose(_label_rgb(labels)[0], sqparts.part_colors(25)[:, :3] / 255, atol=0.5 / 255)
    assert tuple(sqparts.part_colors(1)[0]) == tuple(
        np.round(np.asarray(matplotlib.colormaps["tab20"](0.0)) * 255).astype(int)
    )


def test_scene_trimesh_names(parts):
    assert sorted(sqparts.scene_trimesh(parts, names=["arm", "leg"], resolution=8).geometry) == ["arm", "leg"]
    with pytest.raises(ValueError, match=r"names: got \['arm', 'arm'\], expected 2 distinct names"):
        sqparts.scene_trimesh(parts, names=["arm", "arm"], resolution=8)


def test_scene_open3d(parts):
    _open3d()
    meshes = sqparts.scene_open3d(parts, resolution=8)
    assert len(meshes) == 2
    for mesh, color in zip(meshes, sqparts.part_colors(2)):
        assert mesh.is_watertight() and mesh.has_vertex_normals()
        np.testing.assert_allclose(np.asarray(mesh.vertex_colors), np.tile(color[:3] / 255, (len(mesh.vertices), 1)))


# --- parts.json and its schema ----------------------------------------------------------


def _validator():
    jsonschema = pytest.importorskip("jsonschema")
    schema = sqparts.parts_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def test_schema_ships_with_the_package():
    assert sqparts.PARTS_SCHEMA_PATH.is_file()
    assert sqparts.parts_schema()["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    # the schema's part keys are exactly what the reader accepts
    assert set(sqparts.parts_schema()["$defs"]["part"]["properties"]) == PART_KEYS | ANNOTATION_KEYS


def test_save_scene_file_validates(tmp_path, parts):
    sqparts.save_scene(tmp_path / "s.json", parts, [{"name": "a", "gamma": 3.0}, {}], note="kept as metadata")
    _validator().validate(json.loads((tmp_path / "s.json").read_text()))


@pytest.mark.parametrize(
    "change, path",
    [
        ({"squareness": [3.0, 1.0]}, ["parts", 0, "squareness", 0]),
        ({"size": [0.1, -0.1, 0.2]}, ["parts", 0, "size", 1]),
        ({"colour": "red"}, ["parts", 0]),
        ({"rotation": [[1, 0], [0, 1]]}, ["parts", 0, "rotation", 0]),
        ({"taper": 2}, ["parts", 0, "taper"]),
        ({"size": None}, ["parts", 0, "size"]),
    ],
)
def test_schema_rejects_what_the_reader_rejects(tmp_path, change, path):
    data = json.loads(json.dumps(SCENE))
    data["parts"][0].update(change)
    if change.get("size", 0) is None:
        del data["parts"][0]["size"]
        path = ["parts", 0]
    errors = list(_validator().iter_errors(data))
    assert errors and any(list(e.absolute_path) == path for e in errors), [
        (e.message, list(e.absolute_path)) for e in errors
    ]
    (tmp_path / "bad.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"parts\[0\]"):
        sqparts.load_scene(tmp_path / "bad.json")


def test_schema_rejects_no_parts():
    validator = _validator()
    assert not validator.is_valid({"parts": []})
    assert not validator.is_valid({"camera": {}})


@pytest.mark.slow
def test_recovery_meshes_and_schema(tmp_path):
    import trimesh

    camera = sqparts.PinholeCamera(32, 24, 40.0, 40.0, 15.5, 11.5)
    (tmp_path / "scene.json").write_text(json.dumps(SCENE))
    depth = np.asarray(sqparts.render_range_image(sqparts.load_scene(tmp_path / "scene.json"), camera))
    scene = sqparts.recover_scene(
        depth, camera, scene=sqparts.SceneSettings(resolution=None), refine=sqparts.RefineSettings.none()
    )
    n = len(scene.parts)
    for result in (scene, scene.figures[0]):
        meshes = result.to_trimesh(resolution=6)
        assert isinstance(meshes, trimesh.Scene)
        assert sorted(meshes.geometry) == sorted(f"part_{i}" for i in range(len(result.parts)))
    glb = tmp_path / "model.glb"
    sqparts.save_mesh(glb, scene.to_trimesh(resolution=6))
    assert len(trimesh.load(glb).geometry) == n
    try:
        import open3d  # noqa: F401
    except ImportError:
        pass
    else:
        assert len(scene.to_open3d(resolution=6)) == n
    _validator().validate(json.loads(json.dumps(scene.scene_dict())))
    _validator().validate(json.loads(json.dumps(scene.figures[0].scene_dict())))


def test_readme_export_example(tmp_path, monkeypatch, parts):
    """The README's export example runs as written, on a result's parts."""
    import re
    from pathlib import Path

    from sqparts._recover import _Meshes

    class Result(_Meshes):
        def __init__(self, parts):
            self.parts = parts

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = next(b for b in re.findall(r"```python\n(.*?)```", readme, re.S) if "to_trimesh" in b)
    monkeypatch.chdir(tmp_path)
    sqparts.save_scene("parts.json", parts)
    try:
        import open3d  # noqa: F401
    except ImportError:
        block = block.replace("o3d_meshes = result.to_open3d()", "pass")
    namespace = {"sqparts": sqparts, "result": Result(parts)}
    exec(compile(block, "README.md", "exec"), namespace)
    assert (tmp_path / "model.glb").stat().st_size > 0
    assert sorted(namespace["meshes"].geometry) == ["part_0", "part_1"]


def test_interop_errors(parts, monkeypatch):
    with pytest.raises(ValueError, match=r"camera: got list, expected RealSense intrinsics with keys"):
        sqparts.camera_from_realsense([1, 2])
    monkeypatch.setitem(__import__("sys").modules, "open3d", None)
    with pytest.raises(ImportError, match=r"open3d: got .*, expected open3d installed"):
        sqparts.scene_open3d(parts)


def test_exr_without_openexr(tmp_path, monkeypatch):
    _write_exr(tmp_path / "d.exr", {"Z": np.ones((24, 32), np.float32)})
    monkeypatch.setitem(__import__("sys").modules, "OpenEXR", None)
    with pytest.raises(ValueError, match=r"input: got .*d.exr', expected the OpenEXR package to read it"):
        sqparts.read_range_image(tmp_path / "d.exr")
