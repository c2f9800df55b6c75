"""softras_cl.io.video: frames and their times from a video or a folder, rotation, bad files."""
from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from softras_cl.errors import InputError
from softras_cl.io import video
from softras_cl.io.video import VideoReadError, VideoWriter, open_video, upright

pytestmark = pytest.mark.video

H, W = 48, 64


def marked_frame(k: int) -> np.ndarray:
    """A grey frame with a white block in its top-left corner and a level that tells frame k."""
    img = np.full((H, W, 3), 40 + 20 * (k % 8), np.uint8)
    img[:16, :16] = 255
    return img


def noisy_frame(k: int) -> np.ndarray:
    """Noise: frames that take many bytes, so that a cut file ends among them."""
    return np.random.default_rng(k).integers(0, 256, (H, W, 3), dtype=np.uint8)


def write_mp4(path, times_ms, rotation=None, faststart=False, frame=marked_frame):
    """An H.264 mp4 of frame(k) written straight through PyAV (not through the module under test)."""
    import av

    with av.open(str(path), "w", options={"movflags": "faststart"} if faststart else {}) as c:
        s = c.add_stream("libx264", rate=30)
        s.width, s.height, s.pix_fmt = W, H, "yuv420p"
        s.codec_context.time_base = Fraction(1, 1000)
        if rotation is not None:
            s.set_display_rotation(rotation)
        for k, ms in enumerate(times_ms):
            f = av.VideoFrame.from_ndarray(frame(k), format="rgb24")
            f.pts, f.time_base = ms, Fraction(1, 1000)
            for p in s.encode(f):
                c.mux(p)
        for p in s.encode():
            c.mux(p)


def test_frames_keep_variable_times(tmp_path):
    times = [0, 33, 80, 100, 190]
    write_mp4(tmp_path / "v.mp4", times)
    source = open_video(tmp_path / "v.mp4")
    frames = list(source.frames())
    assert [f.index for f in frames] == list(range(5))
    assert [round(f.time * 1000) for f in frames] == times
    assert frames[0].image.shape == (H, W, 3) and frames[0].image.dtype == np.uint8
    assert np.abs(frames[2].image[30, 40].astype(int) - (40 + 20 * 2)).max() <= 4   # lossy codec
    assert source.frame_count == 5
    assert [f.index for f in source.frames(start=3)] == [3, 4]
    chosen = list(source.frames(only={1, 3}))
    assert [f.index for f in chosen] == [1, 3] and [f.time for f in chosen] == [frames[1].time, frames[3].time]
    assert np.array_equal(chosen[1].image, frames[3].image)


def test_display_rotation_is_applied(tmp_path):
    write_mp4(tmp_path / "r.mp4", [0, 33], rotation=90)
    frame = next(open_video(tmp_path / "r.mp4").frames())
    # turned 90 degrees counter-clockwise: 64 x 48, the top-left block now bottom-left
    assert frame.image.shape == (W, H, 3)
    assert frame.image[W - 5, 5].min() > 200 and frame.image[5, 5].max() < 120


def test_upright_turns_counter_clockwise():
    img = np.zeros((2, 3, 3), np.uint8)
    img[0, 0] = 255
    assert upright(img, 90)[2, 0, 0] == 255          # top-left -> bottom-left
    assert upright(img, -90)[0, 1, 0] == 255         # top-left -> top-right
    assert upright(img, 0) is img


@pytest.mark.parametrize("faststart", [False, True])
def test_truncated_video_names_the_file(tmp_path, faststart):
    write_mp4(tmp_path / "full.mp4", [33 * k for k in range(30)], faststart=faststart, frame=noisy_frame)
    data = (tmp_path / "full.mp4").read_bytes()
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(VideoReadError, match="cut.mp4") as caught:
        list(open_video(cut).frames())
    if faststart:                      # the index is at the front: the first frames decode
        assert 0 < caught.value.frames_read < 30
        assert "breaks off" in str(caught.value)


def test_not_a_video(tmp_path):
    (tmp_path / "junk.mp4").write_bytes(b"not a video")
    with pytest.raises(InputError, match="cannot read video .*junk.mp4"):
        open_video(tmp_path / "junk.mp4")
    with pytest.raises(InputError, match="video not found"):
        open_video(tmp_path / "missing.mp4")


def test_folder_of_frames(tmp_path):
    from PIL import Image

    for k in (2, 0, 1):
        Image.fromarray(marked_frame(k)).save(tmp_path / f"frame{k:03d}.png")
    (tmp_path / "notes.txt").write_text("not a frame")
    with pytest.raises(InputError, match="--fps"):
        open_video(tmp_path)
    frames = list(open_video(tmp_path, fps=25).frames())
    assert [f.time for f in frames] == [0.0, 0.04, 0.08]
    assert [int(f.image[30, 40, 0]) for f in frames] == [40, 60, 80]
    chosen = list(open_video(tmp_path, fps=25).frames(start=1, only={0, 2}))
    assert [(f.index, f.time, int(f.image[30, 40, 0])) for f in chosen] == [(2, 0.08, 80)]
    with pytest.raises(InputError, match="--fps must be"):
        open_video(tmp_path, fps=0)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no frames"):
        open_video(tmp_path / "empty")


def test_fps_refused_for_a_video_file(tmp_path):
    write_mp4(tmp_path / "v.mp4", [0, 33])
    with pytest.raises(InputError, match="--fps is for a folder"):
        open_video(tmp_path / "v.mp4", fps=30)


def test_writer_round_trip(tmp_path):
    with VideoWriter(tmp_path / "w.mp4", fps=30, crf=10) as w:
        for k, t in enumerate([0.0, 0.05, 0.07]):
            w.write(np.pad(marked_frame(k), ((0, 1), (0, 1), (0, 0))), t)   # odd size: padded
        with pytest.raises(ValueError, match="must increase"):
            w.write(np.zeros((H + 1, W + 1, 3), np.uint8), 0.07)
        with pytest.raises(ValueError, match="first one's size"):
            w.write(marked_frame(0), 0.5)
    frames = list(open_video(tmp_path / "w.mp4").frames())
    assert [round(f.time, 3) for f in frames] == [0.0, 0.05, 0.07]
    assert frames[0].image.shape == (H + 2, W + 2, 3)
    assert abs(int(frames[1].image[30, 40, 0]) - 60) <= 3


def test_expand_videos_names_files_folders_of_videos_or_frames_and_globs(tmp_path):
    from softras_cl.io.video import expand_videos

    (tmp_path / "clips").mkdir()
    for name in ("b.mp4", "a.MOV", ".hidden.mp4", "notes.txt"):
        (tmp_path / "clips" / name).write_bytes(b"")
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "0001.png").write_bytes(b"")
    (tmp_path / "one.mkv").write_bytes(b"")
    clips = [tmp_path / "clips" / "a.MOV", tmp_path / "clips" / "b.mp4"]
    assert expand_videos([tmp_path / "clips"]) == clips                       # its videos, by name
    assert expand_videos([tmp_path / "frames"]) == [tmp_path / "frames"]      # one video of frames
    assert expand_videos([tmp_path / "one.mkv", tmp_path / "clips", str(tmp_path / "clips" / "*.mp4")]) == \
        [tmp_path / "one.mkv", *clips]                                        # each once, in order
    assert expand_videos([str(tmp_path / "f*")]) == [tmp_path / "frames"]
    with pytest.raises(InputError, match="video not found: .*missing.mp4"):
        expand_videos([tmp_path / "missing.mp4"])
    with pytest.raises(InputError, match="no videos or folders match"):
        expand_videos([str(tmp_path / "*.avi")])


def test_frames_decoded_after_a_break_keep_their_times(tmp_path):
    """A cut file (60% of its bytes): the frames the decoder still holds at the break come with
    their presentation times (they had none: NaN), then the break is reported."""
    times = [33 * k for k in range(30)]
    write_mp4(tmp_path / "full.mp4", times, faststart=True, frame=noisy_frame)
    data = (tmp_path / "full.mp4").read_bytes()
    (tmp_path / "cut.mp4").write_bytes(data[: int(len(data) * 0.6)])
    frames = []
    with pytest.raises(VideoReadError, match="cut.mp4 breaks off after") as caught:
        for frame in open_video(tmp_path / "cut.mp4").frames():
            frames.append(frame)
    assert 0 < len(frames) == caught.value.frames_read < 30
    ms = [f.time * 1000 for f in frames]
    assert np.all(np.isfinite(ms)) and np.all(np.diff(ms) > 0), ms
    assert set(round(t) for t in ms) <= set(times), ms


def _save_frames(folder, images, names):
    from PIL import Image

    folder.mkdir()
    for image, name in zip(images, names):
        Image.fromarray(image).save(folder / name)


def test_folder_frames_numbered_without_zeros_come_in_number_order(tmp_path):
    """1.png ... 12.png (as ffmpeg's %d.png writes them) are frames 1 to 12, not 1, 10, 11, 12, 2, ...:
    the folder gives the frames a video of them gives, at the same times."""
    images = [marked_frame(k) for k in range(12)]
    _save_frames(tmp_path / "plain", images, [f"{k + 1}.png" for k in range(12)])
    _save_frames(tmp_path / "named", images, [f"take2_frame{k + 1}.png" for k in range(12)])
    for folder in ("plain", "named"):
        frames = list(open_video(tmp_path / folder, fps=10).frames())
        assert [f.time for f in frames] == [k / 10 for k in range(12)]
        for frame, image in zip(frames, images):
            np.testing.assert_array_equal(frame.image, image, err_msg=f"{folder}: frame {frame.index}")


def test_folder_frames_of_another_size_are_refused_before_any_frame(tmp_path):
    """A frame of another size (here the third; a stray thumbnail, a crop) is named when the
    folder is opened; a frame turned by its EXIF orientation counts upright."""
    from PIL import Image

    images = [marked_frame(k) for k in range(4)]
    images[2] = np.zeros((H + 2, W, 3), np.uint8)
    _save_frames(tmp_path / "sizes", images, [f"{k:04d}.png" for k in range(4)])
    other = r"frame .*0002\.png is 64x50, but the frames before it are 64x48 \(the first: .*0000\.png\)"
    with pytest.raises(InputError, match=other):
        open_video(tmp_path / "sizes", fps=10)

    images = [marked_frame(k) for k in range(3)]
    _save_frames(tmp_path / "turned", images, [f"{k:04d}.jpg" for k in range(3)])
    exif = Image.Exif()
    exif[0x0112] = 6                               # shown turned a quarter: 48x64
    Image.fromarray(images[1]).save(tmp_path / "turned/0001.jpg", exif=exif)
    with pytest.raises(InputError, match=r"0001\.jpg is 48x64"):
        open_video(tmp_path / "turned", fps=10)


def _move_chunk_to_the_end(path, kind: bytes) -> None:
    """Rewrite a PNG file with its chunk ``kind`` just before IEND (after the image data)."""
    data = path.read_bytes()
    at, chunks = 8, []
    while at < len(data):
        length = int.from_bytes(data[at:at + 4], "big")
        chunks.append(data[at:at + 12 + length])
        at += 12 + length
    moved = [c for c in chunks if c[4:8] == kind]
    rest = [c for c in chunks if c[4:8] != kind]
    path.write_bytes(data[:8] + b"".join(rest[:-1] + moved + rest[-1:]))


@pytest.mark.parametrize("where", ["before the image data", "after the image data"])
def test_a_png_frame_turned_by_its_exif_counts_upright(tmp_path, where):
    """PNG frames: the EXIF orientation is read from an eXIf chunk wherever it stands (the
    headers are scanned; Pillow would decode the image to find one after the data), and a
    PNG without one is sized from its header alone."""
    from PIL import Image

    images = [marked_frame(k) for k in range(3)]
    _save_frames(tmp_path / "turned", images, [f"{k:04d}.png" for k in range(3)])
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(images[1]).save(tmp_path / "turned/0001.png", exif=exif)
    if where == "after the image data":
        _move_chunk_to_the_end(tmp_path / "turned/0001.png", b"eXIf")
    assert video._png_has_exif(tmp_path / "turned/0001.png") and not video._png_has_exif(tmp_path / "turned/0000.png")
    with pytest.raises(InputError, match=r"0001\.png is 48x64"):
        open_video(tmp_path / "turned", fps=10)
