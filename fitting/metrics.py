"""Image metrics reported by the fitting recipes and benchmarks."""
from __future__ import annotations

import math

import numpy as np

from softras_cl.errors import ResultError


def psnr(a, b, mask) -> float:
    """PSNR (dB, peak 1) between images a, b (H, W, 3) over the pixels where mask (H, W)."""
    m = np.asarray(mask, bool)
    if not m.any():
        return float("nan")
    mse = float(np.mean((np.asarray(a)[m] - np.asarray(b)[m]) ** 2))
    return float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)


def finite_metrics(fit, folder, required) -> dict:
    """``fit.metrics()`` (a FaceFit's or BodyFit's), or ResultError when one of the ``required``
    metric names is not finite: a meaningless fit must not be reported as a success. ``folder``
    is where the solver's files of that fit are, for the message."""
    metrics = fit.metrics()
    bad = [f"{name} is {metrics[name]}" for name in required if not math.isfinite(metrics[name])]
    if bad:
        raise ResultError(f"the fit failed: {', '.join(bad)}; checkpoint.npz, history.json and "
                          f"loss_curve.png in {folder} show how it went")
    return metrics
