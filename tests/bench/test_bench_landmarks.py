"""`bench landmarks`: the scoring (NME, which face a candidate is, the chosen face, the bins and
targets), the frames' geometry, bad options, and the quick run end to end (Mitsuba + detectors)."""
import json

import numpy as np
import pytest

from softras_cl.bench import landmarks as bench
from softras_cl.cli import main
from softras_cl.fitting.detection import FaceCandidate
from softras_cl.fitting.detection.faces import sort_candidates
from softras_cl.io.landmarks import read_landmarks


@pytest.fixture
def truth(examples_landmarks):
    """The astronaut's 68 shipped points: a real face's layout."""
    return read_landmarks(examples_landmarks / "astronaut.pts")


def candidate(points, scale=1.0):
    """A FaceCandidate whose landmarks are ``points`` and whose box is their box times ``scale``."""
    lo, hi = points.min(0), points.max(0)
    centre, size = (lo + hi) / 2, (hi - lo) * scale
    return FaceCandidate(np.concatenate([centre - size / 2, size]), 0.9, points, None, "mediapipe", "test")


def test_nme_is_zero_on_the_truth_and_the_shift_over_the_eye_corner_distance(truth):
    eyes = np.linalg.norm(truth[36] - truth[45])
    assert bench.nme(truth, truth) == 0.0
    assert bench.nme(truth + [3.0, 4.0], truth) == pytest.approx(5.0 / eyes)
    jaw_moved = truth.copy()
    jaw_moved[:17] += [0.0, 10.0]
    assert bench.nme(jaw_moved, truth) == pytest.approx(10.0 * 17 / 68 / eyes)
    assert bench.nme(jaw_moved, truth, slice(17, 68)) == 0.0


def test_a_frame_scores_the_face_found_and_the_face_chosen(truth):
    far = truth * 0.5 + [900.0, 500.0]                     # a second, smaller face elsewhere
    faces = [dict(landmarks=truth), dict(landmarks=far)]
    row = bench.score_frame([candidate(truth + [2.0, 0.0]), candidate(far)], faces, 0.1)
    assert row["found"] and row["chosen_right"] and row["second_found"] and row["false_faces"] == 0
    assert row["nme"] == pytest.approx(2.0 / np.linalg.norm(truth[36] - truth[45]))
    # the detector's box of the small face larger than the intended one's: the default takes the wrong face
    wrong = bench.score_frame(sort_candidates([candidate(truth), candidate(far, scale=3.0)]), faces, 0.1)
    assert wrong["found"] and not wrong["chosen_right"] and wrong["nme"] == 0.0
    # a face that is neither, and no landmarks on the intended one: not found
    stray = bench.score_frame([candidate(truth + [3000.0, 0.0])], faces, 0.1)
    assert not stray["found"] and not stray["chosen_right"] and stray["false_faces"] == 1 and "nme" not in stray
    assert not bench.score_frame([], faces, 0.1)["found"]


def rows(*specs):
    """score rows (found, chosen_right, nme, yaw, width_px, two_faces) for summarise and targets."""
    return [dict(found=f, chosen_right=c, nme=n, nme_51=n, yaw=y, width_px=w, two_faces=t, seconds=0.2)
            for f, c, n, y, w, t in specs]


def test_bins_and_targets():
    r = rows((True, True, 0.02, -10, 100, True), (True, False, 0.04, 50, 45, True),
             (False, False, None, 70, 200, False), (False, False, None, 20, 35, False))
    r = [{k: v for k, v in x.items() if v is not None} for x in r]
    s = bench.summarise(r)
    assert s["detection_rate"] == 0.5 and s["right_face_rate"] == 0.5 and s["nme_median"] == pytest.approx(0.03)
    by_yaw = bench.by_bins(r, "yaw", bench.YAW_BINS)
    assert [b["faces"] for b in by_yaw] == [1, 1, 0, 1, 1] and by_yaw[2]["detection_rate"] is None
    assert by_yaw[4]["detection_rate"] == 0.0 and by_yaw[4]["nme_median"] is None
    t = bench.targets(r, s)
    # the 35 px and the 70 degree faces are not counted: 2 of 2 found
    assert t["detection_rate"] == dict(value=1.0, faces=2, reached=True)
    assert not t["right_face_every_frame"]["reached"] and t["nme_median"]["reached"]
    assert t["seconds_per_photo"] == dict(value=0.2, reached=True)


def test_frames_spread_over_yaw_and_width_with_a_second_face_every_third():
    plans = bench.frame_plans(np.random.default_rng(0), 10, (640, 480))
    yaws = sorted(p["faces"][0]["yaw"] for p in plans)
    assert all(-80 + 16 * i <= y < -80 + 16 * (i + 1) for i, y in enumerate(yaws))
    widths = np.log([p["faces"][0]["width_px"] for p in plans])
    assert 30 <= np.exp(widths.min()) and np.exp(widths.max()) <= 500 and np.ptp(widths) > 0.7 * np.log(500 / 30)
    assert [len(p["faces"]) for p in plans] == [1, 1, 2] * 3 + [1]
    assert all(p["faces"][1]["width_px"] < 0.8 * p["faces"][0]["width_px"] for p in plans if len(p["faces"]) > 1)


def test_a_placed_face_has_its_width_and_stays_apart_from_the_first(demo_face_model):
    plan = dict(frame=[640, 480], faces=[dict(yaw=0.0, pitch=0.0, roll=0.0, width_px=120.0, seed=1),
                                         dict(yaw=30.0, pitch=5.0, roll=-5.0, width_px=60.0, seed=2)])
    first, second = bench.place_faces(demo_face_model, plan, np.random.default_rng(3))
    marks = first["landmarks"]
    assert np.linalg.norm(marks[0] - marks[16]) == pytest.approx(120.0, rel=0.03)    # frontal: the jaw width
    assert marks[36, 0] < marks[45, 0] and marks[27, 1] < marks[8, 1]                  # upright, not mirrored
    for face in (first, second):
        assert face["box"][:2].min() >= 0 and face["box"][2] <= 640 and face["box"][3] <= 480
    assert not bench.boxes_meet(first["box"], second["box"])


@pytest.mark.parametrize("options, says", [(("--frame", "1280"), "--frame must be WIDTH,HEIGHT"),
                                           (("--frame", "32,32"), "--frame must be WIDTH,HEIGHT"),
                                           (("--backends", "opencv"), "--backends must name some of"),
                                           (("--frames", "0"), "--frames must be >= 1")])
def test_bad_options_are_refused(tmp_path, capsys, options, says):
    assert main(["bench", "landmarks", *options, "--out", str(tmp_path / "b")]) == 2
    assert says in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.mitsuba
@pytest.mark.detect
def test_the_quick_bench_runs_and_reuses_its_renders(tmp_path, capsys):
    out = tmp_path / "bench"
    assert main(["bench", "landmarks", "--quick", "--backends", "mediapipe", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    doc = json.loads((out / "landmarks.json").read_text())
    report = doc["backends"]["mediapipe"]
    assert "mediapipe, by |yaw| deg" in said and "mediapipe targets" in said
    assert len(report["frames"]) == 3 and [b["bin"] for b in report["by_yaw"]] == ["0-15", "15-30", "30-45", "45-60", "60-80"]
    assert set(report["targets"]) == {"detection_rate", "right_face_every_frame", "nme_median", "seconds_per_photo"}
    assert report["summary"]["detection_rate"] == 1.0        # faces 60-110 px at |yaw| <= 30 are found
    assert 0.0 < report["summary"]["nme_median"] < 0.3
    assert doc["provenance"]["cpu"] and (out / "landmarks.png").is_file()
    frame = out / "landmarks_cache" / "frame_0000.png"
    before = frame.stat().st_mtime_ns
    assert main(["bench", "landmarks", "--quick", "--backends", "mediapipe", "--out", str(out), "--json"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert frame.stat().st_mtime_ns == before                 # read from the cache, not rendered again
    assert [r["nme"] for r in again["backends"]["mediapipe"]["frames"]] == [r["nme"] for r in report["frames"]]


def test_the_systematic_part_is_the_offset_every_face_shares_in_its_own_frame(truth):
    shift = np.zeros((68, 2))
    shift[:17, 1] = 0.1                                   # the jaw 0.1 eye distances lower, in the face's frame
    eyes = truth[45] - truth[36]
    rows = []
    for k, angle in enumerate((0.0, 0.4, -0.3)):          # the same offset on faces at three rolls
        turn = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        face = truth @ turn.T
        offsets = shift * np.linalg.norm(eyes) @ np.array([[eyes[0], eyes[1]], [-eyes[1], eyes[0]]]) / np.linalg.norm(eyes)
        found = face + offsets @ turn.T
        rows.append(dict(found=True, yaw=5.0, offsets=bench.face_frame_offsets(found, face)))
    rows.append(dict(found=True, yaw=5.0, offsets=np.full((68, 2), 3.0)))    # one face meshed wrongly
    rows.append(dict(found=True, yaw=50.0, offsets=np.full((68, 2), 9.0)))   # a turned face is not counted
    assert bench.systematic_nme(rows) == pytest.approx(0.1 * 17 / 68)
    assert bench.systematic_nme([dict(found=False, yaw=0.0)]) is None
