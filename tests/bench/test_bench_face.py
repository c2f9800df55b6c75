"""`softras-cl bench face`: the focal-length error and the landmarks-only baseline."""
import json
import re

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


@pytest.mark.parametrize("args, says", [
    (("--renderers", "softras,blender"), "--renderers must name some of softras, mitsuba"),
    (("--renderers", "softras,softras"), "--renderers"),
    (("--contour", "fixed,bent"), "--contour must name some of fixed, sliding"),
    (("--yaws", "45-30"), "--yaws"),
])
def test_options_are_checked_before_any_fit(run_cli, args, says):
    result = run_cli("bench", "face", *args)
    assert result.code == 2 and says in result.err


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


def _jaw_crossings(points) -> int:
    from softras_cl.fitting.keypoints.plausibility import _jaw_crossings as crossings

    return crossings(points)


def test_silhouette_jaw_moves_hidden_jaw_points_to_the_edge_of_the_render(demo_face_model):
    """A face turned by 60 degrees: the jaw points the render hides end on the silhouette's
    edge (a pixel inside it on one side, outside on the other), the visible ones and the other
    51 points stay the projected truth, and the line does not cross itself."""
    from scipy.ndimage import binary_erosion

    from softras_cl.fitting.recipes.face import FaceScene, depth_range
    from softras_cl.scene.renderer import SHARP

    truth = bench.random_truth(demo_face_model, np.random.default_rng(1), 128)
    truth["rotation"] = np.radians([0.0, 60.0, 0.0])
    scene = FaceScene(demo_face_model, (128, 128), alpha_agg="hard", depth_range=depth_range(truth["translation"]))
    world, _ = scene.geometry(truth)
    projected, _ = scene.camera(truth["focal"][0]).project_pixels(demo_face_model.landmarks(world)[0])
    moved = bench.silhouette_jaw(scene, truth, projected)
    changed = np.nonzero(np.any(moved != projected, axis=1))[0]
    assert 4 <= len(changed) <= 12 and changed.max() < 17
    np.testing.assert_array_equal(moved[17:], projected[17:])
    inside = scene.render(truth, *SHARP).alpha[0] > 0.5
    edge = inside & ~binary_erosion(inside)
    for u, v in moved[changed]:
        near = edge[max(int(v) - 1, 0):int(v) + 2, max(int(u) - 1, 0):int(u) + 2]
        assert near.any(), (u, v)
    assert _jaw_crossings(moved) == 0
    frontal = dict(truth, rotation=np.zeros(3))
    world, _ = scene.geometry(frontal)
    projected, _ = scene.camera(truth["focal"][0]).project_pixels(demo_face_model.landmarks(world)[0])
    assert np.abs(bench.silhouette_jaw(scene, frontal, projected) - projected)[:, 0].max() < 5.0


def test_in_jaw_order_untangles_moved_points_only():
    angle = np.linspace(0.0, np.pi, 17)                          # a convex arc, 8 at the bottom
    jaw = 50.0 * np.column_stack([-np.cos(angle), np.sin(angle)])
    points = np.vstack([jaw, np.zeros((51, 2))])
    swapped = points.copy()
    swapped[[10, 12]] = points[[12, 10]]
    assert _jaw_crossings(swapped) > 0
    np.testing.assert_array_equal(bench.in_jaw_order(swapped, [10, 11, 12]), points)
    # a visible point between them is never moved: the crossing stays
    np.testing.assert_array_equal(bench.in_jaw_order(swapped, [10, 12]), swapped)


@pytest.mark.parametrize("text, says", [
    ("0-15,45", "--yaws must be comma-separated bins lo-hi"),
    ("30-15", "0 <= lo < hi <= 90"),
    ("0-100", "got '0-100'"),
    ("a-b", "got 'a-b'"),
])
def test_yaw_bins_are_checked(text, says):
    from softras_cl.errors import InputError

    with pytest.raises(InputError, match=re.escape(says)):
        bench.parse_yaws(text)


def test_yaws_and_contours_parse_and_name_the_runs():
    assert bench.parse_yaws("0-15, 45-75") == [(0.0, 15.0), (45.0, 75.0)] and bench.parse_yaws(None) == []
    assert bench.parse_contours("fixed,sliding") == ["fixed", "sliding"] and bench.parse_contours(None) == [None]
    assert bench.run_name("softras", "fast") == "fast"
    assert bench.run_name("mitsuba", "fast", (45.0, 75.0), "sliding") == "mitsuba/yaw 45-75/fast/sliding contour"


def test_contour_comparison_pairs_fixed_with_sliding_per_bin_and_budget():
    def run(contour, lmk, rmse, yaw="yaw 45-75"):
        return dict(renderer="softras", yaw_bin=yaw, budget="fast", contour=contour, faces=3,
                    landmark_error_px=lmk, rmse_mm=rmse, median_seconds=2.0)

    summary = {"a": run("fixed", 4.0, 2.0), "b": run("sliding", 1.0, 1.5), "c": run("sliding", 1.0, 1.0, "yaw 0-15")}
    row, = bench.contour_comparison(summary)
    assert row["yaw_bin"] == "yaw 45-75" and row["landmark_reduction"] == 0.75 and row["rmse_reduction"] == 0.25
    assert "yaw 45-75" in bench.format_comparison([row]) and bench.format_comparison([]) == ""
    assert "landmarks" not in bench.format_comparison([row])      # one landmark source: no column for it
    by_source = {k + s: dict(v, landmarks=s) for k, v in summary.items() for s in ("truth", "detected")}
    table = bench.format_comparison(bench.contour_comparison(by_source))
    assert "landmarks" in table and "truth" in table and "detected" in table


def test_yaw_bin_faces_are_turned_that_far_and_plausible(demo_face_model):
    from softras_cl.fitting.keypoints.plausibility import layout_faults
    from softras_cl.scene.rotation import axis_angle_to_matrix

    faces, redrawn = bench.draw_faces(demo_face_model, np.random.default_rng(0), 96, 3, (45.0, 75.0))
    assert len(faces) == 3 and redrawn >= 0
    for face in faces:
        R = axis_angle_to_matrix(face["truth"]["rotation"])
        forward = R @ [0.0, 0.0, 1.0]                          # where the face looks
        assert 40 < np.degrees(np.arctan2(abs(forward[0]), forward[2])) < 80
        assert not layout_faults(face["landmarks"])


def _bench(tmp_path, capsys, *options) -> tuple[str, dict]:
    """`bench face --faces 1 --budgets fast` with these options: (what it printed, face.json)."""
    out = tmp_path / "bench"
    assert main(["bench", "face", "--faces", "1", "--budgets", "fast", *options, "--out", str(out)]) == 0
    return capsys.readouterr().out, json.loads((out / "face.json").read_text())


def _run_names(template: str, choices) -> list[str]:
    """The summary names of a comparison run by _bench: `template` with {budget} (landmarks-only,
    then fast) and {choice} (each of `choices`) filled in."""
    return [template.format(budget=b, choice=c) for b in ("landmarks-only", "fast") for c in choices]


@pytest.mark.slow
def test_bench_face_compares_contours_per_yaw_bin(tmp_path, capsys):
    said, doc = _bench(tmp_path, capsys, "--size", "96", "--yaws", "45-75", "--contour", "fixed,sliding", "--seed", "2")
    assert "fixed against sliding jaw points" in said
    assert list(doc["summary"]) == _run_names("yaw 45-75/{budget}/{choice} contour", ("fixed", "sliding"))
    assert doc["yaw_bins"] == [[45.0, 75.0]] and set(doc["redrawn_faces"]) == {"yaw 45-75"}
    assert [(r["yaw_bin"], r["budget"]) for r in doc["contour_comparison"]] == [
        ("yaw 45-75", "landmarks-only"), ("yaw 45-75", "fast")]
    fixed, sliding = (doc["summary"][f"yaw 45-75/fast/{c} contour"] for c in ("fixed", "sliding"))
    assert fixed["contour"] == "fixed" and sliding["contour"] == "sliding"
    assert fixed["landmark_error_px"] != sliding["landmark_error_px"]


@pytest.mark.parametrize("text, says", [("truth,truth", "got 'truth,truth'"), ("mediapipe", "got 'mediapipe'")])
def test_landmark_sources_are_checked(text, says):
    from softras_cl.errors import InputError

    with pytest.raises(InputError, match=re.escape(says)):
        bench.parse_landmark_sources(text)


@pytest.mark.parametrize("text", ["0,-1", "0,0", "a", "0,nan", ","])
def test_dense_weights_are_checked(text):
    from softras_cl.errors import InputError

    with pytest.raises(InputError, match=re.escape(f"--dense must be comma-separated dense landmark weights >= 0, "
                                                   f"each once, e.g. 0,0.5; got {text!r}")):
        bench.parse_dense(text)


def test_landmark_sources_and_dense_weights_parse_and_name_the_runs():
    assert bench.parse_landmark_sources("truth, detected") == ["truth", "detected"]
    assert bench.parse_landmark_sources(None) == [None] and bench.parse_dense(None) == [None]
    assert bench.parse_dense("0, 0.5") == [0.0, 0.5]
    assert bench.run_name("softras", "fast", landmarks="detected", dense=0.5) == "detected landmarks/fast/dense 0.5"
    assert bench.run_name("softras", "fast", (0.0, 15.0), "fixed", "truth", 0.0) == \
        "yaw 0-15/truth landmarks/fast/fixed contour/dense 0"
    assert bench.budget_config("fast", 96, dense_weight=0.5).dense_weight == 0.5
    assert bench.budget_config("fast", 96).dense_weight == 0.0


def test_dense_comparison_pairs_each_weight_with_none_per_landmark_source():
    def run(landmarks, dense, lmk, rmse):
        return dict(renderer="softras", yaw_bin=None, budget="fast", contour="sliding", landmarks=landmarks,
                    dense=dense, faces=3, landmark_error_px=lmk, rmse_mm=rmse, median_seconds=2.0)

    summary = {"a": run("detected", 0.0, 4.0, 2.0), "b": run("detected", 0.5, 3.0, 1.0),
               "c": run("truth", 0.0, 1.0, 1.0), "d": run("truth", 0.5, 2.0, 1.5), "e": run("detected", 1.0, 2.0, 1.5)}
    rows = bench.dense_comparison(summary)
    assert [(r["landmarks"], r["dense_weight"]) for r in rows] == [("detected", 0.5), ("truth", 0.5), ("detected", 1.0)]
    assert rows[0]["landmark_reduction"] == 0.25 and rows[0]["rmse_reduction"] == 0.5
    assert rows[0]["rmse_mm_off"] == 2.0 and rows[0]["rmse_mm_on"] == 1.0
    assert rows[1]["rmse_reduction"] == -0.5
    table = bench.format_comparison(rows, ("off", "on"), "dense")
    assert table.startswith("dense:") and "RMSE mm on" in table and "detected" in table


@pytest.mark.detect
def test_detected_samples_hold_mediapipe_points_near_the_truth(demo_face_model):
    samples = [bench.synthetic_face(demo_face_model, np.random.default_rng(s), 256) for s in (0, 2)]
    by_source, missed = bench.detect_photos({"softras": samples})
    truth, detected = by_source["truth"]["softras"], by_source["detected"]["softras"]
    assert missed == {"softras": 0} and len(truth) == len(detected) == 2
    for t, d, sample in zip(truth, detected, samples):
        np.testing.assert_array_equal(t["landmarks"], sample["landmarks"])     # the true ones, noisy
        assert d["dense"].shape == (468, 2) and np.array_equal(t["dense"], d["dense"])
        error = np.linalg.norm(d["landmarks"] - sample["clean_landmarks"], axis=1)
        assert 0.5 < np.median(error) < 15.0             # MediaPipe's points, not the truth's


@pytest.mark.detect
def test_each_renderers_photo_is_fitted_from_the_points_found_on_it(demo_face_model):
    """A second renderer's photo moved by 9 px right and 6 px down: its detected points move
    with it, so they were found on its own photo; a face missed on one photo leaves every run."""
    samples = [bench.synthetic_face(demo_face_model, np.random.default_rng(s), 256) for s in (0, 2)]
    moved = [dict(s, photo=np.roll(s["photo"], (6, 9), axis=(0, 1))) for s in samples]
    blank = [moved[0], dict(moved[1], photo=np.full_like(moved[1]["photo"], 0.3))]
    by_source, missed = bench.detect_photos({"softras": samples, "other": moved})
    assert missed == {"softras": 0, "other": 0}
    for a, b in zip(by_source["detected"]["softras"], by_source["detected"]["other"]):
        shift = np.median(b["landmarks"] - a["landmarks"], axis=0)
        np.testing.assert_allclose(shift, [9.0, 6.0], atol=1.5)
    by_source, missed = bench.detect_photos({"softras": samples, "other": blank})
    assert missed == {"softras": 0, "other": 1}
    assert [len(by_source[s][r]) for s in ("truth", "detected") for r in ("softras", "other")] == [1, 1, 1, 1]


@pytest.mark.slow
@pytest.mark.detect
def test_bench_face_compares_the_dense_term_on_detected_landmarks(tmp_path, capsys):
    said, doc = _bench(tmp_path, capsys, "--size", "128", "--landmarks", "detected", "--dense", "0,0.5", "--seed", "0")
    assert "without against with the dense landmark term" in said
    assert list(doc["summary"]) == _run_names("detected landmarks/{budget}/dense {choice}", ("0", "0.5"))
    assert [(r["budget"], r["dense_weight"]) for r in doc["dense_comparison"]] == [("landmarks-only", 0.5),
                                                                                    ("fast", 0.5)]
    off, on = (doc["summary"][f"detected landmarks/fast/dense {w}"] for w in ("0", "0.5"))
    assert off["landmark_error_px"] != on["landmark_error_px"]


@pytest.mark.detect
def test_bench_face_says_so_when_the_detector_finds_no_face(tmp_path, capsys):
    out = tmp_path / "bench"
    assert main(["bench", "face", "--faces", "1", "--size", "64", "--yaws", "75-80", "--landmarks", "truth,detected",
                 "--budgets", "fast", "--out", str(out)]) == 1
    assert "the detector found none of the 1 faces: nothing to fit" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.detect
def test_bench_face_leaves_out_a_yaw_bin_the_detector_misses(tmp_path, capsys):
    said, doc = _bench(tmp_path, capsys, "--size", "128", "--yaws", "0-15,75-80", "--landmarks", "truth,detected",
                       "--seed", "1")
    assert doc["undetected_faces"] == {"yaw 0-15": {"softras": 0}, "yaw 75-80": {"softras": 1}}
    assert {s["yaw_bin"] for s in doc["summary"].values()} == {"yaw 0-15"} and "yaw 0-15" in said
