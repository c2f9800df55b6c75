"""The Dask cluster that runs a batch's tasks: a local one (:func:`local_cluster`: worker
processes, no more than the items and the cores, :func:`split_cores`, each with its OpenCL (PoCL)
and BLAS threads limited so that workers x threads <= cores, :func:`worker_env`; workers that
never see a terminal's Ctrl-C), or a running scheduler's (:func:`batch_client`).

Needs the ``batch`` extra (dask[distributed]): :func:`import_distributed` says how to install it.
"""
from __future__ import annotations

import contextlib
import logging
import os

from softras_cl.errors import InputError, ResourceError

__all__ = ["split_cores", "worker_env", "worker_plugin", "local_cluster", "import_distributed", "batch_client",
           "STARTUP_SECONDS"]

logger = logging.getLogger(__name__)



def split_cores(workers: int | None, threads: int | None, cores: int | None = None,
                items: int | None = None) -> tuple[int, int]:
    """(workers, OpenCL threads per worker) of a local cluster on ``cores`` cores (default: this
    machine's) for ``items`` items (None: not known yet).

    No more workers than items or cores, no more threads than cores; what is left None fills
    the cores (workers x threads <= cores; both None: one worker per core, one thread each). A
    value given and capped is logged in one line (a warning). InputError for values < 1."""
    cores = cores or os.cpu_count() or 1
    for name, value in (("--workers", workers), ("--threads-per-worker", threads)):
        if value is not None and value < 1:
            raise InputError(f"{name} must be >= 1, got {value}")
    most = min(cores, items or cores)
    n = min(workers, most) if workers is not None else max(1, min(most, cores // (threads or 1)))
    t = min(threads, cores) if threads is not None else max(1, cores // n)
    capped = [f"{name} {given} -> {used}" for name, given, used in
              (("--workers", workers, n), ("--threads-per-worker", threads, t)) if given not in (None, used)]
    if capped:
        counts = f"{cores} cores" if items is None else f"{items} items, {cores} cores"
        logger.warning("%s (%s): a local cluster runs no more workers than items or cores, and no more "
                       "threads than cores", ", ".join(capped), counts)
    if n * t > cores:
        logger.warning("%d workers x %d threads oversubscribe the %d cores", n, t, cores)
    return n, t


def worker_env(threads: int) -> dict:
    """Environment of a worker process: PoCL's CPU device and the BLAS/OpenMP pools limited to
    ``threads`` threads (POCL_MAX_PTHREAD_COUNT for PoCL's pthread device up to PoCL 4,
    POCL_CPU_MAX_CU_NUM for its cpu device from PoCL 5)."""
    n = str(int(threads))
    return dict(POCL_MAX_PTHREAD_COUNT=n, POCL_CPU_MAX_CU_NUM=n, OMP_NUM_THREADS=n,
                OPENBLAS_NUM_THREADS=n, MKL_NUM_THREADS=n)


class _IgnoreInterrupts:
    """Worker plugin: the workers ignore SIGINT; a Ctrl-C in the terminal reaches the whole
    process group, and the client alone decides what stops."""
    name = "softras-cl-ignore-sigint"

    def setup(self, worker=None):
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)


def worker_plugin():
    """The plugin that makes a cluster's workers ignore SIGINT (register it on a client)."""
    from distributed.diagnostics.plugin import WorkerPlugin

    return type("IgnoreInterrupts", (_IgnoreInterrupts, WorkerPlugin), {})()


@contextlib.contextmanager
def _sigint_blocked():
    """SIGINT blocked in the calling (main) thread, and so in the threads it starts meanwhile and
    in the processes those threads spawn (the signal mask is inherited): a local cluster's
    workers never see a terminal's Ctrl-C, from their first instruction on. Unblocked on the
    way out, when a Ctrl-C that came meanwhile raises KeyboardInterrupt.

    multiprocessing's resource tracker is started first: starting it later, from a thread of
    the cluster, would unblock SIGINT in that thread."""
    import signal
    import threading

    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        yield
        return
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


STARTUP_SECONDS = 120.0     # default bound on a local cluster's start (its workers up)


def local_cluster(workers: int, threads: int, startup_seconds: float = STARTUP_SECONDS):
    """A started distributed.LocalCluster of ``workers`` processes, one task at a time each, with
    ``threads`` OpenCL threads (worker_env), whose workers never see a terminal's SIGINT.

    ResourceError when the workers are not all up within ``startup_seconds``; Ctrl-C while
    they start closes the cluster and raises KeyboardInterrupt (the wait stays interruptible:
    the scheduler starts first, the workers are then added while this thread waits).

    The workers start without Dask's default MALLOC_TRIM_THRESHOLD_=65536: with it, every numpy
    array above 64 KiB is a fresh mmap whose pages fault in again, and a face fit took 2.1x as
    long in a worker as in a plain process (5.5-5.9 s against 2.2-2.7 s at 64 px).
    """
    import dask
    from distributed import LocalCluster

    environ = {k: v for k, v in dask.config.get("distributed.nanny.pre-spawn-environ").items()
               if k != "MALLOC_TRIM_THRESHOLD_"}
    cluster = None
    try:
        with dask.config.set({"distributed.worker.daemon": False,       # read as each worker spawns
                              "distributed.nanny.pre-spawn-environ": environ}):
            with _sigint_blocked():
                cluster = LocalCluster(n_workers=0, threads_per_worker=1, processes=True,
                                       env=worker_env(threads), dashboard_address=None,
                                       silence_logs=logging.CRITICAL)
            cluster.scale(workers)
            cluster.wait_for_workers(workers, timeout=startup_seconds)
    except BaseException as error:
        if cluster is not None:
            cluster.close(timeout=30)
        if isinstance(error, TimeoutError):
            raise ResourceError(f"the local Dask cluster did not start its {workers} workers within "
                                f"{startup_seconds:g} s (a loaded machine? try fewer --workers)") from None
        raise
    return cluster


def import_distributed():
    """The distributed module; InputError saying how to install it when it is missing."""
    try:
        import distributed
    except ImportError as e:
        raise InputError('fitting many photos needs Dask: pip install "softras-cl[batch]"') from e
    return distributed


@contextlib.contextmanager
def batch_client(client, scheduler, workers, threads, items):
    """The Dask client to use: the caller's, one of a scheduler address, or a new LocalCluster's
    for ``items`` items (None: not known yet; closed on the way out)."""
    distributed = import_distributed()
    if client is not None:
        yield client
        return
    if scheduler is not None:
        with distributed.Client(scheduler, timeout="20s") as c:
            yield c
        return
    n, t = split_cores(workers, threads, items=items)
    with local_cluster(n, t) as cluster, distributed.Client(cluster) as c:
        c.register_plugin(worker_plugin())
        yield c
