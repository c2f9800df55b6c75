"""Image metrics reported by the fitting recipes and benchmarks."""
from __future__ import annotations

import math

import numpy as np

from softras_cl.errors import ResultError
from softras_cl.fitting.plausibility import check_face_result


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
    (fitting.plausibility.check_face_result, for each photo): a meaningless fit must not be
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
