"""Schuler-test observability against docs/rigs/schuler.md: Cramer-Rao bounds at half a period
and at four periods, the weakly separable pairs with their correlations, and the velocity-only
(classical) test's weakest directions."""

import numpy as np
import pytest

from gyrojax.analysis.schuler import schuler_observability
from gyrojax.models.schuler import PARAM_NAMES, SchulerConditions, SchulerRig

RIG = SchulerRig()
COND = SchulerConditions.create()
T = float(COND.schuler_period)
SPACE = RIG.param_space

# docs/rigs/schuler.md CRLB table (deg/h, ppm = 1e-6 of the scale errors, m/s^2, arcmin)
CRLB = {0.5: [0.067, 0.011, 0.0016, 480, 800, 1.0e-3, 1.0e-3, 510, 510, 0.36, 0.36, 27],
        4: [7.6e-5, 1.4e-4, 4.1e-5, 6.0, 15, 2.9e-5, 2.9e-5, 16, 6.1, 0.010, 0.010, 0.029]}


def _display(name, value):
    return float(SPACE[name].to_display(value))


@pytest.mark.parametrize("periods", [0.5, pytest.param(4, marks=pytest.mark.slow)])  # 4: ~17 s
def test_cramer_rao_bounds_and_weak_pairs(periods):
    ob = schuler_observability(RIG, COND, periods * T)
    assert ob.rank == 12  # full rank from half a period on
    got = [_display(n, s) for n, s in zip(PARAM_NAMES, ob.crlb, strict=True)]
    np.testing.assert_allclose(got, CRLB[periods], rtol=0.1)
    corr = {frozenset((a, b)): c for a, b, c in ob.weak_pairs(0.9)}
    assert corr[frozenset(("alpha10", "df2"))] == pytest.approx(-1.0, abs=2e-3)
    assert corr[frozenset(("alpha20", "df1"))] == pytest.approx(1.0, abs=2e-3)
    assert corr[frozenset(("D11", "K22"))] == pytest.approx(-0.99, abs=0.01)
    assert 0.98 <= corr[frozenset(("nu1", "dA0"))] <= 1.0
    if periods >= 1:
        assert corr[frozenset(("D22", "K11"))] == pytest.approx(-0.999, abs=2e-3)


def test_velocity_only_test_leaves_two_directions_to_the_prior():
    """docs/rigs/schuler.md: with the velocities alone, at one period the directions alpha10/df2 and K11/D22
    carry Fisher information 0.03 and 0.1 (prior units: less than the prior), alpha20/df1 1.7."""
    ob = schuler_observability(RIG, COND, T, channels="velocity")
    weakest = ob.weakest_directions(3)
    np.testing.assert_allclose([w for w, _ in weakest], [0.03, 0.10, 1.7], rtol=0.15)
    assert "alpha10" in weakest[0][1] and "df2" in weakest[0][1]
    assert "D22" in weakest[1][1] and "K11" in weakest[1][1]
    full = schuler_observability(RIG, COND, T)
    assert np.all(full.crlb <= ob.crlb)
    with pytest.raises(ValueError, match="channels='gyro'"):
        schuler_observability(RIG, COND, T, channels="gyro")
