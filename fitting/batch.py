"""Fit many photos (faces) or targets (bodies) on a Dask cluster: ``fit_many(inputs, out_dir)``.

An item is plain data (:class:`Item`: the photo's path, its landmark or joints file or None,
its options, its output folder's name). One task per item runs :func:`run_item` on a worker:

1. it computes the item's run record (a SHA-256 of each input file and the options that change
   the fit: the same record ``softras-cl fit-face``/``fit-body`` write to run.json);
2. if ``OUT/NAME/complete.json`` holds that record, the item is skipped (its metrics are read
   back from complete.json);
3. otherwise it fits into ``OUT/.NAME.partial`` (locked while it runs, emptied first, so what a
   killed attempt left is replaced), writes every output and complete.json last, then renames
   the folder to ``OUT/NAME``. A reader therefore sees a complete item folder or none.

It returns a small row (input, name, status ok/failed/skipped, error, metrics, seconds, output
folder). A bad photo (unreadable, no face, non-finite metrics) is a failed row, not an
exception: the run goes on. A worker that dies (kill -9, out of memory) loses its task; the
scheduler gives it to another worker (Dask's allowed-failures, 3 by default).

The client side (:func:`fit_many`) submits every item, writes results.csv and results.jsonl as
rows arrive (softras_cl.fitting.reports.batch), shows a progress bar, and on Ctrl-C cancels the
work in flight, keeps every finished item and writes the table and summary.png before it
returns with ``interrupted=True``. Without a client it starts a ``distributed.LocalCluster`` of
worker processes with the OpenCL (PoCL) threads of each worker set so that workers x threads
<= cores (:func:`worker_env`). OpenCL programs are built once per worker process and reused
(softras_cl.cl.program caches them per context, the context is cached per process), as are the
models (:func:`load_model`).

Needs the ``batch`` extra (dask[distributed]); docs/batch.md is the user's guide.
"""
from __future__ import annotations

import contextlib
import csv
import functools
import glob
import json
import logging
import os
import shutil
import time
import uuid
from dataclasses import dataclass, field, replace
from pathlib import Path

from softras_cl.errors import InputError, ResultError, SoftrasError
from softras_cl.fitting.metrics import finite_metrics
from softras_cl.io.outputs import (COMPLETE_RECORD, LOCK_NAME, OutputFolder, file_sha256, json_safe)

__all__ = ["Item", "BatchResult", "KINDS", "FACE_OPTIONS", "BODY_OPTIONS", "collect_items",
           "read_manifest", "face_record", "body_record", "item_record", "run_item", "fit_many",
           "worker_env", "local_cluster", "split_cores", "IMAGE_SUFFIXES"]

logger = logging.getLogger(__name__)

KINDS = ("face", "body")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
# option name -> type, per kind: what changes a fit (the run record's "options") plus the model
# files (the record's "inputs"); the defaults are the commands' defaults
FACE_OPTIONS = dict(budget=str, size=int, photo_weight=float, focal=float, n_id=int, n_exp=int,
                    n_albedo=int, model=str, model_landmarks=str)
BODY_OPTIONS = dict(silhouette=bool, background=str, budget=str, size=int, distance=float,
                    height=float, fov=float, robust_joints=float, model=str)
FACE_DEFAULTS = dict(budget="default", size=256)
FACE_REQUIRED = ("landmark_error_px_full", "psnr_face_db")
PARTIAL = ".{}.partial"       # the temporary folder of item NAME, beside OUT/NAME
OLD = ".{}.old"               # where a replaced OUT/NAME goes for the instant of the swap


@dataclass(frozen=True)
class Item:
    """One fit of a batch (plain data, sent to a worker).

    kind: "face" or "body"; photo: the photo (face) or target image (body) path, str; name:
    the output folder's name under the batch's folder; landmarks: the face's 68-landmark file
    or the body's 2D joints file, or None (face: a file beside the photo, else the detector);
    face: with all faces, the index of the detected face (0 = largest), else None; options:
    (name, value) pairs of FACE_OPTIONS/BODY_OPTIONS (missing: the command's default).
    """
    kind: str
    photo: str
    name: str
    landmarks: str | None = None
    face: int | None = None
    options: tuple = ()

    @property
    def opts(self) -> dict:
        return dict(self.options)


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


# ---------------------------------------------------------------------------------------------
# items: paths, folders, globs, a manifest; stable names

def _is_photo(path: Path, kind: str) -> bool:
    suffixes = IMAGE_SUFFIXES + ((".npy",) if kind == "body" else ())
    return path.is_file() and path.suffix.lower() in suffixes and not path.name.startswith(".")


def _folder_photos(folder: Path, kind: str) -> list[Path]:
    """The photos of a folder (not its subfolders), sorted by name, without the drawings of
    another photo's landmarks (``X_landmarks.png`` beside a photo ``X.*``, as
    `softras-cl detect-landmarks --overlay` and examples/data have them)."""
    photos = sorted(p for p in folder.iterdir() if _is_photo(p, kind))
    stems = {p.stem for p in photos}
    return [p for p in photos if not (p.stem.endswith("_landmarks") and p.stem[:-10] in stems)]


def expand_paths(inputs, kind: str = "face") -> list[Path]:
    """Photos named by ``inputs`` (files, folders, glob patterns), in the order given, each once.
    InputError when an input names nothing."""
    photos: list[Path] = []
    for text in map(str, inputs):
        path = Path(text)
        if path.is_dir():
            found = _folder_photos(path, kind)
        elif path.is_file():
            found = [path]
        elif glob.has_magic(text):
            found = [Path(p) for p in sorted(glob.glob(text)) if _is_photo(Path(p), kind)]
        else:
            raise InputError(f"photo not found: {text}")
        if not found:
            raise InputError(f"no photos in {text} (looked for {', '.join(IMAGE_SUFFIXES)})")
        photos += [p for p in found if p not in photos]
    return photos


def _parse_option(kind: str, name: str, text: str):
    types = FACE_OPTIONS if kind == "face" else BODY_OPTIONS
    key = name.strip().replace("-", "_")
    if key not in types:
        raise InputError(f"manifest column {name!r} is not an option of fit-{kind} "
                         f"(options: {', '.join(sorted(types))})")
    if types[key] is bool:
        if text.strip().lower() not in ("1", "0", "true", "false", "yes", "no"):
            raise InputError(f"manifest column {name!r}: expected true/false, got {text!r}")
        return key, text.strip().lower() in ("1", "true", "yes")
    try:
        return key, types[key](text.strip())
    except ValueError:
        raise InputError(f"manifest column {name!r}: {text!r} is not a {types[key].__name__}") from None


def read_manifest(path, kind: str = "face") -> list[dict]:
    """A CSV manifest -> list of dict(photo=Path, landmarks=Path or None, name=str or None,
    options=dict). Columns: photo (or target), optional landmarks (or joints) and name, and
    any option of FACE_OPTIONS/BODY_OPTIONS (dashes or underscores); an empty cell takes the
    command's value. Relative paths are relative to the manifest's folder."""
    path = Path(path)
    try:
        with open(path, newline="") as f:
            table = list(csv.DictReader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise InputError(f"cannot read manifest {path}: {e}") from e
    if not table:
        raise InputError(f"manifest {path} has no rows")
    return [_manifest_row(path, i + 2, row, kind) for i, row in enumerate(table)]


def _manifest_row(path: Path, line: int, row: dict, kind: str) -> dict:
    row = {(k or "").strip().lower(): (v or "").strip() for k, v in row.items()}
    photo = row.pop("photo", "") or row.pop("target", "")
    if not photo:
        raise InputError(f"manifest {path} line {line}: no photo (a 'photo' column is required)")
    side = row.pop("landmarks", "") or row.pop("joints", "")
    name = row.pop("name", "") or None
    options = dict(_parse_option(kind, k, v) for k, v in row.items() if v)
    for key in ("model", "model_landmarks"):
        if key in options:
            options[key] = str(path.parent / options[key])
    return dict(photo=path.parent / photo, landmarks=(path.parent / side) if side else None,
                name=name, options=options)


def stable_names(photos: list[Path]) -> list[str]:
    """One folder name per photo: its file name without the suffix; photos that would share a
    name get ``-`` and 8 hex digits of a hash of their absolute path appended (stable across
    runs for the same set of photos)."""
    import hashlib

    stems = [p.stem for p in photos]
    names = []
    for p, stem in zip(photos, stems):
        if stems.count(stem) > 1:
            stem += "-" + hashlib.sha1(str(p.resolve()).encode()).hexdigest()[:8]
        names.append(stem)
    return names


def collect_items(inputs=(), kind: str = "face", options: dict | None = None, manifest=None,
                  landmarks=None) -> list[Item]:
    """Items from photos, folders and globs (``inputs``) and/or a CSV ``manifest``; ``options``
    apply to every item (a manifest's cells override them); ``landmarks``: one landmark/joints
    file, allowed with a single photo only. InputError on an empty or inconsistent list."""
    if kind not in KINDS:
        raise InputError(f"kind must be one of {KINDS}, got {kind!r}")
    base = _checked_options(kind, options or {})
    rows = [dict(photo=p, landmarks=None, name=None, options={}) for p in expand_paths(inputs, kind)]
    if manifest is not None:
        rows += read_manifest(manifest, kind)
    if not rows:
        raise InputError("no photos given")
    if landmarks is not None:
        if len(rows) != 1:
            raise InputError("--landmarks/--joints names the file of one photo; for several photos "
                             "put each file beside its photo or in a manifest's landmarks column")
        rows[0]["landmarks"] = Path(landmarks)
    names = stable_names([r["photo"] for r in rows])
    items = [Item(kind, os.path.abspath(r["photo"]), r["name"] or n,
                  None if r["landmarks"] is None else os.path.abspath(r["landmarks"]),
                  options=tuple(sorted({**base, **r["options"]}.items())))
             for r, n in zip(rows, names)]
    check_names(items)
    return items


def _checked_options(kind: str, options: dict) -> dict:
    types = FACE_OPTIONS if kind == "face" else BODY_OPTIONS
    unknown = sorted(set(options) - set(types))
    if unknown:
        raise InputError(f"unknown fit-{kind} options {unknown} (options: {', '.join(sorted(types))})")
    return {k: v for k, v in options.items() if v is not None}


def check_names(items) -> None:
    """InputError when two items would write the same folder or a name is not a plain name."""
    seen: dict[str, str] = {}
    for item in items:
        if not item.name or item.name != Path(item.name).name or item.name.startswith("."):
            raise InputError(f"output name {item.name!r} of {item.photo} must be a plain folder name")
        if item.name in seen:
            raise InputError(f"{item.photo} and {seen[item.name]} would both write into "
                             f"{item.name}/ (give distinct names in the manifest's name column)")
        seen[item.name] = item.photo


# ---------------------------------------------------------------------------------------------
# run records: the same as the single-photo commands'

def _digest(path) -> str | None:
    return None if path is None else file_sha256(path)


def face_landmarks_source(photo, landmarks=None, face: int | None = None) -> str | None:
    """What the run record says about a face's landmarks: the SHA-256 of the file (given, or
    beside the photo), else which detector and face found them."""
    from softras_cl.fitting import landmark_detect as detect

    if landmarks is not None:
        return file_sha256(landmarks)
    beside = detect.landmarks_beside(photo)
    if beside is not None:
        return file_sha256(beside)
    return f"detected by {detect.default_backend() or 'no detector'}, face {face or 0}"


def face_record(photo, landmarks: str | None, options: dict) -> dict:
    """The run record of a face fit: dict(command, inputs (SHA-256 per file), options).
    ``landmarks``: what face_landmarks_source returned."""
    inputs = dict(photo=file_sha256(photo), landmarks=landmarks,
                  model=_digest(options.get("model")), model_landmarks=_digest(options.get("model_landmarks")))
    keys = ("budget", "size", "photo_weight", "focal", "n_id", "n_exp", "n_albedo")
    opts = {k: options.get(k, FACE_DEFAULTS.get(k)) for k in keys}
    return dict(command="fit-face", inputs=inputs, options=opts)


def body_record(target, joints, options: dict) -> dict:
    """The run record of a body fit: dict(command, inputs (SHA-256 per file), options)."""
    from softras_cl.fitting.recipes.body import BodyFitConfig

    d = BodyFitConfig()
    defaults = dict(silhouette=False, background="0,0,0", budget="default", size=d.size,
                    distance=d.distance, height=d.height, fov=d.fov_deg, robust_joints=None)
    inputs = dict(target=file_sha256(target), model=_digest(options.get("model")), joints=_digest(joints))
    return dict(command="fit-body", inputs=inputs,
                options={k: options.get(k, v) for k, v in defaults.items()})


def item_record(item: Item) -> dict:
    """The run record of an item (see face_record, body_record)."""
    if item.kind == "face":
        return face_record(item.photo, face_landmarks_source(item.photo, item.landmarks, item.face),
                           item.opts)
    return body_record(item.photo, item.landmarks, item.opts)


def completed(folder: Path, record: dict) -> dict | None:
    """folder/complete.json when it holds ``record`` (and is a finished run), else None."""
    try:
        doc = json.loads((folder / COMPLETE_RECORD).read_text())
    except (OSError, ValueError):
        return None
    want = json.loads(json.dumps(json_safe(record), default=str))
    if isinstance(doc, dict) and doc.get("status") == "done" and all(doc.get(k) == v for k, v in want.items()):
        return doc
    return None


# ---------------------------------------------------------------------------------------------
# the task on a worker

@functools.lru_cache(maxsize=8)
def load_model(kind: str, path: str | None = None, landmarks: str | None = None):
    """The face or body model (the shipped demo model when ``path`` is None), loaded once per
    process."""
    if kind == "face":
        from softras_cl.fitting.models.face_loaders import load_demo_face_model, load_face_model
        return load_demo_face_model() if path is None else load_face_model(path, landmarks=landmarks)
    from softras_cl.fitting.models.body_loaders import load_body_model, load_demo_body_model
    return load_demo_body_model() if path is None else load_body_model(path)


def face_points(item: Item):
    """(68, 2) float64 landmarks of the item's face: its file, a file beside the photo, or the
    detector (face ``item.face``)."""
    from softras_cl.fitting.landmark_detect import resolve_landmarks

    found = resolve_landmarks(item.photo, item.landmarks, all_faces=item.face is not None)
    k = item.face or 0
    if k >= len(found):
        raise InputError(f"face {k} of {item.photo} is no longer found ({len(found)} faces now)")
    return found[k].points


def face_config(options: dict):
    """FaceFitConfig of an item's options (the command's defaults for the rest)."""
    from softras_cl.fitting.recipes.face import FaceFitConfig

    keys = ("size", "focal", "n_id", "n_exp", "n_albedo")
    changes = {k: options[k] for k in keys if options.get(k) is not None}
    return FaceFitConfig.from_budget(options.get("budget", "default"),
                                     photo_weight=options.get("photo_weight"), **changes)


def _fit_face(item: Item, folder: Path) -> tuple[dict, float]:
    from softras_cl.io.images import read_image
    from softras_cl.fitting.recipes.face import fit_face
    from softras_cl.fitting.reports.face import write_outputs

    options = item.opts
    photo = read_image(item.photo)[..., :3]
    landmarks = face_points(item)
    model = load_model("face", options.get("model"), options.get("model_landmarks"))
    config = face_config(options)
    start = time.perf_counter()
    fit = fit_face(photo, landmarks, model, config, out_dir=folder, progress=False)
    seconds = time.perf_counter() - start
    metrics = finite_metrics(fit, folder, FACE_REQUIRED)
    write_outputs(fit, photo, folder, metrics=metrics, run_config=dict(fit=config, options=options),
                  extra=dict(photo=item.photo, face=item.face, seconds=seconds,
                             budget=options.get("budget", "default")))
    return metrics, seconds


def body_inputs(item: Item):
    """(target, joints (J, 2) or None, weights (J,) or None, model, BodyFitConfig) of an item."""
    from softras_cl.fitting.body_files import parse_background, read_joints, read_target
    from softras_cl.fitting.recipes.body import BodyFitConfig

    o = item.opts
    model = load_model("body", o.get("model"))
    target = read_target(item.photo, bool(o.get("silhouette", False)))
    joints, weights = (None, None) if item.landmarks is None else read_joints(item.landmarks, model.n_joints)
    names = dict(size="size", distance="distance", height="height", fov="fov_deg", robust_joints="robust_px")
    changes = {field_: o[k] for k, field_ in names.items() if o.get(k) is not None}
    config = BodyFitConfig.from_budget(o.get("budget", "default"),
                                       background=parse_background(o.get("background", "0,0,0")), **changes)
    return target, joints, weights, model, config


def _fit_body(item: Item, folder: Path) -> tuple[dict, float]:
    from softras_cl.fitting.recipes.body import fit_body
    from softras_cl.fitting.reports.body import write_outputs

    target, joints, weights, model, config = body_inputs(item)
    start = time.perf_counter()
    fit = fit_body(target, model, config, joints, weights, out_dir=folder, progress=False)
    seconds = time.perf_counter() - start
    required = ("silhouette_iou",) + (("joint_error_px_full",) if joints is not None else ())
    metrics = finite_metrics(fit, folder, required)
    write_outputs(fit, target, folder, metrics=metrics, run_config=dict(fit=config, options=item.opts),
                  extra=dict(target=item.photo, seconds=seconds, budget=item.opts.get("budget", "default")))
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


def count_faces(item: Item) -> int:
    """How many faces the detector finds for an item whose landmarks are detected; 0 when its
    landmarks come from a file (or the photo cannot be read: its fit then reports why)."""
    from softras_cl.fitting.landmark_detect import landmarks_beside, resolve_landmarks

    if item.landmarks is not None or landmarks_beside(item.photo) is not None:
        return 0
    try:
        return len(resolve_landmarks(item.photo, None, all_faces=True))
    except Exception:           # no detector, no face, bad photo: the item's own fit says so
        return 0


def expand_faces(client, items: list[Item]) -> list[Item]:
    """With all faces: each face item with detected landmarks -> one item per face found,
    named NAME-face0 (largest), NAME-face1, ...; counted on the workers."""
    face_items = [it for it in items if it.kind == "face"]
    counts = dict(zip(face_items, client.gather(client.map(count_faces, face_items, pure=False))))
    out = []
    for item in items:
        n = counts.get(item, 0)
        out += ([item] if n == 0 else
                [replace(item, name=f"{item.name}-face{k}", face=k) for k in range(n)])
    check_names(out)
    return out


# ---------------------------------------------------------------------------------------------
# the cluster

def split_cores(workers: int | None, threads: int | None, cores: int | None = None) -> tuple[int, int]:
    """(workers, OpenCL threads per worker) with workers x threads <= cores when one of them is
    left None (both None: one worker per core, one thread each). InputError for values < 1."""
    cores = cores or os.cpu_count() or 1
    for name, value in (("--workers", workers), ("--threads-per-worker", threads)):
        if value is not None and value < 1:
            raise InputError(f"{name} must be >= 1, got {value}")
    if workers is None and threads is None:
        return cores, 1
    if workers is None:
        return max(1, cores // threads), threads
    if threads is None:
        return workers, max(1, cores // workers)
    if workers * threads > cores:
        logger.warning("%d workers x %d threads oversubscribe the %d cores", workers, threads, cores)
    return workers, threads


def worker_env(threads: int) -> dict:
    """Environment of a worker process: PoCL's CPU device and the BLAS/OpenMP pools limited to
    ``threads`` threads (POCL_MAX_PTHREAD_COUNT for PoCL's pthread device up to PoCL 4,
    POCL_CPU_MAX_CU_NUM for its cpu device from PoCL 5)."""
    n = str(int(threads))
    return dict(POCL_MAX_PTHREAD_COUNT=n, POCL_CPU_MAX_CU_NUM=n, OMP_NUM_THREADS=n,
                OPENBLAS_NUM_THREADS=n, MKL_NUM_THREADS=n)


class _IgnoreInterrupts:
    """Worker plugin: the workers of a local cluster ignore SIGINT; a Ctrl-C in the terminal
    reaches the whole process group, and the client alone decides what stops."""
    name = "softras-cl-ignore-sigint"

    def setup(self, worker=None):
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)


def local_cluster(workers: int, threads: int):
    """A distributed.LocalCluster of ``workers`` processes, one task at a time each, with
    ``threads`` OpenCL threads (worker_env).

    The workers start without Dask's default MALLOC_TRIM_THRESHOLD_=65536: with it, every numpy
    array above 64 KiB is a fresh mmap whose pages fault in again, and a face fit took 2.1x as
    long in a worker as in a plain process (5.5-5.9 s against 2.2-2.7 s at 64 px).
    """
    import dask
    from distributed import LocalCluster

    environ = {k: v for k, v in dask.config.get("distributed.nanny.pre-spawn-environ").items()
               if k != "MALLOC_TRIM_THRESHOLD_"}
    with dask.config.set({"distributed.worker.daemon": False,
                          "distributed.nanny.pre-spawn-environ": environ}):
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                            env=worker_env(threads), dashboard_address=None,
                            silence_logs=logging.ERROR)


def _import_distributed():
    try:
        import distributed
    except ImportError as e:
        raise InputError('fitting many photos needs Dask: pip install "softras-cl[batch]"') from e
    return distributed


@contextlib.contextmanager
def _client(client, scheduler, workers, threads):
    """The Dask client to use: the caller's, one of a scheduler address, or a new LocalCluster's
    (closed on the way out)."""
    distributed = _import_distributed()
    if client is not None:
        yield client
        return
    if scheduler is not None:
        with distributed.Client(scheduler, timeout="20s") as c:
            yield c
        return
    n, t = split_cores(workers, threads)
    with local_cluster(n, t) as cluster, distributed.Client(cluster) as c:
        c.register_plugin(_worker_plugin())
        yield c


def _worker_plugin():
    from distributed.diagnostics.plugin import WorkerPlugin

    return type("IgnoreInterrupts", (_IgnoreInterrupts, WorkerPlugin), {})()


# ---------------------------------------------------------------------------------------------
# the client side

def fit_many(inputs, out_dir, kind: str = "face", options: dict | None = None, *, client=None,
             scheduler: str | None = None, workers: int | None = None, threads_per_worker: int | None = None,
             all_faces: bool = False, retries: int = 2, progress: bool = True) -> BatchResult:
    """Fit every item into its folder under ``out_dir``; returns a BatchResult.

    inputs: Items, or photo paths / folders / glob patterns (turned into items with
    ``options``, see collect_items). client: a distributed.Client to use; else ``scheduler``
    (tcp://HOST:PORT of a running Dask scheduler whose workers see the same files); else a
    LocalCluster of ``workers`` processes with ``threads_per_worker`` OpenCL threads each
    (split_cores). all_faces: fit every detected face of a photo whose landmarks are detected.
    retries: Dask retries of a task that raised (a failed fit is a row, not a raise).
    ``out_dir`` is locked while the batch runs; it receives one folder per item, results.csv,
    results.jsonl and summary.png. Ctrl-C cancels what is in flight and returns with
    ``interrupted=True`` after writing the table and the summary.
    """
    from softras_cl.interrupts import first_interrupt_calls
    from softras_cl.fitting.reports.batch import ResultsTable

    items = [it if isinstance(it, Item) else None for it in inputs]
    if None in items:
        items = collect_items(inputs, kind, options)
    with OutputFolder(out_dir, f"fit-{kind} (batch)", "--out") as folder:
        table = None
        try:
            with _client(client, scheduler, workers, threads_per_worker) as c:
                if all_faces:
                    items = expand_faces(c, items)
                table = ResultsTable(folder.path, items)
                interrupted = run_items(c, items, table, retries, progress)
        except KeyboardInterrupt:       # before the items ran, or again while the cluster closed
            if table is None:
                raise
            interrupted = True
        with first_interrupt_calls(lambda signum: None):      # another Ctrl-C stops at once
            table.finish(interrupted)       # after the local workers stopped: the table is final
        return BatchResult(table.rows(), interrupted, folder.path, table.counts())


def run_items(client, items: list[Item], table, retries: int = 2, progress: bool = True) -> bool:
    """Submit one run_item task per item and add the rows to ``table`` (a ResultsTable) as they
    arrive; on Ctrl-C cancel the rest. Returns whether the run was interrupted."""
    token = uuid.uuid4().hex[:8]
    out = str(table.out.resolve())
    futures = {client.submit(run_item, item, out, key=f"fit-{item.name}-{token}",
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

    with tqdm(total=len(futures), unit="photo", desc="fit", disable=not progress, smoothing=0.1) as bar:
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
