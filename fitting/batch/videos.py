"""What makes a run of `softras-cl track-face`: its options checked (:func:`check_options`) and
its record (:func:`run_record`); and the command on several videos: files, folders of videos or
of frames, glob patterns and `--manifest CSV` (fitting.batch_items, kind "track"), each tracked
into its own folder under --out by the single-video command (softras_cl.cli.track_face.run_one,
passed in), with results.csv/.jsonl (fitting.reports.batch): one after the other, or with the
cluster options (--workers, --threads-per-worker, --scheduler) as tasks of the photo batch's Dask
cluster (fitting.batch.fit_many with :func:`video_task`), one video per task: a video is a
long, sequential job (each frame is warm-started from the one before)."""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

from softras_cl.cli.runs import fit_values
from softras_cl.errors import EXIT_INTERRUPTED, EXIT_OK, InputError, ResultError, SoftrasError

__all__ = ["check_options", "run_record", "is_several", "run_several", "video_items", "video_task"]

SUMMARY = ("frames", "frames_held", "frame_fit_fps", "end_to_end_fps", "identity_seconds")   # results' metrics
LABEL = "track-face (several videos)"      # the command named in --out's lock


def check_options(values: dict):
    """(TrackConfig, the --face-box box or None) of the options ``values`` (option name -> value,
    fitting.run_options.TRACK); InputError naming the option, before any work."""
    from softras_cl.fitting.detection import parse_face_box
    from softras_cl.fitting.run_options import TRACK

    config = TRACK.config(values)
    values = TRACK.values(values)
    for option, value in (("--chunk", values["chunk"]), ("--scan", values["scan"])):
        if value < 1:
            raise InputError(f"{option} must be an integer >= 1 (frames), got {value}")
    face, face_box = values["face"], values["face_box"]
    if face is not None and face_box is not None:
        raise InputError("--face and --face-box cannot be combined: give one")
    if face is not None and face < 0:
        raise InputError(f"--face must be >= 0 (0 is the largest face), got {face}")
    return config, None if face_box is None else parse_face_box(face_box)


def _input_record(source) -> dict:
    """The video's digest: the file's SHA-256, or for a folder one over its frames' names and digests."""
    import hashlib

    from softras_cl.io.outputs import file_sha256

    if not source.is_folder:
        return dict(video=str(source.path), video_sha256=file_sha256(source.path))
    digest = hashlib.sha256()
    for path in source.files:
        digest.update(f"{path.name}:{file_sha256(path)}\n".encode())
    return dict(video=str(source.path), frames_sha256=digest.hexdigest())


def run_record(args, source) -> dict:
    """The run record of tracking ``source`` (softras_cl.io.video.VideoSource) with the options of
    ``args``: its digests (and the model's) and the recorded options."""
    from softras_cl.fitting.run_options import TRACK
    from softras_cl.io.outputs import file_sha256

    inputs = _input_record(source)
    if args.model is not None:
        inputs["model_sha256"] = file_sha256(args.model)
    return dict(command="track-face", inputs=inputs, options=TRACK.record_options(fit_values(args, TRACK)))


def is_several(args: argparse.Namespace) -> bool:
    """Several inputs, a glob pattern, a folder holding video files or a manifest make a run of
    several videos; one video file (or one folder of frames) alone goes into --out itself."""
    from softras_cl.io.video import expand_videos

    from softras_cl.cli.batch import cluster_asked

    if len(args.videos) != 1 or args.manifest or cluster_asked(args):
        return True
    return expand_videos(args.videos) != [Path(args.videos[0])]


def video_items(args: argparse.Namespace) -> list:
    """The videos' fitting.batch_items.Item (kind "track", ``photo`` the video's path) with their
    options: the command line's, a manifest row's cells over them; --fps only for folders of
    frames. InputError naming the video and option that cannot be used, before any work."""
    from softras_cl.fitting.batch_items import collect_items
    from softras_cl.fitting.run_options import TRACK

    if args.resume:
        raise InputError("--resume goes with one video; with several, run the same command again: it "
                         "skips the videos done and goes on with an interrupted one at its first unfinished chunk")
    if args.face_box is not None:
        raise InputError("--face-box names a box in one video's frames: give it per video in a manifest's "
                         "face_box column, or --face N")
    given = {k: v for k, v in fit_values(args, TRACK).items() if k != "fps"}
    items = collect_items(args.videos, "track", given, manifest=args.manifest)
    items = [replace(it, options=tuple(sorted({**it.opts, "fps": args.fps}.items())))
             if args.fps is not None and "fps" not in it.opts and Path(it.photo).is_dir() else it
             for it in items]
    for item in items:
        try:
            check_options(item.opts)
        except InputError as error:
            raise InputError(f"{item.photo}: {error}") from None
    return items


def _item_args(args: argparse.Namespace, item, out: Path) -> argparse.Namespace:
    """The single-video command's arguments for ``item``, into ``out``/NAME."""
    from softras_cl.fitting.run_options import TRACK

    return argparse.Namespace(**{**vars(args), **TRACK.values(item.opts), "video": item.photo,
                                 "out": str(out / item.name), "resume": False})


def _run_item(args: argparse.Namespace, item, out: Path, track_one) -> dict:
    """Track one video by ``track_one(args) -> exit code`` (skipped when its folder holds its
    complete run; resumed when it holds its interrupted one); its results row.
    KeyboardInterrupt when Ctrl-C stopped it."""
    from softras_cl.fitting.batch_task import describe, make_row
    from softras_cl.fitting.run_records import completed
    from softras_cl.io.outputs import RUN_RECORD, json_safe
    from softras_cl.io.video import open_video

    start = time.perf_counter()
    one = _item_args(args, item, out)
    folder = Path(one.out)
    try:
        record = run_record(one, open_video(one.video, one.fps))
        done = completed(folder, record)
        if done is not None:
            print(f"track-face: {item.name}: done before with these inputs and options (skipped)")
            return make_row(item, "skipped", folder, _summary(done), done.get("seconds"))
        one.resume = _read_json(folder / RUN_RECORD) == json.loads(json.dumps(json_safe(record), default=str))
        code = track_one(one)
    except (SoftrasError, ValueError, OSError) as error:
        print(f"track-face: {item.name}: failed: {describe(error)}")
        return make_row(item, "failed", seconds=time.perf_counter() - start, error=describe(error))
    if code == EXIT_INTERRUPTED:
        raise KeyboardInterrupt
    doc = _read_json(folder / "complete.json") or {}
    return make_row(item, "ok", folder, _summary(doc), doc.get("seconds"))


def video_task(item, out_dir: str, args: argparse.Namespace, track_one) -> dict:
    """One video on a Dask worker (fitting.batch.fit_many's task): its row, as :func:`_run_item`
    (a Ctrl-C there stops the cluster, not this task)."""
    return _run_item(args, item, Path(out_dir), track_one)


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _summary(complete: dict) -> dict:
    return {k: complete.get(k) for k in SUMMARY}


def run_several(args: argparse.Namespace, track_one) -> int:
    """Track every video into its folder under --out by ``track_one(args) -> exit code`` (the
    single-video command), one after the other or on a Dask cluster (the cluster options);
    results.csv/.jsonl; the exit code."""
    from softras_cl.cli.batch import check_cluster_args, cluster_asked

    items = video_items(args)
    check_cluster_args(args)
    rows, counts, interrupted, out = (_on_cluster if cluster_asked(args) else _one_by_one)(args, items, track_one)
    print(f"track-face: {len(items)} videos: {', '.join(f'{n} {s}' for s, n in counts.items())}; "
          f"results in {out}/results.csv")
    if interrupted:
        return EXIT_INTERRUPTED
    failed = [r for r in rows if r["status"] == "failed"]
    if failed:
        raise ResultError(f"{len(failed)} of {len(items)} videos failed (first: {failed[0]['name']}: "
                          f"{failed[0]['error']}); {out}/results.csv says which")
    return EXIT_OK


def _one_by_one(args: argparse.Namespace, items: list, track_one) -> tuple:
    """(rows, counts, interrupted, --out) of tracking the videos in turn in this process."""
    from softras_cl.fitting.reports.batch import ResultsTable
    from softras_cl.io.outputs import OutputFolder

    with OutputFolder(args.out, LABEL, "--out") as folder:
        table, interrupted = ResultsTable(folder.path, items), False
        try:
            for item in items:
                table.add(_run_item(args, item, folder.path, track_one))
        except KeyboardInterrupt:
            interrupted = True
        table.finish(interrupted)
    return table.rows(), table.counts(), interrupted, folder.path


def _on_cluster(args: argparse.Namespace, items: list, track_one) -> tuple:
    """(rows, counts, interrupted, --out) of tracking the videos as tasks of a Dask cluster
    (fitting.batch.fit_many), without each video's own progress line."""
    from softras_cl.fitting.batch import fit_many

    quiet = argparse.Namespace(**{**vars(args), "no_progress": True})
    result = fit_many(items, args.out, "track", scheduler=args.scheduler, workers=args.workers,
                      threads_per_worker=args.threads_per_worker, progress=not args.no_progress,
                      task=video_task, task_args=(quiet, track_one), label=LABEL)
    return result.rows, result.counts, result.interrupted, result.out
