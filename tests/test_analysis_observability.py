import numpy as np
import pytest
from helpers import LAT, TS_24H, design

import gyrojax as gj
from gyrojax import units
from gyrojax.analysis.observability import analyse_jacobian, format_combination, observability

S, C = np.sin(np.radians(LAT)), np.cos(np.radians(LAT))
ERRS = {"theta1": 10 * units.ARCMIN, "theta2": 10 * units.ARCMIN}


def _report(scheme, alpha0, base_param="eps", method="regression"):
    rig, cond, p = design(scheme, base_param, alpha0_deg=alpha0, **ERRS)
    p = p | {n: p[n] + units.ARCMIN for n in rig.base_names}
    free = rig.regression_names if method == "regression" else \
        ("alpha10", "alpha20", *rig.regression_names)
    return observability(rig, p, cond, TS_24H, free=free, method=method)


def _comb(rep, text_names, coeffs, which="weak"):
    """Is the combination sum(coeffs * names) (natural units) in the identifiable row space?"""
    v = np.zeros(len(rep.names))
    for n, c in zip(text_names, coeffs):
        v[rep.names.index(n)] = c
    null = rep.null_weak if which == "weak" else rep.null_exact
    q, _ = np.linalg.qr(null.T)
    # identifiable <=> orthogonal to the null space (relative residual of the projection)
    return np.linalg.norm(q.T @ v) / np.linalg.norm(v)


def test_variant1_polar_small_angles():
    """(6.11): only mc1' = mc1 - theta1 - eps2 and mc2' = mc2 - theta2 + eps1 are identifiable
    among mc, theta, eps (four weak null directions, sigma ~ 1e-7 .. 2e-5)."""
    rep = _report("polar", (0, 0))
    assert rep.rank == 9 and rep.strong_rank == 6
    assert rep.null_weak.shape[0] == 4
    assert _comb(rep, ("mc1", "theta1", "eps2"), (1, -1, -1)) < 0.02
    assert _comb(rep, ("mc2", "theta2", "eps1"), (1, -1, 1)) < 0.02
    assert _comb(rep, ("mc1",), (1,)) > 0.5  # mc1 alone is not
    for n in ("m11", "m12", "m21", "m22"):
        assert _comb(rep, (n,), (1,)) < 0.05


def test_variant2_polar_large_angles_all_observable():
    rep = _report("polar", (20, 30))
    assert rep.rank == len(rep.names) == rep.strong_rank
    assert rep.singular_values[-1] == pytest.approx(1.4e-3, rel=0.3)


def test_variant3_equatorial_small_alpha2():
    """theta exactly unobservable; (6.12) mc2 + eps1 ... and the source's correction: m11 is not
    separable from mc2, eps3 either (null dm11 = 1, dmc2 = sin phi, deps3 = cos phi)."""
    rep = _report("equatorial", (0, 0))
    assert rep.unobservable == ["theta1", "theta2"]
    weak = [v for v in rep.null_weak if abs(v[rep.names.index("theta1")]) < 1e-6
            and abs(v[rep.names.index("theta2")]) < 1e-6]
    assert len(weak) == 1
    v = weak[0] / weak[0][rep.names.index("m11")]
    assert v[rep.names.index("mc2")] == pytest.approx(S, abs=0.01)
    assert v[rep.names.index("eps3")] == pytest.approx(C, abs=0.01)


def test_variant4_equatorial_large_alpha2():
    rep = _report("equatorial", (0, 30))
    assert rep.unobservable == ["theta1", "theta2"]
    assert rep.strong_rank == rep.rank == len(rep.names) - 2


@pytest.mark.parametrize("scheme", ["polar", "equatorial"])
def test_m11_aliases_eps_when_eps_is_free(scheme):
    """Spec correction 6: with eps unconstrained, dm11 = 1, deps = -g_zeta is an exact null
    direction of the exact-model trajectory Jacobian (m11 ~ eps)."""
    rep = _report(scheme, (10, 20), "eps_free", method="trajectory")
    assert rep.null_exact.shape[0] == 1
    v = rep.null_exact[0] / rep.null_exact[0][rep.names.index("m11")]
    g = {"polar": (-C, 0, -S), "equatorial": (-S, 0, -C)}[scheme]
    for i in range(3):
        assert v[rep.names.index(f"eps{i + 1}")] == pytest.approx(-g[i], abs=1e-6)
    assert rep.unobservable[0].startswith("m11 +")


@pytest.mark.parametrize("scheme", [pytest.param("vertical", marks=pytest.mark.slow),
                                    "horizontal"])  # the same law; one scheme in the default suite
def test_base_rotation_about_earth_axis_has_no_signature(scheme):
    """A base rotation about u does not change u: in the paper's model (3.1) (gravity not rotated
    with the base) dchi || u_zeta is an exact null direction of the trajectory Jacobian. In the
    exact model the same rotation turns g, so the direction is only weakly observable, at O(m)."""
    free = ("alpha10", "alpha20", "m11", "m12", "m21", "m22", "mc1", "mc2", "dchi1", "dchi2",
            "dchi3")
    _, cond, p = design(scheme, "rotvec", alpha0_deg=(0, 10))
    u = np.asarray(cond.base_vectors()[0])
    first = observability(gj.ESGRig(base_param="rotvec", order="first"), p, cond, TS_24H,
                          free=free)
    assert first.null_exact.shape[0] == 1
    v = first.null_exact[0]
    assert abs(v[-3:] @ u) / np.linalg.norm(v[-3:]) == pytest.approx(1.0, abs=1e-6)
    assert np.max(np.abs(v[:-3])) < 1e-6
    exact = observability(gj.ESGRig(base_param="rotvec"), p, cond, TS_24H, free=free,
                          weak_tol=2e-3)  # O(m/10) with m = 0.01; the next is 6e-3
    assert exact.null_exact.shape[0] == 0 and exact.null_weak.shape[0] == 1
    w = exact.null_weak[0][-3:]
    assert abs(w @ u) / np.linalg.norm(w) > 0.99


def test_format_and_bad_input():
    assert format_combination([1, 0, -1, -1], ["mc1", "x", "theta1", "eps2"]) == \
        "mc1 - theta1 - eps2"
    with pytest.raises(ValueError, match="4 names"):
        analyse_jacobian(np.ones((5, 3)), ["a", "b", "c", "d"])
    rig, cond, p = design("polar")
    with pytest.raises(ValueError, match="method='fisher'"):
        observability(rig, p, cond, TS_24H[:10], free=("m11",), method="fisher")


@pytest.mark.parametrize("eps,rank,unobservable", [(1e-9, 3, ["0.5 a - b - 0.5 c"]),
                                                   (2e-5, 4, []), (1e-2, 4, [])])
def test_rank_thresholds_on_a_constructed_near_null_direction(eps, rank, unobservable):
    """Columns a, b, c = a - 2 b + eps w, d (orthonormal a, b, w, d; d scaled by 4, which the
    column normalisation removes). After normalisation the Gram matrix has eigenvalues 2, 1, 1
    and ~eps^2 / 10, so the relative singular values are 1, 1/sqrt(2), 1/sqrt(2) and
    eps / sqrt(20) (to O(eps^2)), the last along a - 2 b - c (0.5 a - b - 0.5 c in the report's
    form). It is counted by the rank from exact_tol = 1e-6 up (eps = 2e-5: 4.5e-6) and by the
    strong rank from weak_tol = 1e-3."""
    t = np.linspace(0.0, 1.0, 200)
    v = np.linalg.qr(np.stack([np.sin(3 * t), np.cos(5 * t), t**2, np.ones_like(t)], 1))[0]
    j = np.stack([v[:, 0], v[:, 1], v[:, 0] - 2 * v[:, 1] + eps * v[:, 2], 4.0 * v[:, 3]], 1)
    r = analyse_jacobian(j, ["a", "b", "c", "d"])
    np.testing.assert_allclose(r.singular_values,
                               [1.0, 2**-0.5, 2**-0.5, eps / np.sqrt(20)], rtol=1e-5)
    assert r.rank == rank and r.unobservable == unobservable
    assert r.strong_rank == (4 if eps / np.sqrt(20) >= 1e-3 else 3)
    assert r.weak == ([] if r.strong_rank == 4 else ["0.5 a - b - 0.5 c"])
