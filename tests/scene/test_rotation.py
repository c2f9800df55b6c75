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


def test_rodrigues_rows_equals_rodrigues_row_by_row():
    """Bit for bit, from zero through the Taylor-series range to large angles; errors name the
    argument."""
    from softras_cl.scene.rotation import rodrigues, rodrigues_rows

    rng = np.random.default_rng(3)
    omegas = np.concatenate([np.zeros((1, 3))] + [rng.normal(size=(50, 3)) * s for s in (1e-9, 1e-3, 0.05, 1.0, 3.0)])
    R, ctxs = rodrigues_rows(omegas)
    for w, r, ctx in zip(omegas, R, ctxs):
        one, one_ctx = rodrigues(w)
        assert np.array_equal(r, one) and np.array_equal(ctx.k, one_ctx.k) and np.array_equal(ctx.omega, one_ctx.omega)
        # the vjp's coefficients, made by the forward: those of |omega|
        assert ctx.coeffs == one_ctx.coeffs == _rodrigues_coeffs(float(np.linalg.norm(w)))
    with pytest.raises(ValueError, match="omegas"):
        rodrigues_rows(np.zeros((4, 2)))
