"""The absolute-value filter ("abs", docs/newton.md): PSD on the cases where the exact
Hessian is indefinite, equal to the exact Hessian where that is PSD (stretch, bend;
twist at rest), and equal to an independent dense reference |H| (eigh with absolute
eigenvalues) where its closed form is exact: stretch always, bend with |e0| == |e1|."""

import numpy as np

from lc_petsc.elements import bend, segment_contact, stretch, twist

import element_helpers as eh
from test_elements_filters import _crushed_case, _smashed_wisp_case, _assert_psd

MODULES = {"stretch": stretch, "bend": bend, "twist": twist}
N = 40


def _dense_abs(H):
    lam, q = np.linalg.eigh(H)
    return np.matmul(q * np.abs(lam)[:, None, :], q.transpose(0, 2, 1))


def test_abs_is_psd_where_exact_is_indefinite():
    rng = np.random.default_rng(7)
    for term, mod in MODULES.items():
        for kind in ("random", "crushed", "smash"):
            if kind == "random":
                x, rest, k = eh.random_case(term, rng, N, 1.0)
            elif kind == "crushed":
                x, rest, k = _crushed_case(term, rng, N)
            else:
                x, rest, k = _smashed_wisp_case(term, 0.4)
            _assert_psd(mod.hessian(x, rest, k, filter="abs"), f"{term}/{kind}/abs")
            if kind != "smash":   # not vacuous: the exact Hessian is indefinite here
                assert np.any(eh.min_eig_ratio(mod.hessian(x, rest, k, filter="none")) < -1e-3)


def test_abs_equals_exact_where_exact_is_psd():
    rng = np.random.default_rng(8)
    x, _ = eh.random_stretch(rng, N, 1.0)
    cases = {"stretch": (x, stretch.length(x) * rng.uniform(0.3, 0.99, N))}   # stretched
    x = eh.random_bend(rng, N, 1.0)
    cases["bend"] = (x, bend.angle(x))
    x = eh.random_twist(rng, N, 1.0)
    cases["twist"] = (x, twist.angle(x))
    for term, (x, rest) in cases.items():
        mod = MODULES[term]
        k = rng.uniform(0.5, 2, N)
        H = mod.hessian(x, rest, k, filter="none")
        _assert_psd(H, f"{term} exact")
        err = eh.rel_fro(mod.hessian(x, rest, k, filter="abs"), H)
        assert np.all(err < 1e-10), f"{term}: {err.max():.2e}"


def test_abs_matches_dense_reference_where_closed_form_is_exact():
    rng = np.random.default_rng(9)
    # stretch: |H_e| of the 3x3 Hessian in e, mapped with D = [-I, I]
    x, _ = eh.random_stretch(rng, N, 1.0)
    rest = stretch.length(x) * rng.uniform(0.5, 2.0, N)      # both signs of k (1 - Lbar/L)
    k = rng.uniform(0.5, 2, N)
    He = np.array([eh.ref_stretch_hessian_e(e, r, kk)
                   for e, r, kk in zip(x[:, 1] - x[:, 0], rest, k)])
    D = eh.stretch_D()
    ref = D.T @ _dense_abs(He) @ D
    assert np.all(eh.rel_fro(stretch.hessian(x, rest, k, filter="abs"), ref) < 1e-10)
    # bend with |e0| == |e1|: |H_T| of the exact Hessian in T, mapped with D
    x = eh.random_bend(rng, N, 1.0, min_sin=0.05)
    e0, e1 = x[:, 0] - x[:, 1], x[:, 2] - x[:, 1]
    x[:, 2] = x[:, 1] + e1 * (np.linalg.norm(e0, axis=1) / np.linalg.norm(e1, axis=1))[:, None]
    rest = np.where(bend.angle(x) > np.pi / 2, 0.3, np.pi - 0.3)
    Db = eh.bend_D()
    P = eh.pinv_rows(Db)
    HT = P.T @ bend.hessian(x, rest, 1.0, filter="none") @ P
    ref = Db.T @ _dense_abs(HT) @ Db
    got = bend.hessian(x, rest, 1.0, filter="abs")
    assert np.any(eh.min_eig_ratio(HT) < -1e-3)
    assert np.all(eh.rel_fro(got, ref) < 1e-9), eh.rel_fro(got, ref).max()


def test_abs_segment_contact_is_dense_abs_of_exact():
    rng = np.random.default_rng(10)
    X = np.zeros((20, 4, 3))
    X[:, 0], X[:, 1] = (-1.0, 0, 0), (1.0, 0, 0)
    X[:, 2], X[:, 3] = (-0.3, -1.0, 0.05), (0.3, 1.0, 0.05)
    X += rng.normal(scale=0.01, size=X.shape)
    H = segment_contact.hessian(X, 0.1, 1e3, filter="none")
    got = segment_contact.hessian(X, 0.1, 1e3, filter="abs")
    assert np.any(eh.min_eig_ratio(H) < -1e-3)
    assert np.all(eh.rel_fro(got, _dense_abs(0.5 * (H + H.transpose(0, 2, 1)))) < 1e-10)
