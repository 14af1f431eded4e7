import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import DRIFTS, LAT, design

import gyrojax as gj
from gyrojax import units
from gyrojax.estimate.spiral import spiral_parameters, spiral_trajectory

S = np.sin(np.radians(LAT))
C = np.cos(np.radians(LAT))


@pytest.mark.parametrize("scheme,u,g", [
    ("polar", (0, 0, 1), (-C, 0, -S)), ("equatorial", (1, 0, 0), (-S, 0, -C)),
    ("horizontal", (S, 0, C), (-1, 0, 0)), ("vertical", (0, C, S), (0, 0, -1))])
def test_table1_base_vectors(scheme, u, g):
    cond = gj.ESGConditions.from_scheme(scheme, LAT)
    uz, gz = cond.base_vectors()
    np.testing.assert_allclose(uz, u, atol=1e-15)
    np.testing.assert_allclose(gz, g, atol=1e-15)


@pytest.mark.parametrize("scheme", ["polar", "equatorial", "horizontal", "vertical"])
@pytest.mark.parametrize("base_param", ["eps_free", "eps", "rotvec", "euler"])
def test_regression_terms_equal_autodiff_tangent_of_exact_model(scheme, base_param):
    """The hand-written F (6.7)/(6.10) with the corrected f18 equals d(alpha')/dp of the exact
    model (5.1) at p = 0, and c equals the error-free rate (independent derivation by autodiff)."""
    rig, cond, _ = design(scheme, base_param, drift=0.0)
    sp = rig.param_space
    names = rig.regression_names
    alphas = jax.random.uniform(jax.random.key(3), (5, 2), minval=-1.0, maxval=1.0)
    c, f = rig.regression_terms(alphas, cond)
    p0 = sp.make()

    def rate(x, a):
        return rig.vector_field(0.0, a, sp.unflatten(x, p0, names) , cond)

    x0 = jnp.zeros(len(names))
    for i, a in enumerate(alphas):
        np.testing.assert_allclose(c[i], rate(x0, a), atol=1e-13)
        jac = jax.jacfwd(rate)(x0, a) / sp.scales(names)
        np.testing.assert_allclose(f[i], jac, atol=1e-11, err_msg=f"alpha={a}")


def test_first_order_model_matches_exact_to_second_order():
    """(3.1) is the first-order expansion of (5.1) in the mounting errors: halving the errors
    quarters the difference of the rates (and it is small against the first-order effect)."""
    errs = {"theta1": 10 * units.ARCMIN, "theta2": -7 * units.ARCMIN, "dchi1": units.ARCMIN,
            "dchi2": -2 * units.ARCMIN, "dchi3": 1.5 * units.ARCMIN}
    rig_e = gj.ESGRig(base_param="rotvec")
    rig_1 = gj.ESGRig(base_param="rotvec", order="first")
    cond = gj.ESGConditions.from_scheme("vertical", LAT)
    sp = rig_e.param_space
    a = jnp.array([0.4, -0.3])
    base = sp.make({n: 0.01 for n in DRIFTS})
    diffs = []
    for s in (1.0, 0.5):
        p = base | {k: jnp.asarray(v * s) for k, v in errs.items()}
        d = rig_e.vector_field(0.3, a, p, cond) - rig_1.vector_field(0.3, a, p, cond)
        diffs.append(float(jnp.max(jnp.abs(d))))
    effect = float(jnp.max(jnp.abs(rig_e.vector_field(0.3, a, base | errs, cond)
                                   - rig_e.vector_field(0.3, a, base, cond))))
    # the O(m dchi) gravity term is dropped by (3.1): it is first order in dchi times m
    assert diffs[0] < 0.05 * effect
    assert diffs[1] / diffs[0] == pytest.approx(0.5, abs=0.3) or diffs[1] / diffs[0] < 0.3


def test_first_order_model_exact_when_gravity_term_is_excluded():
    """With m = 0 (no O(m dchi) term) the first-order model differs from the exact one at second
    order only: the ratio for halved errors is 1/4."""
    rig_e = gj.ESGRig(base_param="rotvec")
    rig_1 = gj.ESGRig(base_param="rotvec", order="first")
    cond = gj.ESGConditions.from_scheme("horizontal", LAT)
    sp = rig_e.param_space
    a = jnp.array([0.4, 0.6])
    errs = {"theta1": 10 * units.ARCMIN, "theta2": -7 * units.ARCMIN, "dchi1": 3 * units.ARCMIN,
            "dchi2": -2 * units.ARCMIN, "dchi3": 1.5 * units.ARCMIN}
    d = []
    for s in (1.0, 0.5):
        p = sp.make({k: v * s for k, v in errs.items()})
        d.append(float(jnp.max(jnp.abs(rig_e.vector_field(0.0, a, p, cond)
                                       - rig_1.vector_field(0.0, a, p, cond)))))
    assert d[1] / d[0] == pytest.approx(0.25, abs=0.02)


def _linear_polar_solution(m, lat, alpha0, tau):
    """Exact solution of the small-angle model (4.1) by the matrix exponential."""
    m11, m12, m21, m22, mc1, mc2 = m
    s, c = jnp.sin(lat), jnp.cos(lat)
    s2, c2 = jnp.sin(2 * lat), jnp.cos(2 * lat)
    a = jnp.array([[-(m21 * s - 2 * m22 * s**2), 1 - m11 * s - 2 * m12 * c2],
                   [-(1 - m11 * s + 2 * m12 * s**2), -(m21 * s + 2 * m22 * c2)]])
    b = jnp.array([-mc2 + m11 * c - m12 * s2, mc1 + m21 * c - m22 * s2])
    centre = -jnp.linalg.solve(a, b)
    prop = jax.vmap(lambda t: jax.scipy.linalg.expm(a * t))(tau)
    return centre + prop @ (alpha0 - centre), a


def test_polar_small_angle_model_vs_analytic_spiral():
    """docs/rigs/esg.md: (i) the exact model near the pole follows the linear model (4.1) up to O(alpha^2);
    (ii) (4.1) follows the spiral (4.2)-(4.3) up to O(m r) (the dropped ellipticity); (iii) lambda
    is exact: -lambda is half the trace of the (4.1) matrix."""
    m0 = jnp.array([0.004, 0.003, 0.005, -0.002, 0.003, -0.004])
    lat = LAT * units.DEG
    ts = jnp.arange(0.0, 48 * 3600.0 + 1, 300.0)
    tau = ts * units.EARTH_RATE
    errs = []
    for scale, a0 in ((1.0, 0.2), (0.5, 0.1)):  # alpha ~ m: scale both together
        m = m0 * scale
        ac1, ac2, lam, nu = spiral_parameters(m, lat)
        rig, cond, p = design("polar", drift=0.0, alpha0_deg=(a0, -0.6 * a0))
        p = p | dict(zip(DRIFTS, m))
        alpha0 = jnp.stack([p["alpha10"], p["alpha20"]])
        y = gj.integrate(rig, p, cond, ts)
        ylin, amat = _linear_polar_solution(m, lat, alpha0, tau)
        errs.append(float(jnp.max(jnp.abs(y - ylin))))
        r1, r2 = alpha0[0] - ac1, alpha0[1] - ac2
        r, psi = jnp.hypot(r1, r2), jnp.arctan2(-r2, r1)
        ys = spiral_trajectory(jnp.stack([ac1, ac2, r, lam, nu, psi]), tau)
        # (4.2) vs (4.1): order m r over the run
        assert float(jnp.max(jnp.abs(ylin - ys))) < 3 * float(jnp.max(jnp.abs(m)) * r) * 2
        assert float(-lam) == pytest.approx(float(jnp.trace(amat)) / 2, rel=1e-12)
    # exact vs small-angle model: the neglected terms are O(alpha^3, m alpha^2) near the pole (the
    # quadratic ones cancel in the polar mount), so halving alpha and m divides the error by 8
    assert errs[1] / errs[0] == pytest.approx(0.125, abs=0.03), errs


def test_eps_parametrisation_equals_rotation_vector():
    """eps = u x dchi (normal to u) drives the same motion as the rotation vector dchi = eps x u."""
    rig_eps, cond, p = design("vertical", "eps", eps1=units.ARCMIN, eps2=-2 * units.ARCMIN)
    u, _ = cond.base_vectors()
    eps = rig_eps._eps_vector(p, u)
    assert float(jnp.dot(eps, u)) == pytest.approx(0.0, abs=1e-18)
    dchi = jnp.cross(eps, u)
    rig_rv = gj.ESGRig(base_param="rotvec")
    p_rv = rig_rv.param_space.make({n: 0.01 for n in DRIFTS} | dict(zip(("dchi1", "dchi2", "dchi3"),
                                                                      dchi)))
    a = jnp.array([0.2, 0.1])
    np.testing.assert_allclose(rig_eps.vector_field(0, a, p, cond),
                               rig_rv.vector_field(0, a, p_rv, cond), atol=1e-16)


def test_drift_step_sensitivity_equals_central_difference():
    """The drift step is a jump in the vector field. Its forward sensitivity at zero amplitude
    (the diagnosis' step signature) must equal the central difference in the amplitude (the model
    is linear in it): the solver steps to the onset (``jump_times``), which the step-size
    controller would not do by itself, since the primal sees no jump at zero amplitude (without
    it: 0.3-5 % errors, found through the blind suite's onset localisation)."""
    from gyrojax.estimate.least_squares import trajectory_jacobian

    rig, cond, p = design("vertical", "rotvec")
    ts = jnp.asarray(np.arange(541) * 120.0)  # 18 h
    d = 1e-3 * rig.param_space["smc1"].scale
    for onset_h in (2.0, 10.0):
        q = p | {"t_step": jnp.asarray(onset_h * 3600 * units.EARTH_RATE)}
        jac = np.asarray(trajectory_jacobian(rig, q, cond, ts, ("smc1",)))[:, 0]
        up, down = (np.asarray(gj.integrate(rig, q | {"smc1": jnp.asarray(s)}, cond, ts))
                    for s in (d, -d))
        fd = (up - down).reshape(-1) / (2 * d)
        assert np.abs(fd[: 2 * int(onset_h * 30)]).max() < 1e-9 * np.abs(fd).max()  # none before
        assert np.abs(jac - fd).max() < 1e-5 * np.abs(fd).max(), onset_h


@pytest.mark.slow  # ~25 s: four forward-mode solves of the exact model
def test_vector_transient_and_step_are_sums_of_single_ones():
    """The transient's amplitudes (with ``k_tr``) and the step's sizes (with ``t_step``) may be
    vectors, one transient / step per entry (the diagnosis linearizes at every grid value in
    one solve): an entry alone gives the scalar trajectory at its own decay rate and onset, and
    the solver stops at every onset (two steps at two onsets: each jump within tolerance)."""
    rig, cond, p = design("vertical", "rotvec")
    ts = jnp.asarray(np.arange(361) * 120.0)  # 12 h
    k = jnp.array([1 / 0.5, 1 / 2.0]) / (3600 * units.EARTH_RATE)
    on = jnp.array([3.0, 7.0]) * 3600 * units.EARTH_RATE
    a, b = 0.02, 0.01  # internal units: large enough to move the trajectory by arcminutes
    vec = p | {"k_tr": k, "dmc1_0": jnp.array([0.0, a]), "t_step": on,
               "smc2": jnp.array([b, 0.0])}
    one = p | {"k_tr": k[1], "dmc1_0": jnp.asarray(a), "t_step": on[0], "smc2": jnp.asarray(b)}
    y_vec, y_one = (np.asarray(gj.integrate(rig, q, cond, ts)) for q in (vec, one))
    base = np.asarray(gj.integrate(rig, p, cond, ts))
    assert np.abs(y_one - base).max() > 1e-3  # the effects are there
    # rad: both at rtol 1e-10 on angles of ~1 rad, on different step sequences (the vector
    # solve also stops at the 7 h onset); the effect is ~1e-2 rad
    assert np.abs(y_vec - y_one).max() < 1e-8
    # two steps, the second undoing the first at 7 h (a pulse), small enough for the model to
    # be linear in them: the sum of the two single steps' effects
    c = b / 100
    pulse = np.asarray(gj.integrate(rig, p | {"t_step": on, "smc2": jnp.array([c, -c])}, cond,
                                    ts)) - base
    single = [np.asarray(gj.integrate(rig, p | {"t_step": o, "smc2": jnp.asarray(x)}, cond, ts))
              - base for o, x in ((on[0], c), (on[1], -c))]
    assert np.abs(pulse[ts <= on[0] / units.EARTH_RATE]).max() < 1e-9  # nothing before
    assert np.abs(pulse - single[0] - single[1]).max() < 1e-3 * np.abs(pulse).max()


def test_bad_rig_configuration():
    with pytest.raises(ValueError, match="base_param='quat'"):
        gj.ESGRig(base_param="quat")
    with pytest.raises(ValueError, match="unknown mounting scheme 'diagonal'"):
        gj.ESGConditions.from_scheme("diagonal", LAT)
    with pytest.raises(ValueError, match="latitude 95"):
        gj.ESGConditions.from_scheme("polar", 95)
