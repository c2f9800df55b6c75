"""The dlib backend (opt-in: ``--backend dlib``, extra ``landmarks``; non-commercial model).

dlib's HOG frontal-face detector, then dlib's 68-point shape predictor (an ensemble of regression
trees trained on iBUG 300-W), so the points *are* iBUG 300-W points, in whole pixels. The model
file ``shape_predictor_68_face_landmarks.dat`` comes from the ``face_recognition_models`` wheel;
that package's ``__init__`` needs ``pkg_resources`` (gone from recent setuptools), so it is found
with ``importlib.util.find_spec`` and never imported. Licence: dlib is Boost-licensed; the
68-point model is trained on iBUG 300-W, whose annotations are for research only, and its author
was asked to say it cannot be used in a commercial product (docs/landmarks.md has the details).
It finds frontal, upright faces down to about 40 px (upsample 1).
"""
from __future__ import annotations

import importlib.util
from functools import lru_cache
from pathlib import Path

import numpy as np

from softras_cl.fitting.detection.faces import FaceCandidate, package_folders

INSTALL_HINT = ('the "dlib" face detector needs the optional "landmarks" extra (dlib and its iBUG 300-W '
                '68-point model; installs beside numpy 2): pip install "softras-cl[landmarks]". The '
                "68-point model is for non-commercial use only (docs/landmarks.md).")


def model_path() -> Path | None:
    """Path of shape_predictor_68_face_landmarks.dat in the installed face_recognition_models
    package (found without importing it), or None when the package or the file is missing."""
    for folder in package_folders("face_recognition_models"):
        path = folder / "models" / "shape_predictor_68_face_landmarks.dat"
        if path.is_file():
            return path
    return None


def available() -> bool:
    """dlib and its 68-point model are installed."""
    try:
        found = importlib.util.find_spec("dlib") is not None
    except (ImportError, ValueError):
        found = False
    return found and model_path() is not None


@lru_cache(maxsize=2)
def _models(path: str):
    """(HOG face detector, 68-point shape predictor), loaded once per model file (about 0.6 s)."""
    import dlib

    return dlib.get_frontal_face_detector(), dlib.shape_predictor(path)


def _candidate(predictor, image: np.ndarray, rect, score: float, found_by: str) -> FaceCandidate:
    shape = predictor(image, rect)
    points = np.array([[shape.part(i).x, shape.part(i).y] for i in range(shape.num_parts)], dtype=np.float64)
    box = np.array([rect.left(), rect.top(), rect.width(), rect.height()], dtype=np.float64)
    return FaceCandidate(box, float(score), points, None, "dlib", found_by)


#: find()'s options and their defaults
DEFAULTS = dict(upsample=1, min_score=0.5)


def find(image: np.ndarray, upsample: int = DEFAULTS["upsample"],
         min_score: float = DEFAULTS["min_score"]) -> list[FaceCandidate]:
    """Every face dlib finds in an (H, W, 3) uint8 RGB image, unordered.

    upsample: how many times the image is doubled before the HOG detector runs; 1 finds faces
        down to about 40 px across (0: about 80 px) and takes about 3x the time.
    min_score: detections scoring below this are dropped. dlib's own threshold is 0; 0.5 drops a
        false face (score 0.12) that upsample 1 finds in examples/data/astronaut.png, while the
        faces of the shipped photos, alone or pasted at 60 % size, score 1.1-1.6.
    """
    if int(upsample) != upsample or not 0 <= upsample <= 4:
        raise ValueError(f"upsample must be an integer 0-4, got {upsample}")
    detector, predictor = _models(str(model_path()))
    rects, scores, _ = detector.run(image, int(upsample), float(min_score))
    how = f"HOG detector, upsample {upsample}"
    return [_candidate(predictor, image, r, s, how) for r, s in zip(rects, scores)]


def find_in_box(image: np.ndarray, box) -> FaceCandidate:
    """The 68-point predictor on a given (x, y, w, h) box (dlib always returns 68 points)."""
    import dlib

    _, predictor = _models(str(model_path()))
    x, y, w, h = (round(v) for v in box)
    rect = dlib.rectangle(x, y, x + w - 1, y + h - 1)
    return _candidate(predictor, image, rect, float("nan"), "68-point predictor on the given box")
