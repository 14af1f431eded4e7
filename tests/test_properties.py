"""Property-based checks (hypothesis) of the frame and parameter machinery."""

import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from gyrojax import rotations
from gyrojax.models.esg import ESGRig

angles = st.floats(-3.0, 3.0, allow_nan=False)


@settings(max_examples=40, deadline=None)
@given(angles, angles, angles)
def test_rotvec_matrix_is_a_rotation_and_inverts(a, b, c):
    v = jnp.array([a, b, c]) / 2
    r = rotations.rotvec_to_matrix(v)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert float(jnp.linalg.det(r)) > 0
    np.testing.assert_allclose(r @ rotations.rotvec_to_matrix(-v), np.eye(3), atol=1e-12)
    np.testing.assert_allclose(r @ v, v, atol=1e-12)  # the axis is fixed


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=4, max_size=4))
def test_flatten_unflatten_roundtrip(xs):
    sp = ESGRig().param_space
    free = ("m11", "theta2", "eps2", "k_tr")
    base = sp.make()
    p = sp.unflatten(jnp.array(xs), base, free)
    np.testing.assert_allclose(sp.flatten(p, free), xs, rtol=1e-12, atol=1e-12)
    for n in sp.names:
        if n not in free:
            assert float(p[n]) == float(base[n])


def test_sincos_matches_libm_to_one_ulp_and_differentiates():
    """``rotations.sincos`` (the polynomial float64 sine and cosine of the ESG hot paths) against
    numpy's libm on 400,000 seeded points from 1e-3 to 1e6 rad, the quadrant boundaries and
    special points; its derivatives against the analytic cos / -sin."""
    import jax

    rng = np.random.default_rng(7)
    x = np.concatenate([rng.uniform(-lim, lim, 100_000) for lim in (1e-3, 4.0, 1e3, 1e6)]
                       + [np.arange(-40, 41) * np.pi / 4, [0.0, -0.0, 1e-300, np.pi / 2]])
    s, c = jax.jit(rotations.sincos)(x)
    s, c = np.asarray(s), np.asarray(c)
    # absolute error in units of ulp(1) (|sin|, |cos| <= 1) and relative error near zero
    assert np.max(np.abs(s - np.sin(x))) <= 1.1 * np.spacing(1.0)
    assert np.max(np.abs(c - np.cos(x))) <= 1.1 * np.spacing(1.0)
    small = np.abs(x) < 1.5  # no range reduction error: relative accuracy as libm's
    assert np.max(np.abs(s - np.sin(x))[small] / np.spacing(np.abs(np.sin(x[small])))) <= 2.0
    assert np.all(s[x == 0.0] == 0.0) and np.all(c[x == 0.0] == 1.0)
    xs = jnp.linspace(-7.0, 7.0, 29)
    ds = jax.vmap(jax.grad(lambda t: rotations.sincos(t)[0]))(xs)
    dc = jax.vmap(jax.grad(lambda t: rotations.sincos(t)[1]))(xs)
    d2s = jax.vmap(jax.grad(jax.grad(lambda t: rotations.sincos(t)[0])))(xs)
    np.testing.assert_allclose(ds, np.cos(xs), atol=1e-15)
    np.testing.assert_allclose(dc, -np.sin(xs), atol=1e-15)
    np.testing.assert_allclose(d2s, -np.sin(xs), atol=1e-15)
    # other dtypes take jnp.sin / jnp.cos
    s32, _ = rotations.sincos(jnp.float32(0.5))
    assert s32.dtype == jnp.float32 and abs(float(s32) - np.sin(0.5)) < 1e-7


def test_polynomial_log_matches_libm_to_one_ulp():
    """``simulate._log`` (the polynomial float64 logarithm of ``gaussian_noise``) against numpy's
    libm on 1,000,000 seeded uniforms in (0, 1] (its inputs there), every power of two down to
    2**-1022, points beside sqrt(2) (where the mantissa folds) and values above 1."""
    import jax

    from gyrojax.simulate import _log

    rng = np.random.default_rng(13)
    r2 = np.sqrt(2.0)
    x = np.concatenate([1.0 - rng.uniform(0.0, 1.0, 1_000_000), 2.0 ** -np.arange(0.0, 1023.0),
                        [r2, np.nextafter(r2, 0.0), np.nextafter(r2, 2.0), 1 - 2**-53, 1e300],
                        rng.uniform(1.0, 1e6, 10_000)])
    y = np.asarray(jax.jit(_log)(x))
    ref = np.log(x)
    assert y[x == 1.0][0] == 0.0
    assert np.max(np.abs(y - ref) / np.spacing(np.abs(ref) + (ref == 0))) <= 1.0


def test_gaussian_noise_is_standard_normal():
    """``simulate.gaussian_noise`` (Box-Muller) on 2,000,001 seeded deviates: mean, standard
    deviation, kurtosis and the 3-sigma tail within ~4 Monte Carlo standard errors of N(0, 1), a
    Kolmogorov-Smirnov test, the two halves of each pair uncorrelated, and the shape and scale."""
    import jax
    from scipy import stats

    from gyrojax.simulate import gaussian_noise

    n = 2_000_001
    z = np.asarray(gaussian_noise(jax.random.key(11), (n,)))
    se = 1 / np.sqrt(n)
    assert abs(z.mean()) < 4 * se
    assert abs(z.std() - 1) < 4 * se / np.sqrt(2)
    assert abs(stats.kurtosis(z)) < 4 * np.sqrt(24 / n)
    tail = 2 * stats.norm.sf(3)
    assert abs(np.mean(np.abs(z) > 3) - tail) < 4 * np.sqrt(tail / n)
    assert stats.kstest(z[:200_000], "norm").pvalue > 1e-3
    half = n // 2  # the cos and sin deviates of one pair
    assert abs(np.corrcoef(z[:half], z[half : 2 * half])[0, 1]) < 4 / np.sqrt(half)
    assert abs(np.corrcoef(z[:half] ** 2, z[half : 2 * half] ** 2)[0, 1]) < 4 / np.sqrt(half)
    y = np.asarray(gaussian_noise(jax.random.key(1), (1441, 2), std=2.5))
    assert y.shape == (1441, 2) and y.dtype == np.float64 and abs(y.std() / 2.5 - 1) < 0.05


def test_unrolled_threefry_uniforms_equal_jax_random_uniform():
    """``simulate._uniform64`` (the threefry-2x32 hash unrolled) against jaxlib's own
    ``jax.random.uniform`` on the same keys: bit-identical float64 values for odd, even, 1-D and
    2-D shapes, under jit and vmap over keys; other key implementations fall back to jax."""
    import jax

    from gyrojax.simulate import _uniform64

    keys = jax.random.split(jax.random.key(2024), 5)
    for shape in [(1,), (7,), (2, 1441), (3, 4, 5)]:
        ours = jax.jit(jax.vmap(lambda k, s=shape: _uniform64(k, s)))(keys)
        ref = jax.vmap(lambda k, s=shape: jax.random.uniform(k, s, dtype=jnp.float64))(keys)
        np.testing.assert_array_equal(np.asarray(ours), np.asarray(ref))
    for key in [jax.random.key(3, impl="rbg"), jax.random.PRNGKey(3)]:
        np.testing.assert_array_equal(
            np.asarray(_uniform64(key, (9,))),
            np.asarray(jax.random.uniform(key, (9,), dtype=jnp.float64)))
