"""Pictures at the edge: range images and reports as PNG (matplotlib, Agg)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._io import atomic_write


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def range_image_rgb(depth, *, vmin=None, vmax=None, cmap: str = "viridis_r") -> np.ndarray:
    """uint8 RGB picture of a range image: near = bright; no return = black."""
    import matplotlib

    d = np.asarray(depth, np.float64)
    ok = np.isfinite(d)
    lo = np.nanmin(d) if vmin is None and ok.any() else (vmin or 0.0)
    hi = np.nanmax(d) if vmax is None and ok.any() else (vmax or 1.0)
    scaled = np.clip((d - lo) / max(hi - lo, 1e-12), 0, 1)
    rgb = matplotlib.colormaps[cmap](np.where(ok, scaled, 0))[..., :3]
    rgb[~ok] = 0
    return (rgb * 255).astype(np.uint8)


def save_range_image_png(path, depth, *, title: str | None = None) -> None:
    """Save a range image as a PNG picture with a colour bar (atomic)."""
    plt = _pyplot()
    d = np.asarray(depth, np.float32)
    fig, ax = plt.subplots(figsize=(5, 5 * d.shape[0] / max(d.shape[1], 1) + 0.6), dpi=100)
    im = ax.imshow(np.ma.masked_invalid(d), cmap="viridis_r", interpolation="nearest")
    ax.set_facecolor("black")
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="depth")
    ax.set_title(title or f"{d.shape[1]}x{d.shape[0]}, {np.isfinite(d).mean():.0%} returns")
    ax.set_xticks([])
    ax.set_yticks([])
    _save(fig, path)


def _save(fig, path) -> None:
    plt = _pyplot()
    path = Path(path)
    with atomic_write(path, "wb") as f:
        fig.savefig(f, format="png", bbox_inches="tight")
    plt.close(fig)
