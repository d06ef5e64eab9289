"""The supplement's twist claims (its section 3-4; SPEC section 2 and erratum 5).

* The simplified dW/dx of eq. 46 (P, alpha and beta frozen) FAILS a direct finite-difference
  test of W(x): its error is large and does not shrink with h; the exact J passes (h^2).
* Yet P^T g_W == J^T g_W == twist.gradient to round-off (Dt^T g_W = 0 because every block
  of Dt is e1 v^T / |e1|^2 and g_W lies in span(a, b), which is orthogonal to e1).
* For the Hessian the simplification is NOT harmless: P^T H_W P alone is far (> 10%) from the
  finite-difference Hessian, while P^T H_W P - Dt^T H_W Dt matches it (and is what the
  kernel's exact Hessian is).
* The sign convention of phi: sign(phi) == sign(det W), right-handed = positive.
"""

import numpy as np
import pytest

from lc_petsc.elements import twist

import element_helpers as eh

N = 10
HS = np.array([8e-3, 4e-3, 2e-3, 1e-3])


def _cases(seed, n=N, scale=1.0):
    rng = np.random.default_rng(seed)
    x = eh.random_twist(rng, n, scale)
    phi = eh.ref_twist_angle(x)
    k = rng.uniform(0.5, 2.0, n)
    rest = eh.wrap(phi + rng.choice([-1, 1], n) * rng.uniform(0.3, 1.2, n))
    return x, rest, k


def test_P_is_eq46_and_J_is_exact():
    x, rest, k = _cases(41)
    P, J = twist.w_jacobians(x)
    for i in range(N):
        np.testing.assert_allclose(P[i], eh.ref_twist_P(x[i]), rtol=0, atol=1e-13)
        np.testing.assert_allclose(J[i], eh.ref_twist_J(x[i]), rtol=0, atol=1e-12)
    # Dt = P - J has blocks of the form e1 v^T / |e1|^2: every column lies along e1
    e1 = x[:, 2] - x[:, 1]
    Dt = P - J
    for blk in range(3):
        rows = Dt[:, 3 * blk:3 * blk + 3, :]
        perp = rows - eh.unit(e1)[:, :, None] * np.einsum("ni,nij->nj", eh.unit(e1), rows)[:, None, :]
        np.testing.assert_allclose(perp, 0, atol=1e-12)
    assert np.all(np.linalg.norm(Dt.reshape(N, -1), axis=1) > 0.05)  # alpha/beta vary


def test_simplified_P_fails_fd_of_W_while_J_passes():
    x, rest, k = _cases(42)
    P, J = twist.w_jacobians(x)
    errP, errJ = [], []
    for h in HS:
        Jfd = eh.fd_jacobian(lambda y: eh.vecW(twist.w_matrix(y)), x, h)
        nrm = np.linalg.norm(Jfd.reshape(N, -1), axis=1)
        errP.append(np.linalg.norm((Jfd - P).reshape(N, -1), axis=1) / nrm)
        errJ.append(np.linalg.norm((Jfd - J).reshape(N, -1), axis=1) / nrm)
    errP, errJ = np.array(errP), np.array(errJ)
    print("\nrelative FD error of W jacobian, rows = h", HS)
    print("P (eq. 46):", np.array2string(errP.T.max(axis=0), precision=3))
    print("J (exact): ", np.array2string(errJ.T.max(axis=0), precision=3))
    for i in range(N):
        eh.assert_h2_convergence(HS, errJ[:, i], f"J element {i}", final_max=1e-4)
        # P: large and not shrinking (ratios ~1, not ~4)
        assert errP[-1, i] > 0.02, errP[:, i]
        ratios = errP[:-1, i] / errP[1:, i]
        assert np.all(np.abs(ratios - 1) < 0.05), ratios
        assert errP[-1, i] > 1e4 * errJ[-1, i]


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e2])
def test_P_and_J_give_the_same_gradient(scale):
    x, rest, k = _cases(43 + int(np.log10(scale)), scale=scale)
    P, J = twist.w_jacobians(x)
    gW = twist.w_gradient(x, rest, k)
    g = twist.gradient(x, rest, k).reshape(N, 12)
    gP = np.einsum("nij,ni->nj", P, gW)
    gJ = np.einsum("nij,ni->nj", J, gW)
    gn = np.linalg.norm(g, axis=1)[:, None]
    assert np.all(gn > 0)
    np.testing.assert_allclose(gP / gn, g / gn, rtol=0, atol=1e-13)
    np.testing.assert_allclose(gJ / gn, g / gn, rtol=0, atol=1e-13)
    dt = np.einsum("nij,ni->nj", P - J, gW)
    np.testing.assert_allclose(dt / gn, 0, atol=1e-13)
    # and it is the true gradient: closed-form reference J^T g_W with an own g_W
    np.testing.assert_allclose(g / gn, eh.ref_twist_gradient(x, rest, k).reshape(N, 12) / gn,
                               rtol=0, atol=1e-11)


def test_PHP_alone_is_wrong_and_alpha_beta_term_fixes_it():
    x, rest, k = _cases(44)
    P, J = twist.w_jacobians(x)
    Hk = twist.hessian(x, rest, k, filter="none")
    Hfd = eh.fd_hessian_of_gradient(lambda y: eh.ref_twist_gradient(y, rest, k), x, 1e-5)
    err_php, err_full, err_kernel = [], [], []
    for i in range(N):
        HW, *_ = eh.spec_twist_H_W(x[i], rest[i], k[i])   # own H_W, independent of the kernel
        Dt = P[i] - J[i]
        php = P[i].T @ HW @ P[i]
        full = php - Dt.T @ HW @ Dt
        nrm = np.linalg.norm(Hfd[i])
        err_php.append(np.linalg.norm(php - Hfd[i]) / nrm)
        err_full.append(np.linalg.norm(full - Hfd[i]) / nrm)
        err_kernel.append(np.linalg.norm(Hk[i] - full) / np.linalg.norm(full))
    err_php, err_full, err_kernel = map(np.array, (err_php, err_full, err_kernel))
    print("\n|P^T H_W P - H_fd| / |H_fd|:", np.array2string(err_php, precision=3))
    print("|P^T H_W P - Dt^T H_W Dt - H_fd| / |H_fd|:", np.array2string(err_full, precision=2))
    assert np.all(err_full < 1e-6)
    assert np.all(err_kernel < 1e-10)
    assert np.all(err_php > 1e3 * err_full)
    assert np.median(err_php) > 0.10, err_php
    assert np.max(err_php) > 0.30, err_php
    # J^T H_W J is not the Hessian either (the second-order W terms are missing)
    HW0, *_ = eh.spec_twist_H_W(x[0], rest[0], k[0])
    assert np.linalg.norm(J[0].T @ HW0 @ J[0] - Hfd[0]) / np.linalg.norm(Hfd[0]) > 1e3 * err_full[0]


def test_twist_sign_convention():
    # right-handed: e1 along +z, a along +x, b along +y -> phi = +pi/2
    x = np.array([[[1.0, 0, 0], [0, 0, 0], [0, 0, 1], [0, 1, 1]]])
    np.testing.assert_allclose(twist.angle(x), [np.pi / 2], atol=1e-15)
    # mirror image: phi = -pi/2
    xm = x * np.array([1.0, -1.0, 1.0])
    np.testing.assert_allclose(twist.angle(xm), [-np.pi / 2], atol=1e-15)
    # antiparallel a, b: phi = pi (not -pi)
    xp = np.array([[[1.0, 0, 0], [0, 0, 0], [0, 0, 1], [-1, 0, 1]]])
    assert twist.angle(xp)[0] == np.pi
    # generic: sign(phi) == sign(det W)
    rng = np.random.default_rng(45)
    xr = eh.random_twist(rng, 50, 1.0)
    W = twist.w_matrix(xr)
    phi = twist.angle(xr)
    assert np.all(np.sign(phi) == np.sign(np.linalg.det(W)))
    assert (phi > 0).any() and (phi < 0).any()


def test_4c_helix_torsion_magnitude():
    """SPEC section 6: the 4C helix (72 degrees and 0.1 cm per vertex, radius 0.5) has
    edge ~0.596 cm, bend angle ~1.906 rad and torsion magnitude ~0.2425 rad."""
    from lc_petsc.elements import bend, stretch
    w = eh.helix_wisp(12)
    np.testing.assert_allclose(stretch.length(eh.stencils(w, 2)), 0.596, atol=1e-3)
    np.testing.assert_allclose(bend.angle(eh.stencils(w, 3)), 1.906, atol=1e-3)
    np.testing.assert_allclose(np.abs(twist.angle(eh.stencils(w, 4))), 0.2425, atol=1e-3)
