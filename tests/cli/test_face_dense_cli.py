"""`softras-cl fit-face --dense-landmarks`: what it asks for is refused, before the output folder
is made, when the landmarks have no dense points or the option is out of range."""
from pathlib import Path

import pytest

from softras_cl.fitting.run_options import FACE

DATA = Path(__file__).resolve().parents[2] / "examples" / "data"
PHOTO, LANDMARKS = DATA / "astronaut.png", DATA / "landmarks" / "astronaut.pts"
SMALL = ["--size", "80", "--budget", "fast", "--no-progress"]


@pytest.mark.parametrize("extra, says", [
    (["--landmarks", str(LANDMARKS)], "needs the photo's dense points: MediaPipe Face Mesh's 468, which only "
                                      "the MediaPipe detector gives"),
    (["--landmarks", str(LANDMARKS), str(LANDMARKS), "--same-person"], "--same-person fits the photos "
                                                                       "together in this process"),
], ids=["landmark file", "same person"])
def test_dense_landmarks_without_dense_points_is_refused_before_fitting(tmp_path, run_cli, extra, says):
    photos = [str(PHOTO)] * (2 if "--same-person" in extra else 1)
    result = run_cli("fit-face", *photos, "--out", str(tmp_path / "o"), "--dense-landmarks", "1", *SMALL, *extra)
    assert result.code == 2
    assert says in result.err and "--dense-landmarks" in result.err
    assert not (tmp_path / "o").exists()


def test_a_negative_dense_weight_is_named_by_its_flag(tmp_path, run_cli):
    result = run_cli("fit-face", str(PHOTO), "--landmarks", str(LANDMARKS), "--out", str(tmp_path / "o"),
                     "--dense-landmarks", "-1", *SMALL)
    assert result.code == 2
    assert "--dense-landmarks must be >= 0 (0: no dense landmark term), got -1.0" in result.err


def test_dense_landmarks_is_off_by_default_and_sets_the_dense_weight():
    assert FACE["dense_landmarks"].default == 0.0
    assert FACE.config({}).dense_weight == 0.0
    assert FACE.config(dict(dense_landmarks=0.25)).dense_weight == 0.25
    assert FACE.record_options(FACE.values({})).get("dense_landmarks") is None     # old records still match
    assert FACE.record_options(FACE.values(dict(dense_landmarks=0.25)))["dense_landmarks"] == 0.25
