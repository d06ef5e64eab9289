"""Segment-segment barrier kernel (lc_petsc/elements/segment_barrier.py): the scalar
barrier against its closed form, C2 continuity at the thickness, finite-difference
gradient and exact Hessian with h^2 convergence, PSD filters, energy and forces of
parallel and crossing pairs against independent formulas, intersecting pairs refused."""

import numpy as np
import pytest

from lc_petsc.elements import segment_barrier as sb
from lc_petsc.elements import segment_contact as sc
from lc_petsc.errors import ElementError
from test_contact_kernel import crossing_pairs, fd_errors, vertex_edge_pairs

DHAT, KAPPA = 0.3, 4.0e3


def test_scalar_barrier_matches_its_closed_form_and_finite_differences():
    d = np.linspace(0.01, 0.299, 40) * DHAT / 0.3
    b, b1, b2 = sb.barrier(d, DHAT, KAPPA)
    np.testing.assert_allclose(b, -KAPPA * (d - DHAT) ** 2 * np.log(d / DHAT), rtol=1e-14)
    h = 1e-6
    bp, bm = sb.barrier(d + h, DHAT, KAPPA), sb.barrier(d - h, DHAT, KAPPA)
    np.testing.assert_allclose(b1, (bp[0] - bm[0]) / (2 * h), rtol=1e-6)
    np.testing.assert_allclose(b2, (bp[1] - bm[1]) / (2 * h), rtol=1e-6)
    assert np.all(b > 0) and np.all(b1 < 0) and np.all(b2 > 0)      # repulsive, convex
    # unbounded as d -> 0
    assert sb.barrier(np.array([1e-9 * DHAT]), DHAT, KAPPA)[0][0] > 20 * KAPPA * DHAT ** 2
    # zero beyond the thickness
    assert np.all(np.concatenate(sb.barrier(np.array([DHAT, 2 * DHAT]), DHAT, KAPPA)) == 0.0)


def test_c2_at_the_thickness():
    """At d = dhat (1 - eps): b ~ kappa dhat^2 eps^3, -b' ~ 3 kappa dhat eps^2,
    b'' ~ 6 kappa eps, all -> 0 as the pair leaves contact; the penalty's second
    derivative jumps there (the control)."""
    for eps in (1e-2, 1e-4, 1e-6):
        b, b1, b2 = (v[0] for v in sb.barrier(np.array([DHAT * (1 - eps)]), DHAT, KAPPA))
        assert 0 < b < 2 * KAPPA * DHAT ** 2 * eps ** 3
        assert 0 < -b1 < 4 * KAPPA * DHAT * eps ** 2
        assert 0 < b2 < 7 * KAPPA * eps
    # the same on pairs: the Hessian vanishes continuously as the pair leaves contact
    rng = np.random.default_rng(5)
    for gap, bound in ((DHAT * (1 - 1e-3), 1e-2), (DHAT * (1 - 1e-5), 1e-4)):
        X = crossing_pairs(5, rng, gap=gap, jitter=0.0)
        assert np.abs(sb.hessian(X, DHAT, KAPPA, filter="none")).max() < bound * KAPPA
        assert np.abs(sc.hessian(X, DHAT, KAPPA)).max() > 0.2 * KAPPA     # penalty: k w w^T


@pytest.mark.parametrize("make", [crossing_pairs, vertex_edge_pairs])
def test_gradient_and_exact_hessian_match_finite_differences_h2(make):
    X = make(20, np.random.default_rng(1))
    s, t, u, d, fs, ft, par = sc.closest_points(X)
    assert np.all(d < DHAT) and np.all(d > 0.02) and not par.any()
    e1 = fd_errors(X, 1e-3, kernel=sb, d0=DHAT, k=KAPPA)
    e2 = fd_errors(X, 5e-4, kernel=sb, d0=DHAT, k=KAPPA)
    print(make.__name__, "FD rel. errors (grad, Hess) h=1e-3:", e1, "h=5e-4:", e2)
    assert e1[0] < 1e-4 and e1[1] < 1e-3
    assert 3.0 < e1[0] / e2[0] < 5.0 and 3.0 < e1[1] / e2[1] < 5.0


def test_filters_are_psd_and_analytic_is_the_gauss_newton_part():
    rng = np.random.default_rng(2)
    X = np.concatenate([crossing_pairs(30, rng, gap=0.05, jitter=0.1), vertex_edge_pairs(10, rng)])
    d = sc.distance(X)
    assert np.all((d > 0) & (d < DHAT))
    g = sb.gradient(X, DHAT, KAPPA).reshape(len(X), 12)
    b1, b2 = sb.barrier(d, DHAT, KAPPA)[1:]
    gd = g / b1[:, None]                                   # grad d (unit-free weights x n)
    Ha = sb.hessian(X, DHAT, KAPPA, filter="analytic")
    np.testing.assert_allclose(Ha, b2[:, None, None] * gd[:, :, None] * gd[:, None, :],
                               rtol=1e-12, atol=1e-12 * np.abs(Ha).max())
    He = sb.hessian(X, DHAT, KAPPA, filter="none")
    assert np.linalg.eigvalsh(He).min() < -1e-3 * KAPPA     # the exact one is indefinite
    for f in ("analytic", "numerical", "abs"):
        H = sb.hessian(X, DHAT, KAPPA, filter=f)
        lam = np.linalg.eigvalsh(H)
        assert lam.min() >= -1e-9 * np.abs(lam).max(), f
    # numerical = the exact Hessian with negative eigenvalues clamped
    lam, V = np.linalg.eigh(He)
    np.testing.assert_allclose(sb.hessian(X, DHAT, KAPPA, filter="numerical"),
                               (V * np.maximum(lam, 0)[:, None, :]) @ V.transpose(0, 2, 1),
                               atol=1e-9 * np.abs(He).max())


def test_parallel_and_crossing_pairs_against_independent_formulas():
    """Energy -kappa (h - dhat)^2 ln(h / dhat) at separation h; the force on B is
    -b'(h) along the normal from A to B (repulsive), the forces sum to zero and the
    crossing pair's are shared equally by the endpoints (closest points at the middles)."""
    h = np.array([0.02, 0.1, 0.2, 0.29])
    n = len(h)
    ref = -KAPPA * (h - DHAT) ** 2 * np.log(h / DHAT)
    dref = -KAPPA * (2 * (h - DHAT) * np.log(h / DHAT) + (h - DHAT) ** 2 / h)     # b'(h)
    par = np.zeros((n, 4, 3))
    par[:, 1, 0] = 1.0
    par[:, 2] = [0.3, 0.0, 0.0]
    par[:, 3] = [1.5, 0.0, 0.0]
    par[:, 2:, 1] = h[:, None]             # B parallel to A, h above it (overlap 0.3..1)
    cross = np.zeros((n, 4, 3))
    cross[:, 0, 0], cross[:, 1, 0] = -1.0, 1.0
    cross[:, 2, 1], cross[:, 3, 1] = -1.0, 1.0
    cross[:, 2:, 2] = h[:, None]
    for X, up in ((par, 1), (cross, 2)):
        np.testing.assert_allclose(sb.energy(X, DHAT, KAPPA), ref, rtol=1e-12)
        g = sb.gradient(X, DHAT, KAPPA)
        force_B = -g[:, 2:].sum(axis=1)
        np.testing.assert_allclose(force_B[:, up], -dref, rtol=1e-12)
        assert np.abs(np.delete(force_B, up, axis=1)).max() < 1e-9 * np.abs(dref).max()
        assert np.abs(g.sum(axis=1)).max() < 1e-9 * np.abs(g).max()
    gc = sb.gradient(cross, DHAT, KAPPA)
    np.testing.assert_allclose(gc[:, :, 2], np.outer(dref, [-0.5, -0.5, 0.5, 0.5]), rtol=1e-12)


def test_beyond_thickness_zero_and_intersecting_pairs_refused():
    rng = np.random.default_rng(3)
    far = crossing_pairs(5, rng, gap=DHAT * 1.01, jitter=0.0)
    assert np.all(sb.energy(far, DHAT, KAPPA) == 0) and np.all(sb.gradient(far, DHAT, KAPPA) == 0)
    hit = crossing_pairs(3, rng, gap=0.0, jitter=0.0)
    assert np.all(sb.energy(hit, DHAT, KAPPA) == np.inf)
    with pytest.raises(ElementError, match="strand_contact_mode"):
        sb.gradient_hessian(np.concatenate([far, hit]), DHAT, KAPPA)
    with pytest.raises(ElementError, match="thickness"):
        sb.energy(far, 0.0, KAPPA)


def test_penalty_matched_stiffness_equals_the_penalty_force_at_half_thickness():
    k = 1.0e5
    kappa = sb.penalty_matched_stiffness(k)
    b1 = sb.barrier(np.array([DHAT / 2]), DHAT, kappa)[1][0]
    assert -b1 == pytest.approx(k * DHAT / 2, rel=1e-12)


def test_gradient_and_exact_hessian_against_ipc_toolkit():
    """IPC Toolkit's edge-edge squared distance with its derivatives and its barrier's
    scalar derivatives (independent code): b'(d) grad d and
    b''(d) grad d grad d^T + b'(d) Hess d with d = sqrt(D), grad d = grad D / (2 d),
    Hess d = (Hess D / 2 - grad d grad d^T) / d."""
    ipctk = pytest.importorskip("ipctk")
    rng = np.random.default_rng(4)
    X = np.concatenate([crossing_pairs(8, rng, gap=0.08, jitter=0.05), vertex_edge_pairs(4, rng)])
    g = sb.gradient(X, DHAT, KAPPA).reshape(len(X), 12)
    H = sb.hessian(X, DHAT, KAPPA, filter="none")
    for k, (a0, a1, b0, b1) in enumerate(X):
        kind = ipctk.edge_edge_distance_type(a0, a1, b0, b1)
        d = np.sqrt(ipctk.edge_edge_distance(a0, a1, b0, b1, kind))
        gd = ipctk.edge_edge_distance_gradient(a0, a1, b0, b1, kind) / (2 * d)
        hd = (ipctk.edge_edge_distance_hessian(a0, a1, b0, b1, kind) / 2 - np.outer(gd, gd)) / d
        p1 = KAPPA * ipctk.barrier_first_derivative(d, DHAT)
        p2 = KAPPA * ipctk.barrier_second_derivative(d, DHAT)
        assert sb.energy(X[k:k + 1], DHAT, KAPPA)[0] == pytest.approx(KAPPA * ipctk.barrier(d, DHAT), rel=1e-12)
        np.testing.assert_allclose(g[k], p1 * gd, rtol=0, atol=1e-11 * np.abs(g[k]).max())
        np.testing.assert_allclose(H[k], p2 * np.outer(gd, gd) + p1 * hd, rtol=0,
                                   atol=1e-10 * np.abs(H[k]).max())
