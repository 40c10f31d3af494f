"""The batch's Dask side (``pip install "sqparts[distributed]"``): a local cluster of
worker processes, the worker set-up, and the records as the tasks complete.

Imported only when a batch runs on a cluster, so that sqparts itself does not need Dask.
"""

from __future__ import annotations

import contextlib
import logging
import os

from distributed import Client, LocalCluster, WorkerPlugin, as_completed

from ._batch import _run_on_worker, enable_compilation_cache, error_message


class WorkerSetup(WorkerPlugin):
    """Runs once in each worker: JAX's persistent compilation cache on
    (``$SQPARTS_CACHE_DIR`` as the worker sees it, default ``~/.cache/sqparts/jax``),
    and SIGINT ignored (Ctrl-C reaches the whole process group; the caller decides how a
    batch stops). The task function turns the cache on too, for workers that refuse
    plugins."""

    idempotent = True
    name = "sqparts-worker-setup"

    def setup(self, worker):
        import signal

        with contextlib.suppress(ValueError):  # not the main thread: leave signals alone
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        enable_compilation_cache()


def run_on_cluster(tasks, client: Client):
    """Submit every task to ``client``'s workers; yield the records in completion order.
    A task lost with its worker becomes an error record; stopping early cancels the rest."""
    with contextlib.suppress(Exception):  # a cluster that refuses plugins still works
        client.register_plugin(WorkerSetup(), name=WorkerSetup.name)
    token = os.urandom(4).hex()
    keys = [f"sqparts-recover-{token}-{i}" for i in range(len(tasks))]
    futures = dict(zip(client.map(_run_on_worker, list(tasks), key=keys, pure=False), tasks))
    try:
        for future in as_completed(list(futures)):
            task = futures.pop(future)
            try:
                record = future.result()
            except Exception as e:  # noqa: BLE001  (a worker lost, a pickling error: recorded)
                record = task.record("error", seconds=0.0, error=error_message(e))
            yield record
    finally:
        if futures:
            with contextlib.suppress(Exception):
                client.cancel(list(futures))


@contextlib.contextmanager
def local_cluster(workers: int):
    """A ``LocalCluster`` of ``workers`` processes with one thread each; yields its client."""
    cluster = LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,  # pyright: ignore[reportArgumentType]  (None = no dashboard, as distributed documents)
        # Every failure a user needs reaches them as an error record; what distributed logs
        # besides is its own shutdown races (a worker's heartbeat to a scheduler that is
        # closing), printed as tracebacks.
        silence_logs=logging.CRITICAL,
    )
    try:
        with Client(cluster) as client:
            yield client
    finally:
        cluster.close()


@contextlib.contextmanager
def connect(address: str):
    """A client of the running Dask scheduler at ``address``; one line if it cannot connect."""
    try:
        client = Client(address, timeout="10s")
    except (OSError, TimeoutError, ValueError) as e:
        raise ValueError(
            f"--scheduler: got {address!r} ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}), "
            "expected the address of a running Dask scheduler (tcp://HOST:8786)"
        ) from None
    with client:
        yield client
