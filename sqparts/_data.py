"""Data preparation: a range image checked, padded for windowed search and paired with its
camera, its figure and its encoding (:class:`RangeData`), what every later stage reads.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np

from ._camera import Camera, CompiledCamera, check_range_image, image_bucket
from ._encoding import Encoding, encoding_for


@dataclasses.dataclass(frozen=True)
class RangeData:
    """A range image prepared for search: NaN-padded depth and figure mask, camera and
    encoding. Only its arrays (padded to :func:`~sqparts._camera.image_bucket` sizes), σ
    and λ (runtime scalars) and the camera's intrinsics (:class:`CompiledCamera`) enter
    compiled code, so a new image of a size, camera and window seen before compiles
    nothing."""

    depth: jax.Array  # (Hb + 2 pad, Wb + 2 pad) float32, NaN = no return; Hb, Wb: H, W
    figure: jax.Array  # same shape, bool        # rounded up by image_bucket (NaN, False)
    pad: int
    camera: Camera
    encoding: Encoding

    @property
    def arrays(self):
        """(depth, figure, σ, λ): what the compiled stages take."""
        enc = self.encoding
        return (self.depth, self.figure, np.float32(enc.sigma), np.float32(enc.commission_weight))

    @property
    def compiled_camera(self) -> CompiledCamera:
        """The camera the compiled stages see: its model and intrinsics, not its image size."""
        return self.camera.compiled()

    @property
    def image(self) -> np.ndarray:
        p = self.pad
        return np.asarray(self.depth)[p : p + self.camera.height, p : p + self.camera.width]

    @property
    def figure_region(self) -> np.ndarray:
        """The figure's pixels, including those without a return inside its outline
        (neither explained nor commission)."""
        p = self.pad
        return np.asarray(self.figure)[p : p + self.camera.height, p : p + self.camera.width]

    @property
    def figure_mask(self) -> np.ndarray:
        """The figure's pixels that have a return (the pixels to be explained)."""
        return self.figure_region & np.isfinite(self.image)


PAD = 64
"""Pixels of padding around a prepared image: a window (or frame) cut at any pixel stays
inside the array."""


def prepare(depth, camera: Camera, *, figure=None, encoding: Encoding | None = None, pad: int = PAD) -> RangeData:
    """Check a range image and pad it for windowed search.

    ``figure`` (bool, same shape) marks the figure of interest; default: every pixel with
    a return. Figure pixels without a return (holes in a sensor's data) are *unknown*: a
    part drawn there is neither an explained pixel nor an error of commission.
    ``encoding`` defaults to :func:`~sqparts.encoding_for` of the figure, σ at least
    half a pixel footprint at the figure's depth (:func:`figure_footprint`).
    """
    d = check_range_image(depth, camera).astype(np.float32)
    fig = np.isfinite(d) if figure is None else np.asarray(figure, bool)
    if fig.shape != d.shape:
        raise ValueError(f"figure: got shape {fig.shape}, expected {d.shape}")
    if (fig & np.isfinite(d)).sum() < 4:
        raise ValueError(
            f"depth: got a figure of {int((fig & np.isfinite(d)).sum())} pixels with returns, expected at least 4"
        )
    if encoding is not None and not isinstance(encoding, Encoding):
        raise TypeError(
            f"encoding: got {encoding!r:.60} ({type(encoding).__name__}), expected a sqparts.Encoding or None"
        )
    enc = encoding or encoding_for(d[fig & np.isfinite(d)], footprint=figure_footprint(d, fig, camera))
    h, w = d.shape
    grow = ((pad, pad + image_bucket(h) - h), (pad, pad + image_bucket(w) - w))
    # device_put, not jnp.asarray: a transfer, not a compiled program per shape.
    return RangeData(
        jax.device_put(np.pad(d, grow, constant_values=np.nan)),
        jax.device_put(np.pad(fig, grow, constant_values=False)),
        pad,
        camera,
        enc,
    )


def figure_footprint(depth, figure, camera: Camera) -> float:
    """Metric width of one pixel at the median depth of the figure's returns (NaN if it
    has none): the least σ of :func:`~sqparts.encoding_for` is half of it."""
    d = np.asarray(depth)[np.asarray(figure, bool) & np.isfinite(depth)]
    return float(np.asarray(camera.pixel_size_at(np.float32(np.median(d))))) if d.size else math.nan
