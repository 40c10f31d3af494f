"""The ``sqparts`` command line: render, mesh, show, recover, demo.

User errors (missing files, bad JSON, out-of-range parameters) print one line
``sqparts: error: ...`` and exit with status 2; outputs are written atomically, so a
failed command leaves no half-written file.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np


def _enable_compilation_cache() -> None:
    import jax

    cache = os.environ.get("SQPARTS_CACHE_DIR", str(Path.home() / ".cache" / "sqparts" / "jax"))
    try:
        Path(cache).mkdir(parents=True, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", cache)
        # Every program, however small: a later run then compiles nothing.
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        # And the big programs exported, so a later run does not trace them either.
        from ._compile import set_export_dir

        set_export_dir(Path(cache) / "exported")
    except OSError:
        pass


def _range_out(path: str) -> Path:
    p = Path(path)
    if p.suffix.lower() not in (".npy", ".png", ".tif", ".tiff"):
        raise ValueError(f"--out: expected a path ending in .npy, .png or .tif, got {path!r}")
    return p


def cmd_render(args) -> int:
    from ._io import load_camera, load_scene, write_range_image
    from ._render import render_range_image

    out = _range_out(args.out)
    parts = load_scene(args.scene)
    camera = load_camera(args.camera)
    depth = render_range_image(parts, camera)
    write_range_image(out, depth, depth_scale=args.depth_scale)
    _say(args, f"wrote {out} ({camera.width}x{camera.height}, {len(parts)} parts)")
    return 0


def cmd_mesh(args) -> int:
    from ._io import load_scene
    from ._mesh import save_mesh, scene_mesh

    parts = load_scene(args.scene)
    if args.resolution < 4:
        raise ValueError(f"--resolution: expected an integer >= 4, got {args.resolution}")
    mesh = scene_mesh(parts, resolution=args.resolution, union=args.union)
    save_mesh(args.out, mesh)
    _say(args, f"wrote {args.out} ({len(mesh.faces)} triangles, {len(parts)} parts)")
    return 0


def cmd_show(args) -> int:
    from ._io import read_range_image
    from ._plot import save_range_image_png

    if Path(args.out).suffix.lower() != ".png":
        raise ValueError(f"--out: expected a path ending in .png, got {args.out!r}")
    depth, _ = read_range_image(args.input, depth_scale=args.depth_scale)
    save_range_image_png(args.out, depth, title=Path(args.input).name)
    _say(args, f"wrote {args.out}")
    return 0


def _write_recovery(out: Path, recovery, *, title: str, names=None) -> None:
    import json

    from ._io import atomic_write
    from ._mesh import save_mesh, scene_mesh
    from ._plot import save_report

    out.mkdir(parents=True, exist_ok=True)
    text = json.dumps(recovery.scene_dict(names), indent=2)
    with atomic_write(out / "parts.json", "w") as f:
        f.write(text + "\n")
    save_mesh(out / "model.ply", scene_mesh(recovery.parts, resolution=24))
    save_report(out / "report.png", recovery, title=title)


def _recover_options(args) -> dict:
    opts = dict(grid=args.grid, max_size=args.max_size, selection=args.selection,
                refine_rounds=args.refine_rounds, resolution=args.resolution, clean=args.clean,
                figure_ground=args.figure_ground, planes=args.planes, tear=args.tear,
                min_figure_pixels=args.min_figure_pixels, max_figures=args.max_figures,
                max_border_fraction=args.max_border_fraction, prettify=args.prettify, max_angle=args.max_angle, max_bits=args.max_bits)
    for name in ("max_size", "sigma", "tear"):
        v = getattr(args, name)
        if v is not None and not v > 0:
            raise ValueError(f"--{name.replace('_', '-')}: expected a number > 0, got {v}")
    for name in ("refine_rounds", "resolution", "planes"):
        v = getattr(args, name)
        if v < 0:
            raise ValueError(f"--{name.replace('_', '-')}: expected an integer >= 0, got {v}")
    for name in ("min_figure_pixels", "max_figures"):
        v = getattr(args, name)
        if v is not None and v < 1:
            raise ValueError(f"--{name.replace('_', '-')}: expected an integer >= 1, got {v}")
    if not 0 <= args.max_border_fraction <= 1:
        raise ValueError(f"--max-border-fraction: expected a number in [0, 1], got {args.max_border_fraction}")
    if args.up is not None:
        try:
            up = [float(x) for x in args.up.split(",")]
        except ValueError:
            up = []
        if len(up) != 3 or not np.all(np.isfinite(up)) or not any(up):
            raise ValueError(f"--up: expected three numbers x,y,z (camera frame), got {args.up!r}")
        opts["up"] = up
    if args.depth_range is not None:
        try:
            near, far = (float(x) for x in args.depth_range.split(","))
        except ValueError:
            raise ValueError(f"--depth-range: expected NEAR,FAR, got {args.depth_range!r}") from None
        opts["depth_range"] = (near, far)
    return opts


def _inputs(paths) -> list[Path]:
    from ._io import RANGE_IMAGE_SUFFIXES

    out = []
    for p in map(Path, paths):
        if p.is_dir():
            found = sorted(q for q in p.iterdir() if q.suffix.lower() in RANGE_IMAGE_SUFFIXES)
            if not found:
                raise ValueError(f"input: folder {str(p)!r} holds no range images ({', '.join(RANGE_IMAGE_SUFFIXES)})")
            out.extend(found)
        elif not p.exists():
            raise FileNotFoundError(f"input: no such file {str(p)!r}")
        else:
            out.append(p)
    return out


def cmd_recover(args) -> int:
    from ._fit import encoding_for
    from ._io import load_camera, read_range_image
    from ._recover import recover_scene

    inputs = _inputs(args.input)
    camera_arg = load_camera(args.camera) if args.camera else None
    opts = _recover_options(args)
    # Read and check every input before any work, so a bad one fails fast.
    loaded = []
    for path in inputs:
        depth, camera = read_range_image(path, depth_scale=args.depth_scale)
        camera = camera_arg or camera
        if camera is None:
            raise ValueError(f"--camera: {path.name} carries no camera; give --camera CAM.json")
        if depth.shape != (camera.height, camera.width):
            raise ValueError(
                f"--camera: {path.name} is {depth.shape[1]}x{depth.shape[0]} but the camera is "
                f"{camera.width}x{camera.height}"
            )
        loaded.append((path, depth, camera))
    out = Path(args.out)
    progress = None
    if not args.quiet:
        from tqdm import tqdm

        progress = lambda it: tqdm(it, desc="regions", unit="region", leave=False)  # noqa: E731
    for path, depth, camera in loaded:
        enc = encoding_for(depth[np.isfinite(depth)], sigma=args.sigma) if args.sigma else None
        recovery = recover_scene(depth, camera, encoding=enc, progress=progress, **opts)
        target = out if len(loaded) == 1 else out / path.stem
        _write_recovery(target, recovery, title=path.name)
        _say(args, f"{path.name}: {recovery.summary()}\n  wrote {target}/parts.json, model.ply, report.png")
    return 0


def cmd_demo(args) -> int:
    from ._io import write_range_image
    from ._recover import recover
    from ._render import render_range_image
    from ._scenes import builtin_scene

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scene = builtin_scene("human", resolution=args.resolution)
    depth = render_range_image(scene.parts, scene.camera)
    write_range_image(out / "range.npy", depth)
    progress = None
    if not args.quiet:
        from tqdm import tqdm

        progress = lambda it: tqdm(it, desc="regions", unit="region", leave=False)  # noqa: E731
    recovery = recover(np.asarray(depth), scene.camera, progress=progress)
    _write_recovery(out, recovery, title=f"demo: {scene.description}")
    _say(args, f"demo: {scene.description}\n  true parts: {len(scene.parts)}; recovered: "
               f"{recovery.summary()}\n  wall time {time.perf_counter() - t0:.1f} s including compilation\n"
               f"  wrote {out}/range.npy, parts.json, model.ply, report.png")
    return 0


def _say(args, msg: str) -> None:
    if not getattr(args, "quiet", False):
        print(msg)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sqparts",
        description="Recover part structure (deformed superquadrics) from range images.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("render", help="render a scene JSON into a range image")
    p.add_argument("scene", help="scene JSON ({\"parts\": [...]})")
    p.add_argument("--camera", required=True, help="camera JSON (Open3D pinhole or orthographic)")
    p.add_argument("--out", required=True, help="output range image (.npy, .png 16-bit, .tif)")
    p.add_argument("--depth-scale", type=float, default=0.001, help="PNG units per value (m)")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("mesh", help="export a scene JSON as a mesh")
    p.add_argument("scene")
    p.add_argument("--out", required=True, help="mesh file (.ply, .obj, .stl, .glb, .off)")
    p.add_argument("--resolution", type=int, default=32, help="samples per quarter turn")
    p.add_argument("--union", action="store_true", help="Boolean union into one body")
    p.set_defaults(func=cmd_mesh)

    p = sub.add_parser("show", help="save a range image as a PNG picture")
    p.add_argument("input", help="range image (.npy, .png, .tif, .pcd)")
    p.add_argument("--out", required=True, help="output picture (.png)")
    p.add_argument("--depth-scale", type=float, default=0.001)
    p.set_defaults(func=cmd_show)

    p = sub.add_parser("recover", help="recover parts from range images")
    p.add_argument("input", nargs="+", help="range images (.npy .png .tif .pcd) or folders of them")
    p.add_argument("--camera", help="camera JSON (a .pcd carries its own)")
    p.add_argument("--out", required=True, help="output directory (one sub-folder per input if several)")
    p.add_argument("--grid", default="coarse", choices=["coarse", "default", "fine"], help="hypothesis grid")
    p.add_argument("--max-size", type=float, default=None, help="largest semi-axis searched (scene units)")
    p.add_argument("--sigma", type=float, default=None, help="match tolerance σ (scene units)")
    p.add_argument("--selection", default="auto", choices=["auto", "exact", "best-first"])
    p.add_argument("--refine-rounds", type=int, default=2)
    p.add_argument("--depth-scale", type=float, default=0.001, help="PNG units per value (m)")
    g = p.add_argument_group("real data (clean-up, figure/ground, prettifying)")
    g.add_argument("--resolution", type=int, default=160,
                   help="bin the image so its longest side is about this many pixels (0 = full resolution)")
    g.add_argument("--no-clean", dest="clean", action="store_false",
                   help="keep flying pixels and isolated outliers")
    g.add_argument("--no-figure-ground", dest="figure_ground", action="store_false",
                   help="no plane removal or splitting: the whole image is one figure")
    g.add_argument("--planes", type=int, default=3, help="background planes (table or floor and the walls of a corner) to remove")
    g.add_argument("--tear", type=float, default=None,
                   help="depth jump, in pixel footprints, that separates figures (default 8)")
    g.add_argument("--min-figure-pixels", type=int, default=None, help="smallest figure kept")
    g.add_argument("--max-figures", type=int, default=None, help="recover at most this many figures")
    g.add_argument("--max-border-fraction", type=float, default=0.15,
                   help="a piece with more of its pixels on the edge of the measured area is background (1 = keep)")
    g.add_argument("--depth-range", default=None, help="NEAR,FAR: drop returns outside (scene units)")
    g.add_argument("--prettify", action="store_true",
                   help="snap nearly vertical/horizontal parts to gravity (section 4.3)")
    g.add_argument("--up", default=None, help="x,y,z gravity up in the camera frame (default: ground normal)")
    g.add_argument("--max-angle", type=float, default=15.0, help="prettify parts within this many degrees")
    g.add_argument("--max-bits", type=float, default=56.0, help="prettify only if E rises at most this (and every part still pays)")
    p.set_defaults(func=cmd_recover)

    p = sub.add_parser("demo", help="recover the built-in articulated human (Figure 7)")
    p.add_argument("--out", default="sqparts-demo", help="output directory (default sqparts-demo)")
    p.add_argument("--resolution", type=int, default=128)
    p.set_defaults(func=cmd_demo)

    for p in sub.choices.values():
        p.add_argument("--quiet", action="store_true", help="print nothing on success")
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _enable_compilation_cache()
    try:
        return args.func(args)
    except (ValueError, TypeError, OSError) as e:
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        print(f"sqparts: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sqparts: interrupted", file=sys.stderr)
        return 130
