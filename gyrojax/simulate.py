"""diffrax integration of any rig to a BenchRecord, with measurement noise from a PRNG key."""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from .models._base import AbstractRig
from .record import BenchRecord, freeze

__all__ = ["simulate", "integrate", "trajectory"]


@eqx.filter_jit
def trajectory(rig: AbstractRig, params, conditions, ts, *, solver=None, rtol: float = 1e-10,
               atol: float = 1e-12, max_steps: int = 100_000, adjoint=None, throw: bool = True):
    """States of ``rig`` at times ``ts`` (s), shape ``(n, state)``; see :func:`integrate`."""
    tau = jnp.asarray(ts, dtype=float) * rig.time_scale
    y0 = rig.initial_state(params, conditions)

    def field(t, y, args):
        return rig.vector_field(t, y, params, conditions)

    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field), solver or diffrax.Dopri8(), t0=tau[0], t1=tau[-1], dt0=None, y0=y0,
        saveat=diffrax.SaveAt(ts=tau),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        max_steps=max_steps, adjoint=adjoint or diffrax.RecursiveCheckpointAdjoint(),
        throw=throw)
    return sol.ys


@eqx.filter_jit
def integrate(rig: AbstractRig, params, conditions, ts, *, solver=None, rtol: float = 1e-10,
              atol: float = 1e-12, max_steps: int = 100_000, adjoint=None, throw: bool = True):
    """Noise-free measured channels of ``rig`` at times ``ts`` (s), shape ``(n, c)``.

    Integrates ``rig.vector_field`` in the rig's internal time from ``ts[0]`` (where the state is
    ``rig.initial_state``) with an adaptive ``solver`` (default ``diffrax.Dopri8``) and a PID
    controller at ``rtol``/``atol``. Differentiable in ``params``: pass
    ``adjoint=diffrax.ForwardMode()`` for ``jax.jacfwd`` (forward sensitivities).

    jit-compiled (``equinox.filter_jit``) so repeated calls with the same shapes reuse one
    compilation: the vector-field closure is built inside the trace.
    """
    tau = jnp.asarray(ts, dtype=float) * rig.time_scale
    ys = trajectory(rig, params, conditions, ts, solver=solver, rtol=rtol, atol=atol,
                    max_steps=max_steps, adjoint=adjoint, throw=throw)
    return jax.vmap(lambda t, y: rig.observe(t, y, params, conditions))(tau, ys)


@eqx.filter_jit
def _simulate(rig, params, conditions, ts, key, noise_std, rtol, atol, max_steps, solver):
    y = integrate(rig, params, conditions, ts, solver=solver, rtol=rtol, atol=atol,
                  max_steps=max_steps)
    if key is not None:
        y = y + noise_std * jax.random.normal(key, y.shape, dtype=y.dtype)
    return y


def simulate(rig: AbstractRig, params, conditions, ts, *, key=None, noise_std=0.0,
             attrs=None, rtol: float = 1e-10, atol: float = 1e-12,
             max_steps: int = 100_000, solver=None) -> BenchRecord:
    """Simulate a bench test: integrate the rig and add white measurement noise.

    **Arguments:**
    - `rig`, `params` (dict, internal units), `conditions` (the rig's conditions module).
    - `ts`: sample times in s, shape ``(n,)``.
    - `key`: a ``jax.random`` key; required when ``noise_std > 0``.
    - `noise_std`: standard deviation of the white noise on every channel (internal units, e.g.
      rad; may be an array per channel).
    - `attrs`: test conditions written into the record (latitude_deg, scheme...).
    - `solver`, `rtol`, `atol`, `max_steps`: as in :func:`integrate` (an implicit solver such as
      ``diffrax.Kvaerno5`` for stiff rigs, e.g. the gyrotheodolite's 8.7 Hz nutation).

    **Returns:** a :class:`BenchRecord`. jit-compiled; batch it with ``jax.vmap`` over ``params``,
    ``conditions``, ``key`` (a record is a pytree).
    """
    if key is None and not _is_zero(noise_std):
        raise ValueError("simulate: noise_std > 0 needs a PRNG key; pass key=jax.random.key(seed)")
    y = _simulate(rig, params, conditions, ts, key, jnp.asarray(noise_std, dtype=float), rtol, atol,
                  max_steps, solver)
    return BenchRecord(jnp.asarray(ts, dtype=float), y, rig.channels, freeze(attrs or {}))


def _is_zero(x) -> bool:
    try:
        return bool(jnp.all(jnp.asarray(x) == 0))
    except jax.errors.ConcretizationTypeError:
        return False
