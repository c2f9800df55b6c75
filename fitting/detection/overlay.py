"""Pictures to check detections by eye: the 68 points numbered and joined, every face's box."""
from __future__ import annotations

import numpy as np

from softras_cl.fitting.detection.find import Detection, as_rgb8
from softras_cl.fitting.keypoints import ibug68

#: iBUG 68 parts: (indices, closed loop, colour)
PARTS = [(ibug68.JAW, False, (255, 255, 0)), (ibug68.RIGHT_BROW, False, (255, 128, 0)),
         (ibug68.LEFT_BROW, False, (255, 128, 0)), (ibug68.NOSE_BRIDGE, False, (0, 255, 255)),
         (ibug68.NOSTRILS, False, (0, 255, 255)), (ibug68.RIGHT_EYE, True, (0, 255, 0)),
         (ibug68.LEFT_EYE, True, (0, 255, 0)), (ibug68.OUTER_LIPS, True, (255, 0, 255)),
         (ibug68.INNER_LIPS, True, (255, 80, 80))]
CHOSEN_COLOUR, OTHER_COLOUR = (0, 255, 0), (255, 64, 64)


def _scaled(image, scale: float):
    from PIL import Image

    img = Image.fromarray(as_rgb8(image))
    if scale != 1.0:
        img = img.resize((round(img.width * scale), round(img.height * scale)), Image.LANCZOS)
    return img


def _draw_points(draw, face: np.ndarray, scale: float, numbers: bool) -> None:
    p = (face + 0.5) * scale  # pixel centres -> PIL's continuous coords
    for idx, closed, color in PARTS:
        seq = list(idx) + ([idx[0]] if closed else [])
        draw.line([tuple(p[i]) for i in seq], fill=color, width=1)
    for i, (x, y) in enumerate(p):
        draw.ellipse([x - 1.5, y - 1.5, x + 1.5, y + 1.5], fill=(255, 0, 0))
        if numbers:
            draw.text((x + 2, y - 5), str(i), fill=(255, 255, 255), stroke_width=1, stroke_fill=(0, 0, 0))


def draw_landmarks(image, points, scale: float = 1.0, numbers: bool = True):
    """A PIL image: `image` ((H, W, 3) uint8 RGB) scaled by `scale` with the 68 points drawn,
    numbered and joined per part (jaw, brows, nose, eyes, lips) so the order can be checked.
    points: (68, 2) for one face or (K, 68, 2) for K faces, 0-based pixel coordinates."""
    from PIL import ImageDraw

    sets = np.asarray(points, dtype=np.float64)
    if sets.ndim == 2:
        sets = sets[None]
    if sets.ndim != 3 or sets.shape[1:] != (ibug68.COUNT, 2):
        raise ValueError(f"expected ({ibug68.COUNT}, 2) or (K, {ibug68.COUNT}, 2) points, got shape {sets.shape}")
    img = _scaled(image, scale)
    draw = ImageDraw.Draw(img)
    for face in sets:
        _draw_points(draw, face, scale, numbers)
    return img


def draw_detection(image, detection: Detection, scale: float = 1.0, all_landmarks: bool = False):
    """A PIL image: every candidate's box with its number (the chosen one green, the others red)
    and the chosen face's 68 points (every face's with all_landmarks), to choose a face by."""
    from PIL import ImageDraw

    img = _scaled(image, scale)
    draw = ImageDraw.Draw(img)
    for i, face in enumerate(detection.candidates):
        colour = CHOSEN_COLOUR if i == detection.index else OTHER_COLOUR
        x, y, w, h = face.box * scale
        draw.rectangle([x, y, x + w, y + h], outline=colour, width=2)
        draw.text((x + 3, y + 2), str(i), fill=colour, stroke_width=2, stroke_fill=(0, 0, 0))
        if face.landmarks is not None and (all_landmarks or i == detection.index):
            _draw_points(draw, face.landmarks, scale, numbers=False)
    return img
