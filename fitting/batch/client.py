"""Fit many photos (faces) or targets (bodies) on a Dask cluster: ``fit_many(inputs, out_dir)``.

The items (fitting.batch.items: plain data, the photo's path, its landmark or joints file or
None, its options, its output folder's name) each become one task of fitting.batch.tasks'
:func:`run_item` on a worker, which skips a finished item, else runs its job (fitting.jobs) and
publishes its folder whole, and returns a row. A worker that dies (kill -9, out of memory) loses
its task; the scheduler gives it to another worker (Dask's allowed-failures, 3 by default).

The client side (:func:`fit_many`) submits every item, writes results.csv and results.jsonl as
rows arrive (fitting.batch.results), shows a progress bar, and on Ctrl-C cancels the work in
flight, keeps every finished item and writes the table and summary.png before it returns with
``interrupted=True``. Without a client it starts a local cluster (fitting.batch.cluster). OpenCL
programs are built once per worker process and reused (softras_cl.cl.program caches them per
context, the context is cached per process), as are the models (fitting.model_cache).

Needs the ``batch`` extra (dask[distributed]); docs/batch.md is the user's guide. The
single-photo commands do not import this module.
"""
from __future__ import annotations

import uuid
from dataclasses import dataclass, field, replace
from pathlib import Path

from softras_cl.fitting.batch.cluster import batch_client
from softras_cl.fitting.batch.items import Item, check_names, collect_items
from softras_cl.fitting.batch.tasks import describe, face_numbers, make_row, run_item
from softras_cl.io.outputs import OutputFolder

__all__ = ["BatchResult", "fit_many", "run_items", "expand_faces"]


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
    from softras_cl.fitting.batch.results import ResultsTable

    items = [it if isinstance(it, Item) else None for it in inputs]
    if None in items:
        items = collect_items(inputs, kind, options)
    with OutputFolder(out_dir, label or f"fit-{kind} (batch)", "--out") as folder:
        table = None
        known = None if all_faces else len(items)       # all faces: counted on the workers
        try:
            with batch_client(client, scheduler, workers, threads_per_worker, known) as c:
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
