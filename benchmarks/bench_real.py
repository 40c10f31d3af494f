"""Real range data end to end: clean-up, figure/ground, recovery, prettifying, residual model.

Data from ``../shared/data`` (see its README) and scikit-image:

* ``grabber_frame0.pcd``: Kinect, a laptop and a box on a table, wall behind;
* ``table_scene_mug_stereo_textured.pcd``: stereo, a mug on a table;
* ``teapot.obj``: the Utah teapot rendered from three views by trimesh ray casting;
* ``skimage.data.stereo_motorcycle()``: Middlebury 2014 disparity -> depth.

Writes ``docs/real_<name>.png`` (report), ``docs/real_<name>_residual.png`` and
``benchmarks/results/real_<input>.json`` (the three teapot views in one). Each input
is recovered with the default (~2^16) grid at about 160 pixels across.

    python benchmarks/bench_real.py [--grid default] [--only NAME] [--join never|always|auto]

With ``--seeds K`` it measures instead how far each result moves under imperceptible
noise: every input recovered as it is and with K - 1 draws of Gaussian depth noise of
``--noise`` (default 1e-5) times each pixel's depth (0.01 mm at 1 m, far below any
sensor's); per input E, parts and explained for every draw, and their spread, in
``benchmarks/results/real_perturbed.json``. ``--name teapot-above`` picks one input.

    python benchmarks/bench_real.py --seeds 6 [--name teapot-above] [--noise 1e-5]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import machine, save

import sqparts
from sqparts._plot import save_report, save_residual_report
from sqparts.cli import JOIN_MODES

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
DOCS = ROOT / "docs"


def teapot_views():
    """The teapot from the side, from 35° above, and three-quarter, 14 units away."""
    from scipy.spatial.transform import Rotation

    mesh = sqparts.load_mesh(DATA / "teapot.obj")
    cam = sqparts.PinholeCamera(160, 120, 190.0, 190.0, 79.5, 59.5)
    views = {}
    for name, (elev, azim) in {"side": (10, 0), "above": (35, 20), "three-quarter": (20, 50)}.items():
        # world y up -> camera -y; look along world -z; then tilt down by elev, turn by azim.
        r = Rotation.from_euler("x", 180 + elev, degrees=True) * Rotation.from_euler("y", azim, degrees=True)
        m = mesh.copy()
        m.apply_translation(-m.bounds.mean(axis=0))
        t = np.eye(4)
        t[:3, :3] = r.as_matrix()
        t[:3, 3] = [0, 0, 14.0]
        m.apply_transform(t)
        up = r.as_matrix() @ np.array([0.0, 1.0, 0.0])  # the teapot's up in the camera frame
        views[name] = (np.asarray(sqparts.render_mesh(m, cam), np.float32), cam, up)
    return views


def motorcycle():
    import skimage.data

    _, _, disp = skimage.data.stereo_motorcycle()
    with np.errstate(invalid="ignore", divide="ignore"):
        depth = 994.978 * 193.001 / (disp + 31.086) / 1000.0  # metres
    depth = np.where(np.isfinite(disp), depth, np.nan).astype(np.float32)
    # Middlebury 2014 Motorcycle calibration, at scikit-image's quarter resolution.
    return depth, sqparts.PinholeCamera(741, 500, 994.978, 994.978, 311.193, 254.877)


def inputs(only=None):
    if only in (None, "kinect"):
        yield "kinect", "laptop and box on a table (Kinect)", *sqparts.read_range_image(DATA / "grabber_frame0.pcd"), {}
    if only in (None, "mug"):
        yield (
            "mug",
            "mug on a table (stereo)",
            *sqparts.read_range_image(DATA / "table_scene_mug_stereo_textured.pcd"),
            {},
        )
    if only in (None, "teapot"):
        for view, (d, cam, up) in teapot_views().items():
            yield f"teapot-{view}", f"Utah teapot, {view} view (mesh render)", d, cam, {"up": up}
    if only in (None, "motorcycle"):
        d, cam = motorcycle()
        yield "motorcycle", "motorcycle (Middlebury stereo)", d, cam, {"max_figures": 3}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--grid", default="default")
    ap.add_argument("--only", default=None, choices=["kinect", "mug", "teapot", "motorcycle"])
    ap.add_argument("--seeds", type=int, default=0, help="perturbation ensemble of this many draws (0: off)")
    ap.add_argument("--noise", type=float, default=1e-5, help="noise, relative to each pixel's depth")
    ap.add_argument("--name", default=None, help="one input by name (teapot-above, ...)")
    ap.add_argument("--join", default="auto", choices=tuple(JOIN_MODES), help="SceneSettings.join")
    args = ap.parse_args()
    args.join = JOIN_MODES[args.join]
    if args.seeds:
        return perturbed(args)
    DOCS.mkdir(exist_ok=True)
    rows = []
    for name, what, depth, cam, extra in inputs(args.only):
        t0 = time.perf_counter()
        rec = sqparts.recover_scene(
            depth,
            cam,
            scene=sqparts.SceneSettings(prettify=True, join=args.join, **extra),
            search=sqparts.SearchSettings(grid=args.grid),
        )
        wall = time.perf_counter() - t0
        resid = sqparts.residual_model(rec)
        save_report(DOCS / f"real_{name}.png", rec, title=f"{what}: {name}")
        save_residual_report(DOCS / f"real_{name}_residual.png", rec, resid, title=f"{what}: residual surface model")
        fg = rec.figure_ground
        row = {
            "name": name,
            "what": what,
            "input_shape": list(np.shape(depth)),
            "search_shape": [rec.camera.height, rec.camera.width],
            "planes_removed": len(fg.planes) if fg else 0,
            "ground_normal": None if not fg or fg.ground is None else fg.ground.normal.tolist(),
            "figures": len(rec.figures),
            "parts_per_figure": [len(r.parts) for r in rec.figures],
            "pixels_per_figure": [int(r.figure.sum()) for r in rec.figures],
            "explained_per_figure": [r.fraction_explained for r in rec.figures],
            "parts": len(rec.parts),
            "fraction_explained": rec.fraction_explained,
            "commission": rec.commission_fraction,
            "description_length_bits": rec.cost.total,
            "prettified": sum(e["kept"] for rep in rec.prettify for e in rep),
            "fractal_dimension": resid.fractal.fractal_dimension,
            "residual_rms": float(np.sqrt(np.nanmean(resid.residual**2))),
            "clean_up": None if rec.cleaned is None else rec.cleaned.summary(),
            "wall_s": wall,
            "timings_s": dict(rec.timings),
        }
        rows.append(row)
        print(f"{name}: {rec.summary()}; {resid.summary()}; wall {wall:.1f} s", flush=True)
    for family in dict.fromkeys(r["name"].split("-")[0] for r in rows):  # teapot-side -> teapot
        family_rows = [r for r in rows if r["name"].split("-")[0] == family]
        save(f"real_{family}", {"machine": machine(), "grid": args.grid, "join": args.join, "rows": family_rows})


def perturbed(args):
    """The ``--seeds`` ensemble (module docstring)."""
    rows = []
    for name, _, depth, cam, extra in inputs(args.only):
        if args.name not in (None, name):
            continue
        draws = []
        for seed in range(args.seeds):
            d = depth
            if seed:  # draw 0: the input as it is
                noise = np.random.default_rng(seed).normal(0.0, args.noise, depth.shape)
                d = (depth * (1.0 + noise)).astype(np.float32)
            t0 = time.perf_counter()
            rec = sqparts.recover_scene(
                d,
                cam,
                scene=sqparts.SceneSettings(prettify=True, join=args.join, **extra),
                search=sqparts.SearchSettings(grid=args.grid),
            )
            draws.append(
                {
                    "seed": seed,
                    "E": rec.cost.total,
                    "parts": len(rec.parts),
                    "fraction_explained": rec.fraction_explained,
                    "wall_s": time.perf_counter() - t0,
                }
            )
            print(f"{name} draw {seed}: E {rec.cost.total:.0f} bits, {len(rec.parts)} parts", flush=True)
        e = np.array([r["E"] for r in draws])
        rows.append(
            {
                "name": name,
                "draws": draws,
                "E_median": float(np.median(e)),
                "E_min": float(e.min()),
                "E_max": float(e.max()),
                "E_spread_percent": float(100 * (e.max() - e.min()) / np.median(e)),
            }
        )
        print(f"{name}: E median {np.median(e):.0f}, {e.min():.0f}..{e.max():.0f} bits over {len(e)} draws", flush=True)
    save("real_perturbed", {"grid": args.grid, "seeds": args.seeds, "noise": args.noise, "rows": rows})


if __name__ == "__main__":
    main()
