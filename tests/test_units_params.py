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


def test_every_display_unit_is_its_si_value_derived_by_hand():
    """Each display unit's SI value written out from its definition (pi / 180 rad per degree,
    3600 s per hour, g = 9.80665 m/s^2, a temperature rate per minute), not from the module's
    constants; a unit added to the table must be added here."""
    import math

    deg, h, g = math.pi / 180, 3600.0, 9.80665
    si = {"1": 1.0, "rad": 1.0, "deg": deg, "arcmin": deg / 60, "arcsec": deg / 3600,
          "rad/s": 1.0, "deg/h": deg / h, "1/s": 1.0, "1/h": 1 / h, "s": 1.0, "h": h,
          "m/s^2": 1.0, "g": g, "ppm": 1e-6, "deg/s": deg, "mrad": 1e-3, "mg": 1e-3 * g,
          "mg/h": 1e-3 * g / h,  # (m/s^2) / s
          "deg/h/h": deg / h / h, "deg/h/g": deg / h / g,  # (rad/s) / (m/s^2) = s/m
          "deg/h/degC": deg / h,  # rad/s per K
          "mg/degC": 1e-3 * g,
          "deg/h/(degC/min)": (deg / h) / (1 / 60),  # (rad/s) / (K/s) = rad/K
          "mg/(degC/min)": 1e-3 * g / (1 / 60),
          "deg/sqrt(h)": deg / math.sqrt(h),  # angle random walk: rad/sqrt(s)
          "deg/h/sqrt(h)": deg / h / math.sqrt(h),  # rate random walk: rad/s/sqrt(s)
          "m/s/sqrt(h)": 1 / math.sqrt(h), "m/s^2/sqrt(s)": 1.0,
          "mg/sqrt(h)": 1e-3 * g / math.sqrt(h), "m/s": 1.0, "min": 60.0,
          "arcsec/s": deg / 3600, "nN m": 1e-9, "nN m/h": 1e-9 / h}
    assert set(units.known_units()) == set(si)
    for name, value in si.items():
        assert units.from_unit(1.0, name) == pytest.approx(value, rel=1e-14), name
        assert units.to_unit(value, name) == pytest.approx(1.0, rel=1e-14), name


def test_normal_gravity_matches_wgs84_defining_constants_and_free_air_gradient():
    """Somigliana's normal gravity rebuilt from WGS-84's defining and derived constants (NIMA
    TR8350.2: a, 1/f, equatorial and polar normal gravity), not from the code's two derived
    coefficients; and the standard free-air gradient 0.3086 mGal/m. Schuler's and the IMU's g
    come from it."""
    from gyrojax.earth import normal_gravity

    a, f = 6378137.0, 1 / 298.257223563
    b, e2 = a * (1 - f), f * (2 - f)
    g_eq, g_pole = 9.7803253359, 9.8321849378
    k = b * g_pole / (a * g_eq) - 1
    lat = np.radians([-90.0, -30.0, 0.0, 45.0, 51.0784, 90.0])
    s2 = np.sin(lat) ** 2
    want = g_eq * (1 + k * s2) / np.sqrt(1 - e2 * s2)
    np.testing.assert_allclose(np.asarray(normal_gravity(lat)), want, rtol=0, atol=1e-10)
    assert float(normal_gravity(np.radians(90.0))) == pytest.approx(g_pole, abs=1e-9)
    drop = float(normal_gravity(lat[3]) - normal_gravity(lat[3], 1000.0))
    assert drop == pytest.approx(0.3086e-5 * 1000.0, rel=1e-9)  # 308.6 mGal lower at 1 km


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
    """docs/diagnosis.md: Euler increments (1,1,1) give these rotation vectors; checked against the
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


def test_sample_noise_reads_the_white_level_past_a_smooth_signal():
    """``record.sample_noise``: third differences of white noise have variance 20 sigma^2, and a
    smooth signal (a Schuler oscillation of 200 m/s at 1 s, an Earth-rate ramp) adds nothing
    visible; a record with too few samples is refused."""
    from gyrojax.record import sample_noise

    rng = np.random.default_rng(5)
    t = np.arange(20_000.0)
    sigma = np.array([0.05, 3e-4])
    smooth = np.column_stack([200 * np.cos(2 * np.pi * t / 5063.0), 7.3e-5 * t])
    level = sample_noise(smooth + sigma * rng.standard_normal((t.size, 2)))
    # the estimate's relative sd: sqrt(var(d3^2)) / (20 sqrt(n)) ~ 0.9 % here (d3 is MA(3))
    np.testing.assert_allclose(level, sigma, rtol=0.04)
    assert np.all(sample_noise(smooth) < 1e-3 * sigma)
    with pytest.raises(ValueError, match="at least 4"):
        sample_noise(np.zeros((3, 2)))


def test_gravity_outside_the_earths_range_is_refused_by_name():
    """Local gravity is 9.76-9.84 m/s^2 anywhere a bench stands (normal gravity at the equator and
    the pole, Huascaran's summit 9.764); a record giving it in g or mm/s^2 is refused where the
    rig's conditions are built, naming the record's field."""
    from gyrojax.earth import GRAVITY_RANGE, check_gravity, normal_gravity
    from gyrojax.models.imu import IMUConditions
    from gyrojax.models.schuler import SchulerConditions

    for lat in (0.0, 90.0):
        g = float(normal_gravity(np.radians(lat)))
        assert GRAVITY_RANGE[0] < g < GRAVITY_RANGE[1]
        check_gravity(g, "x")
    assert normal_gravity(0.0) == pytest.approx(9.7803, abs=1e-4)
    assert normal_gravity(np.pi / 2) == pytest.approx(9.8322, abs=1e-4)
    for bad in (1.0, 9806.65, 0.0, float("nan")):
        with pytest.raises(ValueError, match=r"the record's gravity_mps2\) is outside 9.7-9.9"):
            IMUConditions(gravity=bad)
        with pytest.raises(ValueError, match=r"the record's g\) is outside 9.7-9.9 m/s\^2"):
            SchulerConditions.create(g=bad)
