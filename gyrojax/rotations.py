"""Elementary rotations, small rotations and Euler sequences.

All matrices are right-handed and *active*. For frames ``a`` and ``b``, ``mat_ab`` has as its columns
the axes of ``b`` written in ``a``, so ``vec_a = mat_ab @ vec_b``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

# pi/2 in three parts (fdlibm's pio2_1, pio2_2, pio2_2t): the first two carry 33 significant
# bits each, so q * part is exact for |q| < 2**20 and the reduction x - q pi/2 keeps full
# precision for |x| up to ~1.6e6 rad.
_PIO2_1 = 1.57079632673412561417e+00
_PIO2_2 = 6.07710050630396597660e-11
_PIO2_2T = 2.02226624879595063154e-21
# Minimax polynomials on |r| <= pi/4 (fdlibm's __kernel_sin / __kernel_cos, Sun Microsystems,
# freely distributable): sin r = r + r^3 S(r^2), cos r = 1 - r^2/2 + r^4 C(r^2), within 0.5 ulp
# of 1 there (test)
_SIN_COEF = (-1.66666666666666324348e-01, 8.33333333332248946124e-03,
             -1.98412698298579493134e-04, 2.75573137070700676789e-06,
             -2.50507602534068634195e-08, 1.58969099521155010221e-10)
_COS_COEF = (4.16666666666666019037e-02, -1.38888888888741095749e-03,
             2.48015872894767294178e-05, -2.75573143513906633035e-07,
             2.08757232129817482790e-09, -1.13596475577881948265e-11)


def _poly(z, coef):
    acc = coef[-1]
    for c in reversed(coef[:-1]):
        acc = c + z * acc
    return acc


@jax.custom_jvp
def sincos(x):
    """``(sin x, cos x)`` of a float64 array, within ~1 ulp of libm for |x| <= 1.6e6 rad.

    XLA's CPU backend evaluates float64 ``sin`` / ``cos`` element by element (~15-20 ns each);
    this version is polynomial arithmetic that its loops vectorise (~3 ns for both), which is
    most of the exact ESG model's vector field and of the integral regression's design
    (docs/decisions/0006-esg-monte-carlo-hot-path.md). Cody-Waite reduction by pi/2 to |r| <= pi/4, minimax
    polynomials, quadrant swap. Beyond |x| ~ 1.6e6 rad the error grows like
    |x| 2**-53, the input's own resolution. Other dtypes go to ``jnp.sin`` / ``jnp.cos``.
    Differentiable: the tangents are ``(cos x dx, -sin x dx)``.
    """
    x = jnp.asarray(x)
    if x.dtype != jnp.float64:
        return jnp.sin(x), jnp.cos(x)
    q = jnp.round(x * (2.0 / np.pi))
    r = ((x - q * _PIO2_1) - q * _PIO2_2) - q * _PIO2_2T
    z = r * r
    s = r + r * z * _poly(z, _SIN_COEF)
    c = 1.0 - 0.5 * z + z * z * _poly(z, _COS_COEF)
    quadrant = q - 4.0 * jnp.floor(0.25 * q)  # 0, 1, 2, 3
    swap = (quadrant == 1.0) | (quadrant == 3.0)
    sin = jnp.where(swap, c, s)
    cos = jnp.where(swap, s, c)
    sin = jnp.where(quadrant >= 2.0, -sin, sin)
    cos = jnp.where((quadrant == 1.0) | (quadrant == 2.0), -cos, cos)
    return sin, cos


@sincos.defjvp
def _sincos_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    s, c = sincos(x)
    return (s, c), (c * dx, -s * dx)


def rot1(a):
    """Rotation by ``a`` about axis 1."""
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([o, z, z]), jnp.stack([z, c, -s]), jnp.stack([z, s, c])])


def rot2(a):
    """Rotation by ``a`` about axis 2."""
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([c, z, s]), jnp.stack([z, o, z]), jnp.stack([-s, z, c])])


def rot3(a):
    """Rotation by ``a`` about axis 3."""
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([c, -s, z]), jnp.stack([s, c, z]), jnp.stack([z, z, o])])


def skew(v):
    """Cross-product matrix: ``skew(v) @ w == cross(v, w)``."""
    z = jnp.zeros_like(v[0])
    return jnp.stack([jnp.stack([z, -v[2], v[1]]), jnp.stack([v[2], z, -v[0]]),
                      jnp.stack([-v[1], v[0], z])])


def rotvec_to_matrix(v):
    """Rotation matrix of the rotation vector ``v`` (Rodrigues), smooth and differentiable at 0."""
    v = jnp.asarray(v)
    a2 = jnp.dot(v, v)
    small = a2 < 1e-8
    a2s = jnp.where(small, 1.0, a2)
    a = jnp.sqrt(a2s)
    # sin(a)/a and (1 - cos a)/a^2 with Taylor branches near zero
    s = jnp.where(small, 1.0 - a2 / 6.0 + a2**2 / 120.0, jnp.sin(a) / a)
    c = jnp.where(small, 0.5 - a2 / 24.0 + a2**2 / 720.0, (1.0 - jnp.cos(a)) / a2s)
    k = skew(v)
    return jnp.eye(3) + s * k + c * (k @ k)


def euler321_to_matrix(chi):
    """``R3(chi3) @ R2(chi2) @ R1(chi1)`` for ``chi = (chi1, chi2, chi3)``: yaw, then pitch, then roll."""
    return rot3(chi[2]) @ rot2(chi[1]) @ rot1(chi[0])


def euler321_increment_to_rotvec(chi, dchi_euler):
    """Small rotation vector (in the rotated frame's components) produced by Euler-angle increments.

    For ``C = R3(chi3) R2(chi2) R1(chi1)``, ``C(chi + d) ~= C(chi) Rot(J d)`` with
    $J = \\begin{pmatrix}1&0&-\\sin\\chi_2\\\\0&\\cos\\chi_1&\\sin\\chi_1\\cos\\chi_2\\\\
    0&-\\sin\\chi_1&\\cos\\chi_1\\cos\\chi_2\\end{pmatrix}$ (docs/rigs/esg.md).
    """
    c1, s1 = jnp.cos(chi[0]), jnp.sin(chi[0])
    c2, s2 = jnp.cos(chi[1]), jnp.sin(chi[1])
    jac = jnp.array([[1.0, 0.0, -s2], [0.0, c1, s1 * c2], [0.0, -s1, c1 * c2]])
    return jac @ dchi_euler


def matrix_to_rotvec(mat):
    """Rotation vector of a rotation matrix (the inverse of :func:`rotvec_to_matrix`), for angles
    below pi (near pi the axis is ill-determined); smooth and differentiable at 0."""
    mat = jnp.asarray(mat)
    vee = 0.5 * jnp.stack([mat[2, 1] - mat[1, 2], mat[0, 2] - mat[2, 0], mat[1, 0] - mat[0, 1]])
    s2 = jnp.dot(vee, vee)
    small = s2 < 1e-12
    sin_a = jnp.sqrt(jnp.where(small, 1.0, s2))  # the double where keeps gradients finite at 0
    cos_a = 0.5 * (jnp.trace(mat) - 1.0)
    a = jnp.arctan2(sin_a, cos_a)
    ratio = jnp.where(small, 1.0 + s2 / 6.0, a / sin_a)
    return ratio * vee
