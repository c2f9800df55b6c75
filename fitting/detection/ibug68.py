"""The iBUG 300-W 68-point order and the MediaPipe Face Mesh vertex that stands for each point.

The table is an approximation: the Face Mesh is a dense surface mesh, not a
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

import numpy as np

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
