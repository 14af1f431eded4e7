"""Unit constants and conversions: SI inside, engineering units at the edges.

Every constant converts *from* the named unit *to* SI, so ``x_si = x * ARCSEC`` and
``x_arcsec = x_si / ARCSEC``. Angles are in rad, rates in rad/s, accelerations in m/s^2.

The ESG rig works in the normalized time ``tau = U t`` (``U`` = Earth's sidereal rate); a normalized
drift coefficient ``m`` is the drift rate in units of ``U``: ``drift[deg/h] = m * EARTH_RATE_DEG_PER_HOUR``.
"""

from __future__ import annotations

import math

DEG = math.pi / 180.0
"""One degree in rad."""
ARCMIN = DEG / 60.0
"""One arc-minute in rad (2.909e-4)."""
ARCSEC = DEG / 3600.0
"""One arc-second in rad (4.848e-6)."""
HOUR = 3600.0
"""One hour in s."""
DEG_PER_HOUR = DEG / HOUR
"""One deg/h in rad/s."""
G0 = 9.80665
"""Standard gravity in m/s^2 (the 'g' of instrument specifications)."""
PPM = 1e-6

EARTH_RATE = 7.2921150e-5
"""Earth's sidereal rotation rate U in rad/s (WGS-84)."""
EARTH_RATE_DEG_PER_HOUR = EARTH_RATE / DEG_PER_HOUR
"""U in deg/h (15.0411)."""

# Display units: name -> factor from the internal unit to the display unit (display = internal / factor).
_DISPLAY = {
    "1": 1.0,
    "rad": 1.0,
    "deg": DEG,
    "arcmin": ARCMIN,
    "arcsec": ARCSEC,
    "rad/s": 1.0,
    "deg/h": DEG_PER_HOUR,
    "1/s": 1.0,
    "1/h": 1.0 / HOUR,
    "s": 1.0,
    "h": HOUR,
    "m/s^2": 1.0,
    "g": G0,
    "ppm": PPM,
    "deg/s": DEG,
    "mrad": 1e-3,
    "mg": 1e-3 * G0,
    "mg/h": 1e-3 * G0 / HOUR,
    "deg/h/h": DEG_PER_HOUR / HOUR,
    "deg/h/g": DEG_PER_HOUR / G0,
    "deg/h/degC": DEG_PER_HOUR,
    "mg/degC": 1e-3 * G0,
    "deg/h/(degC/min)": DEG_PER_HOUR * 60.0,
    "mg/(degC/min)": 1e-3 * G0 * 60.0,
    "deg/sqrt(h)": DEG / 60.0,
    "deg/h/sqrt(h)": DEG_PER_HOUR / 60.0,
    "m/s/sqrt(h)": 1.0 / 60.0,
    "m/s^2/sqrt(s)": 1.0,
    "mg/sqrt(h)": 1e-3 * G0 / 60.0,
    "m/s": 1.0,
    "min": 60.0,
    "arcsec/s": ARCSEC,
    "nN m": 1e-9,
    "nN m/h": 1e-9 / HOUR,
}


def to_unit(value, unit: str):
    """Convert an SI value to ``unit`` (e.g. rad -> arcsec)."""
    try:
        return value / _DISPLAY[unit]
    except KeyError:
        raise ValueError(f"unknown unit {unit!r}; known units: {', '.join(_DISPLAY)}") from None


def from_unit(value, unit: str):
    """Convert a value given in ``unit`` to SI (e.g. arcsec -> rad)."""
    try:
        return value * _DISPLAY[unit]
    except KeyError:
        raise ValueError(f"unknown unit {unit!r}; known units: {', '.join(_DISPLAY)}") from None


def known_units() -> tuple[str, ...]:
    return tuple(_DISPLAY)
