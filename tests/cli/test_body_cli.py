"""`softras-cl fit-body` end to end on a rendered target, its bad-input messages, what an
interrupted run leaves behind, and `softras-cl bench body --quick`."""
import json

import numpy as np
import pytest
from softras_cl.fitting.recipes import body

from support.interrupted_fit import run_interrupted_fit
from softras_cl.cli import main
from softras_cl.io.images import write_image

SMALL = ["--size", "40", "--budget", "fast", "--no-progress"]


@pytest.fixture(scope="module")
def target(tmp_path_factory, demo_body_model):
    """(target.png 48x48 of a posed demo body, joints.txt with its 24 joints)."""
    model = demo_body_model
    values = body.rest_values(model)
    values["body_pose"][model.joint_names.index("left_shoulder") - 1] = [0.0, 0.0, 0.4]
    scene = body.BodyScene(model, (48, 48), body.BodyFitConfig(size=48))
    state, _ = scene.pose(values)
    out = scene.render(state.vertices, 1e-6, 1e-4, color_agg="hard", alpha_agg="hard")
    folder = tmp_path_factory.mktemp("body")
    write_image(folder / "target.png", scene.composite(out))
    np.savetxt(folder / "joints.txt", scene.camera.project_pixels(state.joints)[0])
    return folder / "target.png", folder / "joints.txt"


@pytest.mark.slow
def test_fit_body_writes_every_output(tmp_path, capsys, target):
    out = tmp_path / "fit"
    image, joints = target
    assert main(["fit-body", str(image), "--joints", str(joints), "--out", str(out), *SMALL]) == 0
    for name in ("body.ply", "overlay.png", "params.json", "params.npz", "loss_curve.png", "history.json",
                 "checkpoint.npz"):
        assert (out / name).stat().st_size > 0, name
    doc = json.loads((out / "params.json").read_text())
    assert doc["interrupted"] is False and doc["target_size"] == [48, 48] and doc["working_size"] == [40, 40]
    assert doc["metrics"]["silhouette_iou"] > 0.7 and doc["metrics"]["joint_error_px_full"] < 3.0
    params = np.load(out / "params.npz")
    assert params["body_pose"].shape == (23, 3) and params["joints_px"].shape == (24, 2)
    np.testing.assert_allclose(params["joints_px"], np.loadtxt(joints), atol=3.0)
    assert "silhouette IoU" in capsys.readouterr().out


@pytest.mark.parametrize("case, match", [
    ("two channels", "target must be"),
    ("tiny image", "at least 16 pixels"),
    ("23 joints", "has 23 joints, the model has 24"),
    ("unknown model", "unknown"),
])
def test_bad_input_is_reported_before_fitting(tmp_path, run_cli, target, case, match):
    image, joints = target
    extra = []
    if case == "two channels":
        image = tmp_path / "target.npy"
        np.save(image, np.zeros((48, 48, 2)))
    elif case == "tiny image":
        image = tmp_path / "tiny.png"
        write_image(image, np.ones((10, 10, 3)))
    elif case == "23 joints":
        joints = tmp_path / "joints.txt"
        np.savetxt(joints, np.full((23, 2), 20.0))
    else:
        model = tmp_path / "model.npz"
        np.savez(model, something=np.zeros(3))
        extra = ["--model", str(model)]
    argv = ["fit-body", str(image), "--joints", str(joints), "--out", str(tmp_path / "o"), *SMALL, *extra]
    result = run_cli(*argv)
    assert result.code == 2
    err = result.err
    assert "fit-body" in err and match in err
    assert not (tmp_path / "o").exists()


def test_interrupted_fit_keeps_and_writes_the_best_result(tmp_path, target, capsys):
    out = tmp_path / "fit"
    values = run_interrupted_fit(["fit-body", str(target[0]), "--out", str(out), "--size", "48",
                                  "--budget", "thorough", "--no-progress"], out, capsys, "body_pose")
    np.testing.assert_allclose(np.load(out / "params.npz")["body_pose"], values["body_pose"])
    assert (out / "overlay.png").exists() and (out / "body.ply").exists()


@pytest.mark.slow
def test_bench_body_quick(tmp_path, capsys):
    """On the device objective, which a GPU would take by default."""
    assert main(["bench", "body", "--quick", "--objective", "device", "--json", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "body.json").read_text())
    assert doc["objective"] == "device"
    row = doc["summary"]["fast"]
    assert row["poses"] == 1 and np.isfinite(row["mpjpe_mm"]) and 0.0 < row["silhouette_iou"] <= 1.0
    assert (tmp_path / "body.png").exists() and (tmp_path / "body_strip.png").exists()
    assert json.loads(capsys.readouterr().out)["summary"]["fast"]["poses"] == 1


@pytest.mark.slow
def test_fit_body_batch_from_a_manifest_with_joints(tmp_path, target):
    pytest.importorskip("distributed")
    image, joints = target
    manifest = tmp_path / "items.csv"
    manifest.write_text(f"target,joints,name,size\n{image},{joints},with_joints,40\n{image},,silhouette_only,32\n")
    out = tmp_path / "batch"
    assert main(["fit-body", "--manifest", str(manifest), "--workers", "1", "--out", str(out),
                 "--budget", "fast", "--no-progress"]) == 0
    rows = {json.loads(line)["name"]: json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()}
    assert {n: r["status"] for n, r in rows.items()} == {"with_joints": "ok", "silhouette_only": "ok"}
    with_joints = json.loads((out / "with_joints" / "params.json").read_text())
    alone = json.loads((out / "silhouette_only" / "params.json").read_text())
    assert with_joints["working_size"] == [40, 40] and alone["working_size"] == [32, 32]   # per-row size
    assert with_joints["metrics"]["joint_error_px_full"] < 3.0 and "joint_error_px_full" not in alone["metrics"]
    assert with_joints["metrics"]["silhouette_iou"] > 0.7
    assert (out / "summary.png").stat().st_size > 0 and (out / "results.csv").exists()
