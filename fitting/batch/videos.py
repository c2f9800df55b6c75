"""track-face on several videos: files, folders of videos or of frames, glob patterns and a
manifest (fitting.batch.items, kind "track"), each tracked into its own folder under the output
folder by fitting.jobs.face_video.track_video, with results.csv/.jsonl (fitting.batch.results):
one after the other (:func:`track_in_turn`), or as tasks of the photo batch's Dask cluster
(:func:`track_on_cluster`: fitting.batch.client.fit_many with :func:`video_task`), one video
per task: a video is a long, sequential job (each frame is warm-started from the one before)."""
from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

from softras_cl.errors import InputError, SoftrasError
from softras_cl.fitting.batch.items import collect_items
from softras_cl.fitting.batch.results import ResultsTable
from softras_cl.fitting.batch.tasks import describe, make_row
from softras_cl.fitting.jobs.face_video import BrokenVideoError, check_options, run_record, track_video
from softras_cl.fitting.run_options import TRACK
from softras_cl.fitting.run_records import completed
from softras_cl.io.outputs import RUN_RECORD, OutputFolder, json_safe
from softras_cl.io.video import open_video

__all__ = ["LABEL", "video_items", "video_task", "track_in_turn", "track_on_cluster"]

SUMMARY = ("frames", "frames_held", "frame_fit_fps", "end_to_end_fps", "identity_seconds")   # results' metrics
LABEL = "track-face (several videos)"      # the command named in the output folder's lock


def video_items(videos: list, options: dict, manifest=None) -> list:
    """The videos' fitting.batch.items.Item (kind "track", ``photo`` the video's path) with their
    options: ``options`` (track-face's, fitting.run_options.TRACK), a manifest row's cells over
    them; the ``fps`` option only for folders of frames. InputError naming the video and option
    that cannot be used, before any work."""
    fps = options.get("fps")
    given = {k: v for k, v in options.items() if k != "fps"}
    items = collect_items(videos, "track", given, manifest=manifest)
    items = [replace(it, options=tuple(sorted({**it.opts, "fps": fps}.items())))
             if fps is not None and "fps" not in it.opts and Path(it.photo).is_dir() else it
             for it in items]
    for item in items:
        try:
            check_options(item.opts)
        except InputError as error:
            raise InputError(f"{item.photo}: {error}") from None
    return items


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _summary(complete: dict) -> dict:
    return {k: complete.get(k) for k in SUMMARY}


def _track_item(item, out: Path, progress: bool) -> dict:
    """Track one video into ``out``/NAME (skipped when that folder holds its complete run with
    every output; resumed when it holds its interrupted one, or a complete one that lost an
    output); its results row (a video that breaks off: failed, with the frames written before
    the break). KeyboardInterrupt when Ctrl-C stopped it."""
    start = time.perf_counter()
    values = TRACK.values(item.opts)
    folder = out / item.name
    try:
        record = run_record(open_video(item.photo, values["fps"]), values)
        done = completed(folder, record)
        if done is not None:
            print(f"track-face: {item.name}: done before with these inputs and options (skipped)")
            return make_row(item, "skipped", folder, _summary(done), done.get("seconds"))
        resume = _read_json(folder / RUN_RECORD) == json.loads(json.dumps(json_safe(record), default=str))
        run = track_video(item.photo, folder, values, resume=resume, progress=progress)
    except BrokenVideoError as error:           # the frames before the break are written
        print(f"track-face: {item.name}: failed: {describe(error)}")
        return make_row(item, "failed", error.folder, _summary(error.summary), time.perf_counter() - start,
                        error=describe(error))
    except (SoftrasError, ValueError, OSError) as error:
        print(f"track-face: {item.name}: failed: {describe(error)}")
        return make_row(item, "failed", seconds=time.perf_counter() - start, error=describe(error))
    if run.interrupted:
        raise KeyboardInterrupt
    doc = _read_json(folder / "complete.json") or {}
    return make_row(item, "ok", folder, _summary(doc), doc.get("seconds"))


def video_task(item, out_dir: str, progress: bool) -> dict:
    """One video on a Dask worker (fitting.batch.client.fit_many's task): its row, as
    :func:`_track_item` (a Ctrl-C there stops the cluster, not this task)."""
    return _track_item(item, Path(out_dir), progress)


def track_in_turn(items: list, out, progress: bool = True) -> tuple:
    """(rows, counts, interrupted, the output folder) of tracking the videos one after the other
    in this process."""
    with OutputFolder(out, LABEL, "--out") as folder:
        table, interrupted = ResultsTable(folder.path, items), False
        try:
            for item in items:
                table.add(_track_item(item, folder.path, progress))
        except KeyboardInterrupt:
            interrupted = True
        table.finish(interrupted)
    return table.rows(), table.counts(), interrupted, folder.path


def track_on_cluster(items: list, out, cluster: dict, progress: bool = True) -> tuple:
    """(rows, counts, interrupted, the output folder) of tracking the videos as tasks of a Dask
    cluster (fit_many's ``scheduler``, ``workers``, ``threads_per_worker`` in ``cluster``),
    without each video's own progress line."""
    from softras_cl.fitting.batch.client import fit_many

    result = fit_many(items, out, "track", **cluster, progress=progress, task=video_task, task_args=(False,),
                      label=LABEL)
    return result.rows, result.counts, result.interrupted, result.out
