"""Face candidates, the choice among them, and the check that landmarks form a face.

Boxes are (4,) float64 ``(x, y, w, h)`` on the pixel grid: the image spans x 0..W, y 0..H and
pixel (i, j) covers [i, i + 1) x [j, j + 1), so ``--face-box 100,50,80,80`` covers pixel columns
100-179 and rows 50-129. Landmarks are (N, 2) float64 ``(x, y)`` 0-based pixel centres (the
top-left pixel's centre is (0, 0)), the convention of softras_cl.io.landmarks: a landmark at
pixel centre c lies at c + 0.5 on the box grid.
"""
from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softras_cl.errors import InputError, ResultError
from softras_cl.fitting.keypoints import ibug68
from softras_cl.fitting.keypoints.plausibility import layout_faults

#: the order candidates are listed, numbered and chosen in (``--face N`` is the N-th)
ORDER = "largest first (size: its box and its Face Mesh points; ties: higher score first)"


class DetectorUnavailableError(InputError, ImportError):
    """The detector asked for (or the default one) is not installed; the message says what to
    install. An ImportError and an InputError (a ValueError: the command line exits with 2)."""


class NoFaceError(InputError):
    """The detector found no face ("no face found in ..."). An InputError (exit 2)."""


class ImplausibleFaceError(ResultError):
    """The chosen face's landmarks do not form a plausible face (exit 1): fitting them would fit
    something that is not a face."""


def package_folders(name: str) -> list[Path]:
    """The folders of the installed package ``name``, found without importing it (a detector's
    import can take a second); [] when it is not installed."""
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return []
    return [Path(p) for p in (spec.submodule_search_locations or [])] if spec is not None else []


@dataclass(frozen=True)
class FaceCandidate:
    """One face found in an image.

    box: (4,) float64 (x, y, w, h) on the pixel grid (module docstring): the detector's box.
    score: the detector's confidence (MediaPipe: 0-1; dlib: the HOG detector's SVM score;
        NaN where no detector ran, e.g. Face Mesh on a box the user gave).
    landmarks: (68, 2) float64 iBUG 300-W points, 0-based pixel centres, or None when the
        landmark stage found none for this face.
    dense: (478, 2) float64 MediaPipe Face Mesh points (468 + 10 iris), 0-based pixel centres,
        or None (dlib, or no mesh).
    backend: "mediapipe" or "dlib".
    found_by: how it was found, for people ("full-range detector, whole image", ...).
    roll_deg: in-plane rotation of the eye line in degrees (0 upright, positive clockwise in
        the image), NaN when unknown.
    """
    box: np.ndarray
    score: float
    landmarks: np.ndarray | None
    dense: np.ndarray | None
    backend: str
    found_by: str
    roll_deg: float = float("nan")

    @property
    def area(self) -> float:
        """Box area in square pixels, w * h."""
        return float(self.box[2] * self.box[3])

    @property
    def size(self) -> float:
        """What "largest" means, in px: the mean of the box's longer side and the longer side of
        the box of its Face Mesh points where it has them (MediaPipe), else sqrt(area). Either
        alone misjudges some faces: the detectors' boxes of faces of 20-30 px are a few px too
        large, and Face Mesh's points of a face turned 50 degrees or more span less than its
        box (on bench landmarks' frames each put the smaller face first in a frame where the
        other did not; their mean in neither)."""
        if self.dense is None or not np.isfinite(self.dense).all():
            return math.sqrt(max(self.area, 0.0))
        extent = self.dense.max(0) - self.dense.min(0)
        return 0.5 * (float(max(self.box[2], self.box[3])) + float(max(extent)))

    def to_json(self) -> dict:
        """A JSON-ready dict: box, score (None for NaN), landmarks and dense (lists of [x, y],
        0-based pixel centres, 3 decimals; None when absent), backend, found_by, roll_deg."""
        def points(p):
            return None if p is None else np.round(p, 3).tolist()

        def number(v):
            return None if not math.isfinite(v) else round(float(v), 4)

        return dict(box=np.round(self.box, 2).tolist(), score=number(self.score),
                    landmarks=points(self.landmarks), dense=points(self.dense), backend=self.backend,
                    found_by=self.found_by, roll_deg=number(self.roll_deg))


def sort_candidates(candidates) -> list[FaceCandidate]:
    """The candidates in the stated ORDER: largest first (FaceCandidate.size), ties by higher score."""
    def key(c):
        return (-c.size, -(c.score if math.isfinite(c.score) else -np.inf))
    return sorted(candidates, key=key)


def box_iou(a, b) -> float:
    """Intersection over union of two (x, y, w, h) boxes (0 when they do not overlap)."""
    inter = _intersection(a, b)
    union = a[2] * a[3] + b[2] * b[3] - inter
    return float(inter / union) if union > 0 else 0.0


def _intersection(a, b) -> float:
    w = min(a[0] + a[2], b[0] + b[2]) - max(a[0], b[0])
    h = min(a[1] + a[3], b[1] + b[3]) - max(a[1], b[1])
    return float(max(w, 0.0) * max(h, 0.0))


def suppress_overlaps(boxes: np.ndarray, scores: np.ndarray, max_iou: float) -> list[int]:
    """Non-maximum suppression: indices of the boxes kept, highest score first; a box is dropped
    when it overlaps a kept, higher-scoring one by IoU > max_iou. boxes (K, 4) (x, y, w, h)."""
    kept: list[int] = []
    for i in np.argsort(-np.asarray(scores), kind="stable"):
        if all(box_iou(boxes[i], boxes[k]) <= max_iou for k in kept):
            kept.append(int(i))
    return kept


def parse_face_box(text: str, option: str = "--face-box") -> np.ndarray:
    """"X,Y,W,H" (pixels, numbers) -> (4,) float64 box; InputError naming `option` otherwise."""
    try:
        values = [float(v) for v in str(text).split(",")]
    except ValueError:
        values = []
    if len(values) != 4 or not all(math.isfinite(v) for v in values) or min(values[2:]) <= 0:
        raise InputError(f"{option} {text!r}: expected X,Y,W,H in pixels (the box's top-left corner, "
                         "its width and height > 0), e.g. 100,50,80,80")
    return np.array(values, dtype=np.float64)


def check_box_on_image(box, image_shape, option: str = "--face-box") -> None:
    """InputError naming `option` when the (x, y, w, h) box does not overlap the (H, W, ...) image."""
    h, w = image_shape[:2]
    if _intersection(box, (0.0, 0.0, float(w), float(h))) <= 0:
        x, y, bw, bh = box
        raise InputError(f"{option} {x:g},{y:g},{bw:g},{bh:g} lies outside the {w}x{h} image")


#: a candidate is "in" the user's box when at least this fraction of its box lies inside it
MIN_INSIDE_FACE_BOX = 0.5


def choose_face(candidates, face: int | None = None, face_box=None) -> tuple[int | None, str]:
    """Which candidate to use, and why: (index into `candidates`, reason).

    candidates: FaceCandidate list in the stated ORDER (largest first, as find_faces returns).
    face: the N-th candidate (0 = the largest); InputError naming --face when there is none.
    face_box: (x, y, w, h): the candidate with the largest IoU among those with at least
        MIN_INSIDE_FACE_BOX of their box inside it; (None, reason) when no candidate is, and the
        caller then looks for landmarks in the box itself (detect_face does).
    Neither: the largest (index 0). face and face_box together are a ValueError.
    Raises NoFaceError when there are no candidates (and no face_box).
    """
    candidates = list(candidates)
    if face is not None and face_box is not None:
        raise InputError("--face and --face-box cannot be combined: give one")
    if face_box is not None:
        return _choose_in_box(candidates, np.asarray(face_box, dtype=np.float64))
    if not candidates:
        raise NoFaceError("no face found")
    if face is None:
        return 0, f"the largest of {len(candidates)} faces (the default; --face N or --face-box X,Y,W,H choose another)" \
            if len(candidates) > 1 else "the only face found"
    if int(face) != face or not 0 <= face < len(candidates):
        found = "1 face was found (face 0)" if len(candidates) == 1 else \
            f"{len(candidates)} faces were found, numbered 0-{len(candidates) - 1}, {ORDER}"
        raise InputError(f"--face {face}: only {found}")
    return int(face), f"--face {face}: number {face} of {len(candidates)}, {ORDER}"


def _choose_in_box(candidates, box) -> tuple[int | None, str]:
    inside = [(_intersection(c.box, box) / c.area if c.area > 0 else 0.0) for c in candidates]
    usable = [i for i, f in enumerate(inside) if f >= MIN_INSIDE_FACE_BOX]
    text = ",".join(f"{v:g}" for v in box)
    if not usable:
        return None, (f"--face-box {text}: no detected face lies in it (at least "
                      f"{MIN_INSIDE_FACE_BOX:.0%} of its box), so landmarks were sought in the box itself")
    best = max(usable, key=lambda i: box_iou(candidates[i].box, box))
    return best, (f"--face-box {text}: face {best} overlaps it best (IoU "
                  f"{box_iou(candidates[best].box, box):.2f})")


# ---------------------------------------------------------------------------------------------
# Is it a face?

def implausible_landmarks(points) -> str | None:
    """Why (68, 2) iBUG points do not form a plausible face, or None when they do: not 68 finite
    points, the two eyes' outer corners together (closer than 2 % of the face's extent), or a
    layout no face has (fitting.keypoints.plausibility.layout_faults, the check a fit makes of its
    landmarks: valid at any in-plane rotation, catches mirror-image and shuffled point orders)."""
    p = np.asarray(points, dtype=np.float64)
    if p.shape != (ibug68.COUNT, 2) or not np.isfinite(p).all():
        return f"the landmarks are not {ibug68.COUNT} finite points"
    extent = float(np.linalg.norm(p.max(0) - p.min(0)))
    right, left = ibug68.OUTER_EYE_CORNERS
    if extent <= 0 or np.linalg.norm(p[left] - p[right]) < 0.02 * extent:
        return "the two eyes' landmarks coincide"
    faults = layout_faults(p)
    return "; ".join(faults) + ": the points do not form a face" if faults else None


def check_plausible(candidate: FaceCandidate, index: int) -> None:
    """ImplausibleFaceError (exit 1) when the candidate has no landmarks or implausible ones."""
    if candidate.landmarks is None:
        raise ImplausibleFaceError(f"face {index} has no landmarks (the landmark stage found no face "
                                   "in its box); choose another with --face N or --face-box X,Y,W,H")
    why = implausible_landmarks(candidate.landmarks)
    if why is not None:
        raise ImplausibleFaceError(f"face {index}'s landmarks were refused: {why}; check them with "
                                   "detect-landmarks --overlay, or give the 68 points as a file")
