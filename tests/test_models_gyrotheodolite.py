import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gyrojax.estimate.observer import (
    ackermann_observer,
    binomial_poles,
    frequency_response,
    observability_matrix,
)
from gyrojax.models.gyrotheodolite import GyrotheodoliteConditions, GyrotheodoliteRig

RIG = GyrotheodoliteRig()
P = RIG.default_params()
COND = GyrotheodoliteConditions.create(50.45)
OMEGA0 = (1.0, 10.0, 100.0, 1000.0)


def test_state_matrix_equals_autodiff_linearization_and_char_poly():
    """A of (3) is the Jacobian of the equations (1) (no vibration), and det(pE - A) has the
    closed-form coefficients a0..a3."""
    a, c, g, b = RIG.state_space(P, COND)
    jac = jax.jacfwd(lambda x: RIG.vector_field(0.0, x, P, COND))(jnp.zeros(4))
    np.testing.assert_allclose(a, jac, rtol=1e-14, atol=1e-18)
    np.testing.assert_allclose(RIG.vector_field(0.0, jnp.zeros(4), P, COND), b, rtol=1e-14)
    poly = np.poly(np.asarray(a))
    a0, a1, a2, a3 = (float(x) for x in RIG.open_loop_coefficients(P, COND))
    np.testing.assert_allclose(poly[1:], [a3, a2, a1, a0], rtol=1e-9)
    # G of (7): the response of the tilt acceleration to n_X
    vib = GyrotheodoliteConditions.create(50.45, n_m=1.0, omega=1.0)
    dx = RIG.vector_field(np.pi / 2, jnp.zeros(4), P, vib) - RIG.vector_field(0.0, jnp.zeros(4), P,
                                                                              vib)
    np.testing.assert_allclose(dx, g, rtol=1e-12)


def test_observability_rank_and_determinant():
    """rank Q = 4 from the rig's own linearization; det Q = H^2 mgl / (J_y^2 J_z)."""
    a, c, _, _ = RIG.state_space(P, COND)
    q = np.asarray(observability_matrix(a, c))
    assert np.linalg.matrix_rank(q / np.linalg.norm(q, axis=0)) == 4
    expected = P["H"] ** 2 * P["mgl"] / (P["J_y"] ** 2 * P["J_z"])
    assert abs(np.linalg.det(q)) == pytest.approx(float(expected), rel=1e-9)


@pytest.mark.parametrize("omega0", OMEGA0)
def test_closed_form_gains_equal_ackermann_and_place_poles(omega0):
    a, c, _, _ = RIG.state_space(P, COND)
    k_closed = RIG.observer_gains(P, COND, omega0)
    k_ack = ackermann_observer(a, c, binomial_poles(omega0))
    np.testing.assert_allclose(k_closed, k_ack, rtol=1e-6)
    eig = np.linalg.eigvals(np.asarray(a - jnp.outer(k_closed, c[0])))
    # a quadruple root splits by ~eps^(1/4) relative
    assert np.max(np.abs(eig + omega0)) < 2e-3 * omega0
    poly = np.poly(eig).real
    np.testing.assert_allclose(poly, np.poly(-omega0 * np.ones(4)), rtol=1e-6)


@pytest.mark.parametrize("omega0", OMEGA0)
def test_printed_gains_give_unstable_observer(omega0):
    a, c, _, _ = RIG.state_space(P, COND)
    k = RIG.observer_gains(P, COND, omega0, printed=True)
    eig = np.linalg.eigvals(np.asarray(a - jnp.outer(k, c[0])))
    assert np.max(eig.real) > 0


@pytest.mark.parametrize("kappa,period,damping", [(0.0, 493, 0.49), (10.0, 131, 0.15)])
def test_plant_modes_match_spec(kappa, period, damping):
    """docs/rigs/gyrotheodolite.md: slow north-seeking mode 493 s, damping 0.49 (131 s and 0.15 with the
    compensation link at kappa = 10, k_alpha's factor 1 + kappa); nutation 54.7 rad/s, damping
    0.029 either way."""
    a, _, _, _ = RIG.state_space(RIG.default_params(kappa=kappa), COND)
    eig = np.linalg.eigvals(np.asarray(a))
    eig = eig[eig.imag > 0]
    slow, fast = sorted(eig, key=abs)
    assert 2 * np.pi / slow.imag == pytest.approx(period, rel=0.01)
    assert -slow.real / abs(slow) == pytest.approx(damping, abs=0.01)
    assert abs(fast) == pytest.approx(54.7, rel=0.01)
    assert -fast.real / abs(fast) == pytest.approx(0.029, abs=0.002)


def test_frequency_responses_match_closed_forms_and_fig1_bandwidth():
    """(pE - A)^{-1} G against the source's N_IT1, N_IT2 (9)-(10); the observer's rate-estimate error
    |W_HY2 / W_IT2 - 1| against the docs/rigs/gyrotheodolite.md figures: omega0 = 100: 1.2 % at 1 1/s, 120 %
    at 500; omega0 = 1000: < 10 % up to 309 1/s, 32 % at 500. (The source's "< 10 % below 60 1/s" for
    omega0 = 100 contradicts its own 1.2 % at 1 1/s, since the error grows linearly there; see
    docs/decisions/0008-gyrotheodolite-observer-and-vibration.md.)"""
    a, c, g, _ = RIG.state_space(P, COND)
    w = np.logspace(-2, 3, 400)
    wit = np.asarray(frequency_response(a, g, w))
    a0, a1, a2, a3 = (float(x) for x in RIG.open_loop_coefficients(P, COND))
    gain = float(P["mgl"] * P["H"] / (P["J_y"] * P["J_z"]))
    den = np.sqrt((w**4 - a2 * w**2 + a0) ** 2 + (a1 * w - a3 * w**3) ** 2)
    np.testing.assert_allclose(np.abs(wit[:, 0]), gain * w / den, rtol=1e-9)
    np.testing.assert_allclose(np.abs(wit[:, 1]), gain * w**2 / den, rtol=1e-9)
    err = {}
    for omega0 in (100.0, 1000.0):
        k = RIG.observer_gains(P, COND, omega0)
        a_obs = a - jnp.outer(k, c[0])
        # observer driven by the measured alpha: x_hat = (pE - A + KC)^{-1} K alpha
        why = np.asarray(frequency_response(a_obs, k, w))[:, 1] * wit[:, 0]
        err[omega0] = np.abs(why / wit[:, 1] - 1)
    at = lambda om, x: float(np.interp(x, w, err[om]))  # noqa: E731
    assert at(100.0, 1.0) == pytest.approx(0.012, abs=0.001)
    assert at(100.0, 500.0) == pytest.approx(1.2, rel=0.1)
    assert w[np.argmax(err[1000.0] > 0.1)] == pytest.approx(309, rel=0.1)
    assert at(1000.0, 500.0) == pytest.approx(0.32, rel=0.1)


def test_bad_input():
    a, c, _, _ = RIG.state_space(P, COND)
    with pytest.raises(ValueError, match="omega0=0"):
        binomial_poles(0.0)
    with pytest.raises(ValueError, match="one output"):
        ackermann_observer(a, jnp.eye(4)[:2], binomial_poles(10.0))
    with pytest.raises(ValueError, match="H=0.0 N m s must be > 0"):
        RIG.default_params(H=0.0)
    no_gyro = RIG.param_space.make({"H": 0.0})  # unchecked, to reach the placement's own check
    a0, c0, _, _ = RIG.state_space(no_gyro, COND)
    with pytest.raises(ValueError, match="not observable"):
        ackermann_observer(a0, c0, binomial_poles(10.0))
    with pytest.raises(ValueError, match="conjugation"):
        ackermann_observer(a, c, np.array([-1 + 1j, -1 + 1j, -2, -3]))
    with pytest.raises(ValueError, match="latitude 91"):
        GyrotheodoliteConditions.create(91)
