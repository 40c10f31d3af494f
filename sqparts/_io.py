"""Files at the edge: scenes and cameras (JSON), range images (.npy/.png/.tif/.pcd).

Scene JSON (also what recovery writes)::

    {"parts": [{"size": [a1, a2, a3], "squareness": [e1, e2],
                "position": [x, y, z], "rotation": [[...], [...], [...]],
                "bend": [b0, b1], "taper": t}, ...]}

``rotation`` is the 3x3 matrix taking part coordinates to camera coordinates (row-major
nested lists); ``bend`` and ``taper`` are optional (default 0), see :class:`sqparts.Part`.
Per part, ``name``, ``gamma``, ``bits_saved`` and ``fraction_explained`` are accepted as
annotations; any other key is an error. Top-level keys other than ``parts`` are kept as
metadata.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from ._camera import Camera, PinholeCamera, camera_from_json
from ._part import Part, rotation_vector, stack_parts

PART_KEYS = {"size", "squareness", "position", "rotation", "bend", "taper"}
ANNOTATION_KEYS = {"name", "gamma", "bits_saved", "fraction_explained", "pixels", "level", "figure", "prettify", "parent"}
RANGE_IMAGE_SUFFIXES = (".npy", ".png", ".tif", ".tiff", ".pcd")


@contextlib.contextmanager
def atomic_write(path, mode: str = "wb"):
    """Open a temporary file next to ``path`` and move it into place only on success."""
    path = Path(path)
    if path.parent and not path.parent.exists():
        raise FileNotFoundError(f"out: directory {str(path.parent)!r} does not exist")
    fd, tmp = tempfile.mkstemp(dir=path.parent or ".", prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode) as f:
            yield f
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def _load_json(path, what: str):
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what}: no such file {str(path)!r}")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{what}: {str(path)!r} is not valid JSON ({e})") from None


# --- scenes ------------------------------------------------------------------------


def part_from_dict(d: dict, *, index: int = 0) -> tuple[Part, dict]:
    """One part from its JSON dict; returns the part and its annotations."""
    where = f"parts[{index}]"
    if not isinstance(d, dict):
        raise ValueError(f"{where}: expected a JSON object, got {type(d).__name__}")
    unknown = sorted(set(d) - PART_KEYS - ANNOTATION_KEYS)
    if unknown:
        raise ValueError(
            f"{where}: unknown key(s) {unknown}; expected {sorted(PART_KEYS)} "
            f"(+ annotations {sorted(ANNOTATION_KEYS)})"
        )
    missing = sorted({"size", "squareness", "position"} - set(d))
    if missing:
        raise ValueError(f"{where}: missing key(s) {missing}")
    try:
        rotation = np.asarray(d.get("rotation", np.eye(3)), dtype=float)
        orientation = rotation_vector(rotation)
        part = Part(
            size=np.asarray(d["size"], dtype=np.float32),
            squareness=np.asarray(d["squareness"], dtype=np.float32),
            position=np.asarray(d["position"], dtype=np.float32),
            orientation=orientation.astype(np.float32),
            bend=np.asarray(d.get("bend", [0.0, 0.0]), dtype=np.float32),
            taper=np.asarray(d.get("taper", 0.0), dtype=np.float32),
        )
    except (ValueError, TypeError) as e:
        raise ValueError(f"{where}.{e}") from None
    return part, {k: d[k] for k in d if k in ANNOTATION_KEYS}


def part_to_dict(part: Part, **annotations) -> dict:
    """JSON dict of one (unbatched) part, with optional annotations."""
    from ._part import rotation_matrix

    out = {
        "size": np.asarray(part.size, float).tolist(),
        "squareness": np.asarray(part.squareness, float).tolist(),
        "position": np.asarray(part.position, float).tolist(),
        "rotation": np.asarray(rotation_matrix(part.orientation), float).tolist(),
        "bend": np.asarray(part.bend, float).tolist(),
        "taper": float(part.taper),
    }
    out.update({k: _jsonable(v) for k, v in annotations.items()})
    return out


def _jsonable(v):
    if isinstance(v, (np.ndarray, np.generic)) or hasattr(v, "__array__"):
        return np.asarray(v).tolist()
    return v


def scene_from_dict(data) -> tuple[Part, list[dict], dict]:
    """Parse scene JSON: returns (batched parts, per-part annotations, top-level metadata)."""
    if not isinstance(data, dict) or "parts" not in data:
        raise ValueError('scene: expected a JSON object with a "parts" list')
    if not isinstance(data["parts"], list) or not data["parts"]:
        raise ValueError('scene.parts: expected a non-empty list of parts')
    parsed = [part_from_dict(d, index=i) for i, d in enumerate(data["parts"])]
    meta = {k: v for k, v in data.items() if k != "parts"}
    return stack_parts([p for p, _ in parsed]), [a for _, a in parsed], meta


def scene_to_dict(parts: Part, annotations=None, **metadata) -> dict:
    """Scene JSON dict of a batched :class:`Part` (plus annotations and metadata)."""
    n = len(parts)
    annotations = annotations or [{} for _ in range(n)]
    return {
        "parts": [part_to_dict(parts[i], **annotations[i]) for i in range(n)],
        **{k: _jsonable(v) for k, v in metadata.items()},
    }


def load_scene(path) -> Part:
    """Read a scene JSON file into a batched :class:`Part`."""
    parts, _, _ = scene_from_dict(_load_json(path, "scene"))
    return parts


def save_scene(path, parts: Part, annotations=None, **metadata) -> None:
    """Write a scene JSON file atomically."""
    text = json.dumps(scene_to_dict(parts, annotations, **metadata), indent=2)
    with atomic_write(path, "w") as f:
        f.write(text + "\n")


# --- cameras -----------------------------------------------------------------------


def load_camera(path) -> Camera:
    """Read a camera JSON file (Open3D pinhole intrinsics, orthographic or scanner)."""
    return camera_from_json(_load_json(path, "camera"))


def save_camera(path, camera: Camera) -> None:
    with atomic_write(path, "w") as f:
        f.write(json.dumps(camera.to_json(), indent=2) + "\n")


# --- range images ------------------------------------------------------------------


def read_range_image(path, *, depth_scale: float = 0.001) -> tuple[np.ndarray, Camera | None]:
    """Read a range image; returns (float32 depth with NaN = no return, camera or None).

    * ``.npy``: a 2-D float array (NaN, inf or <= 0 = no return).
    * ``.png``: 16-bit grey, depth = value * ``depth_scale`` (default 0.001: millimetres
      to metres, as Kinect/TUM data); 0 = no return.
    * ``.tif``/``.tiff``: 2-D float (or integer, scaled by ``depth_scale``).
    * ``.pcd``: an organized point cloud (x, y, z in the camera frame); the depth is z and
      the pinhole camera is recovered from the points by least squares.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in RANGE_IMAGE_SUFFIXES:
        raise ValueError(
            f"input: expected a range image ending in {', '.join(RANGE_IMAGE_SUFFIXES)}, "
            f"got {str(path)!r}"
        )
    if not path.is_file():
        raise FileNotFoundError(f"input: no such file {str(path)!r}")
    if not (isinstance(depth_scale, (int, float)) and np.isfinite(depth_scale) and depth_scale > 0):
        raise ValueError(f"depth_scale: expected a number > 0, got {depth_scale!r}")
    camera = None
    try:
        if suffix == ".npy":
            depth = np.load(path, allow_pickle=False)
        elif suffix == ".png":
            from PIL import Image

            with Image.open(path) as im:
                raw = np.asarray(im)
            if raw.ndim != 2 or raw.dtype not in (np.uint16, np.int32, np.uint8):
                raise ValueError(
                    f"input: expected a single-channel 16-bit PNG, got {raw.dtype} "
                    f"with shape {raw.shape}"
                )
            depth = np.where(raw == 0, np.nan, raw.astype(np.float64) * depth_scale)
        elif suffix in (".tif", ".tiff"):
            import tifffile

            raw = tifffile.imread(path)
            depth = raw if np.issubdtype(raw.dtype, np.floating) else raw * depth_scale
        else:
            depth, camera = _read_pcd(path)
    except (OSError, ValueError, EOFError) as e:
        msg = str(e)
        if msg.startswith("input:"):
            raise ValueError(msg) from None
        raise ValueError(f"input: could not read {str(path)!r} ({e})") from None
    depth = np.asarray(depth)
    if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.number):
        raise ValueError(
            f"input: expected a 2-D numeric range image, got {depth.dtype} with shape {depth.shape}"
        )
    depth = depth.astype(np.float32)
    depth[~np.isfinite(depth) | (depth <= 0)] = np.nan
    return depth, camera


def _read_pcd(path) -> tuple[np.ndarray, PinholeCamera]:
    from pypcd4 import PointCloud

    pc = PointCloud.from_path(path)
    w, h = int(pc.metadata.width), int(pc.metadata.height)
    if h <= 1:
        raise ValueError(f"input: expected an organized .pcd (height > 1), got height {h}")
    xyz = pc.numpy(("x", "y", "z")).astype(np.float64).reshape(h, w, 3)
    return xyz[..., 2], intrinsics_from_points(xyz)


def intrinsics_from_points(xyz: np.ndarray) -> PinholeCamera:
    """Pinhole intrinsics of an organized cloud by least squares: u = fx x/z + cx."""
    h, w = xyz.shape[:2]
    v, u = np.mgrid[0:h, 0:w]
    ok = np.isfinite(xyz).all(-1) & (xyz[..., 2] > 0)
    if ok.sum() < 10:
        raise ValueError("input: the point cloud has fewer than 10 valid points")
    xz = xyz[..., 0][ok] / xyz[..., 2][ok]
    yz = xyz[..., 1][ok] / xyz[..., 2][ok]
    fx, cx = np.linalg.lstsq(np.c_[xz, np.ones_like(xz)], u[ok], rcond=None)[0]
    fy, cy = np.linalg.lstsq(np.c_[yz, np.ones_like(yz)], v[ok], rcond=None)[0]
    return PinholeCamera(w, h, float(fx), float(fy), float(cx), float(cy))


def write_range_image(path, depth, *, depth_scale: float = 0.001) -> None:
    """Write a range image atomically: .npy (float32, NaN kept), .png (uint16 of
    depth / depth_scale, 0 = no return) or .tif (float32)."""
    path = Path(path)
    depth = np.asarray(depth, dtype=np.float32)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        with atomic_write(path) as f:
            np.save(f, depth)
    elif suffix == ".png":
        from PIL import Image

        scaled = np.where(np.isfinite(depth), np.round(depth / depth_scale), 0)
        if scaled.max(initial=0) > 65535:
            raise ValueError(
                f"depth_scale: depth {np.nanmax(depth):.3g} / {depth_scale} does not fit 16 bits"
            )
        with atomic_write(path) as f:
            Image.fromarray(scaled.astype(np.uint16)).save(f, format="PNG")
    elif suffix in (".tif", ".tiff"):
        import io

        import tifffile

        buffer = io.BytesIO()
        tifffile.imwrite(buffer, depth)
        with atomic_write(path) as f:
            f.write(buffer.getvalue())
    else:
        raise ValueError(f"out: expected a path ending in .npy, .png or .tif, got {str(path)!r}")
