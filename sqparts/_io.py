"""Files at the edge: scenes and cameras (JSON), range images (.npy/.png/.tif/.pcd/.exr).

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

import collections
import contextlib
import json
import logging
import math
import numbers
import os
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from ._camera import MAX_PIXELS, MAX_SIDE, Camera, PinholeCamera, camera_from_json, json_numbers
from ._part import Part, rotation_vector, stack_parts

PART_KEYS = {"size", "squareness", "position", "rotation", "bend", "taper"}
ANNOTATION_KEYS = {
    "name",
    "gamma",
    "bits_saved",
    "fraction_explained",
    "pixels",
    "level",
    "figure",
    "prettify",
    "parent",
}
RANGE_IMAGE_SUFFIXES = (".npy", ".png", ".tif", ".tiff", ".pcd", ".exr")
EXR_DEPTH_CHANNELS = ("Z", "depth", "Y", "R")
"""Channels of an OpenEXR file read as depth, in order of preference (R only where the
file's R, G and B agree: a grey image, not a colour render)."""


MAX_JSON_BYTES = 64 * 2**20
"""Largest scene or camera JSON file read (64 MiB)."""


def _temporary_name(directory: Path, suffix: str) -> Path:
    # Short, so that a legal name of up to 255 bytes can still be staged beside it.
    return directory / f".sqparts-{os.urandom(6).hex()}{suffix}"


@contextlib.contextmanager
def atomic_write(path, mode: str = "wb"):
    """Open a temporary file next to ``path`` and move it into place only on success.

    The file gets the mode the umask gives (as ``open`` would), not ``mkstemp``'s 0600.
    """
    path = Path(path)
    if path.parent and not path.parent.is_dir():
        raise FileNotFoundError(f"--out: got {str(path)!r}, expected a path in an existing directory")
    tmp = _temporary_name(path.parent, ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def check_new_output(path, *, overwrite: bool = False, inputs=(), argument: str = "--out") -> Path:
    """``path`` if it may be written: it does not exist, is an empty folder, or
    ``overwrite`` is set and it neither is nor holds one of the ``inputs`` (paths read
    to make it: replacing a folder replaces everything in it); raises ``FileExistsError`` (naming
    ``argument``, the flag that gave it) otherwise."""
    path = Path(path)
    if not overwrite and path.exists() and not (path.is_dir() and not any(path.iterdir())):
        raise FileExistsError(f"{argument}: got {str(path)!r}, which exists, expected a new path (or --overwrite)")
    if path.exists():
        inside = path.resolve()
        for p in inputs:
            if p is not None and inside in (q := Path(p).resolve(), *q.parents):
                what = "is" if inside == q else "holds"
                raise FileExistsError(
                    f"{argument}: got {str(path)!r}, which {what} the input {str(p)!r}, "
                    "expected a path apart from the inputs (--overwrite replaces it whole)"
                )
    ancestor = next(p for p in path.absolute().parents if p.exists())
    if not ancestor.is_dir():
        raise NotADirectoryError(
            f"{argument}: got {str(path)!r}, expected a path in a folder ({str(ancestor)!r} is a file)"
        )
    try:  # before any work: a file made and removed where the output's folders will go
        import tempfile

        with tempfile.TemporaryFile(dir=ancestor, prefix=".sqparts-"):
            pass
    except OSError:
        raise ValueError(
            f"{argument}: got {str(path)!r}, expected a path in a folder this user can write ({str(ancestor)!r} is not)"
        ) from None
    return path


@contextlib.contextmanager
def staged_folder(path, *, overwrite: bool = False, inputs=()):
    """Write a set of outputs that appear together or not at all.

    Yields a temporary folder beside ``path``; on success it is renamed to ``path`` in
    one step (an existing ``path`` is replaced only with ``overwrite``, or when it is
    an empty folder, and never when it holds one of the ``inputs``: see
    :func:`check_new_output`); on any exception or signal the temporary folder is removed and
    ``path`` is left as it was. The folder gets the mode the umask gives.
    """
    import shutil

    path = check_new_output(path, overwrite=overwrite, inputs=inputs)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary_name(path.parent, ".tmp")
    tmp.mkdir(mode=0o777)
    old = None
    try:
        yield tmp
        check_new_output(path, overwrite=overwrite, inputs=inputs)  # nobody made it meanwhile
        if path.exists() and (not path.is_dir() or any(path.iterdir())):
            old = _temporary_name(path.parent, ".old")
            os.rename(path, old)
        elif path.is_dir():
            path.rmdir()
        os.rename(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None and not path.exists():
            os.rename(old, path)
            old = None
        raise
    finally:
        if old is not None:
            if old.is_dir():
                shutil.rmtree(old, ignore_errors=True)
            else:
                old.unlink(missing_ok=True)
            if old.exists():  # e.g. a read-only folder inside it: the new output is in place
                logging.getLogger(__name__).warning(
                    "sqparts: warning: %s replaced, but its old copy could not be removed: %s", path, old
                )


def _load_json(path, what: str):
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what}: got {str(path)!r}, expected an existing file")
    size = path.stat().st_size
    if size > MAX_JSON_BYTES:
        raise ValueError(f"{what}: got a file of {size} bytes, expected at most {MAX_JSON_BYTES}")
    try:
        return json.loads(
            path.read_bytes(), parse_constant=_reject_constant, parse_int=_parse_int, object_pairs_hook=_unique_keys
        )
    except RecursionError:
        raise ValueError(
            f"{what}: got JSON nested too deeply to parse in {str(path)!r}, expected a {what} file"
        ) from None
    except (ValueError, UnicodeDecodeError) as e:  # JSONDecodeError is a ValueError
        raise ValueError(f"{what}: got {str(path)!r}, expected valid JSON ({e})") from None


def _reject_constant(name: str):
    raise ValueError(f"got {name}, expected finite numbers")


def _unique_keys(pairs) -> dict:
    """A JSON object, refused when it gives one key twice (Python would keep the last
    silently)."""
    out = dict(pairs)
    if len(out) != len(pairs):
        twice = sorted(k for k, n in collections.Counter(k for k, _ in pairs).items() if n > 1)
        raise ValueError(f"got the key(s) {twice} twice in one object, expected each key once")
    return out


def _parse_int(text: str):
    """A JSON integer; one of more than 18 digits as a float (inf beyond float64's
    range), so the checks of the value it fills refuse it by name instead of an
    OverflowError where it is converted."""
    return float(text) if len(text.lstrip("-")) > 18 else int(text)


# --- scenes ------------------------------------------------------------------------


def part_from_dict(d: dict, *, index: int = 0) -> tuple[Part, dict]:
    """One part from its JSON dict; returns the part and its annotations."""
    where = f"parts[{index}]"
    if not isinstance(d, dict):
        raise ValueError(f"{where}: got {type(d).__name__}, expected a JSON object")
    unknown = sorted(set(d) - PART_KEYS - ANNOTATION_KEYS)
    if unknown:
        raise ValueError(
            f"{where}: got unknown key(s) {unknown}, expected {sorted(PART_KEYS)} "
            f"(+ annotations {sorted(ANNOTATION_KEYS)})"
        )
    missing = sorted({"size", "squareness", "position"} - set(d))
    if missing:
        raise ValueError(
            f"{where}: got no {', '.join(missing)}, expected keys {sorted(PART_KEYS)} (size, squareness and position required)"
        )

    def numbers(key, default, shape):
        if key in d and not json_numbers(d[key]):
            raise ValueError(f"{where}.{key}: got {d[key]!r:.60}, expected numbers")
        try:
            value = np.asarray(d.get(key, default), dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{where}.{key}: got {d[key]!r:.60}, expected numbers") from None
        if value.shape != shape:
            raise ValueError(f"{where}.{key}: got shape {value.shape}, expected {shape}")
        return value

    fields = {
        key: numbers(key, default, shape)
        for key, default, shape in (
            ("size", None, (3,)),
            ("squareness", None, (2,)),
            ("position", None, (3,)),
            ("rotation", np.eye(3), (3, 3)),
            ("bend", [0.0, 0.0], (2,)),
            ("taper", 0.0, ()),
        )
    }
    try:
        orientation = rotation_vector(fields.pop("rotation"))
        with np.errstate(over="ignore"):  # beyond float32: an inf that Part rejects by name
            part = Part(
                orientation=orientation.astype(np.float32), **{k: v.astype(np.float32) for k, v in fields.items()}
            )
    except (ValueError, TypeError) as e:
        raise ValueError(f"{where}.{e}") from None
    annotations = {k: d[k] for k in d if k in ANNOTATION_KEYS}
    for key, value in annotations.items():
        kind, check = _ANNOTATION_CHECKS[key]
        if not check(value):
            raise ValueError(f"{where}.{key}: got {value!r:.60}, expected {kind}")
    return part, annotations


def _integer(v) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_))


def _count(v) -> bool:
    return _integer(v) and v >= 0


def _number(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)) and math.isfinite(v)


_ANNOTATION_CHECKS = {  # as the JSON Schema (schema/parts.schema.json) types them
    "name": ("a string", lambda v: isinstance(v, str)),
    "gamma": ("a finite number", _number),
    "bits_saved": ("a finite number", _number),
    "fraction_explained": ("a number in [0, 1]", lambda v: _number(v) and 0 <= v <= 1),
    "pixels": ("an integer >= 0", _count),
    "level": ("an integer >= 0", _count),
    "figure": ("an integer >= 0", _count),
    "parent": ("an integer or null", lambda v: v is None or _integer(v)),
    "prettify": ("an object or null", lambda v: v is None or isinstance(v, dict)),
}


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
    """``v`` as JSON data: arrays as nested lists; the read-only mappings and tuples of an
    immutable result (:func:`sqparts._typing.freeze_fields`) as dicts and lists."""
    if isinstance(v, (np.ndarray, np.generic)) or hasattr(v, "__array__"):
        return np.asarray(v).tolist()
    if isinstance(v, Mapping):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    return v


def scene_from_dict(data) -> tuple[Part, list[dict], dict]:
    """Parse scene JSON: returns (batched parts, per-part annotations, top-level metadata)."""
    if not isinstance(data, dict) or "parts" not in data:
        raise ValueError(
            f'scene: got {type(data).__name__}{" without parts" if isinstance(data, dict) else ""}, expected a JSON object with a "parts" list'
        )
    if not isinstance(data["parts"], list) or not data["parts"]:
        raise ValueError(f"scene.parts: got {data['parts']!r:.40}, expected a non-empty list of parts")
    parsed = [part_from_dict(d, index=i) for i, d in enumerate(data["parts"])]
    meta = {k: v for k, v in data.items() if k != "parts"}
    return stack_parts([p for p, _ in parsed]), [a for _, a in parsed], meta


def scene_to_dict(parts: Part, annotations=None, **metadata) -> dict:
    """Scene JSON dict of a batched :class:`Part` (plus annotations and metadata)."""
    n = len(parts)
    if annotations is not None and len(annotations) != n:
        raise ValueError(f"annotations: got {len(annotations)}, expected one per part ({n})")
    annotations = annotations or [{} for _ in range(n)]
    return {
        "parts": [part_to_dict(parts[i], **annotations[i]) for i in range(n)],
        **{k: _jsonable(v) for k, v in metadata.items()},
    }


PARTS_SCHEMA_PATH = Path(__file__).with_name("schema") / "parts.schema.json"
"""JSON Schema (draft 2020-12) of scene JSON and of a recovery's ``parts.json``."""


def parts_schema() -> dict:
    """The JSON Schema (draft 2020-12) of scene JSON / ``parts.json``, as a dict; the
    file is :data:`PARTS_SCHEMA_PATH`, shipped with the package. Validate with e.g.
    ``jsonschema.validate(data, sqparts.parts_schema())``."""
    return json.loads(PARTS_SCHEMA_PATH.read_text(encoding="utf-8"))


def load_scene(path) -> Part:
    """Read a scene JSON file into a batched :class:`Part`."""
    parts, _, _ = scene_from_dict(_load_json(path, "scene"))
    return parts


def save_scene(path, parts: Part, annotations=None, **metadata) -> None:
    """Write a scene JSON file atomically, one that :func:`load_scene` reads back: known
    annotations of their types and finite numbers (JSON has no NaN), or nothing written."""
    try:
        text = json.dumps(scene_to_dict(parts, annotations, **metadata), indent=2, allow_nan=False)
    except ValueError as e:
        if "JSON compliant" not in str(e):
            raise
        raise ValueError(
            "scene: got a NaN or infinite value to write, expected finite numbers (JSON has none)"
        ) from None
    scene_from_dict(json.loads(text))  # what load_scene would refuse is refused now
    with atomic_write(path, "w") as f:
        f.write(text + "\n")


# --- cameras -----------------------------------------------------------------------


def load_camera(path) -> Camera:
    """Read a camera JSON file: Open3D pinhole intrinsics (or Open3D's camera parameters,
    whose ``"intrinsic"`` they are; the extrinsic pose is not needed for a range image in
    the camera's own frame), orthographic, scanner, or RealSense intrinsics (see
    :func:`camera_from_realsense`)."""
    data = _load_json(path, "camera")
    if isinstance(data, dict) and "intrinsic_matrix" not in data and isinstance(data.get("intrinsic"), dict):
        data = data["intrinsic"]  # open3d.io.write_pinhole_camera_parameters
    if isinstance(data, dict) and _realsense_intrinsics(data) is not None:
        return camera_from_realsense(data)
    if isinstance(data, dict) and "intrinsic_matrix" not in data and {"fx", "fy", "ppx", "ppy"} & set(data):
        missing = ", ".join(sorted(REALSENSE_KEYS - set(data)))
        raise ValueError(f"camera: got no {missing}, expected RealSense intrinsics with keys {sorted(REALSENSE_KEYS)}")
    return camera_from_json(data)


REALSENSE_KEYS = {"width", "height", "fx", "fy", "ppx", "ppy"}


def camera_depth_scale(path) -> float | None:
    """The ``depth_scale`` (metres per depth unit) of a RealSense camera JSON file, beside
    its intrinsics (flat, or at the top of a dump with them under ``"intrinsics"`` or
    ``"depth"``); None when the file has none. ``sqparts`` reads integer depth (a PNG's)
    with it unless ``--depth-scale`` is given."""
    data = _load_json(path, "camera")
    intr = _realsense_intrinsics(data) if isinstance(data, dict) else None
    if intr is None:
        return None
    found = [d["depth_scale"] for d in (data, intr) if "depth_scale" in d]
    for value in found:
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not (number and math.isfinite(value) and value > 0):
            raise ValueError(f"camera.depth_scale: got {value!r:.40}, expected a finite number > 0 (metres per unit)")
    if len(set(found)) > 1:
        raise ValueError(f"camera.depth_scale: got {found[0]!r} and {found[1]!r}, expected one value")
    return float(found[0]) if found else None


def _realsense_intrinsics(data: dict) -> dict | None:
    """The RealSense intrinsics in ``data``: at the top level or under one of
    ``intrinsics``, ``depth`` (as a dump of several streams); None if there are none."""
    if REALSENSE_KEYS <= set(data):
        return data
    found = {}
    for key in ("intrinsics", "depth"):
        inner = data.get(key)
        if isinstance(inner, dict) and (intr := _realsense_intrinsics(inner)) is not None:
            found[key] = intr
    if len(found) > 1 and found["intrinsics"] != found["depth"]:
        raise ValueError(
            "camera: got RealSense intrinsics under both 'intrinsics' and 'depth', and they differ, "
            "expected one set (the depth stream's)"
        )
    return next(iter(found.values()), None)


def camera_from_realsense(data: dict) -> PinholeCamera:
    """A :class:`PinholeCamera` from Intel RealSense intrinsics as JSON.

    The fields are those of ``pyrealsense2.intrinsics`` (and of ``rs-enumerate-devices
    -c``'s listing): ``width``, ``height``, ``fx``, ``fy``, ``ppx``, ``ppy`` in pixels, and
    optionally ``model`` (the distortion model's name) and ``coeffs`` (5 numbers), flat or
    under ``"intrinsics"`` or ``"depth"``. The depth stream of a D400 camera has no
    distortion; non-zero ``coeffs`` are an error, since the renderer casts ideal pinhole
    rays (undistort the image first).
    """
    intr = _realsense_intrinsics(data) if isinstance(data, dict) else None
    if intr is None:
        raise ValueError(
            f"camera: got {type(data).__name__}, expected RealSense intrinsics with keys {sorted(REALSENSE_KEYS)}"
        )
    known = REALSENSE_KEYS | {"model", "coeffs", "depth_scale"}  # depth_scale: camera_depth_scale's
    unknown = sorted(set(intr) - known)
    if unknown:
        raise ValueError(
            f"camera: got unknown key(s) {unknown}, expected only {sorted(known)} for RealSense intrinsics"
        )
    coeffs = intr.get("coeffs", [0.0] * 5)
    try:
        coeffs = np.asarray(coeffs, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"camera.coeffs: got {intr['coeffs']!r:.60}, expected 5 numbers") from None
    if coeffs.ndim != 1 or not np.all(np.isfinite(coeffs)) or np.any(coeffs != 0):
        raise ValueError(
            f"camera.coeffs: got {coeffs.tolist()!r:.80}, expected zero distortion (an undistorted depth stream)"
        )
    for key in ("fx", "fy", "ppx", "ppy"):
        if not isinstance(intr[key], (int, float)) or isinstance(intr[key], bool):
            raise ValueError(f"camera.{key}: got {intr[key]!r:.40}, expected a number")
    try:
        return PinholeCamera(
            intr["width"], intr["height"], float(intr["fx"]), float(intr["fy"]), float(intr["ppx"]), float(intr["ppy"])
        )
    except ValueError as e:  # a field's check: name it as the file does
        name, _, rest = str(e).partition(": ")
        name = {"cx": "ppx", "cy": "ppy"}.get(name, name)
        raise ValueError(f"camera.{name}: {rest}" if name in REALSENSE_KEYS else str(e)) from None


def save_camera(path, camera: Camera) -> None:
    with atomic_write(path, "w") as f:
        f.write(json.dumps(camera.to_json(), indent=2) + "\n")


# --- range images ------------------------------------------------------------------


DEPTH_SCALE = 0.001
"""Metres per unit of integer depth (a 16-bit PNG's) when none is given: millimetres."""


def read_range_image(path, *, depth_scale: float = DEPTH_SCALE) -> tuple[np.ndarray, Camera | None]:
    """Read a range image; returns (float32 depth with NaN = no return, camera or None).

    * ``.npy``: a 2-D float array (NaN, inf or <= 0 = no return).
    * ``.png``: 16-bit grey, depth = value * ``depth_scale`` (default 0.001: millimetres
      to metres, as Kinect/TUM data); 0 = no return.
    * ``.tif``/``.tiff``: 2-D float (or integer, scaled by ``depth_scale``).
    * ``.pcd``: an organized point cloud (x, y, z in the camera frame, or in a frame where
      its ``VIEWPOINT`` places the camera); the depth is z in the camera frame and the
      pinhole camera is recovered from the points by least squares.
    * ``.exr``: OpenEXR (through the ``OpenEXR`` package: ``pip install sqparts[interop]``),
      the first of the channels ``Z``, ``depth``, ``Y``, ``R`` (or the only one), float in
      scene units (an integer channel is scaled by ``depth_scale``).

    Datasets: TUM RGB-D depth PNGs hold 5000 units per metre (``depth_scale=0.0002``);
    RealSense PNGs hold the device's depth scale (usually 0.001), its intrinsics read by
    :func:`load_camera`.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"input: got {type(path).__name__}, expected a file path")
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in RANGE_IMAGE_SUFFIXES:
        raise ValueError(
            f"input: got {str(path)!r}, expected a range image ending in {', '.join(RANGE_IMAGE_SUFFIXES)}"
        )
    if not path.is_file():
        raise FileNotFoundError(f"input: got {str(path)!r}, expected an existing file")
    if not (isinstance(depth_scale, (int, float)) and np.isfinite(depth_scale) and depth_scale > 0):
        raise ValueError(f"depth_scale: got {depth_scale!r}, expected a number > 0")
    camera = None
    try:
        _check_image_size(path, _declared_shape(path, suffix))
        if suffix == ".npy":
            depth = np.load(path, allow_pickle=False)
            if np.issubdtype(depth.dtype, np.integer) and depth.ndim == 2:  # sensor units, as a PNG's
                depth = np.where(depth == 0, np.nan, depth.astype(np.float64) * depth_scale)
        elif suffix == ".png":
            from PIL import Image

            with Image.open(path) as im:
                raw, mode = np.asarray(im), im.mode
            if raw.ndim != 2 or raw.dtype not in (np.uint16, np.int32, np.uint8) or mode in ("P", "PA", "1"):
                raise ValueError(
                    f"input: got a PNG (mode {mode}) of {raw.dtype} with shape {raw.shape}, expected a single-channel 16-bit PNG"
                )
            if raw.dtype == np.uint8:  # 255 levels: a picture of depth (a visualisation), not sensor units
                raise ValueError(
                    f"input: got an 8-bit PNG (mode {mode}) in {str(path)!r}, expected a 16-bit depth PNG "
                    "(an 8-bit picture of depth holds 255 grey levels, not depths)"
                )
            depth = np.where(raw == 0, np.nan, raw.astype(np.float64) * depth_scale)
        elif suffix in (".tif", ".tiff"):
            import tifffile

            raw = tifffile.imread(path)
            if raw.dtype == bool:
                raise ValueError(f"input: got a TIFF of bool with shape {raw.shape}, expected depths")
            depth = raw if np.issubdtype(raw.dtype, np.floating) else raw * depth_scale
        elif suffix == ".exr":
            depth = _read_exr(path, depth_scale)
        else:
            depth, camera = _read_pcd(path)
    except (OSError, ValueError, EOFError, MemoryError) as e:
        msg = str(e)
        if msg.startswith("input:"):
            raise ValueError(msg) from None
        raise ValueError(
            f"input: got {str(path)!r}, expected a readable range image ({type(e).__name__}: {e})"
        ) from None
    depth = np.asarray(depth)
    numeric = np.issubdtype(depth.dtype, np.integer) or np.issubdtype(depth.dtype, np.floating)
    if depth.ndim != 2 or not numeric or 0 in depth.shape:
        raise ValueError(
            f"input: got {depth.dtype} with shape {depth.shape}, expected a 2-D numeric range image with pixels"
        )
    return _float32_depth(depth, "input", f" in {str(path)!r}"), camera


def _float32_depth(raw: np.ndarray, argument: str, where: str = "") -> np.ndarray:
    """A numeric 2-D array as float32 depths, NaN where there is no return (NaN, inf, 0
    or negative), as both reading and writing keep them; depths float32 cannot hold are
    refused (``argument: got depths up to X{where}, ...``) rather than turned into inf."""
    finite = np.abs(raw[np.isfinite(raw)])
    if finite.size and float(finite.max()) > float(np.finfo(np.float32).max):
        raise ValueError(
            f"{argument}: got depths up to {float(finite.max()):.3g}{where}, expected depths that float32 holds"
        )
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(raw) & (raw > 0), raw, np.nan).astype(np.float32)


def _declared_shape(path: Path, suffix: str) -> tuple[int, ...]:
    """The image shape a file's header declares, read before any pixel is decoded."""
    if suffix == ".npy":  # the header alone: mapping a file shorter than it declares fails
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            read = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
            if version in read:
                return tuple(read[version](f)[0])
        return tuple(np.load(path, mmap_mode="r", allow_pickle=False).shape)
    if suffix == ".png":
        from PIL import Image

        # PIL's own bomb check (an error past 2 x MAX_IMAGE_PIXELS) is ours to make.
        limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
        try:
            with Image.open(path) as im:
                return (im.size[1], im.size[0])
        finally:
            Image.MAX_IMAGE_PIXELS = limit
    if suffix == ".exr":
        exr = _open_exr(path, header_only=True)
        (x0, y0), (x1, y1) = (np.asarray(c, np.int64) for c in exr.header()["dataWindow"])
        return (int(y1 - y0 + 1), int(x1 - x0 + 1))
    if suffix in (".tif", ".tiff"):
        import tifffile

        with tifffile.TiffFile(path) as tif:
            return tuple(tif.series[0].shape) if tif.series else ()
    header = {}
    with open(path, "rb") as f:
        for line in f:
            words = line.decode("ascii", "replace").split()
            if words and not words[0].startswith("#"):
                header[words[0].upper()] = words[1:]
            if words[:1] == ["DATA"] or len(header) > 32:
                break
    try:
        shape = (int(header["HEIGHT"][0]), int(header["WIDTH"][0]))
    except (KeyError, IndexError, ValueError):
        raise ValueError(f"input: got {str(path)!r}, expected a .pcd header with WIDTH and HEIGHT") from None
    if min(shape) < 1:
        raise ValueError(
            f"input: got WIDTH {shape[1]} and HEIGHT {shape[0]} in {str(path)!r}, expected positive integers"
        )
    return shape


def _open_exr(path: Path, *, header_only: bool = False):
    try:
        import OpenEXR
    except ImportError:
        raise ValueError(
            f"input: got {str(path)!r}, expected the OpenEXR package to read it (pip install 'sqparts[interop]')"
        ) from None
    try:
        return OpenEXR.File(str(path), separate_channels=True, header_only=header_only)
    except RuntimeError as e:  # OpenEXR's error for a file it cannot parse
        raise ValueError(f"input: got {str(path)!r}, expected a readable OpenEXR file ({e})") from None


def _read_exr(path: Path, depth_scale: float) -> np.ndarray:
    channels = {name: c.pixels for name, c in _open_exr(path).channels().items()}
    colour = [channels[c] for c in ("R", "G", "B") if c in channels]
    grey = all(np.array_equal(colour[0], c, equal_nan=True) for c in colour[1:])
    name = next((n for n in EXR_DEPTH_CHANNELS if n in channels and (n != "R" or grey)), None)
    if name is None and len(channels) == 1:
        name = next(iter(channels))
    if name is None:
        raise ValueError(
            f"input: got channels {sorted(channels)} in {str(path)!r}, expected one of {list(EXR_DEPTH_CHANNELS)} "
            "(R where R, G and B agree: not a colour image) or a single channel"
        )
    raw = np.asarray(channels[name])
    return raw if np.issubdtype(raw.dtype, np.floating) else raw * depth_scale


def _check_image_size(path: Path, shape: tuple[int, ...]) -> None:
    shape = tuple(int(n) for n in shape)  # Python integers: a header may declare any size
    pixels = math.prod(shape) if shape else 0
    if pixels > MAX_PIXELS or any(n > MAX_SIDE for n in shape):
        raise ValueError(
            f"input: got an image of shape {str(shape):.80} in {str(path)!r}, expected at most "
            f"{MAX_PIXELS} pixels and {MAX_SIDE} per side"
        )


def _read_pcd(path) -> tuple[np.ndarray, PinholeCamera]:
    from pypcd4 import PointCloud  # pyright: ignore[reportPrivateImportUsage]  # pypcd4 re-exports it without `as` or __all__

    try:
        pc = PointCloud.from_path(path)
        w, h, declared = int(pc.metadata.width), int(pc.metadata.height), int(pc.metadata.points)
        points = pc.numpy(("x", "y", "z")).astype(np.float64) if h > 1 else None
    except Exception as e:  # pypcd4 reports malformed data as struct, zlib, lzf or index errors
        raise ValueError(
            f"input: got a .pcd whose data cannot be read ({type(e).__name__}: {e}), expected a valid point cloud"
        ) from None
    if points is None:
        raise ValueError(f"input: got height {h}, expected an organized .pcd (height > 1)")
    if points.size != h * w * 3 or declared != h * w:
        raise ValueError(
            f"input: got {points.size // 3} points (POINTS {declared}), expected width x height = {w} x {h} (an organized .pcd)"
        )
    xyz = points.reshape(h, w, 3)
    try:
        return xyz[..., 2], intrinsics_from_points(xyz)
    except ValueError:
        posed = _sensor_frame(points, pc.metadata.viewpoint)
        if posed is points:
            raise
    xyz = posed.reshape(h, w, 3)
    return xyz[..., 2], intrinsics_from_points(xyz)


def _sensor_frame(points: np.ndarray, viewpoint) -> np.ndarray:
    """A cloud's (n, 3) points in its sensor's frame by its .pcd's ``VIEWPOINT tx ty tz
    qw qx qy qz``, the sensor's pose in the frame of the points (PCL's ``sensor_origin_``
    and ``sensor_orientation_``): R^T (p - t); the points themselves for the default 0 0
    0 1 0 0 0. Only for a cloud that a pinhole at its origin does not explain as it is:
    PCL's OpenNI grabber writes its Kinect frames in the camera's optical frame with
    VIEWPOINT 0 0 0 0 1 0 0 (a half turn about x that its viewer applies)."""
    v = np.asarray(viewpoint, np.float64).reshape(-1)
    norm = float(np.linalg.norm(v[3:])) if v.size == 7 else 0.0
    if not (v.size == 7 and np.isfinite(v).all() and norm > 1e-9):
        raise ValueError(
            f"input: got VIEWPOINT {' '.join(f'{x:g}' for x in v)}, expected tx ty tz qw qx qy qz "
            "(finite, a non-zero quaternion)"
        )
    if np.array_equal(v, [0, 0, 0, 1, 0, 0, 0]):
        return points
    from scipy.spatial.transform import Rotation

    rotation = Rotation.from_quat([*v[4:], v[3]]).as_matrix()  # scipy's quaternions are scalar-last
    return (points - v[:3]) @ rotation


PCD_MAX_REPROJECTION = 0.5
"""Largest RMS reprojection error, in pixels, of the pinhole fitted to an organized
cloud (:func:`intrinsics_from_points`): a pinhole camera's own cloud fits to a small
fraction of a pixel (the Kinect and stereo clouds in the shared data: 3e-5 and 0.02)."""


def intrinsics_from_points(xyz: np.ndarray) -> PinholeCamera:
    """Pinhole intrinsics of an organized cloud by least squares: u = fx x/z + cx. A
    cloud that no pinhole at the origin explains within :data:`PCD_MAX_REPROJECTION`
    pixels is refused: its points are not in its camera's optical frame (moved to a
    world or robot frame), or its camera is not a pinhole (a scanner's), and its z is
    then not the depth its pixels saw."""
    h, w = xyz.shape[:2]
    v, u = np.mgrid[0:h, 0:w]
    ok = np.isfinite(xyz).all(-1) & (xyz[..., 2] > 0)
    if ok.sum() < 10:
        raise ValueError(f"input: got a point cloud with {int(ok.sum())} valid points, expected at least 10")
    xz = xyz[..., 0][ok] / xyz[..., 2][ok]
    yz = xyz[..., 1][ok] / xyz[..., 2][ok]
    fx, cx = np.linalg.lstsq(np.c_[xz, np.ones_like(xz)], u[ok], rcond=None)[0]
    fy, cy = np.linalg.lstsq(np.c_[yz, np.ones_like(yz)], v[ok], rcond=None)[0]
    error = float(np.sqrt(np.mean((fx * xz + cx - u[ok]) ** 2 + (fy * yz + cy - v[ok]) ** 2)))
    if not error <= PCD_MAX_REPROJECTION:
        raise ValueError(
            f"input: got an organized cloud that a pinhole camera at its origin reprojects to its pixels within "
            f"{error:.3g} px (RMS), expected {PCD_MAX_REPROJECTION} px at most (points in the camera's optical frame, "
            "x right, y down, z forward, or a VIEWPOINT giving the camera's pose; give a range image and --camera "
            "otherwise)"
        )
    return PinholeCamera(w, h, float(fx), float(fy), float(cx), float(cy))


def write_range_image(path, depth, *, depth_scale: float = DEPTH_SCALE) -> None:
    """Write a range image atomically: .npy (float32, NaN kept), .png (uint16 of
    depth / depth_scale, 0 = no return) or .tif (float32). Pixels without a return
    (NaN, inf, 0 or negative) are written as NaN (0 in a PNG), as reading gives them."""
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: got {type(path).__name__}, expected a file path")
    path = Path(path)
    raw = np.asarray(depth)
    real = np.issubdtype(raw.dtype, np.integer) or np.issubdtype(raw.dtype, np.floating)
    if raw.ndim != 2 or 0 in raw.shape or not real:
        raise ValueError(f"depth: got {raw.dtype} with shape {raw.shape}, expected a 2-D range image with pixels")
    depth = _float32_depth(raw, "depth")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        with atomic_write(path) as f:
            np.save(f, depth)
    elif suffix == ".png":
        from PIL import Image

        if not (isinstance(depth_scale, (int, float, np.floating)) and np.isfinite(depth_scale) and depth_scale > 0):
            raise ValueError(f"depth_scale: got {depth_scale!r}, expected a finite number > 0")
        returns = np.isfinite(depth) & (depth > 0)
        scaled = np.where(returns, np.round(np.where(returns, depth, 0) / depth_scale), 0)
        if returns.any() and not (1 <= scaled[returns].min() and scaled[returns].max() <= 65535):
            near, far = float(depth[returns].min()), float(depth[returns].max())
            raise ValueError(
                f"depth_scale: got {depth_scale!r}, expected a scale at which depths "
                f"{near:.4g}..{far:.4g} are 1..65535 units (16-bit PNG, 0 = no return)"
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
        raise ValueError(f"--out: got {str(path)!r}, expected a path ending in .npy, .png or .tif")


# --- what the viewers read beside parts.json ---------------------------------------------

VIEW_FILES = ("range.npy", "camera.json", "pixels.npz")
"""Written by ``sqparts recover`` beside parts.json for ``sqparts view`` and ``--rerun``."""


def save_view_data(folder, depth, camera: Camera, *, status, model, labels) -> None:
    """Write :data:`VIEW_FILES` into ``folder`` (a staged output folder).

    ``range.npy``: the float32 range image the parts were recovered from (after binning
    and clean-up), NaN = no return; ``camera.json``: its camera; ``pixels.npz``: per pixel
    ``status`` (uint8: 0 none, 1 explained, 2 omitted, 3 commission), ``model`` (float32,
    the parts' range image) and ``labels`` (int16: the part seen, -1 none).
    """
    import io

    folder = Path(folder)
    write_range_image(folder / "range.npy", depth)
    save_camera(folder / "camera.json", camera)
    buffer = io.BytesIO()
    np.savez_compressed(
        buffer,
        status=np.asarray(status, np.uint8),
        model=np.asarray(model, np.float32),
        labels=np.asarray(labels, np.int16),
    )
    with atomic_write(folder / "pixels.npz") as f:
        f.write(buffer.getvalue())


def load_view_data(folder) -> dict:
    """What the viewers need from a ``sqparts recover`` (or ``demo``) output folder.

    Returns a dict: ``parts`` (batched :class:`Part`), ``annotations``, ``meta`` (parts.json's
    other keys), ``title``; and, when their files are there, ``depth`` and ``camera``
    (``camera.json``, else parts.json's ``camera``), ``status``, ``model``, ``labels``
    (``pixels.npz``) and ``report`` (report.png as an RGB array); ``folder`` is the path.
    Only parts.json is required.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"folder: got {str(folder)!r}, expected a sqparts recover output folder")
    if not (folder / "parts.json").is_file():
        raise FileNotFoundError(
            f"folder: got {str(folder)!r} without parts.json, expected a sqparts recover output folder"
        )
    parts, annotations, meta = scene_from_dict(_load_json(folder / "parts.json", "scene"))
    data = {"parts": parts, "annotations": annotations, "meta": meta, "title": folder.resolve().name, "folder": folder}
    if (folder / "camera.json").is_file():
        data["camera"] = load_camera(folder / "camera.json")
    elif isinstance(meta.get("camera"), dict):
        data["camera"] = camera_from_json(meta["camera"])
    if (folder / "range.npy").is_file():
        try:
            data["depth"], _ = read_range_image(folder / "range.npy")
        except ValueError as e:  # named as the folder's file, not as an input
            raise ValueError(f"range.npy: {str(e).partition(': ')[2]}") from None
        camera = data.get("camera")
        if camera is not None and data["depth"].shape != (camera.height, camera.width):
            raise ValueError(
                f"range.npy: got shape {data['depth'].shape}, expected {(camera.height, camera.width)} (camera.json's size)"
            )
    if (folder / "pixels.npz").is_file():
        try:
            with np.load(folder / "pixels.npz", allow_pickle=False) as z:
                pixels = {k: np.asarray(z[k]) for k in ("status", "model", "labels")}
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            raise ValueError(
                f"pixels.npz: got {str(folder / 'pixels.npz')!r}, expected status, model and labels arrays (as sqparts recover writes)"
            ) from None
        if "depth" in data and any(v.shape != data["depth"].shape for v in pixels.values()):
            raise ValueError(
                f"pixels.npz: got shapes {[v.shape for v in pixels.values()]}, expected {data['depth'].shape} (range.npy's)"
            )
        data.update(pixels)
    if (folder / "report.png").is_file():
        from PIL import Image

        try:
            with Image.open(folder / "report.png") as im:
                data["report"] = np.asarray(im.convert("RGB"))
        except (OSError, ValueError, SyntaxError) as e:  # PIL's UnidentifiedImageError is an OSError
            raise ValueError(f"report.png: got {str(folder / 'report.png')!r}, expected a PNG picture ({e})") from None
    return data
