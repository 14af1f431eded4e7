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
