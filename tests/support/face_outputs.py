"""Checks of a face fit's landmark outputs (landmarks_detected.pts, landmarks_fitted.pts) against
the fit's own numbers: the points it was given, and the model's landmarks projected with the
camera params.npz holds."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from support.face_scenes import read_pts


def projected_model_landmarks(folder: Path, model) -> np.ndarray:
    """(68, 2) the face model's landmarks of the shape in folder/params.npz (id, exp), projected
    into the full photo with its K, R, t: pixel = K (R X + t) / Z, 0-based pixel centres."""
    params = np.load(folder / "params.npz")
    model = model.truncated(len(params["id"]), len(params["exp"]))
    points = model.landmarks(model.shape(params["id"], params["exp"])[0])[0]
    camera = points @ params["R"].T + params["t"]
    pixels = camera @ params["K"].T
    return pixels[:, :2] / pixels[:, 2:]


def check_landmark_files(folder: Path, model, given: np.ndarray) -> None:
    """landmarks_detected.pts holds ``given`` (68, 2), the points the fit was given; and
    landmarks_fitted.pts the model's landmarks (tied as fit-face ties them by default:
    landmark_model "auto" for the source params.json names) projected with the fitted camera (the jaw line's
    17 may slide to the occluding contour, fitting.recipes.contour: the other 51 are the model's own
    points), at the mean distance from the given points (over those the fit weighs) that
    params.json reports as the landmark error."""
    from softras_cl.fitting.detection.find import FACE_MESH_BACKENDS
    from softras_cl.fitting.recipes.face import tied_landmarks

    params = json.loads((folder / "params.json").read_text())
    on_mesh = params["landmarks_input"]["source"] in FACE_MESH_BACKENDS
    tied, weights = tied_landmarks(model, "auto", on_mesh)     # the fit's default
    detected, fitted = read_pts(folder / "landmarks_detected.pts"), read_pts(folder / "landmarks_fitted.pts")
    np.testing.assert_allclose(detected, given, atol=1e-9)
    np.testing.assert_allclose(fitted[17:], projected_model_landmarks(folder, tied)[17:], atol=1e-6)
    error = params["metrics"]["landmark_error_px_full"]
    used = weights > 0
    assert abs(np.linalg.norm(fitted[used] - given[used], axis=1).mean() - error) < 1e-6 * max(error, 1.0)
