"""The ``sqparts`` command line: render, mesh, show, demo.

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


def _enable_compilation_cache() -> None:
    import jax

    cache = os.environ.get("SQPARTS_CACHE_DIR", str(Path.home() / ".cache" / "sqparts" / "jax"))
    try:
        Path(cache).mkdir(parents=True, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
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


def cmd_demo(args) -> int:
    from ._io import save_scene, write_range_image
    from ._plot import save_range_image_png
    from ._render import render_range_image
    from ._scenes import builtin_scene

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scene = builtin_scene("human", resolution=args.resolution)
    depth = render_range_image(scene.parts, scene.camera)
    write_range_image(out / "range.npy", depth)
    save_scene(out / "scene.json", scene.parts, [{"name": n} for n in scene.part_names])
    save_range_image_png(out / "range.png", depth, title=scene.description)
    _say(args, f"demo: rendered {scene.name} ({len(scene.parts)} parts) in "
               f"{time.perf_counter() - t0:.1f} s; wrote {out}/range.npy, range.png, scene.json")
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

    p = sub.add_parser("demo", help="run the pipeline on the built-in articulated human")
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
