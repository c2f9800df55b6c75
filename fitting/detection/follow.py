"""A face followed from frame to frame of a video: :class:`FaceFollower` finds the followed
face's 68 landmarks in each frame, searching near where the last frame's fit put them."""
from __future__ import annotations

import numpy as np

from softras_cl.fitting.detection.faces import ImplausibleFaceError, NoFaceError
from softras_cl.fitting.detection.find import detect_face, face_near
from softras_cl.fitting.keypoints import ibug68

__all__ = ["FaceFollower"]


class FaceFollower:
    """The 68 landmarks of the followed face in each frame (fitting.detection).

    The first frame with a face: detect_face on the whole frame, choosing by ``face`` (the N-th,
    largest first) or ``face_box`` (x, y, w, h), else the largest. Then, given the previous
    frame's fitted landmarks (:meth:`find`'s ``previous``), the face is looked for around them:
    first by the backend's landmark stage alone on a crop they place (find.face_near: Face Mesh
    without MediaPipe's detector passes, as MediaPipe tracks a face in a video), then by the
    detector on a square crop CROP_MARGIN times their extent, for the face overlapping their box;
    when it is not there (or its landmarks do not form a face), the whole frame again, for the largest face.
    Landmarks that cannot be the same face one frame later (:meth:`agrees`: the eye line turned
    by more than MAX_TURN_DEG, or the eyes moved by more than MAX_SHIFT eye distances; a detector
    may return a face upside down, or a face-like patch beside the face) are not taken: the
    whole frame is searched, and when that finds no such face either, the frame has none (held).
    ``backend``: the detection backend (None: the default).
    """

    CROP_MARGIN = 2.0
    MAX_TURN_DEG = 60.0
    MAX_SHIFT = 1.5

    def __init__(self, face: int | None = None, face_box=None, backend: str | None = None):
        self.face, self.face_box, self.backend = face, face_box, backend
        self.started = False

    def find(self, image: np.ndarray, previous=None) -> np.ndarray | None:
        """(68, 2) frame pixels of the face in image (H, W, 3) uint8 RGB, or None (no face)."""
        if previous is None or not np.all(np.isfinite(previous)):
            return self._whole(image)
        previous = np.asarray(previous, np.float64)
        for search in (self._near, lambda image, previous: self._whole(image)):
            points = search(image, previous)
            if points is not None and self.agrees(points, previous):
                return points
        return None

    @classmethod
    def agrees(cls, points: np.ndarray, previous: np.ndarray) -> bool:
        """Whether (68, 2) landmarks can be the face whose (68, 2) landmarks the previous frame's
        fit gave: its eye line (outer corners, iBUG 37 and 46) turned by at most MAX_TURN_DEG and
        the eyes' midpoint moved by at most MAX_SHIFT of the previous eye distance."""
        corners = list(ibug68.OUTER_EYE_CORNERS)
        eyes, eyes_before = points[corners], previous[corners]
        line, line_before = eyes[1] - eyes[0], eyes_before[1] - eyes_before[0]
        turn = np.degrees(abs(np.arctan2(line_before[0] * line[1] - line_before[1] * line[0], line_before @ line)))
        shift = np.linalg.norm(eyes.mean(0) - eyes_before.mean(0)) / max(np.linalg.norm(line_before), 1e-9)
        return bool(turn <= cls.MAX_TURN_DEG and shift <= cls.MAX_SHIFT)

    def _detect(self, image, **choice) -> np.ndarray | None:
        try:
            chosen = detect_face(image, self.backend, **choice).chosen
        except (NoFaceError, ImplausibleFaceError):
            return None
        return chosen.landmarks

    def _whole(self, image) -> np.ndarray | None:
        choice = {} if self.started else dict(face=self.face, face_box=self.face_box)
        points = self._detect(image, **choice)
        self.started = self.started or points is not None
        return points

    def _near(self, image, previous: np.ndarray) -> np.ndarray | None:
        """The face around the previous landmarks (None: not there): the landmark stage alone
        on a crop placed by them (find.face_near) when it finds a face that agrees with them,
        else the detector on a crop around them."""
        points = face_near(image, previous, self.backend)
        if points is not None and self.agrees(points, previous):
            return points
        lo, hi = previous.min(0), previous.max(0)
        centre, half = (lo + hi) / 2, 0.5 * self.CROP_MARGIN * float(np.max(hi - lo))
        x0, y0 = np.maximum(np.floor(centre - half), 0).astype(int)
        x1, y1 = np.minimum(np.ceil(centre + half), [image.shape[1], image.shape[0]]).astype(int)
        if x1 - x0 < 16 or y1 - y0 < 16:            # the face has left the frame
            return None
        box = np.array([lo[0] + 0.5 - x0, lo[1] + 0.5 - y0, *(hi - lo)])   # the pixel grid: centres + 0.5
        points = self._detect(np.ascontiguousarray(image[y0:y1, x0:x1]), face_box=box, tiles=False)
        return None if points is None else points + [x0, y0]
