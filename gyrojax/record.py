"""The BenchRecord data contract: sample times, measured channels, test conditions.

A record is an ``equinox.Module`` so a stack of records (leading batch axes on ``t`` and ``y``)
passes through ``vmap`` and ``jit``. Conditions (latitude, mounting scheme, ...) are static
metadata, stored as a sorted tuple of ``(key, value)`` pairs so that records are hashable.
"""

from __future__ import annotations

from collections.abc import Mapping

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

MAX_SAMPLES = 10_000_000  # ~160 MB per two-channel float64 record


def sample_times(span_s: float, sample_s: float, *, span: str = "the test length",
                 sample: str = "the sampling interval") -> np.ndarray:
    """Uniform sample times ``0, sample_s, ...`` up to ``span_s`` (inclusive, to half a sample),
    refusing a test the machine could not hold (more than :data:`MAX_SAMPLES` samples) or one
    too short to fit (fewer than 3). ``span`` / ``sample`` name the options that set them,
    with their values as given (``"--hours 24"``, ``"--sample 60"``)."""
    if not (np.isfinite(span_s) and span_s > 0 and np.isfinite(sample_s) and sample_s > 0):
        raise ValueError(f"{span} and {sample} must be positive numbers (test length "
                         f"{span_s} s, sampling interval {sample_s} s)")
    n = int(span_s / sample_s + 0.5) + 1
    if n > MAX_SAMPLES:
        raise ValueError(f"{span} with {sample} s gives {n:.3g} samples "
                         f"(~{n * 16 / 1e9:.3g} GB per two channels); a simulated record holds at "
                         f"most {MAX_SAMPLES:,}: shorten the test or lengthen the sampling "
                         "interval")
    ts = np.arange(0.0, span_s + 0.5 * sample_s, sample_s)
    if ts.size < 3:
        raise ValueError(f"{span} with {sample} s gives {ts.size} samples; "
                         "need at least 3")
    return ts


def sample_noise(y) -> np.ndarray:
    """Each channel's sample-to-sample (white) noise level of ``y`` (N, c), from its third
    differences (white noise: variance 20 sigma^2). They see past a record's smooth motion (the
    ESG's Earth-rate curvature adds ~0.02 arcsec a minute, a Schuler oscillation ~1e-6 m/s a
    second), so a fit's residual RMS read against this level tells a model that misses the
    record (a record in other units, wrong conditions) from one that fits to its noise."""
    y = np.asarray(y, float)
    if y.shape[0] < 4:
        raise ValueError(f"sample_noise: {y.shape[0]} samples; third differences need at least 4")
    return np.sqrt(np.mean(np.diff(y, 3, axis=0) ** 2, axis=0) / 20)


class BenchRecord(eqx.Module):
    """A bench test record.

    **Fields:**
    - `t`: sample times in s, shape ``(..., n)``, strictly increasing.
    - `y`: measurements, shape ``(..., n, c)``, SI units (rad, rad/s, m/s^2).
    - `channels`: the ``c`` channel names (``("alpha1", "alpha2")`` for the ESG rig).
    - `attrs`: test conditions as a sorted tuple of ``(key, value)``; read them with
      :attr:`conditions`.
    """

    t: Float[Array, "*batch n"]
    y: Float[Array, "*batch n c"]
    channels: tuple[str, ...] = eqx.field(static=True)
    attrs: tuple = eqx.field(static=True, default=())

    def __check_init__(self):
        if self.y.shape[-1] != len(self.channels):
            raise ValueError(
                f"BenchRecord: y has {self.y.shape[-1]} channels (last axis) but channels names "
                f"{len(self.channels)}: {self.channels}; give one name per column")
        if self.y.shape[:-1] != self.t.shape:
            raise ValueError(f"BenchRecord: y.shape {self.y.shape} does not match t.shape "
                             f"{self.t.shape} (expected y.shape == t.shape + (n_channels,))")

    @staticmethod
    def create(t, channels: Mapping[str, object], conditions: Mapping | None = None):
        """Build a record from a time vector and a mapping ``name -> samples``."""
        names = tuple(channels)
        y = jnp.stack([jnp.asarray(channels[k], dtype=float) for k in names], axis=-1)
        return BenchRecord(jnp.asarray(t, dtype=float), y, names, freeze(conditions or {}))

    @property
    def conditions(self) -> dict:
        return dict(self.attrs)

    @property
    def n_samples(self) -> int:
        return self.t.shape[-1]

    def channel(self, name: str):
        try:
            return self.y[..., self.channels.index(name)]
        except ValueError:
            raise KeyError(f"record has no channel {name!r}; it has {self.channels}") from None

    def with_conditions(self, **kwargs) -> BenchRecord:
        return BenchRecord(self.t, self.y, self.channels, freeze(self.conditions | kwargs))

    def __getitem__(self, index) -> BenchRecord:
        """Select one record out of a batch (``records[i]``)."""
        return BenchRecord(self.t[index], self.y[index], self.channels, self.attrs)

    def to_xarray(self, *, units: Mapping[str, str] | None = None):
        """This (single) record as an ``xarray.Dataset`` (:func:`gyrojax.io.to_xarray`)."""
        from .io import to_xarray

        return to_xarray(self, units=units)

    @staticmethod
    def from_xarray(ds, *, channels=None, conditions: Mapping | None = None) -> BenchRecord:
        """A record from an ``xarray.Dataset``, checked as a file is
        (:func:`gyrojax.io.from_xarray`)."""
        from .io import from_xarray

        return from_xarray(ds, channels=channels, conditions=conditions)

    def to_pandas(self):
        """This (single) record as a ``pandas.DataFrame`` indexed by ``t``
        (:func:`gyrojax.io.to_pandas`)."""
        from .io import to_pandas

        return to_pandas(self)

    @staticmethod
    def from_pandas(df, *, channels=None, conditions: Mapping | None = None) -> BenchRecord:
        """A record from a ``pandas.DataFrame``, checked as a file is
        (:func:`gyrojax.io.from_pandas`)."""
        from .io import from_pandas

        return from_pandas(df, channels=channels, conditions=conditions)

    def slice(self, start: int, stop: int | None = None) -> BenchRecord:
        """Samples ``start:stop`` along the time axis."""
        return BenchRecord(self.t[..., start:stop], self.y[..., start:stop, :], self.channels,
                           self.attrs)


def freeze(mapping: Mapping) -> tuple:
    """Sorted tuple of (key, value) with numpy scalars made plain Python (hashable)."""
    out = []
    for k, v in sorted(mapping.items()):
        if isinstance(v, np.generic):
            v = v.item()
        elif isinstance(v, (list, np.ndarray)):
            v = tuple(np.asarray(v).tolist())
        out.append((str(k), v))
    return tuple(out)
