"""Parameter grids for the massively parallel search (paper section 3.3.2).

A :class:`Grid` lists, per parameter, the values to try. Orientation is sampled as the
direction of the part's longest (local z) axis relative to the viewing ray through the
region, on a spherical grid of ``axis_step`` degrees, times a roll about that axis in
steps of ``roll_step``. The superquadric's symmetries are used so that no shape is
sampled twice:

* an undeformed superquadric is unchanged by 180° turns about its axes, and a bend of
  the z axis (x += b z²) is even in z, so z and -z are the same axis: the axis
  directions cover a hemisphere (half the azimuths on its rim); a taper is odd in z, so
  a taper grid keeps both signs instead;
* roll covers [0°, 180°): a 180° roll is a symmetry (and turns +bend into -bend, which
  the bend values already cover);
* sizes are ordered a3 ≥ a1 ≥ a2 (z is the longest axis; swapping a1 and a2 is a 90°
  roll): a3 takes ``lengths`` and a1 = a3·r1, a2 = a1·r2 with ratios ≤ 1.

The default preset is the paper's: ~2^16 hypotheses, most parameters at two or three
values, orientation every 22.5°, bending on the longest axis, no taper.
"""

from __future__ import annotations

import dataclasses
import math
import types
from collections.abc import Mapping

import numpy as np


def _values(name, v, lo=None, hi=None):
    arr = np.atleast_1d(np.asarray(v, np.float64))
    if arr.ndim != 1 or arr.size == 0 or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: got {v!r}, expected a non-empty list of finite numbers")
    if (lo is not None and np.any(arr < lo)) or (hi is not None and np.any(arr > hi)):
        raise ValueError(f"{name}: got {arr.tolist()}, expected values in [{lo}, {hi}]")
    return tuple(float(x) for x in arr)


@dataclasses.dataclass(frozen=True)
class Grid:
    """A declarative hypothesis grid.

    Parameters
    ----------
    lengths : relative values of a3 (the longest semi-axis), as fractions of the search's
        ``max_size`` (so the grid is scale-free).
    ratios1 : a1 / a3 values (≤ 1).
    ratios2 : a2 / a1 values (≤ 1).
    squareness1, squareness2 : ε1 and ε2 values.
    axis_step : spacing in degrees of the longest-axis directions.
    roll_step : spacing in degrees of the roll about that axis, over [0, 180).
    bends : values of bend[0] (the longest axis bending toward x).
    tapers : taper values.
    """

    lengths: tuple = (0.25, 0.5, 1.0)
    ratios1: tuple = (1.0, 0.55, 0.3)
    ratios2: tuple = (1.0, 0.55)
    squareness1: tuple = (0.3, 1.0)
    squareness2: tuple = (0.3, 1.0)
    axis_step: float = 22.5
    roll_step: float = 22.5
    bends: tuple = (-0.3, 0.0, 0.3)
    tapers: tuple = (0.0,)

    def __post_init__(self):
        for name, lo, hi in (
            ("lengths", 1e-6, None),
            ("ratios1", 1e-6, 1.0),
            ("ratios2", 1e-6, 1.0),
            ("squareness1", 0.1, 2.0),
            ("squareness2", 0.1, 2.0),
            ("bends", -1.0, 1.0),
            ("tapers", -1.0, 1.0),
        ):
            object.__setattr__(self, name, _values(name, getattr(self, name), lo, hi))
        for name in ("axis_step", "roll_step"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 < v <= 180):
                raise ValueError(f"{name}: got {v!r}, expected degrees in (0, 180]")

    # ---------------------------------------------------------------------------
    def axis_directions(self) -> np.ndarray:
        """Unit axis directions (n, 3) in the view frame (+z = along the viewing ray)."""
        step = math.radians(self.axis_step)
        symmetric = all(t == 0 for t in self.tapers)
        max_polar = math.pi / 2 if symmetric else math.pi
        dirs = []
        rings = int(round(max_polar / step))
        for i in range(rings + 1):
            polar = min(i * step, max_polar)
            n = max(1, int(round(2 * math.pi * math.sin(polar) / step)))
            if symmetric and abs(polar - math.pi / 2) < 1e-9:
                n = max(1, n // 2)  # rim of the hemisphere: d and -d coincide
                az = np.arange(n) * math.pi / n
            else:
                az = np.arange(n) * 2 * math.pi / n
            if polar in (0.0, math.pi):
                az = az[:1]
            for a in az:
                dirs.append([math.sin(polar) * math.cos(a), math.sin(polar) * math.sin(a), math.cos(polar)])
        return np.asarray(dirs)

    def rolls(self) -> np.ndarray:
        n = max(1, int(round(180.0 / self.roll_step)))
        return np.arange(n) * math.pi / n

    def relative_orientations(self) -> np.ndarray:
        """Rotation vectors (n, 3) of every (axis, roll) pair, in the view frame."""
        from scipy.spatial.transform import Rotation

        out = []
        z = np.array([0.0, 0.0, 1.0])
        for d in self.axis_directions():
            c = np.cross(z, d)
            s = np.linalg.norm(c)
            align = Rotation.from_rotvec(c / s * math.atan2(s, d @ z)) if s > 1e-12 else Rotation.identity()
            for r in self.rolls():
                out.append((align * Rotation.from_rotvec([0, 0, r])).as_rotvec())
        return np.asarray(out)

    def shapes(self) -> np.ndarray:
        """Every non-orientation combination, (n, 8): relative a1 a2 a3, ε1, ε2, bend0,
        bend1 (= 0), taper."""
        rows = []
        for a3 in self.lengths:
            for r1 in self.ratios1:
                for r2 in self.ratios2:
                    for e1 in self.squareness1:
                        for e2 in self.squareness2:
                            for b in self.bends:
                                for t in self.tapers:
                                    rows.append([a3 * r1, a3 * r1 * r2, a3, e1, e2, b, 0.0, t])
        return np.asarray(rows)

    def hypotheses(self) -> dict[str, np.ndarray]:
        """The full grid as flat float32 arrays (orientation-major), see :meth:`size`."""
        rot = self.relative_orientations()
        shp = self.shapes()
        n_rot, n_shp = len(rot), len(shp)
        return {
            "orientation": np.repeat(rot, n_shp, axis=0).astype(np.float32),
            "shape": np.tile(shp, (n_rot, 1)).astype(np.float32),
        }

    @property
    def size(self) -> int:
        """Number of hypotheses."""
        return len(self.axis_directions()) * len(self.rolls()) * len(self.shapes())


PRESETS = types.MappingProxyType(
    {
        "coarse": Grid(
            lengths=(0.3, 0.6, 1.0),
            ratios1=(1.0, 0.55, 0.3),
            ratios2=(1.0, 0.55),
            squareness1=(0.4, 1.0),
            squareness2=(0.4, 1.0),
            axis_step=45.0,
            roll_step=45.0,
            bends=(0.0,),
        ),
        "default": Grid(),
        "fine": Grid(
            lengths=(0.2, 0.35, 0.6, 1.0),
            ratios1=(1.0, 0.7, 0.45, 0.25),
            ratios2=(1.0, 0.6),
            squareness1=(0.25, 0.6, 1.0),
            squareness2=(0.25, 0.6, 1.0),
            axis_step=22.5,
            roll_step=22.5,
            bends=(-0.3, 0.0, 0.3),
        ),
    }
)
"""Named grids: ``coarse`` (~3 k hypotheses), ``default`` (~2^16, the paper's), ``fine``."""


def lookup_preset(value, kind: type, presets: Mapping, argument: str):
    """``value`` itself if it is a ``kind`` (a settings class), else the preset of that
    name in ``presets``; any other value is refused in the one message style."""
    if isinstance(value, kind):
        return value
    if not isinstance(value, str) or value not in presets:
        raise ValueError(f"{argument}: got {value!r:.60}, expected a {kind.__name__} or one of {sorted(presets)}")
    return presets[value]


def grid_preset(name_or_grid) -> Grid:
    """A :class:`Grid` from a preset name or a Grid (returned as is)."""
    return lookup_preset(name_or_grid, Grid, PRESETS, "grid")
