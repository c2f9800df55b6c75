"""68-point face landmarks for photos: files beside a photo, and optional detectors.

Two detector backends, each an optional extra; the core package needs neither, they are imported
only inside the functions that run them:

- ``dlib`` (the default when importable; extra ``landmarks``: ``dlib-bin`` +
  ``face-recognition-models``, installs beside numpy 2): dlib's HOG frontal-face detector, then
  dlib's 68-point shape predictor (an ensemble of regression trees trained on iBUG 300-W), so the
  points *are* iBUG 300-W points. The model file ``shape_predictor_68_face_landmarks.dat`` comes
  from the ``face_recognition_models`` wheel; that package's ``__init__`` needs ``pkg_resources``
  (gone from recent setuptools), so it is located with ``importlib.util.find_spec`` and never
  imported. Licence: dlib is Boost-licensed; the 68-point model is trained on iBUG 300-W, whose
  annotations are for research only, and its author was asked to say it cannot be used in a
  commercial product (docs/landmarks.md has the details). dlib returns whole pixels.
- ``mediapipe`` (extra ``landmarks-mediapipe``: mediapipe 0.10.21, which needs numpy<2, so a
  separate environment): MediaPipe Face Mesh (468 points, the model ships inside the wheel,
  Apache-2.0), and 68 of its vertices that stand for the iBUG points (``MP468_TO_IBUG68``, an
  approximation, see below). Later mediapipe releases install beside numpy 2 but ship no model
  (they load ``.task`` files at run time), so they are not used.

Every point array is (68, 2) float64 ``(x, y)``: x right, y down, 0-based pixel centres (the
top-left pixel's centre is (0, 0)), the convention of ``softras_cl.io.landmarks``.

``resolve_landmarks(photo, landmarks=None)`` is what a command calls: an explicit file, else a
file beside the photo (``landmarks_beside``), else the detector, else an error that says how to
install one.

This module imports nothing but numpy (and softras_cl.errors, when there) at load time, so it can
also be loaded by file path from an environment that has mediapipe but not the rest of
softras-cl (scripts/make_example_landmarks.py does so).

The MediaPipe 468 -> 68 table is an approximation: the Face Mesh is a dense surface mesh, not a
set of iBUG landmarks, so each iBUG point is the mesh vertex that best stands for it. How it was
made: vertex semantics from MediaPipe's published mesh topology (eye-lid, lip, brow and face-oval
vertex loops, e.g. 33/133 right-eye corners, 61/291 mouth corners, 152 chin, 4 nose tip), then
checked against dlib's 68-point predictor on the two example photos in examples/data: the mean
distance between the chosen vertices and dlib's points is 0.05 of the inter-ocular distance
(worst 0.15: outer brow end, jaw). Left/right pairs use mirror-image mesh vertices. Known
differences to hand-made iBUG annotations: the jaw points follow MediaPipe's face oval (its
upper part, points 0-1 and 15-16, lies towards the ears), the brows are the upper brow edge, and
on a closed mouth the inner-lip points 61-63 and 65-67 are near each other, as they are in iBUG.
"""
from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

try:
    from softras_cl.errors import InputError as _InputError
except ImportError:          # loaded by file path where softras-cl is not installed
    _InputError = ValueError

BACKENDS = ("dlib", "mediapipe")

INSTALL_HINT = ('68-point face landmark detection needs the optional "landmarks" extra (dlib and '
                "its iBUG 300-W 68-point model; installs beside numpy 2): "
                'pip install "softras-cl[landmarks]". The 68-point model is for non-commercial '
                "use only (docs/landmarks.md). Or give the 68 points as a file (.pts, .txt or "
                ".npy): --landmarks FILE, or PHOTO.pts beside the photo.")
MEDIAPIPE_INSTALL_HINT = ('the "mediapipe" backend needs the optional "landmarks-mediapipe" extra: '
                          'pip install "softras-cl[landmarks-mediapipe]". mediapipe 0.10.21 requires '
                          "numpy<2, so install it in a separate environment (e.g. python3.11 -m venv "
                          "lmkenv) rather than beside packages that need numpy 2.")
_HINTS = {"dlib": INSTALL_HINT, "mediapipe": MEDIAPIPE_INSTALL_HINT}

#: suffixes of landmark files looked for beside a photo, in order of precedence
BESIDE_SUFFIXES = (".pts", ".txt", ".npy")


class DetectorUnavailableError(_InputError, ImportError):
    """No landmark detector is installed (or the one asked for is missing); the message says
    exactly what to install. An ImportError and a ValueError (softras_cl.errors.InputError:
    the command line exits with code 2)."""


class NoFaceError(_InputError):
    """The detector found no face ("no face found in ..."). A ValueError (InputError)."""

# iBUG 300-W 68-point order (0-based). "right"/"left" are the subject's: the subject's right
# is the left of the image for a frontal photo.  index -> (MediaPipe Face Mesh vertex, name)
_TABLE = [
    # jaw 0-16, subject's right ear level -> chin (8) -> subject's left ear level (face oval)
    (127, "jaw, right, ear level"), (234, "jaw, right"), (132, "jaw, right"), (58, "jaw, right"),
    (172, "jaw, right angle"), (150, "jaw, right"), (149, "jaw, right"), (148, "jaw, right of chin"),
    (152, "chin"),
    (377, "jaw, left of chin"), (378, "jaw, left"), (379, "jaw, left"), (397, "jaw, left angle"),
    (288, "jaw, left"), (361, "jaw, left"), (454, "jaw, left"), (356, "jaw, left, ear level"),
    # brows 17-21 (right, outer -> inner), 22-26 (left, inner -> outer): upper brow edge
    (70, "right brow outer"), (63, "right brow"), (105, "right brow middle"), (66, "right brow"),
    (107, "right brow inner"),
    (336, "left brow inner"), (296, "left brow"), (334, "left brow middle"), (293, "left brow"),
    (300, "left brow outer"),
    # nose bridge 27-30 (top -> tip), nostrils 31-35 (right -> left)
    (168, "nose bridge top"), (197, "nose bridge"), (5, "nose bridge low"), (4, "nose tip"),
    (75, "right nostril outer"), (97, "right nostril"), (2, "below nose tip (subnasale)"),
    (326, "left nostril"), (305, "left nostril outer"),
    # right eye 36-41: outer corner, upper lid x2, inner corner, lower lid x2
    (33, "right eye outer corner"), (160, "right eye upper lid, outer"),
    (158, "right eye upper lid, inner"), (133, "right eye inner corner"),
    (153, "right eye lower lid, inner"), (144, "right eye lower lid, outer"),
    # left eye 42-47: inner corner, upper lid x2, outer corner, lower lid x2
    (362, "left eye inner corner"), (385, "left eye upper lid, inner"),
    (387, "left eye upper lid, outer"), (263, "left eye outer corner"),
    (373, "left eye lower lid, outer"), (380, "left eye lower lid, inner"),
    # outer lips 48-59: right corner, upper lip -> left corner (54), lower lip back
    (61, "mouth right corner"), (39, "upper lip, right"), (37, "upper lip, right peak"),
    (0, "upper lip top middle"), (267, "upper lip, left peak"), (269, "upper lip, left"),
    (291, "mouth left corner"), (405, "lower lip, left"), (314, "lower lip, left"),
    (17, "lower lip bottom middle"), (84, "lower lip, right"), (181, "lower lip, right"),
    # inner lips 60-67: right inner corner, upper inner -> left inner corner (64), lower inner back
    (78, "inner mouth right corner"), (82, "upper lip inner, right"), (13, "upper lip inner middle"),
    (312, "upper lip inner, left"), (308, "inner mouth left corner"), (317, "lower lip inner, left"),
    (14, "lower lip inner middle"), (87, "lower lip inner, right"),
]

#: MP468_TO_IBUG68[i] is the MediaPipe Face Mesh vertex used for iBUG point i.
MP468_TO_IBUG68 = np.array([v for v, _ in _TABLE], dtype=np.int64)
#: IBUG68_NAMES[i] describes iBUG point i (subject's left/right).
IBUG68_NAMES = tuple(n for _, n in _TABLE)




@dataclass(frozen=True)
class DetectedFace:
    """One face found by a detector.

    points: (68, 2) float64 iBUG 300-W points, x right, y down, 0-based pixel centres.
    box: (4,) float64 (x0, y0, x1, y1), the face box's first and last pixel column and row
        (0-based, inclusive): dlib's detection box; for MediaPipe the box around its 468 points.
    score: the detector's confidence (dlib: the HOG detector's SVM score, higher is surer;
        MediaPipe's Face Mesh gives none: NaN).
    backend: "dlib" or "mediapipe".
    """
    points: np.ndarray
    box: np.ndarray
    score: float
    backend: str

    @property
    def area(self) -> float:
        """Box area in pixels, (x1 - x0 + 1) * (y1 - y0 + 1): what "largest" means."""
        x0, y0, x1, y1 = self.box
        return float((x1 - x0 + 1.0) * (y1 - y0 + 1.0))


def _uint8_rgb(image) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got shape {img.shape} dtype {img.dtype}")
    return np.ascontiguousarray(img)


def read_photo_rgb8(path) -> np.ndarray:
    """A photo as the detectors take it: (H, W, 3) uint8 RGB, turned upright by its EXIF
    orientation (as softras_cl.io.images.read_image does, so points match the fitted image).
    Raises FileNotFoundError for a missing file, ValueError (naming it) for an unreadable one."""
    from PIL import Image, ImageOps

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image file not found: {path}")
    try:
        with Image.open(path) as img:
            img.load()
            return np.asarray(ImageOps.exif_transpose(img).convert("RGB"))
    except Exception as e:   # Pillow raises many kinds (OSError, SyntaxError, ...)
        raise ValueError(f"cannot read image {path}: {type(e).__name__}: {e}") from e


# ---------------------------------------------------------------------------------------------
# Backends

def dlib_model_path() -> Path | None:
    """Path of shape_predictor_68_face_landmarks.dat in the installed face_recognition_models
    package (found without importing it), or None when the package or the file is missing."""
    try:
        spec = importlib.util.find_spec("face_recognition_models")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    for folder in spec.submodule_search_locations:
        path = Path(folder) / "models" / "shape_predictor_68_face_landmarks.dat"
        if path.is_file():
            return path
    return None


def _importable(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def available_backends() -> list[str]:
    """The backends whose packages are installed, in order of preference ("dlib" first)."""
    found = []
    if _importable("dlib") and dlib_model_path() is not None:
        found.append("dlib")
    if _importable("mediapipe"):
        found.append("mediapipe")
    return found


def default_backend() -> str | None:
    """"dlib" when dlib and its 68-point model are installed, else "mediapipe" when mediapipe is,
    else None."""
    found = available_backends()
    return found[0] if found else None


def _check_backend(backend: str | None) -> str:
    """The backend to use; DetectorUnavailableError when it (or, for None, every one) is missing."""
    if backend is None:
        backend = default_backend()
        if backend is None:
            raise DetectorUnavailableError(INSTALL_HINT)
        return backend
    if backend not in BACKENDS:
        raise ValueError(f"unknown landmark backend {backend!r}; expected one of {', '.join(BACKENDS)}")
    if backend not in available_backends():
        raise DetectorUnavailableError(_HINTS[backend])
    return backend


@lru_cache(maxsize=2)
def _dlib_models(model_path: str):
    """(HOG face detector, 68-point shape predictor), loaded once per model file (about 0.6 s)."""
    import dlib

    return dlib.get_frontal_face_detector(), dlib.shape_predictor(model_path)


def _detect_dlib(img: np.ndarray, upsample: int, min_score: float) -> list[DetectedFace]:
    try:
        import dlib  # noqa: F401  (the import error is the one to report)
    except ImportError as e:
        raise DetectorUnavailableError(INSTALL_HINT) from e
    model = dlib_model_path()
    if model is None:
        raise DetectorUnavailableError(INSTALL_HINT)
    detector, predictor = _dlib_models(str(model))
    rects, scores, _ = detector.run(img, int(upsample), float(min_score))
    faces = []
    for rect, score in zip(rects, scores):
        shape = predictor(img, rect)
        points = np.array([[shape.part(i).x, shape.part(i).y] for i in range(shape.num_parts)],
                          dtype=np.float64)
        box = np.array([rect.left(), rect.top(), rect.right(), rect.bottom()], dtype=np.float64)
        faces.append(DetectedFace(points, box, float(score), "dlib"))
    return faces


def _mediapipe_meshes(img: np.ndarray, max_faces: int) -> list[np.ndarray]:
    """MediaPipe Face Mesh: one (468, 2) float64 array per face (x, y 0-based pixel centres),
    in MediaPipe's order."""
    try:
        from mediapipe.python.solutions import face_mesh
    except ImportError as e:
        raise DetectorUnavailableError(MEDIAPIPE_INSTALL_HINT) from e
    h, w = img.shape[:2]
    with face_mesh.FaceMesh(static_image_mode=True, max_num_faces=max_faces, refine_landmarks=False,
                            min_detection_confidence=0.5) as fm:
        result = fm.process(img)
    # MediaPipe's normalised coordinates span the image: 0 and 1 are the outer edges of the
    # first and last pixel, so pixel i's centre is at (i + 0.5) / W. Shift to 0-based centres.
    return [np.array([[p.x * w - 0.5, p.y * h - 0.5] for p in face.landmark], dtype=np.float64)
            for face in (result.multi_face_landmarks or [])]


def _detect_mediapipe(img: np.ndarray, max_faces: int) -> list[DetectedFace]:
    faces = []
    for xy in _mediapipe_meshes(img, max_faces):
        box = np.concatenate([xy.min(0), xy.max(0)])
        faces.append(DetectedFace(xy[MP468_TO_IBUG68].copy(), box, float("nan"), "mediapipe"))
    return faces


# ---------------------------------------------------------------------------------------------
# Detection

def detect_faces(image, backend: str | None = None, *, upsample: int = 1,
                 min_score: float = 0.5, max_faces: int = 20) -> list[DetectedFace]:
    """Every face in an (H, W, 3) uint8 RGB image, largest box first (ties: higher score first).

    backend: "dlib", "mediapipe" or None (dlib when installed, else mediapipe).
    upsample (dlib): how many times the image is doubled before the HOG detector runs; 1 finds
        faces down to about 40 px across (0: about 80 px) and takes about 3x the time.
    min_score (dlib): detections scoring below this are dropped. dlib's own threshold is 0; 0.5
        drops a false face (score 0.12) that upsample 1 finds in examples/data/astronaut.png,
        while the faces of the shipped photos, alone or pasted at 60 % size, score 1.1-1.6.
    max_faces (mediapipe): the most faces Face Mesh looks for.
    Returns [] when there is no face. Raises ValueError for a bad image or backend name and
    DetectorUnavailableError (an ImportError) when the backend is not installed.
    """
    img = _uint8_rgb(image)
    if int(upsample) != upsample or not 0 <= upsample <= 4:
        raise ValueError(f"upsample must be an integer 0-4, got {upsample}")
    backend = _check_backend(backend)
    if backend == "dlib":
        faces = _detect_dlib(img, upsample, min_score)
    else:
        faces = _detect_mediapipe(img, max_faces)
    scores = [(-np.inf if np.isnan(f.score) else f.score) for f in faces]
    order = sorted(range(len(faces)), key=lambda i: (-faces[i].area, -scores[i]))
    return [faces[i] for i in order]


def detect_landmarks(image, backend: str | None = None, *, name: str = "the image",
                     **options) -> np.ndarray:
    """The 68 iBUG 300-W points of the largest face in an (H, W, 3) uint8 RGB image.

    Returns (68, 2) float64: x right, y down, 0-based pixel centres. `options` go to
    detect_faces (upsample, min_score, max_faces). Raises NoFaceError (a ValueError,
    "no face found in <name> ...") when there is none, DetectorUnavailableError (an ImportError,
    with INSTALL_HINT) when no detector is installed.
    """
    faces = detect_faces(image, backend, **options)
    if not faces:
        raise no_face_error(name, backend, options)
    return faces[0].points.copy()


def no_face_error(name: str, backend: str | None = None, options: dict | None = None) -> NoFaceError:
    """The NoFaceError for `name` (a photo's path or "the image"): "no face found in <name>
    (<what was tried and what to do>)". backend and options as given to detect_faces."""
    options = options or {}
    used = backend or default_backend()
    if used == "dlib":
        how = (f"dlib HOG detector, upsample {options.get('upsample', 1)}, min score "
               f"{options.get('min_score', 0.5)}: a frontal, upright face at least about 40 px across; "
               "a lower min score or a higher upsample finds more, or give the 68 points as a file")
    else:
        how = "MediaPipe Face Mesh; or give the 68 points as a file"
    return NoFaceError(f"no face found in {name} ({how})")


# ---------------------------------------------------------------------------------------------
# Landmarks for a photo: a file, a file beside it, or the detector

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
    source: "file" (given explicitly), "beside" (found by landmarks_beside), "dlib" or
        "mediapipe" (detected).
    path: the file read, or None when detected.
    face: the DetectedFace (box, score) when detected, else None.
    """
    points: np.ndarray
    source: str
    path: Path | None = None
    face: DetectedFace | None = None


def resolve_landmarks(photo, landmarks=None, *, all_faces: bool = False, backend: str | None = None,
                      image=None, beside: bool = True, **options) -> list[PhotoLandmarks]:
    """The 68 landmarks of a photo: an explicit file > a file beside the photo > the detector.

    photo: the photo's path (also read, unless `image` is given, for its size and for detection).
    landmarks: an explicit landmark file (.pts 1-based, .txt/.npy 0-based), or None.
    all_faces: with a detector, every face, largest first; otherwise only the largest. A file
        holds one face, so then the list has one entry whatever `all_faces` says.
    backend: "dlib", "mediapipe" or None (the default backend); options go to detect_faces.
    image: the photo as (H, W, 3) uint8 RGB, upright (EXIF applied), if already read.
    beside: look for landmarks_beside(photo) (False: skip that step).

    Returns a non-empty list of PhotoLandmarks. Raises FileNotFoundError (missing photo or
    explicit file), ValueError naming the file (unreadable photo or landmark file, wrong point
    count, a point outside the photo), NoFaceError (a ValueError: the detector found no face),
    DetectorUnavailableError (an ImportError and ValueError: no file and no detector installed;
    its message is INSTALL_HINT, or the hint of the backend asked for).
    """
    from softras_cl.io.landmarks import read_landmarks

    photo = Path(photo)
    img = read_photo_rgb8(photo) if image is None else _uint8_rgb(image)
    size = img.shape[:2]
    if landmarks is not None:
        return [PhotoLandmarks(read_landmarks(landmarks, image_size=size), "file", Path(landmarks))]
    found = landmarks_beside(photo) if beside else None
    if found is not None:
        return [PhotoLandmarks(read_landmarks(found, image_size=size), "beside", found)]
    backend = _check_backend(backend)
    faces = detect_faces(img, backend, **options)
    if not faces:
        raise no_face_error(str(photo), backend, options)
    return [PhotoLandmarks(f.points.copy(), backend, None, f) for f in (faces if all_faces else faces[:1])]


def format_pts(points) -> str:
    """iBUG .pts text for (N, 2) 0-based pixel coordinates. The .pts convention is 1-based
    (the top-left pixel's centre is (1, 1)), so 1 is added to each coordinate. Same convention as
    softras_cl.io.landmarks.write_pts (which the CLI uses); this copy, with 3 decimals, needs
    only numpy, for scripts/make_example_landmarks.py's mediapipe-only environment."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or not np.isfinite(pts).all():
        raise ValueError(f"expected finite (N, 2) points, got shape {pts.shape}")
    lines = ["version: 1", f"n_points: {len(pts)}", "{"]
    lines += [f"{x + 1.0:.3f} {y + 1.0:.3f}" for x, y in pts]
    lines.append("}")
    return "\n".join(lines) + "\n"


def draw_landmarks(image, points, scale: float = 1.0, numbers: bool = True):
    """A PIL image: `image` ((H, W, 3) uint8 RGB) scaled by `scale` with the 68 points drawn,
    numbered and joined per part (jaw, brows, nose, eyes, lips) so the order can be checked.
    points: (68, 2) for one face or (K, 68, 2) for K faces, 0-based pixel coordinates."""
    from PIL import Image, ImageDraw

    img = Image.fromarray(_uint8_rgb(image))
    if scale != 1.0:
        img = img.resize((round(img.width * scale), round(img.height * scale)), Image.LANCZOS)
    d = ImageDraw.Draw(img)
    sets = np.asarray(points, dtype=np.float64)
    if sets.ndim == 2:
        sets = sets[None]
    if sets.ndim != 3 or sets.shape[1:] != (68, 2):
        raise ValueError(f"expected (68, 2) or (K, 68, 2) points, got shape {sets.shape}")
    parts = [(range(17), False, (255, 255, 0)), (range(17, 22), False, (255, 128, 0)),
             (range(22, 27), False, (255, 128, 0)), (range(27, 31), False, (0, 255, 255)),
             (range(31, 36), False, (0, 255, 255)), (range(36, 42), True, (0, 255, 0)),
             (range(42, 48), True, (0, 255, 0)), (range(48, 60), True, (255, 0, 255)),
             (range(60, 68), True, (255, 80, 80))]
    for face in sets:
        p = (face + 0.5) * scale  # pixel centres -> PIL's continuous coords
        for idx, closed, color in parts:
            seq = list(idx) + ([idx[0]] if closed else [])
            d.line([tuple(p[i]) for i in seq], fill=color, width=1)
        for i, (x, y) in enumerate(p):
            d.ellipse([x - 1.5, y - 1.5, x + 1.5, y + 1.5], fill=(255, 0, 0))
            if numbers:
                d.text((x + 2, y - 5), str(i), fill=(255, 255, 255), stroke_width=1, stroke_fill=(0, 0, 0))
    return img
