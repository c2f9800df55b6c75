"""Faces and people in photos: find them, choose one and say why; a face's 68 iBUG landmarks, a
person's 33 body keypoints and mask (people.py: MediaPipe's pose model, docs/body_photos.md).

Backends (find.py): "mediapipe" (the default; MediaPipe's short- and full-range face detectors
on the whole image and on a pyramid of tiles; then Face Mesh, 478 points, on each face's
upright crop, and 68 of its points for the iBUG ones, fitting.keypoints.face_mesh), "dlib" (opt-in,
non-commercial 68-point model), and the user's own files (files.py). Every face is a FaceCandidate (faces.py); faces are listed and numbered
largest first; detect_face chooses one (the largest, --face N, --face-box X,Y,W,H) and says
why, and refuses landmarks that do not form a face; face_near follows a face from its last
landmarks by the landmark stage alone (a video's next frame). docs/landmarks.md is the guide.

Coordinates: landmarks (N, 2) float64 (x, y), 0-based pixel centres; boxes (x, y, w, h) on the
pixel grid, where pixel (i, j) covers [i, i + 1) x [j, j + 1).
"""
from softras_cl.fitting.detection.faces import (ORDER, DetectorUnavailableError, FaceCandidate,
                                                ImplausibleFaceError, NoFaceError, choose_face,
                                                implausible_landmarks, parse_face_box)
from softras_cl.fitting.detection.files import (PhotoLandmarks, format_pts, landmarks_beside,
                                                resolve_landmarks)
from softras_cl.fitting.detection.find import (BACKENDS, DEFAULT_BACKEND, Detection, available_backends,
                                               default_backend, detect_face, face_near, find_faces,
                                               no_face_error)
from softras_cl.fitting.detection.overlay import draw_detection, draw_landmarks
from softras_cl.fitting.detection.people import (PEOPLE_INSTALL_HINT, NoPersonError, PersonDetection,
                                                 detect_person, people_available)

__all__ = ["ORDER", "BACKENDS", "DEFAULT_BACKEND", "FaceCandidate", "Detection", "PhotoLandmarks",
           "DetectorUnavailableError", "NoFaceError", "ImplausibleFaceError", "find_faces", "detect_face",
           "face_near",
           "choose_face", "implausible_landmarks", "parse_face_box", "resolve_landmarks", "landmarks_beside",
           "available_backends", "default_backend", "no_face_error", "format_pts",
           "draw_landmarks", "draw_detection", "PEOPLE_INSTALL_HINT", "NoPersonError", "PersonDetection", "detect_person",
           "people_available"]
