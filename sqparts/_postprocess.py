"""After recovery: prettifying (section 4.3) and the residual surface model (section 2.1.1).

**Prettifying** (Figure 10d) applies the domain knowledge that nearly vertical or
horizontal parts are likely to *be* vertical or horizontal. :func:`snap_to_gravity`
turns a part by the smallest rotation that makes its axis nearest to "up" exactly
vertical (or, failing that, its longest axis exactly horizontal) when the axis is within
``max_angle`` of it; :func:`prettify` keeps each snap only when the description length
E rises by at most ``max_bits``: a part is straightened when the data allow it. A
snapped part that is bent or tapered is also tried without its deformation (a taper can
stand in for a lean), and the cheaper of the two is judged.

**Residual surface model** (section 2.1.1, Figure 11f): the parts are a "cartoon"; the
data's small deviations from them, R - R*, are described separately by a fractal
(fractional Brownian) surface: E[(r(x + d) - r(x))²] = s² |d|^(2H). The Hurst exponent
H gives the fractal dimension D = 3 - H of the residual surface (2 = smooth, 3 = as rough
as white noise). :func:`fit_fractal` estimates H and s from the residual's variogram and
:meth:`FractalSurface.synthesize` draws a surface with the same statistics, which added to
the parts' range image gives Figure 11(f).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ._encoding import Costs
from ._part import Part, rotation_matrix, rotation_vector, stack_parts
from ._typing import freeze_fields

# --- prettifying ------------------------------------------------------------------------


def _unit(name: str, v) -> np.ndarray:
    a = np.asarray(v, np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) < 1e-12:
        raise ValueError(f"{name}: got {v!r}, expected a non-zero 3-vector")
    return a / np.linalg.norm(a)


def _turn(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation (3×3) taking unit vector a to unit vector b."""
    c = np.cross(a, b)
    s, cos = np.linalg.norm(c), float(a @ b)
    if s < 1e-15:
        return np.eye(3)
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(c / s * math.atan2(s, cos)).as_matrix()


def snap_rotation(matrix, up, *, max_angle: float = 15.0) -> tuple[np.ndarray, str, float]:
    """Snap one part's rotation (part-to-camera 3×3) to gravity.

    Returns (rotation, kind, angle): ``kind`` is ``"vertical"`` when the local axis
    nearest to ``up`` was within ``max_angle`` degrees of it and is now parallel to it,
    ``"horizontal"`` when instead the longest axis (local z) was within ``max_angle`` of
    the horizontal plane and now lies in it, else ``"none"``; ``angle`` is the turn in
    degrees.
    """
    r = np.asarray(matrix, np.float64)
    u = _unit("up", up)
    cos = r.T @ u  # each local axis against up
    k = int(np.argmax(np.abs(cos)))
    tilt = math.degrees(math.acos(min(1.0, abs(float(cos[k])))))
    if tilt <= max_angle:
        q = _turn(r[:, k], np.sign(cos[k]) * u)
        return q @ r, "vertical", tilt
    z = r[:, 2]
    slope = math.degrees(math.asin(min(1.0, abs(float(z @ u)))))
    if slope <= max_angle:
        flat = z - (z @ u) * u
        q = _turn(z, flat / np.linalg.norm(flat))
        return q @ r, "horizontal", slope
    return r, "none", 0.0


def snap_to_gravity(parts: Part, up, *, max_angle: float = 15.0) -> tuple[Part, list[dict]]:
    """:func:`snap_rotation` for every part (turned about its own centre)."""
    if not (isinstance(max_angle, (int, float)) and 0 <= max_angle <= 90):
        raise ValueError(f"max_angle: got {max_angle!r}, expected degrees in [0, 90]")
    out, report = [], []
    for i in range(len(parts)):
        p = parts[i]
        r, kind, angle = snap_rotation(np.asarray(rotation_matrix(p.orientation)), up, max_angle=max_angle)
        out.append(dataclasses.replace(p, orientation=np.asarray(rotation_vector(r), np.asarray(p.orientation).dtype)))
        report.append({"snap": kind, "angle_deg": angle})
    return stack_parts(out), report


def prettify(parts: Part, data, costs: Costs, *, up, max_angle: float = 15.0, max_bits: float = 56.0):
    """Snap nearly vertical / horizontal parts to gravity, one part at a time, keeping a
    snap only if the joint description length E rises by at most ``max_bits``
    (default: half a part's κ0) and every part that paid for itself still does (removing
    it would not shorten the description: a snap may not make a part worth dropping).
    Returns (parts, cost, report), where each report entry says what was tried (``snap``,
    ``angle_deg``), the change in E (``delta_bits``), whether it was ``kept`` and, if
    not, ``why``. A snapped part that is bent or tapered is also tried straight
    (``straightened``: the cheaper of the two is the one judged)."""
    from ._encoding import Edit, edit_costs, encoding_cost

    if not (isinstance(max_bits, (int, float)) and math.isfinite(max_bits) and max_bits >= 0):
        raise ValueError(f"max_bits: got {max_bits!r}, expected a finite number >= 0")
    snapped, report = snap_to_gravity(parts, up, max_angle=max_angle)
    cost = encoding_cost(parts, data, costs)
    every = range(len(parts))

    def paying(c):  # which parts lower E by their presence
        return np.array([r.total > c.total for r in edit_costs(c, [Edit((i,)) for i in every], data, costs)])

    current, pays = parts, paying(cost)
    for i, entry in enumerate(report):
        entry["kept"], entry["straightened"], entry["delta_bits"] = False, False, 0.0
        if entry["snap"] == "none":
            continue
        # A bend or taper can stand in for a tilt (a tapered post leaning back shows a
        # front at one depth), so the snapped part is also tried straight.
        shapes = [snapped[i]]
        if np.any(np.asarray(snapped[i].bend) != 0) or np.asarray(snapped[i].taper) != 0:
            shapes.append(
                dataclasses.replace(
                    snapped[i], bend=np.zeros_like(snapped[i].bend), taper=np.zeros_like(snapped[i].taper)
                )
            )
        trials = [stack_parts([shape if j == i else current[j] for j in every]) for shape in shapes]
        trial_costs = [encoding_cost(t, data, costs) for t in trials]
        k = int(np.argmin([c.total for c in trial_costs]))
        trial, trial_cost = trials[k], trial_costs[k]
        entry["delta_bits"], entry["straightened"] = trial_cost.total - cost.total, k == 1
        if entry["delta_bits"] > max_bits:
            entry["why"] = "costs more than max_bits"
            continue
        trial_pays = paying(trial_cost)
        if (pays & ~trial_pays).any():
            entry["why"] = "a part would no longer pay for itself"
            continue
        current, cost, pays, entry["kept"] = trial, trial_cost, trial_pays, True
    return current, cost, report


# --- residual surface model ---------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class FractalSurface:
    """A fractional Brownian surface: E[(r(x + d) - r(x))²] = s² |d|^(2H), d in pixels.

    Attributes
    ----------
    hurst : H in (0, 1).
    scale : s, the rms difference between neighbouring pixels (depth units).
    lags, variogram : the measured variogram it was fitted to (for plots).
    """

    hurst: float
    scale: float
    lags: tuple = ()
    variogram: tuple = ()

    @property
    def fractal_dimension(self) -> float:
        """D = 3 - H, the fractal dimension of the surface z = r(x, y)."""
        return 3.0 - self.hurst

    def synthesize(self, shape, *, seed: int = 0) -> np.ndarray:
        """A surface of this H and s (spectral synthesis: white noise filtered by
        |f|^-(H+1), scaled so the lag-1 variogram is s²)."""
        h, w = (int(x) for x in shape)
        n = 2 * max(h, w)  # synthesize larger, crop: no wrap-around correlation
        rng = np.random.default_rng(seed)
        fy, fx = np.fft.fftfreq(n)[:, None], np.fft.fftfreq(n)[None, :]
        f = np.hypot(fy, fx)
        f[0, 0] = np.inf
        spectrum = (rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))) * f ** (-(self.hurst + 1.0))
        z = np.real(np.fft.ifft2(spectrum))[:h, :w]
        g1 = 0.5 * (np.mean(np.diff(z, axis=0) ** 2) + np.mean(np.diff(z, axis=1) ** 2))
        return (z - z.mean()) * (self.scale / math.sqrt(max(g1, 1e-300)))


def variogram(residual, lags=(1, 2, 3, 4, 6, 8)) -> tuple[np.ndarray, np.ndarray]:
    """Mean squared difference of a map (NaN = unknown) at each lag, along rows and
    columns; returns (lags, values) for the lags with at least 16 pairs."""
    r = np.asarray(residual, np.float64)
    out_l, out_v = [], []
    for d in lags:
        diffs = []
        if r.shape[1] > d:
            diffs.append((r[:, d:] - r[:, :-d]).ravel())
        if r.shape[0] > d:
            diffs.append((r[d:] - r[:-d]).ravel())
        if not diffs:
            continue
        x = np.concatenate(diffs)
        x = x[np.isfinite(x)]
        if x.size >= 16:
            out_l.append(d)
            out_v.append(float(np.mean(x**2)))
    return np.asarray(out_l, float), np.asarray(out_v, float)


def fit_fractal(residual, *, lags=(1, 2, 3, 4, 6, 8)) -> FractalSurface:
    """Fit H and s of a fractional Brownian surface to a residual map (NaN = unknown) by
    least squares on log variogram = 2H log d + 2 log s."""
    lag, v = variogram(residual, lags)
    ok = v > 0
    if ok.sum() < 2:
        raise ValueError(
            "residual: got too few valid pixel pairs, expected at least two lags with 16 pairs and non-zero variance"
        )
    slope, icpt = np.polyfit(np.log(lag[ok]), np.log(v[ok]), 1)
    hurst = float(np.clip(slope / 2.0, 0.01, 0.99))
    return FractalSurface(hurst, float(math.exp(icpt / 2.0)), tuple(lag.tolist()), tuple(v.tolist()))


@dataclasses.dataclass(frozen=True)
class ResidualModel:
    """The data's deviation from the parts and its fractal description.

    Attributes
    ----------
    residual : (H, W) R - R* on the figure where both exist and |R - R*| ≤ ``clip``·σ
        (farther pixels are omissions, not surface detail), NaN elsewhere.
    fractal : the :class:`FractalSurface` fitted to it.
    model : (H, W) the parts' range image R*.
    model_plus_residual : R* plus a synthesized fractal surface with the residual's
        mean, where the parts are drawn (Figure 11f).
    """

    residual: np.ndarray
    fractal: FractalSurface
    model: np.ndarray
    model_plus_residual: np.ndarray

    def __post_init__(self):
        freeze_fields(self)

    def summary(self) -> str:
        f = self.fractal
        rms = float(np.sqrt(np.nanmean(self.residual**2)))
        return f"residual rms {rms:.3g}; fractal dimension {f.fractal_dimension:.2f} (H = {f.hurst:.2f}, s = {f.scale:.3g})"


def residual_model(recovery, *, clip: float = 2.0, seed: int = 0) -> ResidualModel:
    """The residual surface model of a :class:`~sqparts.Recovery` (section 2.1.1)."""
    if not (isinstance(clip, (int, float)) and clip > 0):
        raise ValueError(f"clip: got {clip!r}, expected a number > 0")
    model = np.asarray(recovery.cost.rendered, np.float64)
    depth = np.asarray(recovery.depth, np.float64)
    sigma = float(recovery.settings["sigma"])
    with np.errstate(invalid="ignore"):
        r = depth - model
        keep = recovery.figure & np.isfinite(r) & (np.abs(r) <= clip * sigma)
    residual = np.where(keep, r, np.nan)
    fractal = fit_fractal(residual)
    texture = fractal.synthesize(model.shape, seed=seed) + float(np.nanmean(residual))
    return ResidualModel(
        residual.astype(np.float32),
        fractal,
        model.astype(np.float32),
        np.where(np.isfinite(model), model + texture, np.nan).astype(np.float32),
    )
