"""Start-up: ahead-of-time exported programs, kept on disk between processes.

A new process that calls a ``jax.jit`` function traces and lowers it again even when
JAX's persistent compilation cache holds the compiled program; for the search's and the
refinement's big programs (the renderer inlined into an optimistix solver inside
``lax.map``) tracing and lowering cost seconds. :func:`persistent_jit` is ``jax.jit``
plus one more cache: the first call with a given signature exports the program with
``jax.export`` and stores it; a later process deserializes it and calls it, which needs
neither tracing nor (with JAX's persistent compilation cache, set by the CLI) compiling.

This module is the only place the JAX core touches files for compilation. Its interface:

* :func:`persistent_jit` (a decorator, used in place of ``jax.jit`` on entry points);
* :func:`set_export_dir` (``None`` turns exporting off: every call is a plain ``jit``).
  Off by default in the library; the CLI turns it on in its cache folder. The
  environment variable ``SQPARTS_EXPORT=0`` turns it off whatever is set.
* :func:`prefetching` (a block that loads, on two background threads while it runs,
  the programs the last block with its label used; the CLI wraps each command in one).

An entry is ``<dir>/<name>-<key>.jaxexport``; the key hashes the JAX and jaxlib
versions, the package's source files, the backend and device count, the function, its
static arguments and its arguments' tree, shapes and dtypes, so a stale entry is never
looked up. An entry holds a SHA-256 of its payload; an unreadable, truncated, corrupt or
mismatched one is ignored (logged at WARNING) and replaced by a fresh export, and any
failure of the export itself falls back to the plain ``jit``: results never depend on
the cache. Entries are unpickled: the folder is trusted like the installed package.
Exporting is skipped (plain ``jit``) inside an outer trace, with more than
one device (sharded programs are not exported) and for static arguments whose ``repr``
is not stable across processes.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import gc
import hashlib
import inspect
import logging
import os
import pickle
import tempfile
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import jax
import jax.core
import numpy as np

__all__ = [
    "persistent_jit",
    "set_export_dir",
    "export_dir",
    "forget_loaded",
    "enable_caches",
    "caches_enabled",
    "release_if_crowded",
    "prefetching",
    "concurrently",
]

_log = logging.getLogger(__name__)
_MAGIC = b"sqparts-export-1\n"
_state: dict[str, Path | None] = {"dir": None}
_loaded_tables: list[dict] = []  # every persistent_jit's loaded programs (see forget_loaded)
_records: list[dict[str, None]] = []  # the entries used inside each open prefetching block, in order
_prefetched: dict[str, Future] = {}  # entry name -> its runner (or None), being loaded in the background


CACHE_MAX_BYTES = 1 << 30
"""Most bytes JAX's persistent compilation cache keeps (least recently used entries are
evicted beyond it). A bound also makes JAX read and write every entry under a file lock,
so processes sharing the folder (a batch's local workers, Dask workers on one host, the
test suite's workers) never read an entry another is still writing."""

_CACHE_SETTINGS = (
    "jax_compilation_cache_dir",
    "jax_persistent_cache_min_compile_time_secs",
    "jax_compilation_cache_max_size",
)


def enable_caches() -> None:
    """What the command line and its Dask workers turn on: JAX's persistent compilation
    cache in ``$SQPARTS_CACHE_DIR`` (default ``~/.cache/sqparts/jax``), for every program
    however small, bounded by :data:`CACHE_MAX_BYTES` and safe to share between
    processes, and the exported programs beside it (``exported/``), so that a later
    process neither compiles nor traces them. An unwritable cache folder leaves both off."""
    cache = Path(os.environ.get("SQPARTS_CACHE_DIR", str(Path.home() / ".cache" / "sqparts" / "jax")))
    try:
        cache.mkdir(parents=True, exist_ok=True)
        _repair_cache(cache)
        jax.config.update("jax_compilation_cache_max_size", CACHE_MAX_BYTES)
        jax.config.update("jax_compilation_cache_dir", str(cache))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        set_export_dir(cache / "exported")
    except OSError:
        pass


def _repair_cache(cache: Path) -> None:
    """Give every entry of JAX's bounded compilation cache in ``cache`` that lacks its
    access-time file one (its own modification time).

    JAX writes an entry (``<key>-cache``) and then its access time (``<key>-atime``); a
    process killed between the two leaves an entry without one, and from then on every
    write to the cache fails (its eviction reads every entry's access time), each with a
    warning, so no new program is ever kept again. Writing the missing file is harmless
    when another process is itself just about to write it."""
    for entry in cache.glob("*-cache"):
        atime = entry.with_name(entry.name.removesuffix("-cache") + "-atime")
        if not atime.exists():
            with contextlib.suppress(OSError):  # e.g. evicted meanwhile by another process
                atime.write_bytes(entry.stat().st_mtime_ns.to_bytes(8, "little"))


@contextlib.contextmanager
def caches_enabled():
    """:func:`enable_caches` for the duration of a ``with`` block (one command-line run),
    then the settings as they were: ``main()`` called from Python leaves the caller's
    process as it found it."""
    before = {name: getattr(jax.config, name) for name in _CACHE_SETTINGS}
    export = _state["dir"]
    enable_caches()
    try:
        yield
    finally:
        for name, value in before.items():
            jax.config.update(name, value)
        _state["dir"] = export


def release_if_crowded(fraction: float = 0.5) -> bool:
    """Drop this process's compiled programs (``jax.clear_caches``) when its memory
    mappings pass ``fraction`` of the kernel's limit (``vm.max_map_count``, Linux only).

    Every live XLA CPU executable holds a few mappings per kernel (~2 000-4 000 for one
    recovery's programs); a long-lived process that meets many image sizes or settings
    would reach the limit, after which the next compilation aborts inside LLVM ("unable
    to allocate section memory"). Called between the inputs of a batch; the programs
    dropped are compiled again, or read back from the persistent cache, when next
    needed. Returns whether it released them."""
    try:
        limit = int(Path("/proc/sys/vm/max_map_count").read_text())
        with open("/proc/self/maps", "rb") as f:
            count = sum(1 for _ in f)
    except (OSError, ValueError):
        return False
    if count <= fraction * limit:
        return False
    _log.info("sqparts: %d of %d memory mappings in use; releasing compiled programs", count, limit)
    forget_loaded()
    jax.clear_caches()
    gc.collect()
    return True


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


_pools: dict[int, ThreadPoolExecutor] = {}  # by thread count (SQPARTS_THREADS may change)
_pools_lock = threading.Lock()


class RowMemo:
    """Results of a deterministic per-row computation, by a digest of the row's inputs
    (least recently used first out, at most ``max_bytes`` of results), kept while a
    :func:`memo_scope` is open (one recovery): refinement asks again for what it has
    computed before (the merges of parts a pass left alone, the same start fitted on
    the same pixels), and a row's result does not depend on what shares its batch, so a
    repeat is looked up instead of computed. Outside every scope nothing is kept.
    Thread-safe."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self._rows: collections.OrderedDict[bytes, np.ndarray] = collections.OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self.hits = 0
        _memos.append(self)

    @staticmethod
    def key(*parts) -> bytes:
        """Digest of the row's inputs: arrays (by dtype, shape and bytes) and reprs."""
        h = hashlib.blake2b(digest_size=20)
        for x in parts:
            if isinstance(x, np.ndarray):
                h.update(f"{x.dtype}{x.shape}".encode())
                h.update(np.ascontiguousarray(x).tobytes())
            else:
                h.update(repr(x).encode())
        return h.digest()

    def get(self, key: bytes) -> np.ndarray | None:
        if not _scopes:
            return None
        with self._lock:
            row = self._rows.get(key)
            if row is not None:
                self._rows.move_to_end(key)
                self.hits += 1
            return row

    def put(self, key: bytes, row: np.ndarray) -> None:
        if not _scopes:
            return
        row = np.array(row)  # an owned copy: callers may write into theirs
        with self._lock:
            if key in self._rows:
                return
            self._rows[key] = row
            self._bytes += row.nbytes
            while self._bytes > self.max_bytes and self._rows:
                self._bytes -= self._rows.popitem(last=False)[1].nbytes

    def rows(self, keys, out: np.ndarray, compute) -> np.ndarray:
        """``out`` with the row of each of ``keys`` looked up, or, for the rows not known,
        computed by ``compute(indices)`` (their rows, in that order) and kept."""
        todo = []
        for i, k in enumerate(keys):
            row = self.get(k)
            if row is None:
                todo.append(i)
            else:
                out[i] = row
        if todo:
            for i, row in zip(todo, compute(todo)):
                out[i] = row
                self.put(keys[i], row)
        return out

    def clear(self) -> None:
        with self._lock:
            self._rows.clear()
            self._bytes = 0


_memos: list[RowMemo] = []
_scopes = 0
_scopes_lock = threading.Lock()


def clear_memos() -> None:
    """Forget every :class:`RowMemo`'s results."""
    for memo in _memos:
        memo.clear()


@contextlib.contextmanager
def memo_scope():
    """Keep :class:`RowMemo` results while inside (scopes nest, and may be open in several
    threads at once); when the last one closes, they are forgotten: a recovery looks up
    its own repeats, never another call's."""
    global _scopes
    with _scopes_lock:
        _scopes += 1
    try:
        yield
    finally:
        with _scopes_lock:
            _scopes -= 1
            if not _scopes:
                clear_memos()


def workers() -> int:
    """Threads :func:`concurrently` runs its calls on: one per usable CPU core, or
    ``SQPARTS_THREADS``."""
    try:
        return int(os.environ.get("SQPARTS_THREADS", "0")) or _cores()
    except ValueError:
        return _cores()


def balanced_groups(n: int, size: int) -> list[np.ndarray]:
    """Indices 0..n-1 in consecutive groups of at most ``size``, as few as there can be
    but, when the calls run on the CPU's own cores, at least one per :func:`workers`
    thread (while there are items), their sizes differing by at most one: compiled calls
    of ``size`` padded rows, run :func:`concurrently`, then finish together (12 parts:
    two calls of 6, not 8 and 4; 2 parts: two calls of one, not one of two). On an
    accelerator one call of many rows beats several small ones: as few as there can be."""
    if n <= 0:
        return []
    count = -(-n // size)
    if jax.default_backend() == "cpu":
        count = min(n, -(-count // workers()) * workers())
    return np.array_split(np.arange(n), count)


def concurrently(fn: Callable, items, *, progress=None) -> list:
    """``[fn(x) for x in items]``, the calls run on a pool of threads, one per usable CPU
    core (``SQPARTS_THREADS`` overrides; 1: one after another in this thread).

    For independent compiled calls (a batch of parts split into buckets): XLA runs each
    on the thread that waits for it, mostly on one core, and releases the GIL meanwhile,
    so two buckets on two cores take about half the time (4 buckets of 8 parts polished in
    0.13 s instead of 0.28 s on the 2-core CPU). Host work whose time goes to calls that
    release the GIL gains too (matching a query against every stored view: scipy's k-d
    tree queries and LAPACK's SVDs, 1.3x on two cores). Each call computes what it computes alone:
    the results do not depend on the threads. An exception is raised as in the loop.
    ``progress`` (e.g. ``tqdm.tqdm``) wraps the iteration over the calls as they are
    waited for, in order."""
    items = list(items)
    wrap = progress or (lambda it: it)
    threads = workers()
    if threads <= 1 or len(items) <= 1:
        return [fn(x) for x in wrap(items)]
    with _pools_lock:
        pool = _pools.get(threads) or _pools.setdefault(
            threads, ThreadPoolExecutor(threads, thread_name_prefix="sqparts")
        )
    futures = [pool.submit(fn, x) for x in items]
    try:
        return [f.result() for f in wrap(futures)]
    finally:
        for f in futures:  # an exception or an interrupt: what has not started never will
            f.cancel()


def set_export_dir(directory) -> None:
    """Store exported programs under ``directory`` (created if needed); ``None``: off."""
    if directory is None:
        _state["dir"] = None
        return
    path = Path(directory)
    path.mkdir(parents=True, exist_ok=True)
    _state["dir"] = path


def forget_loaded() -> None:
    """Forget the exported programs loaded in this process (as a new process would
    start); the next call of each looks in :func:`export_dir` again. For tests."""
    for table in _loaded_tables:
        table.clear()


@contextlib.contextmanager
def prefetching(label: str):
    """Inside the block, the exported programs that the last block with the same
    ``label`` used are loaded (and compiled, i.e. read from JAX's persistent cache) by
    two background threads, in the order they were first used, while this thread goes
    on; the ones this block uses are recorded for the next. Loading a program is mostly
    XLA's work, done without the GIL, so a new process overlaps it with its own Python
    work (importing the package, reading the input) and with the programs it already
    runs (on the 2-core CPU, a one-part ``sqparts recover`` has its seven programs
    loaded 1.8 s after start instead of 2.7 s with one thread). A call that needs a
    program not yet being loaded loads it itself; one being loaded is waited for. A
    program loaded and never used costs only background time; results never depend on
    what was loaded. A plain block when exporting is off."""
    directory = export_dir()
    if directory is None:
        yield
        return
    manifest = directory / f"{label}.programs"
    try:
        names = [n for n in manifest.read_text().split() if Path(n).name == n and n.endswith(".jaxexport")]
    except (OSError, UnicodeDecodeError):
        names = []
    pool = ThreadPoolExecutor(2, thread_name_prefix="sqparts-prefetch")
    for name in names:
        if name not in _prefetched:
            _prefetched[name] = pool.submit(_load, directory / name)
    used: dict[str, None] = {}
    _records.append(used)
    try:
        yield
    finally:
        _records.remove(used)
        # What has not started loading never will; the one loading finishes before the
        # process may exit (XLA must not be torn down under it).
        pool.shutdown(wait=True, cancel_futures=True)
        for name in names:
            _prefetched.pop(name, None)
    if used and list(used) != names:
        with contextlib.suppress(OSError):
            fd, tmp = tempfile.mkstemp(dir=directory, prefix=".tmp-", suffix=".programs")
            with os.fdopen(fd, "w") as f:
                f.write("\n".join(used) + "\n")
            os.replace(tmp, manifest)


def _take_prefetched(entry: str, avals):
    """The runner :func:`prefetching` loaded for ``entry`` (waiting while it loads), or
    ``None`` when it was not asked for, not started yet (then never), not loadable or
    not for these arguments."""
    future = _prefetched.pop(entry, None)
    if future is None or future.cancel():
        return None
    runner = future.result()
    if runner is not None and getattr(runner, "shapes", None) != _shapes(avals):
        _log.warning("sqparts: ignoring exported program %s (argument shapes or dtypes differ)", entry)
        return None
    return runner


def _shapes(avals) -> list:
    return [(a.shape, a.dtype) for a in avals]


def export_dir() -> Path | None:
    """The folder exported programs go to, or ``None`` when exporting is off."""
    if os.environ.get("SQPARTS_EXPORT", "1").strip().lower() in ("0", "false", "no", "off"):
        return None
    return _state["dir"] if _serializable() else None


@functools.lru_cache(maxsize=1)
def _serializable() -> bool:
    """Whether ``jax.export`` can serialize here (it needs the ``flatbuffers`` package)."""
    try:
        import flatbuffers  # noqa: F401
    except ImportError:
        _log.warning("sqparts: the flatbuffers package is missing; programs are not exported")
        return False
    return True


@functools.lru_cache(maxsize=1)
def _environment_key() -> str:
    """JAX/jaxlib versions, backend, device count and a hash of this package's source."""
    import jaxlib.version

    h = hashlib.sha256()
    for f in sorted(Path(__file__).resolve().parent.rglob("*.py")):
        h.update(f.name.encode())
        h.update(f.read_bytes())
    dev = jax.devices()
    return "|".join(
        [
            jax.__version__,
            jaxlib.version.__version__,
            jax.default_backend(),
            dev[0].device_kind,
            str(len(dev)),
            str(jax.config.read("jax_enable_x64")),
            h.hexdigest(),
        ]
    )


def _aval(x) -> jax.ShapeDtypeStruct:
    a = jax.typeof(x)
    return jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type)


class _Skeleton:
    """Stands for a leaf in a pickled output tree (pickles of PyTreeDefs of equinox
    Modules do not unflatten)."""


def persistent_jit(fun=None, *, static_argnames=()):
    """``jax.jit(fun, static_argnames=...)`` whose programs are exported to, and loaded
    from, :func:`export_dir` (see the module docstring). Same arguments, same results."""
    if fun is None:
        return functools.partial(persistent_jit, static_argnames=static_argnames)
    static_argnames = (static_argnames,) if isinstance(static_argnames, str) else tuple(static_argnames)
    jitted = jax.jit(fun, static_argnames=static_argnames)
    signature = inspect.signature(fun)
    loaded: dict[str, Callable | None] = {}  # key -> callable on the flat leaves, or None (use jitted)
    _loaded_tables.append(loaded)
    lock = threading.Lock()
    name = getattr(fun, "__qualname__", getattr(fun, "__name__", "fun"))
    stem = f"{fun.__module__.rsplit('.', 1)[-1]}.{name}"

    @functools.wraps(fun)
    def call(*args, **kwargs):
        directory = export_dir()
        if directory is None or jax.device_count() != 1:
            return jitted(*args, **kwargs)
        bound = signature.bind(*args, **kwargs)
        bound.apply_defaults()
        static = {k: v for k, v in bound.arguments.items() if k in static_argnames}
        dynamic = {k: v for k, v in bound.arguments.items() if k not in static_argnames}
        leaves, tree = jax.tree_util.tree_flatten(dynamic)
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            return jitted(*args, **kwargs)
        avals = [_aval(x) for x in leaves]
        text = "\n".join(
            [
                _environment_key(),
                fun.__module__,
                name,
                repr(sorted(static.items())),
                str(tree),
                repr([(a.shape, str(a.dtype), a.weak_type) for a in avals]),
            ]
        )
        if " at 0x" in text:  # an object's default repr: not the same in another process
            return jitted(*args, **kwargs)
        key = hashlib.sha256(text.encode()).hexdigest()[:32]
        entry = f"{stem}-{key}.jaxexport"
        for used in _records:
            used.setdefault(entry)
        runner = loaded.get(key)
        if runner is None and key not in loaded:
            with lock:  # threads meeting a new signature together (concurrently): one export
                if key not in loaded:
                    path = directory / entry
                    loaded[key] = (
                        _take_prefetched(entry, avals) or _load(path, avals) or _export(path, fun, static, tree, avals)
                    )
                runner = loaded[key]
        if runner is None:
            return jitted(*args, **kwargs)
        try:
            return runner(leaves)
        except Exception as e:  # noqa: BLE001 - e.g. an entry this JAX cannot compile: jit it
            _log.warning("sqparts: exported %s failed (%s: %s); using jit", name, type(e).__name__, e)
            loaded[key] = None
            return jitted(*args, **kwargs)

    setattr(call, "jitted", jitted)  # noqa: B010 (a function attribute pyright accepts this way)
    return call


class _Runner:
    """An exported program compiled (or read from JAX's persistent cache), called on the
    flat leaves; ``shapes`` are its arguments' shapes and dtypes."""

    def __init__(self, exported, out_skeleton):
        self.out_tree = jax.tree_util.tree_structure(out_skeleton, is_leaf=lambda x: isinstance(x, _Skeleton))
        if self.out_tree.num_leaves != len(exported.out_avals):
            raise ValueError("output tree does not match the exported program")
        self.shapes = _shapes(exported.in_avals)
        self.compiled = jax.jit(exported.call).lower(*exported.in_avals).compile()

    def __call__(self, leaves):
        return jax.tree_util.tree_unflatten(self.out_tree, self.compiled(*leaves))


def _load(path: Path, avals=None):
    """The runner stored at ``path``, or ``None`` (missing, corrupt or stale entry);
    ``avals``, when given, must be its arguments' shapes and dtypes."""
    try:
        blob = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as e:
        _log.warning("sqparts: cannot read exported program %s (%s); tracing instead", path, e)
        return None
    try:
        if not blob.startswith(_MAGIC):
            raise ValueError("not an sqparts export")
        digest, payload = blob[len(_MAGIC) : len(_MAGIC) + 32], blob[len(_MAGIC) + 32 :]
        if hashlib.sha256(payload).digest() != digest:
            raise ValueError("checksum mismatch")
        serialized, out_skeleton = pickle.loads(payload)
        exported = jax.export.deserialize(bytearray(serialized))
        if avals is not None and _shapes(exported.in_avals) != _shapes(avals):
            raise ValueError("argument shapes or dtypes differ")
        return _Runner(exported, out_skeleton)
    except Exception as e:  # noqa: BLE001 - any bad entry: trace again, never fail
        _log.warning("sqparts: ignoring exported program %s (%s: %s); tracing instead", path, type(e).__name__, e)
        return None


def _export(path: Path, fun, static, tree, avals):
    """Export ``fun`` for these arguments, store it at ``path`` and return its runner;
    ``None`` (use the plain jit) if it cannot be exported."""
    out = {}

    def flat(*leaves):
        result = fun(**jax.tree_util.tree_unflatten(tree, leaves), **static)
        out_leaves, out["tree"] = jax.tree_util.tree_flatten(result)
        return out_leaves

    try:
        exported = jax.export.export(jax.jit(flat))(*avals)
        skeleton = jax.tree_util.tree_unflatten(out["tree"], [_Skeleton() for _ in range(out["tree"].num_leaves)])
        payload = pickle.dumps((bytes(exported.serialize()), skeleton), protocol=pickle.HIGHEST_PROTOCOL)
        runner = _Runner(exported, skeleton)
    except Exception as e:  # noqa: BLE001 - not exportable: plain jit
        _log.warning("sqparts: cannot export %s (%s: %s); using jit", path.name, type(e).__name__, e)
        return None
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".jaxexport")
        with os.fdopen(fd, "wb") as f:
            f.write(_MAGIC + hashlib.sha256(payload).digest() + payload)
        os.replace(tmp, path)
    except OSError as e:
        _log.warning("sqparts: cannot store exported program %s (%s)", path, e)
    return runner
