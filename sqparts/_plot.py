"""Pictures at the edge: range images and reports as PNG (matplotlib, Agg)."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.figure import Figure

from ._io import atomic_write


def _subplots(nrows: int = 1, ncols: int = 1, **figure):
    """A figure and its axes without pyplot: no global state and no backend switched,
    so a report can be drawn on any thread and beside the caller's own figures."""
    fig = Figure(**figure)
    return fig, fig.subplots(nrows, ncols)


def range_image_rgb(depth, *, vmin=None, vmax=None, cmap: str = "viridis_r") -> np.ndarray:
    """uint8 RGB picture of a range image: near = bright; no return = black."""
    d = np.asarray(depth, np.float64)
    ok = np.isfinite(d)
    lo = np.nanmin(d) if vmin is None and ok.any() else (vmin or 0.0)
    hi = np.nanmax(d) if vmax is None and ok.any() else (vmax or 1.0)
    scaled = np.clip((d - lo) / max(hi - lo, 1e-12), 0, 1)
    rgb = matplotlib.colormaps[cmap](np.where(ok, scaled, 0))[..., :3]
    rgb[~ok] = 0
    return (rgb * 255).astype(np.uint8)


def _printable(text: str | None) -> str | None:
    """``text`` as a title can show it: a file name that is not UTF-8 (kept by Python as
    surrogate escapes) gets replacement characters."""
    return None if text is None else text.encode("utf-8", "surrogateescape").decode("utf-8", "replace")


def save_range_image_png(path, depth, *, title: str | None = None) -> None:
    """Save a range image as a PNG picture with a colour bar (atomic)."""
    title = _printable(title)
    d = np.asarray(depth, np.float32)
    fig, ax = _subplots(figsize=(5, 5 * d.shape[0] / max(d.shape[1], 1) + 0.6), dpi=100)
    im = ax.imshow(np.ma.masked_invalid(d), cmap="viridis_r", interpolation="nearest")
    ax.set_facecolor("black")
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="depth")
    ax.set_title(title or f"{d.shape[1]}x{d.shape[0]}, {np.isfinite(d).mean():.0%} returns")
    ax.set_xticks([])
    ax.set_yticks([])
    _save(fig, path)


def _save(fig, path) -> None:
    path = Path(path)
    with atomic_write(path, "wb") as f:
        fig.savefig(f, format="png", bbox_inches="tight")


def _label_rgb(labels, depth=None) -> np.ndarray:
    """A colour per part label (-1 = black), shaded by depth when given."""
    lab = np.asarray(labels)
    cmap = matplotlib.colormaps["tab20"]
    rgb = cmap((lab % 20) / 19.999)[..., :3]
    if depth is not None:
        d = np.asarray(depth, np.float64)
        ok = np.isfinite(d)
        if ok.any():
            lo, hi = np.nanmin(d), np.nanmax(d)
            shade = 1.0 - 0.5 * np.clip((d - lo) / max(hi - lo, 1e-12), 0, 1)
            rgb = rgb * np.where(ok, shade, 1.0)[..., None]
    rgb[lab < 0] = 0
    return rgb


def save_report(path, recovery, *, title: str | None = None) -> None:
    """Report PNG in the spirit of Figures 7-11: the data, the initial explanation (parts
    chosen by selection), the final model (parts after refinement), the model's range
    image against the data, and the residual R* - R; with a one-line summary."""
    title = _printable(title)
    depth = recovery.depth
    fig_mask = recovery.figure
    ok = np.isfinite(depth)
    lo, hi = (np.nanmin(depth[fig_mask]), np.nanmax(depth[fig_mask])) if fig_mask.any() else (0, 1)
    fig, axes = _subplots(2, 3, figsize=(13, 8.6), dpi=90)
    ax = axes.ravel()
    ax[0].imshow(np.ma.masked_invalid(np.where(fig_mask, depth, np.nan)), cmap="viridis_r", vmin=lo, vmax=hi)
    ax[0].set_title("(a) range data (figure)")
    ax[1].imshow(_label_rgb(recovery.initial_cost.labels, recovery.initial_cost.rendered))
    ax[1].set_title(f"(b) initial explanation: {len(recovery.initial_parts)} parts")
    ax[2].imshow(_label_rgb(recovery.cost.labels, recovery.cost.rendered))
    ax[2].set_title(f"(c) final model: {len(recovery.parts)} parts")
    im = ax[3].imshow(np.ma.masked_invalid(recovery.cost.rendered), cmap="viridis_r", vmin=lo, vmax=hi)
    ax[3].set_title("(d) range image of the model")
    fig.colorbar(im, ax=ax[3], fraction=0.046, pad=0.04)
    resid = np.where(ok & fig_mask, recovery.cost.rendered - depth, np.nan)
    sigma = recovery.settings["sigma"]
    im = ax[4].imshow(np.ma.masked_invalid(resid), cmap="coolwarm", vmin=-2 * sigma, vmax=2 * sigma)
    ax[4].set_title("(e) residual R* - R (±2σ)")
    fig.colorbar(im, ax=ax[4], fraction=0.046, pad=0.04)
    status = np.zeros(depth.shape + (3,))
    status[fig_mask] = [0.85, 0.2, 0.2]  # omission
    status[recovery.cost.explained_mask] = [0.2, 0.7, 0.3]
    status[recovery.cost.commission_mask] = [0.2, 0.4, 0.9]
    ax[5].imshow(status)
    ax[5].set_title("(f) explained / omitted / commission")
    for a in ax:
        a.set_xticks([])
        a.set_yticks([])
    fig.suptitle((title + "\n" if title else "") + _wrap(recovery.summary()), fontsize=9)
    fig.tight_layout()
    _save(fig, path)


def _wrap(text: str, width: int = 150) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width))


def save_residual_report(path, recovery, model, *, title: str | None = None) -> None:
    """Figure 11 panels for a :class:`~sqparts.ResidualModel`: the residual R - R*, its
    variogram with the fractal fit, the parts' range image and parts plus residual model."""
    title = _printable(title)
    f = model.fractal
    fig, ax = _subplots(1, 4, figsize=(16, 4), dpi=90)
    sigma = recovery.settings["sigma"]
    im = ax[0].imshow(np.ma.masked_invalid(model.residual), cmap="coolwarm", vmin=-sigma, vmax=sigma)
    ax[0].set_title("residual R - R* (±σ)")
    fig.colorbar(im, ax=ax[0], fraction=0.046, pad=0.04)
    lags = np.asarray(f.lags)
    ax[1].loglog(lags, f.variogram, "o", label="measured")
    ax[1].loglog(lags, f.scale**2 * lags ** (2 * f.hurst), "-", label=f"fBm fit, H = {f.hurst:.2f}")
    ax[1].set_xlabel("lag (pixels)")
    ax[1].set_ylabel("mean squared difference")
    ax[1].set_title(f"fractal dimension {f.fractal_dimension:.2f}")
    ax[1].legend(fontsize=8)
    fm = recovery.figure
    d = recovery.depth
    lo, hi = (np.nanmin(d[fm]), np.nanmax(d[fm])) if fm.any() else (0, 1)
    ax[2].imshow(np.ma.masked_invalid(model.model), cmap="viridis_r", vmin=lo, vmax=hi)
    ax[2].set_title("parts R*")
    ax[3].imshow(np.ma.masked_invalid(model.model_plus_residual), cmap="viridis_r", vmin=lo, vmax=hi)
    ax[3].set_title("parts + fractal residual model (Fig. 11f)")
    for a in (ax[0], ax[2], ax[3]):
        a.set_xticks([])
        a.set_yticks([])
    if title:
        fig.suptitle(title + "\n" + model.summary(), fontsize=9)
    fig.tight_layout()
    _save(fig, path)


def save_recognition_report(path, recognition, *, title: str | None = None) -> None:
    """Report PNG of a recognition: the input, its recovered parts and the best-matching
    stored object's parts placed by the estimated pose (and articulated, when that
    verified better), corresponding parts in the same
    colour (unmatched recovered parts grey); with the scores of the top matches."""
    title = _printable(title)
    from ._render import render_range_image

    rec = recognition.recovery
    depth, camera = rec.depth, rec.camera
    parts = rec.parts
    _, labels = render_range_image(parts, camera, return_labels=True)
    labels = np.asarray(labels)
    match = recognition.matches[0] if recognition.matches else None
    colour = np.full(len(parts), -2)
    if match is not None:
        for k, (i, _) in enumerate(match.parts):
            colour[i] = k
    lab = np.where(labels >= 0, colour[np.clip(labels, 0, None)], -1)
    rgb = _label_rgb(np.where(lab == -2, 0, lab), depth)
    rgb[lab == -2] = 0.6
    panels = [("input", range_image_rgb(depth)), ("recovered parts (matched in colour)", rgb)]
    if match is not None:
        model = match.posed_parts()
        mdepth, mlabels = render_range_image(model, camera, return_labels=True)
        mlabels = np.asarray(mlabels)
        mcolour = np.full(len(model), -2)
        for k, (_, j) in enumerate(match.parts):
            mcolour[j] = k
        mlab = np.where(mlabels >= 0, mcolour[np.clip(mlabels, 0, None)], -1)
        mrgb = _label_rgb(np.where(mlab == -2, 0, mlab), mdepth)
        mrgb[mlab == -2] = 0.6
        posed = "at the estimated pose" + (", articulated" if match.articulation is not None else "")
        panels.append((f"model {match.name!r} ({match.kind}, view {match.view}) {posed}", mrgb))
    fig, axes = _subplots(1, len(panels), figsize=(4.2 * len(panels), 4.8), dpi=100)
    for ax, (name, img) in zip(np.atleast_1d(axes), panels):
        ax.imshow(img, interpolation="nearest")
        ax.set_title(_wrap(name, 40), fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(_wrap(f"{title + ': ' if title else ''}{recognition.summary()}", 110), fontsize=9)
    _save(fig, path)
