"""The iBUG 300-W 68-point face landmarks: their order, the parts they make up, their names.

Indices are 0-based. "Right" and "left" are the subject's own sides: the subject's right is the
left of the image for a frontal photo. Each part is a ``range`` of indices (``points[JAW]`` is
the (17, 2) jaw line of points (68, 2)); the eyes and lips are closed loops, the others open lines.
"""
from __future__ import annotations

__all__ = ["COUNT", "JAW", "RIGHT_BROW", "LEFT_BROW", "BROWS", "NOSE_BRIDGE", "NOSTRILS", "RIGHT_EYE",
           "LEFT_EYE", "OUTER_LIPS", "INNER_LIPS", "MOUTH", "CHIN", "NOSE_BRIDGE_TOP", "NOSE_TIP",
           "OUTER_EYE_CORNERS", "FACE_OUTLINE", "OPENINGS", "NAMES"]

COUNT = 68

JAW = range(0, 17)              # the subject's right ear level -> chin (8) -> left ear level
RIGHT_BROW = range(17, 22)      # outer -> inner
LEFT_BROW = range(22, 27)       # inner -> outer
BROWS = range(17, 27)
NOSE_BRIDGE = range(27, 31)     # top -> tip
NOSTRILS = range(31, 36)        # right -> left
RIGHT_EYE = range(36, 42)       # outer corner, upper lid x2, inner corner, lower lid x2
LEFT_EYE = range(42, 48)        # inner corner, upper lid x2, outer corner, lower lid x2
OUTER_LIPS = range(48, 60)      # right corner, upper lip -> left corner (54), lower lip back
INNER_LIPS = range(60, 68)      # right inner corner, upper -> left inner corner (64), lower back
MOUTH = range(48, 68)

CHIN = 8
NOSE_BRIDGE_TOP = 27
NOSE_TIP = 30
#: (right eye's outer corner, left eye's outer corner): the eye line, and the usual face size
OUTER_EYE_CORNERS = (36, 45)

#: the face's outline: the jaw line, then the brows back from the left to the right
FACE_OUTLINE = tuple(JAW) + tuple(reversed(BROWS))
#: what skin does not cover inside the outline: the eyes and the inside of the mouth
OPENINGS = (RIGHT_EYE, LEFT_EYE, INNER_LIPS)

#: NAMES[i] describes point i
NAMES = (
    # jaw 0-16
    "jaw, right, ear level", "jaw, right", "jaw, right", "jaw, right", "jaw, right angle", "jaw, right",
    "jaw, right", "jaw, right of chin", "chin", "jaw, left of chin", "jaw, left", "jaw, left",
    "jaw, left angle", "jaw, left", "jaw, left", "jaw, left", "jaw, left, ear level",
    # brows 17-21, 22-26
    "right brow outer", "right brow", "right brow middle", "right brow", "right brow inner",
    "left brow inner", "left brow", "left brow middle", "left brow", "left brow outer",
    # nose bridge 27-30, nostrils 31-35
    "nose bridge top", "nose bridge", "nose bridge low", "nose tip",
    "right nostril outer", "right nostril", "below nose tip (subnasale)", "left nostril", "left nostril outer",
    # right eye 36-41
    "right eye outer corner", "right eye upper lid, outer", "right eye upper lid, inner",
    "right eye inner corner", "right eye lower lid, inner", "right eye lower lid, outer",
    # left eye 42-47
    "left eye inner corner", "left eye upper lid, inner", "left eye upper lid, outer",
    "left eye outer corner", "left eye lower lid, outer", "left eye lower lid, inner",
    # outer lips 48-59
    "mouth right corner", "upper lip, right", "upper lip, right peak", "upper lip top middle",
    "upper lip, left peak", "upper lip, left", "mouth left corner", "lower lip, left", "lower lip, left",
    "lower lip bottom middle", "lower lip, right", "lower lip, right",
    # inner lips 60-67
    "inner mouth right corner", "upper lip inner, right", "upper lip inner middle", "upper lip inner, left",
    "inner mouth left corner", "lower lip inner, left", "lower lip inner middle", "lower lip inner, right",
)
