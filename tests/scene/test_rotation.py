"""Rotations (softras_cl.scene.rotation): Rodrigues against scipy, its vjp against central
finite differences, the inverse map, and bad input raising ValueError that names the argument."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from softras_cl.scene.rotation import (_SMALL_ANGLE, _rodrigues_coeffs, axis_angle_to_matrix,
                                       matrix_to_axis_angle, rodrigues, rodrigues_vjp)
from tests.scene.test_camera import assert_grad, fd_gradient, raises

RNG = np.random.default_rng(7)


OMEGAS = [np.zeros(3), np.array([1e-12, 0, 0]), np.array([3e-5, -1e-5, 2e-5]),
          np.array([0.05, 0.03, -0.06]), np.array([0.0999, 0, 0]), np.array([0.1001, 0, 0]),
          np.array([0.3, -1.2, 0.7]), np.array([0, 0, np.pi - 1e-7]),
          np.pi * np.array([1.0, 1.0, 1.0]) / math.sqrt(3), np.array([2.0, 2.5, -1.0])]


@pytest.mark.parametrize("omega", OMEGAS)
def test_rodrigues_vs_scipy(omega):
    np.testing.assert_allclose(axis_angle_to_matrix(omega), Rotation.from_rotvec(omega).as_matrix(), atol=1e-14)


@pytest.mark.parametrize("omega", OMEGAS)
def test_rodrigues_vjp_vs_fd(omega):
    G = RNG.standard_normal((3, 3))
    g = rodrigues_vjp(rodrigues(omega)[1], G)["omega"]
    assert np.isfinite(g).all()
    assert_grad(g, fd_gradient(lambda w: np.sum(G * axis_angle_to_matrix(w)), omega.astype(float)))


def test_rodrigues_vjp_at_zero_is_the_skew_part():
    """At omega = 0, dR/domega_i = hat(e_i): the gradient is the vee of G - G^T."""
    G = RNG.standard_normal((3, 3))
    expected = np.array([G[2, 1] - G[1, 2], G[0, 2] - G[2, 0], G[1, 0] - G[0, 1]])
    np.testing.assert_allclose(rodrigues_vjp(rodrigues(np.zeros(3))[1], G)["omega"], expected, atol=1e-15)


@pytest.mark.parametrize("omega", OMEGAS + [np.array([0, np.pi, 0]), np.array([np.pi - 1e-9, 0, 0]),
                                            np.array([1e-9, np.pi - 1e-9, 0]), np.array([0, 0, 1e-300])])
def test_matrix_to_axis_angle_roundtrip(omega):
    R = Rotation.from_rotvec(omega).as_matrix()
    w = matrix_to_axis_angle(R)
    assert np.linalg.norm(w) <= np.pi + 1e-12
    np.testing.assert_allclose(axis_angle_to_matrix(w), R, atol=1e-12)
    if np.linalg.norm(omega) < np.pi - 1e-6:
        np.testing.assert_allclose(w, omega, atol=1e-12)



def test_rodrigues_bad_input():
    with raises("omega"):
        rodrigues(np.zeros(4))
    with raises("omega"):
        rodrigues([0, np.nan, 0])
    with raises("grad_R"):
        rodrigues_vjp(rodrigues(np.zeros(3))[1], np.eye(2))
    with raises("R"):
        matrix_to_axis_angle(np.eye(4))


def test_rodrigues_series_meets_closed_form():
    """The small-angle Taylor branch and the closed form agree at the switch-over angle."""
    below = _rodrigues_coeffs(_SMALL_ANGLE * (1 - 1e-12))
    above = _rodrigues_coeffs(_SMALL_ANGLE * (1 + 1e-12))
    np.testing.assert_allclose(below, above, rtol=1e-11)
    np.testing.assert_allclose(_rodrigues_coeffs(0.0), [1, 0.5, -1 / 3, -1 / 12], rtol=1e-15)


def _omegas(rng, n=200):
    """Axis-angles from 1e-10 to 3 rad, zero, and either side of the series threshold."""
    omegas = rng.normal(size=(n, 3)) * 10.0 ** rng.uniform(-10, 0.5, size=(n, 1))
    omegas[0] = 0.0
    omegas[1:3] = [[_SMALL_ANGLE * (1 - 1e-12), 0.0, 0.0], [0.0, _SMALL_ANGLE, 0.0]]
    return omegas


def test_batched_rodrigues_equals_one_call_per_joint():
    """R within 4e-16 and A, B within 1e-15 of softras_cl.scene.rotation's; C and D within
    1e-12: their closed forms cancel (by 1e3 near the series threshold) in both, a last-bit
    difference of sin or cos between numpy and math grows by that much."""
    from softras_cl.scene.rotation import rodrigues, rodrigues_rows

    omegas = _omegas(np.random.default_rng(7))
    rotations, coeffs = rodrigues_rows(omegas)
    for w, r, c in zip(omegas, rotations, coeffs.T):
        want, ctx = rodrigues(w)
        np.testing.assert_allclose(r, want, rtol=0, atol=4e-16)
        np.testing.assert_allclose(c[:2], ctx.coeffs[:2], rtol=1e-15, atol=0)
        np.testing.assert_allclose(c[2:], ctx.coeffs[2:], rtol=1e-12, atol=0)


def test_batched_rodrigues_vjp_equals_one_call_per_joint():
    """Within 1e-15 of the largest cotangent entry of each row, over magnitudes 1e-4..1e4."""
    from softras_cl.scene.rotation import rodrigues, rodrigues_rows, rodrigues_rows_vjp, rodrigues_vjp

    rng = np.random.default_rng(7)
    omegas = _omegas(rng)
    grads = rng.normal(size=(len(omegas), 3, 3)) * 10.0 ** rng.uniform(-4, 4, size=(len(omegas), 1, 1))
    got = rodrigues_rows_vjp(omegas, rodrigues_rows(omegas)[1], grads)
    for w, g, row in zip(omegas, grads, got):
        np.testing.assert_allclose(row, rodrigues_vjp(rodrigues(w)[1], g)["omega"], rtol=0, atol=1e-15 * np.abs(g).max())
