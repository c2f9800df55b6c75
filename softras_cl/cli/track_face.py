"""`softras-cl track-face VIDEO --out DIR`: one face followed through a video
(fitting.jobs.face_video), or several (fitting.batch.videos); this module reads the command line
and prints."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from softras_cl.cli.shared import (add_cluster_options, add_fit_options, add_manifest_option, add_out_option,
                                   add_progress_option, add_rerun_options, check_cluster_args, cluster_asked,
                                   cluster_values, fit_values)
from softras_cl.errors import EXIT_INTERRUPTED, EXIT_OK, InputError, ResultError

DESCRIPTION = """\
Follow one face through a video (mp4/mov/avi/webm/mkv through PyAV, the "video" extra; or a folder
of frames with --fps). The face is found in the first frames (MediaPipe Face Mesh, as
detect-landmarks; --face N / --face-box X,Y,W,H choose it) and followed: each frame is searched
around the previous frame's fitted landmarks, and over the whole frame again when the face is
lost. The identity, albedo and one focal length are fitted once, jointly on a few keyframes
chosen among the first --scan frames for pose variety (as fit-face --same-person does); then each
frame's head pose and expression are fitted to its landmarks, warm-started from the previous
frame, with temporal terms that keep them steady (--rotation-speed, --translation-speed,
--exp-speed, --momentum), and its light to its pixels, changing slowly (--light-speed); a
fixed-lag smoothing pass then steadies pose and expression over --smooth-lag frames either side
(a frame's outputs come that many frames after its fit). A frame without a face keeps the last
pose and is marked "held".

Writes into --out: identity.npz / identity.ply, chunks/ (per chunk of --chunk frames: the frames'
parameters and landmarks as .npz and JSON lines, and the overlay video's part; each chunk is
written when done), then frames.npz and frames.jsonl (every frame: time, held, rotation,
translation, expression, light, detected and fitted landmarks, the loss terms), overlay.mp4 (each
frame beside the fitted face drawn over it; no audio), track.png (pose, expression and the loss
terms over time), with --export-meshes a mesh per frame in meshes/, run.json and, last,
complete.json (listing every output with its size: a run is done while they are all there). Ctrl-C
or SIGTERM keeps the chunks done (exit 130); --resume goes on at the first unfinished chunk and
writes again any output of the finished part that is missing. A video that breaks off (truncated
or damaged) is tracked up to the break: the outputs of the frames before it are written, stderr
says where it broke off, exit 1 (no complete.json). A folder of frames is read in name order,
numbers by value (2.png before 10.png); its frames must all have one size. A run refused (exit 2)
leaves --out as it found it.

Several videos: give several video files, folders (a folder holding video files: each of them; a
folder of images: one video of frames) or quoted glob patterns, and/or --manifest CSV (a 'video'
column, an optional 'name' column, and any option of this command as a column, e.g. face_box or
fps; empty cells take the command line's value; paths relative to the CSV's folder). Each video is
tracked into its own folder under --out, named after its file (a hash of the path is appended when
two share a name), one after the other, or side by side on a Dask cluster with --workers N (a
local cluster of N processes; extra "batch") or --scheduler; --fps applies to the folders of
frames among them.
Running the same command again skips every video whose folder holds a complete run with the same
inputs and options and all its outputs, goes on with an interrupted one at its first unfinished
chunk (or one that lost an output: that is written again), and redoes the others. --out also gets results.csv, results.jsonl (one row per video: status ok, skipped,
failed or cancelled, the error, frames, frames held, frames per second) and summary.png. Exit
code 0 when every video was tracked, 1 when some failed, 130 on Ctrl-C (the chunks done are
kept)."""


def register(sub) -> None:
    """Add `track-face` to the `softras-cl` subparsers `sub`."""
    from softras_cl.fitting.run_options import TRACK

    p = sub.add_parser("track-face", help="follow a face through a video: one identity, pose and expression "
                       "per frame", description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("videos", nargs="*", metavar="VIDEO",
                   help="the video file, or a folder of frames (with --fps); several videos, folders of "
                        "videos or of frames, or glob patterns track each into its own folder under --out")
    add_fit_options(p, TRACK, files=True)
    add_out_option(p)
    add_fit_options(p, TRACK, files=False)
    add_rerun_options(p, "track-face")
    add_manifest_option(p, "videos: a 'video' column, optional 'name' column")
    add_cluster_options(p, "videos")
    add_progress_option(p, "track-face")
    p.set_defaults(func=run)


def _options(args: argparse.Namespace) -> dict:
    from softras_cl.fitting.run_options import TRACK

    return fit_values(args, TRACK)


def run(args: argparse.Namespace) -> int:
    """One video into --out itself, or several (files, folders of videos, globs, a manifest)."""
    if not args.videos and not args.manifest:
        raise InputError("give a video (or several, folders, glob patterns, or --manifest CSV)")
    if is_several(args):
        return run_several(args)
    return run_one(args, args.videos[0])


def run_one(args: argparse.Namespace, video) -> int:
    """Track ``video`` into --out (fitting.jobs.face_video.track_video); the exit code."""
    from softras_cl.fitting.jobs.face_video import track_video

    run = track_video(video, args.out, _options(args), resume=args.resume, overwrite=args.overwrite,
                      progress=not args.no_progress)
    summary = run.summary
    if run.interrupted:
        print(f"track-face interrupted: {run.chunks} chunk(s) of {args.chunk} frames kept in {run.folder}/ "
              "(--resume goes on from there)", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(f"track-face done in {run.seconds:.1f} s: {summary.get('frames', 0)} frames, "
          f"{summary.get('frames_held', 0)} without a face (held); per-frame fits at "
          f"{summary.get('frame_fit_fps') or 0:.1f} frames/s; outputs in {run.folder}/")
    return EXIT_OK


def is_several(args: argparse.Namespace) -> bool:
    """Several inputs, a glob pattern, a folder holding video files or a manifest make a run of
    several videos; one video file (or one folder of frames) alone goes into --out itself."""
    from softras_cl.io.video import expand_videos

    if len(args.videos) != 1 or args.manifest or cluster_asked(args):
        return True
    return expand_videos(args.videos) != [Path(args.videos[0])]


def run_several(args: argparse.Namespace) -> int:
    """Track every video into its folder under --out (fitting.batch.videos), one after the other
    or on a Dask cluster (the cluster options); the exit code."""
    from softras_cl.fitting.batch.videos import track_in_turn, track_on_cluster, video_items

    if args.resume:
        raise InputError("--resume goes with one video; with several, run the same command again: it "
                         "skips the videos done and goes on with an interrupted one at its first unfinished chunk")
    if args.face_box is not None:
        raise InputError("--face-box names a box in one video's frames: give it per video in a manifest's "
                         "face_box column, or --face N")
    items = video_items(args.videos, _options(args), args.manifest)
    check_cluster_args(args)
    progress = not args.no_progress
    if cluster_asked(args):
        rows, counts, interrupted, out = track_on_cluster(items, args.out, cluster_values(args), progress)
    else:
        rows, counts, interrupted, out = track_in_turn(items, args.out, progress)
    print(f"track-face: {len(items)} videos: {', '.join(f'{n} {s}' for s, n in counts.items())}; "
          f"results in {out}/results.csv")
    if interrupted:
        return EXIT_INTERRUPTED
    failed = [r for r in rows if r["status"] == "failed"]
    if failed:
        raise ResultError(f"{len(failed)} of {len(items)} videos failed (first: {failed[0]['name']}: "
                          f"{failed[0]['error']}); {out}/results.csv says which")
    return EXIT_OK
