"""The former home of face landmark detection, kept so that existing imports work: every name
here comes from softras_cl.fitting.detection (new code imports it from there)."""
from softras_cl.fitting.detection import (BACKENDS, IBUG68_NAMES, MP468_TO_IBUG68,  # noqa: F401
                                          DetectorUnavailableError, NoFaceError, PhotoLandmarks,
                                          available_backends, default_backend, draw_landmarks,
                                          format_pts, landmarks_beside, read_photo_rgb8,
                                          resolve_landmarks)
