"""diffrax integration of any rig to a BenchRecord, with measurement noise from a PRNG key."""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .models._base import AbstractRig
from .record import BenchRecord, freeze
from .rotations import sincos

__all__ = ["simulate", "integrate", "trajectory", "grid_steps", "gaussian_noise"]


def gaussian_noise(key: PRNGKeyArray, shape: tuple[int, ...],
                   std: float | Float[ArrayLike, "*shape"] = 1.0) -> Float[Array, "*shape"]:
    """White Gaussian deviates of standard deviation ``std`` (float64), by the Box-Muller
    transform of 64-bit uniforms: ``sqrt(-2 ln u1) (cos, sin)(2 pi u2)``, exact in distribution
    up to the uniforms' 2**-52 grid (the largest deviate is 8.5 sigma).

    The Monte Carlo hot path's sampler: on XLA's CPU backend ``jax.random.normal`` in float64
    spends more on its ``erf_inv`` than on the random bits (~100 us per 1441 x 2 deviates);
    this draws the same uniforms as ``jax.random.uniform`` (by an unrolled hash, :func:`_uniform64`)
    and takes one polynomial logarithm and the polynomial :func:`~gyrojax.rotations.sincos` per
    pair (~36 us against ~69 us). A different stream from
    ``jax.random.normal`` for the same key: :func:`simulate` keeps ``jax.random.normal``, so
    its seeded records are unchanged.
    """
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    n = int(np.prod(shape, dtype=np.int64))
    half = -(-n // 2)
    u = _uniform64(key, (2, half))
    radius = jnp.sqrt(-2.0 * _log(1.0 - u[0]))  # 1 - u in (0, 1], exact
    s, c = sincos(2.0 * np.pi * u[1])
    z = jnp.concatenate([radius * c, radius * s])[:n]
    return std * z.reshape(shape)


def _uniform64(key, shape):
    """``jax.random.uniform(key, shape, float64)``, the same values, by the threefry-2x32 hash
    unrolled. jaxlib lowers the hash on the CPU as a rolled 5-iteration loop, each round a
    separate pass over the counters; straight-line, the 20 rounds fuse into one pass. Run as a
    scan over two halves of the counters, so the uniforms are materialized once: as plain
    elementwise code XLA would fuse the hash into each of their consumers (four in
    :func:`gaussian_noise`). 2 x 1441 uniforms and their Box-Muller: ~36 us against ~69 us (one
    core, docs/decisions/0006-esg-monte-carlo-hot-path.md). Other key implementations, the
    non-partitionable threefry stream, raw uint32 keys, or 2**32 or more draws go through
    ``jax.random.uniform``."""
    n = int(np.prod(shape, dtype=np.int64))
    if (not jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key) or n >= 2**32
            or jax.random.key_impl(key) != "threefry2x32"
            or not jax.config.jax_threefry_partitionable):
        return jax.random.uniform(key, shape, dtype=jnp.float64)
    k = jax.random.key_data(key)

    def uniforms(_, index):
        # the partitionable stream hashes the flat index as (high word, low word): high is 0
        hi, lo = _threefry2x32(k[0], k[1], jnp.zeros_like(index), index)
        bits = (hi.astype(jnp.uint64) << np.uint64(32)) | lo.astype(jnp.uint64)
        # 52 random mantissa bits under the exponent of 1.0: [1, 2) - 1, as jax.random.uniform
        one_to_two = (bits >> np.uint64(12)) | np.uint64(0x3FF0000000000000)
        return None, jax.lax.bitcast_convert_type(one_to_two, jnp.float64) - 1.0

    halves = 2 if n % 2 == 0 else 1
    _, u = jax.lax.scan(uniforms, None, jax.lax.iota(jnp.uint32, n).reshape(halves, -1))
    return u.reshape(shape)


_THREEFRY_ROTATIONS = ((13, 15, 26, 6), (17, 29, 16, 24))


def _threefry2x32(key1, key2, x0, x1):
    """The threefry-2x32 hash (20 rounds; Salmon et al. 2011, as ``jax.random``) of the counter
    pairs ``(x0, x1)`` (uint32 arrays) under the key ``(key1, key2)``."""
    ks = (key1, key2, key1 ^ key2 ^ np.uint32(0x1BD11BDA))
    x0, x1 = x0 + ks[0], x1 + ks[1]
    for i in range(5):
        for r in _THREEFRY_ROTATIONS[i % 2]:
            x0 = x0 + x1
            x1 = ((x1 << np.uint32(r)) | (x1 >> np.uint32(32 - r))) ^ x0
        x0 = x0 + ks[(i + 1) % 3]
        x1 = x1 + ks[(i + 2) % 3] + np.uint32(i + 1)
    return x0, x1


# fdlibm's e_log.c: ln 2 in two parts and the minimax coefficients of log(1+f) = 2s + s R(s^2)
_LN2_HI, _LN2_LO = 6.93147180369123816490e-01, 1.90821492927058770002e-10
_LG = (6.666666666666735130e-01, 3.999999999940941908e-01, 2.857142874366239149e-01,
       2.222219843214978396e-01, 1.818357216161805012e-01, 1.531383769920937332e-01,
       1.479819860511658591e-01)


def _log(x):
    """Natural logarithm of positive normal float64 numbers, within 1 ulp of libm: x = 2^k m,
    m in [sqrt(2)/2, sqrt(2)), from the bits; then fdlibm's polynomial in s = (m-1)/(m+1). XLA's
    CPU backend evaluates float64 ``log`` element by element (~5 ns); this is ~2 ns. No zero,
    negative, subnormal or non-finite input: the uniforms of :func:`gaussian_noise` are never
    those."""
    bits = jax.lax.bitcast_convert_type(x, jnp.int64)
    mantissa = (bits & 0x000FFFFFFFFFFFFF) | 0x3FF0000000000000  # the exponent of 1.0
    m = jax.lax.bitcast_convert_type(mantissa, jnp.float64)
    big = m > np.sqrt(2.0)
    m = jnp.where(big, 0.5 * m, m)
    k = ((bits >> 52) - 1023 + big).astype(jnp.float64)
    f = m - 1.0
    s = f / (2.0 + f)
    z = s * s
    w = z * z
    r = (z * (_LG[0] + w * (_LG[2] + w * (_LG[4] + w * _LG[6])))
         + w * (_LG[1] + w * (_LG[3] + w * _LG[5])))
    hfsq = 0.5 * f * f
    return k * _LN2_HI - ((hfsq - (s * (hfsq + r) + k * _LN2_LO)) - f)


@eqx.filter_jit
def trajectory(rig: AbstractRig, params, conditions, ts: Float[ArrayLike, " n"], *, solver=None,
               rtol: float = 1e-10, atol: float = 1e-12, max_steps: int = 100_000, adjoint=None,
               throw: bool = True, steps: int | None = None) -> Float[Array, "n state"]:
    """States of ``rig`` at times ``ts`` (s), shape ``(n, state)``; see :func:`integrate`."""
    tau = jnp.asarray(ts, dtype=float) * rig.time_scale
    y0 = rig.initial_state(params, conditions)
    solver = solver or diffrax.Dopri8()

    def field(t, y, args):
        return rig.vector_field(t, y, params, conditions)

    jumps = rig.jump_times(params, conditions)
    if steps is not None:
        return _grid_trajectory(diffrax.ODETerm(field), solver, tau, y0, steps, rtol, atol, throw,
                                jumps is not None)
    controller = diffrax.PIDController(rtol=rtol, atol=atol)
    stops = rig.step_times(params, conditions)
    if jumps is not None or stops is not None:
        controller = diffrax.ClipStepSizeController(controller, step_ts=stops, jump_ts=jumps)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field), solver, t0=tau[0], t1=tau[-1], dt0=None, y0=y0,
        saveat=diffrax.SaveAt(ts=tau), stepsize_controller=controller,
        max_steps=max_steps, adjoint=adjoint or diffrax.RecursiveCheckpointAdjoint(),
        throw=throw)
    return sol.ys


def grid_steps(rig: AbstractRig, params, conditions, ts: Float[ArrayLike, " n"], *, solver=None,
               rtol: float = 1e-10,
               atol: float = 1e-12, margin: float = 0.05, max_factor: float = 2.5) -> int | None:
    """A fixed step grid for :func:`trajectory`'s ``steps``, or None where adaptive steps are
    the better choice.

    Starts from the adaptive solve's step count on ``params`` and returns the smallest divisor
    of the ``len(ts) - 1`` sample intervals whose steps all have error estimates within
    ``margin`` of the ``rtol``/``atol`` acceptance bound on ``params`` (so that draws near
    ``params``, a Monte Carlo over small mounting errors, still pass: the grid path checks every
    step of every draw and raises if one does not). None if that needs more than ``max_factor``
    times the adaptive count (a trajectory whose rates vary strongly along it, e.g. the
    horizontal scheme passing near the gimbal singularity: a uniform grid would waste steps) or
    the samples are coarser than the steps. For several schemes take the largest, or None if
    any is None.
    """
    tau = jnp.asarray(ts, dtype=float) * rig.time_scale
    solver = solver or diffrax.Dopri8()
    count = int(_step_count(rig, params, conditions, tau, solver, rtol, atol))
    n = int(tau.shape[0]) - 1
    divisors = [d for d in range(max(count, 1), n + 1) if n % d == 0 and d <= max_factor * count]
    want = count
    while True:
        d = next((d for d in divisors if d >= want), None)
        if d is None:
            return None
        ratio = float(_grid_error(rig, params, conditions, tau, solver, rtol, atol, d))
        if ratio <= margin:
            return d
        # Dopri8's local error ~ h^8: jump to the step count that would meet the margin
        want = max(d + 1, int(np.ceil(d * (ratio / margin) ** (1 / 8))))


@eqx.filter_jit
def _step_count(rig, params, conditions, tau, solver, rtol, atol):
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, y, args: rig.vector_field(t, y, params, conditions)), solver,
        t0=tau[0], t1=tau[-1], dt0=None, y0=rig.initial_state(params, conditions),
        saveat=diffrax.SaveAt(t1=True), stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol))
    return sol.stats["num_accepted_steps"]


@eqx.filter_jit
def _grid_error(rig, params, conditions, tau, solver, rtol, atol, steps):
    term = diffrax.ODETerm(lambda t, y, args: rig.vector_field(t, y, params, conditions))
    return _grid_solve(term, solver, tau, rig.initial_state(params, conditions), steps, rtol,
                       atol)[1]


def _grid_trajectory(term, solver, tau, y0, steps, rtol, atol, throw, has_jumps=False):
    """The fixed-grid path of :func:`trajectory`: ``steps`` equal steps of ``solver``, the
    samples read from its dense interpolant, every step's error estimate checked against
    ``rtol``/``atol`` with the RMS norm the PID controller uses: a grid too coarse (or
    nonuniform samples) raises with ``throw=True`` and gives NaN states otherwise. A jump of
    the vector field inside a step (the rig's ``jump_times``, which the grid does not stop at)
    fails that check unless it is too small to matter at ``rtol``/``atol``: such records need
    ``steps=None``."""
    ys, worst, uniform = _grid_solve(term, solver, tau, y0, steps, rtol, atol)
    if throw:
        ys = eqx.error_if(ys, ~uniform, "trajectory(steps=...): the sample times are not uniform; "
                          "a fixed step grid needs uniform samples (use steps=None)")
        jump = (" (this rig's vector field jumps at its jump_times, e.g. a drift step's onset: "
                "a step across a jump fails the check at any grid, so use steps=None, whose "
                "adaptive steps stop at the jumps)") if has_jumps else ""
        return eqx.error_if(ys, worst > 1.0,
                            f"trajectory(steps={steps}): a step's error estimate exceeds rtol/atol; "
                            f"the grid is too coarse: use more steps (or steps=None){jump}")
    return jnp.where(uniform & (worst <= 1.0), ys, jnp.nan)


def _grid_solve(term, solver, tau, y0, steps, rtol, atol):
    """``steps`` equal steps of ``solver`` under ``lax.scan``, each ending on a sample, and the
    samples inside a step read from the solver's own dense interpolant. Returns the states, the
    largest step error ratio (<= 1: every step within rtol/atol) and whether ``tau`` is uniform.

    For a Runge-Kutta solver that interpolant is linear in the step's dense information
    (``y0``, ``y1``, the stage increments ``k``) with weights that depend only on the fraction
    ``theta`` of the step. With uniform samples and ``steps`` dividing the intervals, the
    ``theta`` of every sample is known from the shapes, so the weights are computed once at
    trace time and the samples of all steps come out of one small contraction (a saving loop
    inside the step loop is what costs an adaptive solve half its time).
    """
    n = tau.shape[0]
    if jnp.ndim(y0) != 1:
        raise ValueError(f"steps={steps}: the fixed step grid takes a state vector, not a state "
                         f"of shape {jnp.shape(y0)}; use steps=None")
    if steps < 1 or (n - 1) % steps:
        raise ValueError(f"steps={steps}: the fixed step grid must divide the {n - 1} sample "
                         f"intervals; use a divisor of {n - 1} (or steps=None for adaptive steps)")
    per = (n - 1) // steps
    dt = (tau[-1] - tau[0]) / (n - 1)
    uniform = jnp.max(jnp.abs(jnp.diff(tau) - dt)) <= 1e-9 * jnp.abs(dt)
    edges = tau[::per]
    state = solver.init(term, edges[0], edges[1], y0, None)

    def step(carry, t01):
        y, state = carry
        y1, err, dense, state, _ = solver.step(term, t01[0], t01[1], y, None, state, False)
        scale = atol + rtol * jnp.maximum(jnp.abs(y), jnp.abs(y1))
        return (y1, state), (dense, jnp.sqrt(jnp.mean((err / scale) ** 2)))

    (y_end, _), (dense, err_ratio) = jax.lax.scan(step, (y0, state),
                                                  jnp.stack([edges[:-1], edges[1:]], axis=1))
    weights = _interpolation_weights(solver, dense, per)
    # y(step j, sample i) = sum over the dense leaves of weight_i . leaf_j, state component-wise
    inside = sum(jnp.einsum("is,jsc->jic" if leaf.ndim == 3 else "i,jc->jic", w, leaf)
                 for w, leaf in zip(jax.tree.leaves(weights), jax.tree.leaves(dense), strict=True))
    ys = jnp.concatenate([inside.reshape(steps * per, -1), y_end[None]], axis=0)
    return ys, jnp.max(err_ratio), uniform


def _interpolation_weights(solver, dense, per):
    """Weights of the dense interpolant of ``solver`` at ``theta = i / per`` (i < per), per leaf of
    one step's dense information for a scalar state: the interpolant is linear in that
    information and acts on each state component alike. Computed at trace time."""
    scalar = jax.tree.map(lambda x: jnp.zeros(x.shape[1:-1], x.dtype), dense)
    interp = solver.interpolation_cls

    def at(theta):
        return jax.grad(lambda d: interp(t0=0.0, t1=1.0, **d).evaluate(theta))(scalar)

    with jax.ensure_compile_time_eval():
        return jax.vmap(at)(jnp.arange(per) / per)


@eqx.filter_jit
def integrate(rig: AbstractRig, params, conditions, ts: Float[ArrayLike, " n"], *, solver=None,
              rtol: float = 1e-10, atol: float = 1e-12, max_steps: int = 100_000, adjoint=None,
              throw: bool = True, steps: int | None = None) -> Float[Array, "n c"]:
    """Noise-free measured channels of ``rig`` at times ``ts`` (s), shape ``(n, c)``.

    Integrates ``rig.vector_field`` in the rig's internal time from ``ts[0]`` (where the state is
    ``rig.initial_state``) with an adaptive ``solver`` (default ``diffrax.Dopri8``) and a PID
    controller at ``rtol``/``atol``. Differentiable in ``params``: pass
    ``adjoint=diffrax.ForwardMode()`` for ``jax.jacfwd`` (forward sensitivities).

    ``steps`` (an int dividing ``len(ts) - 1``, uniform ``ts``) takes that many equal steps of
    ``solver`` instead, reading the samples from its dense interpolant, and checks every step's
    error estimate against ``rtol``/``atol`` (raising if the grid is too coarse; NaN states with
    ``throw=False``). The same solution to rounding as diffrax with ``ConstantStepSize``, about 3x
    faster than adaptive steps for batched Monte Carlo; :func:`grid_steps` picks the grid.

    jit-compiled (``equinox.filter_jit``) so repeated calls with the same shapes reuse one
    compilation: the vector-field closure is built inside the trace.
    """
    tau = jnp.asarray(ts, dtype=float) * rig.time_scale
    ys = trajectory(rig, params, conditions, ts, solver=solver, rtol=rtol, atol=atol,
                    max_steps=max_steps, adjoint=adjoint, throw=throw, steps=steps)
    return jax.vmap(lambda t, y: rig.observe(t, y, params, conditions))(tau, ys)


@eqx.filter_jit
def _simulate(rig, params, conditions, ts, key, noise_std, rtol, atol, max_steps, solver, steps):
    y = integrate(rig, params, conditions, ts, solver=solver, rtol=rtol, atol=atol,
                  max_steps=max_steps, steps=steps)
    if key is not None:
        y = y + noise_std * jax.random.normal(key, y.shape, dtype=y.dtype)
    return y


def simulate(rig: AbstractRig, params, conditions, ts: Float[ArrayLike, " n"], *, key=None,
             noise_std: float | Float[ArrayLike, " c"] = 0.0,
             attrs=None, rtol: float = 1e-10, atol: float = 1e-12,
             max_steps: int = 100_000, solver=None, steps: int | None = None) -> BenchRecord:
    """Simulate a bench test: integrate the rig and add white measurement noise.

    **Arguments:**
    - `rig`, `params` (dict, internal units), `conditions` (the rig's conditions module).
    - `ts`: sample times in s, shape ``(n,)``.
    - `key`: a ``jax.random`` key; required when ``noise_std > 0``.
    - `noise_std`: standard deviation of the white noise on every channel (internal units, e.g.
      rad; may be an array per channel).
    - `attrs`: test conditions written into the record (latitude_deg, scheme...).
    - `solver`, `rtol`, `atol`, `max_steps`, `steps`: as in :func:`integrate` (an implicit solver such as
      ``diffrax.Kvaerno5`` for stiff rigs, e.g. the gyrotheodolite's 8.7 Hz nutation).

    **Returns:** a :class:`BenchRecord`. jit-compiled; batch it with ``jax.vmap`` over ``params``,
    ``conditions``, ``key`` (a record is a pytree).
    """
    if key is None and not _is_zero(noise_std):
        raise ValueError("simulate: noise_std > 0 needs a PRNG key; pass key=jax.random.key(seed)")
    check_inputs(rig, params, ts, noise_std)
    y = _simulate(rig, _traced(params), conditions, ts, key, jnp.asarray(noise_std, dtype=float),
                  rtol, atol, max_steps, solver, steps)
    return BenchRecord(jnp.asarray(ts, dtype=float), y, rig.channels, freeze(attrs or {}))


def _concrete(x):
    """``x`` as a NumPy array, or None when it is traced (checked inside jit, or not at all)."""
    try:
        return np.asarray(x, dtype=float)
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError):
        return None


def check_inputs(rig, params, ts, noise_std=0.0, *, what: str = "simulate"):
    """The boundary checks of :func:`simulate` (and of analyses that integrate the rig, named by
    ``what`` in the message) on what is concrete: every parameter a name of the rig's (a
    misspelt name was ignored, the rig ran on its null value) and finite (NaN made the solver
    report its step limit), ``ts`` 1-D and strictly increasing (a record's contract; decreasing
    times integrated backwards; :func:`gyrojax.io.check_times`), ``noise_std`` finite and
    >= 0."""
    from .io import check_times

    rig.param_space.check_names(params, what=f"{type(rig).__name__} parameter")
    for k, v in params.items():
        a = _concrete(v)
        if a is not None and not np.all(np.isfinite(a)):
            raise ValueError(f"{what}: parameter {k} = {v} is not finite; give a number "
                             "(internal units)")
    t = _concrete(ts)
    if t is not None:
        check_times(t, source=f"{what}: ts", min_samples=1)
    sd = _concrete(noise_std)
    if sd is not None and not np.all(np.isfinite(sd) & (sd >= 0)):
        raise ValueError(f"{what}: noise_std = {noise_std} must be finite and >= 0 (a standard "
                         "deviation, internal units)")


def _traced(params):
    """``params`` with every Python number as a float64 array: ``equinox.filter_jit`` treats a
    Python float as static, so ``params | {"theta1": 1e-3}`` would compile once per value."""
    return jax.tree.map(lambda v: jnp.asarray(v, dtype=float)
                        if isinstance(v, int | float) and not isinstance(v, bool) else v, params)


def _is_zero(x) -> bool:
    """Whether ``x`` is known to be zero (False when traced); NumPy, so that it also answers
    inside ``jax.jit``, where ``jnp`` would stage the comparison out."""
    a = _concrete(x)
    return a is not None and bool(np.all(a == 0))
