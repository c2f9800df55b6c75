"""The task of one batch item, on a worker (:func:`run_item`): skip it when finished, else run
its job (fitting.jobs) and publish its folder whole.

1. the item's job and run record (the same record ``softras-cl fit-face``/``fit-body`` write to
   run.json);
2. if ``OUT/NAME/complete.json`` holds that record, the item is skipped (its metrics are read
   back from complete.json);
3. otherwise it fits into ``OUT/.NAME.partial`` (locked while it runs, emptied first, so what a
   killed attempt left is replaced), writes every output and complete.json last, then renames
   the folder to ``OUT/NAME``. A reader therefore sees a complete item folder or none.

It returns a small row (input, name, status ok/failed/skipped, error, metrics, seconds, output
folder). A bad photo (unreadable, no face, non-finite metrics) is a failed row, not an
exception: the batch goes on.
"""
from __future__ import annotations

import logging
import os
import shutil
import time
from pathlib import Path

from softras_cl.errors import ResultError, SoftrasError
from softras_cl.fitting.batch.items import Item
from softras_cl.fitting.detection import landmarks_beside, resolve_landmarks
from softras_cl.fitting.jobs.body import body_job
from softras_cl.fitting.jobs.face_photo import FacePhotoJob
from softras_cl.fitting.jobs.run import fit_and_write
from softras_cl.fitting.run_records import completed
from softras_cl.io.outputs import LOCK_NAME, OutputFolder, json_safe

__all__ = ["run_item", "item_job", "make_row", "describe", "face_numbers", "publish", "fit_into"]

logger = logging.getLogger(__name__)

PARTIAL = ".{}.partial"       # the temporary folder of item NAME, beside OUT/NAME
OLD = ".{}.old"               # where a replaced OUT/NAME goes for the instant of the swap


def item_job(item: Item):
    """The job of an item (fitting.jobs: FacePhotoJob, BodyPhotoJob, BodyTargetJob), made as
    the single-photo command makes it from the same options."""
    if item.kind == "face":
        return FacePhotoJob(item.photo, item.landmarks, item.opts, face=item.face, all_faces=item.all_faces)
    return body_job(item.photo, item.landmarks, item.opts)


def _empty(folder: Path) -> None:
    """Remove what a killed attempt left in ``folder`` (all but the lock file)."""
    for path in folder.iterdir():
        if path.name == LOCK_NAME:
            continue
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()


def publish(partial: Path, final: Path) -> None:
    """Rename the finished ``partial`` folder to ``final``, replacing an older ``final``."""
    old = final.with_name(OLD.format(final.name))
    shutil.rmtree(old, ignore_errors=True)
    if final.exists():
        os.replace(final, old)
    os.replace(partial, final)
    shutil.rmtree(old, ignore_errors=True)


def fit_into(item: Item, job, record: dict, final: Path) -> tuple[dict, float]:
    """Run ``job`` (the item's) into the temporary folder beside ``final``, then rename it into
    place. Returns (metrics, seconds of the fit). A fit that fails on its input leaves nothing;
    one with a non-finite result (ResultError) leaves the temporary folder (its checkpoint and
    loss curve show what happened) until the next attempt."""
    partial = final.with_name(PARTIAL.format(final.name))
    held = False
    try:
        with OutputFolder(partial, f"fit of {item.name}", "item folder") as out:
            held = True
            _empty(partial)
            out.begin(record)
            run = fit_and_write(job, out, progress=False, resume=False)
    except Exception as error:
        if held and not isinstance(error, ResultError):
            shutil.rmtree(partial, ignore_errors=True)
        raise
    publish(partial, final)
    return run.metrics, run.seconds


def describe(error: BaseException) -> str:
    """One line about an item's error: the message (with the class for unexpected ones)."""
    text = str(error).strip().splitlines()[0] if str(error).strip() else ""
    if isinstance(error, (SoftrasError, ValueError, OSError, MemoryError)) and text:
        return text
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def make_row(item: Item, status: str, output=None, metrics=None, seconds=None, error="") -> dict:
    """A results row (JSON-able dict): input, name, face, status, error, metrics, seconds, output."""
    return dict(input=item.photo, name=item.name, face=item.face, status=status, error=error,
                metrics=json_safe(metrics or {}), seconds=seconds,
                output=None if output is None else str(output))


def run_item(item: Item, out_dir: str) -> dict:
    """The task of one item (runs on a worker): skip when complete, else fit and publish.
    Returns a row (see make_row); every error of the item becomes a failed row."""
    start = time.perf_counter()
    final = Path(out_dir) / item.name
    try:
        job = item_job(item)
        record = job.record()
        done = completed(final, record)
        if done is not None:
            return make_row(item, "skipped", final, done.get("metrics"), done.get("seconds"))
        metrics, seconds = fit_into(item, job, record, final)
        return make_row(item, "ok", final, metrics, seconds)
    except Exception as error:      # the item failed; the batch goes on
        logger.debug("item %s failed", item.name, exc_info=True)
        return make_row(item, "failed", seconds=time.perf_counter() - start, error=describe(error))


def face_numbers(item: Item) -> list[int]:
    """The numbers of the faces the detector finds in an item whose landmarks are detected,
    those whose landmarks form a face (fitting.detection.ORDER: largest first); [] when its
    landmarks come from a file (or the photo cannot be read: its fit then reports why)."""
    if item.landmarks is not None or landmarks_beside(item.photo) is not None:
        return []
    try:
        return [f.index for f in resolve_landmarks(item.photo, None, all_faces=True)]
    except Exception:           # no detector, no face, bad photo: the item's own fit says so
        return []
