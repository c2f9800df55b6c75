"""The task of one batch item, on a worker (:func:`run_item`): skip it when finished, else fit
it and publish its folder whole.

1. the item's run record (fitting.run_records: the same record ``softras-cl fit-face``/
   ``fit-body`` write to run.json);
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

from softras_cl.errors import InputError, ResultError, SoftrasError
from softras_cl.fitting.batch_items import Item
from softras_cl.fitting.metrics import finite_metrics
from softras_cl.fitting.model_cache import load_model
from softras_cl.fitting.run_options import BODY, FITS
from softras_cl.fitting.run_records import body_record, completed, face_landmarks_source, face_record
from softras_cl.io.outputs import LOCK_NAME, OutputFolder, json_safe

__all__ = ["run_item", "item_record", "item_config", "make_row", "describe", "face_numbers", "body_inputs",
           "publish", "fit_into"]

logger = logging.getLogger(__name__)

FACE_REQUIRED = ("landmark_error_px_full", "psnr_face_db")
PARTIAL = ".{}.partial"       # the temporary folder of item NAME, beside OUT/NAME
OLD = ".{}.old"               # where a replaced OUT/NAME goes for the instant of the swap


def item_record(item: Item) -> dict:
    """The run record of an item (see face_record, body_record)."""
    if item.kind == "face":
        return face_record(item.photo, face_landmarks_source(item.photo, item.landmarks, item.face),
                           item.opts)
    return body_record(item.photo, item.landmarks, item.opts)


def item_config(item: Item):
    """The fit's config of an item (FaceFitConfig, BodyFitConfig): the same as the single-photo
    command makes of the same options."""
    return FITS[item.kind].config(item.opts)


def face_points(item: Item):
    """The item's face landmarks, a fitting.detection.PhotoLandmarks ((68, 2) float64 .points):
    its file, a file beside the photo, or the detector's face number ``item.face`` (the
    largest when None)."""
    from softras_cl.fitting.detection import resolve_landmarks

    if not item.all_faces:
        return resolve_landmarks(item.photo, item.landmarks, face=item.face)[0]
    found = [f for f in resolve_landmarks(item.photo, item.landmarks, all_faces=True) if f.index == item.face]
    if not found:
        raise InputError(f"face {item.face} of {item.photo} is no longer found among the faces whose "
                         "landmarks form a face")
    return found[0]


def _fit_face(item: Item, folder: Path) -> tuple[dict, float]:
    from softras_cl.io.images import read_image
    from softras_cl.fitting.recipes.face import detected_dense, fit_face
    from softras_cl.fitting.reports.face import write_outputs

    options = item.opts
    photo = read_image(item.photo)[..., :3]
    landmarks = face_points(item)
    model = load_model("face", options.get("model"), options.get("model_landmarks"))
    config = item_config(item)
    start = time.perf_counter()
    fit = fit_face(photo, landmarks.points, model, config, out_dir=folder, progress=False,
                   dense=detected_dense(landmarks.face), detector=landmarks.source)
    seconds = time.perf_counter() - start
    metrics = finite_metrics(fit, folder, FACE_REQUIRED)
    write_outputs(fit, photo, landmarks, folder, metrics=metrics, run_config=dict(fit=config, options=options),
                  extra=dict(photo=item.photo, seconds=seconds, budget=options.get("budget", "default")))
    return metrics, seconds


def body_inputs(item: Item):
    """(target, joints (J, 2) or None, weights (J,) or None, model, BodyFitConfig) of an item."""
    from softras_cl.fitting.body_files import read_joints, read_target

    values = BODY.values(item.opts)
    model = load_model("body", values["model"])
    target = read_target(item.photo, values["silhouette"] or values["input"] == "mask")
    joints, weights = (None, None) if item.landmarks is None else read_joints(item.landmarks, model.n_joints)
    return target, joints, weights, model, item_config(item)


def _fit_body(item: Item, folder: Path) -> tuple[dict, float]:
    from softras_cl.fitting.recipes.body import fit_body
    from softras_cl.fitting.recipes.body_photo import input_kind
    from softras_cl.fitting.reports.body import write_outputs

    values = BODY.values(item.opts)
    kind = input_kind(item.photo, values["input"], values["silhouette"], item_config(item).background,
                      item.landmarks is not None)
    if kind == "photo":
        return _fit_body_photo(item, folder)
    target, joints, weights, model, config = body_inputs(item)
    start = time.perf_counter()
    fit = fit_body(target, model, config, joints, weights, out_dir=folder, progress=False)
    seconds = time.perf_counter() - start
    required = ("silhouette_iou",) + (("joint_error_px_full",) if joints is not None else ())
    metrics = finite_metrics(fit, folder, required)
    write_outputs(fit, target, folder, metrics=metrics, run_config=dict(fit=config, options=item.opts),
                  extra=dict(target=item.photo, seconds=seconds, budget=item.opts.get("budget", "default")))
    return metrics, seconds


def _fit_body_photo(item: Item, folder: Path) -> tuple[dict, float]:
    """A body item whose target is a photo of a person (fitting.recipes.body_photo)."""
    from softras_cl.fitting.recipes.body_photo import fit_body_photo, read_person
    from softras_cl.fitting.reports.body import write_photo_outputs

    if item.landmarks is not None:
        raise InputError(f"{item.photo}: joints are for part-coloured targets and masks: a photo's keypoints "
                         "are detected")
    values, config = BODY.values(item.opts), item_config(item)
    model = load_model("body", values["model"])
    photo, detection, fov = read_person(item.photo)
    start = time.perf_counter()
    fit = fit_body_photo(photo.shape[:2], detection, model, config, values["budget"], fov, out_dir=folder,
                         progress=False)
    seconds = time.perf_counter() - start
    metrics = finite_metrics(fit, folder, ("silhouette_iou", "keypoint_error_px_full"))
    write_photo_outputs(fit, photo, folder, metrics=metrics, run_config=dict(fit=config, options=item.opts),
                        extra=dict(target=item.photo, input="photo", seconds=seconds, budget=values["budget"]))
    return metrics, seconds


FITTERS = {"face": _fit_face, "body": _fit_body}


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


def fit_into(item: Item, record: dict, final: Path) -> tuple[dict, float]:
    """Fit ``item`` into the temporary folder beside ``final``, then rename it into place.
    Returns (metrics, seconds of the fit).
    A fit that fails on its input leaves nothing; one with a non-finite result (ResultError)
    leaves the temporary folder (its checkpoint and loss curve show what happened) until the
    next attempt."""
    partial = final.with_name(PARTIAL.format(final.name))
    held = False
    try:
        with OutputFolder(partial, f"fit of {item.name}", "item folder") as out:
            held = True
            _empty(partial)
            out.begin(record)
            metrics, seconds = FITTERS[item.kind](item, partial)
            out.finish(dict(status="done", metrics=metrics, seconds=seconds))
    except Exception as error:
        if held and not isinstance(error, ResultError):
            shutil.rmtree(partial, ignore_errors=True)
        raise
    publish(partial, final)
    return metrics, seconds


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
        record = item_record(item)
        done = completed(final, record)
        if done is not None:
            return make_row(item, "skipped", final, done.get("metrics"), done.get("seconds"))
        metrics, seconds = fit_into(item, record, final)
        return make_row(item, "ok", final, metrics, seconds)
    except Exception as error:      # the item failed; the batch goes on
        logger.debug("item %s failed", item.name, exc_info=True)
        return make_row(item, "failed", seconds=time.perf_counter() - start, error=describe(error))


def face_numbers(item: Item) -> list[int]:
    """The numbers of the faces the detector finds in an item whose landmarks are detected,
    those whose landmarks form a face (fitting.detection.ORDER: largest first); [] when its
    landmarks come from a file (or the photo cannot be read: its fit then reports why)."""
    from softras_cl.fitting.detection import landmarks_beside, resolve_landmarks

    if item.landmarks is not None or landmarks_beside(item.photo) is not None:
        return []
    try:
        return [f.index for f in resolve_landmarks(item.photo, None, all_faces=True)]
    except Exception:           # no detector, no face, bad photo: the item's own fit says so
        return []
