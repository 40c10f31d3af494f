"""The ``sqparts`` command line: render, mesh, show, recover, demo, view.

What it promises (README, "Errors and guarantees"):

* A user error (missing file, bad JSON, an out-of-range or non-finite number, an
  option argparse rejects) prints one line ``sqparts: error: ARGUMENT: got X, expected
  Y`` and exits with status 2; no traceback.
* Outputs appear together or not at all: a recovery's files are written into a
  temporary folder beside the output and renamed into place in one step; a single
  file is written to a temporary name and renamed. An existing output is never
  replaced unless ``--overwrite`` is given.
* SIGINT and SIGTERM stop the run at any moment with status 130 or 143, leaving no
  partial output (outputs already complete stay).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

# --- arguments ------------------------------------------------------------------------


JOIN_MODES = {"never": False, "always": True, "auto": "auto"}
"""``--join``'s words as :class:`~sqparts.SceneSettings`' ``join``."""


class UsageError(ValueError):
    """A command line argparse rejected, in the one message style."""


def _number(want: str, *, low=None, high=None, integer: bool = False, open_low: bool = False):
    """An argparse ``type`` accepting a finite number (or integer) in [low, high]; a
    number also fits float32, as the package computes in it (1e308 would become inf, and
    a positive 1e-300 zero)."""

    def parse(text: str):
        try:
            value = int(text) if integer else float(text)
            ok = math.isfinite(value)  # an integer beyond float64 raises OverflowError
        except (ValueError, OverflowError):
            value, ok = None, False
        ok = ok and (low is None or (value > low if open_low else value >= low))
        ok = ok and (high is None or value <= high)
        if not ok:
            raise argparse.ArgumentTypeError(f"got {text!r}, expected {want}")
        from ._camera import fits_float32

        if not integer and not fits_float32(value):
            raise argparse.ArgumentTypeError(f"got {text!r}, expected {want} that float32 holds")
        return value

    return parse


_POSITIVE = _number("a finite number > 0", low=0, open_low=True)
_POSITIVE_INT = _number("an integer >= 1", low=1, integer=True)


def _argparse_message(message: str) -> str:
    """argparse's messages in the one style ``ARGUMENT: got X, expected Y``."""
    import re

    if m := re.match(r"the following arguments are required: (.*)", message):
        return f"{m[1]}: got nothing, expected a value (required)"
    if m := re.match(r"unrecognized arguments: (.*)", message):
        return f"arguments: got {m[1]!r}, expected only the options that --help lists"
    if m := re.match(r"argument (\S+?)(?:/\S+)?: invalid choice: (\S+) \(choose from (.*)\)", message):
        return f"{m[1]}: got {m[2]}, expected one of {m[3]}"
    if m := re.match(r"argument (\S+?)(?:/\S+)?: invalid \S+ value: (.*)", message):
        return f"{m[1]}: got {m[2]}, expected a number"
    if m := re.match(r"argument (\S+?)(?:/\S+)?: expected (.*)", message):
        return f"{m[1]}: got nothing, expected {m[2]} (a value starting with '-' goes as {m[1]}=VALUE)"
    if m := re.match(r"argument (\S+?)(?:/\S+)?: ignored explicit argument (.*)", message):
        return f"{m[1]}: got {m[2]}, expected no value"
    if m := re.match(r"ambiguous option: (\S+) could match (.*)", message):
        return f"{m[1]}: got an abbreviation of several options, expected one of {m[2]}"
    if m := re.match(r"argument (\S+?)(?:/\S+)?: (.*)", message):
        return f"{m[1]}: {m[2]}"
    return f"arguments: {message}"


class _Parser(argparse.ArgumentParser):
    def parse_known_args(self, args=None, namespace=None):
        self._argv = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    def error(self, message):
        argv = getattr(self, "_argv", [])
        if message.endswith("required: COMMAND") and argv and argv[0].startswith("-"):
            raise UsageError(f"arguments: got {argv[0]!r}, expected a COMMAND first (sqparts --help lists them)")
        raise UsageError(_argparse_message(message))


# --- outputs ----------------------------------------------------------------------------


def _range_out(path: str) -> Path:
    p = Path(path)
    if p.suffix.lower() not in (".npy", ".png", ".tif", ".tiff"):
        raise ValueError(f"--out: got {path!r}, expected a path ending in .npy, .png or .tif")
    return p


def _new_file(args, path, inputs) -> Path:
    from ._io import check_new_output

    path = check_new_output(path, overwrite=args.overwrite, inputs=inputs)
    if path.is_dir():
        raise IsADirectoryError(f"--out: got {str(path)!r}, which is a folder, expected a file path")
    return path


def cmd_render(args) -> int:
    from ._io import load_camera, load_scene, write_range_image
    from ._render import render_range_image

    out = _new_file(args, _range_out(args.out), (args.scene, args.camera))
    parts = load_scene(args.scene)
    camera = load_camera(args.camera)
    scale = _depth_scale(args)  # checked before any work
    depth = render_range_image(parts, camera)
    if not np.isfinite(np.asarray(depth)).any():  # an image of NaN alone: nothing to write
        raise ValueError(
            f"scene: got {len(parts)} part(s) that no pixel of the camera sees, "
            "expected at least one in view (in front of the camera, not around it)"
        )
    write_range_image(out, depth, depth_scale=scale)
    _say(args, f"wrote {out} ({camera.width}x{camera.height}, {len(parts)} parts)")
    return 0


def cmd_mesh(args) -> int:
    from ._io import load_scene
    from ._mesh import MESH_SUFFIXES, save_mesh, scene_mesh

    if Path(args.out).suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"--out: got {args.out!r}, expected a mesh path ending in {', '.join(MESH_SUFFIXES)}")
    out = _new_file(args, args.out, (args.scene,))
    parts = load_scene(args.scene)
    mesh = scene_mesh(parts, resolution=args.resolution, union=args.union)
    save_mesh(out, mesh)
    _say(args, f"wrote {out} ({len(mesh.faces)} triangles, {len(parts)} parts)")
    return 0


def cmd_show(args) -> int:
    from ._io import read_range_image
    from ._plot import save_range_image_png

    if Path(args.out).suffix.lower() != ".png":
        raise ValueError(f"--out: got {args.out!r}, expected a path ending in .png")
    out = _new_file(args, args.out, (args.input,))
    depth, _ = read_range_image(args.input, depth_scale=_depth_scale(args))
    save_range_image_png(out, depth, title=Path(args.input).name)
    _say(args, f"wrote {out}")
    return 0


def _recover_options(args) -> dict:
    """The settings objects of ``recover`` (:func:`~sqparts.recover_scene`'s keywords)."""
    from ._recover import SceneSettings
    from ._refine import RefineSettings
    from ._search import SearchSettings
    from ._select import SelectSettings

    try:
        scene = SceneSettings(
            resolution=args.resolution,
            depth_range=None if args.depth_range is None else args.depth_range.split(","),
            clean=args.clean,
            tear=args.tear,
            figure_ground=args.figure_ground,
            planes=args.planes,
            min_figure_pixels=args.min_figure_pixels,
            max_figures=args.max_figures,
            max_border_fraction=args.max_border_fraction,
            join=JOIN_MODES[args.join],
            holes=args.holes,
            prettify=args.prettify,
            up=None if args.up is None else args.up.split(","),
            max_angle=args.max_angle,
            max_bits=args.max_bits,
        )
    except ValueError as e:  # a value the settings refused: name the flag and the text given
        field, _, rest = str(e).partition(": got ")
        if not hasattr(args, field):
            raise
        flag = "--" + field.replace("_", "-")
        raise ValueError(f"{flag}: got {getattr(args, field)!r}, expected {rest.partition(', expected ')[2]}") from None
    return dict(
        scene=scene,
        search=SearchSettings(grid=args.grid, max_size=args.max_size),
        select=SelectSettings(method=args.selection),
        refine=RefineSettings(rounds=args.refine_rounds),
    )


def _inputs(paths, *, recursive: bool = False) -> list[Path]:
    from ._batch import expand_inputs

    return expand_inputs(paths, recursive=recursive)


def output_names(paths) -> list[str]:
    """One sub-folder name per input (see :func:`sqparts._batch.output_names`)."""
    from ._batch import output_names

    return output_names(paths)


def _progress(args, desc: str, unit: str):
    if args.quiet:
        return None
    from tqdm import tqdm

    # On a terminal only (disable=None): a log file gets no carriage-return frames.
    return lambda it: tqdm(it, desc=desc, unit=unit, leave=False, disable=None)


def _is_batch(args) -> bool:
    """Several inputs, a folder or a pattern, or a batch option: one sub-folder per input
    and ``results.jsonl``; else one input, whose outputs go into ``--out`` itself."""
    one = len(args.input) == 1 and Path(args.input[0]).is_file()
    return not one or args.resume or args.jobs is not None or args.scheduler is not None


def _cluster(args):
    """The Dask client for ``--jobs``/``--scheduler`` (a context manager), or no client."""
    if args.jobs is not None and args.scheduler is not None:
        raise ValueError(f"--jobs: got {args.jobs} with --scheduler, expected one of them")
    if args.jobs is None and args.scheduler is None:
        return contextlib.nullcontext(None)
    cores = os.cpu_count() or 1
    if args.jobs is not None and args.jobs > cores:  # each worker is a process importing JAX
        raise ValueError(f"--jobs: got {args.jobs}, expected at most {cores} (this machine's cores)")
    try:
        from . import _dask
    except ImportError as e:
        flag = "--jobs" if args.jobs is not None else "--scheduler"
        raise ValueError(
            f"{flag}: got it without Dask ({e}), expected dask.distributed installed "
            "(pip install 'sqparts[distributed]')"
        ) from None
    return _dask.local_cluster(args.jobs) if args.jobs is not None else _dask.connect(str(args.scheduler))


def cmd_recover(args) -> int:
    from ._batch import plan_batch, recover_file, remove_staging, run_batch
    from ._io import check_new_output, load_camera

    if not _is_batch(args):
        path = _inputs(args.input)[0]
        out = check_new_output(args.out, overwrite=args.overwrite, inputs=(path, args.camera))  # before any work
        camera = load_camera(args.camera) if args.camera else None
        opts = _recover_options(args)
        recovery = recover_file(
            path,
            out,
            camera=camera,
            depth_scale=_depth_scale(args),
            sigma=args.sigma,
            overwrite=args.overwrite,
            progress=_progress(args, "regions", "region"),
            **opts,
        )
        _after_recovery(args, out)
        _say(args, f"{path.name}: {recovery.summary()}\n  wrote {out}/parts.json, model.ply, report.png")
        return 0
    # Everything cheap is checked before any work; each input is read when it is recovered.
    opts = _recover_options(args)
    plan = plan_batch(
        args.input,
        out=args.out,
        camera=args.camera,  # read there, and never inside an output folder it replaces
        recursive=args.recursive,
        overwrite=args.overwrite,
        resume=args.resume,
        depth_scale=_depth_scale(args),
        sigma=args.sigma,
        **opts,
    )
    cluster = _cluster(args)
    since, failed, done = time.time(), [], 0
    try:
        with cluster as client:
            for record in run_batch(plan, client=client, progress=not args.quiet):
                done += 1
                if record["status"] == "ok":
                    _after_recovery(args, plan.out / record["output"])
                if record["status"] != "ok":
                    failed.append(record)
                    if not args.quiet:
                        from tqdm import tqdm

                        tqdm.write(f"{_shown(record['input'])}: {record['error']}", file=sys.stderr)
    finally:
        if args.jobs is not None:  # workers stopped mid-write leave their staging folders
            remove_staging(plan, since=since)
    _say(
        args,
        f"{done - len(failed)} of {done} inputs recovered, {len(failed)} failed, {len(plan.skipped)} "
        f"already complete (skipped); records in {plan.results}",
    )
    if failed:
        first = failed[0]
        print(
            f"sqparts: error: input: got {len(failed)} of {done} inputs failing (first {first['input']!r}: "
            f"{first['error']}), expected each to recover; see {plan.results}",
            file=sys.stderr,
        )
        return 1
    return 0


def _recover_command(args) -> int:
    """``recover``: ``--rerun`` checked before any work, then :func:`cmd_recover`."""
    from ._io import check_new_output

    if args.rerun is not None:
        if Path(args.rerun).suffix.lower() != ".rrd":
            raise ValueError(f"--rerun: got {args.rerun!r}, expected a path ending in .rrd")
        rrd = Path(args.rerun)
        if rrd.is_dir():
            raise IsADirectoryError(f"--rerun: got {args.rerun!r}, which is a folder, expected a file path")
        if not rrd.parent.is_dir():
            raise FileNotFoundError(f"--rerun: got {args.rerun!r}, expected a path in an existing directory")
        # Exists only with --overwrite, is none of the inputs, and can be written: before any work.
        check_new_output(rrd, overwrite=args.overwrite, inputs=(*args.input, args.camera), argument="--rerun")
        try:
            import rerun  # noqa: F401
        except ImportError:
            raise ValueError("--rerun: got no rerun-sdk installed, expected pip install 'sqparts[view]'") from None
        args.rerun_entries = []
    return cmd_recover(args)


def _after_recovery(args, folder: Path) -> None:
    """The ``--rerun`` recording, rewritten (atomically) with every input finished so
    far, each under its own entity path, from the view files in its output folder."""
    if getattr(args, "rerun", None) is None:
        return
    from ._io import atomic_write, load_view_data
    from ._view import entity_name, rerun_bytes, rerun_entries

    name = Path(folder).resolve().relative_to(Path(args.out).resolve()).as_posix()
    prefix = "/".join(entity_name(x) for x in (Path(args.out).name if name == "." else name).split("/"))
    args.rerun_entries.extend(rerun_entries(load_view_data(folder), prefix))
    data = rerun_bytes(args.rerun_entries)
    with atomic_write(args.rerun) as f:
        f.write(data)


def cmd_view(args) -> int:
    from ._view import serve

    serve(args.folder, port=args.port, announce=lambda message: print(message, flush=True))
    return 0


def cmd_demo(args) -> int:
    from ._batch import write_recovery
    from ._io import check_new_output, staged_folder, write_range_image
    from ._recover import recover
    from ._render import render_range_image
    from ._scenes import builtin_scene

    out = check_new_output(args.out, overwrite=args.overwrite)
    t0 = time.perf_counter()
    scene = builtin_scene("human", resolution=args.resolution)
    depth = render_range_image(scene.parts, scene.camera)
    recovery = recover(np.asarray(depth), scene.camera, progress=_progress(args, "regions", "region"))
    with staged_folder(out, overwrite=args.overwrite) as folder:
        write_range_image(folder / "range.npy", depth)
        write_recovery(folder, recovery, title=f"demo: {scene.description}")
    _say(
        args,
        f"demo: {scene.description}\n  true parts: {len(scene.parts)}; recovered: "
        f"{recovery.summary()}\n  wall time {time.perf_counter() - t0:.1f} s including compilation\n"
        f"  wrote {out}/range.npy, parts.json, model.ply, report.png",
    )
    return 0


def _read_inputs(args, inputs) -> list:
    """(path, depth, camera) per input, every one read and checked before any work."""
    from ._batch import read_input
    from ._io import load_camera

    camera = load_camera(args.camera) if args.camera else None
    scale = _depth_scale(args)
    return [(path, *read_input(path, camera=camera, depth_scale=scale)) for path in inputs]


def _depth_scale(args) -> float:
    """Metres per unit of integer depth (a PNG's): ``--depth-scale`` as given, else the
    camera file's own ``depth_scale`` (a RealSense dump's), else 0.001 (millimetres).
    A flag that contradicts the camera file is an error."""
    from ._io import DEPTH_SCALE, camera_depth_scale

    own = camera_depth_scale(args.camera) if getattr(args, "camera", None) else None
    if args.depth_scale is None:
        return DEPTH_SCALE if own is None else own
    if own is not None and own != args.depth_scale:
        raise ValueError(
            f"--depth-scale: got {args.depth_scale:g}, expected the camera file's depth_scale {own:g} (or no --depth-scale)"
        )
    return args.depth_scale


def _recognition_options(args) -> dict:
    """The settings objects of ``learn`` and ``recognize`` (:func:`~sqparts.recover_scene`'s keywords)."""
    from ._recover import SceneSettings
    from ._refine import RefineSettings
    from ._search import SearchSettings

    return dict(
        scene=SceneSettings(resolution=args.resolution),
        search=SearchSettings(grid=args.grid),
        refine=RefineSettings(rounds=args.refine_rounds),
    )


def cmd_learn(args) -> int:
    from ._batch import naming_input
    from ._database import ModelDatabase, check_name, view_from_recovery
    from ._io import check_new_output
    from ._recover import recover_scene

    check_name(args.name)
    db = ModelDatabase(args.db)  # read and checked before any work
    if not db.path.exists():
        check_new_output(db.path, argument="--db")  # a folder that can be made
    inputs = _inputs(args.input)
    loaded = _read_inputs(args, inputs)
    progress = _progress(args, "regions", "region")
    views = []
    for path, depth, camera in loaded:
        with naming_input(path):
            rec = recover_scene(depth, camera, progress=progress, **_recognition_options(args))
        if not rec.figures:
            raise ValueError(f"input: got {str(path)!r}, in which nothing was recovered, expected a view of the object")
        views.append(view_from_recovery(rec, source=str(path), levels=args.levels))
        _say(args, f"{path.name}: {rec.summary()}")
    db.add_views(args.name, views, replace=args.overwrite)
    _say(
        args,
        f"learnt {args.name!r}: {len(db.objects[args.name])} view(s); {len(db.objects)} object(s) in "
        f"{db.path}, threshold {db.threshold:.3f} on the {db.statistic}",
    )
    return 0


def cmd_recognize(args) -> int:
    import json

    from ._batch import RESULTS_NAME, _ResultsLog, error_message, naming_input
    from ._database import ModelDatabase, recognize
    from ._io import atomic_write, check_new_output, staged_folder
    from ._plot import save_recognition_report

    if not Path(args.db).is_dir():
        raise FileNotFoundError(
            f"--db: got {args.db!r}, which is not a folder, expected a database made by sqparts learn"
        )
    db = ModelDatabase(args.db)
    if not db.objects:
        raise ValueError(f"--db: got {args.db!r} with no objects, expected a database made by sqparts learn")
    inputs = _inputs(args.input)
    out = Path(args.out)
    if db.path.resolve() in (out.resolve(), *out.resolve().parents):
        raise ValueError(
            f"--out: got {args.out!r}, which is in --db {args.db!r}, expected a folder apart from the database"
        )
    targets = [out / name for name in output_names(inputs)]
    # Several inputs are a batch, as for recover: one line each in results.jsonl, a
    # failing input recorded and the rest recognised, exit status 1 if any failed.
    results = out / RESULTS_NAME if len(inputs) > 1 else None
    if results is not None and results.exists() and not args.overwrite:
        raise FileExistsError(
            f"--out: got {str(out)!r}, which holds the {RESULTS_NAME} of an earlier run, "
            "expected a new folder (or --overwrite)"
        )
    kept = (*inputs, args.camera, args.db)  # never inside a folder replaced
    for target in targets:  # before any work: never overwrite silently
        check_new_output(target, overwrite=args.overwrite, inputs=kept)
    loaded = _read_inputs(args, inputs)
    if not db.calibrated_for():  # as recognize() would, once, before the inputs
        if not args.quiet:
            print(
                f"--db {args.db}: calibrated with other match settings or model files; calibrating it again",
                file=sys.stderr,
            )
        db.calibrate()
    progress = _progress(args, "regions", "region")
    log = _ResultsLog(results, keep=()) if results is not None else None
    failed = []
    try:
        for (path, depth, camera), target in zip(loaded, targets):
            t0 = time.perf_counter()
            try:
                with naming_input(path):
                    result = recognize(depth, camera, database=db, progress=progress, **_recognition_options(args))
                with staged_folder(target, overwrite=args.overwrite, inputs=kept) as folder:
                    with atomic_write(folder / "recognition.json", "w") as f:
                        f.write(json.dumps(dict(result.to_json(), input=str(path)), indent=1) + "\n")
                    with atomic_write(folder / "parts.json", "w") as f:
                        f.write(json.dumps(result.recovery.scene_dict(), indent=2) + "\n")
                    save_recognition_report(folder / "report.png", result, title=path.name)
            except Exception as e:
                if log is None:
                    raise
                error = error_message(e)
                failed.append((path, error))
                record = {"status": "error", "best": None, "evidence": None, "error": error}
                if not args.quiet:
                    print(f"{_shown(path)}: {error}", file=sys.stderr)  # as recover's batch reports a failure
            else:
                record = {"status": "ok", "best": result.best, "evidence": float(result.evidence), "error": None}
                _say(
                    args, f"{path.name}: {result.summary()}\n  wrote {target}/recognition.json, parts.json, report.png"
                )
            if log is not None:
                seconds = round(time.perf_counter() - t0, 3)
                log.append({"input": str(path), "output": str(target.relative_to(out)), **record, "seconds": seconds})
    finally:
        if log is not None:
            log.close()
    if failed:
        print(
            f"sqparts: error: input: got {len(failed)} of {len(inputs)} inputs failing (first {str(failed[0][0])!r}: "
            f"{failed[0][1]}), expected each to be recognised; see {results}",
            file=sys.stderr,
        )
        return 1
    return 0


def _shown(path) -> str:
    """A file name as one line of a message: as it is, or quoted with its escapes when it
    holds a newline or another character a terminal does not print."""
    text = str(path)
    return text if text.isprintable() else repr(text)


def _say(args, msg: str) -> None:
    if not getattr(args, "quiet", False):
        print(msg)


DEPTH_SCALE_HELP = (
    "metres per unit of integer depth, e.g. a 16-bit PNG's (default: the camera file's depth_scale, else 0.001)"
)


def build_parser() -> argparse.ArgumentParser:
    from ._refine import MAX_REFINE_ROUNDS

    depth_scale = _number(
        "a number in (0, 1]: metres per unit (Open3D's and TUM's 1000 or 5000 units per metre are 0.001 or 0.0002)",
        low=0,
        open_low=True,
        high=1,
    )
    parser = _Parser(
        prog="sqparts",
        description="Recover part structure (deformed superquadrics) from range images.",
    )
    from . import __version__

    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)

    p = sub.add_parser("render", help="render a scene JSON into a range image")
    p.add_argument("scene", help='scene JSON ({"parts": [...]})')
    p.add_argument("--camera", required=True, help="camera JSON (Open3D pinhole or orthographic)")
    p.add_argument("--out", required=True, help="output range image (.npy, .png 16-bit, .tif)")
    p.add_argument("--depth-scale", type=depth_scale, default=None, help=DEPTH_SCALE_HELP)
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("mesh", help="export a scene JSON as a mesh")
    p.add_argument("scene")
    p.add_argument("--out", required=True, help="mesh file (.ply, .obj, .stl, .glb, .off)")
    p.add_argument(
        "--resolution",
        type=_number("an integer in [4, 512]", low=4, high=512, integer=True),
        default=32,
        help="samples per quarter turn",
    )
    p.add_argument("--union", action="store_true", help="Boolean union into one body")
    p.set_defaults(func=cmd_mesh)

    p = sub.add_parser("show", help="save a range image as a PNG picture")
    p.add_argument("input", help="range image (.npy, .png, .tif, .pcd)")
    p.add_argument("--out", required=True, help="output picture (.png)")
    p.add_argument("--depth-scale", type=depth_scale, default=None, help=DEPTH_SCALE_HELP)
    p.set_defaults(func=cmd_show)

    p = sub.add_parser("recover", help="recover parts from range images")
    p.add_argument(
        "input",
        nargs="+",
        help="range images (.npy .png .tif .pcd), folders of them, or glob patterns ('scans/**/*.png'; quote them)",
    )
    p.add_argument("--camera", help="camera JSON (a .pcd carries its own; this one, if given, is used instead)")
    p.add_argument(
        "--out",
        required=True,
        help="output directory (for several inputs, a folder or a pattern: one sub-folder per input and results.jsonl)",
    )
    b = p.add_argument_group("batches (many inputs)")
    b.add_argument("--recursive", action="store_true", help="folders include their sub-folders")
    b.add_argument(
        "--resume",
        action="store_true",
        help="skip inputs already recovered (complete folder, ok line in results.jsonl); redo the rest",
    )
    b.add_argument(
        "--jobs",
        type=_POSITIVE_INT,
        default=None,
        metavar="N",
        help="recover on N local worker processes (Dask LocalCluster, one thread each)",
    )
    b.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="recover on the workers of a running Dask scheduler (tcp://HOST:8786)",
    )
    p.add_argument("--grid", default="coarse", choices=["coarse", "default", "fine"], help="hypothesis grid")
    p.add_argument("--max-size", type=_POSITIVE, default=None, help="largest semi-axis searched (scene units)")
    p.add_argument("--sigma", type=_POSITIVE, default=None, help="match tolerance σ (scene units)")
    p.add_argument("--selection", default="auto", choices=["auto", "tabu", "exact", "best-first"])
    p.add_argument(
        "--refine-rounds",
        type=_number(f"an integer in [0, {MAX_REFINE_ROUNDS}]", low=0, high=MAX_REFINE_ROUNDS, integer=True),
        default=2,
    )
    p.add_argument("--depth-scale", type=depth_scale, default=None, help=DEPTH_SCALE_HELP)
    g = p.add_argument_group("real data (clean-up, figure/ground, prettifying)")
    g.add_argument(
        "--resolution",
        type=_number("an integer >= 0", low=0, integer=True),
        default=160,
        help="bin the image so its longest side is about this many pixels (0 = full resolution)",
    )
    g.add_argument("--no-clean", dest="clean", action="store_false", help="keep flying pixels and isolated outliers")
    g.add_argument(
        "--no-figure-ground",
        dest="figure_ground",
        action="store_false",
        help="no plane removal or splitting: the whole image is one figure",
    )
    g.add_argument(
        "--planes",
        type=_number("an integer in [0, 16]", low=0, high=16, integer=True),
        default=3,
        help="background planes (table or floor and the walls of a corner) to remove",
    )
    g.add_argument(
        "--tear",
        type=_POSITIVE,
        default=None,
        help="depth jump, in pixel footprints, that separates figures (default 8)",
    )
    g.add_argument(
        "--join",
        nargs="?",
        const="always",
        default="auto",
        choices=tuple(JOIN_MODES),
        help="pieces that touch with a depth jump less than the smaller one's size (an arm before the body, a "
        "mug's handle, but also objects side by side): auto (default): joined where a part spans the tear and "
        "that is the shorter description; never; or always (--join alone)",
    )
    g.add_argument("--min-figure-pixels", type=_POSITIVE_INT, default=None, help="smallest figure kept")
    g.add_argument("--max-figures", type=_POSITIVE_INT, default=None, help="recover at most this many figures")
    g.add_argument(
        "--max-border-fraction",
        type=_number("a number in [0, 1]", low=0, high=1),
        default=0.15,
        help="a piece with more of its pixels on the edge of the measured area is background (1 = keep)",
    )
    g.add_argument("--depth-range", default=None, help="NEAR,FAR: drop returns outside (scene units)")
    g.add_argument(
        "--holes",
        default="auto",
        choices=["auto", "free", "missing"],
        help="pixels with no return: free space (a part there pays commission) or missing data; "
        "auto: small interior holes are missing, wide ones and see-through ones free (default auto)",
    )
    g.add_argument(
        "--prettify", action="store_true", help="snap nearly vertical/horizontal parts to gravity (section 4.3)"
    )
    g.add_argument("--up", default=None, help="x,y,z gravity up in the camera frame (default: ground normal)")
    g.add_argument(
        "--max-angle",
        type=_number("a number of degrees in (0, 90]", low=0, high=90, open_low=True),
        default=15.0,
        help="prettify parts within this many degrees",
    )
    g.add_argument(
        "--max-bits",
        type=_number("a finite number >= 0", low=0),
        default=56.0,
        help="prettify only if E rises at most this (and every part still pays)",
    )
    p.add_argument(
        "--rerun",
        default=None,
        metavar="FILE.rrd",
        help="also log the points, parts and pixel classes to a Rerun recording",
    )
    p.set_defaults(func=_recover_command)

    p = sub.add_parser("demo", help="recover the built-in articulated human (Figure 7)")
    p.add_argument("--out", default="sqparts-demo", help="output directory (default sqparts-demo)")
    p.add_argument(
        "--resolution", type=_number("an integer in [32, 1024]", low=32, high=1024, integer=True), default=128
    )
    p.set_defaults(func=cmd_demo)

    def recognition_options(p):
        p.add_argument("--camera", help="camera JSON (a .pcd carries its own; this one, if given, is used instead)")
        p.add_argument("--db", required=True, help="model database folder")
        p.add_argument("--grid", default="coarse", choices=["coarse", "default", "fine"], help="hypothesis grid")
        p.add_argument(
            "--refine-rounds",
            type=_number(f"an integer in [0, {MAX_REFINE_ROUNDS}]", low=0, high=MAX_REFINE_ROUNDS, integer=True),
            default=2,
        )
        p.add_argument(
            "--resolution",
            type=_number("an integer >= 0", low=0, integer=True),
            default=160,
            help="bin the image so its longest side is about this many pixels (0 = full resolution)",
        )
        p.add_argument("--depth-scale", type=depth_scale, default=None, help=DEPTH_SCALE_HELP)

    p = sub.add_parser("learn", help="recover views of an object and add them to a model database")
    p.add_argument("name", help="the object's name (letters, digits, '.', '_', '-')")
    p.add_argument("input", nargs="+", help="range images (.npy .png .tif .pcd) or folders of them")
    recognition_options(p)
    p.add_argument(
        "--levels",
        type=_number("an integer in [1, 4]", low=1, high=4, integer=True),
        default=2,
        help="multiscale levels stored per view (1 = the recovery only)",
    )
    p.set_defaults(func=cmd_learn)

    p = sub.add_parser("recognize", help="recognise objects of a model database in range images")
    p.add_argument("input", nargs="+", help="range images (.npy .png .tif .pcd) or folders of them")
    recognition_options(p)
    p.add_argument("--out", required=True, help="output directory: one sub-folder per input")
    p.set_defaults(func=cmd_recognize)

    for p in sub.choices.values():
        p.add_argument("--overwrite", action="store_true", help="replace an existing output (default: refuse)")
        p.add_argument("--quiet", action="store_true", help="print nothing on success")

    p = sub.add_parser("view", help="view a recover output folder in 3-D in the browser (viser)")
    p.add_argument("folder", help="a sqparts recover output folder (parts.json, range.npy, camera.json, ...)")
    p.add_argument(
        "--port",
        type=_number("an integer in [1, 65535]", low=1, high=65535, integer=True),
        default=8080,
        help="serve on http://127.0.0.1:PORT (default 8080)",
    )
    p.set_defaults(func=cmd_view)
    return parser


# --- signals and exit status ------------------------------------------------------------


class Interrupted(BaseException):
    """SIGINT or SIGTERM arrived: unwinds like KeyboardInterrupt (staged outputs are
    removed on the way) and ends the run with status 128 + the signal's number."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


_signal_state = {"pending": None, "raised": False, "defer": False}


def _on_signal(signum, frame):
    state = _signal_state
    if state["raised"]:  # the run is already stopping: its clean-up must not be interrupted
        return
    state["pending"] = signum
    if state["defer"]:
        return
    state["raised"] = True
    raise Interrupted(signum)


def _deliver_again(signum, frame):
    _signal_state["raised"] = False
    _on_signal(_signal_state["pending"], frame)


def _unraisable(hook):
    """Python swallows an exception raised where it cannot propagate (a garbage-collector
    callback, ``__del__``; JAX's GC callback runs often). When that swallows an
    :class:`Interrupted`, the signal is delivered again 10 ms later (SIGALRM), in
    whatever ordinary frame runs then. Once a signal has arrived the run is stopping, and
    what such code raises next is the interruption's echo (Dask's GC callback, stopped
    between its start and stop phases, fails an assertion at the stop): it is dropped,
    not printed as a traceback."""

    def handle(unraisable):
        if isinstance(unraisable.exc_value, Interrupted):
            signal.setitimer(signal.ITIMER_REAL, 0.01)
        elif _signal_state["pending"] is None:
            hook(unraisable)

    return handle


@contextlib.contextmanager
def _signals_stop_the_run():
    """SIGINT and SIGTERM raise :class:`Interrupted`, whatever the inherited disposition
    (a shell starts background jobs with SIGINT ignored). Only the main thread can."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _signal_state.update(pending=None, raised=False, defer=False)
    handlers = {signal.SIGINT: _on_signal, signal.SIGTERM: _on_signal, signal.SIGALRM: _deliver_again}
    previous = {s: signal.signal(s, handler) for s, handler in handlers.items()}
    hook, sys.unraisablehook = sys.unraisablehook, _unraisable(sys.unraisablehook)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        sys.unraisablehook = hook
        for s, handler in previous.items():
            signal.signal(s, handler)


@contextlib.contextmanager
def _signals_deferred():
    """Hold a signal back while compiled extensions load (an exception raised inside
    jaxlib's initialisation can crash the process); it stops the run right after."""
    _signal_state["defer"] = True
    try:
        yield
    finally:
        _signal_state["defer"] = False
        if _signal_state["pending"] is not None and not _signal_state["raised"]:
            _signal_state["raised"] = True
            raise Interrupted(_signal_state["pending"])


def _error(message: str) -> int:
    print(f"sqparts: error: {message.splitlines()[0] if message else 'unknown error'}", file=sys.stderr)
    return 2


def run() -> None:
    """The ``sqparts`` command (and ``python -m sqparts``): :func:`main`, then an exit
    that skips tearing down the interpreter. Freeing JAX's compiled programs and every
    module at exit takes 0.5-0.9 s of a 4 s call on a 2-core CPU; by the time
    :func:`main` returns every output is written and closed (atomically), so the
    process has nothing left to do but flush its streams and logs."""
    status = main()
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except OSError:  # e.g. a reader that closed the pipe: as Python's own exit reports it
        status = status or 120
    logging.shutdown()
    os._exit(status)


def _as_typed(message: str, argv) -> str:
    """An error of a setting named as the library names it (``sigma: got ...``) named by
    the flag the user typed for it (``--sigma: got ...``)."""
    field, sep, rest = message.partition(": got ")
    flag = "--" + field.replace("_", "-")
    if sep and field.isidentifier() and any(a == flag or a.startswith(flag + "=") for a in argv):
        return f"{flag}: got {rest}"
    return message


def main(argv=None) -> int:
    """Run the command line; returns the exit status (0, 2 for a user error, 130/143
    when interrupted by SIGINT/SIGTERM)."""
    typed = sys.argv[1:] if argv is None else argv  # the flags as the user typed them
    with _signals_stop_the_run(), contextlib.ExitStack() as stack:
        try:
            with _signals_deferred():
                from . import _compile

                args = build_parser().parse_args(argv)
                stack.enter_context(_compile.caches_enabled())
                # The programs this command used last time load while the rest is imported.
                stack.enter_context(_compile.prefetching(args.func.__name__))
                from . import _io, _mesh, _plot, _recover  # noqa: F401  (equinox, scipy, matplotlib)
            return args.func(args)
        except OSError as e:
            if e.strerror and e.filename:  # raised by the OS, not by us: name the file
                return _error(
                    f"file: got {str(e.filename)!r} ({e.strerror}), expected a path that can be read or written"
                )
            return _error(_as_typed(str(e) or type(e).__name__, typed))
        except (ValueError, TypeError) as e:
            return _error(_as_typed(str(e) or type(e).__name__, typed))
        except MemoryError:
            return _error(
                "memory: got an input too large for this machine's memory, expected a smaller image or fewer parts"
            )
        except RuntimeError as e:  # XLA's allocation failure; anything else is a bug and keeps its traceback
            if "RESOURCE_EXHAUSTED" not in str(e):
                raise
            return _error(
                "memory: got an input too large for the device's memory, expected a smaller image or fewer parts"
            )
        except (Interrupted, KeyboardInterrupt) as e:
            signum = getattr(e, "signum", signal.SIGINT)
            print(f"sqparts: interrupted by {signal.Signals(signum).name}; no partial output left", file=sys.stderr)
            return 128 + int(signum)
