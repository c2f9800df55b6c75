"""`softras-cl fit-face A B --same-person` end to end on synthetic photos of one person, and its
bad-input messages (exit 2 before any fitting)."""
import hashlib
import json

import numpy as np
import pytest
from support.face_outputs import check_landmark_files

from softras_cl.bench.face_views import subject
from softras_cl.fitting.recipes import face, face_settings, face_views
from softras_cl.io.images import write_image

TINY = dict(landmark_iters=10, photo_stages=((1e-4, 3e-3, 4), (1e-5, 1e-3, 4)))
SMALL = ["--size", "48", "--n-id", "4", "--n-exp", "3", "--n-albedo", "2", "--no-progress"]


@pytest.fixture(scope="module")
def person(tmp_path_factory, demo_face_model):
    """Two 64 px photos of one synthetic person, A.png with A.npy landmarks and B.png with B.npy."""
    folder = tmp_path_factory.mktemp("person")
    paths = []
    for name, sample in zip("AB", subject(demo_face_model, np.random.default_rng(11), 64, 2)):
        write_image(folder / f"{name}.png", sample["photo"])
        np.save(folder / f"{name}.npy", sample["landmarks"])
        paths.append((folder / f"{name}.png", folder / f"{name}.npy"))
    return paths


def _sha256(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.slow
def test_same_person_writes_the_shared_face_and_every_photos_outputs(person, tmp_path, run_cli, monkeypatch,
                                                                     demo_face_model):
    monkeypatch.setitem(face.BUDGETS, "fast", TINY)          # seconds, not a real fit
    (a, a_lmk), (b, b_lmk) = person
    out = tmp_path / "fit"
    result = run_cli("fit-face", a, b, "--same-person", "--landmarks", a_lmk, b_lmk, "--budget", "fast",
                     "--out", out, *SMALL)
    assert result.code == 0, result.err
    assert "fit-face --same-person done" in result.out and "2 photos" in result.out
    for name in ("face.ply", "figure.png", "params.json", "params.npz", "history.json", "checkpoint.npz",
                 "run.json", "complete.json", "photos/A/overlay.png", "photos/B/figure.png",
                 "photos/B/params.json", "photos/A/face.ply"):
        assert (out / name).stat().st_size > 0, name
    doc = json.loads((out / "params.json").read_text())
    assert [p["photo_sha256"] for p in doc["photos"]] == [_sha256(a), _sha256(b)]
    assert doc["photos"][1]["landmarks_source"] == _sha256(b_lmk) and doc["photos"][0]["folder"] == "photos/A"
    assert len(doc["metrics"]["views"]) == 2 and np.isfinite(doc["metrics"]["psnr_face_db"])
    run = json.loads((out / "run.json").read_text())
    assert run["command"] == "fit-face --same-person" and run["options"]["n_id"] == 4
    assert [i["photo"] for i in run["inputs"]] == [_sha256(a), _sha256(b)]
    joint = np.load(out / "params.npz")
    for k, name in enumerate("AB"):
        per_photo = np.load(out / "photos" / name / "params.npz")
        np.testing.assert_array_equal(per_photo["id"], joint["id"])
        np.testing.assert_array_equal(per_photo["exp"], joint[f"exp.{k}"])
    for name, landmarks in (("A", a_lmk), ("B", b_lmk)):
        check_landmark_files(out / "photos" / name, demo_face_model, np.load(landmarks))
    last = (out / "complete.json").stat().st_mtime_ns
    assert all(p.stat().st_mtime_ns <= last for p in out.rglob("*") if p.is_file())


@pytest.mark.slow
@pytest.mark.detect
def test_same_person_prints_and_writes_each_photos_detection(tmp_path, run_cli, monkeypatch, examples_data):
    monkeypatch.setitem(face.BUDGETS, "fast", TINY)
    photos = [tmp_path / "in" / name for name in ("astronaut.png", "grace_hopper.jpg")]
    photos[0].parent.mkdir()
    for photo in photos:
        photo.write_bytes((examples_data / photo.name).read_bytes())
    out = tmp_path / "fit"
    result = run_cli("fit-face", *photos, "--same-person", "--budget", "fast", "--out", out, *SMALL)
    assert result.code == 0, result.err
    for photo in photos:
        assert f"{photo}: 1 face found by mediapipe" in result.out
        assert f"{photo}: * face 0: box " in result.out
        folder = out / "photos" / photo.stem
        detection = json.loads((folder / "detection.json").read_text())
        assert detection["chosen"] == 0 and detection["reason"] == "the only face found"
        source = json.loads((folder / "params.json").read_text())["landmarks_input"]
        assert source["source"] == "mediapipe" and source["face"] == 0 and source["box"] == detection["candidates"][0]["box"]
        assert (folder / "landmarks_detected.pts").is_file() and (folder / "landmarks_fitted.pts").is_file()


@pytest.mark.parametrize("extra, says", [
    (["--all-faces"], "--same-person fits the photos together in this process, as one person with one face "
                      "each (the largest when detected); it does not go with --all-faces"),
    (["--face-box", "1,1,9,9"], "it does not go with --face-box"),
    (["--workers", "2"], "it does not go with --workers"),
    (["--landmarks", "{a_lmk}"], "--landmarks gives 1 files for 2 photos: with --same-person give one per photo"),
])
def test_same_person_refuses_clashing_options_before_fitting(person, tmp_path, run_cli, extra, says):
    (a, a_lmk), (b, _) = person
    out = tmp_path / "fit"
    result = run_cli("fit-face", a, b, "--same-person", *[e.format(a_lmk=a_lmk) for e in extra], "--out", out, *SMALL)
    assert result.code == 2 and says in result.err, result.err
    assert not out.exists()


@pytest.mark.parametrize("extra, says", [
    ([], "--same-camera goes with --same-person"),
    (["--same-person", "--focal", "100"], "--same-camera fits one focal length for all the photos; --focal gives it"),
])
def test_same_camera_clashes_are_refused(person, tmp_path, run_cli, extra, says):
    (a, a_lmk), (b, b_lmk) = person
    out = tmp_path / "fit"
    result = run_cli("fit-face", a, b, "--same-camera", *extra, "--landmarks", a_lmk, b_lmk, "--out", out, *SMALL)
    assert result.code == 2 and says in result.err, result.err
    assert not out.exists()


def test_same_camera_fits_one_focal_with_the_joint_landmark_weight(person, tmp_path, run_cli, monkeypatch):
    """--same-camera: one focal block; and the joint fit's landmark weight (face_settings.joint_config)
    in the photometric stage, not the single fit's."""
    monkeypatch.setitem(face.BUDGETS, "fast", dict(landmark_iters=3, photo_stages=((1e-4, 3e-3, 2),)))
    (a, a_lmk), (b, b_lmk) = person
    out = tmp_path / "fit"
    result = run_cli("fit-face", a, b, "--same-person", "--same-camera", "--landmarks", a_lmk, b_lmk,
                     "--budget", "fast", "--out", out, *SMALL)
    assert result.code == 0, result.err
    joint = np.load(out / "params.npz")
    assert "focal" in joint and "focal.0" not in joint
    assert json.loads((out / "run.json").read_text())["options"]["same_camera"] is True
    stages = {s["name"]: s for s in json.loads((out / "history.json").read_text())["stages"]}
    assert (stages["photo-1"]["weights"]["landmarks"]
            == stages["landmarks"]["weights"]["landmarks"] * face_settings.LANDMARK_WEIGHT_PHOTO)


def test_same_person_needs_two_photos(person, tmp_path, run_cli):
    (a, a_lmk), _ = person
    result = run_cli("fit-face", a, "--same-person", "--landmarks", a_lmk, "--out", tmp_path / "f", *SMALL)
    assert result.code == 2 and "--same-person needs at least two photos of the person, got 1" in result.err


def test_several_landmark_files_need_same_person(person, tmp_path, run_cli):
    (a, a_lmk), (b, b_lmk) = person
    result = run_cli("fit-face", a, b, "--landmarks", a_lmk, b_lmk, "--out", tmp_path / "f", *SMALL)
    assert result.code == 2 and "--landmarks takes one file, got 2" in result.err and "--same-person" in result.err
    result = run_cli("fit-face", "--landmarks", a_lmk, a, "--out", tmp_path / "f", *SMALL)
    assert result.code == 2 and "before --landmarks" in result.err


@pytest.mark.slow
def test_interrupted_same_person_fit_keeps_the_best_and_resumes(person, tmp_path, run_cli, monkeypatch):
    from support.interrupt import sigint_once_written
    from softras_cl.fitting.solver import load_checkpoint

    (a, a_lmk), (b, b_lmk) = person
    out = tmp_path / "fit"
    argv = ["fit-face", a, b, "--same-person", "--landmarks", a_lmk, b_lmk, "--budget", "fast", "--out", out, *SMALL]
    with sigint_once_written(out / "checkpoint.npz"):
        result = run_cli(*argv)
    assert result.code == 130, result.err
    assert json.loads((out / "params.json").read_text())["interrupted"] is True
    assert not (out / "complete.json").exists() and (out / "photos" / "B" / "overlay.png").exists()
    values, _ = load_checkpoint(out / "checkpoint.npz")
    assert np.isfinite(values["exp.1"]).all()
    monkeypatch.setitem(face.BUDGETS, "fast", TINY)          # the rest of the fit, in seconds
    result = run_cli(*argv, "--resume")
    assert result.code == 0, result.err
    assert json.loads((out / "complete.json").read_text())["status"] == "done"
