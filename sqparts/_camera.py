"""Cameras: one ray per pixel, in the OpenCV camera frame (x right, y down, z forward).

Every camera gives, for pixel (u, v) (u = column, v = row, centres at integers), a ray
``origin + t * direction``. Directions are scaled so that the ray parameter ``t`` is
exactly what the range image stores:

* :class:`PinholeCamera`: origin 0, direction ((u-cx)/fx, (v-cy)/fy, 1); ``t`` is the
  z-depth.
* :class:`OrthographicCamera`: origin ((u-cx) s, (v-cy) s, 0), direction (0, 0, 1);
  ``t`` is the z-depth.
* :class:`ScannerCamera`: a wide-angle range finder like the paper's ERIM laser scanner.
  Column u looks at azimuth az = (u - cx) * azimuth_step (positive to the right), row v
  at elevation el = (v - cy) * elevation_step (positive downward); the unit direction is
  (sin az cos el, sin el, cos az cos el); ``t`` is the *range along the ray*, not z.

Range images are float32 arrays of shape (height, width) with NaN where there is no
return.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from ._typing import Array, Float

MAX_SIDE = 32768
"""Longest image side a camera or range image may have."""
DEPTH_RANGE = (1e-9, 1e9)
"""Depths a recovery takes, in scene units: squares and reciprocals of depths, and the
quantisation step of the nearest, stay normal float32 numbers (a figure at 3e38 overflowed
and one at 1e-42 underflowed deep in the recovery)."""
MAX_PIXELS = 2**24
"""Most pixels a camera or range image may have (4096 x 4096): rendering allocates a
few hundred bytes per pixel, so larger images are refused before anything is allocated."""


def _check_image_size(width: int, height: int) -> None:
    if width > MAX_SIDE or height > MAX_SIDE or width * height > MAX_PIXELS:
        raise ValueError(
            f"camera: got {width}x{height} pixels, expected at most {MAX_PIXELS} pixels and {MAX_SIDE} per side"
        )


def _check_positive_int(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
        raise ValueError(f"{name}: got {value!r}, expected a positive integer")
    return int(value)


def fits_float32(value) -> bool:
    """Whether a finite ``value`` keeps its meaning in float32, the precision the package
    computes in: not beyond its largest number (1e39 would become inf) and, unless 0,
    not below its smallest normal one (1e-300 would become 0)."""
    f = np.finfo(np.float32)
    return bool(value == 0 or float(f.tiny) <= abs(float(value)) <= float(f.max))


def _check_finite(name: str, value, *, positive: bool = False) -> float:
    shown = value.item() if isinstance(value, np.generic) else value  # 1e+39, not np.float64(1e+39)
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: got {shown!r}, expected a number") from None
    if not np.isfinite(v) or (positive and v <= 0) or not fits_float32(v):
        want = "a finite number > 0" if positive else "a finite number"
        raise ValueError(f"{name}: got {shown!r}, expected {want} that float32 holds")
    return v


def _array(x):
    """``x`` as an array and its module: JAX arrays (and tracers) stay JAX, anything
    else becomes a numpy array (no device round trip for host geometry)."""
    return (x, jnp) if isinstance(x, jax.Array) else (np.asarray(x), np)


def _pixel_grid(window, xp=jnp, stride=1):
    """Pixel centres (u, v) of the window (row0, col0, rows, cols), float32 arrays of
    ``xp`` (jax.numpy or numpy); with ``stride``, the window's ``rows`` × ``cols`` pixels
    at every stride-th row and column from stride // 2."""
    row0, col0, rows, cols = window
    every = isinstance(stride, (int, np.integer)) and stride == 1  # a traced stride is a lattice

    def pixels(n):
        return xp.arange(n, dtype=xp.float32) if every else (stride // 2 + stride * xp.arange(n)).astype(xp.float32)

    v, u = row0 + pixels(rows), col0 + pixels(cols)
    return xp.meshgrid(u, v, indexing="xy")


@dataclasses.dataclass(frozen=True)
class _Camera:
    width: int
    height: int

    measures_range = False
    """True when the image stores range along the ray rather than z-depth."""

    if TYPE_CHECKING:  # every subclass has a principal point; not a field of the base
        cx: float
        cy: float

    def ray_params(self) -> np.ndarray:
        """The (4,) float32 numbers the model's rays are computed from
        (:meth:`_rays_of`): what a compiled program takes of the camera
        (:class:`CompiledCamera`)."""
        raise NotImplementedError

    @staticmethod
    def _rays_of(params, uu, vv) -> tuple[Float[Array, "h w 3"], Float[Array, "h w 3"]]:
        """Origins and directions of the rays through pixel centres ``uu``, ``vv`` of a
        camera with :meth:`ray_params` ``params``: host (numpy) arrays for host input,
        JAX arrays for JAX input (as :func:`_array`)."""
        raise NotImplementedError

    def _rays(self, uu, vv) -> tuple[Float[Array, "h w 3"], Float[Array, "h w 3"]]:
        return self._rays_of(self.ray_params(), uu, vv)

    def compiled(self) -> CompiledCamera:
        """This camera as compiled programs take it (:class:`CompiledCamera`)."""
        return CompiledCamera(type(self), self.ray_params())

    def _scaled_fields(self, f: int) -> dict:
        """The model-specific fields of :meth:`downsampled` (``cx``, ``cy`` excluded)."""
        raise NotImplementedError

    def _pixel_grid(self, window, xp=jnp, stride=1):
        """:func:`_pixel_grid` of ``window``, or of the full image (``window`` None)."""
        return _pixel_grid((0, 0, self.height, self.width) if window is None else window, xp, stride)

    def rays(self, window=None, *, stride=1) -> tuple[Float[Array, "h w 3"], Float[Array, "h w 3"]]:
        """Ray origins and directions for every pixel, or for ``window``.

        ``window`` is ``(row0, col0, rows, cols)``; ``row0``/``col0`` may be traced,
        ``rows``/``cols`` must be Python ints. Pixels outside the image are still given
        rays (the window may hang over the border). With ``stride`` (may be traced), the
        window's rows and columns are every stride-th from stride // 2: a pruning
        lattice, whose rays are the full window's at those pixels, bit for bit.
        """
        uu, vv = self._pixel_grid(window, stride=stride)
        return self._rays(uu, vv)

    def pixel_size_at(
        self, depth: Float[Array, "..."] | Float[np.ndarray, "..."] | float | np.floating
    ) -> Float[Array, "..."]:
        """Metric width of one pixel at the given depth (for pixel-equivalent errors)."""
        raise NotImplementedError

    def downsampled(self, factor: int):
        """The camera of an image binned ``factor`` × ``factor`` (pixel (i, j) of the new
        image covers old pixels [factor·i, factor·i + factor))."""
        f = self._factor("factor", factor)
        shift = (f - 1) / 2.0
        common = dict(
            width=self.width // f, height=self.height // f, cx=(self.cx - shift) / f, cy=(self.cy - shift) / f
        )
        return dataclasses.replace(self, **common, **self._scaled_fields(f))

    def cropped(self, window, step: int = 1):
        """The camera of ``image[row0 : row0 + rows : step, col0 : col0 + cols : step]``,
        ``window`` = (row0, col0, rows, cols) inside the image: the same rays as those
        pixels of this camera."""
        s = self._factor("step", step)
        row0, col0, rows, cols = (int(x) for x in window)
        if not (
            0 <= row0
            and 0 <= col0
            and rows >= 1
            and cols >= 1
            and row0 + rows <= self.height
            and col0 + cols <= self.width
        ):
            raise ValueError(
                f"window: got {window!r}, expected (row0, col0, rows, cols) inside {self.width}x{self.height}"
            )
        common = dict(width=-(-cols // s), height=-(-rows // s), cx=(self.cx - col0) / s, cy=(self.cy - row0) / s)
        return dataclasses.replace(self, **common, **self._scaled_fields(s))

    def _factor(self, name: str, f) -> int:
        if not (isinstance(f, (int, np.integer)) and f >= 1):
            raise ValueError(f"{name}: got {f!r}, expected an integer >= 1")
        if f > min(self.width, self.height):
            raise ValueError(
                f"{name}: got {f}, expected at most {min(self.width, self.height)} for a {self.width}x{self.height} camera"
            )
        return int(f)

    def points(self, range_image) -> np.ndarray:
        """Back-project a range image to camera-frame points, shape (h, w, 3), NaN = none
        (float64, computed on the host)."""
        o, d = (np.asarray(a, np.float64) for a in camera_rays(self))
        r = np.asarray(range_image, np.float64)[..., None]
        return o + r * d


MAX_RAY_ANGLE = 85
"""Degrees off the optical axis a pinhole camera's image may reach (a 170-degree field of
view): beyond it a pinhole model is not the camera (a fisheye is not one, and real
rectified cameras stay well within it)."""


@dataclasses.dataclass(frozen=True)
class PinholeCamera(_Camera):
    """Pinhole camera with focal lengths ``fx``, ``fy`` and principal point ``cx``, ``cy``
    in pixels; reads and writes Open3D's PinholeCameraIntrinsic JSON."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self):
        _check_image_size(_check_positive_int("width", self.width), _check_positive_int("height", self.height))
        for name in ("fx", "fy"):
            object.__setattr__(self, name, _check_finite(name, getattr(self, name), positive=True))
        for name in ("cx", "cy"):
            object.__setattr__(self, name, _check_finite(name, getattr(self, name)))
        # The image's edges (pixel centres at 0 .. n-1, edges half a pixel out) seen at most
        # MAX_RAY_ANGLE off the optical axis: a focal length given in metres or millimetres
        # instead of pixels is refused, not recovered into meaningless parts.
        for f, focal, c, centre, n, side in (
            ("fx", self.fx, "cx", self.cx, self.width, "wide"),
            ("fy", self.fy, "cy", self.cy, self.height, "high"),
        ):
            least = max(abs(-0.5 - centre), abs(n - 0.5 - centre)) / math.tan(math.radians(MAX_RAY_ANGLE))
            if focal < least:
                raise ValueError(
                    f"{f}: got {focal!r}, expected at least {least:.4g} pixels for an image {n} pixels {side} "
                    f"with {c} {centre!r} (rays within {MAX_RAY_ANGLE} degrees of the optical axis)"
                )

    def ray_params(self):
        # The reciprocals of the focal lengths, rounded once on the host: the host's and
        # the compiled programs' rays are bit for bit the same.
        return np.array([self.cx, self.cy, 1.0 / self.fx, 1.0 / self.fy], np.float32)

    @staticmethod
    def _rays_of(params, uu, vv):
        uu, xp = _array(uu)
        cx, cy, rx, ry = (params[i] for i in range(4))
        d = xp.stack([(uu - cx) * rx, (vv - cy) * ry, xp.ones_like(uu)], -1)
        return xp.zeros_like(d), d

    def pixel_size_at(self, depth):
        return depth / (0.5 * (self.fx + self.fy))

    def _scaled_fields(self, f):
        return {"fx": self.fx / f, "fy": self.fy / f}

    def project(self, points):
        """Camera-frame points (..., 3) to pixel coordinates (..., 2) as (u, v): a host
        (numpy) array for host points, a JAX array for JAX arrays."""
        p, xp = _array(points)
        return xp.stack([self.fx * p[..., 0] / p[..., 2] + self.cx, self.fy * p[..., 1] / p[..., 2] + self.cy], -1)

    def to_json(self) -> dict:
        k = np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=float)
        return {
            "width": self.width,
            "height": self.height,
            "intrinsic_matrix": k.flatten(order="F").tolist(),
        }


@dataclasses.dataclass(frozen=True)
class OrthographicCamera(_Camera):
    """Parallel rays along +z from the plane z = 0; ``pixel_size`` in scene units."""

    pixel_size: float
    cx: float
    cy: float

    def __post_init__(self):
        _check_image_size(_check_positive_int("width", self.width), _check_positive_int("height", self.height))
        object.__setattr__(self, "pixel_size", _check_finite("pixel_size", self.pixel_size, positive=True))
        for name in ("cx", "cy"):
            object.__setattr__(self, name, _check_finite(name, getattr(self, name)))

    def ray_params(self):
        return np.array([self.cx, self.cy, self.pixel_size, 0.0], np.float32)

    @staticmethod
    def _rays_of(params, uu, vv):
        uu, xp = _array(uu)
        cx, cy, s = (params[i] for i in range(3))
        o = xp.stack([(uu - cx) * s, (vv - cy) * s, xp.zeros_like(uu)], -1)
        d = xp.broadcast_to(xp.asarray([0.0, 0.0, 1.0], xp.float32), o.shape)
        return o, d

    def pixel_size_at(self, depth):
        # The same at every depth. Host input gets a numpy array: filling one with JAX
        # outside a trace would compile a program per shape.
        if isinstance(depth, jax.Array):
            return jnp.full_like(depth, self.pixel_size)
        depth = np.asarray(depth)
        return np.full(depth.shape, self.pixel_size, depth.dtype if depth.dtype.kind == "f" else np.float64)

    def _scaled_fields(self, f):
        return {"pixel_size": self.pixel_size * f}

    def project(self, points):
        """As :meth:`PinholeCamera.project` (z plays no part)."""
        p, xp = _array(points)
        return xp.stack([p[..., 0] / self.pixel_size + self.cx, p[..., 1] / self.pixel_size + self.cy], -1)

    def to_json(self) -> dict:
        return {
            "model": "orthographic",
            "width": self.width,
            "height": self.height,
            "pixel_size": self.pixel_size,
            "cx": self.cx,
            "cy": self.cy,
        }


@dataclasses.dataclass(frozen=True)
class ScannerCamera(_Camera):
    """Wide-angle azimuth/elevation scanner; stores *range along the ray*.

    ``azimuth_step`` and ``elevation_step`` are radians per pixel; ``cx``, ``cy`` the
    pixel looking straight along +z. JSON: ``{"model": "scanner", "width", "height",
    "azimuth_step", "elevation_step", "cx", "cy"}``.
    """

    azimuth_step: float
    elevation_step: float
    cx: float
    cy: float

    measures_range = True

    def __post_init__(self):
        _check_image_size(_check_positive_int("width", self.width), _check_positive_int("height", self.height))
        for name in ("azimuth_step", "elevation_step"):
            object.__setattr__(self, name, _check_finite(name, getattr(self, name), positive=True))
        for name in ("cx", "cy"):
            object.__setattr__(self, name, _check_finite(name, getattr(self, name)))
        half_az = max(self.cx, self.width - 1 - self.cx) * self.azimuth_step
        half_el = max(self.cy, self.height - 1 - self.cy) * self.elevation_step
        if half_az >= np.pi / 2 or half_el >= np.pi / 2:
            raise ValueError(
                f"azimuth_step/elevation_step: got half-angles {np.degrees(half_az):.1f} and "
                f"{np.degrees(half_el):.1f} degrees, expected a field of view under 180 degrees"
            )

    def ray_params(self):
        return np.array([self.cx, self.cy, self.azimuth_step, self.elevation_step], np.float32)

    @staticmethod
    def _rays_of(params, uu, vv):
        uu, xp = _array(uu)
        cx, cy, az_step, el_step = (params[i] for i in range(4))
        az = (uu - cx) * az_step
        el = (vv - cy) * el_step
        d = xp.stack([xp.sin(az) * xp.cos(el), xp.sin(el), xp.cos(az) * xp.cos(el)], -1)
        return xp.zeros_like(d), d

    def pixel_size_at(self, depth):
        return depth * 0.5 * (self.azimuth_step + self.elevation_step)

    def _scaled_fields(self, f):
        return {"azimuth_step": self.azimuth_step * f, "elevation_step": self.elevation_step * f}

    def to_json(self) -> dict:
        return {
            "model": "scanner",
            "width": self.width,
            "height": self.height,
            "azimuth_step": self.azimuth_step,
            "elevation_step": self.elevation_step,
            "cx": self.cx,
            "cy": self.cy,
        }


Camera = PinholeCamera | OrthographicCamera | ScannerCamera


def check_range_image(depth, camera: Camera) -> np.ndarray:
    """A range image checked against its camera, as float64 with NaN for every pixel
    without a return (NaN, inf, 0 or negative, or beyond :data:`DEPTH_RANGE` beside
    returns within it: a renderer's background marker, Blender's 1e10)."""
    if not isinstance(camera, _Camera):
        raise TypeError(f"camera: got {type(camera).__name__}, expected a sqparts camera")
    raw = np.asarray(depth) if not isinstance(depth, (str, bytes)) else np.asarray(None)
    if not (np.issubdtype(raw.dtype, np.integer) or np.issubdtype(raw.dtype, np.floating)):
        raise TypeError(f"depth: got {type(depth).__name__} of {raw.dtype}, expected an array of real depths")
    d = raw.astype(np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth: got shape {d.shape}, expected a 2-D range image")
    if d.shape != (camera.height, camera.width):
        raise ValueError(f"depth: got shape {d.shape}, expected {(camera.height, camera.width)} to match the camera")
    with np.errstate(invalid="ignore"):
        d = np.where(np.isfinite(d) & (d > 0), d, np.nan)
        far = d > DEPTH_RANGE[1]
    if far.any() and not far[np.isfinite(d)].all():  # a renderer's "no hit" (Blender's Z pass: 1e10)
        d[far] = np.nan
    if np.isfinite(d).any():
        lo, hi = float(np.nanmin(d)), float(np.nanmax(d))
        if lo < DEPTH_RANGE[0] or hi > DEPTH_RANGE[1]:
            raise ValueError(
                f"depth: got returns from {lo:.3g} to {hi:.3g}, expected depths in "
                f"[{DEPTH_RANGE[0]:g}, {DEPTH_RANGE[1]:g}] scene units (rescale the image)"
            )
    return d


def json_numbers(value) -> bool:
    """Whether a JSON value is a number or nested lists of numbers (not true/false,
    which Python counts as integers, nor strings)."""
    if isinstance(value, list):
        return all(json_numbers(v) for v in value)
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


def camera_from_json(data: dict) -> Camera:
    """Build a camera from its JSON dict (Open3D pinhole, orthographic or scanner)."""
    if not isinstance(data, dict):
        raise ValueError(f"camera: got {type(data).__name__}, expected a JSON object")
    model = data.get("model", "pinhole")
    known = {
        "pinhole": {"width", "height", "intrinsic_matrix", "model"},
        "orthographic": {"model", "width", "height", "pixel_size", "cx", "cy"},
        "scanner": {"model", "width", "height", "azimuth_step", "elevation_step", "cx", "cy"},
    }
    if not isinstance(model, str) or model not in known:
        raise ValueError(f"camera.model: got {model!r:.60}, expected one of {sorted(known)}")
    required = known[model] - {"model"}
    missing = sorted(required - set(data))
    if missing:
        raise ValueError(
            f"camera: got no {', '.join(missing)}, expected keys {sorted(required)} for camera model {model!r}"
        )
    unknown = sorted(set(data) - known[model])
    if unknown:
        raise ValueError(
            f"camera: got unknown key(s) {unknown}, expected only {sorted(known[model])} for camera model {model!r}"
        )
    try:
        return _camera_of_model(model, data)
    except ValueError as e:  # a field's check: name it as the file does
        name, _, rest = str(e).partition(": ")
        if name in ("fx", "fy", "cx", "cy") and model == "pinhole":
            raise ValueError(f"camera.intrinsic_matrix: {rest} ({name})") from None
        if name in known[model]:
            raise ValueError(f"camera.{name}: {rest}") from None
        raise


def _camera_of_model(model: str, data: dict) -> Camera:
    for key, value in data.items():
        if key != "model" and not json_numbers(value):
            raise ValueError(f"camera.{key}: got {value!r:.60}, expected numbers")
    if model == "pinhole":
        try:
            k = np.asarray(data["intrinsic_matrix"], dtype=float)
        except (TypeError, ValueError):
            raise ValueError(
                f"camera.intrinsic_matrix: got {data['intrinsic_matrix']!r:.80}, expected 9 numbers"
            ) from None
        if k.size != 9:
            raise ValueError(f"camera.intrinsic_matrix: got {k.size}, expected 9 numbers (column-major 3x3)")
        k = k.reshape(3, 3, order="F")
        if (
            not np.all(np.isfinite(k))
            or abs(k[0, 1]) > 1e-9
            or abs(k[1, 0]) > 1e-9
            or np.any(np.abs(k[2] - [0, 0, 1]) > 1e-9)
        ):
            raise ValueError(
                f"camera.intrinsic_matrix: got {k.tolist()}, expected finite "
                "[[fx,0,cx],[0,fy,cy],[0,0,1]] (column-major)"
            )
        return PinholeCamera(data["width"], data["height"], k[0, 0], k[1, 1], k[0, 2], k[1, 2])
    if model == "orthographic":
        return OrthographicCamera(data["width"], data["height"], data["pixel_size"], data["cx"], data["cy"])
    return ScannerCamera(
        data["width"],
        data["height"],
        data["azimuth_step"],
        data["elevation_step"],
        data["cx"],
        data["cy"],
    )


# --- a camera and an image as compiled programs take them ------------------------------


@functools.partial(jax.tree_util.register_dataclass, data_fields=["params"], meta_fields=["model"])
@dataclasses.dataclass(frozen=True, eq=False)  # its params an array: compared by identity
class CompiledCamera:
    """A camera as the compiled stages take it: its model (the class) is part of the
    program, its intrinsics (``params``, :meth:`~PinholeCamera.ray_params`) are an
    argument, and its image size plays no part. So every camera of one model, whatever
    its intrinsics and image size, shares the programs; the rays are the camera's bit for
    bit (the same float32 arithmetic on the same float32 numbers)."""

    model: type
    params: Float[Array, "4"] | np.ndarray

    def rays(self, window, *, stride=1) -> tuple[Float[Array, "h w 3"], Float[Array, "h w 3"]]:
        """:meth:`PinholeCamera.rays` of ``window`` (row0, col0, rows, cols; ``rows`` and
        ``cols`` Python ints, the rest may be traced)."""
        uu, vv = _pixel_grid(window, jnp, stride)
        return self.model._rays_of(self.params, uu, vv)


IMAGE_BUCKET = 32
"""Rows and columns of the image a part's tiles are laid out in
(:func:`~sqparts._encoding.render_layers`) are a multiple of this (:func:`bucket_camera`)."""


def bucket_camera(camera: Camera) -> Camera:
    """``camera`` for its image padded at the bottom and right to a multiple of
    ``IMAGE_BUCKET`` pixels: the same rays at every pixel of the image."""

    def up(n):
        return -(-int(n) // IMAGE_BUCKET) * IMAGE_BUCKET

    return dataclasses.replace(camera, width=up(camera.width), height=up(camera.height))


IMAGE_SIDE = 320
"""Rows and columns of the smallest array the compiled stages see an image in
(:func:`image_bucket`): an image :func:`~sqparts.recover_scene` bins to its default
resolution (a longest side of 160-319 pixels, :func:`~sqparts._preprocess.auto_factor`)
fits it."""


def image_bucket(n: int) -> int:
    """Rows (or columns) of the array an image of ``n`` rows (columns) is padded into, at
    the bottom (right), for the compiled stages: the least multiple of
    :data:`IMAGE_SIDE` that holds it. Their programs take the image's array, so images
    of any size up to 320 x 320 share them; a search computes on windows of it, so the
    padding costs no work."""
    return IMAGE_SIDE * max(1, -(-int(n) // IMAGE_SIDE))


def camera_rays(camera: _Camera) -> tuple[np.ndarray, np.ndarray]:
    """``camera.rays()`` as host (numpy, float32) arrays, (h, w, 3) each, computed on the
    host: the same float32 arithmetic, and no XLA program built for it."""
    origins, directions = camera._rays(*camera._pixel_grid(None, np))
    return np.asarray(origins), np.asarray(directions)
