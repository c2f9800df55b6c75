"""`softras-cl detect-landmarks` with the default backend (marker `detect`): which face is
written and why, what is printed, the JSON of every face, the overlay, and the errors (a --face
that was not found, dlib options without dlib, implausible landmarks: exit 1)."""
import json

import numpy as np
import pytest
from PIL import Image
from support.face_scenes import nme, read_pts, two_faces

from softras_cl.fitting.detection import FaceCandidate, mediapipe_backend

#: as test_detection.MAX_NME_PASTED: the pasted, resized faces against their moved shipped points
MAX_NME = 0.07


@pytest.fixture(scope="module")
def two_face_photo(tmp_path_factory):
    """(the two-face picture as a PNG file, [large's, small's points])."""
    picture, points = two_faces()
    path = tmp_path_factory.mktemp("two") / "two.png"
    Image.fromarray(picture).save(path)
    return path, points


@pytest.mark.detect
def test_largest_face_by_default(two_face_photo, tmp_path, run_cli):
    photo, (large, small) = two_face_photo
    shown = run_cli("detect-landmarks", photo, "--out", tmp_path / "f.pts", "--overlay", tmp_path / "o.png")
    assert shown.code == 0, shown.err
    lines = shown.out.splitlines()
    assert lines[0] == "2 faces found by mediapipe, numbered largest first (size: its box and its Face Mesh points; ties: higher score first):"
    assert lines[1].startswith("* face 0: box ") and "chosen: the largest of 2 faces" in lines[1]
    assert lines[2].startswith("  face 1: box ") and "score 0.9" in lines[2]
    assert nme(read_pts(tmp_path / "f.pts"), large) < MAX_NME
    doc = json.loads((tmp_path / "f.json").read_text())
    assert doc["chosen"] == 0 and doc["backend"] == "mediapipe" and doc["written"] == {"0": str(tmp_path / "f.pts")}
    assert [len(c["landmarks"]) for c in doc["candidates"]] == [68, 68]
    assert [len(c["dense"]) for c in doc["candidates"]] == [478, 478]
    assert nme(np.array(doc["candidates"][1]["landmarks"]), small) < MAX_NME
    x, y, w, h = doc["candidates"][1]["box"]
    assert f"face 1: box {x:.0f},{y:.0f},{w:.0f},{h:.0f} (x,y,w,h)" in lines[2]
    overlay = np.asarray(Image.open(tmp_path / "o.png").convert("RGB"))
    assert overlay.shape == (600, 900, 3)
    top_edge = overlay[int(round(y)), int(x) + 5:int(x + w) - 5]      # face 1's box, drawn in red
    assert (top_edge == [255, 64, 64]).all(axis=1).mean() > 0.8


@pytest.mark.detect
def test_face_number_and_face_box_choose_the_other(two_face_photo, tmp_path, run_cli):
    photo, (_, small) = two_face_photo
    shown = run_cli("detect-landmarks", photo, "--out", tmp_path / "n.pts", "--face", "1")
    assert shown.code == 0 and "chosen: --face 1: number 1 of 2" in shown.out
    assert nme(read_pts(tmp_path / "n.pts"), small) < MAX_NME
    shown = run_cli("detect-landmarks", photo, "--out", tmp_path / "b.pts", "--face-box", "590,290,140,160",
                    "--json", tmp_path / "faces.json")
    assert shown.code == 0 and "chosen: --face-box 590,290,140,160: face 1 overlaps it best" in shown.out
    assert nme(read_pts(tmp_path / "b.pts"), small) < MAX_NME
    assert json.loads((tmp_path / "faces.json").read_text())["chosen"] == 1 and not (tmp_path / "b.json").exists()


@pytest.mark.detect
def test_all_faces(two_face_photo, tmp_path, run_cli):
    photo, (large, small) = two_face_photo
    shown = run_cli("detect-landmarks", photo, "--out", tmp_path / "f.pts", "--all-faces")
    assert shown.code == 0, shown.err
    assert nme(read_pts(tmp_path / "f_0.pts"), large) < MAX_NME
    assert nme(read_pts(tmp_path / "f_1.pts"), small) < MAX_NME
    assert "* face 0" in shown.out and "* face 1" in shown.out and "chosen:" not in shown.out
    doc = json.loads((tmp_path / "f.json").read_text())
    assert doc["chosen"] == [0, 1] and sorted(doc["written"]) == ["0", "1"]


@pytest.mark.detect
def test_face_not_found_is_an_input_error(two_face_photo, tmp_path, run_cli):
    photo, _ = two_face_photo
    shown = run_cli("detect-landmarks", photo, "--out", tmp_path / "f.pts", "--face", "2")
    assert shown.code == 2 and "--face 2: only 2 faces were found, numbered 0-1" in shown.err
    assert not (tmp_path / "f.pts").exists() and not (tmp_path / "f.json").exists()


def test_bad_choice_options_before_detecting(tmp_path, run_cli, examples_data, monkeypatch):
    monkeypatch.setattr(mediapipe_backend, "find", lambda *a, **k: pytest.fail("detected"))
    photo = examples_data / "astronaut.png"
    shown = run_cli("detect-landmarks", photo, "--out", tmp_path / "f.pts", "--face-box", "1,2,3")
    assert shown.code == 2 and "--face-box '1,2,3': expected X,Y,W,H" in shown.err
    shown = run_cli("detect-landmarks", photo, "--out", tmp_path / "f.pts", "--upsample", "2")
    assert shown.code == 2 and "--upsample is an option of the dlib backend" in shown.err
    shown = run_cli("detect-landmarks", photo, "--out", tmp_path / "f.pts", "--face", "1", "--all-faces")
    assert shown.code == 2 and "not allowed with argument" in shown.err
    shown = run_cli("detect-landmarks", photo, "--out", tmp_path / "f.json")
    assert shown.code == 2 and "--out" in shown.err and "--json" in shown.err
    assert list(tmp_path.iterdir()) == []


def test_implausible_landmarks_exit_1(tmp_path, run_cli, examples_data, examples_landmarks, monkeypatch):
    mirrored = read_pts(examples_landmarks / "astronaut.pts") * [-1, 1] + [600, 0]
    face = FaceCandidate(np.array([100.0, 50.0, 200.0, 200.0]), 0.9, mirrored, None, "mediapipe", "fake")
    monkeypatch.setattr(mediapipe_backend, "available", lambda: True)
    monkeypatch.setattr(mediapipe_backend, "find", lambda image: [face])
    shown = run_cli("detect-landmarks", examples_data / "astronaut.png", "--out", tmp_path / "f.pts")
    assert shown.code == 1 and "face 0's landmarks were refused" in shown.err
    assert not (tmp_path / "f.pts").exists()
