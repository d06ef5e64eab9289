"""The compiled per-wisp block Cholesky of the strand band (lc_petsc/elements/compiled_band.py)
and its use as the contact preconditioner's singleton solve (``-lc_band_factor``,
lc_petsc/contact_pc.py): exact solves on banded SPD wisps of any length (one vertex,
pinned identity rows, stiff chains where a block LDL^T fails), the fallback to PETSc's
LU where A is not positive definite or couples wisps, and the option's check."""

import numpy as np
import pytest
from petsc4py import PETSc

from lc_petsc.contact_pc import ClusterPC
from lc_petsc.elements.compiled_band import BandCholesky
from lc_petsc.errors import ConfigError
from lc_petsc.solver_plan import SolverPlan


def block_csr(D, b):
    """(block rows, block columns, column-major block values) of the dense D's blocks
    within b of the diagonal (3x3 blocks)."""
    nb = len(D) // 3
    indptr, indices, values = [0], [], []
    for i in range(nb):
        for j in range(max(0, i - b), min(nb, i + b + 1)):
            if np.any(D[3 * i:3 * i + 3, 3 * j:3 * j + 3]) or i == j:
                indices.append(j)
                values.append(D[3 * i:3 * i + 3, 3 * j:3 * j + 3].T.ravel())
        indptr.append(len(indices))
    return (np.array(indptr, np.int32), np.array(indices, np.int32),
            np.concatenate(values) if values else np.zeros(0))


def banded_spd_wisps(rng, sizes, b=3, pinned=2):
    """Dense SPD A, block diagonal by wisp, each wisp block banded (half bandwidth b
    blocks), the first ``pinned`` vertices of each wisp identity rows and columns."""
    off = np.concatenate([[0], np.cumsum(sizes)])
    A = np.zeros((3 * off[-1], 3 * off[-1]))
    for w, n in enumerate(sizes):
        G = rng.standard_normal((3 * n, 3 * n)) * (np.abs(np.subtract.outer(np.arange(3 * n) // 3,
                                                                         np.arange(3 * n) // 3)) <= b // 2)
        W = G @ G.T + 0.1 * np.eye(3 * n)
        W *= 10.0 ** rng.integers(-3, 4)
        for v in range(min(pinned, n)):
            W[3 * v:3 * v + 3, :] = 0.0
            W[:, 3 * v:3 * v + 3] = 0.0
            W[3 * v:3 * v + 3, 3 * v:3 * v + 3] = np.eye(3)
        s = slice(3 * off[w], 3 * off[w + 1])
        A[s, s] = W
    return A, off


def test_band_cholesky_solves_exactly_on_wisps_of_any_length():
    rng = np.random.default_rng(0)
    sizes = [1, 2, 7, 30, 4, 1, 12]
    A, off = banded_spd_wisps(rng, sizes)
    chol = BandCholesky(off)
    assert chol.factor(*block_csr(A, 3)) is None
    assert chol.b == 2          # the widest block coupling of this pattern
    x = rng.standard_normal(len(A))
    y = np.full(len(A), np.nan)
    chol.apply(x, y)
    np.testing.assert_allclose(y, np.linalg.solve(A, x), rtol=1e-9, atol=1e-12 * np.abs(y).max())


def test_band_cholesky_solves_the_chosen_wisps_only():
    """The cluster preconditioner skips its clustered wisps (their cluster's LU writes
    their rows): the other wisps' rows equal the full solve's bit for bit, the skipped
    rows are left as they were."""
    rng = np.random.default_rng(3)
    sizes = [3, 5, 2, 6]
    A, off = banded_spd_wisps(rng, sizes)
    chol = BandCholesky(off)
    assert chol.factor(*block_csr(A, 3)) is None
    x = rng.standard_normal(len(A))
    full = np.empty_like(x)
    chol.apply(x, full)
    part = np.full(len(A), np.nan)
    chol.apply(x, part, np.array([1, 3], np.int64))
    rows = np.repeat(np.arange(len(sizes)), 3 * np.array(sizes))
    solved = np.isin(rows, [1, 3])
    assert np.array_equal(part[solved], full[solved])
    assert np.isnan(part[~solved]).all() and solved.sum() == 3 * (5 + 6)


def stiff_chain(n=101, k=1e9, m=1.0, seed=0):
    """A chain of rank-one springs of stiffness k between n vertices of mass m (3D)."""
    rng = np.random.default_rng(seed)
    A = m * np.eye(3 * n)
    for i in range(n - 1):
        d = rng.standard_normal(3)
        P = k * np.outer(d, d) / (d @ d)
        a, c = slice(3 * i, 3 * i + 3), slice(3 * i + 3, 3 * i + 6)
        A[a, a] += P
        A[c, c] += P
        A[a, c] -= P
        A[c, a] -= P
    return A


def test_band_cholesky_is_stable_on_a_stiff_chain():
    """Condition ~3e9: the factor's solve stays at the round-off of a pivoted LU (a block
    LDL^T of the same band leaves a residual ~1e2 of the right-hand side)."""
    A = stiff_chain()
    chol = BandCholesky([0, len(A) // 3])
    assert chol.factor(*block_csr(A, 3)) is None
    x = np.random.default_rng(1).standard_normal(len(A))
    y = np.empty_like(x)
    chol.apply(x, y)
    assert np.abs(A @ y - x).max() < 1e-5 * np.abs(x).max()


def test_band_cholesky_refuses_what_it_cannot_factor():
    rng = np.random.default_rng(2)
    A, off = banded_spd_wisps(rng, [5, 6])
    indefinite = A.copy()
    indefinite[3 * 7 + 1, 3 * 7 + 1] = -1.0                 # vertex 7 (wisp 1, row 2)
    why = BandCholesky(off).factor(*block_csr(indefinite, 3))
    assert why is not None and "not positive definite" in why
    coupled = A.copy()                                      # wisps 0 and 1 coupled
    coupled[3 * 4:3 * 5, 3 * 5:3 * 6] = coupled[3 * 5:3 * 6, 3 * 4:3 * 5] = 0.01 * np.eye(3)
    assert "couples two wisps" in BandCholesky(off).factor(*block_csr(coupled, 3))
    assert "block rows" in BandCholesky([0, 4]).factor(*block_csr(A, 3))


def seq_baij(D):
    indptr, indices, values = block_csr(D, len(D) // 3)
    n = len(D)
    M = PETSc.Mat().createBAIJ(size=(n, n), bsize=3, comm=PETSc.COMM_SELF,
                               nnz=np.diff(indptr).astype(PETSc.IntType))
    for i in range(n // 3):
        for t in range(indptr[i], indptr[i + 1]):
            j = indices[t]
            M.setValuesBlocked([i], [j], D[3 * i:3 * i + 3, 3 * j:3 * j + 3].ravel())
    M.assemble()
    return M


def apply_pc(A, off, band_factor):
    """(P^-1 r, the PC's stats) of the cluster preconditioner on the sequential BAIJ of
    the dense A (no contact: every wisp a singleton)."""
    M = seq_baij(A)
    pcx = ClusterPC(3 * np.diff(off), band_factor=band_factor)
    pc = PETSc.PC().create(comm=PETSc.COMM_SELF)
    pc.setType(PETSc.PC.Type.PYTHON)
    pc.setPythonContext(pcx)
    pc.setOperators(M, M)
    x, y = M.createVecs()
    try:
        pc.setUp()
        x.array[:] = np.arange(len(A)) % 7 - 3.0
        pc.apply(x, y)
        return y.array.copy(), dict(pcx.stats)
    finally:
        for obj in (x, y, pc, M):
            obj.destroy()


def test_cluster_pc_singletons_by_cholesky_or_lu():
    rng = np.random.default_rng(4)
    A, off = banded_spd_wisps(rng, [6, 9, 3])
    r = np.arange(len(A)) % 7 - 3.0
    want = np.linalg.solve(A, r)
    for factor in ("cholesky", "ilu"):
        got, stats = apply_pc(A, off, factor)
        assert stats["band_factor"] == ("cholesky" if factor == "cholesky" else "ilu (-lc_band_factor ilu)")
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12 * np.abs(want).max())
    # an indefinite band (an exact Hessian's negative curvature): PETSc's LU instead
    A[3 * 8, 3 * 8] = -5.0
    got, stats = apply_pc(A, off, "cholesky")
    assert stats["band_factor"].startswith("ilu (not positive definite")
    np.testing.assert_allclose(got, np.linalg.solve(A, r), rtol=1e-8, atol=1e-12 * np.abs(got).max())


def test_cluster_pc_set_up_again_switches_factor_and_cleans_up():
    """One preconditioner set up three times (as every Newton iteration does): SPD band
    (Cholesky), indefinite (PETSc's LU, created), SPD again (Cholesky, the LU destroyed);
    each application exact for its matrix."""
    rng = np.random.default_rng(6)
    A, off = banded_spd_wisps(rng, [5, 8])
    bad = A.copy()
    bad[3 * 6, 3 * 6] = -2.0
    pcx = ClusterPC(3 * np.diff(off))
    pc = PETSc.PC().create(comm=PETSc.COMM_SELF)
    pc.setType(PETSc.PC.Type.PYTHON)
    pc.setPythonContext(pcx)
    r = np.arange(len(A)) % 5 - 2.0
    try:
        for D, factor in ((A, "cholesky"), (bad, "ilu"), (2.0 * A, "cholesky")):
            M = seq_baij(D)
            x, y = M.createVecs()
            pc.setOperators(M, M)
            pc.setUp()
            x.array[:] = r
            pc.apply(x, y)
            assert pcx.stats["band_factor"].startswith(factor)
            assert (pcx.band is None) == (factor == "cholesky")
            np.testing.assert_allclose(y.array, np.linalg.solve(D, r), rtol=1e-8,
                                       atol=1e-12 * np.abs(y.array).max())
            for obj in (x, y, M):
                obj.destroy()
    finally:
        pc.destroy()


def test_far_coupling_is_refused_without_a_band_sized_allocation():
    """A block coupling the first and the last vertex (two wisps): refused before any
    array of the band's size (n x (2 b + 1)) is made."""
    rng = np.random.default_rng(7)
    A, off = banded_spd_wisps(rng, [200, 200])
    A[0:3, -3:] = A[-3:, 0:3] = 0.01 * np.eye(3)
    chol = BandCholesky(off)
    assert "couples two wisps" in chol.factor(*block_csr(A, len(A) // 3))
    assert chol.F is None and chol.pos.size == 0


def test_band_factor_option_is_checked():
    assert SolverPlan.resolve("", strand_contact=True).cluster_caps[-1] == "cholesky"
    assert SolverPlan.resolve("-lc_band_factor ilu", strand_contact=True).cluster_caps[-1] == "ilu"
    with pytest.raises(ConfigError, match="lc_band_factor"):
        SolverPlan.resolve("-lc_band_factor lu", strand_contact=True)
    with pytest.raises(ValueError, match="use one of cholesky, ilu"):
        ClusterPC([9], band_factor="lu")
