"""The sRGB transfer functions: linear values <-> sRGB-encoded values, in numpy.

All shading and losses in softras-cl work in linear RGB; image files and the detectors' 8-bit
images hold sRGB-encoded values. The curves are IEC 61966-2-1's piecewise ones (equal to
colour-science's `cctf_decoding` / `cctf_encoding` with function="sRGB", which a test checks,
without its ~1 s import on every run), applied to every value of any array, with no clipping:
values outside [0, 1] follow the curves' extensions. A low module (numpy only): softras_cl.io
reads and writes image files with it, the fitting recipes and the reports convert with it.
"""
from __future__ import annotations

import numpy as np

__all__ = ["to_linear", "to_srgb"]


def _curve(x: np.ndarray, knee: float, below, above) -> np.ndarray:
    """below(x) where x <= knee, else above(x) (NaN included), as float64 of x's shape; above,
    the power, is evaluated on those values only (it is most of the cost)."""
    out = np.array(below(x), dtype=np.float64)
    upper = ~(x <= knee)
    out[upper] = above(x[upper])
    return out


_LINEAR_KNEE = 0.0031308
_ENCODED_KNEE = 1.055 * _LINEAR_KNEE ** (1.0 / 2.4) - 0.055   # 0.0404499..., where the curves meet


def to_linear(srgb) -> np.ndarray:
    """sRGB-encoded values (any shape) -> linear values, float64 (IEC 61966-2-1 decoding)."""
    v = np.asarray(srgb, dtype=np.float64)
    return _curve(v, _ENCODED_KNEE, lambda v: v / 12.92, lambda v: ((v + 0.055) / 1.055) ** 2.4)


def to_srgb(linear) -> np.ndarray:
    """Linear values (any shape) -> sRGB-encoded values, float64 (IEC 61966-2-1 encoding)."""
    x = np.asarray(linear, dtype=np.float64)
    return _curve(x, _LINEAR_KNEE, lambda x: x * 12.92, lambda x: 1.055 * x ** (1.0 / 2.4) - 0.055)
