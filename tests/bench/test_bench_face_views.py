"""`softras-cl bench face-views`: the synthetic subjects, the identity ratio, the target verdict,
and a tiny run end to end."""
import json

import numpy as np
import pytest

from softras_cl.bench import face_views
from softras_cl.fitting.recipes import face
from softras_cl.scene.rotation import axis_angle_to_matrix, matrix_to_axis_angle


def test_subject_is_one_person_seen_from_different_sides(demo_face_model):
    photos = face_views.subject(demo_face_model, np.random.default_rng(0), 64, 3)
    truths = [p["truth"] for p in photos]
    for t in truths[1:]:
        np.testing.assert_array_equal(t["id"], truths[0]["id"])
        np.testing.assert_array_equal(t["albedo"], truths[0]["albedo"])
        assert not np.array_equal(t["exp"], truths[0]["exp"]) and not np.array_equal(t["sh"], truths[0]["sh"])
    yaws = [face_views.yaw_deg(t["rotation"]) for t in truths]
    assert -30 <= yaws[0] < -10 <= yaws[1] < 10 <= yaws[2] < 30
    assert all(p["photo"].shape == (64, 64, 3) for p in photos)


def test_same_camera_subject_shares_the_focal_and_keeps_the_framing(demo_face_model):
    own = face_views.subject(demo_face_model, np.random.default_rng(0), 64, 3)
    shared = face_views.subject(demo_face_model, np.random.default_rng(0), 64, 3, one_camera=True)
    focals = [p["truth"]["focal"][0] for p in shared]
    assert focals == [own[0]["truth"]["focal"][0]] * 3 and len({p["truth"]["focal"][0] for p in own}) == 3
    for a, b in zip(own, shared):
        np.testing.assert_array_equal(a["truth"]["exp"], b["truth"]["exp"])
        extent = np.ptp(a["clean_landmarks"], axis=0)
        np.testing.assert_allclose(np.ptp(b["clean_landmarks"], axis=0), extent, rtol=0.05)
        np.testing.assert_allclose(b["clean_landmarks"].mean(0), a["clean_landmarks"].mean(0), atol=0.03 * 64)


def test_yaw_of_a_yaw_pitch_roll_rotation():
    R = axis_angle_to_matrix([0, np.radians(-23.0), 0]) @ axis_angle_to_matrix([0.2, 0, 0]) @ axis_angle_to_matrix([0, 0, 0.15])
    assert face_views.yaw_deg(matrix_to_axis_angle(R)) == pytest.approx(-23.0, abs=1e-9)


def test_identity_ratio_is_0_for_the_truth_and_1_for_the_mean_face(demo_face_model):
    true_id = np.random.default_rng(1).normal(size=demo_face_model.n_id)
    assert face_views.identity_ratio(demo_face_model, true_id, true_id) < 1e-9
    assert face_views.identity_ratio(demo_face_model, np.zeros(demo_face_model.n_id), true_id) == pytest.approx(1.0)


def _row(reduction, best=0.4):
    return dict(reduction=reduction, best_single_ratio=best, mean_single_ratio=best, joint_ratio=best * (1 - reduction),
                single_seconds=[1.0, 2.0], single_cpu_seconds=[1.0, 1.0], joint_seconds=3.0, joint_cpu_seconds=3.0,
                single_shape_ratios=[0.5, 0.7], joint_shape_ratios=[0.4, 0.4])


@pytest.mark.parametrize("reductions, reached", [([0.5, 0.31, 0.1], True), ([0.5, 0.29, 0.1], False)])
def test_target_is_the_median_reduction(reductions, reached):
    summary = face_views.summarise([_row(r) for r in reductions])
    assert summary["median_reduction"] == pytest.approx(reductions[1]) and summary["target_reached"] is reached
    assert summary["median_single_seconds"] == 1.5


@pytest.mark.slow
def test_tiny_run_writes_json_and_chart(tmp_path, run_cli, monkeypatch):
    monkeypatch.setitem(face.BUDGETS, "fast", dict(landmark_iters=5, photo_stages=((1e-4, 3e-3, 3),)))
    out = tmp_path / "bench"
    result = run_cli("bench", "face-views", "--subjects", "1", "--views", "2", "--size", "64", "--budget", "fast",
                     "--same-camera", "--out", out)
    assert result.code == 0, result.err
    assert "target >= 30%" in result.out and (out / "face_views.png").stat().st_size > 0
    doc = json.loads((out / "face_views.json").read_text())
    row = doc["subjects"][0]
    assert doc["same_camera"] is True
    assert len(row["single_ratios"]) == 2 and row["best_single_ratio"] == min(row["single_ratios"])
    assert len(row["joint_shape_ratios"]) == 2 and np.isfinite(row["joint_ratio"]) and doc["provenance"]["cpu"] is not None and len(doc["load_average"]) == 2


def test_bad_counts_are_refused(tmp_path, run_cli):
    result = run_cli("bench", "face-views", "--views", "1", "--out", tmp_path / "b")
    assert result.code == 2 and "--views >= 2" in result.err
