"""Schuler-test rig (docs/rigs/schuler.md): the nonlinear model (S7) against an
independent direction-cosine integration, the zero-order solution (S9), the analytic response to an
initial tilt, the source's departure figures, and the pass/fail period estimate."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gyrojax import units
from gyrojax.models.schuler import (
    EARTH_RADIUS,
    EARTH_RATE_SOURCE,
    ERROR_STATES,
    PARAM_NAMES,
    SchulerConditions,
    SchulerRig,
    error_matrix,
    platform_matrix,
    propagate_error_model,
    schuler_period,
    schuler_solution,
)
from gyrojax.rotations import skew
from gyrojax.simulate import integrate

RIG = SchulerRig()
COND = SchulerConditions.create()
T = float(COND.schuler_period)
TYPICAL = {"nu1": 0.2, "nu2": -0.2, "nu3": 0.2, "D11": 1e4, "D22": -1e4, "df1": 1e-2, "df2": -1e-2,
           "K11": 1e4, "K22": -1e4, "alpha10": 1e-3 / units.ARCMIN,
           "alpha20": -1e-3 / units.ARCMIN, "dA0": 1e-2 / units.ARCMIN}
"""docs/rigs/schuler.md's typical error set in display units (deg/h, ppm, m/s^2, arcmin)."""


def _states(params, cond, ts):
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, y, a: RIG.vector_field(t, y, params, cond)), diffrax.Dopri8(),
        ts[0], ts[-1], None, RIG.initial_state(params, cond), saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=1e-11, atol=1e-12), max_steps=200_000)
    return np.asarray(sol.ys)


def test_defaults_match_spec():
    """docs/rigs/schuler.md: g = 9.815557 m/s^2, omega0 = 1.241223e-3 rad/s, T = 5062.09 s, sqrt(g a_R) =
    7908."""
    assert float(COND.g) == pytest.approx(9.815557, abs=1e-6)
    assert float(COND.schuler_frequency) == pytest.approx(1.241223e-3, rel=1e-6)
    assert T == pytest.approx(5062.09, abs=0.01)
    assert float(jnp.sqrt(COND.g * EARTH_RADIUS)) == pytest.approx(7908.0, abs=0.05)
    p = RIG.param_space.make(TYPICAL, display=True)
    assert float(p["nu1"]) == pytest.approx(0.2 * units.DEG_PER_HOUR)
    assert float(p["D11"]) == pytest.approx(1e-2)
    assert float(p["alpha10"]) == pytest.approx(1e-3) and float(p["dA0"]) == pytest.approx(1e-2)


def test_zero_order_solution_satisfies_its_equations():
    """(S9) solves (S8): derivatives by forward-mode autodiff in tau."""
    tau = jnp.linspace(0.0, 2 * T, 37)

    def f(t):
        return jnp.stack(schuler_solution(COND, t))

    x, dx = jax.jvp(jax.vmap(f), (tau,), (jnp.ones_like(tau),))
    a1, a2, am, v1, v2 = x.T
    np.testing.assert_allclose(dx[:, 0], -v2 / EARTH_RADIUS, atol=1e-15)
    np.testing.assert_allclose(dx[:, 1], v1 / EARTH_RADIUS, atol=1e-15)
    np.testing.assert_allclose(dx[:, 3], -COND.g * a2, atol=1e-12)
    np.testing.assert_allclose(dx[:, 4], COND.g * a1, atol=1e-12)
    np.testing.assert_allclose(dx[:, 2], EARTH_RATE_SOURCE * np.sin(COND.latitude), rtol=1e-14)
    quarter = schuler_solution(COND, T / 4)
    assert float(quarter[0]) == pytest.approx(0.02529, abs=1e-5)  # 200 m/s / 7908 m/s = 1.449 deg
    assert float(quarter[3]) == pytest.approx(0.0, abs=1e-9)


def test_vector_field_equals_direction_cosine_kinematics():
    """(S7) against an independent integration of dC/dt = -[omega_rel x] C with the same commanded
    rates, drifts and accelerometer errors (typical error set, one period): the platform matrices
    agree to 1e-9 and the model velocities to 1e-5 m/s."""
    p = RIG.param_space.make(TYPICAL, display=True)
    ts = jnp.linspace(0.0, T, 201)
    x = _states(p, COND, ts)
    un = EARTH_RATE_SOURCE * jnp.cos(COND.latitude)
    uv = EARTH_RATE_SOURCE * jnp.sin(COND.latitude)

    def dcm_field(t, y, args):
        c = y[:9].reshape(3, 3)
        v1, v2, am = y[9], y[10], y[11]
        w1 = -v2 / EARTH_RADIUS - un * jnp.sin(am)
        w2 = v1 / EARTH_RADIUS + un * jnp.cos(am)
        nu = jnp.stack([p["nu1"] + p["D11"] * w1, p["nu2"] + p["D22"] * w2, p["nu3"]])
        w_rel = jnp.stack([w1, w2, 0.0]) + nu - c @ jnp.stack([0.0, un, uv])
        f = c @ jnp.stack([0.0, 0.0, COND.g])
        dv = f[:2] + jnp.stack([p["df1"], p["df2"]]) + jnp.stack([p["K11"], p["K22"]]) * f[:2]
        return jnp.concatenate([(-skew(w_rel) @ c).ravel(), dv, uv[None]])

    x0 = RIG.initial_state(p, COND)
    y0 = jnp.concatenate([platform_matrix(x0[0], x0[1], x0[2]).ravel(), x0[3:]])
    sol = diffrax.diffeqsolve(diffrax.ODETerm(dcm_field), diffrax.Dopri8(), 0.0, T, None, y0,
                              saveat=diffrax.SaveAt(ts=ts),
                              stepsize_controller=diffrax.PIDController(rtol=1e-11, atol=1e-13),
                              max_steps=100_000)
    c_dcm = np.asarray(sol.ys[:, :9]).reshape(-1, 3, 3)
    c_euler = np.asarray(jax.vmap(platform_matrix)(x[:, 0], x[:, 1], x[:, 2]))
    assert np.max(np.abs(c_dcm - c_euler)) < 1e-9
    assert np.max(np.abs(np.asarray(sol.ys[:, 9:11]) - x[:, 3:5])) < 1e-5


def test_initial_tilt_response_is_the_analytic_schuler_oscillation():
    """From rest with a small initial tilt: V1 = -sqrt(g a_R) alpha20 sin(omega0 t) and
    V2 = +sqrt(g a_R) alpha10 sin(omega0 t) (the signs the source's correction 4 states)."""
    cond = SchulerConditions.create(v10=0.0, v20=0.0)
    p = RIG.param_space.make({"alpha10": 2e-5, "alpha20": 1e-4})
    ts = jnp.linspace(0.0, T, 101)
    y = np.asarray(integrate(RIG, p, cond, ts))
    root = float(jnp.sqrt(cond.g * EARTH_RADIUS))
    s = np.sin(float(cond.schuler_frequency) * np.asarray(ts))
    np.testing.assert_allclose(y[:, 0], -root * 1e-4 * s, atol=2e-3 * root * 1e-4)
    np.testing.assert_allclose(y[:, 1], root * 2e-5 * s, atol=2e-3 * root * 1e-4)


def test_nonlinear_model_departs_from_zero_order_solution_as_the_spec_states():
    """docs/rigs/schuler.md, error-free model over 4 periods: departure from (S9) up to 2.4 m/s and 0.3 mrad;
    azimuth error A' - A_z oscillating with amplitude up to 7 arcmin."""
    ts = jnp.arange(0.0, 4 * T, 10.0)
    x = _states(RIG.param_space.make({}), COND, ts)
    a1, a2, _, v1, v2 = (np.asarray(v) for v in schuler_solution(COND, ts))
    dv = max(np.max(np.abs(x[:, 3] - v1)), np.max(np.abs(x[:, 4] - v2)))
    da = max(np.max(np.abs(x[:, 0] - a1)), np.max(np.abs(x[:, 1] - a2)))
    assert dv == pytest.approx(2.4, abs=0.1)
    assert da == pytest.approx(0.3e-3, abs=0.02e-3)
    assert np.max(np.abs(x[:, 5] - x[:, 2])) / units.ARCMIN == pytest.approx(7.0, abs=0.3)


def test_schuler_period_pass_fail_check():
    """docs/rigs/schuler.md item 3: a sinusoid fit to the error-free model velocities over 4 periods gives
    84.34 min (V1') and 84.33 min (V2'), within 0.06 % of 2 pi sqrt(a_R/g) = 84.368 min."""
    ts = np.arange(0.0, 4 * T, 10.0)
    y = np.asarray(integrate(RIG, RIG.param_space.make({}), COND, jnp.asarray(ts)))
    r1 = schuler_period(ts, y[:, 0], conditions=COND)
    r2 = schuler_period(ts, y[:, 1], conditions=COND)
    assert r1["period_min"] == pytest.approx(84.34, abs=0.005)
    assert r2["period_min"] == pytest.approx(84.33, abs=0.005)
    assert r1["theoretical_min"] == pytest.approx(84.368, abs=0.001)
    assert abs(r1["relative_difference"]) < 6e-4 and abs(r2["relative_difference"]) < 6e-4
    blind = schuler_period(ts, y[:, 0])  # started from the spectral peak, no theory given
    assert blind["period_min"] == pytest.approx(r1["period_min"], abs=1e-6)
    # the scale errors shift the period by about (K + D) / 2 (docs/rigs/schuler.md)
    p = RIG.param_space.make({"K11": 1e-2, "D22": 1e-2})
    y = np.asarray(integrate(RIG, p, COND, jnp.asarray(ts)))
    shifted = schuler_period(ts, y[:, 0], conditions=COND)
    assert shifted["period_s"] / r1["period_s"] - 1 == pytest.approx(-1e-2, rel=0.05)


def test_bad_input_and_measurement_channels():
    ts = np.arange(0.0, 0.4 * T, 10.0)
    with pytest.raises(ValueError, match="less than half a Schuler period"):
        schuler_period(ts, np.cos(ts / 800), conditions=COND)
    with pytest.raises(ValueError, match="strictly increasing"):
        schuler_period(ts[::-1], np.cos(ts / 800))
    with pytest.raises(ValueError, match="must be equal 1-D"):
        schuler_period(ts, np.zeros(3))
    with pytest.raises(ValueError, match="latitude 95"):
        SchulerConditions.create(95.0)
    p = RIG.param_space.make(TYPICAL, display=True)
    y = np.asarray(integrate(RIG, p, COND, jnp.array([0.0, 600.0])))
    assert RIG.channels == ("V1", "V2", "rot1", "rot2", "rot3")
    np.testing.assert_allclose(y[0], [200.0, -200.0, 0.0, 0.0, 0.0], atol=1e-12)
    assert np.linalg.norm(y[1, 2:]) > 1e-3  # the platform has turned since t0


def test_error_matrix_matches_the_explicit_table():
    """The autodiff A(t) against the explicit entries of docs/rigs/schuler.md (first order in the reference
    tilts) at tau = T/8 on the zero-order solution, columns scaled by typical state sizes; the
    exact and explicit rows differ only at second order in alpha^0 (~6e-4)."""
    tau = T / 8
    a1, a2, am, v1, v2 = (float(v) for v in schuler_solution(COND, tau))
    x_ref = jnp.array([a1, a2, am, v1, v2, am])
    a = np.asarray(error_matrix(RIG, RIG.param_space.make({}), COND, x_ref))
    assert a.shape == (17, 17) and not np.any(a[5:])
    un = EARTH_RATE_SOURCE * np.cos(float(COND.latitude))
    g = float(COND.g)
    w1 = -v2 / EARTH_RADIUS - un * np.sin(am)
    ix = {n: i for i, n in enumerate(ERROR_STATES)}
    table = {
        "dalpha1": {"dV2": -1 / EARTH_RADIUS, "dA": -un * np.cos(am), "nu1": 1.0, "D11": w1,
                    "dalpha2": -w1 * a2, "nu3": a2},
        "dV1": {"dalpha2": -g, "df1": 1.0, "K11": -g * a2},
        "dV2": {"dalpha1": g, "df2": 1.0, "K22": g * a1},
        "dA": {"dalpha1": un * np.cos(am), "dalpha2": -w1, "dV2": a2 / EARTH_RADIUS, "nu3": 1.0,
               "dA": un * np.sin(am) * a1, "nu1": -a2, "D11": -w1 * a2},
    }
    scale = np.array([1e-3, 1e-3, 1.0, 1.0, 1e-2] + [RIG.param_space[n].scale for n in PARAM_NAMES])
    for row, entries in table.items():
        expected = np.zeros(17)
        for col, val in entries.items():
            expected[ix[col]] = val
        got = a[ix[row]] * scale
        np.testing.assert_allclose(got, expected * scale, rtol=0,
                                   atol=2e-3 * np.max(np.abs(expected * scale)))


@pytest.mark.parametrize("periods,factor,bound", [(1, 1.0, 0.23), (4, 1.0, 0.55), (1, 0.1, 0.0023)])
def test_exact_error_model_matches_nonlinear_model_to_second_order(periods, factor, bound):
    """docs/rigs/schuler.md table, 'exact Jacobian along the nonlinear reference', typical error set: the
    linear model's velocity errors differ from the nonlinear model's by 0.22 m/s (1 period) and 0.53 m/s
    (4 periods) out of signals up to 33 m/s; with the errors scaled by 0.1 the difference falls
    100x (second order)."""
    p = RIG.param_space.make({k: v * factor for k, v in TYPICAL.items()}, display=True)
    ts = jnp.linspace(0.0, periods * T, 400 * periods + 1)
    x_ref, e = (np.asarray(v) for v in propagate_error_model(RIG, COND, p, ts))
    x = _states(p, COND, ts)
    diff = np.max(np.abs(e[:, 2:4] - (x[:, 3:5] - x_ref[:, 3:5])))
    assert 0.9 * bound < diff < bound
    # the azimuth error too (states: A' - A_z)
    da = (x[:, 5] - x[:, 2]) - (x_ref[:, 5] - x_ref[:, 2])
    assert np.max(np.abs(e[:, 4] - da)) < 0.05 * factor**2 * units.ARCMIN


@pytest.mark.slow  # ~27 s: a forward-mode Jacobian and central differences of the error model
def test_smooth_drift_step_sensitivity_equals_central_difference():
    """The diagnosis screens the drift step by its forward sensitivity at zero amplitude, where
    the primal does not move and the step-size control, left to itself, strides over the 60-s
    tanh rise: the whitened signature was 7e-4 of its norm off on this record. The rig's
    ``step_times`` make the solver step through the rise: against central differences at the
    prior scale (the primal sees the step; tight tolerances) it is now ~2e-7 off."""
    from gyrojax.estimate.least_squares import trajectory_jacobian

    rig, cond = SchulerRig(), SchulerConditions.create()
    sp = rig.param_space
    period = float(cond.schuler_period)
    ts = jnp.asarray(np.arange(0.0, period, 20.0))
    w = 1 / np.array([0.05, 0.05, units.ARCMIN, units.ARCMIN, units.ARCMIN])  # docs/rigs/schuler.md noise
    q = sp.make() | {"t_step": jnp.asarray(0.4 * period + 3.7)}
    for name in ("nustep1", "nustep3"):
        d = sp[name].scale
        jac = np.asarray(trajectory_jacobian(rig, q, cond, ts, (name,)))[:, 0].reshape(-1, 5)
        up, down = (np.asarray(integrate(rig, q | {name: jnp.asarray(s)}, cond, ts, rtol=1e-12,
                                         atol=1e-14)) for s in (d, -d))
        fd = (up - down) / (2 * d)
        assert np.linalg.norm((jac - fd) * w) < 1e-5 * np.linalg.norm(fd * w), name
