"""The compiled products of the contact operator A + C (lc_petsc/contact.py
``_BlockProduct``, lc_petsc/elements/compiled_mult.py): an exactly symmetric block
matrix is multiplied from its upper triangle and gives ``MatMult``'s result bit for bit;
anything else takes the full product; new values are picked up through the matrix's
state; and the simulator's A and C (penalty contact, analytic filter) are symmetric
exactly, so the run takes the half-byte path (mpi: the same on 1-3 ranks)."""

import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc

import lc_petsc.simulator as simmod
from lc_petsc.contact import _BlockProduct
from lc_petsc.elements import compiled_mult
from sim_helpers import touching_wisps_config, touching_wisps_source


def random_baij(rng, nb, density, symmetric=True, diagonal=True, wide=True):
    """A sequential BAIJ (bs 3) matrix: random blocks on a random pattern (symmetric
    pattern and values if ``symmetric``; diagonal blocks if ``diagonal``), entries of
    magnitudes 1e-8 to 1e8 (``wide``, else of order 1); and its dense copy."""
    n = 3 * nb
    mask = rng.random((nb, nb)) < density
    mask[rng.integers(0, nb, 3)] = False
    if symmetric:
        mask = np.triu(mask, 1)
        mask = mask | mask.T
    np.fill_diagonal(mask, diagonal)
    D = rng.standard_normal((n, n)) * (10.0 ** rng.integers(-8, 9, (n, n)) if wide else 1.0)
    if symmetric:
        D = np.triu(D) + np.triu(D, 1).T
    D *= np.kron(mask, np.ones((3, 3)))
    M = PETSc.Mat().createBAIJ(size=(n, n), bsize=3, comm=PETSc.COMM_SELF,
                               nnz=np.maximum(mask.sum(axis=1), 1).astype(PETSc.IntType))
    for i, j in zip(*np.nonzero(mask)):
        M.setValuesBlocked([i], [j], D[3 * i:3 * i + 3, 3 * j:3 * j + 3].ravel())
    M.assemble()
    return M, D


def products(M, x, y0):
    """(_BlockProduct's M x and y0 + M x, MatMult's and MatMultAdd's, the product object)."""
    prod = _BlockProduct(M)
    X = PETSc.Vec().createWithArray(x.copy(), comm=PETSc.COMM_SELF)
    Y0 = PETSc.Vec().createWithArray(y0.copy(), comm=PETSc.COMM_SELF)
    Y = Y0.duplicate()
    try:
        got = np.empty_like(y0)
        prod(x, got, False)
        got_add = y0.copy()
        prod(x, got_add, True)
        M.mult(X, Y)
        want = Y.array.copy()
        M.multAdd(X, Y0, Y)
        return got, got_add, want, Y.array.copy(), prod
    finally:
        for v in (X, Y0, Y):
            v.destroy()


def bits(a):
    return np.ascontiguousarray(a).view(np.int64)


@pytest.mark.parametrize("diagonal", [True, False])
@pytest.mark.parametrize("wide", [True, False])
def test_symmetric_product_equals_matmult_to_the_bit(diagonal, wide):
    """Entries of magnitudes 1e-8 to 1e8 (``wide``), or all of order 1, where every
    regrouping of a row's sum changes bits (checked: the control below)."""
    rng = np.random.default_rng(1)
    M, D = random_baij(rng, 40, 0.15 if wide else 0.3, diagonal=diagonal, wide=wide)
    try:
        for _ in range(3):
            x = rng.standard_normal(len(D)) * (10.0 ** rng.integers(-8, 9, len(D)) if wide else 1.0)
            y0 = rng.standard_normal(len(D))
            got, got_add, want, want_add, prod = products(M, x, y0)
            assert prod.symmetric, "an exactly symmetric matrix takes the upper-triangle product"
            assert len(prod.upper_values) < 0.65 * prod.n       # about half the bytes
            np.testing.assert_array_equal(bits(got), bits(want))
            np.testing.assert_array_equal(bits(got_add), bits(want_add))
            np.testing.assert_allclose(want, D @ x, rtol=1e-10, atol=1e-10 * np.abs(D).max() * np.abs(x).max())
        if not wide:    # control: the same sums grouped otherwise differ in many entries
            other = sum(D[:, 3 * j:3 * j + 3] @ x[3 * j:3 * j + 3] for j in reversed(range(len(D) // 3)))
            assert np.sum(bits(other) != bits(want)) > 0.2 * len(D)
    finally:
        M.destroy()


def test_signed_zeros_and_nan_take_the_full_product():
    """A block below the diagonal holding -0.0 against its mirror's +0.0, or a NaN: not
    symmetric bit for bit, so the full product (PETSc's signs of zero, its NaNs)."""
    rng = np.random.default_rng(5)
    for bad in (-0.0, np.nan):
        M, D = random_baij(rng, 20, 0.3, wide=False)
        i, j = map(int, np.argwhere(np.triu(np.abs(D[::3, ::3]) > 0, 1))[0])
        M.setValues([3 * i], [3 * j], [0.0 if bad == 0.0 else bad])
        M.setValues([3 * j], [3 * i], [bad])
        M.assemble()
        x = rng.standard_normal(len(D))
        try:
            got, got_add, want, want_add, prod = products(M, x, -0.0 * np.ones(len(D)))
            assert not prod.symmetric, bad
            np.testing.assert_array_equal(bits(got), bits(want))
            np.testing.assert_array_equal(bits(got_add), bits(want_add))
        finally:
            M.destroy()


def test_unsymmetric_values_or_pattern_take_the_full_product():
    rng = np.random.default_rng(2)
    M, D = random_baij(rng, 30, 0.2)
    i, j = map(int, np.argwhere(np.triu(np.abs(D[::3, ::3]) > 0, 1))[0])
    x = rng.standard_normal(len(D))
    y0 = rng.standard_normal(len(D))
    # one entry below the diagonal one ulp off its mirror: not symmetric, the full product
    value = D[3 * j, 3 * i]
    M.setValues([3 * j], [3 * i], [np.nextafter(value, np.inf)])
    M.assemble()
    N, _ = random_baij(rng, 30, 0.2, symmetric=False)          # an unsymmetric pattern
    try:
        for A in (M, N):
            got, got_add, want, want_add, prod = products(A, x, y0)
            assert not prod.symmetric
            np.testing.assert_array_equal(bits(got), bits(want))
            np.testing.assert_array_equal(bits(got_add), bits(want_add))
        assert _BlockProduct(N).upper is None                  # decided from the pattern
        flags = compiled_mult.bsr3_upper_pattern(*N.getRowIJ(compressed=True))[5]
        assert not flags
    finally:
        M.destroy()
        N.destroy()


def test_new_values_are_read_after_assembly():
    """The upper copy follows the matrix's state: values changed and assembled (as the
    assembler does every Newton iteration) are used by the next product."""
    rng = np.random.default_rng(3)
    M, D = random_baij(rng, 30, 0.2)
    x = rng.standard_normal(len(D))
    X, Y = M.createVecs()
    X.array[:] = x
    try:
        prod = _BlockProduct(M)
        first = np.empty(len(D))
        prod(x, first, False)
        M.scale(3.0)                    # assembles: a new state
        M.shift(1.0)
        again = np.empty(len(D))
        prod(x, again, False)
        M.mult(X, Y)
        assert prod.symmetric
        np.testing.assert_array_equal(bits(again), bits(Y.array))
        assert not np.array_equal(first, again)
    finally:
        for obj in (M, X, Y):
            obj.destroy()


@pytest.mark.mpi
def test_simulator_operator_takes_the_symmetric_products(monkeypatch):
    """Touching wisps with penalty contact (the default analytic filter) on 1-3 ranks:
    A's band and C's rank-local block are exactly symmetric after assembly, so CG's
    products read their upper triangles; the operator's product equals MatMult +
    MatMultAdd bit for bit."""
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: touching_wisps_source())
    cfg = touching_wisps_config(2)
    sim = simmod.build_simulator(cfg, comm=MPI.COMM_WORLD)
    try:
        sim.run()
        st = sim.strand
        assert st.shell_ctx is not None and st.C is not None, "no contact pair: the test needs some"
        x, y = st.shell.createVecs()
        z = y.duplicate()
        x.setRandom()
        st.shell.mult(x, y)
        ctx = st.shell_ctx
        assert ctx._band and ctx._band.symmetric, "A (the strand band) is symmetric"
        assert ctx._contact and ctx._contact[0][0].symmetric, "C's local block is symmetric"
        assert sim.solver.clusters.stats["band_factor"] == "cholesky"
        # A's pattern is the same every Newton iteration: its upper pattern and copy are reused
        assert ctx._band_kept is not None and ctx._band.upper_values is ctx._band_kept.upper_values
        A = sim.assembler.mat
        A.mult(x, z)
        st.C.multAdd(x, z, z)
        np.testing.assert_array_equal(bits(y.array), bits(z.array))
        for v in (x, y, z):
            v.destroy()
    finally:
        sim.close()
