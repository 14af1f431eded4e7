"""The turns between still poses as a second residual block of the IMU diagnosis.

Each turn the record holds (:func:`~gyrojax.estimate.multiposition.recorded_turns`) carries the
pose before it into the pose after it: the up vector of the pose before (its accelerometer
first guess tilted by the pose terms) is propagated through the turn by the gyro rates the
error model makes true (:func:`~gyrojax.models.imu.true_rate`, at the specific force the
accelerometers' model makes true: :func:`~gyrojax.models.imu.true_force`), and its miss of the pose after's
up vector, resolved on that pose's tilt frame, is two residual entries per turn. Gyro scale
factor, misalignment, g-sensitivity, drift and warm-up act on them where the turns excite them;
on the still rows a gyro scale factor scales the Earth rate alone.

The block's noise level is its own. Each entry's is first the gyros' white noise integrated
over its turn (``sigma_w dt sqrt(L)``, ``sigma_w`` the gyros' per-sample level from first
differences on the still poses: :attr:`TurnBlock.prior_std`), which sets the entries' relative
weights; their scale is the misclosures' scatter about the full model (the nominal model plus
every catalogued mean effect, fitted jointly with the whitened still rows, so that a catalogued
effect is not taken for noise), divided by the dof that fit leaves on the block
(:func:`turn_level`): a hand turn's misclosure holds more than the gyros' noise (6 times more
on the MPU-9150 records). Where the full model leaves fewer than ``MIN_TURN_DOF`` dof on the
turns, they are not used. The propagation neglects the horizontal Earth rate's turn of the up
vector during a turn (``Omega cos(lat)`` times its length: 0.008 deg over a 3-s hand turn).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..estimate.multiposition import recorded_turns, up_step
from ..models.imu import true_force, true_rate

__all__ = ["TurnBlock", "build_turns", "turn_misclosure", "turn_parts", "turn_jacobian",
           "propagate_turns", "turn_level"]

TURN_PAD = 64  # samples: turns are padded to a multiple (few compiled shapes across records)
TURN_COUNT_PAD = 8  # turns: the count is padded to a multiple
MIN_TURN_DOF = 8  # the fewest dof an estimated level of the block may rest on


@dataclasses.dataclass
class TurnBlock:
    """The turns of one record, padded for one compiled propagation.

    `k0`, `k1` ``(m,)``: poses before and after; `t0`, `t1` ``(m,)``: the turn's first and last
    sample (s); `angle_deg` ``(m,)``: the angle between the poses' up vectors (accelerometers);
    `axis` ``(m,)``: the body axis the turn is mostly about (``"x"``, ``"y"``, ``"z"``);
    `n_train`: the turns that end before the held-out rows (the first ones); `prior_std`
    ``(m,)``: each misclosure component's level from the gyros' white noise alone (rad);
    `arrays`: the padded ``(w, f, t, live, dT, dT/dt, k0, k1, dt)`` the compiled residual
    takes."""

    k0: np.ndarray
    k1: np.ndarray
    t0: np.ndarray
    t1: np.ndarray
    angle_deg: np.ndarray
    axis: tuple
    n_train: int
    prior_std: np.ndarray
    arrays: tuple

    @property
    def m(self) -> int:
        return len(self.k0)

    def weights(self, std) -> np.ndarray:
        """``(2 m_padded,)``: the fit weights of the train turns' entries, ``1 / std`` (``std``
        ``(2 m,)``, rad), 0 elsewhere."""
        w = np.zeros(2 * self.arrays[0].shape[0])
        w[: 2 * self.n_train] = 1.0 / np.asarray(std)[: 2 * self.n_train]
        return w

    def labels(self) -> list[str]:
        """One label per turn: its poses, time and size."""
        return [f"turn {j} (pose {a}->{b}, {s:.0f} s, {g:.0f} deg about {x})"
                for j, (a, b, s, g, x) in enumerate(zip(self.k0, self.k1, self.t0,
                                                          self.angle_deg, self.axis))]


def build_turns(record, segments, members, ups, t_split: float, thermal_at,
                max_turn_s: float = 30.0) -> TurnBlock | None:
    """The :class:`TurnBlock` of ``record`` (``None`` when it holds no turn between member
    poses, or lacks a gyro or accelerometer triad). `ups` ``(poses, 3)``: the poses' first-guess
    up vectors; `t_split`: the first held-out row's time (s; a turn is train when it ends
    before it); `thermal_at(t)`: ``(dT, dT/dt)`` at sample times."""
    if not all(c in record.channels for c in ("wx", "wy", "wz", "ax", "ay", "az")):
        return None
    turns = recorded_turns(record, segments, members, max_turn_s=max_turn_s)
    if not turns:
        return None
    t = np.asarray(record.t, float)
    w = np.stack([np.asarray(record.channel(c), float) for c in ("wx", "wy", "wz")], 1)
    f = np.stack([np.asarray(record.channel(c), float) for c in ("ax", "ay", "az")], 1)
    dt = float(np.median(np.diff(t)))
    m = len(turns)
    m_pad = TURN_COUNT_PAD * -(-m // TURN_COUNT_PAD)
    lmax = TURN_PAD * -(-max(i1 - i0 for *_, i0, i1 in turns) // TURN_PAD)
    wt, ft = np.zeros((m_pad, lmax, 3)), np.zeros((m_pad, lmax, 3))
    tt, live = np.zeros((m_pad, lmax)), np.zeros((m_pad, lmax, 1))
    ft[..., 2] = 9.8  # padding: a still, level sensor (masked by live anyway)
    for j, (_, _, i0, i1) in enumerate(turns):
        n = i1 - i0
        wt[j, :n], ft[j, :n], tt[j, :n], live[j, :n] = w[i0:i1], f[i0:i1], t[i0:i1], 1.0
        tt[j, n:] = t[i1 - 1]
    d_t, r_t = (np.asarray(x) for x in thermal_at(tt.reshape(-1)))
    k0 = np.array([a for a, *_ in turns])
    k1 = np.array([b for _, b, *_ in turns])
    ks0, ks1 = np.zeros(m_pad, int), np.zeros(m_pad, int)
    ks0[:m], ks1[:m] = k0, k1
    ups = np.asarray(ups, float)
    ang = np.degrees(np.arccos(np.clip(np.sum(ups[k0] * ups[k1], 1), -1, 1)))
    # the axis a turn is mostly about: its integrated rate's largest component
    rot = np.abs(np.sum(wt * live, axis=1))[:m]
    axis = tuple("xyz"[int(i)] for i in np.argmax(rot, axis=1))
    t0 = np.array([t[i0] for *_, i0, _ in turns])
    t1 = np.array([t[i1 - 1] for *_, _, i1 in turns])
    n_train = int(np.sum(t1 < t_split))
    # the gyros' per-sample white level on the still poses (first differences), pooled
    still = [s for k, s in enumerate(segments) if members[k] and s.i1 - s.i0 > 2]
    d2 = [np.mean(np.diff(w[s.i0:s.i1], axis=0) ** 2) / 2 for s in still]
    sigma_w = float(np.sqrt(np.average(d2, weights=[s.i1 - s.i0 for s in still])))
    prior = sigma_w * dt * np.sqrt([i1 - i0 for *_, i0, i1 in turns])
    arrays = tuple(jnp.asarray(x) for x in (wt, ft, tt, live, d_t.reshape(tt.shape),
                                            r_t.reshape(tt.shape), ks0, ks1, dt))
    return TurnBlock(k0, k1, t0, t1, ang, axis, n_train, prior, arrays)


def turn_parts(params, tilt_a, tilt_b, u0, e1, e2, arrays):
    """The turns' inputs to their propagation: ``(phi, ua, ub)``, each sample's body rotation
    ``(m, L, 3)`` (rate the error model makes true times step, zero on the padding) and the up
    vectors of the poses before and after ``(m, 3)``. Arguments as :func:`turn_misclosure`."""
    w, f, t, live, d_t, r_t, k0, k1, dt = arrays

    def up(k):
        u = u0[k] + tilt_a[k][:, None] * e1[k] + tilt_b[k][:, None] * e2[k]
        return u / jnp.linalg.norm(u, axis=1, keepdims=True)

    thermal = (d_t, r_t)
    rate = true_rate(params, w, true_force(params, f, t, thermal), t, thermal) * live
    return rate * dt, up(k0), up(k1)


def _tilt_frames(e1, e2, arrays):
    """``(m, 2, 3)``: the tilt frame of each turn's pose after."""
    k1 = arrays[7]
    return jnp.stack([e1[k1], e2[k1]], 1)


def turn_misclosure(params, tilt_a, tilt_b, u0, e1, e2, arrays):
    """``(2 m_padded,)``: each turn's propagated up vector minus the pose after's, on that pose's
    tilt frame ``(e1, e2)`` (rad), per turn ``[along e1, along e2]``. `params`: the error model
    (:func:`~gyrojax.models.imu.imu_measure`'s dict); `tilt_a`, `tilt_b` ``(poses,)``: the pose
    terms (rad); `u0`, `e1`, `e2` ``(poses, 3)``: first-guess up vectors and tilt frames."""
    phi, ua, ub = turn_parts(params, tilt_a, tilt_b, u0, e1, e2, arrays)
    d = propagate_turns(ua, phi) - ub
    return jnp.einsum("mci,mi->mc", _tilt_frames(e1, e2, arrays), d).reshape(-1)


def turn_jacobian(parts, vec, e1, e2, arrays):
    """``(misclosures (2 m,), their Jacobian in vec (2 m, len(vec)))``, where ``parts(vec,
    arrays)`` is :func:`turn_parts` at the parameter vector ``vec``. Each turn's two entries
    depend on its own samples: the end's sensitivities to the rotations and the start
    (:func:`_sensitivities`, no tangent in them) become two cotangents per turn, pulled back to
    ``vec`` by one reverse pass per turn (batched). That costs about two propagations where K
    tangents pushed forward through every turn's samples cost K (a fit's Jacobian: K = 96)."""
    phi, ua, ub = parts(vec, arrays)
    end, a, s0 = _sensitivities(ua, phi)
    e = _tilt_frames(e1, e2, arrays)
    value = jnp.einsum("mci,mi->mc", e, end - ub).reshape(-1)
    cots = (jnp.einsum("mci,mlij->mclj", e, a), jnp.einsum("mci,mij->mcj", e, s0), -e)
    *per, dt = arrays

    def rows(own, c_phi, c_ua, c_ub):  # one turn: its arrays (1, ...) and two cotangents
        _, pull = jax.vjp(lambda v: parts(v, (*own, dt)), vec)
        return jax.vmap(lambda *c: pull(tuple(x[None] for x in c))[0])(c_phi, c_ua, c_ub)

    jac = jax.vmap(rows)(tuple(x[:, None] for x in per), *cots)
    return value, jac.reshape(-1, vec.shape[0])


def _forward(u0, phi):
    """The up vectors before each step ``(m, L, 3)`` and after the last ``(m, 3)``."""
    def scan_one(u, ph):
        def body(v, p):
            return up_step(v, p), v
        end, before = jax.lax.scan(body, u, ph)
        return before, end
    return jax.vmap(scan_one)(u0, phi)


def _sensitivities(u0, phi):
    """``(end, a, s0)``: the propagated up vectors ``(m, 3)``, the end's Jacobian in each
    sample's rotation ``a`` ``(m, L, 3, 3)`` (``S_i B_i``: ``B_i`` one step's Jacobian in its
    rotation, ``S_i`` the product of the steps after it) and in the start ``s0`` ``(m, 3, 3)``."""
    before, end = _forward(u0, phi)
    b = jax.vmap(jax.vmap(jax.jacfwd(up_step, argnums=1)))(before, phi)
    r = jax.vmap(jax.vmap(jax.jacfwd(up_step, argnums=0)))(before, phi)

    def suffix(acc, ri):  # S_{i-1} = S_i R_i, from the last sample back
        return acc @ ri, acc
    eye = jnp.broadcast_to(jnp.eye(3), u0.shape[:1] + (3, 3))
    s0, s = jax.lax.scan(suffix, eye, jnp.swapaxes(r, 0, 1), reverse=True)
    return end, jnp.swapaxes(s, 0, 1) @ b, s0


@jax.custom_jvp
def propagate_turns(u0, phi):
    """``(m, 3)``: each turn's up vector ``u0`` ``(m, 3)`` carried through its samples' body
    rotations ``phi`` ``(m, L, 3)`` (rate times step, zero rotation pads), sample by sample
    as :func:`~gyrojax.estimate.multiposition.propagate_up`.

    Its derivative is written out: the end's change is ``sum_i S_i B_i dphi_i + S_0 du0``
    (:func:`_sensitivities`, free of the tangent), so a fit's Jacobian over K parameters costs
    one contraction over the samples instead of K tangents pushed through the sequential
    scan."""
    return _forward(u0, phi)[1]


@propagate_turns.defjvp
def _propagate_turns_jvp(primals, tangents):
    u0, phi = primals
    du0, dphi = tangents
    end, a, s0 = _sensitivities(u0, phi)
    out = jnp.einsum("mlij,mlj->mi", a, dphi) + jnp.einsum("mij,mj->mi", s0, du0)
    return end, out


def turn_level(grid_cols, grid_resid, block_cols, block_resid, iterations: int = 20):
    """The scale of the turns' levels from the full model's joint fit.

    The full model's columns on the whitened still rows (`grid_cols` ``(n c, K)``, residual
    `grid_resid` ``(n c,)``) and on the train turns' entries, each divided by its prior level
    (`block_cols` ``(m, K)``, `block_resid` ``(m,)``), are fitted together with the block
    divided by the scale ``s``; ``s^2`` is the block's residual sum of squares over the dof the
    fit leaves there (``m`` minus the hat matrix's trace on the block), iterated to its fixed
    point.

    **Returns:** ``(s, dof, q)``: the scale, its dof and the orthonormal basis ``q`` ``(n c + m,
    r)`` of the weighted full-model span (the null draws re-estimate the scale through it:
    :func:`rescale_block`); ``(nan, dof, None)`` where the fit leaves fewer than
    ``MIN_TURN_DOF`` dof on the block."""
    m = len(block_resid)
    scale = max(float(np.sqrt(np.mean(block_resid ** 2))), 1e-3)
    q, dof = None, 0.0
    for _ in range(iterations):
        a = np.concatenate([grid_cols, block_cols / scale])
        y = np.concatenate([grid_resid, block_resid / scale])
        u, sv, _ = np.linalg.svd(a, full_matrices=False)
        q = u[:, sv > 1e-10 * sv[0]]
        r = y - q @ (q.T @ y)
        dof = m - float(np.sum(q[-m:] ** 2))
        if dof < MIN_TURN_DOF:
            return float("nan"), dof, None
        new = scale * float(np.sqrt(np.sum(r[-m:] ** 2) / dof))
        done = abs(new - scale) < 1e-6 * scale
        scale = new
        if done:
            break
    return scale, dof, q


def rescale_block(z, q, m: int, dof: float):
    """Null draws ``z`` ``(b, n c + m)`` (unit white, the block last) with the block divided by
    its level re-estimated as on the data (:func:`turn_level` with the basis ``q``)."""
    r = z - (z @ q) @ q.T
    s = np.sqrt(np.sum(r[:, -m:] ** 2, axis=1) / dof)
    z = z.copy()
    z[:, -m:] /= s[:, None]
    return z
