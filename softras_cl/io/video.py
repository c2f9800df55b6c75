"""Video in and out: frames with their times from a video file (through PyAV, the optional
``video`` extra) or from a folder of images; an H.264 video written from frames.

Reading (:func:`open_video`): every frame is a :class:`Frame`, an (H, W, 3) uint8 RGB image
as it is meant to be shown (the stream's display matrix, or an older file's ``rotate`` tag,
applied: a phone's portrait video comes out upright) with its presentation time in seconds
from the stream's own timestamps, so a variable frame rate is kept. A folder of frames is its
image files in name order, numbers by their value (1.png, 2.png, ..., 10.png, as ffmpeg's %d.png
names them), frame k at time k / fps; every frame must have the first one's size (upright).

Bad input is an InputError naming the file: one PyAV cannot open, no video stream, or a stream
that breaks off (a truncated download): :class:`VideoReadError` is raised once the frames that
could be decoded have been yielded, so a caller keeps what it did with them (the frames the
decoder still held at the break come with their presentation times too).

Writing (:class:`VideoWriter`): H.264 (yuv420p, no audio) into an .mp4 (index first), each frame at its
given time (times in milliseconds, so a variable rate stays variable).
"""
from __future__ import annotations

import contextlib
import glob
import math
import re
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Iterator

import numpy as np

from softras_cl.errors import InputError
from softras_cl.io.images import read_rgb8

__all__ = ["Frame", "VideoSource", "VideoReadError", "VideoWriter", "open_video", "expand_videos", "IMAGE_SUFFIXES",
           "VIDEO_SUFFIXES", "INSTALL_HINT", "upright"]

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".webm", ".mkv")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
INSTALL_HINT = "reading and writing videos needs PyAV: pip install 'softras-cl[video]'"
TIME_BASE = Fraction(1, 1000)     # the writer's timestamps: milliseconds


class VideoReadError(InputError):
    """A video that cannot be read, or breaks off; ``frames_read``: frames yielded before."""

    def __init__(self, message: str, frames_read: int = 0):
        super().__init__(message)
        self.frames_read = frames_read


@dataclass(frozen=True)
class Frame:
    """One frame: index (0-based, in decoding order), time (s, presentation time), image
    (H, W, 3) uint8 RGB, upright."""
    index: int
    time: float
    image: np.ndarray


def _av():
    try:
        import av
    except ImportError:
        raise InputError(INSTALL_HINT) from None
    return av


def upright(image: np.ndarray, rotation_deg: float) -> np.ndarray:
    """The image turned counter-clockwise by ``rotation_deg`` (a multiple of 90: what a display
    matrix or rotate tag says the frame must be turned by to be shown)."""
    quarter = int(round(rotation_deg / 90.0)) % 4
    return np.ascontiguousarray(np.rot90(image, quarter)) if quarter else image


@dataclass(frozen=True)
class VideoSource:
    """Where frames come from. path: the video file or the folder; files: a folder's images in
    order (empty for a video); fps: the folder's rate, or the video's average rate (nominal:
    frame times come from the stream); frame_count: frames the container announces (None
    when it does not say; a folder's image count)."""
    path: Path
    files: tuple[Path, ...]
    fps: float | None
    frame_count: int | None

    @property
    def is_folder(self) -> bool:
        return bool(self.files)

    def frames(self, start: int = 0, only=None) -> Iterator[Frame]:
        """The frames from index ``start`` on (the ones before are decoded and dropped for a
        video: a stream is only read in order); only: a set of frame indices, the others
        skipped (a folder's files are not read, a video's frames not converted to RGB)."""
        return self._folder_frames(start, only) if self.is_folder else self._video_frames(start, only)

    def _folder_frames(self, start: int, only) -> Iterator[Frame]:
        size = None
        for index in range(start, len(self.files)):
            if only is not None and index not in only:
                continue
            image = _read_frame(self.files[index])
            size = size or image.shape[:2]
            if image.shape[:2] != size:       # changed since the folder was opened
                raise InputError(_other_size(self.files[index], image.shape[:2], self.files[start], size))
            yield Frame(index, index / self.fps, image)

    def _video_frames(self, start: int, only) -> Iterator[Frame]:
        index, error, last = 0, None, None
        with _opened(self.path) as container:
            stream = container.streams.video[0]
            tag = _rotate_tag(stream)
            for decoded, error in _decoded(container, stream):
                if decoded is not None:
                    last = _frame_time(decoded, index, self.fps, stream.time_base)
                    if index >= start and (only is None or index in only):
                        yield Frame(index, last, upright(decoded.to_ndarray(format="rgb24"), decoded.rotation or tag))
                    index += 1
        at = "" if last is None else f"the last at {last:.2f} s; "
        if error is not None:
            raise VideoReadError(f"video {self.path} breaks off after {index} frames ({at}truncated or "
                                 f"damaged: {error})", index)
        if self.frame_count is not None and index < self.frame_count:
            raise VideoReadError(f"video {self.path} breaks off after {index} of the {self.frame_count} frames "
                                 f"its header announces ({at}truncated?)", index)


def _decoded(container, stream) -> Iterator[tuple]:
    """(decoded frame, None) for each frame a stream's packets give, in order; at the first
    packet that cannot be read or decoded, the frames the decoder still holds, then
    (None, the error)."""
    av = _av()
    try:
        for packet in container.demux(stream):
            for decoded in packet.decode():
                yield decoded, None
    except av.error.FFmpegError as e:
        with contextlib.suppress(av.error.FFmpegError):
            for decoded in stream.decode(None):
                yield decoded, None
        yield None, e


def _frame_time(decoded, index: int, fps: float | None, time_base=None) -> float:
    """A decoded frame's presentation time in seconds: its timestamp in its own time base, else
    in the stream's ``time_base`` (the frames a decoder gives when flushed after a break carry a
    timestamp but no time base: PyAV's ``time`` is NaN), else index / fps."""
    if decoded.time is not None and math.isfinite(decoded.time):
        return float(decoded.time)
    if decoded.pts is not None and time_base:
        return float(decoded.pts * time_base)
    return index / fps if fps else float(index)


def _rotate_tag(stream) -> float:
    """An older file's ``rotate`` tag (degrees clockwise) as a counter-clockwise angle; 0 when
    absent."""
    text = stream.metadata.get("rotate")
    try:
        return -float(text) if text else 0.0
    except ValueError:
        return 0.0


@contextlib.contextmanager
def _opened(path: Path):
    """PyAV's container of a video file; InputError naming the file when it cannot be opened
    or holds no video stream."""
    av = _av()
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError) as e:
        raise VideoReadError(f"cannot read video {path}: {type(e).__name__}: {e}") from None
    try:
        if not container.streams.video:
            raise VideoReadError(f"video {path} holds no video stream")
        yield container
    finally:
        container.close()


def _read_frame(path: Path) -> np.ndarray:
    """A folder's frame file as (H, W, 3) uint8 RGB (images.read_rgb8); InputError naming it
    when it cannot be read."""
    try:
        return read_rgb8(path)
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read frame {path}: {e}") from None


def open_video(path, fps: float | None = None) -> VideoSource:
    """The frames of a video file or of a folder of images (``fps`` frames per second, needed
    for a folder and refused for a file: a video's frames carry their own times). InputError
    naming the path or --fps when the input cannot be used (checked before any frame is
    decoded, but for a video's damaged frames, see the module docstring)."""
    path = Path(path)
    if path.is_dir():
        return _folder_source(path, fps)
    if not path.is_file():
        raise InputError(f"video not found: {path} (expected a video file or a folder of frames)")
    if fps is not None:
        raise InputError(f"--fps is for a folder of frames; the video {path} gives its frames' times itself")
    with _opened(path) as container:
        stream = container.streams.video[0]
        rate = float(stream.average_rate) if stream.average_rate else None
        count = int(stream.frames) or None
    return VideoSource(path, (), rate, count)


def _files(folder: Path, suffixes: tuple) -> list[Path]:
    """The files of ``folder`` (not its subfolders) with one of ``suffixes``, hidden ones left out, sorted."""
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in suffixes and not p.name.startswith("."))


def expand_videos(inputs) -> list[Path]:
    """The videos named by ``inputs`` (str or Path each), in the order given, each once: a file
    (a video, checked when it is opened); a folder holding video files (VIDEO_SUFFIXES): those,
    by name; any other folder: one video of frames (checked when opened: images and --fps); a
    glob pattern: the files and folders it matches, by name. InputError when an input names
    nothing."""
    videos: list[Path] = []
    for text in map(str, inputs):
        path = Path(text)
        if path.is_dir():
            found = _files(path, VIDEO_SUFFIXES) or [path]
        elif path.is_file():
            found = [path]
        elif glob.has_magic(text):
            found = [Path(p) for p in sorted(glob.glob(text))]
            if not found:
                raise InputError(f"no videos or folders match {text}")
        else:
            raise InputError(f"video not found: {text} (expected a video file, a folder of videos or of "
                             "frames, or a glob pattern)")
        videos += [p for p in found if p not in videos]
    return videos


def _folder_source(path: Path, fps: float | None) -> VideoSource:
    files = tuple(sorted(_files(path, IMAGE_SUFFIXES), key=_frame_order))
    if not files:
        raise InputError(f"no frames in the folder {path} (looked for {', '.join(IMAGE_SUFFIXES)})")
    if fps is None:
        raise InputError(f"the folder of frames {path} needs --fps (its frames' rate: frame k is at k / fps s)")
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise InputError(f"--fps must be a positive number of frames per second, got {fps!r}")
    _check_frame_sizes(files)
    return VideoSource(path, files, float(fps), len(files))


def _frame_order(path: Path) -> tuple:
    """The sort key of a frame file: its name with each run of digits compared by value, so that
    ``2.png`` comes before ``10.png`` (names of one width, ``0002.png``, keep their plain order);
    the name itself breaks ties (``01.png``, ``1.png``)."""
    parts = re.split(r"(\d+)", path.name)
    return tuple(int(p) if i % 2 else p for i, p in enumerate(parts)), path.name


# EXIF orientations that turn an image a quarter (width and height swap when shown upright)
_QUARTER_TURNS = (5, 6, 7, 8)


def _png_has_exif(path: Path) -> bool:
    """Whether a PNG file holds an eXIf chunk, from its chunk headers (the data is skipped):
    Pillow finds one after the image data only by decoding the image (10 ms a 640x480 frame)."""
    with open(path, "rb") as f:
        f.seek(8)                                   # the signature
        while header := f.read(8):
            if len(header) < 8 or header[4:] == b"IEND":
                return False
            if header[4:] == b"eXIf":
                return True
            f.seek(int.from_bytes(header[:4], "big") + 4, 1)     # the data and its CRC
    return False


def _frame_size(path: Path) -> tuple[int, int]:
    """(height, width) of a frame file as read_rgb8 gives it (upright by its EXIF orientation),
    from its header; InputError naming it when it cannot be read."""
    from PIL import Image

    try:
        with Image.open(path) as img:
            width, height = img.size
            exif = img.format != "PNG" or _png_has_exif(path)
            if exif and img.getexif().get(0x0112) in _QUARTER_TURNS:
                width, height = height, width
    except Exception as e:    # Pillow raises many kinds (OSError, SyntaxError, ...)
        raise InputError(f"cannot read frame {path}: {type(e).__name__}: {e}") from None
    return height, width


def _other_size(path: Path, size, first: Path, first_size) -> str:
    """The message about a frame whose (height, width) is not the first frame's."""
    return (f"frame {path} is {size[1]}x{size[0]}, but the frames before it are {first_size[1]}x{first_size[0]} "
            f"(the first: {first}): every frame of a folder must have one size (a stray image, a crop "
            "or a thumbnail among the frames?)")


def _check_frame_sizes(files) -> None:
    """InputError naming the first frame whose size is not the first frame's (read from the
    headers, before any frame is decoded)."""
    first = _frame_size(files[0])
    for path in files[1:]:
        size = _frame_size(path)
        if size != first:
            raise InputError(_other_size(path, size, files[0], first))


class VideoWriter:
    """An H.264 .mp4 written frame by frame: ``with VideoWriter(path, fps) as w: w.write(image,
    time)``. image (H, W, 3) uint8 RGB, every frame of one size (odd sizes are padded by one
    black row/column: yuv420p needs even ones); time in seconds (None: the previous one + 1 /
    fps), increasing by at least a millisecond. No audio."""

    def __init__(self, path, fps: float = 30.0, crf: int = 23):
        self.path, self.fps, self.crf = Path(path), float(fps), int(crf)
        self._container = self._stream = None
        self._last_ms = None

    def __enter__(self) -> "VideoWriter":
        av = _av()
        # the index first ("faststart"): players start at once, and a cut file still opens
        self._container = av.open(str(self.path), "w", format="mp4", options={"movflags": "faststart"})
        return self

    def _start(self, height: int, width: int) -> None:
        stream = self._container.add_stream("libx264", rate=Fraction(self.fps).limit_denominator(1001),
                                            options={"crf": str(self.crf)})
        stream.width, stream.height = width + width % 2, height + height % 2
        stream.pix_fmt = "yuv420p"
        stream.codec_context.time_base = TIME_BASE
        self._stream = stream

    def write(self, image: np.ndarray, time: float | None = None) -> None:
        av = _av()
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"a video frame must be an (H, W, 3) uint8 RGB image, got {img.shape} {img.dtype}")
        if self._stream is None:
            self._start(*img.shape[:2])
        pad = ((0, self._stream.height - img.shape[0]), (0, self._stream.width - img.shape[1]), (0, 0))
        if min(pad[0][1], pad[1][1]) < 0 or max(pad[0][1], pad[1][1]) > 1:
            raise ValueError(f"every frame of {self.path} must have the first one's size "
                             f"{self._stream.height}x{self._stream.width}, got {img.shape[0]}x{img.shape[1]}")
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(np.pad(img, pad)), format="rgb24")
        ms = self._next_ms(time)
        frame.pts, frame.time_base = ms, TIME_BASE
        for packet in self._stream.encode(frame):
            self._container.mux(packet)

    def _next_ms(self, time: float | None) -> int:
        if time is None:
            ms = 0 if self._last_ms is None else self._last_ms + max(1, round(1000.0 / self.fps))
        else:
            ms = int(round(1000.0 * time))
        if self._last_ms is not None and ms <= self._last_ms:
            raise ValueError(f"frame times of {self.path} must increase (by 1 ms at least): "
                             f"{ms} ms after {self._last_ms} ms")
        self._last_ms = ms
        return ms

    def __exit__(self, *exc) -> None:
        try:
            if self._stream is not None and exc[0] is None:
                for packet in self._stream.encode():
                    self._container.mux(packet)
        finally:
            self._container.close()
