"""Whether 68 points can be a face's iBUG 300-W landmarks: checks that stop a face fit which
cannot be right (docs/reliability.md, "Fits that cannot be right"), and that refuse a detected
face's points (fitting.detection.faces.implausible_landmarks uses :func:`layout_faults`).

Before the fit, :func:`check_landmark_layout` refuses 68 landmarks whose order does not fit the
iBUG 300-W layout (0-16 jaw line from the face's right to its left, 17-21 and 22-26 brows, 27-35
nose, 36-41 and 42-47 eyes, 48-67 mouth; the face's right is the photo's left). Each test is made
in the face's own frame, set by the landmarks themselves (across: from the right half of the jaw
line to its left half; up: across turned a quarter turn), so a face at any roll passes, and so
does the photo of a mirrored face with its landmarks detected on it.
:func:`check_distinct_landmarks` refuses landmarks that are (nearly) all one point. After the
fit, fitting.metrics.check_face_result checks its result. The thresholds and the measurements
behind them are in docs/reliability.md.
"""
from __future__ import annotations

import numpy as np

from softras_cl.errors import InputError, ResultError
from softras_cl.fitting.keypoints.ibug68 import (CHIN, JAW, LEFT_BROW, LEFT_EYE, MOUTH, NOSE_TIP, RIGHT_BROW,
                                                 RIGHT_EYE)

__all__ = ["check_distinct_landmarks", "check_landmark_layout", "layout_faults", "MIN_DISTINCT_LANDMARKS"]

# Fewer distinct points than this (of 68) are not a face: a detector's placeholder output, or
# one point repeated. A closed mouth makes at most 3 inner-lip points coincide.
MIN_DISTINCT_LANDMARKS = 34
# Landmarks that all lie within this many pixels of each other are one point, not a face.
COINCIDENT_PX = 1.0

# More crossings of the jaw line than this are not a face: measured at most 2 on synthetic faces
# with noisy landmarks (yaw up to 80 degrees, or 4 px noise), at least 3 with the points shuffled.
MAX_JAW_CROSSINGS = 2


def check_distinct_landmarks(points) -> None:
    """InputError when the landmarks (N, 2) are (nearly) all the same point: all within
    COINCIDENT_PX pixels, or fewer than MIN_DISTINCT_LANDMARKS distinct points."""
    points = np.asarray(points, np.float64)
    extent = float(np.ptp(points, axis=0).max())
    distinct = len(np.unique(points, axis=0))
    if extent < COINCIDENT_PX:
        x, y = np.median(points, axis=0)
        found = (f"all {len(points)} landmarks lie within {extent:.2g} pixels of "
                 f"({x:.6g}, {y:.6g}): they are (nearly) identical")
    elif distinct < MIN_DISTINCT_LANDMARKS:
        found = f"only {distinct} of the {len(points)} landmarks are distinct points, the others repeat them"
    else:
        return
    raise InputError(f"{found}; they are not the points of a face (a failed detection, or a "
                     f"placeholder file?)")


def _face_frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(across, up): unit vectors of the face's frame in the photo (x right, y down): across
    from the right half of the jaw line (points 0-6) to its left half (10-16), up a quarter turn
    from it (towards the brows for a face in iBUG order)."""
    across = points[JAW[10:]].mean(0) - points[JAW[:7]].mean(0)
    across = across / max(float(np.linalg.norm(across)), 1e-12)
    return across, np.array([across[1], -across[0]])


def _segments_cross(a, b, c, d) -> bool:
    """Whether the segments ab and cd (2-vectors) cross at a point inside both."""
    def side(p, q, r):
        return np.sign((q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0]))
    return side(a, b, c) * side(a, b, d) < 0 and side(c, d, a) * side(c, d, b) < 0


def _jaw_crossings(points: np.ndarray) -> int:
    """How many times the jaw line (points 0-16 in order) crosses itself."""
    jaw = points[JAW]
    return sum(_segments_cross(jaw[i], jaw[i + 1], jaw[j], jaw[j + 1])
               for i in range(len(jaw) - 1) for j in range(i + 2, len(jaw) - 1))


def layout_faults(points) -> list[str]:
    """What is wrong with 68 landmarks (68, 2) pixels as iBUG 300-W points, in words (empty:
    nothing found). Each test holds for any roll of a face and with the face turned (yaw,
    pitch) as far as its landmarks can be placed."""
    points = np.asarray(points, np.float64)
    across, up = _face_frame(points)
    crossings = _jaw_crossings(points)

    def along(axis, index):
        return float(np.mean(points[index] @ axis))

    tests = {
        "the eyes (36-41, 42-47) are in the wrong order across the face":
            along(across, RIGHT_EYE) < along(across, LEFT_EYE),
        "the brows (17-21, 22-26) are in the wrong order across the face":
            along(across, RIGHT_BROW) < along(across, LEFT_BROW),
        "the brows are not above the eyes": along(up, np.r_[RIGHT_BROW, LEFT_BROW])
            > along(up, np.r_[RIGHT_EYE, LEFT_EYE]),
        "the eyes are not above the mouth": along(up, np.r_[RIGHT_EYE, LEFT_EYE]) > along(up, MOUTH),
        "the nose tip (30) is not above the chin (8)": along(up, NOSE_TIP) > along(up, CHIN),
        f"the jaw line (0-16) crosses itself {crossings} times": crossings <= MAX_JAW_CROSSINGS,
    }
    return [fault for fault, holds in tests.items() if not holds]


def check_landmark_layout(points) -> None:
    """ResultError (exit 1) naming the likely cause when 68 landmarks (68, 2) pixels cannot be
    a face's iBUG 300-W points (see :func:`layout_faults`): a fit from them cannot be right."""
    points = np.asarray(points, np.float64)
    faults = layout_faults(points)
    if not faults:
        return
    if not layout_faults(points * [-1.0, 1.0]):
        cause = ("they are mirrored: the face's left and right points are swapped (landmarks "
                 "flipped left-right or top-bottom without renumbering them)")
    else:
        cause = ("they are not in the iBUG 300-W 68-point order (shuffled, written in another "
                 "point order, or the points of another face)")
    raise ResultError(f"the landmarks cannot be a face's: {'; '.join(faults)}. Likely cause: {cause}; "
                      f"fitting needs the 68 points in iBUG 300-W order")

