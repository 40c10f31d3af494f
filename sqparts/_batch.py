"""Many range images in one call: :func:`recover_many` (issue 29), at the edge with
``_io`` and ``cli``.

A batch writes one sub-folder per input into ``out`` (``parts.json``, ``model.ply``,
``report.png``, staged so that they appear together or not at all) and one line per
input into ``out/results.jsonl``::

    {"input": "scans/a.npy", "output": "a", "status": "ok", "parts": 3, "E": 1834.2,
     "fraction_explained": 0.93, "seconds": 4.1, "error": null}

``output`` is the input's sub-folder relative to ``out``; ``E`` the description length
in bits (Eq. 6); ``fraction_explained`` the fraction of figure pixels explained within
±σ/2. A failing input gets ``"status": "error"`` and its one-line message, and the batch
goes on. Each line is appended whole with one ``write`` and made durable (``fsync``)
before the next, so a crash or a signal can leave at most a torn last line, which a
resumed run ignores and drops.

The work runs in this process, input after input (the compiled programs shared by all),
or on a Dask cluster (``client=``): each worker compiles once, keeps JAX's persistent
compilation cache in ``$SQPARTS_CACHE_DIR`` (default ``~/.cache/sqparts/jax``) and
writes its outputs into ``out`` itself (a remote cluster needs ``out`` on a shared file
system); the lines are written by the caller, in completion order.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import glob
import json
import os
import re
import time
from pathlib import Path

RESULTS_NAME = "results.jsonl"
OUTPUT_FILES = ("parts.json", "model.ply", "report.png")
VIEW_FILES = ("range.npy", "camera.json", "pixels.npz")
"""What ``sqparts view`` reads, written beside the outputs of a recovery with a camera."""
_PATTERN_CHARACTERS = frozenset("*?[")


# --- inputs and names ----------------------------------------------------------------


def expand_inputs(paths, *, recursive: bool = False, exclude=None) -> list[Path]:
    """Range image files from files, folders and glob patterns, in order.

    A folder gives the range images in it (sorted; with ``recursive``, also in its
    sub-folders, skipping hidden ones); a path that does not exist but holds ``*``,
    ``?`` or ``[`` is a glob pattern (``**`` matches any depth) giving the range images
    it matches, sorted. Neither gives the ``report.png`` or ``range.npy`` of an sqparts
    output folder (one holding ``parts.json``), nor anything in the folder ``exclude``
    (a batch's ``--out``: a resumed batch inside the folders it scans would take its
    own outputs for inputs). Raises
    ``FileNotFoundError`` for a missing path, ``ValueError`` for a folder or pattern
    without range images or an input given twice.
    """
    from ._io import RANGE_IMAGE_SUFFIXES

    wanted = ", ".join(RANGE_IMAGE_SUFFIXES)

    written = {n for n in (*OUTPUT_FILES, *VIEW_FILES) if Path(n).suffix in RANGE_IMAGE_SUFFIXES}
    skip = None if exclude is None else Path(exclude).resolve()

    def images(found, root=None):
        keep = []
        for q in found:
            if q.suffix.lower() not in RANGE_IMAGE_SUFFIXES or not q.is_file():
                continue
            if root is not None and any(part.startswith(".") for part in q.relative_to(root).parts):
                continue
            if q.name in written and (q.parent / "parts.json").is_file():
                continue
            if skip is not None and q.resolve().is_relative_to(skip):
                continue
            keep.append(q)
        return sorted(keep)

    out = []
    for given in paths:
        if not isinstance(given, (str, os.PathLike)):
            raise TypeError(
                f"input: got {type(given).__name__}, expected a path (a range image file, a folder or a glob pattern)"
            )
        text = str(given)
        p = Path(text)
        if p.is_dir():
            found = images(p.rglob("*") if recursive else p.iterdir(), root=p)
            if not found:
                where = "in it or its sub-folders" if recursive else "in it (or --recursive for its sub-folders)"
                raise ValueError(f"input: got folder {text!r}, expected range images {where} ({wanted})")
            out.extend(found)
        elif not p.exists() and _PATTERN_CHARACTERS & set(text):
            found = images(map(Path, glob.glob(text, recursive=True)))
            if not found:
                raise ValueError(
                    f"input: got pattern {text!r}, which matches no range images, expected one matching {wanted} files"
                )
            out.extend(found)
        elif not p.exists():
            raise FileNotFoundError(f"input: got {text!r}, expected an existing file or folder, or a glob pattern")
        elif p.suffix.lower() not in RANGE_IMAGE_SUFFIXES:  # every input's name checked before any work
            raise ValueError(f"input: got {text!r}, expected a range image ending in {wanted}")
        elif not p.is_file():
            raise ValueError(
                f"input: got {text!r}, which is not a regular file (a device, pipe or socket), expected a range image file"
            )
        else:
            out.append(p)
    seen = {}
    for p in out:
        key = p.resolve()
        if key in seen:
            raise ValueError(f"input: got {str(p)!r} twice (also as {str(seen[key])!r}), expected each input once")
        seen[key] = p
    return out


def output_names(paths) -> list[str]:
    """One sub-folder name per input: its stem where no other input shares it, else its
    path relative to the inputs' common folder (without the suffix where that is
    enough: ``a/x.npy b/x.npy`` -> ``a/x``, ``b/x``; ``a.npy a.png`` -> ``a.npy``, ``a.png``)."""
    resolved = [Path(p).resolve() for p in paths]
    if not resolved:
        return []
    root = Path(os.path.commonpath([str(r.parent) for r in resolved]))
    relative = [r.relative_to(root) for r in resolved]
    stems = [r.stem for r in relative]
    bare = [str(r.with_suffix("")) for r in relative]
    stem_count, bare_count = collections.Counter(stems), collections.Counter(bare)
    names = [
        stem if stem_count[stem] == 1 else name if bare_count[name] == 1 else str(r)
        for stem, name, r in zip(stems, bare, relative)
    ]
    # A short name may still meet another input's (``x.npy.png``'s stem is ``x.npy``),
    # hold it (``b.npy``'s ``b`` beside ``b/x.npy``'s ``b/x``) or name no folder of its
    # own (``..npy``'s stem is ``.``, which is --out itself): those take their whole
    # relative path, until none clash (whole paths of distinct files never do).
    while clashing := _clashing(names):
        names = [str(r) if i in clashing else n for i, (n, r) in enumerate(zip(names, relative))]
    return names


def _clashing(names) -> set[int]:
    """Indices of output names equal to another's, holding another (a folder of it) or
    not a folder of their own (empty, or a ``.`` or ``..`` in them)."""
    index = collections.defaultdict(list)
    for i, n in enumerate(names):
        index[n].append(i)
    bad = {i for group in index.values() if len(group) > 1 for i in group}
    bad.update(i for i, n in enumerate(names) if not n or {".", ".."} & set(re.split(r"[\\/]", n)))
    for i, n in enumerate(names):
        for up in Path(n).parents:
            if str(up) != "." and str(up) in index:
                bad.add(i)
                bad.update(index[str(up)])
    return bad


# --- one input ---------------------------------------------------------------------------


def write_recovery(folder, recovery, *, title: str, names=None) -> None:
    """``parts.json``, ``model.ply`` and ``report.png`` of a recovery into ``folder``
    (a staged folder)."""
    from ._io import atomic_write
    from ._mesh import save_ply, scene_surface
    from ._plot import save_report

    folder = Path(folder)
    text = json.dumps(recovery.scene_dict(names), indent=2)
    with atomic_write(folder / "parts.json", "w") as f:
        f.write(text + "\n")
    save_ply(folder / "model.ply", *scene_surface(recovery.parts, resolution=24))
    save_report(folder / "report.png", recovery, title=title)
    if getattr(recovery, "camera", None) is not None:
        from ._io import save_view_data
        from ._view import pixel_status

        save_view_data(
            folder,
            recovery.depth,
            recovery.camera,
            status=pixel_status(recovery),
            model=recovery.cost.rendered,
            labels=recovery.cost.labels,
        )


def read_input(path, *, camera=None, depth_scale: float = 0.001):
    """One range image and the camera it is recovered with: ``camera`` replaces the
    file's own (a ``.pcd`` carries one). Raises ``ValueError`` for an image without a
    camera or of another size than the camera."""
    from ._io import read_range_image

    depth, own = read_range_image(path, depth_scale=depth_scale)
    camera = camera or own
    if camera is None:
        raise ValueError(
            f"--camera: got nothing for {str(path)!r}, which carries no camera, expected --camera CAM.json"
        )
    if depth.shape != (camera.height, camera.width):
        raise ValueError(
            f"--camera: got a {camera.width}x{camera.height} camera for {str(path)!r}, expected "
            f"{depth.shape[1]}x{depth.shape[0]} (the image's size)"
        )
    return depth, camera


@contextlib.contextmanager
def naming_input(path):
    """An image's depths refused inside (``depth: got 0 returns, ...``): the error names
    the file it was read from (``input: got 0 returns in 'x.npy', ...``)."""
    try:
        yield
    except ValueError as e:
        got, _, rest = str(e).partition(": ")
        if got != "depth" or not rest.startswith("got "):
            raise
        found, _, expected = rest.partition(", expected ")
        raise ValueError(f"input: {found} in {str(path)!r}" + (f", expected {expected}" if expected else "")) from None


def recover_file(
    path,
    target,
    *,
    camera=None,
    depth_scale: float = 0.001,
    sigma=None,
    overwrite: bool = False,
    progress=None,
    **options,
):
    """Read one range image, recover its scene (:func:`~sqparts.recover_scene` with
    ``options``) and write its three outputs into the folder ``target`` in one step.

    ``camera`` replaces the file's own (a ``.pcd`` carries one); ``sigma`` is the match
    tolerance σ in scene units (default: from the depth range). Returns the
    :class:`~sqparts.SceneRecovery`; raises ``ValueError`` for an image without a
    camera or of another size than the camera.
    """
    import numpy as np

    from ._camera import check_range_image
    from ._encoding import encoding_for
    from ._io import staged_folder
    from ._recover import recover_scene

    path = Path(path)
    depth, camera = read_input(path, camera=camera, depth_scale=depth_scale)
    with naming_input(path):
        check_range_image(depth, camera)  # the image's depths before --sigma is checked against them
        encoding = encoding_for(depth[np.isfinite(depth)], sigma=sigma) if sigma else None
        recovery = recover_scene(depth, camera, encoding=encoding, progress=progress, **options)
    with staged_folder(target, overwrite=overwrite, inputs=(path,)) as folder:
        write_recovery(folder, recovery, title=path.name)
    return recovery


def error_message(error: BaseException) -> str:
    """One line for a failed input, in the CLI's style where the error is ours."""
    if isinstance(error, OSError) and error.strerror and error.filename:
        return f"file: got {str(error.filename)!r} ({error.strerror}), expected a path that can be read or written"
    if isinstance(error, MemoryError) or "RESOURCE_EXHAUSTED" in str(error):
        return "memory: got an input too large for this machine's memory, expected a smaller image or fewer parts"
    text = (str(error).splitlines() or [""])[0]
    if isinstance(error, (OSError, ValueError, TypeError)) and text:
        return text
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


@dataclasses.dataclass(frozen=True)
class _Task:
    """One input of a batch, as sent to whoever recovers it (this process or a worker)."""

    input: str
    output: str
    out: str
    camera: object
    depth_scale: float
    sigma: float | None
    options: dict
    replace: bool

    def record(self, status: str, *, seconds: float, recovery=None, error=None) -> dict:
        ok = recovery is not None
        return {
            "input": self.input,
            "output": self.output,
            "status": status,
            "parts": len(recovery.parts) if ok else None,
            "E": float(recovery.cost.total) if ok else None,
            "fraction_explained": float(recovery.fraction_explained) if ok else None,
            "seconds": round(seconds, 3),
            "error": error,
        }


def _run_task(task: _Task, *, worker: bool = False) -> dict:
    """Recover one input; a failure becomes an error record (a signal still stops it)."""
    if worker:
        enable_compilation_cache()
    t0 = time.perf_counter()
    try:
        recovery = recover_file(
            task.input,
            Path(task.out) / task.output,
            camera=task.camera,
            depth_scale=task.depth_scale,
            sigma=task.sigma,
            overwrite=task.replace,
            **task.options,
        )
    except Exception as e:  # noqa: BLE001  (any failure of one input is recorded; the batch goes on)
        return task.record("error", seconds=time.perf_counter() - t0, error=error_message(e))
    finally:
        from ._compile import release_if_crowded

        release_if_crowded()  # a long batch of varied inputs must not exhaust the process's mappings
    return task.record("ok", seconds=time.perf_counter() - t0, recovery=recovery)


def _run_on_worker(task: _Task) -> dict:
    return _run_task(task, worker=True)


def enable_compilation_cache() -> None:
    """:func:`sqparts._compile.enable_caches`, once per (worker) process."""
    if _cache_state["enabled"]:
        return
    from ._compile import enable_caches

    enable_caches()
    _cache_state["enabled"] = True


_cache_state = {"enabled": False}


# --- the plan: what to do, checked before any work ---------------------------------------


@dataclasses.dataclass(frozen=True)
class BatchPlan:
    """A batch checked and ready to run.

    Attributes
    ----------
    out : the output folder; ``results`` its ``results.jsonl``.
    tasks : the inputs to recover, in order.
    skipped : the earlier records of the inputs ``resume`` skips (complete).
    keep : the lines ``results.jsonl`` starts with (None: leave the file as it is).
    """

    out: Path
    results: Path
    tasks: tuple
    skipped: tuple
    keep: tuple | None


def read_results(path) -> list[dict]:
    """The records of a ``results.jsonl``; a torn or unreadable line is left out."""
    records = []
    try:
        lines = Path(path).read_bytes().split(b"\n")
    except FileNotFoundError:
        return records
    for line in lines:
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except ValueError:
            continue
        if isinstance(record, dict) and {"input", "output", "status"} <= set(record):
            records.append(record)
    return records


def _complete(folder: Path) -> bool:
    return all((folder / name).is_file() for name in OUTPUT_FILES + VIEW_FILES)


def _ours(folder: Path) -> bool:
    """Only sqparts' own output files (a finished input whose line a signal cut off)."""
    return folder.is_dir() and all(p.name in OUTPUT_FILES + VIEW_FILES for p in folder.iterdir())


def plan_batch(
    inputs,
    *,
    out,
    camera=None,
    recursive: bool = False,
    overwrite: bool = False,
    resume: bool = False,
    depth_scale: float = 0.001,
    sigma=None,
    **options,
) -> BatchPlan:
    """Check a batch before any work (see :func:`recover_many`): inputs exist, names and
    output folders are distinct, nothing would be overwritten silently, the settings are
    :func:`~sqparts.recover_scene`'s."""
    from ._io import check_new_output, load_camera
    from ._preprocess import check_positive
    from ._recover import scene_preset
    from ._refine import RefineSettings
    from ._search import search_preset
    from ._select import SelectSettings

    checks = {
        "scene": scene_preset,
        "search": search_preset,
        "select": SelectSettings,
        "refine": RefineSettings,
    }
    for name, value in options.items():
        if name not in checks:
            raise TypeError(f"{name}: got it as a setting, expected one of {sorted(checks)} (recover_scene's settings)")
        kind = checks[name]
        if isinstance(kind, type):
            if value is not None and not isinstance(value, kind):
                raise TypeError(f"{name}: got {value!r:.60}, expected a sqparts.{kind.__name__} or None")
        else:
            kind(value)
    if resume and overwrite:
        raise ValueError(
            "--resume: got it with --overwrite, expected one of them (resume keeps finished inputs, overwrite redoes all)"
        )
    check_positive("depth_scale", depth_scale)
    if sigma is not None:
        check_positive("sigma", sigma)
    if isinstance(inputs, (str, os.PathLike)):  # one path, not a sequence of its characters
        inputs = [inputs]
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"--out: got {str(out)!r}, which is a file, expected a folder")
    camera_file = camera if isinstance(camera, (str, os.PathLike)) else None  # never inside a folder replaced
    if camera_file is not None:
        camera = load_camera(camera_file)
    paths = expand_inputs(inputs, recursive=recursive, exclude=out)
    if not paths:
        raise ValueError("input: got no inputs, expected at least one range image")
    names = output_names(paths)
    results = out / RESULTS_NAME
    ran = results.exists()  # an earlier run, even if a crash tore its only line
    earlier = read_results(results) if ran else []
    if ran and not (resume or overwrite):
        raise FileExistsError(
            f"--out: got {str(out)!r}, which holds the {RESULTS_NAME} of an earlier run, "
            "expected a new folder (or --resume to finish it, or --overwrite)"
        )
    if resume and not ran and any((out / name).exists() for name in OUTPUT_FILES):
        raise FileExistsError(
            f"--out: got {str(out)!r}, which holds one recovery's outputs, "
            f"expected a batch's folder to resume (with its {RESULTS_NAME}) or a new one"
        )
    if resume and not ran and out.is_dir() and any(not p.name.startswith(".sqparts-") for p in out.iterdir()):
        raise FileExistsError(
            f"--resume: got --out {str(out)!r}, which holds no {RESULTS_NAME} of an earlier run, "
            "expected a batch's folder to resume or a new one"
        )
    latest = {(r["input"], r["output"]): r for r in earlier} if resume else {}
    tasks, skipped = [], []
    for path, name in zip(paths, names):
        target = out / name
        record = latest.get((str(path), name))
        if record is not None and record["status"] == "ok" and _complete(target):
            skipped.append(record)
            continue
        replace = overwrite
        if resume and target.exists() and _ours(target):
            replace = True  # finished but unrecorded, or a failed earlier run's: redo it
        else:
            check_new_output(target, overwrite=overwrite, inputs=[*paths, camera_file])
        tasks.append(_Task(str(path), name, str(out), camera, depth_scale, sigma, dict(options), replace))
    keep = None
    if resume and results.exists():
        redo = {(t.input, t.output) for t in tasks}
        kept = [r for r in earlier if (r["input"], r["output"]) not in redo]
        kept = list({(r["input"], r["output"]): r for r in kept}.values())  # the latest of each
        text = "".join(json.dumps(r) + "\n" for r in kept).encode()
        if text != results.read_bytes():
            keep = tuple(kept)  # drop the torn line, superseded and to-be-redone lines
    elif not resume:
        keep = ()  # a new results.jsonl (an earlier one only with overwrite)
    return BatchPlan(out, results, tuple(tasks), tuple(skipped), keep)


# --- running -----------------------------------------------------------------------------


class _ResultsLog:
    """``results.jsonl`` opened for appending: each record one whole line, one ``write``,
    then ``fsync``, so a crash leaves at most a torn last line."""

    def __init__(self, path: Path, keep):
        from ._io import atomic_write

        path.parent.mkdir(parents=True, exist_ok=True)
        if keep is not None:  # start the file afresh, in one step
            with atomic_write(path, "wb") as f:
                f.write("".join(json.dumps(r) + "\n" for r in keep).encode())
                f.flush()
                os.fsync(f.fileno())
        self.fd: int | None = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)

    def append(self, record: dict) -> None:
        if self.fd is None:
            raise ValueError("results: got a closed results.jsonl, expected one open for appending")
        os.write(self.fd, (json.dumps(record) + "\n").encode())
        os.fsync(self.fd)

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def run_batch(plan: BatchPlan, *, client=None, progress: bool = False):
    """Recover a plan's inputs, appending each record to ``results.jsonl`` as it
    finishes, and yield the records (see :func:`recover_many`)."""
    from tqdm import tqdm

    log = _ResultsLog(plan.results, plan.keep)
    bar = tqdm(
        total=len(plan.tasks),
        desc="inputs",
        unit="input",
        disable=True if not progress or not plan.tasks else None,  # None: on a terminal only
        leave=False,
        dynamic_ncols=True,
    )
    failed = 0
    try:
        if client is None:
            records = _run_here(plan.tasks)
        else:
            from ._dask import run_on_cluster

            records = run_on_cluster(plan.tasks, client)
        for record in records:
            log.append(record)
            if record["status"] != "ok":
                failed += 1
                bar.set_postfix(failed=failed, refresh=False)
            bar.update()
            yield record
    finally:
        bar.close()
        log.close()


def _run_here(tasks):
    for task in tasks:
        yield _run_task(task)


def remove_staging(plan: BatchPlan, *, since: float) -> None:
    """Remove staging folders (``.sqparts-*.tmp``) made since ``since`` (a time stamp)
    beside the plan's outputs: what workers killed mid-write leave."""
    import shutil

    for parent in {(plan.out / t.output).parent for t in plan.tasks}:
        for p in parent.glob(".sqparts-*.tmp") if parent.is_dir() else ():
            with contextlib.suppress(OSError):
                if p.stat().st_mtime >= since - 1:
                    shutil.rmtree(p) if p.is_dir() else p.unlink()


def recover_many(
    inputs,
    *,
    out,
    camera=None,
    client=None,
    recursive: bool = False,
    overwrite: bool = False,
    resume: bool = False,
    depth_scale: float = 0.001,
    sigma=None,
    progress: bool = False,
    **options,
):
    """Recover the scene of each of many range images; yield a record per input.

    Parameters
    ----------
    inputs : range image files, folders of them, and glob patterns (``"scans/**/*.png"``).
    out : the output folder: one sub-folder per input (named as :func:`output_names`
        says) and ``results.jsonl``, one JSON line per input (module docstring).
    camera : a camera or camera JSON path for every input (a ``.pcd`` carries its own).
    client : a ``distributed.Client``: the inputs are recovered on its workers and the
        records come in completion order; None: here, in order.
    recursive : folders include their sub-folders.
    overwrite : replace existing outputs and start ``results.jsonl`` afresh.
    resume : skip the inputs whose sub-folder is complete and whose latest line says
        ``ok``; redo the others (failed, missing, or finished without a line).
    depth_scale, sigma : as for ``sqparts recover``.
    options : :func:`~sqparts.recover_scene`'s settings (``scene``, ``search``, ``select``, ``refine``).
    progress : show a progress bar over the inputs (rate and time left).

    Returns
    -------
    An iterator of the records of the inputs recovered now (not of those skipped); the
    work is done as it is iterated. Everything is checked when this is called, before
    any work: ``FileNotFoundError`` for a missing input, ``FileExistsError`` for an
    output that exists (unless ``overwrite``, or an earlier run's with ``resume``),
    ``ValueError`` for an input given twice.
    """
    plan = plan_batch(
        inputs,
        out=out,
        camera=camera,
        recursive=recursive,
        overwrite=overwrite,
        resume=resume,
        depth_scale=depth_scale,
        sigma=sigma,
        **options,
    )
    return run_batch(plan, client=client, progress=progress)
