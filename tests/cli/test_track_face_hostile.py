"""`softras-cl track-face` on hostile real inputs: videos cut short or damaged in the middle, a disk
that fills up, a run refused after its output folder was chosen, a folder of frames of mixed sizes,
and frames named 1.png, 2.png, ... 10.png (docs/reliability.md, the track-face rows)."""
from __future__ import annotations

import errno
import json

import numpy as np
import pytest
from support.track_clips import FAST, FPS, SIZE, TINY, talking_head

from softras_cl.fitting.recipes import face

pytestmark = [pytest.mark.video, pytest.mark.detect]



@pytest.fixture(scope="module")
def clips(tmp_path_factory, demo_face_model):
    """A 9-frame synthetic talking head (head.mp4, bench track's generator); its frames six times
    over (54 frames, H.264 with B-frames: long.mp4); long.mp4 with its last 40% of bytes cut
    (cut.mp4) and with 10,000 bytes cut from its middle (gouged.mp4)."""
    from softras_cl.bench.track import write_sequence
    from softras_cl.io.video import open_video

    folder = tmp_path_factory.mktemp("clips")
    head = talking_head(demo_face_model, folder / "head.mp4")
    images = [f.image for f in open_video(head["path"]).frames()]
    write_sequence(folder / "long.mp4", images * 6, FPS)
    data = (folder / "long.mp4").read_bytes()
    (folder / "cut.mp4").write_bytes(data[: int(len(data) * 0.6)])
    middle = len(data) // 2
    (folder / "gouged.mp4").write_bytes(data[:middle] + data[middle + 10_000:])
    return dict(head=head["path"], images=images, **{n: folder / f"{n}.mp4" for n in ("long", "cut", "gouged")})


@pytest.fixture(autouse=True)
def tiny_budget(monkeypatch):
    monkeypatch.setitem(face.BUDGETS, "fast", TINY)          # seconds, not a real identity fit


def _readable(path) -> tuple[list, int]:
    """(the times of the frames a damaged video gives before it breaks off, how many)."""
    from softras_cl.io.video import VideoReadError, open_video

    times = []
    with pytest.raises(VideoReadError):
        for frame in open_video(path).frames():
            times.append(frame.time)
    return times, len(times)


def _frames(folder) -> dict:
    with np.load(folder / "frames.npz") as z:
        return {k: z[k] for k in z.files}


def _error_lines(result) -> list[str]:
    return [line for line in result.err.splitlines() if line.startswith("softras-cl")]


# -- 1. a video that breaks off: every frame before the break tracked, the break named, exit 1 ----

@pytest.mark.slow
@pytest.mark.parametrize("name", ["cut", "gouged"])
def test_a_damaged_video_tracks_every_frame_before_the_break(clips, tmp_path, run_cli, name):
    times, count = _readable(clips[name])
    assert count >= 8
    result = run_cli("track-face", clips[name], "--out", tmp_path / "o", *FAST)
    lines = _error_lines(result)
    assert result.code == 1 and len(lines) == 1, result.err
    assert f"{name}.mp4 breaks off after {count} frames" in lines[0] and "written" in lines[0], lines[0]
    frames = _frames(tmp_path / "o")
    assert len(frames["index"]) == count
    np.testing.assert_allclose(frames["time"], times)
    assert np.all(np.isfinite(frames["rotation"])) and not frames["held"].any()
    for output in ("overlay.mp4", "track.png", "frames.jsonl", "identity.ply"):
        assert (tmp_path / "o" / output).is_file(), output
    assert not (tmp_path / "o/complete.json").exists()


@pytest.mark.slow
def test_a_damaged_video_among_several_keeps_its_frames(clips, tmp_path, run_cli):
    _, count = _readable(clips["gouged"])
    out = tmp_path / "out"
    result = run_cli("track-face", clips["head"], clips["gouged"], "--out", out, *FAST)
    assert result.code == 1 and "1 of 2 videos failed" in result.err, result.err
    rows = {row["name"]: row for row in map(json.loads, (out / "results.jsonl").read_text().splitlines())}
    assert rows["head"]["status"] == "ok" and rows["gouged"]["status"] == "failed"
    assert f"breaks off after {count} frames" in rows["gouged"]["error"]
    assert rows["gouged"]["metrics"]["frames"] == count
    assert len(_frames(out / "gouged")["index"]) == count


# -- 2. --resume after a full disk: done means every output is there -----------------------------

def _disk_full_once(monkeypatch, module, name):
    """``module.name`` (a writer taking a path first) fails once as on a full disk, then works."""
    from softras_cl.io.outputs import atomic_path

    real, calls = getattr(module, name), []

    def full_once(path, *args, **kwargs):
        calls.append(path)
        if len(calls) == 1:
            with atomic_path(path):
                raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, *args, **kwargs)

    monkeypatch.setattr(module, name, full_once)


@pytest.mark.slow
def test_resume_after_a_full_disk_writes_what_is_missing(clips, tmp_path, run_cli, monkeypatch):
    from softras_cl.fitting.jobs.face_video import run_record
    from softras_cl.fitting.reports import face_track
    from softras_cl.fitting.run_options import TRACK
    from softras_cl.fitting.run_records import completed
    from softras_cl.io.video import open_video

    out = tmp_path / "o"
    _disk_full_once(monkeypatch, face_track, "save_mesh")          # identity.ply, the first mesh written
    result = run_cli("track-face", clips["head"], "--out", out, *FAST)
    assert result.code == 3 and "identity.ply: No space left on device" in result.err, result.err
    result = run_cli("track-face", clips["head"], "--out", out, *FAST, "--resume")
    assert result.code == 0, result.err
    assert (out / "identity.ply").is_file()
    complete = json.loads((out / "complete.json").read_text())
    assert "identity.ply" in complete["outputs"] and "chunks/chunk_0002.npz" in complete["outputs"]
    assert all((out / name).stat().st_size == size for name, size in complete["outputs"].items())

    values = TRACK.values({"size": 64, "budget": "fast", "keyframes": 2, "chunk": 4})
    record = run_record(open_video(clips["head"]), values)
    assert completed(out, record) is not None
    (out / "identity.ply").unlink()                 # lost since: the run is not done any more
    assert completed(out, record) is None
    result = run_cli("track-face", clips["head"], "--out", out, *FAST, "--resume")
    assert result.code == 0 and (out / "identity.ply").is_file(), result.err
    assert completed(out, record) is not None
    (out / "track.png").write_bytes(b"cut short")       # an output no longer whole
    assert completed(out, record) is None


@pytest.mark.slow
def test_several_videos_redo_a_done_video_that_lost_an_output(clips, tmp_path, run_cli):
    out = tmp_path / "out"
    command = ("track-face", clips["head"], clips["long"], "--out", out, *FAST)
    assert run_cli(*command).code == 0
    (out / "head/track.png").unlink()
    assert run_cli(*command).code == 0
    rows = {row["name"]: row for row in map(json.loads, (out / "results.jsonl").read_text().splitlines())}
    assert rows["head"]["status"] == "ok" and rows["long"]["status"] == "skipped"
    assert (out / "head/track.png").is_file()


# -- 3. a refused run leaves no folder it made, and a folder it found as it was -------------------

@pytest.mark.slow
def test_a_refused_run_leaves_no_folder_behind(clips, tmp_path, run_cli):
    from softras_cl.bench.track import write_sequence

    write_sequence(tmp_path / "empty.mp4", [np.full((SIZE, SIZE, 3), 128, np.uint8)] * 3, FPS)
    result = run_cli("track-face", tmp_path / "empty.mp4", "--out", tmp_path / "new/o", *FAST)
    assert result.code == 2 and "no face found" in result.err, result.err
    assert not (tmp_path / "new").exists()
    result = run_cli("track-face", clips["head"], "--out", tmp_path / "new/o", *FAST, "--resume")
    assert result.code == 2 and "no run was started there" in result.err, result.err
    assert not (tmp_path / "new").exists()

    done = tmp_path / "done"                         # a complete run of another video stays complete
    assert run_cli("track-face", clips["head"], "--out", done, *FAST).code == 0
    before = {p.relative_to(done): p.read_bytes() for p in done.rglob("*") if p.is_file()}
    result = run_cli("track-face", tmp_path / "empty.mp4", "--out", done, *FAST, "--overwrite")
    assert result.code == 2 and "no face found" in result.err, result.err
    assert {p.relative_to(done): p.read_bytes() for p in done.rglob("*") if p.is_file()} == before


# -- 4. and 5. folders of frames ------------------------------------------------------------------

def test_frames_of_another_size_are_refused_before_any_work(tmp_path, run_cli):
    from PIL import Image

    frames = tmp_path / "frames"
    frames.mkdir()
    for k, height in enumerate((64, 64, 64, 60, 64)):
        Image.fromarray(np.zeros((height, 80, 3), np.uint8)).save(frames / f"{k:04d}.png")
    result = run_cli("track-face", frames, "--fps", FPS, "--out", tmp_path / "o", *FAST)
    assert result.code == 2, result.err
    assert "frame" in result.err and "0003.png is 80x60" in result.err and "80x64" in result.err, result.err
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_a_folder_of_frames_numbered_without_zeros_is_tracked_as_the_video(clips, tmp_path, run_cli):
    """The video's frames as 1.png ... N.png (ffmpeg's %d.png), the head moving across the frame:
    the folder is tracked as the video is, no face lost."""
    from PIL import Image

    from softras_cl.bench.track import write_sequence
    from softras_cl.io.video import open_video

    moving = [np.roll(image, 6 * k - 33, axis=1) for k, image in enumerate(clips["images"] + clips["images"][:3])]
    write_sequence(tmp_path / "moving.mp4", moving, FPS)
    (tmp_path / "frames").mkdir()
    for frame in open_video(tmp_path / "moving.mp4").frames():
        Image.fromarray(frame.image).save(tmp_path / f"frames/{frame.index + 1}.png")
    scan = ["--scan", "6"]                           # keyframes where the whole face is in the frame
    assert run_cli("track-face", tmp_path / "moving.mp4", "--out", tmp_path / "video", *FAST, *scan).code == 0
    result = run_cli("track-face", tmp_path / "frames", "--fps", FPS, "--out", tmp_path / "folder", *FAST, *scan)
    assert result.code == 0, result.err
    video, folder = _frames(tmp_path / "video"), _frames(tmp_path / "folder")
    np.testing.assert_allclose(folder["time"], video["time"])
    assert folder["held"].tolist() == video["held"].tolist()
    np.testing.assert_allclose(folder["rotation"], video["rotation"], atol=1e-9)
