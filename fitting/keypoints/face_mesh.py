"""MediaPipe Face Mesh's dense points, and the mesh vertex that stands for each iBUG 300-W point.

Face Mesh gives COUNT surface points, then (with refine_landmarks) IRIS_COUNT iris points:
WITH_IRISES in all, in MediaPipe's published order.

:data:`MP468_TO_IBUG68` is an approximation: the Face Mesh is a dense surface mesh, not a set of
iBUG landmarks, so each iBUG point is the mesh vertex that best stands for it. How it was made:
vertex semantics from MediaPipe's published mesh topology (eye-lid, lip, brow and face-oval vertex
loops, e.g. 33/133 right-eye corners, 61/291 mouth corners, 152 chin, 4 nose tip), then checked
against dlib's 68-point predictor on the two example photos in examples/data: the mean distance
between the chosen vertices and dlib's points is 0.05 of the inter-ocular distance (worst 0.15:
outer brow end, jaw). Left/right pairs use mirror-image mesh vertices. Known differences to
hand-made iBUG annotations: the jaw points follow MediaPipe's face oval (its upper part, points
0-1 and 15-16, lies towards the ears), the brows are the upper brow edge, and on a closed mouth
the inner-lip points 61-63 and 65-67 are near each other, as they are in iBUG. The points' names
are ibug68.NAMES.
"""
from __future__ import annotations

import numpy as np

__all__ = ["COUNT", "IRIS_COUNT", "WITH_IRISES", "MP468_TO_IBUG68"]

COUNT = 468             # the surface points
IRIS_COUNT = 10         # 5 per eye, after the surface points
WITH_IRISES = COUNT + IRIS_COUNT

#: MP468_TO_IBUG68[i] (68,) int64 is the Face Mesh vertex used for iBUG point i
MP468_TO_IBUG68 = np.array([
    # jaw 0-16 (face oval): right ear level -> chin (152) -> left ear level
    127, 234, 132, 58, 172, 150, 149, 148, 152, 377, 378, 379, 397, 288, 361, 454, 356,
    # brows 17-21 (right, outer -> inner), 22-26 (left, inner -> outer): upper brow edge
    70, 63, 105, 66, 107, 336, 296, 334, 293, 300,
    # nose bridge 27-30 (top -> tip), nostrils 31-35 (right -> left)
    168, 197, 5, 4, 75, 97, 2, 326, 305,
    # right eye 36-41, left eye 42-47
    33, 160, 158, 133, 153, 144, 362, 385, 387, 263, 373, 380,
    # outer lips 48-59, inner lips 60-67
    61, 39, 37, 0, 267, 269, 291, 405, 314, 17, 84, 181, 78, 82, 13, 312, 308, 317, 14, 87,
], dtype=np.int64)
