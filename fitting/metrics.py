"""Image metrics reported by the fitting recipes and benchmarks."""
from __future__ import annotations

import math

import numpy as np


def psnr(a, b, mask) -> float:
    """PSNR (dB, peak 1) between images a, b (H, W, 3) over the pixels where mask (H, W)."""
    m = np.asarray(mask, bool)
    if not m.any():
        return float("nan")
    mse = float(np.mean((np.asarray(a)[m] - np.asarray(b)[m]) ** 2))
    return float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)
