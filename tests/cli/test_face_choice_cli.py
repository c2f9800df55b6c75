"""`softras-cl fit-face` choosing among detected faces: --face N and --face-box on a photo with two
faces (marker `detect`), what is printed and written (detection.json, params.json, the landmark
files), the face choice in the run record, the combinations refused before any detection, a
detected face that is no face (exit 1 before fitting), and --all-faces items named by the
detection's numbers."""
import json

import numpy as np
import pytest
from PIL import Image
from support.face_outputs import check_landmark_files
from support.face_scenes import nme, read_pts, two_faces

from softras_cl.fitting.batch.client import expand_faces
from softras_cl.fitting.batch.items import collect_items
from softras_cl.fitting.batch.tasks import item_job, run_item
from softras_cl.fitting.detection import FaceCandidate, mediapipe_backend

SMALL = ["--size", "64", "--budget", "fast", "--n-id", "4", "--n-exp", "4", "--n-albedo", "2", "--no-progress"]
#: as test_detection.MAX_NME_PASTED: the pasted, resized faces against their moved shipped points
MAX_NME = 0.07


@pytest.fixture(scope="module")
def two_face_photo(tmp_path_factory):
    """(the two-face picture (head 240 px at the left, 120 px at the right) as a PNG file,
    [large's, small's points])."""
    picture, points = two_faces()
    path = tmp_path_factory.mktemp("two") / "two.png"
    Image.fromarray(picture).save(path)
    return path, points


@pytest.mark.slow
@pytest.mark.detect
def test_face_1_fits_the_smaller_face_says_why_and_records_it(two_face_photo, tmp_path, run_cli, demo_face_model):
    photo, (_, small) = two_face_photo
    out = tmp_path / "fit"
    shown = run_cli("fit-face", photo, "--face", "1", "--out", out, *SMALL)
    assert shown.code == 0, shown.err
    lines = shown.out.splitlines()
    assert lines[0] == "2 faces found by mediapipe, numbered largest first (size: its box and its Face Mesh points; ties: higher score first):"
    assert lines[1].startswith("  face 0: box ") and "chosen" not in lines[1]
    assert lines[2].startswith("* face 1: box ") and lines[2].endswith("chosen: --face 1: number 1 of 2, "
                                                                      "largest first (size: its box and its Face Mesh points; ties: higher score first)")
    detection = json.loads((out / "detection.json").read_text())
    assert detection["chosen"] == 1 and detection["backend"] == "mediapipe" and len(detection["candidates"]) == 2
    chosen = detection["candidates"][1]
    assert chosen["box"][0] > 450 and detection["candidates"][0]["box"][0] < 300     # the right-hand face
    params = json.loads((out / "params.json").read_text())
    assert params["landmarks_input"] == dict(source="mediapipe", file=None, face=1, box=chosen["box"],
                                             score=chosen["score"], reason=detection["reason"], faces_found=2,
                                             detection="detection.json")
    detected = read_pts(out / "landmarks_detected.pts")
    assert nme(detected, small) < MAX_NME
    np.testing.assert_allclose(detected, chosen["landmarks"], atol=1e-3)        # JSON: 3 decimals
    check_landmark_files(out, demo_face_model, detected)
    assert json.loads((out / "run.json").read_text())["inputs"]["landmarks"] == "detected by mediapipe, face 1"

    # the face choice is part of the run record: another choice is another fit, even of the same face
    for choice in ([], ["--face-box", "590,290,150,170"]):
        again = run_cli("fit-face", photo, *choice, "--out", out, *SMALL)
        assert again.code == 2 and "this run's inputs differ (landmarks): add --overwrite" in again.err
    said = again.out.splitlines()[2]
    assert said.startswith("* face 1: box ") and "chosen: --face-box 590,290,150,170: face 1 overlaps it best" in said


@pytest.mark.parametrize("extra, says", [
    (["--face", "1", "--landmarks", "{pts}"], "--face chooses among the faces the detector finds, but the "
                                              "landmarks come from --landmarks {pts}"),
    (["--face-box", "1,2,3,4"], "--face-box chooses among the faces the detector finds, but the landmarks "
                                "come from the file beside the photo, {beside}"),
    (["--face-box", "1,2,3"], "--face-box '1,2,3': expected X,Y,W,H"),
    (["{other}", "--face-box", "1,2,3,4"], "--face-box names a box in one photo"),
    (["--face-box", "1,2,3,4", "--workers", "1"], "--face-box names a box in one photo"),
    (["--face", "1", "--all-faces"], "not allowed with argument"),
    (["{other}", "--face", "1", "--same-person"], "it does not go with --face"),
])
def test_face_choice_refused_before_detecting(tmp_path, run_cli, examples_data, examples_landmarks, monkeypatch,
                                              extra, says):
    monkeypatch.setattr(mediapipe_backend, "find", lambda *a, **k: pytest.fail("detected"))
    photo, other = tmp_path / "a.png", tmp_path / "b.png"
    for path in (photo, other):
        path.write_bytes((examples_data / "astronaut.png").read_bytes())
    beside = photo.with_suffix(".pts")
    beside.write_text((examples_landmarks / "astronaut.pts").read_text())
    names = dict(pts=examples_landmarks / "astronaut.pts", beside=beside, other=other)
    shown = run_cli("fit-face", photo, *[e.format(**names) for e in extra], "--out", tmp_path / "o", *SMALL)
    assert shown.code == 2 and says.format(**names) in shown.err, shown.err
    assert not (tmp_path / "o").exists()


def _fake_faces(points, monkeypatch):
    """The default detector replaced: three faces, largest first, the middle one mirrored (its
    landmarks form no face)."""
    faces = [FaceCandidate(np.array([x, 10.0, side, side]), 0.9, points * scale + [x, 0.0], None, "mediapipe", "fake")
             for x, side, scale in ((0.0, 300.0, 1.0), (300.0, 200.0, 0.6), (420.0, 100.0, 0.3))]
    mirrored = faces[1].landmarks * [-1, 1] + [2 * 300.0 + 200.0, 0.0]
    faces[1] = FaceCandidate(faces[1].box, 0.9, mirrored, None, "mediapipe", "fake")
    monkeypatch.setattr(mediapipe_backend, "available", lambda: True)
    monkeypatch.setattr(mediapipe_backend, "find", lambda image: faces)
    return faces


def test_implausible_detected_face_exits_1_before_fitting(tmp_path, run_cli, examples_data, examples_landmarks,
                                                          monkeypatch):
    _fake_faces(read_pts(examples_landmarks / "astronaut.pts") * 0.3, monkeypatch)
    shown = run_cli("fit-face", examples_data / "astronaut.png", "--face", "1", "--out", tmp_path / "o", *SMALL)
    assert shown.code == 1 and "face 1's landmarks were refused" in shown.err, shown.err
    assert not (tmp_path / "o").exists()


class _InProcess:
    """The two calls of a Dask client that expand_faces makes, run here."""
    def map(self, fn, items, pure=True):
        return [fn(item) for item in items]

    def gather(self, futures):
        return futures


def test_all_faces_items_are_named_and_fitted_by_the_detections_numbers(tmp_path, examples_data,
                                                                         examples_landmarks, monkeypatch):
    faces = _fake_faces(read_pts(examples_landmarks / "astronaut.pts") * 0.3, monkeypatch)
    photo = tmp_path / "group.png"
    photo.write_bytes((examples_data / "astronaut.png").read_bytes())
    items = expand_faces(_InProcess(), collect_items([photo], "face", {}))
    assert [(it.name, it.face, it.all_faces) for it in items] == [("group-face0", 0, True), ("group-face2", 2, True)]
    job = item_job(items[1])
    job.read()
    found = job.landmarks
    assert found.index == 2 and found.detection.reason == "--all-faces: face 2"
    np.testing.assert_array_equal(found.points, faces[2].landmarks)


def test_batch_face_n_fits_that_face_of_each_photo_and_records_it(tmp_path, examples_data, examples_landmarks,
                                                                   monkeypatch):
    faces = _fake_faces(read_pts(examples_landmarks / "astronaut.pts") * 0.3, monkeypatch)
    photos = [tmp_path / "a.png", tmp_path / "b.png"]
    for photo in photos:
        photo.write_bytes((examples_data / "astronaut.png").read_bytes())
    photos[1].with_suffix(".pts").write_text((examples_landmarks / "astronaut.pts").read_text())
    detected, beside = collect_items(photos, "face", {}, face=2)
    job = item_job(detected)
    job.read()
    found = job.landmarks
    assert found.index == 2 and found.detection.reason.startswith("--face 2: number 2 of 3")
    np.testing.assert_array_equal(found.points, faces[2].landmarks)
    assert job.record()["inputs"]["landmarks"] == "detected by mediapipe, face 2"
    row = run_item(beside, str(tmp_path / "out"))
    assert row["status"] == "failed" and row["error"].startswith("--face chooses among the faces the detector finds, "
                                                                 "but the landmarks come from the file beside the photo")
