"""`softras-cl bench face`: the focal-length error and the landmarks-only baseline."""
import json

import numpy as np
import pytest

from softras_cl.bench import face as bench
from softras_cl.cli import main


def test_focal_error_is_relative_to_the_truth():
    assert bench.focal_error(110.0, 100.0) == pytest.approx(0.1)
    assert bench.focal_error(90.0, 100.0) == pytest.approx(0.1)
    assert bench.focal_error(250.0, 200.0) == pytest.approx(0.25)
    assert bench.focal_error(200.0, 200.0) == 0.0


def test_summary_gives_median_and_max_focal_error():
    rows = [dict(rmse_mm=1.0, mean_face_rmse_mm=2.0, rigid_rmse_mm=1.0, rigid_mean_face_rmse_mm=2.0,
                 landmark_error_px=0.5, psnr_face_db=30.0, seconds=1.0, cpu_seconds=1.0, focal_error=e,
                 residual_rms=0.01)
            for e in (0.02, 0.30, 0.05)]
    s = bench.summarise(rows)
    assert s["focal_error_median"] == pytest.approx(0.05) and s["focal_error_max"] == pytest.approx(0.30)


def test_landmarks_only_baseline_is_the_default_landmark_stage_alone():
    from softras_cl.fitting.recipes.face import BUDGETS

    config = bench.budget_config(bench.LANDMARKS_ONLY, 96)
    assert config.photo_stages == ()
    assert config.landmark_iters == BUDGETS["default"]["landmark_iters"]
    assert bench.budget_config("fast", 96).photo_stages == BUDGETS["fast"]["photo_stages"]


def test_landmarks_only_fit_runs_no_photometric_stage(demo_face_model):
    sample = bench.synthetic_face(demo_face_model, np.random.default_rng(3), 96)
    row, = bench.run_budget(demo_face_model, [sample], bench.LANDMARKS_ONLY, 96, progress=False)
    assert set(row["fit"].result.outcomes) == {"landmarks"}
    assert row["outcomes"] == row["fit"].result.outcomes
    assert row["evaluations"] == {"landmarks": len(row["fit"].result.history)} and len(row["fit"].result.history) > 1
    assert row["true_focal_px"] == sample["truth"]["focal"][0]
    assert row["focal_error"] == pytest.approx(abs(row["focal_px"] / row["true_focal_px"] - 1))


@pytest.mark.slow
def test_bench_face_reports_focal_error_and_baseline(demo_face_model, tmp_path, capsys):
    out = tmp_path / "bench"
    assert main(["bench", "face", "--faces", "1", "--size", "96", "--budgets", "fast",
                 "--out", str(out), "--seed", "4"]) == 0
    table = capsys.readouterr().out
    assert "landmarks-only" in table and "focal err" in table
    doc = json.loads((out / "face.json").read_text())
    assert list(doc["summary"]) == ["landmarks-only", "fast"]
    truth = bench.synthetic_face(demo_face_model, np.random.default_rng(4), 96)["truth"]
    for name in ("landmarks-only", "fast"):
        face, = doc["faces"][name]
        assert face["true_focal_px"] == pytest.approx(truth["focal"][0], rel=1e-12)
        assert doc["summary"][name]["focal_error_median"] == pytest.approx(
            abs(face["focal_px"] - truth["focal"][0]) / truth["focal"][0])
    # the photometric stages moved the fit: the baseline is a different fit, not a copy
    assert doc["faces"]["fast"][0]["psnr_face_db"] != doc["faces"]["landmarks-only"][0]["psnr_face_db"]


def test_renderers_are_checked_before_any_fit(run_cli):
    result = run_cli("bench", "face", "--renderers", "softras,blender")
    assert result.code == 2 and "--renderers must name some of softras, mitsuba" in result.err
    result = run_cli("bench", "face", "--renderers", "softras,softras")
    assert result.code == 2 and "--renderers" in result.err


def test_mitsuba_lines_only_with_mitsuba():
    assert bench.format_mitsuba(dict(summary={})) == ""
    doc = dict(mitsuba=dict(spp=8, silhouette_iou_min=0.98, silhouette_iou_median=0.99, psnr_vs_softras_db_median=21.0,
                            render_seconds_median=1.5, noise_rms=[0.01, 0.02]),
               summary={"mitsuba/fast": dict(renderer="mitsuba", budget="fast", residual_rms_median=0.03),
                        "mitsuba/landmarks-only": dict(renderer="mitsuba", budget="landmarks-only",
                                                       residual_rms_median=0.09)})
    text = bench.format_mitsuba(doc)
    assert "(8 spp)" in text and "min 0.9800" in text and "0.0100, 0.0200" in text
    assert "residual RMS on mitsuba photos 0.0300" in text       # the baseline's is not the fit's
