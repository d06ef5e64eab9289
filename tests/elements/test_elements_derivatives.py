"""Derivative checks of the element kernels (supplement's recipe).

* energy == independent reference energy (NumPy and compiled kernels);
* gradient vs central differences of the kernel's energy, and exact Hessian
  (filter="none") vs central differences of the kernel's gradient, with the error shrinking
  as h^2 over four step sizes (every halving ratio ~4, fitted log-log slope ~2), per element,
  on seeded random configurations at edge-length scales 1e-3, 1 and 1e2 cm;
* gradient == closed-form reference gradient (SPEC section 2 formulas, own implementation);
* bend.angle / twist.angle / twist.w_matrix against their definitions, the SPEC gradient of
  theta against differences of bend.angle, and twist's exact W jacobian J against
  differences of twist.w_matrix.

The energy, gradient and exact-Hessian checks run on both the NumPy kernels and the
compiled ones (lc_petsc.elements.compiled, through tests/compiled_elements.py).
"""

import numpy as np
import pytest

from lc_petsc.elements import bend, stretch, twist

import compiled_elements
import element_helpers as eh

MODULES = {"stretch": stretch, "bend": bend, "twist": twist}
IMPLEMENTATIONS = {"numpy": MODULES, "compiled": {t: compiled_elements.module(t) for t in MODULES}}
SCALES = [1e-3, 1.0, 1e2]
# step sizes relative to the edge-length scale, halving
HS_REL = np.array([8e-3, 4e-3, 2e-3, 1e-3])
N = 6


def _case(term, scale, seed):
    rng = np.random.default_rng(seed)
    return eh.random_case(term, rng, N, scale)


def _seed(term, scale):
    return 1000 * eh.TERMS.index(term) + int(round(np.log10(scale))) + 10


@pytest.mark.parametrize("impl", IMPLEMENTATIONS)
@pytest.mark.parametrize("scale", SCALES)
@pytest.mark.parametrize("term", eh.TERMS)
def test_energy_matches_reference(term, scale, impl):
    mod = IMPLEMENTATIONS[impl][term]
    x, rest, k = _case(term, scale, _seed(term, scale))
    E = mod.energy(x, rest, k)
    assert E.shape == (N,)
    Eref = eh.REF_ENERGY[term](x, rest, k)
    np.testing.assert_allclose(E, Eref, rtol=1e-10, atol=0)
    assert np.all(Eref > 0)  # the cases are away from rest


@pytest.mark.parametrize("impl", IMPLEMENTATIONS)
@pytest.mark.parametrize("scale", SCALES)
@pytest.mark.parametrize("term", eh.TERMS)
def test_gradient_matches_closed_form_reference(term, scale, impl):
    mod = IMPLEMENTATIONS[impl][term]
    x, rest, k = _case(term, scale, _seed(term, scale))
    g = mod.gradient(x, rest, k)
    assert g.shape == (N, eh.NVERT[term], 3)
    gref = eh.REF_GRADIENT[term](x, rest, k)
    err = np.linalg.norm((g - gref).reshape(N, -1), axis=1) / np.linalg.norm(gref.reshape(N, -1), axis=1)
    assert np.all(err < 1e-10), err
    # translation invariance: vertex gradients sum to zero
    np.testing.assert_allclose(g.sum(axis=1), 0, atol=1e-12 * np.abs(g).max())


@pytest.mark.parametrize("impl", IMPLEMENTATIONS)
@pytest.mark.parametrize("scale", SCALES)
@pytest.mark.parametrize("term", eh.TERMS)
def test_gradient_vs_fd_energy_h2(term, scale, impl):
    mod = IMPLEMENTATIONS[impl][term]
    x, rest, k = _case(term, scale, _seed(term, scale))
    g = mod.gradient(x, rest, k).reshape(N, -1)
    gnorm = np.linalg.norm(g, axis=1)
    errs = []
    for hr in HS_REL:
        gfd = eh.fd_gradient(lambda y: mod.energy(y, rest, k), x, hr * scale).reshape(N, -1)
        errs.append(np.linalg.norm(gfd - g, axis=1) / gnorm)
    errs = np.array(errs)  # (nh, N)
    for i in range(N):
        # (relative to |g|, which is small for an edge close to its rest length: loose cap)
        eh.assert_h2_convergence(HS_REL, errs[:, i], f"{term} gradient, scale {scale}, element {i}",
                                 final_max=1e-2)


@pytest.mark.parametrize("impl", IMPLEMENTATIONS)
@pytest.mark.parametrize("scale", SCALES)
@pytest.mark.parametrize("term", eh.TERMS)
def test_exact_hessian_vs_fd_gradient_h2(term, scale, impl):
    mod = IMPLEMENTATIONS[impl][term]
    x, rest, k = _case(term, scale, _seed(term, scale))
    H = mod.hessian(x, rest, k, filter="none")
    m = 3 * eh.NVERT[term]
    assert H.shape == (N, m, m)
    np.testing.assert_allclose(H, np.swapaxes(H, 1, 2), rtol=0, atol=1e-12 * np.abs(H).max())
    Hnorm = np.linalg.norm(H.reshape(N, -1), axis=1)
    errs = []
    for hr in HS_REL:
        Hfd = eh.fd_hessian_of_gradient(lambda y: mod.gradient(y, rest, k), x, hr * scale)
        errs.append(np.linalg.norm((Hfd - H).reshape(N, -1), axis=1) / Hnorm)
    errs = np.array(errs)
    for i in range(N):
        eh.assert_h2_convergence(HS_REL, errs[:, i], f"{term} Hessian, scale {scale}, element {i}",
                                 final_max=1e-4)
    # translation invariance: every block row sums to zero
    rows = H.reshape(N, m, eh.NVERT[term], 3).sum(axis=2)
    np.testing.assert_allclose(rows, 0, atol=1e-11 * np.abs(H).max())


def test_stretch_length_matches_definition():
    rng = np.random.default_rng(5)
    x, _ = eh.random_stretch(rng, 20, 1.0)
    np.testing.assert_allclose(stretch.length(x), np.linalg.norm(x[:, 1] - x[:, 0], axis=1),
                               rtol=1e-14)


def test_bend_angle_matches_definition_and_known_values():
    rng = np.random.default_rng(6)
    x = eh.random_bend(rng, 20, 1.0, min_sin=0.0)
    np.testing.assert_allclose(bend.angle(x), eh.ref_bend_angle(x), rtol=0, atol=1e-14)
    # known angles: 90, 60 and 135 degrees
    c = np.array([1.0, 1.0, 1.0])
    h = np.sqrt(0.5)
    pts = np.array([
        [[1, 0, 0], [0, 0, 0], [0, 2, 0]],
        [[1, 0, 0], [0, 0, 0], [0.5, np.sqrt(3) / 2, 0]],
        [c + [3, 0, 0], c, c + [-h, h, 0]],
    ], float)
    exp = np.array([np.pi / 2, np.pi / 3, 3 * np.pi / 4])
    np.testing.assert_allclose(bend.angle(pts), exp, rtol=0, atol=1e-15)


def test_bend_angle_gradient_spec_formula_vs_fd_of_kernel_angle():
    """SPEC section 2: d theta / d e0 = -(t1 - cos(theta) t0) / (|e0| sin(theta)); checked
    against central differences of bend.angle (which must be smooth and accurate)."""
    rng = np.random.default_rng(7)
    for scale in SCALES:
        x = eh.random_bend(rng, N, scale)
        e0, e1 = x[:, 0] - x[:, 1], x[:, 2] - x[:, 1]
        g0, g1 = eh.ref_angle_gradient(e0, e1)
        gref = np.stack([g0, -(g0 + g1), g1], axis=1).reshape(N, -1)
        errs = []
        for hr in HS_REL:
            gfd = eh.fd_gradient(bend.angle, x, hr * scale).reshape(N, -1)
            errs.append(np.linalg.norm(gfd - gref, axis=1) / np.linalg.norm(gref, axis=1))
        errs = np.array(errs)
        for i in range(N):
            eh.assert_h2_convergence(HS_REL, errs[:, i], f"theta gradient scale {scale} el {i}")


def test_twist_angle_and_w_matrix_match_definition():
    rng = np.random.default_rng(8)
    x = eh.random_twist(rng, 20, 1.0, min_ratio=0.05, min_sin=0.0)
    np.testing.assert_allclose(twist.angle(x), eh.ref_twist_angle(x), rtol=0, atol=1e-13)
    W = twist.w_matrix(x)
    assert W.shape == (20, 3, 3)
    np.testing.assert_allclose(W, eh.ref_w_matrix(x), rtol=0, atol=1e-14)
    # a and b are orthogonal to the middle edge
    np.testing.assert_allclose(np.einsum("ni,ni->n", W[:, :, 0], W[:, :, 2]), 0, atol=1e-14)
    np.testing.assert_allclose(np.einsum("ni,ni->n", W[:, :, 1], W[:, :, 2]), 0, atol=1e-14)


@pytest.mark.parametrize("scale", SCALES)
def test_twist_exact_w_jacobian_vs_fd_of_w_matrix_h2(scale):
    rng = np.random.default_rng(9 + int(np.log10(scale)))
    x = eh.random_twist(rng, N, scale)
    P, J = twist.w_jacobians(x)
    assert J.shape == (N, 9, 12) and P.shape == (N, 9, 12)
    Jref = np.stack([eh.ref_twist_J(xi) for xi in x])
    np.testing.assert_allclose(J, Jref, rtol=0, atol=1e-12 * np.abs(Jref).max())
    Jn = np.linalg.norm(J.reshape(N, -1), axis=1)
    errs = []
    for hr in HS_REL:
        Jfd = eh.fd_jacobian(lambda y: eh.vecW(twist.w_matrix(y)), x, hr * scale)
        errs.append(np.linalg.norm((Jfd - J).reshape(N, -1), axis=1) / Jn)
    errs = np.array(errs)
    for i in range(N):
        eh.assert_h2_convergence(HS_REL, errs[:, i], f"dW/dx scale {scale} element {i}",
                                 final_max=1e-4)
