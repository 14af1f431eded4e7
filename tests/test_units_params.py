import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gyrojax import rotations, units
from gyrojax.models.esg import ESGRig


def test_unit_constants():
    assert units.EARTH_RATE_DEG_PER_HOUR == pytest.approx(15.0411, abs=1e-4)
    assert units.ARCMIN == pytest.approx(2.909e-4, rel=1e-3)
    assert units.ARCSEC == pytest.approx(4.848e-6, rel=1e-3)
    assert units.to_unit(units.from_unit(3.5, "deg/h"), "deg/h") == pytest.approx(3.5)
    with pytest.raises(ValueError, match="unknown unit"):
        units.to_unit(1.0, "furlong")


def test_rotations_orthonormal_and_rodrigues_matches_expm():
    v = jnp.array([0.3, -0.2, 0.5])
    r = rotations.rotvec_to_matrix(v)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(r, jax.scipy.linalg.expm(rotations.skew(v)), atol=1e-13)
    # small-angle branch agrees with the series
    w = jnp.array([1e-6, -2e-6, 3e-6])
    np.testing.assert_allclose(rotations.rotvec_to_matrix(w), np.eye(3) + rotations.skew(w),
                               atol=1e-11)


@pytest.mark.parametrize("scheme,expected", [("polar", (1.563, 1, 0.827)),
                                             ("equatorial", (1.827, 1, 0.563)),
                                             ("horizontal", (2, 1, 0)), ("vertical", (1, 1, 1))])
def test_euler_increment_jacobian_spec_values(scheme, expected):
    """Spec §3.5: Euler increments (1,1,1) give these rotation vectors; checked against the
    matrix logarithm of C(chi)^T C(chi + d) by finite differences."""
    from gyrojax.models.esg import scheme_angles

    chi = scheme_angles(scheme, 55.75 * units.DEG)
    got = rotations.euler321_increment_to_rotvec(chi, jnp.ones(3))
    np.testing.assert_allclose(got, expected, atol=1e-3)
    h = 1e-6
    c0 = rotations.euler321_to_matrix(chi)
    d = c0.T @ rotations.euler321_to_matrix(chi + h * jnp.ones(3))
    fd = jnp.array([d[2, 1] - d[1, 2], d[0, 2] - d[2, 0], d[1, 0] - d[0, 1]]) / (2 * h)
    np.testing.assert_allclose(got, fd, atol=1e-5)


def test_param_space_flatten_unflatten_and_errors():
    sp = ESGRig().param_space
    p = sp.make({"m11": 0.15, "theta1": 600.0}, display=True)
    assert float(p["m11"]) == pytest.approx(0.15 / 15.0410686, rel=1e-6)
    assert float(p["theta1"]) == pytest.approx(10 * units.ARCMIN)
    free = ("m11", "theta1")
    x = sp.flatten(p, free)
    np.testing.assert_allclose(x, [p["m11"] / 0.01, 1.0])
    back = sp.unflatten(x * 2, p, free)
    assert float(back["theta1"]) == pytest.approx(20 * units.ARCMIN)
    assert float(back["m12"]) == 0.0
    assert sp.effects == ("rotor_tilt", "base_misalignment", "drift_transient", "drift_ramp",
                          "drift_step")
    assert sp.free_names(("rotor_tilt",))[-2:] == ("theta1", "theta2")
    with pytest.raises(ValueError, match="unknown parameter name"):
        sp.make({"m13": 1.0})
    with pytest.raises(ValueError, match="unknown effect 'tilt'"):
        sp.effect_names("tilt")
    # null values switch every effect off
    assert all(float(sp.null_values()[n]) == 0.0 for n in sp.effect_names("rotor_tilt"))
