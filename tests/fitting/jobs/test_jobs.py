"""fitting.jobs: each data path's job reads its inputs once, chooses the right recipe and runs
into an output folder as the commands and the batch tasks do (run_fit, fit_and_write); the body
target's kind and a photo's EXIF field of view."""
import json
from types import SimpleNamespace

import numpy as np
import pytest

from softras_cl.errors import InputError, ResultError
from softras_cl.fitting.jobs import face_photo
from softras_cl.fitting.jobs.body import body_job, input_kind
from softras_cl.fitting.jobs.body_photo import BodyPhotoJob, photo_fov
from softras_cl.fitting.jobs.body_target import BodyTargetJob
from softras_cl.fitting.jobs.face_photo import FacePhotoJob
from softras_cl.fitting.jobs.run import run_fit
from softras_cl.io import images
from softras_cl.io.images import write_image


def test_a_face_photo_is_decoded_once(examples_data, examples_landmarks, monkeypatch):
    """The photo is decoded once for the fit and the landmarks' checks (read_photo), not once per
    reader; the landmarks of the file given are taken as they are."""
    calls = []
    decode = images._decode
    monkeypatch.setattr(images, "_decode", lambda path: calls.append(path) or decode(path))
    job = FacePhotoJob(examples_data / "astronaut.png", examples_landmarks / "astronaut.pts", dict(size=64))
    job.read()
    assert len(calls) == 1
    assert job.photo.linear.shape == (512, 512, 3) and job.photo.rgb8.dtype == np.uint8
    assert job.landmarks.source == "file" and not job.landmarks.on_face_mesh
    np.testing.assert_array_equal(job.photo.linear, images.read_image(examples_data / "astronaut.png")[..., :3])


def test_a_job_checks_its_options_before_reading(tmp_path):
    with pytest.raises(InputError, match="size must be an integer >= 32"):
        FacePhotoJob(tmp_path / "missing.png", None, dict(size=8))
    with pytest.raises(InputError, match="budget must be one of"):
        body_job(tmp_path / "missing.png", None, dict(budget="slow", input="photo"))


def test_body_job_chooses_the_photo_or_the_target_job(tmp_path, examples_data):
    parts = np.zeros((40, 40, 3))
    parts[10:30, 15:25] = (0.2, 0.5, 0.7)
    write_image(tmp_path / "parts.png", parts)
    assert isinstance(body_job(examples_data / "people" / "cameraman.png"), BodyPhotoJob)
    target = body_job(tmp_path / "parts.png")
    assert isinstance(target, BodyTargetJob) and not target.silhouette
    assert body_job(tmp_path / "parts.png", None, dict(input="mask")).silhouette
    with pytest.raises(InputError, match="--joints is for part-coloured targets"):
        body_job(examples_data / "people" / "cameraman.png", tmp_path / "j.txt", dict(input="photo"))


class _FakeJob:
    """A job whose fit returns ``metrics`` at once: what run_fit does around any job."""
    command, required = "fit-fake", ("error",)

    def __init__(self, photo, metrics):
        self.photo, self.metrics, self.written = photo, metrics, []

    def record(self):
        return dict(command=self.command, inputs=dict(photo="abc"), options={})

    def files(self):
        return [str(self.photo)]

    def fit(self, folder, progress, resume):
        return SimpleNamespace(metrics=lambda: dict(self.metrics), result=SimpleNamespace(interrupted=False))

    def write(self, fit, folder, metrics, seconds):
        self.written.append(folder)
        return metrics

    def summary(self, metrics):
        return f"error {metrics['error']}"


def test_run_fit_writes_the_outputs_then_complete_json(tmp_path):
    job = _FakeJob(tmp_path / "in.png", dict(error=1.5))
    run = run_fit(job, tmp_path / "out", progress=False)
    assert run.metrics == dict(error=1.5) and not run.interrupted and job.written == [run.folder]
    done = json.loads((tmp_path / "out" / "complete.json").read_text())
    assert done["status"] == "done" and done["metrics"] == dict(error=1.5) and done["command"] == "fit-fake"
    assert str(tmp_path / "in.png") in json.dumps(done)


def test_run_fit_refuses_a_non_finite_result_without_complete_json(tmp_path):
    job = _FakeJob(tmp_path / "in.png", dict(error=float("nan")))
    with pytest.raises(ResultError, match="error is nan"):
        run_fit(job, tmp_path / "out", progress=False)
    assert job.written == [] and not (tmp_path / "out" / "complete.json").exists()


def test_face_model_refuses_model_landmarks_without_a_model():
    with pytest.raises(ValueError, match="--model-landmarks needs --model"):
        face_photo.face_model(dict(model_landmarks="x.txt"))


def test_input_kind_tells_part_coloured_targets_from_photos(tmp_path, examples_data):
    parts = np.zeros((40, 40, 3))
    parts[10:30, 15:25] = (0.2, 0.5, 0.7)
    write_image(tmp_path / "parts.png", parts)
    assert input_kind(tmp_path / "parts.png") == "parts"
    assert input_kind(examples_data / "astronaut.png") == "photo"
    assert input_kind(examples_data / "astronaut.png", "parts") == "parts"
    assert input_kind(examples_data / "astronaut.png", joints=True) == "parts"     # joints: a rendered target
    assert input_kind(examples_data / "people" / "cameraman.png") == "photo"                   # grey, not a mask
    assert input_kind(tmp_path / "parts.png", silhouette=True) == "mask"
    np.save(tmp_path / "t.npy", parts)
    assert input_kind(tmp_path / "t.npy") == "parts"
    with pytest.raises(InputError, match="--input must be one of"):
        input_kind(tmp_path / "parts.png", "video")


def test_photo_fov_reads_the_exif_35mm_focal_length(tmp_path):
    from PIL import Image

    image = Image.new("RGB", (300, 200))
    exif = image.getexif()
    exif.get_ifd(0x8769)[41989] = 50                     # 50 mm equivalent, by the diagonal
    image.save(tmp_path / "exif.jpg", exif=exif)
    image.save(tmp_path / "plain.jpg")
    expected = 2 * np.degrees(np.arctan(np.tan(np.arctan(43.27 / 2 / 50)) * 200 / np.hypot(200, 300)))
    assert photo_fov(tmp_path / "exif.jpg", (200, 300)) == pytest.approx(expected)
    assert photo_fov(tmp_path / "plain.jpg", (200, 300)) is None
