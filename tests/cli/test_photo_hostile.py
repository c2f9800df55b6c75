"""Hostile real inputs on the photo paths of fit-face, fit-body and detect-landmarks: each gets
one line naming what is wrong and the documented exit code, before anything is written, or a
fit that stays valid (docs/reliability.md, "Hostile photos")."""
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import png
import pytest
from PIL import Image

from softras_cl.errors import EXIT_INPUT, EXIT_INTERRUPTED, EXIT_OUTPUT, EXIT_RESULT

REPO = Path(__file__).resolve().parents[2]
FAST_FACE = ["--size", "64", "--budget", "fast", "--n-id", "4", "--n-exp", "4", "--n-albedo", "2", "--no-progress"]
FAST_BODY = ["--size", "64", "--budget", "fast", "--no-progress"]


def one_line(result) -> str:
    """The error line of a failed run: exactly one line, no traceback."""
    assert "Traceback" not in result.err, result.err
    lines = [line for line in result.err.splitlines() if line.strip()]
    assert len(lines) == 1, result.err
    return lines[0]


def grey16(source: Path, out: Path) -> Path:
    """``source`` as a 16-bit greyscale PNG (its 8-bit grey widened: v * 257)."""
    grey = np.asarray(Image.open(source).convert("L")).astype(np.uint16) * 257
    with open(out, "wb") as f:
        png.Writer(width=grey.shape[1], height=grey.shape[0], greyscale=True, bitdepth=16).write(f, grey)
    return out


def crop(source: Path, box, out: Path) -> Path:
    Image.open(source).crop(box).save(out)
    return out


# ---- 1. 16-bit greyscale PNGs reach the detectors as the 8-bit file would ----------------------
@pytest.mark.detect
def test_face_detection_of_a_16bit_grey_png(tmp_path, examples_data):
    from softras_cl.fitting.jobs.face_photo import FacePhotoJob

    job = FacePhotoJob(grey16(examples_data / "astronaut.png", tmp_path / "astronaut16.png"))
    job.read()                                       # fit-face's reading and detection
    eight = FacePhotoJob(examples_data / "astronaut.png")
    eight.read()
    assert job.landmarks.source == "mediapipe"
    assert np.abs(job.landmarks.points - eight.landmarks.points).max() < 8.0     # the same face


@pytest.mark.detect
def test_person_detection_of_a_16bit_grey_png(tmp_path, examples_data):
    from softras_cl.fitting.jobs.body_photo import BodyPhotoJob

    job = BodyPhotoJob(grey16(examples_data / "people" / "cameraman.png", tmp_path / "cameraman16.png"))
    job.read()                                       # fit-body's reading and person detection
    x, y, w, h = job.detection.box
    assert job.detection.score > 0.8 and w > 150 and h > 300


# ---- 2. fit-body keeps the body in front of the camera, or refuses before writing --------------
@pytest.mark.slow
@pytest.mark.detect
def test_fit_body_on_the_upper_half_of_a_person(run_cli, tmp_path, examples_data):
    upper = crop(examples_data / "people" / "cameraman.png", (0, 0, 512, 256), tmp_path / "upper.png")
    result = run_cli("fit-body", upper, "--out", tmp_path / "fit", *FAST_BODY)
    assert result.code == 0, result.err
    assert (tmp_path / "fit" / "complete.json").is_file()
    assert "behind the camera" not in result.err


@pytest.mark.detect
def test_fit_body_with_a_field_of_view_near_180_degrees(run_cli, tmp_path, examples_data):
    out = tmp_path / "fit"
    result = run_cli("fit-body", examples_data / "people" / "cameraman.png", "--fov", "179", "--out", out,
                     *FAST_BODY)
    assert result.code == EXIT_RESULT
    line = one_line(result)
    assert "the body cannot be fitted in view: with a field of view of 179 degrees (from --fov)" in line
    assert "smaller --fov" in line
    assert not out.exists()                          # nothing half-written


# ---- 3. detect-landmarks --overlay-scale ------------------------------------------------------
@pytest.mark.parametrize("scale", ["50", "0", "-1", "nan", "inf", "x"])
def test_overlay_scale_is_checked_before_anything(run_cli, tmp_path, examples_data, monkeypatch, scale):
    from softras_cl.fitting.detection import find

    monkeypatch.setattr(find, "find_faces", lambda *a, **k: pytest.fail("detected before checking the option"))
    result = run_cli("detect-landmarks", examples_data / "astronaut.png", "--out", tmp_path / "a.pts",
                     "--overlay", tmp_path / "o.png", "--overlay-scale", scale)
    assert result.code == EXIT_INPUT
    assert f"argument --overlay-scale: must be a number in (0, 4], got {scale!r}" in result.err
    assert list(tmp_path.iterdir()) == []


# ---- 4. a landmark file beside the photo ------------------------------------------------------
@pytest.mark.detect
def test_a_landmark_file_of_another_face_beside_the_photo_is_refused(run_cli, tmp_path, examples_data,
                                                                     examples_landmarks):
    photo = Path(shutil.copy(examples_data / "astronaut.png", tmp_path / "astronaut.png"))
    beside = Path(shutil.copy(examples_landmarks / "grace_hopper.pts", tmp_path / "astronaut.pts"))
    out = tmp_path / "fit"
    result = run_cli("fit-face", photo, "--out", out, *FAST_FACE)
    assert result.code == EXIT_INPUT
    line = one_line(result)
    assert f"the landmark file beside the photo, {beside}," in line
    assert "does not overlap the face the detector finds" in line and "--landmarks" in line
    assert not out.exists()


@pytest.mark.slow
@pytest.mark.detect
def test_the_landmark_file_beside_the_photo_is_named(run_cli, tmp_path, examples_data, examples_landmarks):
    photo = Path(shutil.copy(examples_data / "astronaut.png", tmp_path / "astronaut.png"))
    beside = Path(shutil.copy(examples_landmarks / "astronaut.pts", tmp_path / "astronaut.pts"))
    result = run_cli("fit-face", photo, "--out", tmp_path / "fit", *FAST_FACE)
    assert result.code == 0, result.err
    assert result.out.splitlines()[0] == (f"landmarks: {beside} (the file beside the photo; --landmarks FILE "
                                          "gives another)")


# ---- 5. a detected face cut by the photo's border ---------------------------------------------
@pytest.mark.detect
def test_a_detected_face_cut_by_the_border(run_cli, tmp_path, examples_data):
    cut = crop(examples_data / "astronaut.png", (200, 0, 512, 512), tmp_path / "cut.png")
    out = tmp_path / "fit"
    result = run_cli("fit-face", cut, "--out", out, *FAST_FACE)
    assert result.code == EXIT_INPUT
    line = one_line(result)
    assert f"face 0 found in {cut} is cut by the photo's border:" in line
    assert "outside the 312x512 photo" in line and "belong to this photo" not in line
    assert not out.exists()


# ---- 6. --out before the photo; the summary's time is the whole run's ---------------------------
@pytest.mark.parametrize("command", ["fit-face", "fit-body"])
def test_out_is_checked_before_the_photo_is_read(run_cli, tmp_path, examples_data, monkeypatch, command):
    from softras_cl.fitting.jobs import body_photo, face_photo

    for module in (face_photo, body_photo):
        monkeypatch.setattr(module, "read_photo", lambda *a: pytest.fail("read the photo before checking --out"))
    (tmp_path / "file.txt").write_text("x")
    photo = examples_data / ("astronaut.png" if command == "fit-face" else "people/cameraman.png")
    options = FAST_FACE if command == "fit-face" else FAST_BODY
    result = run_cli(command, photo, "--out", tmp_path / "file.txt", *options)
    assert result.code == EXIT_OUTPUT
    assert f"--out {tmp_path / 'file.txt'} exists and is not a folder" in one_line(result)


@pytest.mark.slow
def test_the_summary_counts_reading_the_photo(run_cli, tmp_path, examples_data, examples_landmarks,
                                              monkeypatch):
    from softras_cl.fitting.jobs import face_photo

    slow_read = face_photo.read_photo

    def read_slowly(path):
        time.sleep(3.0)                          # as an 8000x6000 photo would take
        return slow_read(path)

    monkeypatch.setattr(face_photo, "read_photo", read_slowly)
    result = run_cli("fit-face", examples_data / "astronaut.png", "--landmarks", examples_landmarks / "astronaut.pts",
                     "--out", tmp_path / "fit", *FAST_FACE)
    assert result.code == 0, result.err
    summary = result.out.splitlines()[-1]
    seconds = float(summary.split(" done in ")[1].split(" s")[0])
    assert seconds >= 3.0, summary
    fit_seconds = json.loads((tmp_path / "fit" / "complete.json").read_text())["seconds"]
    assert fit_seconds < seconds - 2.5           # the records keep the fit's own time


# ---- 7. a folder or a FIFO as the photo; --all-faces without a face ---------------------------
def test_detect_landmarks_on_a_folder(run_cli, tmp_path):
    (tmp_path / "photo.png").mkdir()
    result = run_cli("detect-landmarks", tmp_path / "photo.png", "--out", tmp_path / "a.pts")
    assert result.code == EXIT_INPUT
    assert f"{tmp_path / 'photo.png'} is a directory, not an image file" in one_line(result)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this system")
@pytest.mark.parametrize("command", ["detect-landmarks", "fit-face", "fit-body"])
def test_a_fifo_as_the_photo(run_cli, tmp_path, command):
    fifo = tmp_path / "photo.png"
    os.mkfifo(fifo)
    out = tmp_path / ("a.pts" if command == "detect-landmarks" else "fit")
    result = run_cli(command, fifo, "--out", out)
    assert result.code == EXIT_INPUT
    assert f"{fifo} is not a regular file (a FIFO)" in one_line(result)


@pytest.fixture
def noise(tmp_path) -> Path:
    """A photo of noise: no face, no person."""
    rng = np.random.default_rng(0)
    path = tmp_path / "noise.png"
    Image.fromarray((rng.random((200, 300, 3)) * 255).astype(np.uint8)).save(path)
    return path


@pytest.mark.slow
@pytest.mark.detect
def test_all_faces_on_a_photo_without_a_face_exits_as_without_it(run_cli, tmp_path, noise):
    pytest.importorskip("distributed")
    alone = run_cli("fit-face", noise, "--out", tmp_path / "one", *FAST_FACE)
    every = run_cli("fit-face", noise, "--all-faces", "--out", tmp_path / "all", *FAST_FACE)
    assert alone.code == every.code == EXIT_INPUT
    assert f"no face found in {noise}" in one_line(every)


# ---- 8. --input mask on a photo ---------------------------------------------------------------
@pytest.mark.parametrize("flag", [["--input", "mask"], ["--silhouette"]])
def test_a_photo_given_as_a_mask_is_refused(run_cli, tmp_path, examples_data, flag):
    photo = examples_data / "people" / "cameraman.png"
    result = run_cli("fit-body", photo, *flag, "--out", tmp_path / "fit", *FAST_BODY)
    assert result.code == EXIT_INPUT
    line = one_line(result)
    assert f"{' '.join(flag)} says {photo} is a mask, but it is not one" in line
    assert not (tmp_path / "fit").exists()


def test_a_two_level_mask_is_accepted(tmp_path):
    from softras_cl.fitting.jobs.body_target import check_mask

    mask = np.zeros((40, 30))
    mask[10:30, 10:20] = 1.0
    mask[10:30, 9] = 0.5                            # an anti-aliased edge
    check_mask(mask, tmp_path / "m.png", "--input mask")


# ---- 9. manifests and Ctrl-C in a batch -------------------------------------------------------
def test_a_bad_manifest_cell_names_the_file_and_line(run_cli, tmp_path, examples_data):
    manifest = tmp_path / "items.csv"
    manifest.write_text(f"photo,size\n{examples_data / 'astronaut.png'},64\n{examples_data / 'grace_hopper.jpg'},abc\n")
    result = run_cli("fit-face", "--manifest", manifest, "--out", tmp_path / "batch")
    assert result.code == EXIT_INPUT
    line = one_line(result)
    assert line.endswith(f"manifest column 'size': 'abc' is not a int (manifest {manifest} line 3)")


def test_a_missing_photo_in_a_manifest(run_cli, tmp_path):
    manifest = tmp_path / "items.csv"
    manifest.write_text("photo\nmissing.png\n")
    result = run_cli("fit-face", "--manifest", manifest, "--out", tmp_path / "batch")
    assert result.code == EXIT_INPUT
    assert (f"photo not found: {tmp_path / 'missing.png'} (manifest {manifest} line 2)"
            == one_line(result).split(": ", 1)[1])


def test_ctrl_c_in_a_batch_says_so(run_cli, tmp_path, examples_data, monkeypatch):
    from softras_cl.fitting.batch import client

    def interrupted(items, out, kind, **kwargs):
        rows = [dict(status="ok"), dict(status="skipped"), dict(status="cancelled")]
        return client.BatchResult(rows, True, Path(out), {"ok": 1, "skipped": 1, "cancelled": 1})

    monkeypatch.setattr(client, "fit_many", interrupted)
    result = run_cli("fit-face", examples_data / "astronaut.png", examples_data / "grace_hopper.jpg",
                     "--out", tmp_path / "batch", "--no-progress")
    assert result.code == EXIT_INTERRUPTED
    assert one_line(result) == (f"softras-cl fit-face: interrupted: 2 of 3 items finished (1 ok, 1 skipped), kept "
                                f"and listed in {tmp_path / 'batch'}/results.csv; run the same command again to "
                                "fit the others")


# ---- 10. MediaPipe's own lines stay off stderr ------------------------------------------------
def _stderr_of(code: str) -> str:
    env = dict(os.environ)
    for name in ("GLOG_minloglevel", "TF_CPP_MIN_LOG_LEVEL"):
        env.pop(name, None)
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stderr


@pytest.mark.detect
def test_detect_landmarks_prints_nothing_on_stderr(tmp_path):
    err = _stderr_of("import sys; from softras_cl.cli import main; "
                     f"sys.exit(main(['detect-landmarks', 'examples/data/astronaut.png', '--out', {str(tmp_path / 'a.pts')!r}]))")
    assert err == ""


@pytest.mark.detect
def test_person_detection_prints_nothing_on_stderr():
    err = _stderr_of("from softras_cl.io.images import read_rgb8; "
                     "from softras_cl.fitting.detection.people import detect_person; "
                     "detect_person(read_rgb8('examples/data/people/cameraman.png'))")
    assert err == ""
