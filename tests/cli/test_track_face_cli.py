"""`softras-cl track-face` end to end on a tiny synthetic video: its outputs, Ctrl-C at a chunk
boundary and --resume, a broken video, bad options (exit 2 before any work)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from softras_cl.fitting.recipes import face
from softras_cl.fitting.recipes.face_track import FrameTracker

pytestmark = [pytest.mark.video, pytest.mark.detect]

TINY = dict(landmark_iters=10, photo_stages=((1e-4, 3e-3, 4), (1e-5, 1e-3, 4)))
FAST = ["--size", "64", "--budget", "fast", "--keyframes", "2", "--chunk", "4", "--no-progress"]
FRAMES, FPS, SIZE = 9, 10.0, 128


@pytest.fixture(scope="module")
def video(tmp_path_factory, demo_face_model):
    """A 9-frame, 128 px synthetic talking head at 10 fps (bench track's generator) and its truth."""
    from softras_cl.bench.track import make_sequence

    folder = tmp_path_factory.mktemp("video")
    return make_sequence(demo_face_model, np.random.default_rng(3), FRAMES, SIZE, FPS, "coffee", folder / "head.mp4")


@pytest.fixture
def tiny_budget(monkeypatch):
    monkeypatch.setitem(face.BUDGETS, "fast", TINY)          # seconds, not a real identity fit


@pytest.mark.slow
def test_track_face_writes_every_output_and_resumes_after_ctrl_c(video, tmp_path, run_cli, tiny_budget, monkeypatch):
    whole = tmp_path / "whole"
    result = run_cli("track-face", video["path"], "--out", whole, *FAST, "--export-meshes", "ply")
    assert result.code == 0, result.err
    for name in ("identity.npz", "identity.ply", "frames.npz", "frames.jsonl", "overlay.mp4", "track.png",
                 "complete.json", "chunks/chunk_0000.npz", "chunks/chunk_0002.jsonl", "chunks/overlay_0001.mp4"):
        assert (whole / name).is_file(), name
    with np.load(whole / "frames.npz") as z:
        frames = {k: z[k] for k in z.files}
    np.testing.assert_allclose(frames["time"], np.arange(FRAMES) / FPS)
    assert not frames["held"].any()
    errors = np.linalg.norm(frames["fitted"] - video["landmarks"], axis=2).mean(axis=1)
    assert np.median(errors) < 4.0, errors                       # pixels of a 128 px frame
    lines = (whole / "frames.jsonl").read_text().splitlines()
    assert len(lines) == FRAMES and json.loads(lines[3])["time"] == pytest.approx(0.3)
    complete = json.loads((whole / "complete.json").read_text())
    assert complete["frames"] == FRAMES and complete["frames_held"] == 0 and len(complete["keyframes"]) == 2

    from softras_cl.io.video import open_video

    overlay = list(open_video(whole / "overlay.mp4").frames())
    assert len(overlay) == FRAMES and overlay[0].image.shape == (SIZE, 2 * SIZE, 3)

    # Ctrl-C at frame 6 (in the second chunk): the first chunk is kept, no complete.json
    parted = tmp_path / "parted"
    step = FrameTracker.step

    def interrupted_step(self, landmarks, time_s, index):
        if index == 6:
            raise KeyboardInterrupt
        return step(self, landmarks, time_s, index)

    monkeypatch.setattr(FrameTracker, "step", interrupted_step)
    result = run_cli("track-face", video["path"], "--out", parted, *FAST, "--export-meshes", "ply")
    assert result.code == 130 and "1 chunk(s)" in result.err
    assert (parted / "chunks/chunk_0000.npz").is_file() and not (parted / "chunks/chunk_0001.npz").exists()
    assert not (parted / "complete.json").exists()
    first_chunk = (parted / "chunks/chunk_0000.npz").read_bytes()

    monkeypatch.setattr(FrameTracker, "step", step)
    result = run_cli("track-face", video["path"], "--out", parted, *FAST, "--export-meshes", "ply", "--resume")
    assert result.code == 0, result.err
    assert (parted / "chunks/chunk_0000.npz").read_bytes() == first_chunk        # not done again
    resumed = json.loads((parted / "complete.json").read_text())
    assert resumed["identity_metrics"] == complete["identity_metrics"] and resumed["frames"] == FRAMES
    with np.load(parted / "frames.npz") as z:
        for name in ("rotation", "translation", "exp", "fitted", "detected"):
            np.testing.assert_allclose(z[name], frames[name], rtol=0, atol=1e-9, err_msg=name)
    # a mesh per frame, written as the frames go: the resumed run's are the uninterrupted run's
    meshes = sorted(p.name for p in (parted / "meshes").iterdir())
    assert meshes == [f"frame_{k:06d}.ply" for k in range(FRAMES)]
    assert sorted(p.name for p in (whole / "meshes").iterdir()) == meshes
    for name in (meshes[0], meshes[-1]):
        assert (parted / "meshes" / name).read_bytes() == (whole / "meshes" / name).read_bytes(), name


@pytest.mark.slow
def test_a_broken_video_keeps_the_frames_read(video, tmp_path, run_cli, tiny_budget):
    """A video cut short: the frames before the break are tracked and written, exit 2 naming it."""
    from softras_cl.bench.track import write_sequence
    from softras_cl.io.video import open_video

    images = [f.image for f in open_video(video["path"]).frames()]
    long = tmp_path / "long.mp4"
    write_sequence(long, images * 3, FPS, crf=0)          # 27 frames, large enough to cut among them
    # (the writer puts the index first, "faststart": a cut file opens, and breaks off later)
    data = long.read_bytes()
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    result = run_cli("track-face", cut, "--out", tmp_path / "o", *FAST)
    assert result.code == 2 and "cut.mp4" in result.err and "breaks off" in result.err, result.err
    with np.load(tmp_path / "o/chunks/chunk_0000.npz") as z:      # the frames before the break
        assert len(z["index"]) == 4
    assert not (tmp_path / "o/complete.json").exists()


@pytest.mark.slow
def test_frames_without_a_face_are_held_and_marked(video, tmp_path, run_cli, tiny_budget):
    from softras_cl.bench.track import write_sequence
    from softras_cl.io.video import open_video

    images = [f.image for f in open_video(video["path"]).frames()]
    for k in (4, 5):                           # the face gone: a plain grey frame
        images[k] = np.full_like(images[k], 128)
    write_sequence(tmp_path / "gap.mp4", images, FPS)
    result = run_cli("track-face", tmp_path / "gap.mp4", "--out", tmp_path / "o", *FAST)
    assert result.code == 0, result.err
    with np.load(tmp_path / "o/frames.npz") as z:
        assert z["held"].tolist() == [k in (4, 5) for k in range(FRAMES)]
        assert np.isnan(z["detected"][4]).all() and np.isfinite(z["detected"][6]).all()
        np.testing.assert_array_equal(z["rotation"][5], z["rotation"][3])      # the last pose kept
        assert np.isnan(z["term_landmarks"][4]) and np.isfinite(z["term_landmarks"][6])
    assert json.loads((tmp_path / "o/complete.json").read_text())["frames_held"] == 2
    assert json.loads((tmp_path / "o/frames.jsonl").read_text().splitlines()[4])["held"] is True


@pytest.mark.parametrize("extra, message", [
    (["--chunk", "0"], "--chunk must be"),
    (["--frame-iters", "0"], "--frame-iters must be"),
    (["--momentum", "2"], "--momentum must be"),
    (["--face", "1", "--face-box", "1,2,3,4"], "cannot be combined"),
    (["--fps", "25"], "--fps is for a folder"),
])
def test_bad_options_exit_2_before_any_work(video, tmp_path, run_cli, extra, message):
    result = run_cli("track-face", video["path"], "--out", tmp_path / "o", *extra)
    assert result.code == 2 and message in result.err, result.err
    assert not (tmp_path / "o").exists()


def test_folder_of_frames_needs_fps(tmp_path, run_cli):
    from PIL import Image

    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(tmp_path / "0001.png")
    result = run_cli("track-face", tmp_path, "--out", tmp_path / "o")
    assert result.code == 2 and "needs --fps" in result.err
    result = run_cli("track-face", tmp_path / "missing.mp4", "--out", tmp_path / "o")
    assert result.code == 2 and "video not found" in result.err


def test_a_bad_device_is_refused_before_the_face_search(video, tmp_path):
    """SOFTRAS_CL_DEVICE is read when the process starts: a real process, exit 2, no output folder."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = Path(sys.executable).with_name("softras-cl")
    done = subprocess.run([str(script), "track-face", str(video["path"]), "--out", str(tmp_path / "o")],
                          capture_output=True, text=True, env={**os.environ, "SOFTRAS_CL_DEVICE": "nonsense"},
                          timeout=300)
    assert done.returncode == 2 and "matches no OpenCL device" in done.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "o").exists()
