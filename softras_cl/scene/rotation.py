"""Rotations as axis-angle 3-vectors: the Rodrigues map with its exact vector-Jacobian product,
its value-only form, and the inverse map from a rotation matrix.

    R, ctx = rodrigues(omega)            # omega (3,) -> R (3, 3), both float64
    grads = rodrigues_vjp(ctx, grad_R)   # {"omega": (3,)}
    R = axis_angle_to_matrix(omega)      # the same R, when no gradient is needed
    omega = matrix_to_axis_angle(R)      # |omega| in [0, pi]
    R, coeffs = rodrigues_rows(omegas)   # N at once: (N, 3) -> (N, 3, 3), with rodrigues_rows_vjp

`R = I + A K + B K^2` with `K = hat(omega)`, `A = sin t / t`, `B = (1 - cos t) / t^2`,
`t = |omega|`; below `_SMALL_ANGLE` the coefficients use their Taylor series, so the map and its
gradient are exact and finite at omega = 0.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from softras_cl.checks import real_array

_SMALL_ANGLE = 0.1          # below this |omega| the Rodrigues coefficients use their Taylor series


def vector3(name: str, value) -> np.ndarray:
    """A finite real 3-vector -> (3,) float64 array; ValueError naming `name` otherwise."""
    return real_array(name, value, (3,), what="a real 3-vector").copy()


def matrix3(name: str, value) -> np.ndarray:
    """A finite real 3x3 matrix -> (3, 3) float64 array; ValueError naming `name` otherwise."""
    return real_array(name, value, (3, 3), what="a real 3x3 matrix").copy()


def hat(w: np.ndarray) -> np.ndarray:
    """(3,) -> (3, 3) cross-product matrix K with K v = w x v."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


_E = tuple(hat(np.eye(3)[i]) for i in range(3))       # hat(e_i), the derivatives of hat(w)


def _series(theta2: float, coeffs: tuple) -> float:
    """sum_k coeffs[k] theta2^k."""
    return sum(c * theta2 ** k for k, c in enumerate(coeffs))


_f = math.factorial
# Taylor coefficients (in t^2) of A, B, C and D below _SMALL_ANGLE
_TAYLOR = ([(-1) ** k / _f(2 * k + 1) for k in range(6)], [(-1) ** k / _f(2 * k + 2) for k in range(6)],
           [(-1) ** (k + 1) * 2 * (k + 1) / _f(2 * k + 3) for k in range(6)],
           [(-1) ** (k + 1) * 2 * (k + 1) / _f(2 * k + 4) for k in range(6)])
_TAYLOR_HORNER = np.array(_TAYLOR)[:, ::-1]     # highest power first, for rodrigues_rows


def _rodrigues_coeffs(theta: float) -> tuple[float, float, float, float]:
    """A = sin t / t, B = (1 - cos t) / t^2, C = A'(t) / t, D = B'(t) / t (Taylor for small t)."""
    t2 = theta * theta
    if theta < _SMALL_ANGLE:
        a, b, c, d = (_series(t2, coeffs) for coeffs in _TAYLOR)
        return a, b, c, d
    s, c_ = math.sin(theta), math.cos(theta)
    one_minus_cos = 2.0 * math.sin(0.5 * theta) ** 2
    a = s / theta
    b = one_minus_cos / t2
    c = (theta * c_ - s) / (t2 * theta)
    d = (theta * s - 2.0 * one_minus_cos) / (t2 * t2)
    return a, b, c, d


@dataclass(frozen=True)
class RodriguesContext:
    """What rodrigues_vjp needs: omega (3,) float64, its cross-product matrix k (3, 3) and
    coeffs, the coefficients (A, B, C, D) of |omega| (_rodrigues_coeffs: the forward computes
    all four, the vjp uses them)."""
    omega: np.ndarray
    k: np.ndarray
    coeffs: tuple[float, float, float, float]


def rodrigues(omega) -> tuple[np.ndarray, RodriguesContext]:
    """Axis-angle omega (3,) -> (R (3, 3) float64 = I + A K + B K^2 with K = hat(omega), ctx)."""
    w = vector3("omega", omega)
    coeffs = _rodrigues_coeffs(float(np.linalg.norm(w)))
    a, b = coeffs[:2]
    k = hat(w)
    return np.eye(3) + a * k + b * (k @ k), RodriguesContext(w, k, coeffs)


def rodrigues_rows(omegas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """rodrigues of N axis-angles at once, in numpy: omegas (N, 3) finite float64 (not checked:
    a caller's own values, every evaluation) -> (R (N, 3, 3), the coefficients (4, N): A, B, C
    and D of each |omega|, for rodrigues_rows_vjp). Equal to rodrigues within a few 1e-16
    (tested); for the 24 joints of a body, stacked products instead of 24 calls."""
    t2 = np.einsum("na,na->n", omegas, omegas)
    small = t2 < _SMALL_ANGLE ** 2
    series = _TAYLOR_HORNER[:, 0:1] * np.ones_like(t2)
    for row in _TAYLOR_HORNER.T[1:]:
        series = series * t2 + row[:, None]
    t = np.where(small, 1.0, np.sqrt(t2))           # the closed forms, where they are used
    t2 = np.where(small, 1.0, t2)
    sin, cos = np.sin(t), np.cos(t)
    one_minus_cos = 2.0 * np.sin(0.5 * t) ** 2
    closed = np.stack([sin / t, one_minus_cos / t2, (t * cos - sin) / (t2 * t), (t * sin - 2.0 * one_minus_cos) / (t2 * t2)])
    coeffs = np.where(small, series, closed)
    a, b = coeffs[0][:, None, None], coeffs[1][:, None, None]
    k = _hats(omegas)
    return np.eye(3) + a * k + b * (k @ k), coeffs


def rodrigues_rows_vjp(omegas: np.ndarray, coeffs: np.ndarray, grads: np.ndarray) -> np.ndarray:
    """Back through ``rodrigues_rows``: omegas (N, 3), their coefficients (4, N) and dL/dR
    (N, 3, 3) -> dL/domega (N, 3) float64. rodrigues_vjp's dR/dw_i = w_i (C K + D K^2) + A E_i
    + B (E_i K + K E_i) in closed form: <G, E_i> = skew_i(G), <G, E_i K + K E_i> = -skew_i(G K
    + K G), <G, K> = w . skew(G), <G, K^2> = w^T G w - |w|^2 tr G."""
    a, b, c, d = coeffs
    k = _hats(omegas)
    skew = _skew(grads)
    along_k = np.einsum("na,na->n", omegas, skew)
    along_k2 = (np.einsum("na,nab,nb->n", omegas, grads, omegas)
                - np.einsum("na,na->n", omegas, omegas) * np.trace(grads, axis1=1, axis2=2))
    radial = c * along_k + d * along_k2
    return omegas * radial[:, None] + a[:, None] * skew - b[:, None] * _skew(grads @ k + k @ grads)


def _hats(w: np.ndarray) -> np.ndarray:
    """(N, 3) -> (N, 3, 3) cross-product matrices hat(w_n) (exact: sums of w's entries and zeros)."""
    return (w @ np.stack(_E).reshape(3, 9)).reshape(-1, 3, 3)


def _skew(m: np.ndarray) -> np.ndarray:
    """(N, 3, 3) -> (N, 3): <m_n, hat(e_i)> = (m21 - m12, m02 - m20, m10 - m01)."""
    flat = m.reshape(-1, 9)
    return flat[:, [7, 2, 3]] - flat[:, [5, 6, 1]]


def rodrigues_vjp(ctx: RodriguesContext, grad_R) -> dict:
    """dL/dR (3, 3) -> {"omega": dL/domega (3,) float64}; exact, finite at omega = 0.

    dR/dw_i = w_i (C K + D K^2) + A E_i + B (E_i K + K E_i), E_i = hat(e_i).
    """
    g = matrix3("grad_R", grad_R)
    w, k = ctx.omega, ctx.k
    a, b, c, d = ctx.coeffs
    radial = c * (g * k).sum() + d * (g * (k @ k)).sum()
    out = np.empty(3)
    for i, e in enumerate(_E):
        out[i] = w[i] * radial + a * (g * e).sum() + b * (g * (e @ k + k @ e)).sum()
    return {"omega": out}


def axis_angle_to_matrix(omega) -> np.ndarray:
    """Axis-angle omega (3,) -> rotation matrix (3, 3) float64: rodrigues without the context."""
    return rodrigues(omega)[0]


def _vee_skew(m: np.ndarray) -> np.ndarray:
    """(3, 3) -> the 3-vector of its skew part (m - m^T) / 2."""
    return 0.5 * np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])


def matrix_to_axis_angle(R) -> np.ndarray:
    """Rotation matrix (3, 3) -> axis-angle (3,) float64 with |omega| in [0, pi]; stable near 0
    and pi.

    The angle comes from atan2(|skew|, cos); below pi/2 the axis from the skew part, above it
    from the largest column of the symmetric part (sign taken from the skew part).
    """
    m = matrix3("R", R)
    w = _vee_skew(m)                                   # sin(theta) * axis
    sin_t = float(np.linalg.norm(w))
    cos_t = float(np.clip(0.5 * (np.trace(m) - 1.0), -1.0, 1.0))
    theta = math.atan2(sin_t, cos_t)
    if cos_t > 0.0:
        ratio = 1.0 + theta * theta / 6.0 if sin_t < 1e-8 else theta / sin_t
        return w * ratio
    sym = 0.5 * (m + m.T) - cos_t * np.eye(3)          # (1 - cos) axis axis^T
    j = int(np.argmax(np.diag(sym)))
    axis = sym[:, j] / np.linalg.norm(sym[:, j])
    if axis @ w < 0.0:
        axis = -axis
    return theta * axis
