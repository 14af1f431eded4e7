"""Shared test helpers: standard test designs of the source papers."""

import jax.numpy as jnp

import gyrojax as gj
from gyrojax import units

DRIFTS = ("m11", "m12", "m21", "m22", "mc1", "mc2")
LAT = 55.75
TS_24H = jnp.arange(0.0, 24 * 3600.0 + 1.0, 60.0)


def design(scheme, base_param="eps", *, drift=0.01, alpha0_deg=(0.0, 0.0), **extra):
    """(rig, conditions, params) for a scheme; ``extra`` in internal units."""
    rig = gj.ESGRig.for_scheme(scheme, LAT, base_param=base_param)
    cond = gj.ESGConditions.from_scheme(scheme, LAT)
    vals = {n: drift for n in DRIFTS} | extra
    p = rig.param_space.make(vals, alpha10=alpha0_deg[0] * units.DEG,
                             alpha20=alpha0_deg[1] * units.DEG)
    return rig, cond, p


def deg_h(x):
    return x * units.EARTH_RATE_DEG_PER_HOUR
