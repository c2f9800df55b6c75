"""`softras-cl fit-body PHOTO`: a photo of a person end to end (the shipped cameraman), a photo
with nobody in it, options that do not go with a photo, Ctrl-C and --resume, a batch item, and
`softras-cl bench body-photo --quick`."""
import json
import shutil

import numpy as np
import pytest

from support.interrupt import sigint_once_written
from softras_cl.cli import main

FAST = ["--budget", "fast", "--size", "64", "--no-progress"]
pytestmark = pytest.mark.detect


@pytest.mark.slow
def test_fit_body_on_a_photo_writes_every_output(tmp_path, capsys, examples_data):
    out = tmp_path / "fit"
    assert main(["fit-body", str(examples_data / "people" / "cameraman.png"), "--out", str(out), *FAST]) == 0
    for name in ("body.ply", "overlay.png", "keypoints.png", "mask.png", "figure.png", "params.json", "params.npz",
                 "loss_curve.png", "history.json", "checkpoint.npz", "complete.json"):
        assert (out / name).stat().st_size > 0, name
    doc = json.loads((out / "params.json").read_text())
    assert doc["input"] == "photo" and doc["target_size"] == [512, 512] and doc["working_size"] == [64, 64]
    detection = doc["detection"]
    assert len(detection["keypoints"]) == 33 and detection["score"] > 0.5 and detection["people"] == 1
    assert doc["fov_source"].startswith("--fov") and sum(w > 0 for w in doc["keypoints"]["weights"]) >= 8
    # a fast 64 px fit: the start translation moved by k x 1e-15 m (k = 0..7) spreads its IoU over
    # 0.686-0.790 (docs/notes/body_photo_speed.md); a broken fit lands far below
    assert doc["metrics"]["silhouette_iou"] > 0.6 and np.isfinite(doc["metrics"]["keypoint_error_px_full"])
    said = capsys.readouterr().out
    assert "person in" in said and "torso visibility" in said and "keypoint error" in said
    record = json.loads((out / "run.json").read_text())
    assert record["options"].get("input", "auto") == "auto"


def test_a_photo_with_nobody_exits_1_naming_it(tmp_path, run_cli):
    import skimage.data
    from PIL import Image

    photo = tmp_path / "coffee.png"
    Image.fromarray(skimage.data.coffee()).save(photo)
    result = run_cli("fit-body", str(photo), "--out", str(tmp_path / "o"), *FAST)
    assert result.code == 1 and "no person found in" in result.err and "coffee.png" in result.err
    assert not (tmp_path / "o").exists()


def test_joints_do_not_go_with_a_photo(tmp_path, run_cli, examples_data):
    joints = tmp_path / "joints.txt"
    np.savetxt(joints, np.zeros((24, 2)))
    result = run_cli("fit-body", str(examples_data / "people" / "cameraman.png"), "--input", "photo", "--joints", str(joints),
                     "--out", str(tmp_path / "o"), *FAST)
    assert result.code == 2 and "--joints is for part-coloured targets" in result.err


def test_input_parts_forces_the_renderer_target_path(tmp_path, run_cli, examples_data):
    out = tmp_path / "o"
    result = run_cli("fit-body", str(examples_data / "astronaut.png"), "--input", "parts", "--out", str(out),
                     "--budget", "fast", "--size", "32", "--no-progress")
    assert result.code == 0 and "person in" not in result.out
    doc = json.loads((out / "params.json").read_text())
    assert "detection" not in doc and not (out / "keypoints.png").exists()
    assert json.loads((out / "run.json").read_text())["options"]["input"] == "parts"


@pytest.mark.slow
def test_interrupted_photo_fit_keeps_the_best_and_resumes(tmp_path, capsys, examples_data):
    out = tmp_path / "fit"
    photo = str(examples_data / "people" / "cameraman.png")
    with sigint_once_written(out / "checkpoint.npz"):
        code = main(["fit-body", photo, "--out", str(out), "--budget", "thorough", "--size", "64", "--no-progress"])
    assert code == 130
    assert "interrupted; outputs are from the best values so far" in capsys.readouterr().err
    assert json.loads((out / "params.json").read_text())["interrupted"] is True
    assert (out / "keypoints.png").exists() and not (out / "complete.json").exists()
    assert main(["fit-body", photo, "--out", str(out), "--budget", "thorough", "--size", "64", "--no-progress",
                 "--resume"]) == 0
    assert json.loads((out / "complete.json").read_text())["status"] == "done"


@pytest.mark.slow
def test_a_batch_fits_a_photo_item(tmp_path, examples_data):
    pytest.importorskip("distributed")
    folder = tmp_path / "photos"
    folder.mkdir()
    shutil.copy(examples_data / "people" / "cameraman.png", folder / "cameraman.png")
    out = tmp_path / "batch"
    assert main(["fit-body", str(folder / "*.png"), str(examples_data / "astronaut.png"), "--workers", "1",
                 "--out", str(out), *FAST]) == 0
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert len(rows) == 2 and all(r["status"] == "ok" for r in rows)
    for row in rows:
        doc = json.loads((out / row["name"] / "params.json").read_text())
        assert doc["input"] == "photo" and len(doc["detection"]["keypoints"]) == 33


@pytest.mark.slow
def test_bench_body_photo_quick(tmp_path, capsys):
    assert main(["bench", "body-photo", "--quick", "--json", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "body_photo.json").read_text())
    assert set(doc["summary"]) == {"full", "keypoints", "mask"}
    full = doc["summary"]["full"]
    assert full["photos"] == 1 and full["detection_rate"] == 1.0
    assert np.isfinite(full["pa_mpjpe_mm"]) and 0.0 < full["mask_iou"] <= 1.0 and full["median_seconds"] > 0
    assert "pa_mpjpe_le_60mm" in doc["targets"] and "cpu" in json.dumps(doc["provenance"]).lower()
    assert json.loads(capsys.readouterr().out)["summary"]["full"]["photos"] == 1
