"""Extremes and bad input: degenerate geometry returns finite values by a documented
rule; extremes give finite outputs and PSD filters, with no warnings from NumPy.

Every kernel call here runs with NumPy floating-point errors (divide, overflow, invalid)
and Python warnings turned into exceptions (``element_helpers.no_numpy_warnings``).

Documented rules checked:
* bend, sin(theta) < bend.STRAIGHT_TOL (straight theta = pi, or folded back theta = 0):
  gradient 0; Hessian (every filter) = D^T k [[P/L0^2, -c P/(L0 L1)], [-c P/(L0 L1), P/L1^2]] D,
  P = I - t0 t0^T, c = sign(t0.t1); energy 1/2 k (theta - thetabar)^2 with theta = pi or 0;
* twist, |a| < DEGENERATE_TOL |e0| or |b| < DEGENERATE_TOL |e2|: energy, gradient and
  Hessian zero;
* twist, the rest weight (``twist.rest_weight``): 0 for a straight or nearly straight
  rest stencil (sine below half the configured one), 1 from the configured sine on, a
  smooth step between;
* twist with a parallel or antiparallel to b (phi = 0 or pi, a planar stencil, and
  nearly so): phi is smooth there, so gradient and exact Hessian must match finite
  differences of a signed-angle reference, and the filtered Hessians must stay of the size
  of the exact one (no 1/sin(phi) stiffness);
* batches larger than the kernels' internal chunks name the global element index;
* zero-length edge, non-finite position, wrong shape, negative / non-finite stiffness,
  non-positive rest length, non-finite rest angle, unknown filter: ValueError naming the
  element and saying what is wrong.
"""

import re

import numpy as np
import pytest

from lc_petsc.elements import FILTERS, bend, stretch, twist

import element_helpers as eh

MODULES = {"stretch": stretch, "bend": bend, "twist": twist}
PSD_TOL = 1e-10


def _evaluate(mod, x, rest, k):
    """energy, gradient and all Hessians, with warnings as errors; all finite."""
    with eh.no_numpy_warnings():
        E = mod.energy(x, rest, k)
        g = mod.gradient(x, rest, k)
        H = {f: mod.hessian(x, rest, k, filter=f) for f in FILTERS}
    assert np.all(np.isfinite(E)) and np.all(np.isfinite(g))
    for f, Hf in H.items():
        assert np.all(np.isfinite(Hf)), f
    for f in ("analytic", "numerical"):
        r = eh.min_eig_ratio(H[f])
        assert np.all(r >= -PSD_TOL), f"{f}: min eig / max |eig| = {r.min():.3e}"
    return E, g, H


def _bend_iso(x, k):
    """Documented degenerate bend Hessian, one element, from the own geometry."""
    e0, e1 = x[0] - x[1], x[2] - x[1]
    L0, L1 = np.linalg.norm(e0), np.linalg.norm(e1)
    t0 = e0 / L0
    P = np.eye(3) - np.outer(t0, t0)
    c = np.sign(t0 @ (e1 / L1))
    HT = k * np.block([[P / L0**2, -c * P / (L0 * L1)], [-c * P / (L0 * L1), P / L1**2]])
    D = eh.bend_D()
    return D.T @ HT @ D


# ------------------------------------------------------------------------------ bend
def _collinear_bends(rng, n, folded, exact_axis):
    out = []
    for i in range(n):
        if exact_axis:
            u = np.eye(3)[i % 3] * (1 if i % 2 else -1)
            c = np.array([1.0, -2.0, 0.5]) * (i + 1)
            L0, L1 = 2.0 ** rng.integers(-20, 10, 2)
        else:
            u = eh.unit(rng.standard_normal(3))
            c = rng.uniform(-1, 1, 3)
            L0, L1 = 10 ** rng.uniform(-3, 2, 2)
        out.append([c + L0 * u, c, c + (L1 if folded else -L1) * u])
    return np.array(out)


@pytest.mark.parametrize("exact_axis", [True, False])
@pytest.mark.parametrize("folded", [False, True])
def test_bend_straight_and_folded_rule(folded, exact_axis):
    rng = np.random.default_rng(300 + 2 * folded + exact_axis)
    n = 9
    x = _collinear_bends(rng, n, folded, exact_axis)
    theta_exact = 0.0 if folded else np.pi
    th = bend.angle(x)
    if exact_axis:
        np.testing.assert_array_equal(th, theta_exact)
    else:
        np.testing.assert_allclose(th, theta_exact, atol=1e-11)   # round-off of x - c
    k = 10 ** rng.uniform(-6, 12, n)
    rest = rng.uniform(0.1, np.pi - 0.1, n)
    rest[0] = theta_exact      # rest shape straight (or folded) too
    E, g, H = _evaluate(bend, x, rest, k)
    np.testing.assert_allclose(E, 0.5 * k * (th - rest) ** 2, rtol=1e-13)
    np.testing.assert_array_equal(g, 0.0)
    for f in FILTERS:
        for i in range(n):
            ref = _bend_iso(x[i], k[i])
            err = eh.rel_fro(H[f][i:i + 1], ref[None])[0]
            assert err < 1e-12, f"{f} element {i}: {err:.2e}"


@pytest.mark.parametrize("s", [1e-7, 1e-9, 1e-12])
@pytest.mark.parametrize("near", ["straight", "folded"])
def test_bend_near_straight_and_folded(s, near):
    rng = np.random.default_rng(310)
    n = 8
    xs = []
    delta = np.arcsin(s)
    for i in range(n):
        t0 = eh.unit(rng.standard_normal(3))
        p = eh.unit(np.cross(t0, rng.standard_normal(3)))
        ang = np.pi - delta if near == "straight" else delta
        t1 = np.cos(ang) * t0 + np.sin(ang) * p
        L0, L1 = 10 ** rng.uniform(-3, 1, 2)
        xs.append(eh.bend_from_units(t0, t1, np.zeros(3), L0, L1))
    x = np.array(xs)
    theta_expect = np.pi - delta if near == "straight" else delta
    th = bend.angle(x)
    np.testing.assert_allclose(th, theta_expect, rtol=0, atol=1e-6 * s + 1e-15)
    k = np.full(n, 3.0)
    for rest in (np.full(n, 2.0), np.full(n, theta_expect), np.full(n, np.pi if near == "straight" else 0.0)):
        E, g, H = _evaluate(bend, x, rest, k)
        np.testing.assert_allclose(E, 0.5 * k * (th - rest) ** 2, rtol=1e-12, atol=1e-300)
        if s < bend.STRAIGHT_TOL:
            np.testing.assert_array_equal(g, 0.0)
            for i in range(n):
                assert eh.rel_fro(H["analytic"][i:i + 1], _bend_iso(x[i], k[i])[None])[0] < 1e-10
        else:
            gref = eh.ref_bend_gradient(x, rest, k)
            # |g| ~ k |theta - rest| / L; when rest == theta both are round-off
            Lmin = np.minimum(np.linalg.norm(x[:, 0] - x[:, 1], axis=1), np.linalg.norm(x[:, 2] - x[:, 1], axis=1))
            tol = (1e-6 * np.abs(gref).max(axis=(1, 2)) + 1e-12 * k / Lmin)[:, None, None]
            assert np.all(np.abs(g - gref) <= tol), np.abs(g - gref).max()


def test_bend_very_different_edge_lengths():
    rng = np.random.default_rng(320)
    n = 10
    x = eh.random_bend(rng, n, 1.0)
    t0, t1 = eh.unit(x[:, 0] - x[:, 1]), eh.unit(x[:, 2] - x[:, 1])
    L = [(1e-6, 1e3) if i % 2 else (1e3, 1e-6) for i in range(n)]
    x = np.stack([eh.bend_from_units(t0[i], t1[i], x[i, 1], *L[i]) for i in range(n)])
    rest = np.clip(bend.angle(x) + 0.5, 0, np.pi)
    k = np.full(n, 2.0)
    E, g, H = _evaluate(bend, x, rest, k)
    gref = eh.ref_bend_gradient(x, rest, k)
    np.testing.assert_allclose(g, gref, rtol=1e-8, atol=1e-10 * np.abs(gref).max())


# ------------------------------------------------------------------------------ twist
def _twist_with_ab_ratio(rng, ratio_a, ratio_b, L=(1.0, 1.0, 1.0)):
    e1 = eh.unit(rng.standard_normal(3)) * L[1]
    def outer(ratio, length):
        p = eh.unit(np.cross(e1, rng.standard_normal(3)))
        ax = np.sqrt(max(1 - ratio**2, 0.0))
        return length * (ratio * p + ax * eh.unit(e1) * rng.choice([-1, 1]))
    e0 = outer(ratio_a, L[0])
    e2 = outer(ratio_b, L[2])
    x1 = rng.uniform(-1, 1, 3)
    return np.array([x1 + e0, x1, x1 + e1, x1 + e1 + e2])


@pytest.mark.parametrize("which", ["a", "b", "both"])
def test_twist_collinear_outer_edge_rule(which):
    rng = np.random.default_rng(330)
    n = 6
    xs = []
    for i in range(n):
        ra = 0.0 if which in ("a", "both") else 0.7
        rb = 0.0 if which in ("b", "both") else 0.7
        xs.append(_twist_with_ab_ratio(rng, ra, rb, L=10 ** rng.uniform(-3, 2, 3)))
    # plus a perfectly straight strand on a coordinate axis (a = b = 0 exactly)
    xs.append(np.array([[0, 0, 0], [0, 0, 1.0], [0, 0, 2.5], [0, 0, 3.0]]))
    x = np.array(xs)
    rest = np.full(len(x), 0.25)
    E, g, H = _evaluate(twist, x, rest, 1e3)
    np.testing.assert_array_equal(E, 0.0)
    np.testing.assert_array_equal(g, 0.0)
    for f in FILTERS:
        np.testing.assert_array_equal(H[f], 0.0)
    with eh.no_numpy_warnings():
        phi = twist.angle(x)
        gW = twist.w_gradient(x, rest, 1e3)
    assert np.all(np.isfinite(phi))
    np.testing.assert_array_equal(gW, 0.0)


@pytest.mark.parametrize("ratio", [1e-12, 1e-7, 1e-5, 1e-3])
def test_twist_nearly_collinear_outer_edge(ratio):
    rng = np.random.default_rng(340)
    n = 6
    x = np.array([_twist_with_ab_ratio(rng, ratio if i % 2 else 0.6, 0.6 if i % 2 else ratio)
                  for i in range(n)])
    rest = eh.wrap(eh.ref_twist_angle(x) + 0.5)
    k = np.full(n, 2.0)
    E, g, H = _evaluate(twist, x, rest, k)
    if ratio < twist.DEGENERATE_TOL:
        np.testing.assert_array_equal(E, 0.0)
        np.testing.assert_array_equal(g, 0.0)
        for f in FILTERS:
            np.testing.assert_array_equal(H[f], 0.0)
    else:
        np.testing.assert_allclose(E, eh.ref_twist_energy(x, rest, k), rtol=1e-8)
        gref = eh.ref_twist_gradient(x, rest, k)
        np.testing.assert_allclose(g, gref, rtol=0, atol=1e-7 * np.abs(gref).max())


def test_twist_rest_weight():
    """twist.rest_weight: 0 up to half the sine (a straight or noisy-straight rest
    stencil), exactly 1 from the sine on, the smooth step t^2 (3 - 2 t) of t = 2 s / sine - 1
    between (s the smaller of |a| / |e0| and |b| / |e2|), continuous and monotone; sine 0:
    all ones; bad sine: an error."""
    rng = np.random.default_rng(350)
    sine = 0.05
    ratios = np.array([0.0, 1e-9, 1e-4, 1e-2, 0.025, 0.03, 0.0375, 0.0499, 0.05, 0.3, 0.99])
    x = np.array([_twist_with_ab_ratio(rng, r if i % 2 else 0.8, 0.8 if i % 2 else r,
                                       L=10 ** rng.uniform(-2, 1, 3))
                  for i, r in enumerate(ratios)])
    with eh.no_numpy_warnings():
        w = twist.rest_weight(x, sine)
    t = np.clip(2 * ratios / sine - 1, 0.0, 1.0)
    np.testing.assert_allclose(w, t * t * (3 - 2 * t), rtol=1e-9, atol=1e-12)
    assert np.all(w[ratios <= sine / 2] == 0.0) and np.all(w[ratios >= sine] == 1.0)
    assert w[6] == pytest.approx(0.5, abs=1e-9)              # the step's middle
    assert np.all(np.diff(w) >= 0)
    # continuous: a small change of the rest stencil changes the weight a little
    s = np.linspace(0.0, 2 * sine, 4001)
    tt = np.clip(2 * s / sine - 1, 0, 1)
    assert np.abs(np.diff(tt * tt * (3 - 2 * tt))).max() < 4 * (s[1] - s[0]) / sine
    np.testing.assert_array_equal(twist.rest_weight(x, 0.0), 1.0)
    for bad in (-0.1, 1.0, np.nan):
        with pytest.raises(ValueError, match="twist rest sine"):
            twist.rest_weight(x, bad)


def _planar_twists(rng, n, phi0):
    out = []
    for i in range(n):
        e1 = eh.unit(rng.standard_normal(3)) * rng.uniform(0.5, 2)
        p = eh.unit(np.cross(e1, rng.standard_normal(3)))
        a = p * rng.uniform(0.5, 2)
        b = (np.cos(phi0) * p + np.sin(phi0) * np.cross(eh.unit(e1), p)) * rng.uniform(0.5, 2)
        out.append(eh.twist_from_ab(a, b, e1, rng.uniform(-1, 1, 3)))
    return np.array(out)


def _signed_twist_gradient(x, rest, k):
    """Reference gradient from the signed-angle formulas (smooth through phi = 0, pi):
    dphi/da = -(e1h x a)/|a|^2, dphi/db = (e1h x b)/|b|^2, mapped with the exact J."""
    e0, e1, e2, a, b = eh.ref_twist_parts(x)
    e1h = eh.unit(e1)
    ga = -np.cross(e1h, a) / np.sum(a * a, axis=1, keepdims=True)
    gb = np.cross(e1h, b) / np.sum(b * b, axis=1, keepdims=True)
    d = (k * eh.wrap(eh.ref_twist_angle(x) - rest))[:, None]
    gW = np.concatenate([d * ga, d * gb, 0 * ga], axis=1)
    return np.stack([eh.ref_twist_J(x[i]).T @ gW[i] for i in range(len(x))]).reshape(len(x), 4, 3)


def test_signed_twist_gradient_reference_agrees_with_spec_form():
    rng = np.random.default_rng(349)
    x = eh.random_twist(rng, 10, 1.0)
    rest = eh.wrap(eh.ref_twist_angle(x) + 0.7)
    np.testing.assert_allclose(_signed_twist_gradient(x, rest, 1.5), eh.ref_twist_gradient(x, rest, 1.5),
                               atol=1e-12)


PLANAR_PHI = [0.0, np.pi, 1e-7, np.pi - 1e-7, 1e-12]


def _planar_case(phi0):
    rng = np.random.default_rng(350)
    n = 6
    x = _planar_twists(rng, n, phi0)
    return x, np.full(n, 0.25), np.full(n, 2.0)


@pytest.mark.parametrize("phi0", PLANAR_PHI)
def test_twist_planar_stencil_finite_psd_and_gradient(phi0):
    """a parallel (phi = 0) or antiparallel (phi = pi) to b, and nearly so: torsion is well
    defined and smooth there (signed angle); finite, PSD, no warnings, right gradient."""
    x, rest, k = _planar_case(phi0)
    E, g, H = _evaluate(twist, x, rest, k)
    np.testing.assert_allclose(E, eh.ref_twist_energy(x, rest, k), rtol=1e-10)
    gref = _signed_twist_gradient(x, rest, k)
    np.testing.assert_allclose(g, gref, rtol=0, atol=1e-7 * np.abs(gref).max())


@pytest.mark.parametrize("phi0", PLANAR_PHI)
def test_twist_planar_stencil_exact_hessian(phi0):
    """filter="none" is documented as the exact Hessian; Psi_t(x) is smooth at a planar
    stencil, so it must match finite differences of the (smooth) signed-angle gradient."""
    x, rest, k = _planar_case(phi0)
    with eh.no_numpy_warnings():
        H = twist.hessian(x, rest, k, filter="none")
    Hfd = eh.fd_hessian_of_gradient(lambda y: _signed_twist_gradient(y, rest, k), x, 1e-6)
    err = eh.rel_fro(H, Hfd)
    print(f"phi0={phi0!r}: |H_none - H_fd| / |H_fd| = {np.array2string(err, precision=2)}")
    assert np.all(err < 1e-6), f"exact Hessian vs FD at phi = {phi0}: {err}"


@pytest.mark.parametrize("phi0", PLANAR_PHI + [1e-2, 1e-4])
def test_twist_planar_stencil_filtered_hessian_is_bounded(phi0):
    """The filtered Hessians should stay of the size of the exact one near a planar stencil
    (the exact Hessian is bounded there); a spurious 1/sin(phi) stiffness would make the
    Newton matrix arbitrarily ill-conditioned."""
    x, rest, k = _planar_case(phi0)
    n = len(x)
    Hfd = eh.fd_hessian_of_gradient(lambda y: _signed_twist_gradient(y, rest, k), x, 1e-6)
    for f in ("analytic", "numerical"):
        with eh.no_numpy_warnings():
            Hf = twist.hessian(x, rest, k, filter=f)
        ratio = np.linalg.norm(Hf.reshape(n, -1), axis=1) / np.linalg.norm(Hfd.reshape(n, -1), axis=1)
        print(f"phi0={phi0!r} {f}: |H_filtered| / |H_exact| = {np.array2string(ratio, precision=3)}")
        assert np.all(ratio < 3), f"{f} at phi0 = {phi0}: |H_f|/|H| = {ratio}"


def test_twist_very_different_edge_lengths():
    rng = np.random.default_rng(360)
    xs = []
    for L in [(1e-6, 1.0, 1e3), (1e3, 1e-6, 1.0), (1.0, 1e3, 1e-6), (1e-6, 1e3, 1e-6)]:
        for _ in range(3):
            xs.append(_twist_with_ab_ratio(rng, 0.6, 0.8, L=L))
    x = np.array(xs)
    rest = eh.wrap(eh.ref_twist_angle(x) + 0.4)
    k = np.full(len(x), 2.0)
    E, g, H = _evaluate(twist, x, rest, k)
    np.testing.assert_allclose(E, eh.ref_twist_energy(x, rest, k), rtol=1e-8)
    gref = eh.ref_twist_gradient(x, rest, k)
    for i in range(len(x)):
        np.testing.assert_allclose(g[i], gref[i], rtol=0, atol=1e-7 * np.abs(gref[i]).max())


# --------------------------------------------------------- stiffness x length grid
@pytest.mark.parametrize("term", eh.TERMS)
def test_stiffness_and_length_ranges(term):
    rng = np.random.default_rng(370 + eh.TERMS.index(term))
    mod = MODULES[term]
    for scale in (1e-6, 1e-3, 1.0, 1e3):
        x, rest, _ = eh.random_case(term, rng, 6, scale)
        if term == "stretch":
            rest = stretch.length(x) * rng.uniform(0.5, 1.5, 6)
        for k in (1e-6, 1.0, 1e12):
            E, g, H = _evaluate(mod, x, rest, k)
            np.testing.assert_allclose(E, eh.REF_ENERGY[term](x, rest, k), rtol=1e-8)
            gref = eh.REF_GRADIENT[term](x, rest, k)
            np.testing.assert_allclose(g, gref, rtol=0, atol=1e-8 * np.abs(gref).max())
    # a zero stiffness is allowed (not negative): everything zero
    E, g, H = _evaluate(mod, x, rest, 0.0)
    np.testing.assert_array_equal(E, 0.0)
    np.testing.assert_array_equal(g, 0.0)
    for f in FILTERS:
        np.testing.assert_array_equal(H[f], 0.0)


def test_stretch_extreme_lengths():
    rng = np.random.default_rng(380)
    for L, rest_factor in [(1e-6, 1e9), (1e3, 1e-9), (1e-6, 0.5), (1e3, 2.0)]:
        x, _ = eh.random_stretch(rng, 5, L)
        rest = stretch.length(x) * rest_factor
        E, g, H = _evaluate(stretch, x, rest, 1.0)
        np.testing.assert_allclose(g, eh.ref_stretch_gradient(x, rest, 1.0), rtol=1e-10)


# ------------------------------------------------------------------------ bad input
BAD_IDX = 7
NB = 10


def _good(term, rng):
    x, rest, k = eh.random_case(term, rng, NB, 1.0)
    return x, rest, k


def _calls(mod):
    yield "energy", lambda x, r, k: mod.energy(x, r, k)
    yield "gradient", lambda x, r, k: mod.gradient(x, r, k)
    for f in FILTERS:
        yield f"hessian/{f}", lambda x, r, k, f=f: mod.hessian(x, r, k, filter=f)


def _expect_error(fn, args, what, index=BAD_IDX, words=None):
    with pytest.raises(ValueError) as info:
        with eh.no_numpy_warnings():
            fn(*args)
    msg = str(info.value)
    if index is not None:
        assert re.search(rf"\b{index}\b", msg), f"{what}: message does not name element {index}: {msg!r}"
    if words is not None:
        assert re.search(words, msg, re.I), f"{what}: message does not say what is wrong: {msg!r}"


ZERO_EDGE_CASES = {
    "stretch": [(1, 0)],                      # x1 := x0
    "bend": [(0, 1), (2, 1)],                 # e0 = 0, e1 = 0
    "twist": [(0, 1), (2, 1), (3, 2)],        # e0 = 0, e1 = 0, e2 = 0
}


@pytest.mark.parametrize("term", eh.TERMS)
def test_zero_length_edge_is_an_error(term):
    rng = np.random.default_rng(390)
    mod = MODULES[term]
    x, rest, k = _good(term, rng)
    for dst, src in ZERO_EDGE_CASES[term]:
        y = x.copy()
        y[BAD_IDX, dst] = y[BAD_IDX, src]
        for name, fn in _calls(mod):
            _expect_error(fn, (y, rest, k), f"{term} {name} zero edge {dst}-{src}",
                          words=r"zero|length|coincid")
        # round-off-sized edge far from the origin counts as zero too
        y = x.copy() + 1e3
        y[BAD_IDX, dst] = y[BAD_IDX, src]
        y[BAD_IDX, dst, 0] = np.nextafter(y[BAD_IDX, src, 0], np.inf)   # |e| = 1 ulp of 1e3
        _expect_error(lambda *a: mod.gradient(*a), (y, rest, k), f"{term} 1-ulp edge",
                      words=r"zero|length|coincid")


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("term", eh.TERMS)
def test_non_finite_position_is_an_error(term, bad):
    rng = np.random.default_rng(400)
    mod = MODULES[term]
    x, rest, k = _good(term, rng)
    x[BAD_IDX, 1, 2] = bad
    for name, fn in _calls(mod):
        _expect_error(fn, (x, rest, k), f"{term} {name} {bad}", words=r"finite|nan|inf")


@pytest.mark.parametrize("term", eh.TERMS)
def test_wrong_shape_is_an_error(term):
    rng = np.random.default_rng(410)
    mod = MODULES[term]
    x, rest, k = _good(term, rng)
    nv = eh.NVERT[term]
    shapes = [
        x[:, :, :2],                     # (n, k, 2)
        x.reshape(NB * nv, 3),           # 2-D
        x[0],                            # one element without the batch axis
        np.zeros((NB, nv + 1, 3)) + np.arange(nv + 1)[None, :, None],   # wrong vertex count
        x.reshape(NB, nv, 3, 1),         # 4-D
    ]
    for y in shapes:
        for name, fn in _calls(mod):
            _expect_error(fn, (y, rest, k), f"{term} {name} shape {y.shape}", index=None,
                          words=r"shape")


@pytest.mark.parametrize("term", eh.TERMS)
def test_bad_stiffness_is_an_error(term):
    rng = np.random.default_rng(420)
    mod = MODULES[term]
    x, rest, k = _good(term, rng)
    for bad in (-1.0, -1e-300, np.nan, np.inf):
        kk = k.copy()
        kk[BAD_IDX] = bad
        for name, fn in _calls(mod):
            _expect_error(fn, (x, rest, kk), f"{term} {name} stiffness {bad}", words=r"stiff")
    # a negative scalar stiffness is rejected too
    with pytest.raises(ValueError, match="(?i)stiff"):
        mod.energy(x, rest, -2.0)


@pytest.mark.parametrize("term", eh.TERMS)
def test_unknown_filter_is_an_error(term):
    rng = np.random.default_rng(430)
    mod = MODULES[term]
    x, rest, k = _good(term, rng)
    for bad in ("Analytic", "eigen", "exact", ""):
        _expect_error(lambda *a: mod.hessian(*a, filter=bad), (x, rest, k), f"{term} filter {bad!r}",
                      index=None, words=r"filter")


@pytest.mark.parametrize("term", eh.TERMS)
def test_bad_rest_quantity_is_an_error(term):
    """docs/elements.md: non-positive rest length (stretch), non-finite rest angle."""
    rng = np.random.default_rng(440)
    mod = MODULES[term]
    x, rest, k = _good(term, rng)
    bads = (0.0, -1.0, np.nan, np.inf) if term == "stretch" else (np.nan, np.inf, -np.inf)
    for bad in bads:
        r = rest.copy()
        r[BAD_IDX] = bad
        for name, fn in _calls(mod):
            _expect_error(fn, (x, r, k), f"{term} {name} rest {bad}", words=r"rest")


@pytest.mark.parametrize("term", eh.TERMS)
def test_error_index_is_global_in_large_batches(term):
    """Kernels work chunk by chunk; the element named must be the global index."""
    rng = np.random.default_rng(450)
    mod = MODULES[term]
    x, rest, k = eh.random_case(term, rng, 9000, 1.0)
    bad = 8765
    dst, src = ZERO_EDGE_CASES[term][-1]
    y = x.copy()
    y[bad, dst] = y[bad, src]
    for name, fn in _calls(mod):
        _expect_error(fn, (y, rest, k), f"{term} {name} zero edge at {bad}", index=bad,
                      words=r"zero|length|coincid")
    kk = k.copy()
    kk[bad] = -1.0
    _expect_error(lambda *a: mod.hessian(*a), (x, rest, kk), f"{term} stiffness at {bad}", index=bad)


@pytest.mark.parametrize("term,k", [("stretch", 2), ("bend", 3), ("twist", 4)])
def test_empty_batch(term, k):
    """A rank may hold no element of a term: every kernel takes n = 0."""
    mod = {"stretch": stretch, "bend": bend, "twist": twist}[term]
    x = np.zeros((0, k, 3))
    rest, stiff = np.zeros(0) + 1.0, np.zeros(0)
    assert mod.energy(x, rest, stiff).shape == (0,)
    g, h = mod.gradient_hessian(x, rest, stiff)
    assert g.shape == (0, k, 3) and h.shape == (0, 3 * k, 3 * k)
