"""`softras-cl fit-face --landmark-map`: which model points the 68 landmarks are tied to; what
it asks of the model is checked before the output folder is made."""
from pathlib import Path

import numpy as np
import pytest

from softras_cl.fitting.run_options import FACE
from support.face_outputs import projected_model_landmarks
from support.face_scenes import read_pts

DATA = Path(__file__).resolve().parents[2] / "examples" / "data"
PHOTO, LANDMARKS = DATA / "astronaut.png", DATA / "landmarks" / "astronaut.pts"
DEMO = Path(__file__).resolve().parents[2] / "fitting" / "models" / "data" / "demo_face.npz"
SMALL = ["--size", "80", "--budget", "fast", "--no-progress"]


def _model_without_face_mesh(folder: Path) -> Path:
    arrays = {k: v for k, v in np.load(DEMO).items() if not k.startswith("dense_")}
    path = folder / "no_face_mesh.npz"
    np.savez(path, **arrays)
    return path


def test_face_mesh_map_on_a_model_without_face_mesh_points_is_refused_before_fitting(tmp_path, run_cli):
    result = run_cli("fit-face", str(PHOTO), "--landmarks", str(LANDMARKS), "--out", str(tmp_path / "o"),
                     "--model", str(_model_without_face_mesh(tmp_path)), "--landmark-map", "face-mesh", *SMALL)
    assert result.code == 2
    assert "--landmark-map 'face-mesh' needs a face model with MediaPipe Face Mesh's 468 points" in result.err
    assert not (tmp_path / "o").exists()


def test_an_unknown_landmark_map_is_refused(tmp_path, run_cli):
    result = run_cli("fit-face", str(PHOTO), "--landmarks", str(LANDMARKS), "--out", str(tmp_path / "o"),
                     "--landmark-map", "ibug", *SMALL)
    assert result.code == 2 and "--landmark-map" in result.err and "'face-mesh'" in result.err


def test_landmark_map_is_auto_by_default_and_recorded_when_given():
    assert FACE["landmark_map"].default == "auto"
    assert FACE.config({}).landmark_map == "auto"
    assert FACE.config(dict(landmark_map="face-mesh")).landmark_map == "face-mesh"
    assert FACE.record_options(FACE.values({})).get("landmark_map") is None      # old records still match
    assert FACE.record_options(FACE.values(dict(landmark_map="model")))["landmark_map"] == "model"


def test_a_landmark_file_fitted_with_the_face_mesh_map_writes_the_tied_points(tmp_path, run_cli):
    """The shipped .pts hold Face Mesh's points: --landmark-map face-mesh ties them as the
    detector's; landmarks_fitted.pts holds the tied points (the 51 off the jaw line, which
    slide on neither map)."""
    from softras_cl.fitting.models.face_loaders import load_demo_face_model
    from softras_cl.fitting.recipes.face import landmark_model

    folder = tmp_path / "o"
    result = run_cli("fit-face", str(PHOTO), "--landmarks", str(LANDMARKS), "--out", str(folder),
                     "--landmark-map", "face-mesh", *SMALL)
    assert result.code == 0, result.err
    fitted = read_pts(folder / "landmarks_fitted.pts")
    model = load_demo_face_model()
    tied = projected_model_landmarks(folder, landmark_model(model, "face-mesh"))
    own = projected_model_landmarks(folder, model)
    np.testing.assert_allclose(fitted[17:], tied[17:], atol=1e-6)
    assert np.abs(fitted[17:] - own[17:]).max() > 1.0
