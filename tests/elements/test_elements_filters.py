"""Hessian filters (SPEC section 3; docs/elements.md).

* "analytic" and "numerical" are PSD to round-off (min eig >= -1e-10 max |eig|) on random
  configurations, on crushed ones (stretch compressed 10x, bends/twists far from rest) and
  on the elements of a 4C helix wisp smashed to 40% in x or jittered by +-0.5 cm (SPEC
  section 6, "Smash" and "Jitter");
* both equal the exact Hessian when that is already PSD (stretched edges; bend/twist at rest);
* analytic == numerical where the closed form is an exact projection: stretch always, bend
  with |e0| == |e1|; both also equal independent references built here (eigh-clamp of the
  3x3 Hessian in e; clamped SPEC eigensystem scaled by S, mapped with D);
* bend "analytic" is S Hhat^+ S for any lengths; "numerical" is the eigh-projection of the
  exact reduced Hessian in T (bend) or of the exact 12x12 Hessian (twist);
* twist: docs/elements.md ships, instead of SPEC's split P^T H_W^+ P - Dt^T H_W^- Dt (which
  grows like 1/sin(phi) at planar stencils, measured here), the in-plane pairs plus the PSD
  part of each out-of-plane rank-2 term; checked against an eigh-based reference, with
  |a| == |b| and without (it is not the exact projection even for |a| == |b|);
* the analytic/numerical relative Frobenius difference is measured against the length ratio,
  printed, and bounded (bend: zero at ratio 1);
* filter names are validated and the default is "analytic".
"""

import numpy as np
import pytest

from lc_petsc.elements import FILTERS, bend, stretch, twist

import element_helpers as eh

MODULES = {"stretch": stretch, "bend": bend, "twist": twist}
PSD_TOL = 1e-10
N = 40


def _assert_psd(H, what):
    r = eh.min_eig_ratio(H)
    assert np.all(np.isfinite(H)), f"{what}: non-finite entries"
    assert np.all(r >= -PSD_TOL), f"{what}: min eig / max |eig| = {r.min():.3e} (element {np.argmin(r)})"


def _crushed_case(term, rng, n):
    if term == "stretch":
        x, _ = eh.random_stretch(rng, n, 1.0)
        rest = 10.0 * stretch.length(x)           # compressed to 10% of rest length
        return x, rest, rng.uniform(0.5, 2, n)
    if term == "bend":
        x = eh.random_bend(rng, n, 1.0, min_sin=0.05)
        th = eh.ref_bend_angle(x)
        rest = np.where(th > np.pi / 2, 0.05, np.pi - 0.05)  # folded far from rest
        return x, rest, rng.uniform(0.5, 2, n)
    x = eh.random_twist(rng, n, 1.0, min_ratio=0.05, min_sin=0.05)
    rest = eh.wrap(eh.ref_twist_angle(x) + np.pi - 0.05)     # twisted almost half a turn
    return x, rest, rng.uniform(0.5, 2, n)


def _smashed_wisp_case(term, compress=0.4):
    w = eh.helix_wisp(24)
    k = {"stretch": 2, "bend": 3, "twist": 4}[term]
    xr = eh.stencils(w, k)
    ws = w.copy()
    ws[:, 0] *= compress
    xs = eh.stencils(ws, k)
    if term == "stretch":
        rest = np.linalg.norm(xr[:, 1] - xr[:, 0], axis=1)   # rest lengths
    elif term == "bend":
        rest = eh.ref_bend_angle(xr)
    else:
        rest = eh.ref_twist_angle(xr)
    return xs, rest, np.ones(len(xs))


@pytest.mark.parametrize("flt", ["analytic", "numerical"])
@pytest.mark.parametrize("kind", ["random", "crushed", "smash", "jitter"])
@pytest.mark.parametrize("term", eh.TERMS)
def test_filtered_hessians_are_psd(term, kind, flt):
    rng = np.random.default_rng(100 + eh.TERMS.index(term) * 10 + len(kind))
    mod = MODULES[term]
    if kind == "random":
        x, rest, k = eh.random_case(term, rng, N, 1.0)
    elif kind == "crushed":
        x, rest, k = _crushed_case(term, rng, N)
    elif kind == "smash":
        x, rest, k = _smashed_wisp_case(term, 0.4)
    else:  # jitter scene: uniform offsets in [-0.5, 0.5] cm on a 0.6 cm-edge helix
        w = eh.helix_wisp(24)
        nk = eh.NVERT[term]
        _, rest, k = _smashed_wisp_case(term, 1.0)
        x = eh.stencils(w + rng.uniform(-0.5, 0.5, w.shape), nk)
    H = mod.hessian(x, rest, k, filter=flt)
    _assert_psd(H, f"{term}/{kind}/{flt}")
    # and the exact Hessian really is indefinite on these cases, else the test is vacuous
    if kind in ("crushed", "random"):
        assert np.any(eh.min_eig_ratio(mod.hessian(x, rest, k, filter="none")) < -1e-3)


# ----------------------------------------------------------- equal to exact when PSD
def test_filters_equal_exact_hessian_when_it_is_psd():
    rng = np.random.default_rng(110)
    cases = {}
    x, _ = eh.random_stretch(rng, N, 1.0)
    cases["stretch"] = (x, stretch.length(x) * rng.uniform(0.3, 0.99, N))   # stretched
    x = eh.random_bend(rng, N, 1.0)
    cases["bend"] = (x, bend.angle(x))                                       # at rest
    x = eh.random_twist(rng, N, 1.0)
    cases["twist"] = (x, twist.angle(x))                                     # at rest
    for term, (x, rest) in cases.items():
        mod = MODULES[term]
        k = rng.uniform(0.5, 2, N)
        H = mod.hessian(x, rest, k, filter="none")
        _assert_psd(H, f"{term} exact at rest")
        assert np.abs(H).max() > 0
        for flt in ("analytic", "numerical"):
            Hf = mod.hessian(x, rest, k, filter=flt)
            err = eh.rel_fro(Hf, H)
            assert np.all(err < 1e-10), f"{term}/{flt}: {err.max():.2e}"


# ------------------------------------------------------- analytic == numerical (exact)
def _bend_ref_filtered(x, rest, k, how):
    """Independent reference: vertex Hessian D^T H_T^+ D, with H_T^+ either
    S Hhat^+ S (closed form, 'analytic') or eigh-clamp of S Hhat S ('numerical')."""
    D = eh.bend_D()
    out = []
    for i in range(len(x)):
        e0, e1 = x[i, 0] - x[i, 1], x[i, 2] - x[i, 1]
        L0, L1 = np.linalg.norm(e0), np.linalg.norm(e1)
        d = k[i] * (eh.ref_theta(e0, e1) - rest[i])
        lam, Q = eh.spec_psi_eigensystem(e0 / L0, e1 / L1, k[i], d)
        S = np.diag(np.r_[np.full(3, 1 / L0), np.full(3, 1 / L1)])
        if how == "analytic":
            HT = S @ ((Q * np.maximum(lam, 0)) @ Q.T) @ S
        else:
            w, V = np.linalg.eigh(S @ ((Q * lam) @ Q.T) @ S)
            HT = (V * np.maximum(w, 0)) @ V.T
        out.append(D.T @ HT @ D)
    return np.array(out)


def _twist_exact_pairs(xi, rest_i, k_i):
    """Per-eigenpair contributions of the exact twist Hessian, one element, from the own
    SPEC eigensystem: lam_j (u u^T - w w^T) with u = P^T S q_j, w = Dt^T S q_j."""
    HW, lam, Q, S = eh.spec_twist_H_W(xi, rest_i, k_i)
    P = eh.ref_twist_P(xi)
    Dt = P - eh.ref_twist_J(xi)
    out = []
    for j in range(6):
        v = np.r_[S @ Q[:, j], np.zeros(3)]
        out.append((lam[j], P.T @ v, Dt.T @ v))
    return out


def _psd_part(M):
    w, V = np.linalg.eigh(0.5 * (M + M.T))
    return (V * np.maximum(w, 0)) @ V.T


def _twist_ref_filtered(x, rest, k, how):
    """Independent references for the twist Hessians (docs/elements.md, twist.py doc):
    'exact'      sum_j lam_j (u u^T - w w^T) = P^T H_W P - Dt^T H_W Dt;
    'analytic'   in-plane pairs (w = 0) with lam^+, plus the PSD part (eigh here) of each
                 out-of-plane rank-2 contribution;
    'numerical'  eigh-clamp of the exact 12x12 vertex Hessian;
    'spec_split' SPEC section 2's suggestion P^T H_W^+ P - Dt^T H_W^- Dt."""
    out = []
    for i in range(len(x)):
        H = np.zeros((12, 12))
        for j, (lam, u, w) in enumerate(_twist_exact_pairs(x[i], rest[i], k[i])):
            M = lam * (np.outer(u, u) - np.outer(w, w))
            if how in ("exact", "numerical"):
                H += M
            elif how == "analytic":
                if j >= 2:   # in-plane pairs do not reach Dt
                    assert np.abs(w).max() <= 1e-12 * max(1.0, np.abs(u).max())
                H += _psd_part(M)
            elif how == "spec_split":
                H += max(lam, 0) * np.outer(u, u) - min(lam, 0) * np.outer(w, w)
        out.append(_psd_part(H) if how == "numerical" else H)
    return np.array(out)


def test_stretch_analytic_equals_numerical_always():
    rng = np.random.default_rng(120)
    x, _ = eh.random_stretch(rng, N, 1.0)
    rest = stretch.length(x) * rng.uniform(0.2, 5.0, N)   # both stretched and compressed
    k = rng.uniform(0.5, 2, N)
    Ha = stretch.hessian(x, rest, k, filter="analytic")
    Hn = stretch.hessian(x, rest, k, filter="numerical")
    assert np.all(eh.rel_fro(Ha, Hn) < 1e-12)
    D = eh.stretch_D()
    ref = []
    for i in range(N):
        He = eh.ref_stretch_hessian_e(x[i, 1] - x[i, 0], rest[i], k[i])
        w, V = np.linalg.eigh(He)
        ref.append(D.T @ ((V * np.maximum(w, 0)) @ V.T) @ D)
    assert np.all(eh.rel_fro(Ha, np.array(ref)) < 1e-12)
    # the exact one differs exactly where the edge is compressed
    H = stretch.hessian(x, rest, k, filter="none")
    compressed = stretch.length(x) < rest
    assert compressed.any() and (~compressed).any()
    assert np.all(eh.rel_fro(H[compressed], Ha[compressed]) > 1e-3)
    assert np.all(eh.rel_fro(H[~compressed], Ha[~compressed]) < 1e-12)


def _equal_length_bends(rng, n):
    x = eh.random_bend(rng, n, 1.0)
    L = rng.uniform(0.5, 2, n)
    t0, t1 = eh.unit(x[:, 0] - x[:, 1]), eh.unit(x[:, 2] - x[:, 1])
    return np.stack([eh.bend_from_units(t0[i], t1[i], x[i, 1], L[i], L[i]) for i in range(n)])


def _equal_ab_twists(rng, n, ratio=1.0):
    out = []
    while len(out) < n:
        e1 = eh.unit(rng.standard_normal(3)) * rng.uniform(0.5, 2)
        a = rng.standard_normal(3)
        b = rng.standard_normal(3)
        a -= (a @ e1) / (e1 @ e1) * e1
        b -= (b @ e1) / (e1 @ e1) * e1
        if np.linalg.norm(np.cross(eh.unit(a), eh.unit(b))) < 0.25:
            continue
        L = rng.uniform(0.5, 2)
        a = a / np.linalg.norm(a) * L
        b = b / np.linalg.norm(b) * L * ratio
        out.append(eh.twist_from_ab(a, b, e1, rng.uniform(-1, 1, 3)))
    return np.array(out)


def test_bend_analytic_equals_numerical_for_equal_lengths():
    """|e0| = |e1|: S Hhat^+ S is the exact projection of S Hhat S."""
    rng = np.random.default_rng(130)
    x = _equal_length_bends(rng, N)
    rest = np.clip(bend.angle(x) + rng.uniform(-1, 1, N), 0.05, np.pi - 0.05)
    k = rng.uniform(0.5, 2, N)
    Ha = bend.hessian(x, rest, k, filter="analytic")
    Hn = bend.hessian(x, rest, k, filter="numerical")
    err = eh.rel_fro(Ha, Hn)
    assert np.all(err < 1e-10), err.max()
    assert np.all(eh.rel_fro(Ha, _bend_ref_filtered(x, rest, k, "analytic")) < 1e-10)
    assert np.all(eh.rel_fro(Hn, _bend_ref_filtered(x, rest, k, "numerical")) < 1e-10)
    # and it is a real filter here: the exact Hessian is indefinite and differs
    H = bend.hessian(x, rest, k, filter="none")
    assert np.all(eh.rel_fro(H, Ha) > 1e-3)


def test_bend_analytic_is_S_Hhat_plus_S_for_any_lengths():
    rng = np.random.default_rng(131)
    x, rest, k = eh.random_case("bend", rng, N, 1.0)
    Ha = bend.hessian(x, rest, k, filter="analytic")
    assert np.all(eh.rel_fro(Ha, _bend_ref_filtered(x, rest, k, "analytic")) < 1e-10)


@pytest.mark.parametrize("equal_ab", [True, False])
def test_twist_filters_match_documented_constructions(equal_ab):
    """docs/elements.md: the twist analytic filter keeps the in-plane pairs with positive
    eigenvalue plus the PSD part of each out-of-plane rank-2 contribution; the numerical
    filter is the eigh-projection of the exact 12x12 Hessian. Both against the references
    built here (eigh of each rank-2 term; eigh of the whole exact Hessian)."""
    rng = np.random.default_rng(132 + equal_ab)
    if equal_ab:
        x = _equal_ab_twists(rng, N)
        W = twist.w_matrix(x)
        np.testing.assert_allclose(np.linalg.norm(W[:, :, 0], axis=1), np.linalg.norm(W[:, :, 1], axis=1),
                                   rtol=1e-12)
    else:
        x = eh.random_twist(rng, N, 1.0)
    rest = eh.wrap(twist.angle(x) + rng.choice([-1, 1], N) * rng.uniform(0.2, 1.2, N))
    k = rng.uniform(0.5, 2, N)
    H = twist.hessian(x, rest, k, filter="none")
    assert np.all(eh.rel_fro(H, _twist_ref_filtered(x, rest, k, "exact")) < 1e-10)
    Ha = twist.hessian(x, rest, k, filter="analytic")
    assert np.all(eh.rel_fro(Ha, _twist_ref_filtered(x, rest, k, "analytic")) < 1e-9)
    Hn = twist.hessian(x, rest, k, filter="numerical")
    assert np.all(eh.rel_fro(Hn, _twist_ref_filtered(x, rest, k, "numerical")) < 1e-9)
    # rank <= 4 (documented), and a real filter: the exact Hessian is indefinite
    w = np.linalg.eigvalsh(Ha)
    assert np.all(np.sum(w > 1e-10 * np.abs(w).max(axis=1, keepdims=True), axis=1) <= 4)
    assert np.all(eh.min_eig_ratio(H) < -1e-3)


@pytest.mark.parametrize("term", ["bend", "twist"])
def test_numerical_filter_is_eigh_projection(term):
    """The numerical filter is the reference "exact projection": bend, eigh-clamp of the
    exact 6x6 Hessian in T mapped with D; twist, eigh-clamp of the exact 12x12 Hessian."""
    rng = np.random.default_rng(140)
    mod = MODULES[term]
    x, rest, k = eh.random_case(term, rng, N, 1.0)
    Hn = mod.hessian(x, rest, k, filter="numerical")
    ref = (_bend_ref_filtered if term == "bend" else _twist_ref_filtered)(x, rest, k, "numerical")
    assert np.all(eh.rel_fro(Hn, ref) < 1e-9)


# Bounds on the analytic-vs-numerical relative Frobenius difference
# |H_analytic - H_numerical|_F / |H_numerical|_F. docs/elements.md leaves the figure to this
# test. Measured on the shipped kernels with 2,000 random elements per length ratio
# (ratios 1.5 .. 1e4, rest angles uniform): bend median 0.08 (ratio 1.5) .. 0.16, max 0.365
# (saturates for ratio >= 10); twist (which is not the exact projection even at |a| = |b|)
# median 0.08 .. 0.12, max 0.19 (about independent of the ratio).
ANALYTIC_VS_NUMERICAL_BOUND = {"bend": 0.45, "twist": 0.30}


@pytest.mark.parametrize("term", ["bend", "twist"])
def test_analytic_vs_numerical_difference_is_measured_and_bounded(term):
    rng = np.random.default_rng(150)
    mod = MODULES[term]
    print(f"\n{term}: relative Frobenius |H_analytic - H_numerical| / |H_numerical|")
    for ratio in (1.0, 1.5, 3.0, 10.0, 100.0, 1e4):
        if term == "bend":
            x = eh.random_bend(rng, N, 1.0)
            t0, t1 = eh.unit(x[:, 0] - x[:, 1]), eh.unit(x[:, 2] - x[:, 1])
            x = np.stack([eh.bend_from_units(t0[i], t1[i], x[i, 1], 1.0, ratio) for i in range(N)])
            rest = np.clip(bend.angle(x) + rng.choice([-1, 1], N) * rng.uniform(0.2, 1, N), 0.05, np.pi - 0.05)
        else:
            x = _equal_ab_twists(rng, N, ratio=ratio)     # |b| / |a| = ratio
            rest = eh.wrap(twist.angle(x) + rng.choice([-1, 1], N) * rng.uniform(0.2, 1.2, N))
        k = rng.uniform(0.5, 2, N)
        Ha = mod.hessian(x, rest, k, filter="analytic")
        Hn = mod.hessian(x, rest, k, filter="numerical")
        _assert_psd(Ha, f"{term} analytic ratio {ratio}")
        _assert_psd(Hn, f"{term} numerical ratio {ratio}")
        d = eh.rel_fro(Ha, Hn)
        print(f"  length ratio {ratio:8.1f}: median {np.median(d):.3e}  max {d.max():.3e}")
        if term == "bend" and ratio == 1.0:
            assert d.max() < 1e-10            # exact projection for equal lengths
        else:
            assert np.median(d) > 1e-3, "closed form should differ from the exact projection"
        assert d.max() < ANALYTIC_VS_NUMERICAL_BOUND[term]
        # the analytic filter is never larger than the exact Hessian's own magnitude by much
        H = mod.hessian(x, rest, k, filter="none")
        assert np.all(np.linalg.norm(Ha.reshape(N, -1), axis=1) <= 2.0 * np.linalg.norm(H.reshape(N, -1), axis=1))


def test_twist_spec_split_is_far_stiffer_near_planar_than_shipped_filter():
    """docs/elements.md: SPEC's split P^T H_W^+ P - Dt^T H_W^- Dt grows like 1/sin(phi) at
    planar stencils; the shipped analytic filter stays of the size of the exact Hessian."""
    rng = np.random.default_rng(155)
    print("\nphi     |spec split| / |exact|   |analytic| / |exact|")
    for phi0 in (0.3, 1e-2, 1e-4):
        x = []
        for _ in range(4):
            e1 = eh.unit(rng.standard_normal(3))
            p = eh.unit(np.cross(e1, rng.standard_normal(3)))
            b = np.cos(phi0) * p + np.sin(phi0) * np.cross(e1, p)
            x.append(eh.twist_from_ab(p, 1.3 * b, e1))
        x = np.array(x)
        rest = np.full(len(x), 0.25)
        k = np.ones(len(x))
        H = twist.hessian(x, rest, k, filter="none")
        Ha = twist.hessian(x, rest, k, filter="analytic")
        Hs = _twist_ref_filtered(x, rest, k, "spec_split")
        nH = np.linalg.norm(H.reshape(len(x), -1), axis=1)
        rs = np.linalg.norm(Hs.reshape(len(x), -1), axis=1) / nH
        ra = np.linalg.norm(Ha.reshape(len(x), -1), axis=1) / nH
        print(f"{phi0:6.0e}  {rs.max():12.3g}            {ra.max():8.3g}")
        assert np.all(ra < 3)
        if phi0 <= 1e-2:
            assert np.all(rs > 10)


def test_filter_names():
    assert tuple(FILTERS) == ("analytic", "numerical", "none", "abs")
    rng = np.random.default_rng(160)
    for term, mod in MODULES.items():
        x, rest, k = eh.random_case(term, rng, 3, 1.0)
        np.testing.assert_array_equal(mod.hessian(x, rest, k), mod.hessian(x, rest, k, filter="analytic"))
        for bad in ("bogus", "Analytic ", "exact", ""):
            with pytest.raises(ValueError, match="filter|bogus|exact|Analytic"):
                mod.hessian(x, rest, k, filter=bad)
