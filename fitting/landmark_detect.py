"""Optional 68-point face landmark detection (the `landmarks` extra).

`detect_landmarks(image)` runs MediaPipe's Face Mesh (468 points; the model ships inside the
`mediapipe` wheel, Apache-2.0, runs offline) and picks 68 of its vertices that stand for the
68 iBUG 300-W points (`MP468_TO_IBUG68`). Install with

    pip install "softras-cl[landmarks]"

mediapipe 0.10.21 needs numpy<2, so use a separate environment for it. The core package never
needs mediapipe: it is imported only inside `detect_landmarks`.

This module imports nothing but numpy at load time (and Pillow inside functions), and has no
relative imports at module level, so it can also be loaded by file path from an environment
that has mediapipe but not the rest of softras-cl (scripts/make_example_landmarks.py does so).

The 468 -> 68 table is an approximation: the Face Mesh is a dense surface mesh, not a set of
iBUG landmarks, so each iBUG point is the mesh vertex that best stands for it. How it was made:
vertex semantics from MediaPipe's published mesh topology (eye-lid, lip, brow and face-oval
vertex loops, e.g. 33/133 right-eye corners, 61/291 mouth corners, 152 chin, 4 nose tip), then
checked against dlib's 68-point predictor (an iBUG-trained model, used for this comparison only)
on the two example photos in examples/data: the mean distance between the chosen vertices and
dlib's points is 0.05 of the inter-ocular distance (worst 0.15: outer brow end, jaw). Left/right
pairs use mirror-image mesh vertices. Known differences to hand-made iBUG annotations:
the jaw points follow MediaPipe's face oval (its upper part, points 0-1 and 15-16, lies
towards the ears), the brows are the upper brow edge, and on a closed mouth the inner-lip
points 61-63 and 65-67 are near each other, as they are in iBUG.
"""
from __future__ import annotations

import numpy as np

INSTALL_HINT = ('face landmark detection needs the optional "landmarks" extra (MediaPipe Face Mesh): '
                'pip install "softras-cl[landmarks]". mediapipe 0.10.21 requires numpy<2, so install '
                'it in a separate environment (e.g. python3.11 -m venv lmkenv) rather than beside '
                'packages that need numpy 2.')

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


def _uint8_rgb(image) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got shape {img.shape} dtype {img.dtype}")
    return np.ascontiguousarray(img)


def detect_mesh468(image) -> np.ndarray:
    """MediaPipe Face Mesh on an (H, W, 3) uint8 RGB image: (468, 3) float64 for the largest-
    confidence face, x, y in pixels (0-based pixel centres, x right, y down), z in the same
    pixel scale (relative depth). Raises ImportError (with install hint) without mediapipe and
    ValueError when no face is found."""
    img = _uint8_rgb(image)
    try:
        from mediapipe.python.solutions import face_mesh
    except ImportError as e:
        raise ImportError(INSTALL_HINT) from e
    h, w = img.shape[:2]
    with face_mesh.FaceMesh(static_image_mode=True, max_num_faces=1, refine_landmarks=False,
                            min_detection_confidence=0.5) as fm:
        result = fm.process(img)
    if not result.multi_face_landmarks:
        raise ValueError("no face found in the image")
    lm = result.multi_face_landmarks[0].landmark
    # MediaPipe's normalised coordinates span the image: 0 and 1 are the outer edges of the
    # first and last pixel, so pixel i's centre is at (i + 0.5) / W. Shift to 0-based centres.
    return np.array([[p.x * w - 0.5, p.y * h - 0.5, p.z * w] for p in lm], dtype=np.float64)


def detect_landmarks(image) -> np.ndarray:
    """68 iBUG 300-W landmarks of the face in an (H, W, 3) uint8 RGB image.

    Returns (68, 2) float64 pixel coordinates: x right, y down, 0-based pixel centres (the top-left
    pixel's centre is (0, 0)). Needs the optional `landmarks` extra (see INSTALL_HINT); the 68
    points are MediaPipe Face Mesh vertices picked by `MP468_TO_IBUG68` (an approximation)."""
    return detect_mesh468(image)[MP468_TO_IBUG68, :2].copy()


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
    """A PIL image: `image` scaled by `scale` with the 68 points (0-based pixel coordinates) drawn,
    numbered and joined per part (jaw, brows, nose, eyes, lips) so the order can be checked."""
    from PIL import Image, ImageDraw

    img = Image.fromarray(_uint8_rgb(image))
    if scale != 1.0:
        img = img.resize((round(img.width * scale), round(img.height * scale)), Image.LANCZOS)
    d = ImageDraw.Draw(img)
    p = (np.asarray(points, dtype=np.float64) + 0.5) * scale  # pixel centres -> PIL's continuous coords
    parts = [(range(17), False, (255, 255, 0)), (range(17, 22), False, (255, 128, 0)),
             (range(22, 27), False, (255, 128, 0)), (range(27, 31), False, (0, 255, 255)),
             (range(31, 36), False, (0, 255, 255)), (range(36, 42), True, (0, 255, 0)),
             (range(42, 48), True, (0, 255, 0)), (range(48, 60), True, (255, 0, 255)),
             (range(60, 68), True, (255, 80, 80))]
    for idx, closed, color in parts:
        seq = list(idx) + ([idx[0]] if closed else [])
        d.line([tuple(p[i]) for i in seq], fill=color, width=1)
    for i, (x, y) in enumerate(p):
        d.ellipse([x - 1.5, y - 1.5, x + 1.5, y + 1.5], fill=(255, 0, 0))
        if numbers:
            d.text((x + 2, y - 5), str(i), fill=(255, 255, 255), stroke_width=1, stroke_fill=(0, 0, 0))
    return img
