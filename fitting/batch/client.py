"""Fit many photos (faces) or targets (bodies) on a Dask cluster: ``fit_many(inputs, out_dir)``.

The items (fitting.batch_items: plain data, the photo's path, its landmark or joints file or
None, its options, its output folder's name) each become one task of fitting.batch_task's
:func:`run_item` on a worker, which skips a finished item, else fits it and publishes its folder
whole, and returns a row. A worker that dies (kill -9, out of memory) loses its task; the
scheduler gives it to another worker (Dask's allowed-failures, 3 by default).

The client side (:func:`fit_many`) submits every item, writes results.csv and results.jsonl as
rows arrive (softras_cl.fitting.reports.batch), shows a progress bar, and on Ctrl-C cancels the
work in flight, keeps every finished item and writes the table and summary.png before it
returns with ``interrupted=True``. Without a client it starts a ``distributed.LocalCluster`` of
worker processes, no more than the items and the cores (:func:`split_cores`), with the OpenCL
(PoCL) threads of each worker set so that workers x threads <= cores (:func:`worker_env`).
OpenCL programs are built once per worker process and reused (softras_cl.cl.program caches
them per context, the context is cached per process), as are the models
(fitting.model_cache).

Needs the ``batch`` extra (dask[distributed]); docs/batch.md is the user's guide. The
single-photo commands do not import this module.
"""
from __future__ import annotations

import contextlib
import logging
import os
import uuid
from dataclasses import dataclass, field, replace
from pathlib import Path

from softras_cl.errors import InputError, ResourceError
from softras_cl.fitting.batch_items import Item, check_names, collect_items
from softras_cl.fitting.batch_task import describe, face_numbers, make_row, run_item
from softras_cl.io.outputs import OutputFolder

__all__ = ["BatchResult", "fit_many", "run_items", "expand_faces", "worker_env", "local_cluster",
           "split_cores", "import_distributed", "worker_plugin"]

logger = logging.getLogger(__name__)


@dataclass
class BatchResult:
    """What :func:`fit_many` returns: rows (list of dict, one per item, in input order; see
    run_item), interrupted (Ctrl-C stopped the run), out (the batch folder, Path)."""
    rows: list
    interrupted: bool
    out: Path
    counts: dict = field(default_factory=dict)

    @property
    def failed(self) -> list:
        return [r for r in self.rows if r["status"] == "failed"]


def expand_faces(client, items: list[Item]) -> list[Item]:
    """With all faces: each face item with detected landmarks -> one item per face found whose
    landmarks form a face, named NAME-faceN by the face's number N (0: the largest); found on
    the workers."""
    face_items = [it for it in items if it.kind == "face"]
    numbers = dict(zip(face_items, client.gather(client.map(face_numbers, face_items, pure=False))))
    out = []
    for item in items:
        found = numbers.get(item, [])
        out += ([item] if not found else
                [replace(item, name=f"{item.name}-face{k}", face=k, all_faces=True) for k in found])
    check_names(out)
    return out


# ---------------------------------------------------------------------------------------------
# the cluster

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
def _client(client, scheduler, workers, threads, items):
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


# ---------------------------------------------------------------------------------------------
# the client side

def fit_many(inputs, out_dir, kind: str = "face", options: dict | None = None, *, client=None,
             scheduler: str | None = None, workers: int | None = None, threads_per_worker: int | None = None,
             all_faces: bool = False, retries: int = 2, progress: bool = True,
             task=run_item, task_args: tuple = (), label: str | None = None) -> BatchResult:
    """Fit every item into its folder under ``out_dir``; returns a BatchResult.

    inputs: Items, or photo paths / folders / glob patterns (turned into items with
    ``options``, see collect_items). client: a distributed.Client to use; else ``scheduler``
    (tcp://HOST:PORT of a running Dask scheduler whose workers see the same files); else a
    LocalCluster of ``workers`` processes with ``threads_per_worker`` OpenCL threads each
    (split_cores). all_faces: fit every detected face of a photo whose landmarks are detected.
    retries: Dask retries of a task that raised (a failed fit is a row, not a raise).
    ``out_dir`` is locked while the batch runs; it receives one folder per item, results.csv,
    results.jsonl and summary.png. Ctrl-C cancels what is in flight and returns with
    ``interrupted=True`` after writing the table and the summary. task(item, out_dir, *task_args)
    -> row: what runs on a worker (default run_item; track-face's videos: their own); label: the
    command named in the output folder's lock (default "fit-KIND (batch)").
    """
    from softras_cl.interrupts import first_interrupt_calls
    from softras_cl.fitting.reports.batch import ResultsTable

    items = [it if isinstance(it, Item) else None for it in inputs]
    if None in items:
        items = collect_items(inputs, kind, options)
    with OutputFolder(out_dir, label or f"fit-{kind} (batch)", "--out") as folder:
        table = None
        known = None if all_faces else len(items)       # all faces: counted on the workers
        try:
            with _client(client, scheduler, workers, threads_per_worker, known) as c:
                if all_faces:
                    items = expand_faces(c, items)
                table = ResultsTable(folder.path, items)
                interrupted = run_items(c, items, table, retries, progress, task, task_args)
        except KeyboardInterrupt:       # before the items ran, or again while the cluster closed
            if table is None:
                raise
            interrupted = True
        with first_interrupt_calls(lambda signum: None):      # another Ctrl-C stops at once
            table.finish(interrupted)       # after the local workers stopped: the table is final
        return BatchResult(table.rows(), interrupted, folder.path, table.counts())


def run_items(client, items: list[Item], table, retries: int = 2, progress: bool = True,
              task=run_item, task_args: tuple = ()) -> bool:
    """Submit one ``task(item, out, *task_args)`` (default run_item) per item and add the rows to
    ``table`` (a ResultsTable) as they arrive; on Ctrl-C cancel the rest. Returns whether the
    run was interrupted."""
    token = uuid.uuid4().hex[:8]
    out = str(table.out.resolve())
    futures = {client.submit(task, item, out, *task_args, key=f"fit-{item.name}-{token}",
                             retries=retries, pure=False): item for item in items}
    try:
        _collect(futures, table, progress)
    except KeyboardInterrupt:
        client.cancel(list(futures), force=True)
        return True
    return False


def _collect(futures: dict, table, progress: bool) -> None:
    from distributed import as_completed
    from tqdm import tqdm

    with tqdm(total=len(futures), unit="item", desc="fit", disable=not progress, smoothing=0.1) as bar:
        for future in as_completed(futures):
            table.add(_row_of(future, futures[future]))
            bar.update(1)
            bar.set_postfix(table.counts(), refresh=False)


def _row_of(future, item: Item) -> dict:
    """The task's row, or a failed row when the task itself failed (e.g. its workers died)."""
    if future.status == "finished":
        return future.result()
    try:
        error = future.exception()
    except Exception as e:              # cancelled
        error = e
    if type(error).__name__ == "KilledWorker":
        error = RuntimeError("the workers fitting it died (killed, or out of memory) too often")
    return make_row(item, "failed", error=describe(error))
