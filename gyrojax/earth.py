"""Earth rate and gravity in the local geographic frame.

Frame convention (used throughout gyrojax): the geographic frame ``eta`` is East-North-Up (ENU).
``vec_eta`` is a vector in ENU components. Latitude ``phi`` in rad, positive North.
"""

from __future__ import annotations

import jax.numpy as jnp

from .units import EARTH_RATE, G0

__all__ = ["EARTH_RATE", "G0", "GRAVITY_RANGE", "earth_rate_unit_enu", "gravity_unit_enu",
           "earth_rate_enu", "normal_gravity", "check_gravity"]

GRAVITY_RANGE = (9.70, 9.90)
"""Local gravity a bench can see (m/s^2): 9.764 on Huascaran's summit to 9.834 at the poles."""


def check_gravity(g: float, field: str) -> None:
    """Refuse a local gravity ``g`` (m/s^2) outside :data:`GRAVITY_RANGE`, naming ``field``: a
    value in g (1.0) or mm/s^2 would scale every accelerometer term, or the Schuler period, by
    itself."""
    g = float(g)
    if not GRAVITY_RANGE[0] <= g <= GRAVITY_RANGE[1]:
        raise ValueError(f"gravity {g:g} m/s^2 ({field}) is outside {GRAVITY_RANGE[0]}-"
                         f"{GRAVITY_RANGE[1]} m/s^2, the Earth's surface gravity at any latitude "
                         "and height; give it in m/s^2 (1 g = 9.80665 m/s^2), or leave it out "
                         "for normal gravity at the latitude")


def earth_rate_unit_enu(latitude):
    """Unit vector of Earth's rotation axis in ENU: $u_\\eta = (0, \\cos\\varphi, \\sin\\varphi)$."""
    latitude = jnp.asarray(latitude)
    return jnp.stack([jnp.zeros_like(latitude), jnp.cos(latitude), jnp.sin(latitude)], axis=-1)


def earth_rate_enu(latitude):
    """Earth-rate vector in ENU, rad/s."""
    return EARTH_RATE * earth_rate_unit_enu(latitude)


def gravity_unit_enu(latitude=None):
    """Unit gravity vector in ENU (gravity points down): $g_\\eta = (0, 0, -1)$."""
    del latitude
    return jnp.array([0.0, 0.0, -1.0])


def normal_gravity(latitude, height=0.0):
    """Magnitude of normal gravity (Somigliana, WGS-84) in m/s^2 with a free-air height correction."""
    s2 = jnp.sin(latitude) ** 2
    g = 9.7803253359 * (1 + 0.00193185265241 * s2) / jnp.sqrt(1 - 0.00669437999013 * s2)
    return g - 3.086e-6 * height
