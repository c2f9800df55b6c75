"""Find the faces of an image with a backend, and choose one, saying which and why.

find_faces(image, backend) lists every face (FaceCandidate), largest first; detect_face adds
the choice (choose_face: the largest, --face N or --face-box) and refuses a chosen face whose
landmarks do not form a face. Backends: "mediapipe" (the default; mediapipe_backend.py) and
"dlib" (opt-in; dlib_backend.py). Nothing runs the dlib model unless "dlib" is asked for.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from softras_cl.errors import InputError
from softras_cl.fitting.detection import dlib_backend, mediapipe_backend
from softras_cl.fitting.detection.faces import (ORDER, DetectorUnavailableError, FaceCandidate, NoFaceError,
                                                check_box_on_image, check_plausible, choose_face,
                                                implausible_landmarks,
                                                sort_candidates)

BACKENDS = ("mediapipe", "dlib")
DEFAULT_BACKEND = "mediapipe"
#: backends whose 68 landmarks are Face Mesh points (fitting.keypoints.face_mesh), not iBUG annotations
FACE_MESH_BACKENDS = ("mediapipe",)
_MODULES = {"mediapipe": mediapipe_backend, "dlib": dlib_backend}
#: photos whose longer side is over this many px are searched on a copy reduced to it (faces by
#: find_faces, people by people.detect_person), the results scaled back to the photo's pixels:
#: the models see 128-256 px crops anyway, and an 8000 x 6000 photo took about two minutes and
#: 3 GB searched at full size (docs/reliability.md)
DETECT_MAX_SIDE = 2048
#: the options each backend's find() takes
OPTIONS = {"mediapipe": ("tiles",), "dlib": tuple(dlib_backend.DEFAULTS)}


def available_backends() -> list[str]:
    """The backends whose packages are installed, the default first."""
    return [b for b in BACKENDS if _MODULES[b].available()]


def default_backend() -> str | None:
    """"mediapipe" when it is installed, else None (dlib is never chosen by default)."""
    return DEFAULT_BACKEND if mediapipe_backend.available() else None


def check_backend(backend: str | None) -> str:
    """The backend to use (None: the default); DetectorUnavailableError, with the install hint,
    when it is not installed; ValueError for an unknown name."""
    backend = DEFAULT_BACKEND if backend is None else backend
    if backend not in BACKENDS:
        raise InputError(f"unknown face detector backend {backend!r}; expected one of {', '.join(BACKENDS)}")
    if not _MODULES[backend].available():
        raise DetectorUnavailableError(_MODULES[backend].INSTALL_HINT)
    return backend


def as_rgb8(image) -> np.ndarray:
    """The image as a C-contiguous (H, W, 3) uint8 array; ValueError otherwise."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got shape {img.shape} dtype {img.dtype}")
    return np.ascontiguousarray(img)


def reduced_copy(image: np.ndarray, max_side: int = DETECT_MAX_SIDE) -> tuple[np.ndarray, float]:
    """(the (H, W, 3) uint8 image reduced so that its longer side is ``max_side`` (area-averaged),
    the factor from its pixels to the image's (> 1)); the image itself and 1.0 when it is no
    larger."""
    from PIL import Image

    h, w = image.shape[:2]
    if max(h, w) <= max_side:
        return image, 1.0
    scale = max_side / max(h, w)
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    small = np.asarray(Image.fromarray(image).resize(size, Image.BOX))
    return np.ascontiguousarray(small), w / size[0]


def _scaled(candidate: FaceCandidate, factor: float, note: str) -> FaceCandidate:
    """A face found on a reduced copy in the photo's pixels: the box (on the pixel grid) times
    ``factor``, pixel centres p as (p + 0.5) * factor - 0.5."""
    def points(p):
        return None if p is None else (p + 0.5) * factor - 0.5

    return replace(candidate, box=candidate.box * factor, landmarks=points(candidate.landmarks),
                   dense=points(candidate.dense), found_by=candidate.found_by + note)


def find_faces(image, backend: str | None = None, **options) -> list[FaceCandidate]:
    """Every face in an (H, W, 3) uint8 RGB image, in the stated ORDER (largest first).

    backend: "mediapipe" (None: the default) or "dlib".
    options, mediapipe: tiles (True: the tile pyramid for small faces); dlib: upsample and
        min_score (dlib_backend.DEFAULTS; mediapipe_backend / dlib_backend have the details).
    An image over DETECT_MAX_SIDE px is searched on a reduced copy (reduced_copy), the faces given
    in its own pixels. Returns [] when there is no face. Raises ValueError for a bad image, backend or option and
    DetectorUnavailableError (an ImportError) when the backend is not installed.
    """
    img = as_rgb8(image)
    backend = check_backend(backend)
    unknown = set(options) - set(OPTIONS[backend])
    if unknown:
        raise ValueError(f"the {backend} backend takes the options {', '.join(OPTIONS[backend])}, "
                         f"not {', '.join(sorted(unknown))}")
    small, factor = reduced_copy(img)
    found = _MODULES[backend].find(small, **options)
    if factor != 1.0:
        note = f", on a copy reduced to {small.shape[1]} x {small.shape[0]} px"
        found = [_scaled(c, factor, note) for c in found]
    return sort_candidates(found)


#: backends whose landmark stage can follow a face from its last landmarks alone
_NEAR = {"mediapipe": mediapipe_backend.mesh_near}


def face_near(image, landmarks, backend: str | None = None) -> np.ndarray | None:
    """(68, 2) landmarks of the face that had ``landmarks`` (68, 2) a moment ago (a video's last
    frame), found in an (H, W, 3) uint8 RGB image by the backend's landmark stage alone, on a
    crop around them (mediapipe: mediapipe_backend.mesh_near); None when the backend has no such
    stage (dlib), finds no face there, or finds one whose landmarks do not form a face
    (check_plausible's test). A follower then searches as for a new face."""
    img = as_rgb8(image)
    near = _NEAR.get(check_backend(backend))
    if near is None:
        return None
    candidate = near(img, np.asarray(landmarks, np.float64))
    if candidate is None or implausible_landmarks(candidate.landmarks) is not None:
        return None
    return candidate.landmarks


@dataclass(frozen=True)
class Detection:
    """The faces of an image and the one chosen.

    candidates: every FaceCandidate in the stated ORDER, plus, last, the face found in
        --face-box itself when no candidate lay in that box.
    index: which candidate was chosen; reason: the rule that chose it, for people.
    backend: the backend that found them.
    """
    candidates: tuple[FaceCandidate, ...]
    index: int
    reason: str
    backend: str

    @property
    def chosen(self) -> FaceCandidate:
        return self.candidates[self.index]

    def describe(self, written=None) -> list[str]:
        """Lines for people: how many faces, then one per candidate, the chosen one marked "*"
        and followed by why (written: the numbers to mark instead, e.g. every face written)."""
        marked = [self.index] if written is None else list(written)
        count = len(self.candidates)
        lines = [f"{count} face{'s' if count != 1 else ''} found by {self.backend}, numbered {ORDER}:"]
        for i, c in enumerate(self.candidates):
            x, y, w, h = c.box
            why = f"; chosen: {self.reason}" if written is None and i == self.index else ""
            score = f"score {c.score:.2f}" if math.isfinite(c.score) else "no score"
            lines.append(f"{'*' if i in marked else ' '} face {i}: box {x:.0f},{y:.0f},{w:.0f},{h:.0f} "
                         f"(x,y,w,h), {score}, {c.found_by}{why}")
        return lines

    def to_json(self) -> dict:
        """JSON-ready: backend, order, chosen (index), reason and every candidate's to_json()."""
        return dict(backend=self.backend, order=ORDER, chosen=self.index, reason=self.reason,
                    candidates=[dict(index=i, **c.to_json()) for i, c in enumerate(self.candidates)])


def detect_face(image, backend: str | None = None, *, face: int | None = None, face_box=None,
                name: str = "the image", **options) -> Detection:
    """Find the faces of an (H, W, 3) uint8 RGB image and choose one (choose_face): the largest,
    the `face`-th, or the one in `face_box` (x, y, w, h; when no detected face lies in it, the
    backend looks for landmarks in the box itself). options go to find_faces.

    Raises NoFaceError ("no face found in <name> (...)", exit 2), InputError for a --face number
    that was not found or a box off the image, ImplausibleFaceError (exit 1) when the chosen
    face's landmarks do not form a face, DetectorUnavailableError when the backend is missing.
    """
    img = as_rgb8(image)
    backend = check_backend(backend)
    if face_box is not None:
        face_box = np.asarray(face_box, dtype=np.float64)
        check_box_on_image(face_box, img.shape)
    candidates = find_faces(img, backend, **options)
    if not candidates and face_box is None:
        raise no_face_error(name, backend)
    index, reason = choose_face(candidates, face, face_box)
    if index is None:
        in_box = _MODULES[backend].find_in_box(img, face_box)
        if in_box is None:
            raise NoFaceError(f"no face found in {name} inside {reason.split(':')[0]}: the detector found "
                              "none there, nor did the landmark stage on the box itself")
        candidates, index = candidates + [in_box], len(candidates)
    check_plausible(candidates[index], index)
    return Detection(tuple(candidates), index, reason, backend)


def no_face_error(name: str, backend: str | None = None) -> NoFaceError:
    """The NoFaceError for `name` (a photo's path or "the image"), saying what was tried."""
    if (backend or DEFAULT_BACKEND) == "dlib":
        how = ("dlib HOG detector: a frontal, upright face at least about 40 px across; a lower "
               "--min-score or a higher --upsample finds more")
    else:
        how = ("MediaPipe short- and full-range detectors, on the whole image and on tiles down to "
               f"{mediapipe_backend.MIN_TILE} px: faces from about 32 px, at any in-plane rotation")
    return NoFaceError(f"no face found in {name} ({how}); give --face-box X,Y,W,H around it, or the "
                       "68 points as a file")
