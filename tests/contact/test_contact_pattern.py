"""The cluster preconditioner reads this rank's blocks of the contact matrix C in place
(``contact_pc.local_blocks``: its diagonal and off-diagonal blocks, no copy of its rows):
the same rows, columns and values, in the same order, as a copy of the rows made by
``MatCreateSubMatrices`` (what it did before), bit for bit, for a C with couplings on
both sides of every rank's diagonal block; and a set-up of the preconditioner makes no
such copy (mpi: the same on 1-3 ranks)."""

import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc

from lc_petsc.contact_pc import ClusterPC, block_rows, local_blocks

pytestmark = pytest.mark.mpi

SIZES = np.array([7, 5, 9, 6, 8, 5, 7, 6])        # vertices per wisp


def random_c(rng, comm):
    """A symmetric BAIJ (bs 3) C over the wisps of SIZES (split between the ranks by
    whole wisps): random cross blocks between vertices of different wisps (every wisp
    coupled to the first and the last one, so each rank has columns before and after its
    own), magnitudes 1e-8 to 1e8; and this rank's wisps."""
    off = np.concatenate([[0], np.cumsum(SIZES)])
    n = off[-1]
    wisp = np.repeat(np.arange(len(SIZES)), SIZES)
    mask = (rng.random((n, n)) < 0.08) & (wisp[:, None] != wisp[None, :])
    mask[wisp == 0, off[-2]] = mask[wisp == len(SIZES) - 1, 0] = True
    mask = np.triu(mask, 1)
    mask = mask | mask.T
    parts = np.array_split(np.arange(len(SIZES)), comm.size)
    mine = parts[comm.rank]
    b0, b1 = (off[mine[0]], off[mine[-1] + 1]) if len(mine) else (0, 0)
    C = PETSc.Mat().createBAIJ(size=((3 * (b1 - b0), 3 * n), (3 * (b1 - b0), 3 * n)), bsize=3, comm=comm)
    C.setUp()
    blocks = rng.standard_normal((n, n, 3, 3)) * 10.0 ** rng.integers(-8, 9, (n, n, 3, 3))
    blocks = blocks + blocks.transpose(1, 0, 3, 2)
    for i in range(b0, b1):
        for j in np.flatnonzero(mask[i]):
            C.setValuesBlocked([i], [j], blocks[i, j].ravel())
    C.assemble()
    return C, mine


def copies_made():
    """MatCreateSubMatrices calls so far (PETSc's log, started here if it was not)."""
    PETSc.Log.begin()
    return PETSc.Log.Event("MatCreateSubMats").getPerfInfo()["count"]


def copied_rows(C):
    """block_rows of the rank's rows copied by MatCreateSubMatrices (the rows themselves
    on one rank)."""
    if C.getComm().getSize() == 1:
        return block_rows(C)
    r0, r1 = C.getOwnershipRange()
    rows = PETSc.IS().createStride(r1 - r0, r0, 1, comm=PETSc.COMM_SELF)
    cols = PETSc.IS().createStride(C.getSize()[1], 0, 1, comm=PETSc.COMM_SELF)
    sub = C.createSubMatrices(rows, cols)[0]
    try:
        return block_rows(sub)
    finally:
        for obj in (sub, rows, cols):
            obj.destroy()


def test_local_blocks_equal_a_copy_of_the_rows_bit_for_bit():
    comm = PETSc.COMM_WORLD
    C, _ = random_c(np.random.default_rng(3), comm)
    try:
        want = copied_rows(C)
        r0 = C.getOwnershipRange()[0] // 3
        before = after = 0
        if comm.getSize() > 1:
            before, after = int(np.sum(want[1] < r0)), int(np.sum(want[1] >= C.getOwnershipRange()[1] // 3))
        copies = copies_made()
        got = local_blocks(C)
        assert copies_made() == copies, "a copy of C's rows"
        assert len(want[0]) > 0
        for a, b in zip(got, want):
            assert a.shape == b.shape
            np.testing.assert_array_equal(a.view(np.int64), b.view(np.int64))    # bit for bit
        # the middle ranks read columns on both sides of their diagonal block
        if 0 < comm.getRank() < comm.getSize() - 1:
            assert before > 0 and after > 0
    finally:
        C.destroy()


class _Shell:
    """A shell operator's context with the strand matrix A and the contact matrix C."""

    def __init__(self, A, C):
        self.A, self.C = A, C

    def mult(self, mat, x, y):
        self.A.mult(x, y)
        self.C.multAdd(x, y, y)


def test_cluster_set_up_reads_c_in_place():
    """A set-up of the cluster preconditioner on C copies none of C's rows."""
    comm = PETSc.COMM_WORLD
    C, mine = random_c(np.random.default_rng(4), comm)
    A = PETSc.Mat().createBAIJ(size=C.getSizes(), bsize=3, nnz=(1, 0), comm=comm)
    r0, r1 = A.getOwnershipRange()
    for i in range(r0 // 3, r1 // 3):           # every wisp's band: a stiff diagonal
        A.setValuesBlocked([i], [i], (1.0e9 * np.eye(3)).ravel())
    A.assemble()
    ctx = _Shell(A, C)
    op = PETSc.Mat().createPython(C.getSizes(), ctx, comm=comm)
    op.setUp()
    pc = PETSc.PC().create(comm=comm)
    pcx = ClusterPC(3 * SIZES[mine], band_factor="ilu")
    pc.setType(PETSc.PC.Type.PYTHON)
    pc.setPythonContext(pcx)
    pc.setOperators(op, A)
    copies = copies_made()
    try:
        pc.setUp()
        assert copies_made() == copies, "a copy of C's rows"
        assert pcx.stats["couplings"] > 0
        assert MPI.COMM_WORLD.allreduce(pcx.stats["wisps"]) > 0
    finally:
        for obj in (pc, op, A, C):
            obj.destroy()
