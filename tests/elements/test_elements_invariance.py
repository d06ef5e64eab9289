"""Invariances (zero energy and gradient at rest; rigid rotation and translation leave
the energy unchanged and rotate the gradients), plus the stiffness weights of SPEC section 2.

* At rest (rest quantities measured on the same x, by the kernel and by an independent
  reference) the energy and gradient vanish.
* x -> R x + t: energy unchanged, g(Rx + t) = g(x) R^T row-wise, H(Rx + t) = B H(x) B^T with
  B = blockdiag(R, ..., R), for every filter; angles and lengths unchanged.
* A reflection leaves bend angles and lengths alone and flips the sign of the twist angle.
* Energies are linear in the stiffness.
"""

import numpy as np
import pytest

from lc_petsc.elements import FILTERS, bend, stretch, twist, weights

import element_helpers as eh

MODULES = {"stretch": stretch, "bend": bend, "twist": twist}
MEASURE = {"stretch": stretch.length, "bend": bend.angle, "twist": twist.angle}
REF_MEASURE = {
    "stretch": lambda x: np.linalg.norm(x[:, 1] - x[:, 0], axis=1),
    "bend": eh.ref_bend_angle,
    "twist": eh.ref_twist_angle,
}
N = 12


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e2])
@pytest.mark.parametrize("term", eh.TERMS)
def test_zero_energy_and_gradient_at_rest(term, scale):
    rng = np.random.default_rng(200 + eh.TERMS.index(term))
    mod = MODULES[term]
    x, _, k = eh.random_case(term, rng, N, scale)
    # rest quantities measured by the kernel itself: exactly zero
    gscale = k * (scale if term == "stretch" else 1.0 / scale)   # |dPsi/dx| per unit of rest error
    escale = k * (scale**2 if term == "stretch" else 1.0)
    rest = MEASURE[term](x)
    E = mod.energy(x, rest, k)
    g = mod.gradient(x, rest, k)
    assert np.all(E <= 1e-28 * escale), E
    assert np.all(np.abs(g).max(axis=(1, 2)) <= 1e-14 * gscale), np.abs(g).max()
    # ... and by the independent reference: zero to round-off
    rest_ref = REF_MEASURE[term](x)
    np.testing.assert_allclose(rest_ref, rest, rtol=1e-13, atol=1e-14)
    E = mod.energy(x, rest_ref, k)
    assert np.all(E <= 1e-24 * escale), E
    g = mod.gradient(x, rest_ref, k)
    assert np.all(np.abs(g).max(axis=(1, 2)) <= 1e-12 * gscale)


@pytest.mark.parametrize("term", eh.TERMS)
def test_rigid_motion(term):
    rng = np.random.default_rng(210 + eh.TERMS.index(term))
    mod = MODULES[term]
    x, rest, k = eh.random_case(term, rng, N, 1.0)
    nv = eh.NVERT[term]
    E = mod.energy(x, rest, k)
    g = mod.gradient(x, rest, k)
    Hs = {f: mod.hessian(x, rest, k, filter=f) for f in FILTERS}
    for trial in range(3):
        R = eh.random_rotation(rng)
        t = rng.uniform(-10, 10, 3)
        y = x @ R.T + t
        np.testing.assert_allclose(MEASURE[term](y), MEASURE[term](x), rtol=1e-12, atol=1e-13)
        np.testing.assert_allclose(mod.energy(y, rest, k), E, rtol=1e-10, atol=1e-14)
        gy = mod.gradient(y, rest, k)
        gmax = np.abs(g).max()
        np.testing.assert_allclose(gy, g @ R.T, rtol=0, atol=1e-10 * gmax)
        B = eh.blockdiag_rot(R, nv)
        for f in FILTERS:
            Hy = mod.hessian(y, rest, k, filter=f)
            Hrot = B @ Hs[f] @ B.T
            err = eh.rel_fro(Hy, Hrot)
            assert np.all(err < 1e-9), f"{term}/{f}: {err.max():.2e}"
    # pure translation, large offset relative to the element
    t = np.array([1e3, -2e3, 5e2])
    np.testing.assert_allclose(mod.energy(x + t, rest, k), E, rtol=1e-8)
    np.testing.assert_allclose(mod.gradient(x + t, rest, k), g, rtol=0, atol=1e-8 * np.abs(g).max())


def test_reflection():
    rng = np.random.default_rng(220)
    M = np.diag([1.0, -1.0, 1.0])
    x = eh.random_twist(rng, N, 1.0)
    np.testing.assert_allclose(twist.angle(x @ M), -twist.angle(x), atol=1e-13)
    rest = twist.angle(x) + 0.3
    # Psi_t(Mx, -rest) == Psi_t(x, rest)
    np.testing.assert_allclose(twist.energy(x @ M, -rest, 1.0), twist.energy(x, rest, 1.0), rtol=1e-10)
    xb = eh.random_bend(rng, N, 1.0)
    np.testing.assert_allclose(bend.angle(xb @ M), bend.angle(xb), atol=1e-14)


@pytest.mark.parametrize("term", eh.TERMS)
def test_energy_linear_in_stiffness_and_broadcasts(term):
    rng = np.random.default_rng(230 + eh.TERMS.index(term))
    mod = MODULES[term]
    x, rest, _ = eh.random_case(term, rng, N, 1.0)
    E1 = mod.energy(x, rest, 1.0)
    for k in (1e-6, 3.0, 1e12):
        np.testing.assert_allclose(mod.energy(x, rest, k), k * E1, rtol=1e-12)
        np.testing.assert_allclose(mod.gradient(x, rest, np.full(N, k)), k * mod.gradient(x, rest, 1.0),
                                   rtol=1e-12, atol=0)
    # scalar rest quantity broadcasts like an (n,) array
    r0 = float(rest[0])
    np.testing.assert_array_equal(mod.energy(x, r0, 2.0), mod.energy(x, np.full(N, r0), np.full(N, 2.0)))


def test_weights():
    E = np.array([1.25e8, 3.9e9])
    G = E / 3
    r = np.array([0.35, 0.07])
    L = np.array([0.596, 0.3])
    np.testing.assert_allclose(weights.stretch_stiffness(E, r, L), E * np.pi * r**2 / L, rtol=1e-15)
    np.testing.assert_allclose(weights.bend_stiffness(E, r, L), E * np.pi * r**4 / 4 / L, rtol=1e-15)
    np.testing.assert_allclose(weights.twist_stiffness(G, r, L), G * np.pi * r**4 / 2 / L, rtol=1e-15)
    # scalar inputs
    assert np.isclose(weights.stretch_stiffness(2.0, 1.0, 2.0), np.pi)
    assert np.isclose(weights.bend_stiffness(4.0, 1.0, 1.0), np.pi)
    assert np.isclose(weights.twist_stiffness(2.0, 1.0, 1.0), np.pi)


# ------------------------------------------------------------- batch behaviour / API
@pytest.mark.parametrize("term", eh.TERMS)
def test_batch_independence_and_large_batches(term):
    """Elements do not talk to each other: a permuted batch gives permuted results, and a
    batch larger than any internal chunk (9,000 elements) matches small-batch evaluation."""
    rng = np.random.default_rng(240 + eh.TERMS.index(term))
    mod = MODULES[term]
    n = 9000
    x, rest, k = eh.random_case(term, rng, 40, 1.0)
    idx = rng.integers(0, 40, n)
    X, R, K = x[idx], rest[idx], k[idx]
    E = mod.energy(X, R, K)
    g = mod.gradient(X, R, K)
    E0 = mod.energy(x, rest, k)
    g0 = mod.gradient(x, rest, k)
    np.testing.assert_array_equal(E, E0[idx])
    np.testing.assert_allclose(g, g0[idx], rtol=0, atol=1e-14 * np.abs(g0).max())
    for f in FILTERS:
        H = mod.hessian(X, R, K, filter=f)
        H0 = mod.hessian(x, rest, k, filter=f)
        assert np.all(eh.rel_fro(H, H0[idx]) < 1e-12), f
    perm = rng.permutation(40)
    np.testing.assert_array_equal(mod.energy(x[perm], rest[perm], k[perm]), E0[perm])


@pytest.mark.parametrize("term", eh.TERMS)
def test_gradient_hessian_fused_call_matches_separate_calls(term):
    """docs/elements.md: gradient_hessian(..., filter=, out=) is what the Newton loop calls."""
    rng = np.random.default_rng(250 + eh.TERMS.index(term))
    mod = MODULES[term]
    x, rest, k = eh.random_case(term, rng, N, 1.0)
    m = 3 * eh.NVERT[term]
    buf = np.full((N, m, m), np.nan)
    for f in FILTERS:
        g, H = mod.gradient_hessian(x, rest, k, filter=f)
        np.testing.assert_allclose(g, mod.gradient(x, rest, k), rtol=0, atol=1e-14 * np.abs(g).max())
        np.testing.assert_allclose(H, mod.hessian(x, rest, k, filter=f), rtol=0, atol=1e-13 * np.abs(H).max())
        g2, H2 = mod.gradient_hessian(x, rest, k, filter=f, out=buf)
        assert H2 is buf
        np.testing.assert_array_equal(buf, H)
    with pytest.raises(ValueError):
        mod.gradient_hessian(x, rest, k, out=np.zeros((N + 1, m, m)))
