"""Clusters across ranks (-lc_cluster_span global, lc_petsc/contact_pc.py) on synthetic
matrices: the preconditioner applied on 1, 2 or 3 ranks equals the dense inverse of
P = A + (the cross blocks inside a cluster), with clusters that interleave in wisp order
and cross the partition; with -lc_cluster_span rank the cross-rank couplings drop out.
Collective (mpi): the same numbers on any rank count."""

import numpy as np
import pytest
from petsc4py import PETSc

from lc_petsc.contact import SumOperator
from lc_petsc.contact_pc import ClusterPC, cluster_owners

#: vertices of each wisp (global order); wisp 6 has no contact (a singleton)
SIZES = np.array([3, 4, 3, 3, 2, 3, 2])
#: contact couplings (wisp a, wisp b): clusters {0, 3}, {1, 4}, {2, 5} interleave in wisp order
PAIRS = [(0, 3), (1, 4), (2, 5)]


def global_matrices(rng):
    """Dense A (SPD, block diagonal by wisp), C (symmetric cross blocks between the
    wisps of PAIRS) and the vertex offsets of the wisps."""
    off = np.concatenate([[0], np.cumsum(SIZES)])
    n = 3 * off[-1]
    A = np.zeros((n, n))
    for w in range(len(SIZES)):
        i = slice(3 * off[w], 3 * off[w + 1])
        G = rng.standard_normal((3 * SIZES[w], 3 * SIZES[w]))
        A[i, i] = G @ G.T + 3 * SIZES[w] * np.eye(3 * SIZES[w])
    C = np.zeros((n, n))
    for a, b in PAIRS:
        ia, ib = slice(3 * off[a], 3 * off[a + 1]), slice(3 * off[b], 3 * off[b + 1])
        B = rng.standard_normal((3 * SIZES[a], 3 * SIZES[b]))
        C[ia, ib], C[ib, ia] = B, B.T
    return A, C, off


def petsc_baij(D, r0, r1, comm):
    """Rows r0:r1 (this rank's) of the dense matrix D as an MPI BAIJ (bs 3) matrix."""
    n = len(D)
    M = PETSc.Mat().createBAIJ(size=((r1 - r0, n), (r1 - r0, n)), bsize=3, comm=comm)
    M.setPreallocationNNZ((n // 3, n // 3))
    for i in range(r0, r1):
        cols = np.flatnonzero(D[i]).astype(PETSc.IntType)
        M.setValues([i], cols, D[i, cols])
    M.assemble()
    return M


def apply_cluster_pc(span, comm):
    """(P^-1 r on every rank, gathered; the dense P; r; the PC's last stats)."""
    rng = np.random.default_rng(5)
    A, C, off = global_matrices(rng)
    r = rng.standard_normal(len(A))
    parts = np.array_split(np.arange(len(SIZES)), comm.size)
    mine = parts[comm.rank]
    r0, r1 = 3 * off[mine[0]] if len(mine) else 0, 3 * off[mine[-1] + 1] if len(mine) else 0
    pA, pC = petsc_baij(A, r0, r1, comm), petsc_baij(C, r0, r1, comm)
    ctx = SumOperator(pA)
    ctx.C = pC
    op = PETSc.Mat().createPython(pA.getSizes(), ctx, comm=comm)
    op.setUp()
    pc = PETSc.PC().create(comm=comm)
    pcx = ClusterPC(3 * SIZES[mine], span=span)
    pc.setType(PETSc.PC.Type.PYTHON)
    pc.setPythonContext(pcx)
    pc.setOperators(op, pA)
    x, y = pA.createVecs()
    try:
        pc.setUp()
        x.array[:] = r[r0:r1]
        pc.apply(x, y)
        got = np.concatenate(comm.tompi4py().allgather(y.array.copy()))
        stats = dict(pcx.stats)
    finally:
        for obj in (x, y, pc, op, pA, pC):
            obj.destroy()
    wisp = np.repeat(np.arange(len(SIZES)), 3 * SIZES)
    rank_of = np.repeat(np.arange(comm.size), [len(p) for p in parts])
    keep = np.zeros_like(C, bool)
    for a, b in PAIRS:
        if span == "global" or rank_of[a] == rank_of[b]:
            keep |= np.outer(wisp == a, wisp == b) | np.outer(wisp == b, wisp == a)
    return got, A + np.where(keep, C, 0.0), r, stats


@pytest.mark.mpi
def test_clusters_across_ranks_are_the_exact_inverse():
    comm = PETSc.COMM_WORLD
    got, P, r, stats = apply_cluster_pc("global", comm)
    ok = np.allclose(got, np.linalg.solve(P, r), rtol=1e-10, atol=1e-12 * np.abs(got).max())
    # every rank count holds the same three clusters; on several ranks they cross the partition
    figures = comm.tompi4py().allgather((stats["clusters"], stats["cross_rank_clusters"]))
    assert ok, (np.abs(got - np.linalg.solve(P, r)).max(), stats)
    assert sum(f[0] for f in figures) == 3, figures
    assert all(f[1] == (0 if comm.size == 1 else 3 if comm.size == 3 else 2) for f in figures), figures
    assert stats["cross_rank_couplings"] == figures[0][1]
    # the per-wisp Cholesky solves only wisp 6 (2 vertices), the one wisp in no cluster
    assert sum(comm.tompi4py().allgather(stats["band_rows"])) == 6


@pytest.mark.mpi
def test_rank_span_drops_the_cross_rank_couplings():
    comm = PETSc.COMM_WORLD
    got, P, r, stats = apply_cluster_pc("rank", comm)
    np.testing.assert_allclose(got, np.linalg.solve(P, r), rtol=1e-10, atol=1e-12 * np.abs(got).max())
    if comm.size > 1:       # a control: the global clusters' inverse is a different one
        glob, Pg, _, _ = apply_cluster_pc("global", comm)
        assert np.abs(glob - got).max() > 1e-3 * np.abs(got).max()
        assert stats["couplings"] < len(PAIRS)


def test_cluster_span_is_checked():
    with pytest.raises(ValueError, match="use one of global, rank"):
        ClusterPC([9, 9], span="all")


def test_cluster_owners_balance_the_factorisations():
    # vertices per (cluster, rank): clusters 0-3 all on rank 1, cluster 4 split, row 5 no cluster
    held = np.array([[0, 40], [0, 30], [0, 20], [0, 10], [6, 4], [0, 0]], float)
    owner = cluster_owners(held)
    # majority first (cluster 4 to rank 0: loads 10 / 100), then the largest clusters of
    # rank 1 move to rank 0 while it stays at or below the mean (55): 40 (-> 50 / 60);
    # 30, 20 and 10 would take rank 0 past the mean
    np.testing.assert_array_equal(owner[:5], [0, 1, 1, 1, 0])
    load = np.bincount(owner[:5], weights=held[:5].sum(axis=1), minlength=2)
    np.testing.assert_array_equal(load, [50, 60])
    np.testing.assert_array_equal(cluster_owners(held[:, :1]), np.zeros(6, int))   # one rank


def test_cluster_owners_count_the_per_wisp_rows():
    """Each rank's per-wisp solves count in its load: the clustered wisps' rows are
    skipped there, so two ranks of 100 vertices each, rank 1 with its clusters of 40
    and 20 of them, are balanced as they are (100 / 100), where the cluster rows alone
    (0 / 60) sent the 20 to rank 0 (a VecScatter across ranks at every application)."""
    held = np.array([[0, 40], [0, 20]], float)
    np.testing.assert_array_equal(cluster_owners(held), [1, 0])
    np.testing.assert_array_equal(cluster_owners(held, base=[100, 40]), [1, 1])
    # rank 1 holding more per-wisp rows as well (loads 60 / 140): its 40 moves (100 / 100)
    np.testing.assert_array_equal(cluster_owners(held, base=[60, 80]), [0, 1])


def _sum_product(A, C, comm, mat_type="baij"):
    """(SumOperator's (A + C) r gathered, PETSc's A r + C r gathered, whether A's and C's
    products took the compiled path) for dense A, C on this rank's rows, both of
    ``mat_type``."""
    rng = np.random.default_rng(11)
    r = rng.standard_normal(len(A)) * 10.0 ** rng.integers(-8, 9, len(A))
    parts = np.array_split(np.arange(len(SIZES)), comm.size)
    off = np.concatenate([[0], np.cumsum(SIZES)])
    mine = parts[comm.rank]
    r0, r1 = (3 * off[mine[0]], 3 * off[mine[-1] + 1]) if len(mine) else (0, 0)
    pA, pC = petsc_baij(A, r0, r1, comm), petsc_baij(C, r0, r1, comm)
    if mat_type != "baij":
        pA.convert(mat_type)
        pC.convert(mat_type)
    ctx = SumOperator(pA)
    ctx.C = pC
    op = PETSc.Mat().createPython(pA.getSizes(), ctx, comm=comm)
    op.setUp()
    x, y, z = pA.createVecs() + (pA.createVecLeft(),)
    try:
        x.array[:] = r[r0:r1]
        op.mult(x, y)
        pA.mult(x, z)
        pC.multAdd(x, z, z)
        gather = comm.tompi4py().allgather
        return (np.concatenate(gather(y.array.copy())), np.concatenate(gather(z.array.copy())),
                (bool(ctx._band), bool(ctx._contact)))
    finally:
        ctx.C = None
        for obj in (x, y, z, op, pA, pC):
            obj.destroy()


@pytest.mark.mpi
def test_sum_operator_product_equals_matmult_to_the_bit():
    """A x + C x through the compiled block product (lc_petsc/elements/compiled_mult.py)
    where the matrices are BAIJ, C's couplings across the partition through a scatter:
    PETSc's MatMult + MatMultAdd, bit for bit, with entries of magnitudes 1e-8 to 1e8.
    An A with entries in another rank's columns, or AIJ matrices, go through PETSc: the
    same numbers."""
    comm = PETSc.COMM_WORLD
    A, C, off = global_matrices(np.random.default_rng(3))
    scale = 10.0 ** np.random.default_rng(4).integers(-8, 9, A.shape)
    A = A * np.sqrt(scale * scale.T)                   # still symmetric
    C = C * np.sqrt(scale * scale.T)
    got, want, compiled = _sum_product(A, C, comm)
    assert compiled == (True, True), "BAIJ A (wisps on one rank) and C: the compiled products"
    np.testing.assert_array_equal(got, want)
    got, want, compiled = _sum_product(A, C, comm, "aij")
    assert compiled == (False, False)
    np.testing.assert_array_equal(got, want)
    coupled = A + C                                    # A couples wisps across the partition
    got, want, compiled = _sum_product(coupled, C, comm)
    assert compiled == (comm.size == 1, True)          # serial: no other rank, still compiled
    np.testing.assert_array_equal(got, want)
    # entries in another rank's columns on rank 0 alone (wisp 1's rows, wisp 4's columns):
    # every rank takes MatMult (a rank left alone in it would wait for the others' ghosts)
    one_sided = A.copy()
    rows, cols = slice(3 * off[1], 3 * off[2]), slice(3 * off[4], 3 * off[5])
    one_sided[rows, cols] = C[rows, cols]
    got, want, compiled = _sum_product(one_sided, C, comm)
    assert compiled == (comm.size == 1, True)
    np.testing.assert_array_equal(got, want)
