"""What `softras-cl track-face` writes into --out, chunk by chunk (fitting.recipes.face_track).

- ``identity.npz`` (id, albedo, sh, focal in frame pixels, pixel_scale, keyframes, the joint
  fit's metrics as JSON text) and
  ``identity.ply`` (the neutral face of the identity, albedo vertex colours, model frame; written
  first: the .npz marks both written, and --resume writes a lost .ply again);
- ``chunks/chunk_NNNN.npz``: one chunk's frames: index, time (s), held (bool), rotation (N, 3),
  translation (N, 3), exp (N, K) (after the fixed-lag smoothing; ``fit_rotation``,
  ``fit_translation``, ``fit_exp``: each frame's own fit, before it), sh (N, 3, 9) (each frame's
  light), detected and fitted landmarks (N, 68, 2)
  frame pixels, 0-based (detected NaN where no face was found), the weighted loss terms
  (``term_NAME`` (N,), NaN when held), evaluations and seconds of each frame's fit, and the
  tracker's state after the chunk (``state_*``, where --resume goes on). Written last of a
  chunk's files: a chunk is done when it exists with the others (:func:`chunk_done`).
  ``chunks/chunk_NNNN.jsonl``: the same, a JSON line per frame; ``chunks/overlay_NNNN.mp4``: the
  chunk's overlay frames;
- at the end: ``frames.npz`` / ``frames.jsonl`` (all chunks), ``overlay.mp4`` (each frame, and
  beside it the fitted face drawn over it; no audio), ``track.png`` (head angles, expression and
  the loss terms over time, frames without a face shaded);
- with ``--export-meshes FORMAT``: ``meshes/frame_NNNNNN.FORMAT`` (ply or obj; N the frame's
  index), the fitted face of each frame in the camera's frame (the world of FaceScene: the model
  turned and moved by the frame's rotation and translation), albedo vertex colours, written as
  each frame is done (a held frame: the held pose; none before the first face).
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
from pathlib import Path

import numpy as np

from softras_cl.fitting.keypoints import ibug68
from softras_cl.fitting.recipes.face_track import (FRAME_BLOCKS, FrameResult, Identity, TrackerState, head_angles_deg,
                                                   world_vertices)
from softras_cl.io.meshes import save_mesh
from softras_cl.io.outputs import atomic_path, json_safe, write_bytes, write_figure

__all__ = ["CHUNKS", "MESHES", "OVERLAY_MAX", "ChunkWriter", "MeshExporter", "write_identity", "write_identity_mesh",
           "read_identity", "chunk_path", "chunk_files", "chunk_done", "write_chunk", "read_chunk", "output_names",
           "FINAL_OUTPUTS", "OverlayDrawer", "finish_outputs", "TERMS"]

CHUNKS = "chunks"
MESHES = "meshes"
OVERLAY_MAX = 320         # the overlay video's halves: the frame downscaled to at most this many pixels a side
TERMS = ("landmarks", "exp_prior", "smooth_pose", "smooth_exp", "light_residual")


def write_identity(folder: Path, identity: Identity, model) -> None:
    """identity.ply, then identity.npz (its metrics as JSON text in ``metrics``; module
    docstring): the .npz, which --resume reads, marks both written."""
    write_identity_mesh(folder, identity, model)
    with atomic_path(folder / "identity.npz") as tmp:
        np.savez(tmp, **identity.to_arrays(), metrics=np.array(json.dumps(json_safe(identity.metrics))))


def write_identity_mesh(folder: Path, identity: Identity, model) -> None:
    """identity.ply: the identity's neutral face, albedo vertex colours, model frame."""
    shape = model.shape(identity.id, np.zeros(model.n_exp))[0]
    save_mesh(folder / "identity.ply", shape, model.faces,
              colors=np.clip(model.albedo(identity.albedo)[0], 0.0, 1.0))


def read_identity(folder: Path) -> Identity | None:
    """The identity of an earlier run in ``folder`` (None when it has none)."""
    path = folder / "identity.npz"
    if not path.is_file():
        return None
    with np.load(path) as z:
        return dataclasses.replace(Identity.from_arrays(z), metrics=json.loads(str(z["metrics"])))


def chunk_path(folder: Path, k: int, suffix: str = ".npz", stem: str = "chunk") -> Path:
    return folder / CHUNKS / f"{stem}_{k:04d}{suffix}"


def chunk_arrays(results: list[FrameResult]) -> dict:
    """The frames of a chunk as arrays (module docstring), without the state."""
    def stack(fn):
        return np.array([fn(r) for r in results])

    no_face = np.full((ibug68.COUNT, 2), np.nan)
    arrays = dict(index=stack(lambda r: r.index), time=stack(lambda r: r.time), held=stack(lambda r: r.held),
                  detected=stack(lambda r: no_face if r.detected is None else r.detected),
                  fitted=stack(lambda r: r.fitted), evaluations=stack(lambda r: r.evaluations),
                  seconds=stack(lambda r: r.seconds), sh=stack(lambda r: r.values["sh"]))
    for name in FRAME_BLOCKS:
        arrays[name] = stack(lambda r: r.values[name])
        arrays[f"fit_{name}"] = stack(lambda r: r.own[name])
    for term in TERMS:
        arrays[f"term_{term}"] = stack(lambda r: r.terms.get(term, np.nan))
    return arrays


def frame_line(arrays: dict, i: int) -> str:
    """Frame i of a chunk's (or all frames') arrays as one JSON line."""
    doc = dict(index=int(arrays["index"][i]), time=float(arrays["time"][i]), held=bool(arrays["held"][i]),
               **{name: np.round(arrays[name][i], 6) for name in FRAME_BLOCKS},
               landmarks_detected=np.round(arrays["detected"][i], 3),
               landmarks_fitted=np.round(arrays["fitted"][i], 3),
               terms={t: float(arrays[f"term_{t}"][i]) for t in TERMS})
    return json.dumps(json_safe(doc))


def write_chunk(folder: Path, k: int, results: list[FrameResult], state: TrackerState) -> None:
    """Chunk k's .jsonl, then its .npz (with the tracker's state after it): the .npz marks it done."""
    arrays = chunk_arrays(results)
    (folder / CHUNKS).mkdir(exist_ok=True)
    write_bytes(chunk_path(folder, k, ".jsonl"),
                "".join(frame_line(arrays, i) + "\n" for i in range(len(results))).encode())
    arrays.update({f"state_{name}": v for name, v in state.to_arrays().items()})
    with atomic_path(chunk_path(folder, k)) as tmp:
        np.savez(tmp, **arrays)


def read_history(folder: Path, k: int, lag: int) -> list[FrameResult]:
    """The last ``lag`` frames before chunk k (from the chunks before it; fewer at the start) as
    FrameResults holding what the fixed-lag smoothing needs of them: time, held, and their own
    fit's values (``fit_*``) as values."""
    frames: list[FrameResult] = []
    while k > 0 and len(frames) < lag:
        k -= 1
        arrays = read_chunk(folder, k)[0]
        frames = [FrameResult(int(arrays["index"][i]), float(arrays["time"][i]),
                              {name: arrays[f"fit_{name}"][i] for name in FRAME_BLOCKS}, None,
                              arrays["fitted"][i], bool(arrays["held"][i]), {}, 0, 0.0)
                  for i in range(len(arrays["index"]))] + frames
    return frames[max(0, len(frames) - lag):] if lag else []


def chunk_files(k: int) -> list[str]:
    """Chunk k's files, relative to the output folder: its .jsonl, its overlay part and its .npz."""
    return [chunk_path(Path(), k, suffix, stem).as_posix()
            for suffix, stem in ((".jsonl", "chunk"), (".mp4", "overlay"), (".npz", "chunk"))]


def chunk_done(folder: Path, k: int) -> bool:
    """Whether every file of chunk k is in ``folder`` (a chunk whose .npz is there but another
    file is lost is done again on --resume)."""
    return all((folder / name).is_file() for name in chunk_files(k))


FINAL_OUTPUTS = ("identity.npz", "identity.ply", "frames.npz", "frames.jsonl", "overlay.mp4", "track.png")


def output_names(folder: Path, chunks: int, export_meshes: str | None = None) -> list[str]:
    """The files of a finished run of ``chunks`` chunks in ``folder``, relative to it: the
    identity, each chunk's files, the final outputs and, with ``export_meshes`` ("ply", "obj"),
    the meshes exported (one per frame after the first face)."""
    names = list(FINAL_OUTPUTS) + [name for k in range(chunks) for name in chunk_files(k)]
    if export_meshes is not None and (folder / MESHES).is_dir():
        names += sorted(p.relative_to(folder).as_posix() for p in (folder / MESHES).glob(f"frame_*.{export_meshes}"))
    return names


def read_chunk(folder: Path, k: int) -> tuple[dict, TrackerState] | None:
    """(chunk k's frame arrays, the tracker's state after it), or None when it is not done."""
    path = chunk_path(folder, k)
    if not path.is_file():
        return None
    with np.load(path) as z:
        arrays = {name: np.array(z[name]) for name in z.files}
    state = {name.removeprefix("state_"): arrays.pop(name) for name in list(arrays) if name.startswith("state_")}
    return arrays, TrackerState.from_arrays(state)


class MeshExporter:
    """Writes ``meshes/frame_NNNNNN.FORMAT`` (module docstring) for each frame :meth:`write` is
    given: model and identity, the video's; fmt "ply" or "obj"."""

    def __init__(self, folder: Path, model, identity: Identity, fmt: str):
        self.folder, self.model, self.identity, self.fmt = Path(folder) / MESHES, model, identity, fmt
        self.colors = np.clip(model.albedo(identity.albedo)[0], 0.0, 1.0)
        self.folder.mkdir(exist_ok=True)

    def path(self, index: int) -> Path:
        return self.folder / f"frame_{index:06d}.{self.fmt}"

    def write(self, result: FrameResult) -> None:
        """The mesh of one frame; nothing for a frame before the first face (no pose yet)."""
        if np.all(np.isfinite(result.values["rotation"])):
            save_mesh(self.path(result.index), world_vertices(self.model, self.identity, result.values),
                      self.model.faces, colors=self.colors)


class OverlayDrawer:
    """Overlay frames: the frame (downscaled to at most OVERLAY_MAX a side) and beside it the
    fitted face drawn over it (hard alpha, the eye and mouth openings left open), uint8 RGB."""

    def __init__(self, model, identity: Identity, frame_shape):
        from softras_cl.fitting.recipes.face import FaceScene

        h, w = frame_shape[:2]
        self.scale = min(1.0, OVERLAY_MAX / max(h, w))
        self.size = (max(2, round(h * self.scale)), max(2, round(w * self.scale)))
        self.scene = FaceScene(model, self.size, alpha_agg="hard")
        self.identity = identity

    def draw(self, frame_rgb8: np.ndarray, result: FrameResult) -> np.ndarray:
        from PIL import Image

        from softras_cl.fitting.reports.face import composite, draw
        from softras_cl.srgb import to_linear, to_srgb

        # Pillow's bilinear resize filters over the whole footprint when it shrinks (anti-aliased):
        # 4 ms a 640x480 frame where scikit-image's took 19 ms
        small = frame_rgb8 if self.scale >= 1.0 else np.asarray(
            Image.fromarray(frame_rgb8).resize(self.size[::-1], Image.Resampling.BILINEAR))
        small = small / 255.0
        over = small
        if np.all(np.isfinite(result.values["rotation"])):
            values = dict(result.values, id=self.identity.id, albedo=self.identity.albedo,
                          focal=np.array([self.identity.focal * self.scale]))
            self.scene.set_depth_range(values["translation"])
            over = to_srgb(np.clip(composite(draw(self.scene, values, 1), to_linear(small)), 0.0, 1.0))
        side = np.concatenate([small, over], axis=1)
        if result.held:                       # a red bar along the top: no face found, pose held
            side[: max(2, self.size[0] // 40), :, :] = (1.0, 0.0, 0.0)
        return np.round(np.clip(side, 0.0, 1.0) * 255).astype(np.uint8)


def all_frames(folder: Path, chunks: int) -> dict:
    """Every chunk's frame arrays, concatenated."""
    parts = [read_chunk(folder, k)[0] for k in range(chunks)]
    return {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}


def concatenate_overlays(folder: Path, chunks: int, fps: float) -> None:
    """overlay.mp4 from the chunks' overlay videos (decoded and encoded again, times kept)."""
    from softras_cl.io.video import VideoWriter, open_video

    with atomic_path(folder / "overlay.mp4") as tmp, VideoWriter(tmp, fps) as writer:
        for k in range(chunks):
            for frame in open_video(chunk_path(folder, k, ".mp4", "overlay")).frames():
                writer.write(frame.image, frame.time)


def save_plot(arrays: dict, path: Path) -> None:
    """track.png: yaw, pitch and roll (degrees), the first expression coefficients and the loss
    terms against the frame time; frames without a face shaded."""
    from matplotlib.figure import Figure

    t = arrays["time"]
    fig = Figure(figsize=(9, 7))
    axes = fig.subplots(3, 1, sharex=True)
    angles = np.array([head_angles_deg(r) if np.all(np.isfinite(r)) else (np.nan,) * 3 for r in arrays["rotation"]])
    for i, name in enumerate(("yaw", "pitch", "roll")):
        axes[0].plot(t, angles[:, i], label=name)
    axes[0].set_ylabel("head, degrees")
    for j in range(min(5, arrays["exp"].shape[1])):
        axes[1].plot(t, arrays["exp"][:, j], label=f"exp {j}")
    axes[1].set_ylabel("expression, std")
    for term in TERMS:
        values = arrays[f"term_{term}"]
        if np.any(values > 0):
            axes[2].plot(t, np.where(values > 0, values, np.nan), label=term)
    axes[2].set_yscale("log")
    axes[2].set_ylabel("loss terms")
    axes[2].set_xlabel("time, s")
    half = 0.5 * float(np.median(np.diff(t))) if len(t) > 1 else 0.5
    for ax in axes:
        for held_time in t[arrays["held"]]:
            ax.axvspan(held_time - half, held_time + half, color="0.85", lw=0)
        ax.legend(fontsize=7, loc="upper right", ncol=5)
        ax.grid(True, alpha=0.3)
    fig.suptitle("track-face: pose, expression and per-frame losses (grey: no face found, pose held)")
    fig.tight_layout()
    write_figure(fig, path, dpi=100)


def finish_outputs(folder: Path, chunks: int, fps: float) -> dict:
    """frames.npz, frames.jsonl, overlay.mp4 and track.png from the done chunks; returns the
    summary: frames, frames held, mean evaluations and seconds of the per-frame fits."""
    arrays = all_frames(folder, chunks)
    with atomic_path(folder / "frames.npz") as tmp:
        np.savez(tmp, **arrays)
    write_bytes(folder / "frames.jsonl",
                "".join(frame_line(arrays, i) + "\n" for i in range(len(arrays["index"]))).encode())
    concatenate_overlays(folder, chunks, fps)
    save_plot(arrays, folder / "track.png")
    fitted = ~arrays["held"]
    seconds = float(arrays["seconds"][fitted].sum())
    return dict(frames=int(len(arrays["index"])), frames_held=int(arrays["held"].sum()),
                mean_evaluations=float(arrays["evaluations"][fitted].mean()) if fitted.any() else None,
                frame_fit_seconds=seconds,
                frame_fit_fps=float(fitted.sum() / seconds) if seconds > 0 else None)


class ChunkWriter:
    """A video's outputs as its frames come: each frame's overlay (and, with ``export_meshes``
    "ply" or "obj", its mesh); every ``chunk`` frames the chunk's files with the tracker's state
    after its last frame. Chunks are numbered from ``k``. Used as a context: an error or Ctrl-C
    discards the unfinished chunk's overlay."""

    def __init__(self, model, identity: Identity, folder: Path, k: int, fps: float, chunk: int,
                 export_meshes: str | None = None):
        self.model, self.identity, self.folder, self.k, self.fps = model, identity, folder, k, fps
        self.chunk, self.export_meshes = chunk, export_meshes
        self.stack, self.video, self.results, self.state = contextlib.ExitStack(), None, [], None
        self.drawer = self.meshes = None
        (folder / CHUNKS).mkdir(exist_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, *error):
        return self.stack.__exit__(*error)

    def add(self, result: FrameResult, image, state: TrackerState) -> None:
        """One frame's (smoothed) result, its image (H, W, 3) uint8 and the tracker's state after it."""
        if self.video is None:
            self._open(image.shape)
        self.video.write(self.drawer.draw(image, result), result.time)
        if self.meshes is not None:
            self.meshes.write(result)
        self.results.append(result)
        self.state = state
        if len(self.results) == self.chunk:
            self.end_chunk()

    def _open(self, frame_shape) -> None:
        from softras_cl.io.video import VideoWriter

        if self.drawer is None:
            self.drawer = OverlayDrawer(self.model, self.identity, frame_shape)
            if self.export_meshes is not None:
                self.meshes = MeshExporter(self.folder, self.model, self.identity, self.export_meshes)
        tmp = self.stack.enter_context(atomic_path(chunk_path(self.folder, self.k, ".mp4", "overlay")))
        self.video = self.stack.enter_context(VideoWriter(tmp, self.fps))

    def end_chunk(self) -> None:
        """Write the chunk of the frames added since the last one (none: nothing)."""
        if not self.results:
            return
        self.stack.close()                   # the overlay's part, complete
        write_chunk(self.folder, self.k, self.results, self.state)
        self.k, self.results, self.video = self.k + 1, [], None
