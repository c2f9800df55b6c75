"""`softras-cl track-face` end to end on a tiny synthetic video: its outputs, Ctrl-C at a chunk
boundary and --resume, a broken video, bad options (exit 2 before any work)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from support.track_clips import FAST, FPS, FRAMES, SIZE, TINY, talking_head

from softras_cl.errors import InputError
from softras_cl.fitting.recipes import face
from softras_cl.fitting.recipes.face_track import FrameTracker

pytestmark = [pytest.mark.video, pytest.mark.detect]



@pytest.fixture(scope="module")
def video(tmp_path_factory, demo_face_model):
    """A 9-frame, 128 px synthetic talking head at 10 fps (bench track's generator) and its truth."""
    return talking_head(demo_face_model, tmp_path_factory.mktemp("video") / "head.mp4")


@pytest.fixture
def tiny_budget(monkeypatch):
    monkeypatch.setitem(face.BUDGETS, "fast", TINY)          # seconds, not a real identity fit


def _ctrl_c_at_frame(monkeypatch, stop: int):
    """FrameTracker.step raises KeyboardInterrupt at frame ``stop``; returns the real step."""
    step = FrameTracker.step

    def interrupted_step(self, landmarks, time_s, index, *image):
        if index == stop:
            raise KeyboardInterrupt
        return step(self, landmarks, time_s, index, *image)

    monkeypatch.setattr(FrameTracker, "step", interrupted_step)
    return step


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

    # Ctrl-C at frame 8 (in the third chunk; the smoothing holds back the last 3 fitted): the first
    # chunk is kept, no complete.json
    parted = tmp_path / "parted"
    step = _ctrl_c_at_frame(monkeypatch, 8)
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
    """A video cut short: the frames before the break are tracked and written, exit 1 naming it
    (a partly usable input; tests/cli/test_track_face_hostile.py has more)."""
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
    assert result.code == 1 and "cut.mp4" in result.err and "breaks off" in result.err, result.err
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
        np.testing.assert_array_equal(z["rotation"][5], z["fit_rotation"][3])  # the last frame's own fit kept
        np.testing.assert_array_equal(z["rotation"][4], z["rotation"][5])
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


def _results(folder) -> dict:
    """results.jsonl of a several-videos run: name -> row."""
    return {row["name"]: row for row in map(json.loads, (folder / "results.jsonl").read_text().splitlines())}


@pytest.mark.slow
def test_several_videos_each_into_its_folder_skipped_when_done(video, tmp_path, run_cli, tiny_budget):
    """A video file, the same frames as a folder of PNGs (--fps) and a file that is no video: the
    two are tracked alike into their own folders, the bad one is a failed row (exit 1); the same
    command again skips the two done."""
    from PIL import Image

    from softras_cl.io.video import open_video

    frames = tmp_path / "frames"
    frames.mkdir()
    for frame in open_video(video["path"]).frames():
        Image.fromarray(frame.image).save(frames / f"{frame.index:03d}.png")
    (tmp_path / "bad.mp4").write_bytes(b"not a video")
    out = tmp_path / "out"
    command = ("track-face", video["path"], frames, tmp_path / "bad.mp4", "--fps", FPS, "--out", out, *FAST)
    result = run_cli(*command)
    assert result.code == 1 and "1 of 3 videos failed" in result.err, result.err
    rows = _results(out)
    assert [rows[n]["status"] for n in ("head", "frames", "bad")] == ["ok", "ok", "failed"]
    assert "bad.mp4" in rows["bad"]["error"] and rows["head"]["metrics"]["frames"] == FRAMES
    with np.load(out / "head/frames.npz") as a, np.load(out / "frames/frames.npz") as b:
        np.testing.assert_allclose(a["time"], b["time"])
        np.testing.assert_allclose(a["rotation"], b["rotation"], atol=1e-9)     # the same frames, the same fit
    chunk = (out / "frames/chunks/chunk_0000.npz").stat().st_mtime_ns

    again = run_cli(*command)
    assert again.code == 1
    assert [_results(out)[n]["status"] for n in ("head", "frames", "bad")] == ["skipped", "skipped", "failed"]
    assert (out / "frames/chunks/chunk_0000.npz").stat().st_mtime_ns == chunk


@pytest.mark.slow
def test_several_videos_on_a_dask_cluster_each_into_its_folder(video, tmp_path, run_cli):
    """--workers 2: the videos are tasks of a local Dask cluster (one video per worker process);
    each is tracked into its own folder as one after the other would, a bad file is a failed row,
    and the same command again skips the videos done."""
    import shutil

    pytest.importorskip("distributed")
    clips = tmp_path / "clips"
    clips.mkdir()
    for name in ("one", "two"):
        shutil.copy(video["path"], clips / f"{name}.mp4")
    (clips / "bad.mp4").write_bytes(b"not a video")
    out = tmp_path / "out"
    command = ("track-face", clips, "--out", out, "--workers", "2", "--threads-per-worker", "1", *FAST)
    result = run_cli(*command)
    assert result.code == 1 and "1 of 3 videos failed" in result.err, result.err
    rows = _results(out)
    assert [rows[n]["status"] for n in ("one", "two", "bad")] == ["ok", "ok", "failed"]
    assert rows["one"]["metrics"]["frames"] == rows["two"]["metrics"]["frames"] == FRAMES
    with np.load(out / "one/frames.npz") as a, np.load(out / "two/frames.npz") as b:
        np.testing.assert_allclose(a["rotation"], b["rotation"], atol=1e-9)    # the same video, the same fit
    assert (out / "two/complete.json").exists() and (out / "results.csv").exists()
    again = run_cli(*command)
    assert again.code == 1
    assert [_results(out)[n]["status"] for n in ("one", "two", "bad")] == ["skipped", "skipped", "failed"]


def test_scheduler_and_workers_together_are_refused(video, tmp_path, run_cli):
    result = run_cli("track-face", video["path"], video["path"], "--out", tmp_path / "o", "--workers", "2",
                     "--scheduler", "tcp://127.0.0.1:1")
    assert result.code == 2 and "--workers and --threads-per-worker start a local cluster" in result.err
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_several_videos_go_on_after_ctrl_c_at_the_first_unfinished_chunk(video, tmp_path, run_cli, tiny_budget,
                                                                           monkeypatch):
    """Ctrl-C in the first of two videos: exit 130, its first chunk kept and the other cancelled;
    the same command again goes on with the first at its second chunk and tracks the other."""
    import shutil

    for name in ("a", "b"):
        shutil.copy(video["path"], tmp_path / f"{name}.mp4")
    out = tmp_path / "out"
    command = ("track-face", tmp_path / "a.mp4", tmp_path / "b.mp4", "--out", out, *FAST)
    step = _ctrl_c_at_frame(monkeypatch, 8)
    assert run_cli(*command).code == 130
    assert [_results(out)[n]["status"] for n in ("a", "b")] == ["cancelled", "cancelled"]
    first_chunk = (out / "a/chunks/chunk_0000.npz").stat().st_mtime_ns
    monkeypatch.setattr(FrameTracker, "step", step)
    result = run_cli(*command)
    assert result.code == 0, result.err
    assert [_results(out)[n]["status"] for n in ("a", "b")] == ["ok", "ok"]
    assert (out / "a/chunks/chunk_0000.npz").stat().st_mtime_ns == first_chunk      # not done again
    with np.load(out / "a/frames.npz") as a, np.load(out / "b/frames.npz") as b:
        np.testing.assert_allclose(a["rotation"], b["rotation"], atol=1e-9)


def test_several_videos_from_a_manifest_with_options_per_video(video, tmp_path, monkeypatch):
    """A manifest's video, name and option columns (paths relative to it) become each video's
    options over the command line's; --fps reaches the folders of frames only."""
    import shutil

    from softras_cl.fitting.batch.videos import video_items

    (tmp_path / "clips").mkdir()
    shutil.copy(video["path"], tmp_path / "clips/one.mp4")
    (tmp_path / "stills").mkdir()
    (tmp_path / "manifest.csv").write_text("video,name,face_box,frame_iters\nclips/one.mp4,first,1,2,30,40,\n"
                                           "stills,,,12\n")
    options, manifest = {**_defaults(), "fps": 25.0, "frame_iters": 7}, tmp_path / "manifest.csv"
    with pytest.raises(InputError, match="more cells than the header"):
        video_items([], options, manifest)
    (tmp_path / "manifest.csv").write_text('video,name,face_box,frame_iters\nclips/one.mp4,first,"1,2,30,40",\n'
                                           "stills,,,12\n")
    first, stills = video_items([], options, manifest)
    assert (first.name, first.photo, stills.name) == ("first", str(tmp_path / "clips/one.mp4"), "stills")
    assert first.opts["face_box"] == "1,2,30,40" and first.opts["frame_iters"] == 7 and "fps" not in first.opts
    assert stills.opts["frame_iters"] == 12 and stills.opts["fps"] == 25.0


def _defaults() -> dict:
    from softras_cl.fitting.run_options import TRACK

    return TRACK.values({})


@pytest.mark.parametrize("extra, message", [
    (["--resume"], "--resume goes with one video"),
    (["--face-box", "1,2,3,4"], "--face-box names a box in one video"),
    (["--frame-iters", "0"], "--frame-iters must be"),
])
def test_several_videos_bad_options_exit_2_before_any_work(video, tmp_path, run_cli, extra, message):
    result = run_cli("track-face", video["path"], video["path"].parent, "--out", tmp_path / "o", *extra)
    assert result.code == 2 and message in result.err, result.err
    assert not (tmp_path / "o").exists()


def test_a_manifest_row_with_a_bad_option_is_named(video, tmp_path, run_cli):
    (tmp_path / "m.csv").write_text(f"video,chunk\n{video['path']},0\n")
    result = run_cli("track-face", "--manifest", tmp_path / "m.csv", "--out", tmp_path / "o")
    assert result.code == 2 and "--chunk must be" in result.err and "head.mp4" in result.err, result.err
    (tmp_path / "m.csv").write_text(f"photo\n{video['path']}\n")
    result = run_cli("track-face", "--manifest", tmp_path / "m.csv", "--out", tmp_path / "o")
    assert result.code == 2 and "no video (a 'video' column is required)" in result.err, result.err
