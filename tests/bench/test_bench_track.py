"""`softras-cl bench track`: the synthetic sequences, the measures (one similarity per sequence,
jitter), the target verdicts, and a tiny run end to end."""
import json

import numpy as np
import pytest

from softras_cl.bench import track
from softras_cl.fitting.recipes import face
from softras_cl.scene.rotation import axis_angle_to_matrix


def test_trajectories_are_smooth_and_bounded():
    times = np.arange(300) / 30
    signal = track.smooth_signal(np.random.default_rng(0), times, (25.0, 10.0))
    assert signal.shape == (300, 2)
    assert np.all(np.abs(signal) <= [25.0, 10.0]) and np.ptp(signal[:, 0]) > 10
    # 0.7 Hz at most: a frame's second difference is tiny against the amplitude
    assert np.abs(np.diff(signal[:, 0], n=2)).max() < 25.0 * (2 * np.pi * 0.7 / 30) ** 2 * 1.01


def test_sequence_is_one_person_moving(demo_face_model):
    truth = track.sequence_truth(demo_face_model, np.random.default_rng(1), 20, 64, 30.0)
    assert len(truth) == 20
    for t in truth[1:]:
        np.testing.assert_array_equal(t["id"], truth[0]["id"])
        np.testing.assert_array_equal(t["focal"], truth[0]["focal"])
    steps = [np.degrees(np.linalg.norm(b["rotation"] - a["rotation"])) for a, b in zip(truth, truth[1:])]
    assert 0 < max(steps) < 5                        # degrees per frame at 30 fps
    assert not np.array_equal(truth[0]["exp"], truth[-1]["exp"])


def test_similarity_is_one_for_the_whole_sequence():
    rng = np.random.default_rng(2)
    truth = rng.normal(size=(5, 30, 3))
    R = axis_angle_to_matrix([0.1, -0.3, 0.2])
    moved = 1.7 * truth @ R.T + [0.1, 0.2, -3.0]
    np.testing.assert_allclose(track.similarity_onto(moved, truth), truth, atol=1e-12)
    # a per-frame change cannot be taken out by the one similarity
    wobble = moved.copy()
    wobble[2] += 0.05
    assert track.sequence_errors(wobble, truth, np.zeros((5, 68, 2)), np.zeros((5, 68, 2)))["jitter_mm"] > 0


def test_jitter_is_the_rms_second_difference_of_the_error():
    truth = np.zeros((4, 2, 3))
    fitted = truth.copy()
    fitted[:, :, 0] = np.array([0.0, 0.001, 0.0, 0.001])[:, None]       # +-1 mm zig-zag along x
    fitted[:, 1, 1] = 1.0                                                # two vertices set apart (no collapse)
    truth[:, 1, 1] = 1.0
    errors = track.sequence_errors(fitted, truth, np.ones((4, 68, 2)), np.zeros((4, 68, 2)))
    # the similarity takes out the mean offset; second differences of the zig-zag: +-2 mm
    assert errors["jitter_mm"] == pytest.approx(2.0, rel=1e-6)
    assert errors["landmark_error_px"] == pytest.approx(np.sqrt(2))


def _summary_row(jitter_t, jitter_i, vertex_t=1.0, vertex_i=2.0, identity=0.5, best=0.6, mean=0.8, fps=20.0):
    errors = lambda v, j: dict(vertex_error_mm=v, landmark_error_px=1.0, jitter_mm=j)   # noqa: E731
    return dict(frame_fps=fps, end_to_end_fps=5.0, tracker_on_independent_frames=errors(vertex_t, jitter_t),
                unsmoothed_on_independent_frames=errors(vertex_t, 2 * jitter_t), light_error=0.1, light_error_identity=0.2,
                independent=dict(errors(vertex_i, jitter_i), best_single_ratio=best, mean_single_ratio=mean,
                                 seconds_per_frame=2.0), identity_ratio=identity, identity_seconds=10.0)


@pytest.mark.parametrize("row, targets", [
    (_summary_row(0.3, 1.0), dict(frame_fps=True, jitter=True, identity=True)),
    (_summary_row(0.4, 1.0, fps=9.0), dict(frame_fps=False, jitter=False, identity=True)),
    (_summary_row(0.3, 1.0, vertex_t=3.0), dict(frame_fps=True, jitter=False, identity=True)),
    (_summary_row(0.3, 1.0, identity=0.57), dict(frame_fps=True, jitter=True, identity=False)),
    (_summary_row(0.3, 1.0, identity=0.65), dict(frame_fps=True, jitter=True, identity=False)),
])
def test_targets_are_never_lowered(row, targets):
    assert track.summarise([row])["targets"] == targets


@pytest.mark.video
@pytest.mark.slow
def test_bench_track_runs_end_to_end(tmp_path, run_cli, monkeypatch):
    monkeypatch.setitem(face.BUDGETS, "fast", dict(landmark_iters=10, photo_stages=((1e-4, 3e-3, 4),)))
    result = run_cli("bench", "track", "--sequences", "1", "--frames", "6", "--independent", "4", "--size", "96",
                     "--landmarks", "noisy", "--out", tmp_path)
    assert result.code == 0, result.err
    doc = json.loads((tmp_path / "track.json").read_text())
    row = doc["sequences"][0]
    assert row["frames"] == 6 and row["independent_frames"] == 4 and row["held"] == 0
    assert row["tracker"]["landmark_error_px"] < 5.0
    assert set(doc["summary"]["targets"]) == {"frame_fps", "jitter", "identity"}
    assert "cpu" in json.dumps(doc["provenance"]).lower()
    for name in ("track_strip.png", "track_jitter.png", "sequence_0.mp4"):
        assert (tmp_path / name).is_file()
    assert "per-frame stage" in result.out and "before the fixed-lag smoothing" in result.out
    assert row["light_error"] >= 0 and row["unsmoothed_on_independent_frames"]["jitter_mm"] >= 0


def test_appearance_error_is_relative_to_the_truths_colour(demo_face_model):
    """The truth's own colours: 0; its light 10% brighter: 0.1 x RMS / mean of the true colours."""
    from softras_cl.bench.face import random_truth
    from softras_cl.fitting.recipes.face import FaceScene

    model = demo_face_model
    truth = random_truth(model, np.random.default_rng(2), 128)
    world = FaceScene(model, (128, 128)).geometry(truth)[0]
    albedo = model.albedo(truth["albedo"])[0]
    assert track.appearance_error(model, world, albedo, truth["sh"], truth, world) == pytest.approx(0.0, abs=1e-12)
    brighter = track.appearance_error(model, world, albedo, 1.1 * truth["sh"], truth, world)
    assert 0.1 * 0.9 < brighter < 0.1 * 1.5          # RMS over mean of positive colours: a little above 1
    assert track.appearance_error(model, world, 0.5 * albedo, truth["sh"], truth, world) > 4 * brighter


def test_a_failed_independent_fit_is_counted_and_held(demo_face_model):
    """A frame whose independent fit raised takes the fit before it (the first one after it at
    the start), is left out of the identity ratios and is counted with its message."""
    from types import SimpleNamespace

    model = demo_face_model
    truth_id = np.zeros(model.n_id)

    def fake(k):
        world = np.full((4, 3), float(k))
        return SimpleNamespace(scene=SimpleNamespace(geometry=lambda values: (world, None), model=model),
                               crop=SimpleNamespace(to_full=lambda points: points),
                               fitted_landmarks=lambda: np.full((68, 2), float(k)), values=dict(id=truth_id))

    fits = [(ValueError("behind the camera"), 1.0), (fake(1), 1.0), (ValueError("again"), 1.0), (fake(3), 1.0)]
    sequence = dict(vertices=np.zeros((4, 4, 3)), landmarks=np.zeros((4, 68, 2)), truth=[dict(id=truth_id)])
    measured = track.independent_measures(model, fits, sequence)
    assert measured["failed"] == 2 and measured["first_failure"] == "behind the camera"
    held = np.array([1.0, 1.0, 1.0, 3.0])                       # frames 0 and 2 held
    assert measured["landmark_error_px"] == pytest.approx(np.mean(held * np.sqrt(2)))
    with pytest.raises(ValueError, match="every independent fit failed"):
        track.independent_measures(model, [fits[0]], sequence)


@pytest.mark.mitsuba
def test_mitsuba_frames_differ_from_softras_but_put_the_face_where_the_truth_says(demo_face_model, tmp_path):
    """Two small frames path-traced by Mitsuba: other pixels than softras-cl's, the same truth,
    the face covering the same pixels (and its true landmarks), read from the cache when rendered again."""
    model = demo_face_model
    rng = np.random.default_rng(3)
    truth = track.sequence_truth(model, rng, 2, 96, 30.0)
    back = track.background("coffee", 96)
    skin = dict(uvs=rng.uniform(0.0, 1.0, (len(model.mean_shape), 2)), albedo=rng.uniform(0.2, 0.9, (8, 8, 3)))
    soft, soft_marks, soft_world = track.render_frames(model, truth, back)
    options = dict(skin=skin, spp=4, cache=tmp_path / "cache", seed=5)
    mits, marks, world = track.render_frames_mitsuba(model, truth, back, **options)
    np.testing.assert_allclose(marks, soft_marks)
    np.testing.assert_allclose(world, soft_world)
    photo = track.srgb8(back).astype(int)
    for a, b, points in zip(soft, mits, marks):
        face_a = np.abs(a.astype(int) - photo).max(-1) > 12
        face_b = np.abs(b.astype(int) - photo).max(-1) > 12
        assert (face_a & face_b).sum() / (face_a | face_b).sum() > 0.85
        assert np.abs(a.astype(int) - b.astype(int))[face_a & face_b].mean() > 10
        inner = np.round(points[17:]).astype(int)             # brows, eyes, nose and mouth: on the face
        assert face_b[inner[:, 1], inner[:, 0]].mean() > 0.95
    stored = sorted((tmp_path / "cache").glob("mitsuba_*.png"))
    assert len(stored) == 2
    before = [p.stat().st_mtime_ns for p in stored]
    again = track.render_frames_mitsuba(model, truth, back, **options)[0]
    assert [p.stat().st_mtime_ns for p in stored] == before
    np.testing.assert_array_equal(np.array(again), np.array(mits))


@pytest.mark.parametrize("options, says", [(("--renderer", "blender"), ("--renderer", "'blender'")),
                                           (("--renderer", "mitsuba", "--spp", "1"), ("--spp must be >= 2", "got 1"))])
def test_a_bad_renderer_or_spp_is_refused(tmp_path, run_cli, options, says):
    result = run_cli("bench", "track", *options, "--out", tmp_path / "b")
    assert result.code == 2 and all(words in result.err for words in says), result.err
    assert not (tmp_path / "b").exists()                 # refused before any work
