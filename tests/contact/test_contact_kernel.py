"""Segment-segment penalty kernel (lc_petsc/elements/segment_contact.py): closest points,
finite-difference derivatives with h^2 convergence, filters, parallel pairs."""

import numpy as np
import pytest

from lc_petsc.elements import segment_contact as sc

D0, K = 0.3, 7.0e3


def crossing_pairs(n, rng, gap=0.1, jitter=0.05):
    """Pairs whose closest points are interior to both segments (distance ~ gap < D0)."""
    base = np.array([[-1.0, 0, 0], [1.0, 0, 0], [0, -1.0, gap], [0, 1.0, gap]])
    return base + jitter * rng.normal(size=(n, 4, 3))


def vertex_edge_pairs(n, rng):
    """Segment B's end x3 is the closest point on B; interior on A (t clamped at 1)."""
    base = np.array([[-1.0, 0, 0], [1.0, 0, 0], [0.2, 0.5, 1.0], [0.1, 0.02, 0.12]])
    return base + 0.01 * rng.normal(size=(n, 4, 3))


def fd_errors(X, h, filter="none", kernel=sc, d0=D0, k=K):
    """Largest relative errors of ``kernel``'s gradient (central differences of the
    energy) and Hessian with ``filter`` (central differences of the gradient)."""
    n = len(X)
    g = kernel.gradient(X, d0, k).reshape(n, 12)
    H = kernel.hessian(X, d0, k, filter=filter)
    gfd, Hfd = np.zeros_like(g), np.zeros_like(H)
    flat = X.reshape(n, 12)
    for j in range(12):
        Xp, Xm = flat.copy(), flat.copy()
        Xp[:, j] += h
        Xm[:, j] -= h
        Xp, Xm = Xp.reshape(n, 4, 3), Xm.reshape(n, 4, 3)
        gfd[:, j] = (kernel.energy(Xp, d0, k) - kernel.energy(Xm, d0, k)) / (2 * h)
        Hfd[:, :, j] = (kernel.gradient(Xp, d0, k) - kernel.gradient(Xm, d0, k)).reshape(n, 12) / (2 * h)
    return (np.abs(gfd - g).max() / np.abs(g).max(), np.abs(Hfd - H).max() / np.abs(H).max())


@pytest.mark.parametrize("make", [crossing_pairs, vertex_edge_pairs])
def test_gradient_and_exact_hessian_match_finite_differences_h2(make):
    X = make(20, np.random.default_rng(1))
    s, t, u, d, fs, ft, par = sc.closest_points(X)
    assert np.all(d < D0) and not par.any()
    if make is crossing_pairs:
        assert fs.all() and ft.all()
    else:
        assert fs.all() and np.all(t == 1.0)
    e1 = fd_errors(X, 1e-3)
    e2 = fd_errors(X, 5e-4)
    print(make.__name__, "FD rel. errors (grad, Hess) h=1e-3:", e1, "h=5e-4:", e2)
    assert e1[0] < 1e-4 and e1[1] < 1e-3
    # h^2 convergence: halving h divides the error by ~4
    assert 3.0 < e1[0] / e2[0] < 5.0
    assert 3.0 < e1[1] / e2[1] < 5.0


def test_closest_points_against_brute_force():
    rng = np.random.default_rng(2)
    X = rng.normal(size=(300, 4, 3))
    X[:50, 3] = X[:50, 2] + (X[:50, 1] - X[:50, 0]) * rng.uniform(0.2, 2.0, (50, 1))  # parallel
    d = sc.distance(X)
    grid = np.linspace(0.0, 1.0, 101)
    p = X[:, None, 0] + grid[None, :, None] * (X[:, None, 1] - X[:, None, 0])
    q = X[:, None, 2] + grid[None, :, None] * (X[:, None, 3] - X[:, None, 2])
    brute = np.linalg.norm(p[:, :, None] - q[:, None, :], axis=3).min(axis=(1, 2))
    assert np.all(d <= brute + 1e-12)
    assert np.all(brute - d < 2e-2 * (1 + brute))


def test_energy_zero_beyond_thickness_and_gradient_sums_to_zero():
    rng = np.random.default_rng(3)
    X = crossing_pairs(50, rng, gap=0.2, jitter=0.2)
    g = sc.gradient(X, D0, K)
    # internal force: no net force (momentum) and no net torque (angular momentum)
    assert np.abs(g.sum(axis=1)).max() < 1e-9 * np.abs(g).max()
    torque = np.cross(X, g).sum(axis=1)
    assert np.abs(torque).max() < 1e-9 * np.abs(g).max()
    far = crossing_pairs(10, rng, gap=1.0, jitter=0.01)
    assert np.all(sc.energy(far, D0, K) == 0) and np.all(sc.gradient(far, D0, K) == 0)
    assert np.all(sc.hessian(far, D0, K) == 0)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-8, 1e-6, 1e-4, 1e-2])
def test_parallel_and_nearly_parallel_pairs_are_finite_and_psd(angle):
    """Overlapping (nearly) parallel segments at distance 0.1: every filter finite; the
    analytic (Gauss-Newton) and numerical filters PSD; energy/gradient continuous."""
    rng = np.random.default_rng(4)
    n = 40
    X = np.zeros((n, 4, 3))
    X[:, 0] = (-1.0, 0, 0)
    X[:, 1] = (1.0, 0, 0)
    X[:, 2] = (-0.7, 0.1, 0)
    X[:, 3] = (1.3, 0.1 + 2.0 * np.tan(angle), 0)
    R = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]      # random rotations
    X = X @ R.transpose(0, 2, 1) + rng.normal(size=(n, 1, 3))
    d = sc.distance(X)
    assert np.allclose(d, 0.1, atol=2.1 * np.tan(angle) + 1e-12)
    for f in sc.FILTERS:
        H = sc.hessian(X, D0, K, filter=f)
        g = sc.gradient(X, D0, K)
        assert np.isfinite(H).all() and np.isfinite(g).all(), f
        if f != "none":
            lam = np.linalg.eigvalsh(H)
            assert lam.min() >= -1e-9 * max(lam.max(), 1.0), (f, lam.min())
    H = sc.hessian(X, D0, K)
    # Gauss-Newton bound: k |w|^2 <= 4 k
    assert np.linalg.eigvalsh(H).max() <= 4 * K * (1 + 1e-12)
    # force magnitude k (d0 - d) along n, split between the vertices by w
    fmag = np.linalg.norm(sc.gradient(X, D0, K)[:, :2].sum(axis=1), axis=1)
    assert np.allclose(fmag, K * (D0 - d), rtol=1e-9)


def test_intersecting_segments_finite():
    X = np.array([[[-1.0, 0, 0], [1.0, 0, 0], [0, -1.0, 0], [0, 1.0, 0]],      # crossing
                  [[-1.0, 0, 0], [1.0, 0, 0], [-0.5, 0, 0], [0.5, 0, 0]]])    # collinear overlap
    for f in sc.FILTERS:
        assert np.isfinite(sc.hessian(X, D0, K, filter=f)).all()
    g = sc.gradient(X, D0, K)
    assert np.isfinite(g).all()
    assert np.allclose(np.linalg.norm(g[:, :2].sum(axis=1), axis=1), K * D0)


def test_filters_psd_and_numerical_is_projection_of_exact():
    rng = np.random.default_rng(5)
    X = np.concatenate([crossing_pairs(100, rng, gap=0.15, jitter=0.3), vertex_edge_pairs(20, rng)])
    Hn = sc.hessian(X, D0, K, filter="none")
    Hm = sc.hessian(X, D0, K, filter="numerical")
    Ha = sc.hessian(X, D0, K, filter="analytic")
    for H in (Hm, Ha):
        lam = np.linalg.eigvalsh(H)
        assert lam.min() >= -1e-8 * np.abs(lam).max()
    lam, V = np.linalg.eigh(Hn)
    proj = (V * np.maximum(lam, 0)[:, None, :]) @ V.transpose(0, 2, 1)
    assert np.abs(proj - Hm).max() < 1e-8 * np.abs(Hm).max()
    # the exact Hessian is indefinite in general (tangential curvature of the distance)
    assert (np.linalg.eigvalsh(Hn).min(axis=1) < -1e-6 * K).any()


def test_bad_input_raises():
    with pytest.raises(ValueError, match="thickness"):
        sc.energy(np.zeros((1, 4, 3)), -1.0, K)
    with pytest.raises(ValueError, match="shape"):
        sc.energy(np.zeros((1, 3, 3)), D0, K)
    with pytest.raises(ValueError, match="filter"):
        sc.hessian(np.zeros((1, 4, 3)) + np.arange(4)[None, :, None], D0, K, filter="bogus")


def test_separation_reaches_the_target_and_conserves_momentum():
    """The projection takes pairs below the target to it (to first order: exactly for
    translations along the normal), moves nothing else, and sum m dx = 0."""
    rng = np.random.default_rng(5)
    n = 200
    x = rng.normal(size=(n, 4, 3))
    x[:, 2:] = x[:, :2] + rng.normal(size=(n, 2, 3)) * 0.05 + 0.02   # close pairs
    d = sc.distance(x)
    target = np.median(d)
    m = rng.uniform(0.5, 2.0, size=(n, 4))
    dx = sc.separation(x, 1.0 / m, target)
    below = d < target
    assert below.sum() > 50 and np.all(dx[~below] == 0.0)
    assert np.abs((m[:, :, None] * dx).sum(axis=1)).max() < 1e-14
    d1 = sc.distance(x + dx)
    assert np.all(d1[below] > d[below])
    # first order: the new distance is within O(step^2) of the target
    step = np.linalg.norm(dx, axis=2).max(axis=1)
    assert np.all(np.abs(d1[below] - target) <= 2.0 * step[below] ** 2 / np.maximum(d[below], 1e-3) + 1e-12)
    # a pure translation of B along the normal: exact
    y = np.array([[[0, 0, 0], [1, 0, 0], [0.5, 0.05, -1], [0.5, 0.05, 1]]], float)
    dy = sc.separation(y, np.ones((1, 4)), 0.2)
    assert sc.distance(y + dy)[0] == pytest.approx(0.2, rel=1e-12)
    # pinned vertices (inverse mass 0) do not move; all pinned: nothing moves
    im = np.ones((1, 4))
    im[0, :2] = 0.0
    dy = sc.separation(y, im, 0.2)
    assert np.all(dy[0, :2] == 0.0) and sc.distance(y + dy)[0] == pytest.approx(0.2, rel=1e-12)
    assert np.all(sc.separation(y, np.zeros((1, 4)), 0.2) == 0.0)
    with pytest.raises(ValueError, match="inverse_mass"):
        sc.separation(y, -np.ones((1, 4)), 0.2)
    with pytest.raises(ValueError, match="inverse_mass"):
        sc.separation(y, np.ones((2, 4)), 0.2)


def test_compiled_penalty_rows_equal_the_numpy_kernel_to_the_bit():
    """lc_petsc.elements.compiled_contact.penalty_rows (what the simulator assembles with
    the default penalty and filter) against this module's gradient and analytic Hessian,
    the pinned vertices zeroed and the rows and cross blocks cut out as the contact
    assembly did before: equal to the bit, on crossing, vertex-edge, random, inactive,
    parallel, intersecting, coincident and zero-length pairs."""
    from lc_petsc.elements import compiled_ccd, compiled_contact
    rng = np.random.default_rng(7)
    X = np.concatenate([crossing_pairs(200, rng), vertex_edge_pairs(200, rng),
                        0.3 * rng.normal(size=(2000, 4, 3))])
    X[0, 2:] = X[0, :2] + [0.0, 0.01, 0.0]                               # parallel
    mid = 0.5 * (X[1, 0] + X[1, 1])
    X[1, 2], X[1, 3] = mid + [0.0, 0.0, 0.3], mid - [0.0, 0.0, 0.3]       # intersecting
    X[2, 2:] = X[2, :2]                                                  # coincident
    X[3, 1] = X[3, 0]                                                    # zero length
    X[4, 2:] = X[4, :2] + 1e-7 * rng.normal(size=(2, 3))                 # nearly coincident
    X[5] = [[0, 0, 0], [0, 0, 0], [1, 1, 1], [2, 1, 1]]                  # zero length, t clamped
    n = len(X)
    free = rng.random((n, 4)) < 0.85
    owner_a, owner_b = rng.integers(0, 3, n), rng.integers(0, 3, n)
    rows, cross_ab, cross_ba = compiled_contact.penalty_rows(X, D0, K, free, owner_a, owner_b)
    g, H = sc.gradient_hessian(X, D0, K, filter="analytic")
    fr = free.repeat(3, axis=1).astype(float)
    g *= free[:, :, None]
    H *= fr[:, :, None] * fr[:, None, :]
    def bits(a):        # to the bit: signed zeros told apart
        return np.ascontiguousarray(a).view(np.int64)
    np.testing.assert_array_equal(bits(rows), bits(compiled_ccd.pair_rows(g, H, owner_a, owner_b)))
    np.testing.assert_array_equal(bits(cross_ab), bits(H[:, 0:6, 6:12].reshape(n, 36)))
    np.testing.assert_array_equal(bits(cross_ba), bits(H[:, 6:12, 0:6].reshape(n, 36)))
    active = sc.distance(X) < D0
    assert 0 < active.sum() < n and np.abs(cross_ab[active]).max() > 0.1 * K


def test_compiled_penalty_rows_check_their_input():
    from lc_petsc.elements import compiled_contact
    from lc_petsc.errors import ElementError
    X = crossing_pairs(3, np.random.default_rng(0))
    free, owners = np.ones((3, 4), bool), np.zeros(3, np.int64)
    X[1, 2, 0] = np.nan
    with pytest.raises(ElementError, match="element 1 has a non-finite position"):
        compiled_contact.penalty_rows(X, D0, K, free, owners, owners)
    X[1, 2, 0] = 0.0
    with pytest.raises(ValueError, match="free must be"):
        compiled_contact.penalty_rows(X, D0, K, free[:2], owners, owners)
    with pytest.raises(ElementError, match="thickness"):
        compiled_contact.penalty_rows(X, -D0, K, free, owners, owners)
