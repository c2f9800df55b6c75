"""A photo's 68 landmarks: the user's file, a file beside the photo, or a detector.

resolve_landmarks(photo, landmarks=None) is what a command calls: an explicit file, else a file
beside the photo (landmarks_beside), else the detector (find.detect_face: the largest face, or
the one --face / --face-box names), else an error that says how to install one.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softras_cl.errors import InputError
from softras_cl.io.images import read_rgb8
from softras_cl.fitting.detection.faces import FaceCandidate, ImplausibleFaceError, implausible_landmarks
from softras_cl.fitting.detection.find import (FACE_MESH_BACKENDS, Detection, as_rgb8, check_backend, detect_face, find_faces,
                                               no_face_error)

#: suffixes of landmark files looked for beside a photo, in order of precedence
BESIDE_SUFFIXES = (".pts", ".txt", ".npy")
#: a file beside the photo must overlap a detected face this much (check_beside)
MIN_BESIDE_IOU = 0.25


def landmarks_beside(photo) -> Path | None:
    """The landmark file beside a photo, or None.

    Looks in the photo's folder, in this order (the first that is a file wins): the photo's name
    with its suffix replaced by .pts, .txt, .npy (``face.png`` -> ``face.pts``, ``face.txt``,
    ``face.npy``), then the whole name with .pts, .txt, .npy appended (``face.png.pts``, ...).
    The format is read from the content (softras_cl.io.landmarks.read_landmarks).
    """
    photo = Path(photo)
    names = [photo.with_suffix(s) for s in BESIDE_SUFFIXES] if photo.suffix else []
    names += [photo.with_name(photo.name + s) for s in BESIDE_SUFFIXES]
    for path in names:
        if path != photo and path.is_file():
            return path
    return None


@dataclass(frozen=True)
class PhotoLandmarks:
    """The 68 points of one face of a photo, and where they came from.

    points: (68, 2) float64, x right, y down, 0-based pixel centres.
    source: "file" (given explicitly), "beside" (found by landmarks_beside), "mediapipe" or
        "dlib" (detected).
    path: the file read, or None when detected.
    face: the FaceCandidate (box, score, dense points, how it was found) when detected.
    detection: when detected, every face found, which one this is (detection.index) and why.
    """
    points: np.ndarray
    source: str
    path: Path | None = None
    face: FaceCandidate | None = None
    detection: Detection | None = None

    @property
    def on_face_mesh(self) -> bool:
        """Whether the points are Face Mesh's (a FACE_MESH_BACKENDS detector found them), not an
        annotator's iBUG points (a file, dlib): fit_face ties them to the model accordingly."""
        return self.source in FACE_MESH_BACKENDS

    @property
    def index(self) -> int | None:
        """The face's number among the detected faces (None for a file)."""
        return None if self.detection is None else self.detection.index


def resolve_landmarks(photo, landmarks=None, *, all_faces: bool = False, backend: str | None = None,
                      image=None, beside: bool = True, face: int | None = None, face_box=None,
                      **options) -> list[PhotoLandmarks]:
    """The 68 landmarks of a photo: an explicit file > a file beside the photo > the detector.

    photo: the photo's path (also read, unless `image` is given, for its size and for detection).
    landmarks: an explicit landmark file (.pts 1-based, .txt/.npy 0-based), or None.
    all_faces: with a detector, every face whose landmarks form a face, in the stated order
        (each PhotoLandmarks' index is its number; refused ones are left out but stay in its
        detection); otherwise one face, chosen by `face` / `face_box` (detect_face). A file
        holds one face, so then the list has one entry whatever these say.
    backend: "mediapipe" (None: the default) or "dlib"; options go to find_faces.
    image: the photo as (H, W, 3) uint8 RGB, upright (EXIF applied), if already read.
    beside: look for landmarks_beside(photo) (False: skip that step).

    Returns a non-empty list of PhotoLandmarks. Raises FileNotFoundError (missing photo or
    explicit file), ValueError naming the file (unreadable photo or landmark file, wrong point
    count, a point outside the photo), NoFaceError (no face found), InputError (--face number
    not found), ImplausibleFaceError (exit 1), DetectorUnavailableError (an ImportError and
    InputError: no file and the detector is not installed; its message says what to install).
    """
    from softras_cl.io.landmarks import read_landmarks

    photo = Path(photo)
    img = read_rgb8(photo) if image is None else as_rgb8(image)
    size = img.shape[:2]
    if landmarks is not None:
        return [PhotoLandmarks(read_landmarks(landmarks, image_size=size), "file", Path(landmarks))]
    found = landmarks_beside(photo) if beside else None
    if found is not None:
        return [PhotoLandmarks(read_landmarks(found, image_size=size), "beside", found)]
    if all_faces:
        return _every_face(img, str(photo), check_backend(backend), options)
    detection = detect_face(img, backend, face=face, face_box=face_box, name=str(photo), **options)
    return [_detected(detection)]


def check_beside(path: Path, points: np.ndarray, img: np.ndarray, name: str) -> None:
    """Check the landmark file beside a photo against the faces the default detector finds in
    it (when it is installed; fit-face's jobs call it, resolve_landmarks does not): InputError
    naming the file when faces are found and none of their
    boxes overlaps the box of the file's (68, 2) points by an IoU of at least MIN_BESIDE_IOU, as
    when the file is another photo's (the astronaut with Grace Hopper's points: IoU 0.04; its own
    points: 0.80). A file beside the photo is taken without being asked for, so a wrong one would
    otherwise fit another face's points without a word. No face found, or no detector: the file
    is used as it is."""
    from softras_cl.fitting.detection.find import default_backend

    backend = default_backend()
    if backend is None:
        return
    faces = find_faces(img, backend)
    if not faces:
        return
    box = np.concatenate([points.min(0), points.max(0) - points.min(0)])
    overlaps = [box_iou(box, face.box) for face in faces]
    best = int(np.argmax(overlaps))
    if overlaps[best] >= MIN_BESIDE_IOU:
        return
    x, y, w, h = faces[best].box
    raise InputError(
        f"the landmark file beside the photo, {path}, does not overlap the face the detector finds in "
        f"{name} (its points span x {box[0]:.0f}-{box[0] + box[2]:.0f}, y {box[1]:.0f}-{box[1] + box[3]:.0f}; "
        f"of the {len(faces)} face(s) found, face {best} at box {x:.0f},{y:.0f},{w:.0f},{h:.0f} overlaps them "
        f"best, IoU {overlaps[best]:.2f} < {MIN_BESIDE_IOU}): is it another photo's? Give the right file "
        "with --landmarks FILE, or move it away to use the detector")


def box_iou(a, b) -> float:
    """IoU of two (x, y, w, h) boxes."""
    ax0, ay0, aw, ah = (float(v) for v in a)
    bx0, by0, bw, bh = (float(v) for v in b)
    iw = max(0.0, min(ax0 + aw, bx0 + bw) - max(ax0, bx0))
    ih = max(0.0, min(ay0 + ah, by0 + bh) - max(ay0, by0))
    inter = iw * ih
    union = aw * ah + bw * bh - inter
    return inter / union if union > 0 else 0.0


def _detected(detection: Detection) -> PhotoLandmarks:
    chosen = detection.chosen
    return PhotoLandmarks(chosen.landmarks.copy(), detection.backend, None, chosen, detection)


def _every_face(img: np.ndarray, name: str, backend: str, options: dict) -> list[PhotoLandmarks]:
    candidates = tuple(find_faces(img, backend, **options))
    if not candidates:
        raise no_face_error(name, backend)
    usable = [i for i, c in enumerate(candidates)
              if c.landmarks is not None and implausible_landmarks(c.landmarks) is None]
    if not usable:
        raise ImplausibleFaceError(f"none of the {len(candidates)} face(s) found in {name} has landmarks "
                                   "that form a face; give the 68 points as a file")
    return [_detected(Detection(candidates, i, f"--all-faces: face {i}", backend)) for i in usable]


def format_pts(points) -> str:
    """iBUG .pts text for (N, 2) 0-based pixel coordinates, 3 decimals. The .pts convention is
    1-based (the top-left pixel's centre is (1, 1)), so 1 is added to each coordinate; the
    shipped examples/data/landmarks/*.pts are written with it."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or not np.isfinite(pts).all():
        raise ValueError(f"expected finite (N, 2) points, got shape {pts.shape}")
    lines = ["version: 1", f"n_points: {len(pts)}", "{"]
    lines += [f"{x + 1.0:.3f} {y + 1.0:.3f}" for x, y in pts]
    lines.append("}")
    return "\n".join(lines) + "\n"
