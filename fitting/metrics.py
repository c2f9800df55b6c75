"""Image metrics reported by the fitting recipes and benchmarks, and the checks that a fit's
metrics mean something (:func:`check_face_result`, :func:`finite_metrics`)."""
from __future__ import annotations

import math

import numpy as np

from softras_cl.errors import ResultError

# A fit's face region (FaceFit.metrics()["face_pixels"]) smaller than this is a handful of
# pixels. Measured (fast budget): 66 and more on real fits at the smallest working image (32
# pixels: astronaut 66, Grace Hopper 111, synthetic faces 79-84); 1-13 with shuffled landmarks.
MIN_FACE_PIXELS = 16
# A mean landmark error (working pixels) above this fraction of the landmarks' extent: the model
# is not on the face. Measured 0.011-0.037 on real and synthetic fits at 32-256 pixels; 0.30-0.32
# with shuffled landmarks (docs/reliability.md).
MAX_LANDMARK_ERROR = 0.15


def psnr(a, b, mask) -> float:
    """PSNR (dB, peak 1) between images a, b (H, W, 3) over the pixels where mask (H, W)."""
    m = np.asarray(mask, bool)
    if not m.any():
        return float("nan")
    mse = float(np.mean((np.asarray(a)[m] - np.asarray(b)[m]) ** 2))
    return float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)


def finite_metrics(fit, folder, required) -> dict:
    """``fit.metrics()`` (a FaceFit's, a multi-photo face fit's or a BodyFit's), or ResultError
    when one of the ``required`` metric names is not finite, or when a face fit cannot be right
    (:func:`check_face_result`, for each photo): a meaningless fit must not be
    reported as a success. ``folder`` is where the solver's files of that fit are, for the
    message."""
    metrics = fit.metrics()
    for what, face_fit, face_metrics in _face_fits(fit, metrics):    # first: it names the cause
        check_face_result(face_metrics, face_fit.landmarks, folder, what)
    bad = [f"{name} is {metrics[name]}" for name in required if not math.isfinite(metrics[name])]
    if bad:
        raise ResultError(f"the fit failed: {', '.join(bad)}; checkpoint.npz, history.json and "
                          f"loss_curve.png in {folder} show how it went")
    return metrics


def _face_fits(fit, metrics: dict) -> list[tuple[str, object, dict]]:
    """(name, FaceFit, its metrics) of each photo of a face fit; none for a body fit."""
    if "views" in metrics:
        return [(f"the fit of photo {i + 1}", view, m)
                for i, (view, m) in enumerate(zip(fit.views, metrics["views"]))]
    return [("the fit", fit, metrics)] if "face_pixels" in metrics else []


def check_face_result(metrics: dict, landmarks, folder, what: str = "the fit") -> None:
    """ResultError (exit 1) when a face fit cannot be right: ``metrics`` (FaceFit.metrics():
    face_pixels, landmark_error_px) give a face region under MIN_FACE_PIXELS pixels, or a mean
    landmark error above MAX_LANDMARK_ERROR times the extent of the target ``landmarks``
    (68, 2) working-image pixels. ``folder``: where the solver's files are, and ``what``: the
    fit's name, for the message."""
    extent = float(np.ptp(np.asarray(landmarks, np.float64), axis=0).max())
    error = metrics["landmark_error_px"] / extent
    faults = []
    if metrics["face_pixels"] < MIN_FACE_PIXELS:
        faults.append(f"its face region is {metrics['face_pixels']} pixel(s) (at least "
                      f"{MIN_FACE_PIXELS} needed; the mesh collapsed or left the view)")
    if error > MAX_LANDMARK_ERROR:
        faults.append(f"its landmark error is {error:.2f} of the face's extent (at most "
                      f"{MAX_LANDMARK_ERROR} expected: the model is not on the face)")
    if faults:
        raise ResultError(f"{what} cannot be right: {'; '.join(faults)}. Likely cause: landmarks "
                          f"that do not belong to this face or are not in iBUG 300-W order; "
                          f"checkpoint.npz, history.json and loss_curve.png in {folder} show how it went")
