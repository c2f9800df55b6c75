"""fitting.recipes.face_track: the per-frame objective's gradients, keyframes, the tracker on a
short synthetic sequence."""
from __future__ import annotations

import numpy as np
import pytest

from softras_cl.errors import InputError
from softras_cl.fitting.detection.follow import FaceFollower
from softras_cl.fitting.recipes.face_track import (FrameObjective, FrameTracker, Identity, LandmarkBasis,
                                                   TrackConfig, TrackerState, choose_keyframes, head_angles_deg)
from softras_cl.scene.rotation import axis_angle_to_matrix, matrix_to_axis_angle

SIZE = 256


def truth_identity(model, rng):
    """A random identity seen by a 256 px camera of focal 480 px."""
    return Identity(np.clip(rng.normal(size=model.n_id), -2, 2), np.zeros(model.n_albedo),
                    np.zeros((3, 9)), 480.0, 0.8, (0,))


def head(yaw_deg, exp, distance=0.6):
    R = axis_angle_to_matrix([0.0, np.radians(yaw_deg), 0.0])
    return dict(rotation=matrix_to_axis_angle(R), translation=np.array([0.0, 0.0, -distance]), exp=exp)


@pytest.mark.parametrize("with_previous", [False, True])
def test_frame_objective_gradients_match_central_differences(demo_face_model, with_previous):
    rng = np.random.default_rng(1)
    model = demo_face_model
    tracker = FrameTracker(model, truth_identity(model, rng), (SIZE, SIZE), TrackConfig())
    values = head(12.0, 0.5 * rng.normal(size=model.n_exp))
    target = tracker.fitted_landmarks(values) + rng.normal(0, 2.0, (68, 2))
    previous = head(10.0, 0.5 * rng.normal(size=model.n_exp)) if with_previous else None   # the prediction
    objective = FrameObjective(tracker.basis, tracker.camera, 0.8, TrackConfig(), target, previous, 1 / 30)
    loss, grads, terms = objective(values)
    assert set(terms) == ({"landmarks", "exp_prior", "smooth_pose", "smooth_exp"} if with_previous
                          else {"landmarks", "exp_prior"})
    assert loss == pytest.approx(sum(terms.values()))
    for name in ("rotation", "translation", "exp"):
        step = 1e-6 if name != "translation" else 1e-8
        numeric = np.zeros_like(values[name])
        for i in range(values[name].size):
            up, down = dict(values), dict(values)
            up[name] = values[name].copy()
            down[name] = values[name].copy()
            up[name][i] += step
            down[name][i] -= step
            numeric[i] = (objective(up)[0] - objective(down)[0]) / (2 * step)
        np.testing.assert_allclose(grads[name], numeric, rtol=1e-5, atol=1e-6 * np.abs(numeric).max())


def test_temporal_terms_weigh_by_the_time_between_frames(demo_face_model):
    rng = np.random.default_rng(2)
    tracker = FrameTracker(demo_face_model, truth_identity(demo_face_model, rng), (SIZE, SIZE), TrackConfig())
    values = head(5.0, np.zeros(demo_face_model.n_exp))
    previous = head(3.0, np.full(demo_face_model.n_exp, 0.1))
    target = tracker.fitted_landmarks(values)

    def smooth(dt):
        terms = FrameObjective(tracker.basis, tracker.camera, 1.0, TrackConfig(), target, previous, dt)(values)[2]
        return terms["smooth_pose"], terms["smooth_exp"]

    # a random walk: the same step twice as far apart in time costs half as much
    np.testing.assert_allclose(smooth(1 / 15), np.array(smooth(1 / 30)) / 2)
    cfg = TrackConfig()
    rotation_step = np.linalg.norm(values["rotation"] - previous["rotation"])
    assert smooth(1.0)[0] == pytest.approx(rotation_step ** 2 / cfg.rotation_speed ** 2)
    assert smooth(1.0)[1] == pytest.approx(0.01 * demo_face_model.n_exp / cfg.exp_speed ** 2)


def test_landmark_basis_is_the_model_at_that_expression(demo_face_model):
    rng = np.random.default_rng(3)
    identity = rng.normal(size=demo_face_model.n_id)
    exp = rng.normal(size=demo_face_model.n_exp)
    basis = LandmarkBasis(demo_face_model, identity)
    expected = demo_face_model.landmarks(demo_face_model.shape(identity, exp)[0])[0]
    np.testing.assert_allclose(basis.points(exp), expected, atol=1e-12)


def test_keyframes_spread_over_the_poses(demo_face_model):
    rng = np.random.default_rng(4)
    tracker = FrameTracker(demo_face_model, truth_identity(demo_face_model, rng), (SIZE, SIZE), TrackConfig())
    yaws = {i: y for i, y in enumerate([0, 1, 2, 25, 24, -25, -1, 3])}
    landmarks = {i: tracker.fitted_landmarks(head(y, np.zeros(demo_face_model.n_exp))) for i, y in yaws.items()}
    chosen = choose_keyframes(landmarks, demo_face_model, (SIZE, SIZE), 3)
    picked = sorted(yaws[i] for i in chosen)      # one of each side and a frontal one
    assert picked[0] == -25 and abs(picked[1]) <= 3 and picked[2] >= 24
    assert choose_keyframes({}, demo_face_model, (SIZE, SIZE), 3) == []
    assert head_angles_deg(head(25, None)["rotation"])[0] == pytest.approx(25.0)


def test_config_checks_name_the_field():
    with pytest.raises(InputError, match="frame_iters"):
        TrackConfig(frame_iters=0)
    with pytest.raises(InputError, match="exp_speed"):
        TrackConfig(exp_speed=-1.0)
    with pytest.raises(InputError, match="budget"):
        TrackConfig(identity_budget="nope")


def test_identity_fit_weighs_its_prior_once_per_keyframe():
    """The keyframes share the detector's errors: the joint identity fit's id prior is the
    single photo fit's times the keyframes; the other weights are the joint fit's own."""
    from softras_cl.fitting.recipes.face import FaceFitConfig
    from softras_cl.fitting.recipes.face_settings import joint_config

    single = joint_config(FaceFitConfig.from_budget("fast", size=256))
    for n in (1, 4, 6):
        config = TrackConfig(keyframes=n).face_config()
        assert config.weights["id_prior"] == n * single.weights["id_prior"]
        assert {k: v for k, v in config.weights.items() if k != "id_prior"} == \
            {k: v for k, v in single.weights.items() if k != "id_prior"}
        assert config.landmark_weight_photo == single.landmark_weight_photo


def test_tracker_follows_and_is_steadier_than_without_temporal_terms(demo_face_model):
    """30 frames of a turning, talking head with 1.5 px landmark noise: the fitted landmarks
    follow the truth, and the temporal terms cut the frame-to-frame jitter against a tracker
    whose temporal terms are (nearly) off; a frame without landmarks is held."""
    model = demo_face_model
    rng = np.random.default_rng(5)
    identity = truth_identity(model, rng)
    exp_a, exp_b = 0.8 * rng.normal(size=model.n_exp), 0.8 * rng.normal(size=model.n_exp)
    frames = [head(20 * np.sin(k / 10), exp_a + (exp_b - exp_a) * k / 29) for k in range(30)]
    reference = FrameTracker(model, identity, (SIZE, SIZE), TrackConfig())
    clean = [reference.fitted_landmarks(v) for v in frames]
    noisy = [c + rng.normal(0, 1.5, c.shape) for c in clean]

    def run(config):
        tracker = FrameTracker(model, identity, (SIZE, SIZE), config)
        return [tracker.step(None if k == 12 else noisy[k], k / 30, k) for k in range(30)]

    steady = run(TrackConfig())
    loose = run(TrackConfig(rotation_speed=1e3, translation_speed=1e3, exp_speed=1e3))
    errors = [np.linalg.norm(r.fitted - c, axis=1).mean() for r, c in zip(steady, clean)]
    assert np.median(errors) < 1.0
    assert steady[12].held and steady[12].detected is None and not steady[13].held
    np.testing.assert_array_equal(steady[12].values["rotation"], steady[11].values["rotation"])

    def jitter(results):
        fitted = np.array([r.fitted for r in results[13:]])       # after the held frame
        truth = np.array(clean[13:])
        return np.sqrt(np.mean(np.diff(fitted - truth, n=2, axis=0) ** 2))

    assert jitter(steady) < 0.6 * jitter(loose)


def test_state_round_trips_through_arrays():
    state = TrackerState(dict(rotation=np.arange(3.0), translation=np.ones(3), exp=np.zeros(4)), 1.5, True)
    back = TrackerState.from_arrays(state.to_arrays())
    assert back.time == 1.5 and back.held
    np.testing.assert_array_equal(back.values["rotation"], np.arange(3.0))
    assert TrackerState.from_arrays(TrackerState().to_arrays()).values is None


def test_frames_before_the_first_face_are_held_without_values(demo_face_model):
    rng = np.random.default_rng(6)
    tracker = FrameTracker(demo_face_model, truth_identity(demo_face_model, rng), (SIZE, SIZE), TrackConfig())
    clean = tracker.fitted_landmarks(head(-10.0, np.zeros(demo_face_model.n_exp)))
    before = tracker.step(None, 0.0, 0)
    assert before.held and np.isnan(before.values["rotation"]).all() and np.isnan(before.fitted).all()
    first = tracker.step(clean, 0.04, 1)                      # started from the closed-form pose
    assert not first.held and "smooth_pose" not in first.terms
    assert np.linalg.norm(first.fitted - clean, axis=1).mean() < 0.5
    assert "smooth_pose" in tracker.step(clean, 0.08, 2).terms


def test_ctrl_c_in_a_frames_fit_stops_the_tracking(demo_face_model, monkeypatch):
    """The solver keeps Ctrl-C to itself (it returns interrupted=True): the tracker raises it on."""
    from softras_cl.fitting.recipes import face_track
    from softras_cl.fitting.solver import FitResult

    rng = np.random.default_rng(7)
    tracker = FrameTracker(demo_face_model, truth_identity(demo_face_model, rng), (SIZE, SIZE), TrackConfig())
    clean = tracker.fitted_landmarks(head(0.0, np.zeros(demo_face_model.n_exp)))
    monkeypatch.setattr(face_track, "fit", lambda params, *a, **k: FitResult(params.values(), 0.0, [], {}, True))
    with pytest.raises(KeyboardInterrupt):
        tracker.step(clean, 0.0, 0)
    assert tracker.state.values is None


def test_detector_offsets_are_found_from_keyframes_at_several_yaws(demo_face_model):
    """A detector that puts every landmark a few millimetres off the model's point, the same
    on the face in every frame: the keyframes (yaw -25, 0, 25) recover the offsets, and the
    tracker fitting with them puts the model back where the frame's face is."""
    from softras_cl.fitting.recipes.face_track import detector_offsets

    model = demo_face_model
    rng = np.random.default_rng(8)
    identity = truth_identity(model, rng)
    tracker = FrameTracker(model, identity, (SIZE, SIZE), TrackConfig())
    offsets = rng.normal(0, 0.004, (68, 3))
    shifted = LandmarkBasis(model, identity.id, offsets)
    poses = [head(y, 0.3 * rng.normal(size=model.n_exp)) for y in (-25, 0, 25)]
    from softras_cl.fitting.recipes.face_track import project_landmarks

    detected = [project_landmarks(shifted, tracker.camera, p)[0] for p in poses]
    found = detector_offsets(tracker.basis, tracker.camera, poses, detected, noise_px=0.01)
    # one linearised step: within a few per cent of millimetre offsets
    np.testing.assert_allclose(found, offsets, atol=0.1 * np.abs(offsets).max())
    with_offsets = FrameTracker(model, Identity(identity.id, identity.albedo, identity.sh, identity.focal, 0.8, (0,),
                                                found), (SIZE, SIZE), TrackConfig())
    truth = head(10.0, 0.3 * rng.normal(size=model.n_exp))
    result = with_offsets.step(project_landmarks(shifted, tracker.camera, truth)[0], 0.0, 0)
    error = np.linalg.norm(result.fitted - tracker.fitted_landmarks(truth), axis=1).mean()
    plain = np.linalg.norm(tracker.step(project_landmarks(shifted, tracker.camera, truth)[0], 0.0, 0).fitted
                           - tracker.fitted_landmarks(truth), axis=1).mean()
    assert error < 0.5 * plain


def test_second_identity_pass_fits_landmarks_corrected_by_the_first_offsets(demo_face_model, monkeypatch):
    """fit_identity's passes (the joint fit itself replaced by a stand-in that records what it is
    given): the second pass sees the detected landmarks moved back by the first pass's offsets,
    and the offsets returned are those of the detected landmarks, not of the corrected ones."""
    from softras_cl.fitting.recipes import face_track

    model = demo_face_model
    rng = np.random.default_rng(9)
    identity = truth_identity(model, rng)
    tracker = FrameTracker(model, identity, (SIZE, SIZE), TrackConfig())
    poses = [head(y, np.zeros(model.n_exp)) for y in (-20, 20)]
    offsets = rng.normal(0, 0.004, (68, 3))
    detected = [face_track.project_landmarks(LandmarkBasis(model, identity.id, offsets), tracker.camera, p)[0]
                for p in poses]
    given = []

    def joint(images, landmarks, keyframes, model_, config, progress):
        given.append([np.array(p) for p in landmarks])
        return Identity(identity.id, identity.albedo, identity.sh, identity.focal, 0.8, (0, 1)), tracker.camera, poses

    monkeypatch.setattr(face_track, "_joint_identity", joint)
    found = face_track.fit_identity([None, None], detected, (0, 1), model, TrackConfig(identity_passes=2))
    assert len(given) == 2
    np.testing.assert_array_equal(given[0][0], detected[0])
    plain = [face_track.project_landmarks(tracker.basis, tracker.camera, p)[0] for p in poses]
    # the model here is the truth: the corrected landmarks are (nearly) the model's own
    assert np.abs(given[1][0] - plain[0]).max() < 0.2 * np.abs(detected[0] - plain[0]).max()
    # across the line of sight (depth is left to the prior by two views 40 degrees apart)
    np.testing.assert_allclose(found.landmark_offsets[:, :2], offsets[:, :2], atol=0.15 * np.abs(offsets).max())


@pytest.mark.parametrize("fmt", ["ply", "obj"])
def test_mesh_exporter_writes_each_frames_face_in_the_camera_frame(demo_face_model, tmp_path, fmt):
    """--export-meshes: a frame's mesh is the identity at its expression, turned and moved by its
    pose (computed here from the model itself); a frame before any face writes none."""
    from softras_cl.fitting.reports.face_track import MeshExporter
    from softras_cl.io.meshes import load_mesh

    model = demo_face_model
    identity = truth_identity(model, np.random.default_rng(8))
    tracker = FrameTracker(model, identity, (SIZE, SIZE), TrackConfig())
    values = head(15.0, 0.5 * np.ones(model.n_exp))
    exporter = MeshExporter(tmp_path, model, identity, fmt)
    exporter.write(tracker.step(None, 0.0, 0))                          # before the first face
    exporter.write(tracker.step(tracker.fitted_landmarks(values), 0.1, 1))
    assert sorted(p.name for p in (tmp_path / "meshes").iterdir()) == [f"frame_000001.{fmt}"]
    fitted = tracker.state.values
    R = axis_angle_to_matrix(fitted["rotation"])
    expected = model.shape(identity.id, fitted["exp"])[0] @ R.T + fitted["translation"]
    mesh = load_mesh(tmp_path / "meshes" / f"frame_000001.{fmt}")
    np.testing.assert_allclose(mesh.vertices, expected, atol=1e-6)
    np.testing.assert_array_equal(mesh.faces, model.faces)


def _appearance_error(model, truth, world, sh) -> float:
    """RMS (linear RGB) of albedo x SH shading at the vertices facing the camera, sh against the truth's."""
    from softras_cl.scene.shading import SH_A, sh_basis, vertex_normals

    normals = vertex_normals(world[None], model.faces)[0][0]
    seen = np.einsum("vi,vi->v", normals, -world) / np.linalg.norm(world, axis=1) > 0.3
    basis = sh_basis(normals[seen]) * SH_A
    albedo = model.albedo(truth["albedo"])[0][seen]
    return float(np.sqrt(np.mean((albedo * (basis @ (sh - truth["sh"]).T)) ** 2)))


def test_frame_light_is_fitted_to_the_frames_pixels(demo_face_model):
    """A face rendered under a light other than the identity's: the frame's fitted light shades
    it within a fifth of the identity light's error; with light_speed 0 the identity's is kept;
    the next frame's light is drawn towards the last one by the temporal prior."""
    from softras_cl.bench.face import random_truth
    from softras_cl.bench.track import render_frames

    model = demo_face_model
    rng = np.random.default_rng(11)
    truth = random_truth(model, rng, SIZE)
    images, landmarks, worlds = render_frames(model, [truth], np.full((SIZE, SIZE, 3), 0.2))
    wrong = truth["sh"].copy()
    wrong[:, 1:4] -= 0.4 * truth["sh"][0, 0] * np.array([1.0, -0.5, 0.3])      # the light from elsewhere
    identity = Identity(truth["id"], truth["albedo"], wrong, float(truth["focal"][0]), 1.0, (0,))
    tracker = FrameTracker(model, identity, (SIZE, SIZE), TrackConfig())
    first = tracker.step(landmarks[0], 0.0, 0, images[0])
    before = _appearance_error(model, truth, worlds[0], wrong)
    after = _appearance_error(model, truth, worlds[0], first.values["sh"])
    assert after < 0.2 * before, (after, before)
    assert 0 < first.terms["light_residual"] < 0.03

    held = FrameTracker(model, identity, (SIZE, SIZE), TrackConfig(light_speed=0)).step(landmarks[0], 0.0, 0, images[0])
    np.testing.assert_array_equal(held.values["sh"], wrong)

    slow = FrameTracker(model, identity, (SIZE, SIZE), TrackConfig(light_speed=1e-3))
    slow.step(landmarks[0], 0.0, 0, images[0])
    slow.state.values["sh"] = wrong                                    # as if the last frame had the wrong light
    steady = slow.step(landmarks[0], 1 / 30, 1, images[0]).values["sh"]
    assert np.abs(steady - wrong).max() < 0.1 * np.abs(first.values["sh"] - wrong).max()


def _result(k, values, held=False, time_s=None):
    from softras_cl.fitting.recipes.face_track import FrameResult

    return FrameResult(k, k / 30 if time_s is None else time_s, values, None, np.zeros((68, 2)), held, {}, 1, 0.0)


def test_fixed_lag_smoothing_is_a_savitzky_golay_filter_inside_a_stretch():
    """Inside a stretch of uniform frames: scipy's Savitzky-Golay filter (2 lag + 1 frames, order
    2); frames come out lag frames late, the rest at flush; a held frame passes unchanged and
    ends the stretches on either side of it; a resumed smoother given the frames before gives
    what an uninterrupted one gives."""
    from scipy.signal import savgol_filter

    from softras_cl.fitting.recipes.face_track import FixedLagSmoother

    rng = np.random.default_rng(3)
    lag, n = 3, 40
    raw = [dict(rotation=rng.normal(size=3), translation=rng.normal(size=3), exp=rng.normal(size=5),
                sh=np.full((3, 9), float(k))) for k in range(n)]
    results = [_result(k, v, held=k == 25) for k, v in enumerate(raw)]

    def run(smoother, items):
        out = []
        for r in items:
            done = smoother.push(r, r.index)
            assert all(extra == r.index - smoother.lag for _, extra in done)        # lag frames late
            out += done
        return out + smoother.flush()

    whole = run(FixedLagSmoother(lag, lambda v: np.full((68, 2), v["rotation"][0])), results)
    assert [extra for _, extra in whole] == list(range(n))
    smoothed = np.array([r.values["rotation"] for r, _ in whole])
    reference = savgol_filter(np.array([v["rotation"] for v in raw[:25]]), 2 * lag + 1, 2, axis=0)
    np.testing.assert_allclose(smoothed[lag:25 - lag], reference[lag:25 - lag], atol=1e-12)
    assert whole[25][0] is results[25]                                       # held: as it was
    np.testing.assert_allclose(smoothed[30], savgol_filter(np.array([v["rotation"] for v in raw[26:]]),
                                                           2 * lag + 1, 2, axis=0)[4], atol=1e-12)
    first = whole[10][0]
    assert first.fit is raw[10] and first.fitted[0, 0] == first.values["rotation"][0]
    np.testing.assert_array_equal(first.values["sh"], raw[10]["sh"])          # the light is not smoothed

    resumed = run(FixedLagSmoother(lag, lambda v: np.zeros((68, 2)), history=results[10:20]), results[20:])
    for (a, _), (b, _) in zip(resumed, whole[20:]):
        np.testing.assert_array_equal(a.values["exp"], b.values["exp"])
    assert all(r is s for (r, _), s in zip(run(FixedLagSmoother(0, None), results), results))


def _face_points(centre=(100.0, 80.0), eye_distance=40.0, roll_deg=0.0) -> np.ndarray:
    """(68, 2) landmarks on a grid scaled to the eye distance, outer eye corners (36, 45) level
    at eye_distance apart, turned by roll_deg about centre."""
    rng = np.random.default_rng(3)
    points = rng.uniform(-0.6, 0.6, (68, 2)) * eye_distance
    points[36], points[45] = (-eye_distance / 2, 0.0), (eye_distance / 2, 0.0)
    a = np.radians(roll_deg)
    turn = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return points @ turn.T + centre


@pytest.mark.parametrize("roll, shift, agrees", [(0, 0, True), (20, 10, True), (59, 0, True),
                                                 (180, 0, False), (90, 0, False), (0, 70, False)])
def test_follower_agrees_only_with_a_plausible_next_frame(roll, shift, agrees):
    previous = _face_points()
    points = _face_points(centre=(100.0 + shift, 80.0), roll_deg=roll)
    assert FaceFollower.agrees(points, previous) is agrees


def test_follower_refuses_upside_down_landmarks_near_the_face(monkeypatch):
    """A detector's upside-down face in the crop is not taken: the whole frame's face is, when it
    agrees with the previous frame; when that does not either, the frame has no face."""
    previous = _face_points()
    follower = FaceFollower()
    flipped, steady = _face_points(roll_deg=180.0), _face_points(centre=(104.0, 81.0), roll_deg=5.0)
    monkeypatch.setattr(follower, "_near", lambda image, prev: flipped)
    monkeypatch.setattr(follower, "_whole", lambda image: steady)
    assert np.array_equal(follower.find(None, previous), steady)
    monkeypatch.setattr(follower, "_whole", lambda image: flipped)
    assert follower.find(None, previous) is None
    monkeypatch.setattr(follower, "_near", lambda image, prev: steady)
    assert np.array_equal(follower.find(None, previous), steady)


def test_follower_takes_the_landmark_stage_near_the_face_when_it_agrees(monkeypatch):
    """FaceFollower._near: the backend's landmark stage alone on the crop the previous landmarks
    place (find.face_near) when its face agrees with them; the detector on the crop when it
    finds none or a face that does not agree (turned over)."""
    from softras_cl.fitting.detection import follow

    previous = _face_points()
    steady, flipped = _face_points(centre=(104.0, 81.0), roll_deg=5.0), _face_points(roll_deg=180.0)
    detector = _face_points(centre=(102.0, 80.0))
    follower = FaceFollower()
    detected = []
    monkeypatch.setattr(follower, "_detect", lambda image, **choice: detected.append(choice) or detector)
    image = np.zeros((200, 240, 3), np.uint8)
    monkeypatch.setattr(follow, "face_near", lambda image, points, backend: steady)
    assert np.array_equal(follower._near(image, previous), steady) and detected == []
    for near in (None, flipped):
        detected.clear()
        monkeypatch.setattr(follow, "face_near", lambda image, points, backend: near)
        found = follower._near(image, previous)
        shift = found - detector                  # the detector's points, from its crop's pixels
        assert len(detected) == 1 and np.allclose(shift, shift[0]) and np.all(shift[0] >= 0)


def test_frame_objective_answers_a_head_behind_the_camera(demo_face_model):
    """A solver's point that puts a landmark at or behind the camera (a long step on a wild
    detection) gets fitting.solver.too_close_result instead of stopping the video's fit."""
    from softras_cl.fitting.solver import MIN_DEPTH, TOO_CLOSE_LOSS

    rng = np.random.default_rng(4)
    model = demo_face_model
    tracker = FrameTracker(model, truth_identity(model, rng), (SIZE, SIZE), TrackConfig())
    values = head(5.0, np.zeros(model.n_exp))
    objective = FrameObjective(tracker.basis, tracker.camera, 0.8, TrackConfig(), tracker.fitted_landmarks(values),
                               None, 1 / 30)
    assert objective(values)[0] < 1.0
    for distance in (MIN_DEPTH / 2, 0.0, -0.3):
        assert objective(dict(values, translation=np.array([0.0, 0.0, -distance]))) == (
            TOO_CLOSE_LOSS, {}, {"too_close": TOO_CLOSE_LOSS})
