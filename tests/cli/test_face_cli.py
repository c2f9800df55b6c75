"""`softras-cl fit-face` end to end on a shipped photo, its bad-input messages, and what an
interrupted run leaves behind."""
import json
from pathlib import Path

import numpy as np
import pytest

from support.face_outputs import check_landmark_files
from support.face_scenes import read_pts
from support.interrupted_fit import run_interrupted_fit
from softras_cl.cli import main

DATA = Path(__file__).resolve().parents[2] / "examples" / "data"
PHOTO, LANDMARKS = DATA / "astronaut.png", DATA / "landmarks" / "astronaut.pts"
SMALL = ["--size", "80", "--budget", "fast", "--n-id", "4", "--n-exp", "4", "--n-albedo", "2",
         "--no-progress"]


@pytest.mark.slow
def test_fit_face_writes_every_output(tmp_path, capsys, demo_face_model):
    out = tmp_path / "fit"
    assert main(["fit-face", str(PHOTO), "--landmarks", str(LANDMARKS), "--out", str(out), *SMALL]) == 0
    for name in ("face.ply", "overlay.png", "figure.png", "params.json", "params.npz", "loss_curve.png",
                 "history.json", "checkpoint.npz", "landmarks_detected.pts", "landmarks_fitted.pts"):
        assert (out / name).stat().st_size > 0, name
    doc = json.loads((out / "params.json").read_text())
    assert doc["interrupted"] is False and doc["photo_size"] == [512, 512]
    assert np.isfinite(doc["metrics"]["psnr_face_db"])
    assert doc["metrics"]["landmark_error_px_full"] < 25.0       # 80 px working image of a 512 px photo
    params = np.load(out / "params.npz")
    assert params["K"].shape == (3, 3) and params["id"].shape == (4,)
    assert doc["landmarks_input"] == dict(source="file", file=str(LANDMARKS))
    check_landmark_files(out, demo_face_model, read_pts(LANDMARKS))
    assert not (out / "detection.json").exists()
    said = capsys.readouterr().out
    assert said.startswith("fit-face done in ") and "landmark error" in said      # no detection to print


def _lines(path: Path, points) -> None:
    path.write_text("\n".join(f"{x} {y}" for x, y in points))


@pytest.mark.parametrize("case, match", [
    ("67 points", "67 points"),
    ("outside", "outside"),
    ("bad photo", "astronaut_broken.png"),
    ("unknown model", "unknown face model layout"),
])
def test_bad_input_is_reported_before_fitting(tmp_path, run_cli, case, match):
    photo, lmk, model = PHOTO, LANDMARKS, None
    if case == "67 points":
        lmk = tmp_path / "lmk.txt"
        _lines(lmk, np.full((67, 2), 100.0))
    elif case == "outside":
        lmk = tmp_path / "lmk.txt"
        _lines(lmk, np.full((68, 2), 900.0))
    elif case == "bad photo":
        photo = tmp_path / "astronaut_broken.png"
        photo.write_bytes(b"not an image")
    else:
        model = tmp_path / "model.npz"
        np.savez(model, something=np.zeros(3))
    argv = ["fit-face", str(photo), "--landmarks", str(lmk), "--out", str(tmp_path / "o"), *SMALL]
    result = run_cli(*argv, *(["--model", str(model)] if model else []))
    assert result.code == 2
    err = result.err
    assert "fit-face" in err and match in err
    assert not (tmp_path / "o").exists()


def test_interrupted_fit_keeps_and_writes_the_best_result(tmp_path, capsys):
    out = tmp_path / "fit"
    run_interrupted_fit(["fit-face", str(PHOTO), "--landmarks", str(LANDMARKS), "--out", str(out),
                         "--size", "96", "--budget", "thorough", "--no-progress"], out, capsys, "id")
    assert (out / "overlay.png").exists() and (out / "face.ply").exists()


@pytest.mark.slow
def test_bench_face_reports_accuracy_against_time(tmp_path, capsys):
    out = tmp_path / "bench"
    assert main(["bench", "face", "--faces", "1", "--size", "96", "--budgets", "fast", "--json",
                 "--out", str(out)]) == 0
    doc = json.loads((out / "face.json").read_text())
    fast = doc["summary"]["fast"]
    assert fast["faces"] == 1 and fast["median_seconds"] > 0
    assert fast["rmse_ratio"] < 0.8 and fast["psnr_face_db"] > 25      # far better than the mean face
    assert (out / "face.png").exists() and (out / "face_strip.png").exists()
    assert json.loads(capsys.readouterr().out)["summary"]["fast"]["faces"] == 1


def test_bench_face_rejects_unknown_budgets(run_cli):
    result = run_cli("bench", "face", "--budgets", "fast,quick")
    assert result.code == 2
    assert "--budgets must name some of" in result.err
