"""The contact-aware preconditioner ``-lc_contact_pc clusters`` (docs/contact_solver.md).

With strand contact the Newton operator is A + C: A the strand matrix (one band per
wisp, with the contact blocks that fall on it) and C the contact cross blocks between
wisps (lc_petsc/contact.py).  The per-wisp block Jacobi factors A alone and cannot see C:
CG then needs tens of iterations per solve.  This preconditioner groups the wisps that
C couples into **clusters** and solves each cluster's block of A + C exactly:

1. **Clusters.**  From C's couplings over all ranks (``-lc_cluster_span global``, the
   default: every rank gathers the coupled wisp pairs, each from the rows of its
   smaller wisp, and computes the same clusters; ``rank``: only couplings between two
   wisps of one rank, the couplings across ranks stay outside as in block Jacobi), the
   coupling weight of two wisps is the summed Frobenius norm of their cross blocks;
   wisp pairs are merged by union-find in order of decreasing weight (ties by wisp
   index), a merge being refused when the cluster would hold more than
   ``max_wisps`` wisps (``-lc_cluster_max_wisps``) or more than ``max_blocks`` cross
   blocks (``-lc_cluster_max_blocks``; the cost cap: the fill of a cluster's LU comes
   from its cross blocks, docs/contact_solver.md; a wisp's self-contact blocks count
   too, so a wisp whose own blocks alone exceed the cap joins no other).  The couplings left out (refused
   merges) are dropped from the preconditioner (and with ``rank`` the cross-rank ones).
   **Fallback**: when the clusters hold less than ``min_captured``
   (``-lc_cluster_min_captured``) of the coupling weight, the contact is too
   dense for exact clusters to pay (measured on the 4K hairball: clusters holding 89%
   of it still left CG 75 of its 150 iterations, for a factorisation 50x the per-wisp
   one), and the set-up keeps the per-wisp blocks alone.
   **Self-contact** (``physics.strand_self_contact``): C also holds cross blocks
   between segments of one wisp.  A wisp with such blocks is factored as a cluster
   even when no other wisp joins it (a one-wisp cluster: its band plus its own cross
   blocks, also under the fallback): the per-wisp band factor cannot hold them, and
   without them CG is left with the whole self-contact stiffness (measured: a 60-wisp
   barrier scene with self-contact, 1,000 CG iterations without converging against 7
   with them; docs/contact.md, "Self-contact").
2. **Singletons** (wisps in no cluster): the exact per-wisp factorisation of the
   rank's block of A: a compiled block Cholesky of each wisp's band
   (``-lc_band_factor cholesky``, the default; lc_petsc/elements/compiled_band.py),
   which reads half the bytes per application of PETSc's ILU(0) of the full band (= LU,
   ``-lc_band_factor ilu``, the per-wisp blocks' default in lc_petsc/solver.py).  When
   the band is not positive definite (an exact Hessian's negative curvature) the set-up
   takes PETSc's LU instead, and says so in ``stats["band_factor"]``.
3. **Clusters**: each cluster is factored by one rank, the rank holding most of its
   vertices, then moved to balance the rows each rank solves, per-wisp and cluster
   rows together (:func:`cluster_owners`: the contact of a frame often falls on one
   side of the head, i.e. one rank).  Every
   rank sends the blocks of A (band) and C (inside a cluster) of its rows to the rank
   factoring their cluster (one ``alltoall`` each), which puts them into one sequential
   matrix holding every cluster's block of A + C (clusters
   contiguous, so the matrix is block diagonal by cluster; AIJ, not BAIJ: see
   :func:`factor_cluster_matrix`), factored by PETSc's Cholesky (its LU until 2026-12-08)
   with the reverse Cuthill-McKee ordering (``-lc_cluster_ordering rcm``, the default;
   ``qmd`` (quotient minimum degree), ``nd`` accepted; an ordering never mixes the
   clusters).  On the 2K hairball's cluster matrices (28k-303k rows) RCM's fill is
   1.1-1.4x qmd's but its set-up (ordering + factorisation) takes 0.4-0.6x qmd's
   (qmd's ordering alone is superlinear; docs/contact_solver.md, "Where the 2K frame
   goes" and "Clusters across ranks").
4. **Apply**: the per-wisp solves of the rank's rows (the Cholesky skips the clustered
   wisps: their rows are overwritten), then the cluster rows: gathered from their
   ranks (one ``VecScatter``), solved by their cluster's rank, scattered back over the
   per-wisp values.

The preconditioning matrix is therefore P = A + (the cross blocks of C inside a
cluster): every dropped block belongs to a whole contact pair's cross block, and a
pair's Hessian without its cross blocks keeps its (PSD) diagonal blocks, so P is
symmetric positive definite like A + C, and applying P^-1 exactly keeps CG valid.  With
``-lc_cluster_span global`` the clusters, hence P, are the same on any rank count (to
the round-off of C's sums), so CG needs the 1-rank iterations on 2 or 3 ranks; with
``rank`` P depends on the partition.

The context is PETSc's ``PCPYTHON`` (set up by :class:`lc_petsc.solver.LinearSolver`).
It reads C from the operator: the Python-shell matrix of lc_petsc/contact.py
(:class:`lc_petsc.contact.SumOperator`, attributes ``A`` and ``C``); for any other
operator it uses the preconditioning matrix alone (all wisps singletons).
"""

from __future__ import annotations

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from lc_petsc.elements import compiled_cluster
from lc_petsc.elements.compiled_band import BandCholesky
from lc_petsc.parallel import global_wisp_offsets
from lc_petsc.petsc_capi import block_pattern, mpibaij_blocks, value_array

#: ``-lc_cluster_max_wisps`` default
MAX_WISPS = 64
#: ``-lc_cluster_max_blocks`` default (cross blocks, one per vertex pair A x B, inside one cluster)
MAX_BLOCKS = 1024
#: ``-lc_cluster_min_captured`` default (share of the coupling weight the clusters must hold)
MIN_CAPTURED = 0.9
#: ``-lc_cluster_ordering`` default: the PETSc ordering of the clusters' LU
ORDERING = "rcm"
#: the orderings ``-lc_cluster_ordering`` accepts (the first is the default)
ORDERINGS = (ORDERING, "qmd", "nd")
#: ``-lc_cluster_span`` default: clusters over the global contact graph (across ranks)
SPAN = "global"
#: the values ``-lc_cluster_span`` accepts (the first is the default)
SPANS = (SPAN, "rank")
#: ``-lc_band_factor`` default: the singletons' per-wisp solve, a compiled block Cholesky
#: (lc_petsc/elements/compiled_band.py; half the bytes per apply), or ``ilu``: PETSc's
#: ILU(0) of the band (= LU), also taken whenever the Cholesky cannot hold
BAND_FACTOR = "cholesky"
#: the values ``-lc_band_factor`` accepts (the first is the default)
BAND_FACTORS = (BAND_FACTOR, "ilu")


def block_rows(M, rows=None):
    """Block rows of the sequential BAIJ (bs 3) matrix ``M`` (a petsc4py matrix or a
    block of an MPI one, :func:`mpibaij_blocks`): (row of each block (k,), as a position
    in ``rows`` (default: every row), column (k,), block (k, 3, 3) row-major).  Only the
    selected blocks are copied out of PETSc's (column-major) value array."""
    ia, ja = block_pattern(M)
    ia, ja = ia.astype(np.int64), ja.astype(np.int64)
    if rows is None:
        rows = np.arange(len(ia) - 1)
    counts = ia[rows + 1] - ia[rows]
    first = np.repeat(ia[rows] - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    idx = first + np.arange(int(counts.sum()))
    with value_array(M, 9 * len(ja)) as v:
        blocks = v.reshape(-1, 3, 3)[idx].transpose(0, 2, 1)
    return np.repeat(np.arange(len(rows)), counts), ja[idx], blocks


def factor_cluster_matrix(indptr, cols, blocks, ordering=ORDERING):
    """(matrix, Cholesky PC) of the clusters' block CSR (``indptr``, ``cols``: 3x3
    ``blocks`` (k, 3, 3) row-major), factored by PETSc's Cholesky with ``ordering``.

    The matrix is symmetric positive definite (the module doc), so its Cholesky (PETSc's
    SeqAIJ one: U^T D U of the permuted matrix, one triangle stored) is its LU's half:
    on the 2K hairball's frame-90 systems (1.4-1.9M entries per rank, one-wisp clusters
    of the self-contact wisps under the fallback) 0.76-0.99M factor entries against
    1.47-1.89M, its solve 0.5x the LU's CPU time in every CG iteration, its set-up about
    the same, the same CG iterations (docs/contact_solver.md, "One CG iteration against
    the memory bandwidth"; the LU until 2026-12-08).

    The factor is of the point (AIJ) matrix, not of a BAIJ one: PETSc's BAIJ (and
    SBAIJ) factorisations invert each 3x3 pivot block explicitly, and a vertex held by a
    stiff stretch and a stiff contact in two directions with only its mass term in the
    third has a pivot block of condition 1e9 (a stretch/bend stiffness ratio of 1e8 with
    contact): the BAIJ LU of such an SPD matrix (condition 3.5e9) solved it with a relative
    error of 0.3-3, non-symmetric and indefinite, and CG stopped with
    DIVERGED_INDEFINITE_PC; the AIJ LU of the same matrix errs by 1e-7
    (docs/contact_solver.md, "Clusters").  The AIJ matrix is filled directly from the
    blocks (compiled, ``compiled_cluster.point_csr``, into arrays the matrix keeps;
    block size 3, as a converted BAIJ's): the same matrix as PETSc's ``MatConvert`` of the BAIJ
    one, without building that (docs/contact_solver.md, "Where the cluster set-up
    goes")."""
    n, k = len(indptr) - 1, len(cols)
    point = (np.empty(3 * n + 1, PETSc.IntType), np.empty(9 * k, PETSc.IntType), np.empty(9 * k))
    compiled_cluster.point_csr(np.asarray(indptr, PETSc.IntType), np.asarray(cols, PETSc.IntType),
                               np.ascontiguousarray(blocks, np.float64).reshape(k, 3, 3), *point)
    M = PETSc.Mat().createAIJWithArrays(size=(3 * n, 3 * n), csr=point, comm=PETSc.COMM_SELF)
    M.setBlockSizes(3, 3)                       # (createAIJWithArrays drops ``bsize``)
    pc = PETSc.PC().create(comm=PETSc.COMM_SELF)
    pc.setType(PETSc.PC.Type.CHOLESKY)
    pc.setFactorOrdering(ordering)
    pc.setOperators(M, M)
    pc.setUp()
    return M, pc


def local_block(M):
    """The rank-local diagonal block of ``M`` (the matrix itself when sequential)."""
    return M if M.getComm().getSize() == 1 else M.getDiagonalBlock()


def wisp_couplings(row_wisp, col_wisp, blocks, n_wisps):
    """Coupled wisp pairs of the blocks of a cross-block matrix (``row_wisp``,
    ``col_wisp``: the wisps (k,) of each block's row and column vertex, in
    ``range(n_wisps)``; ``blocks`` (k, 3, 3)): (pairs (m, 2) with a < b, weights (m,) the
    summed Frobenius norms of their blocks in the order given, counts (m,) their
    blocks), pairs sorted by (a, b).  Only the blocks with ``row_wisp < col_wisp`` count
    (C is symmetric: each coupling once, from the rows of its smaller wisp)."""
    a, b = np.asarray(row_wisp, np.int64), np.asarray(col_wisp, np.int64)
    keep = a < b
    n = max(int(n_wisps), 1)
    key, inverse, count = np.unique(a[keep] * n + b[keep], return_inverse=True,
                                    return_counts=True)
    weight = np.bincount(inverse, weights=np.linalg.norm(blocks[keep], axis=(1, 2)),
                         minlength=len(key))
    return np.stack([key // n, key % n], axis=1), weight, count


def self_coupled(row_wisp, col_wisp, blocks, n_wisps):
    """Wisps (n_wisps,) bool with a nonzero block of C between two of their own vertices
    (self-contact), from the blocks of a cross-block matrix as in :func:`wisp_couplings`."""
    a, b = np.asarray(row_wisp, np.int64), np.asarray(col_wisp, np.int64)
    hit = (a == b) & (np.abs(np.reshape(blocks, (len(a), 9))).max(axis=1, initial=0.0) > 0.0)
    return np.bincount(a[hit], minlength=int(n_wisps)) > 0


def self_blocks(row_wisp, col_wisp, row_vertex, col_vertex, n_wisps):
    """Self-contact cross blocks per wisp (n_wisps,): the blocks of C between two vertices
    of one wisp, each vertex pair once (``row_vertex < col_vertex``; C is symmetric), as
    :func:`wisp_couplings` counts a pair of wisps' blocks.  They take part in the cap on
    a cluster's cross blocks (their LU fill is the same as a pair's)."""
    a, b = np.asarray(row_wisp, np.int64), np.asarray(col_wisp, np.int64)
    inside = (a == b) & (np.asarray(row_vertex) < np.asarray(col_vertex))
    return np.bincount(a[inside], minlength=int(n_wisps))


def cluster_labels(n_wisps, pairs, weights, counts, max_wisps=MAX_WISPS, max_blocks=MAX_BLOCKS,
                   own_blocks=None):
    """Cluster of every wisp (n_wisps,): the smallest wisp index of its cluster.

    Union-find over ``pairs`` (m, 2, each pair once) in order of decreasing ``weights``
    (ties: the order of ``pairs``); a merge is refused if the cluster would exceed
    ``max_wisps`` wisps or ``max_blocks`` cross blocks inside it: the two clusters'
    blocks (``own_blocks`` (n_wisps,), each wisp's self-contact blocks,
    :func:`self_blocks`, default none, and ``counts`` of the pairs inside) plus those of
    *every* pair between them, which the merge brings inside (not only the pair being
    merged: a later pair closing a triangle would otherwise add its blocks past the
    cap).  A refused pair stays outside; a wisp whose own blocks alone exceed
    ``max_blocks`` joins no other wisp (it is still factored alone: the caller's
    one-wisp cluster)."""
    # compiled (lc_petsc/elements/compiled_cluster.py): every rank repeats this set-up
    inner = np.zeros(n_wisps, np.int64) if own_blocks is None else np.array(own_blocks, np.int64)
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    order = np.argsort(-np.asarray(weights, np.float64), kind="stable")
    return compiled_cluster.cluster_roots(int(n_wisps), pairs, np.asarray(counts, np.int64), order,
                                          int(max_wisps), int(max_blocks), inner)


def cluster_owners(held, base=None):
    """The rank that factors each cluster, from ``held`` (clusters, ranks): the vertices
    of each cluster on each rank (rows without any: not a cluster), and ``base`` (ranks,)
    the vertices each rank solves outside the clusters (its per-wisp blocks; default
    none).  First the rank holding most of it (ties: the lower rank); then, for balance
    (a cluster's LU and solves cost about its size, a per-wisp block about its, and the
    contact often falls on one rank's side of the head), the clusters of ranks loaded
    above the mean (base + clusters) move, largest first (ties: the lower cluster), to
    the least-loaded rank as long as it stays at or below the mean.  Deterministic:
    every rank computes the same owners.  Returns (clusters,)."""
    size = held.sum(axis=1)
    owner = np.argmax(held, axis=1)
    n_ranks = held.shape[1]
    if n_ranks == 1:
        return owner
    load = np.bincount(owner, weights=size, minlength=n_ranks)
    if base is not None:
        load = load + np.asarray(base, float)
    mean = load.sum() / n_ranks
    for c in np.lexsort((np.arange(len(size)), -size)):
        if size[c] == 0 or load[owner[c]] <= mean:
            continue
        q = int(np.argmin(load))
        if load[q] + size[c] <= mean:
            load[owner[c]] -= size[c]
            load[q] += size[c]
            owner[c] = q
    return owner


def local_blocks(M):
    """This rank's blocks of the BAIJ (bs 3) matrix ``M`` with global block columns, as
    :func:`block_rows` gives them (local block row, column, block (k, 3, 3) row-major), in
    the order of a copy of the rows (``MatCreateSubMatrices``: rows in order, each row's
    columns ascending).  An MPI matrix's are read in place from its diagonal and
    off-diagonal blocks: no copy of the rows and no communication (on the 2K hairball's
    contact frames, 2 ranks: 3.2 ms CPU per set-up against 20 ms for the copy and its
    read; docs/performance.md "C's pattern between Newton iterations")."""
    if M.getComm().getSize() == 1:
        return block_rows(M)
    diag, off, columns = mpibaij_blocks(M)
    rd, cd, vd = block_rows(diag)
    ro, co, vo = block_rows(off)
    first = M.getOwnershipRangeColumn()[0] // 3
    cd = cd + first
    co = np.asarray(columns, np.int64)[co]       # the off-diagonal block's columns, ascending
    # a row's off-diagonal columns lie before or after its diagonal block's
    key = np.concatenate([3 * rd + 1, 3 * ro + np.where(co < first, 0, 2)])
    order = np.argsort(key, kind="stable")
    return tuple(np.concatenate(part)[order] for part in ((rd, ro), (cd, co), (vd, vo)))


class GlobalLayout:
    """The global wisps behind a matrix whose ranks own contiguous ranges of whole wisps
    (lc_petsc/parallel.py): ``comm`` (mpi4py), ``n_wisps``, ``sizes`` (vertices per
    wisp), ``offsets`` (first vertex of each, and the total), ``wisp_rank`` (owner),
    ``vertex_wisp`` (wisp of every global vertex), ``first_wisp`` (this rank's first).
    ``local_sizes``: the vertices of this rank's wisps (collective)."""

    def __init__(self, M, local_sizes):
        self.comm = M.getComm().tompi4py()
        local_sizes = np.asarray(local_sizes, np.int64)
        self.offsets = global_wisp_offsets(self.comm, np.concatenate([[0], np.cumsum(local_sizes)]))
        self.sizes = np.diff(self.offsets)
        self.n_wisps = len(self.sizes)
        per_rank = self.comm.allgather(len(local_sizes))
        self.wisp_rank = np.repeat(np.arange(len(per_rank)), per_rank)
        self.vertex_wisp = np.repeat(np.arange(self.n_wisps), self.sizes)
        self.first_wisp = sum(per_rank[:self.comm.rank])
        if 3 * self.offsets[self.first_wisp] != M.getOwnershipRange()[0]:
            raise ValueError("the cluster preconditioner needs every rank's rows to be its "
                             "wisps' vertices, numbered contiguously rank after rank")


class ClusterPC:
    """``PCPYTHON`` context of the cluster preconditioner (see the module doc).

    ``wisp_rows``: matrix rows (3 x vertices) of each local wisp, in order;
    ``max_wisps``, ``max_blocks``: the cluster caps; ``min_captured``: the fallback's
    threshold; ``ordering``: the clusters' LU ordering; ``span``: ``global`` (clusters
    over the global contact graph, a cluster may hold wisps of several ranks) or
    ``rank`` (only couplings between two wisps of one rank).  After each set-up,
    ``stats`` holds the clusters' figures (this rank's: clusters it factors, their wisps,
    largest, cluster rows, factor over matrix entries; global: coupled wisp pairs, those
    left out, share of the coupling weight held, fallback taken, pairs and weight share
    across ranks, clusters spanning ranks, the most cross blocks inside one cluster,
    self-contact blocks included) and ``history`` keeps them per set-up."""

    def __init__(self, wisp_rows, max_wisps=MAX_WISPS, max_blocks=MAX_BLOCKS,
                 min_captured=MIN_CAPTURED, ordering=ORDERING, span=SPAN, band_factor=BAND_FACTOR):
        sizes = np.asarray(wisp_rows, np.int64) // 3
        self.vertex_wisp = np.repeat(np.arange(len(sizes)), sizes)
        self.offsets = np.concatenate([[0], np.cumsum(sizes)])
        if band_factor not in BAND_FACTORS:
            raise ValueError(f"band factor {band_factor!r}: use one of {', '.join(BAND_FACTORS)}")
        self.cholesky = BandCholesky(self.offsets) if band_factor == "cholesky" else None
        self.use_cholesky = False
        self.max_wisps, self.max_blocks = int(max_wisps), int(max_blocks)
        self.min_captured = float(min_captured)
        if ordering not in ORDERINGS:
            raise ValueError(f"cluster LU ordering {ordering!r}: use one of {', '.join(ORDERINGS)}")
        if span not in SPANS:
            raise ValueError(f"cluster span {span!r}: use one of {', '.join(SPANS)}")
        self.ordering, self.span = ordering, span
        self.band = self.cluster = self.cluster_mat = self.scatter = None
        self.dofs = np.zeros(0, np.int64)
        #: the local wisps the per-wisp Cholesky solves (None: every one); the clustered
        #: wisps' rows come from their cluster's LU, which overwrites them
        self.band_wisps: np.ndarray | None = None
        self._x = self._y = self._cx = self._cy = None
        self.layout: GlobalLayout | None = None
        self.stats: dict = {}
        self.history: list[dict] = []

    # -------------------------------------------------------------- PCPYTHON
    def setUp(self, pc):
        """Factor the singleton blocks and the clusters of the current operators."""
        op, P = pc.getOperators()
        ctx = op.getPythonContext() if op.getType() == PETSc.Mat.Type.PYTHON else None
        A = P if ctx is None else ctx.A
        C = None if ctx is None else ctx.C
        A_loc = local_block(A)
        band = self._setup_band(A, A_loc)
        n = A_loc.getSize()[0]
        if self._x is None or self._x.getSize() != n:
            self._x = PETSc.Vec().createWithArray(np.zeros(n), comm=PETSc.COMM_SELF)
            self._y = PETSc.Vec().createWithArray(np.zeros(n), comm=PETSc.COMM_SELF)
        if self.layout is None:
            self.layout = GlobalLayout(A, np.diff(self.offsets))
        self._setup_clusters(A, A_loc, C)
        self.stats["band_factor"] = band
        self.history.append(dict(self.stats))

    def _setup_band(self, A, A_loc):
        """The singletons' factor of A's rank-local block: the compiled Cholesky, or
        PETSc's ILU(0) of the band (``-lc_band_factor ilu``, or where the Cholesky
        cannot hold on some rank: decided for all ranks alike, so the preconditioner does
        not depend on the partition; collective).  Returns which, with the reason for ILU
        (``stats["band_factor"]``)."""
        why = "-lc_band_factor ilu"
        self.use_cholesky = False
        if self.cholesky is not None:
            if A_loc.getType() != PETSc.Mat.Type.SEQBAIJ or A_loc.getBlockSize() != 3:
                why = f"a {A_loc.getType()} matrix"
            else:
                indptr, indices = block_pattern(A_loc)
                with value_array(A_loc, 9 * len(indices)) as values:
                    why = self.cholesky.factor(indptr, indices, values)
                self.use_cholesky = why is None
            if not A.getComm().tompi4py().allreduce(self.use_cholesky, op=MPI.LAND) and self.use_cholesky:
                self.use_cholesky, why = False, "the Cholesky cannot hold on another rank"
        if self.use_cholesky:
            if self.band is not None:   # a fallback's factor is not kept beside it
                self.band.destroy()
                self.band = None
            return "cholesky"
        if self.band is None:
            self.band = PETSc.PC().create(comm=PETSc.COMM_SELF)
            self.band.setType(PETSc.PC.Type.ILU)       # ILU(0) of a full band = LU
        self.band.setOperators(A_loc, A_loc)
        self.band.setUp()
        return f"ilu ({why})"

    def _couplings(self, C):
        """The global coupled wisp pairs, weights and block counts of C (every rank gets
        all of them, in (a, b) order: each pair comes from the rows of its smaller wisp),
        this rank's blocks of C: (global row vertex (k,), global column vertex (k,),
        blocks (k, 3, 3)), the wisps with self-contact blocks (n_wisps,) bool and their
        self-contact blocks (n_wisps,) (:func:`self_blocks`; a wisp's blocks are all on
        its rank: or-ed and summed over the ranks)."""
        lay = self.layout
        rc, cc, vc = local_blocks(C)
        row_wisp, col_wisp = lay.first_wisp + self.vertex_wisp[rc], lay.vertex_wisp[cc]
        found = wisp_couplings(row_wisp, col_wisp, vc, lay.n_wisps)
        alone = self_coupled(row_wisp, col_wisp, vc, lay.n_wisps)
        mine = (lay.offsets[lay.first_wisp] + rc, cc, vc)
        own = self_blocks(row_wisp, col_wisp, mine[0], cc, lay.n_wisps)
        if lay.comm.size == 1:
            return found, mine, alone, own
        parts = lay.comm.allgather((found, alone, own))
        alone = np.any([p[1] for p in parts], axis=0)
        own = np.sum([p[2] for p in parts], axis=0)
        return tuple(np.concatenate([p[0][k] for p in parts]) for k in range(3)), mine, alone, own

    def _to_owners(self, rows, cols, vals, dest):
        """The blocks (global rows, columns, values) sent to this rank by every rank,
        each sending its blocks to their ``dest`` rank (collective); in rank order."""
        comm = self.layout.comm
        if comm.size == 1:
            return rows, cols, vals
        by = np.argsort(dest, kind="stable")
        send = np.bincount(dest, minlength=comm.size)
        recv = np.asarray(comm.alltoall(send.tolist()), np.int64)
        out = []
        for a, width in ((rows, 1), (cols, 1), (vals, 9)):
            a = np.ascontiguousarray(a[by], np.int64 if width == 1 else np.float64)
            got = np.empty((int(recv.sum()),) + a.shape[1:], a.dtype)
            kind = MPI.INT64_T if width == 1 else MPI.DOUBLE
            comm.Alltoallv([a, (send * width, None), kind], [got, (recv * width, None), kind])
            out.append(got)
        return tuple(out)

    def _cluster_blocks(self, A_loc, c_blocks, label, owner, factored):
        """The blocks of A + C inside the clusters this rank factors (global rows,
        columns, values; A's first), from every rank's rows: its band blocks of clustered
        wisps (``A_loc``) and its blocks of C (``c_blocks``) inside a cluster, by cluster
        ``label``, cluster ``owner`` and ``factored`` (by label: a cluster, not a
        singleton) (collective)."""
        lay = self.layout
        v0 = lay.offsets[lay.first_wisp]
        local = lay.first_wisp + np.arange(len(self.offsets) - 1)
        local = local[factored[label[local]]]                       # clustered wisps here
        sizes = lay.sizes[local]
        verts = np.repeat(lay.offsets[local] - v0 - np.concatenate([[0], np.cumsum(sizes)[:-1]]),
                          sizes) + np.arange(int(sizes.sum()))     # their local vertices
        ra, ca, va = block_rows(A_loc, verts)
        a = self._to_owners(v0 + verts[ra], v0 + ca, va, owner[label[lay.vertex_wisp[v0 + verts[ra]]]])
        rows, cols, vals = c_blocks
        cluster = label[lay.vertex_wisp[rows]]
        inside = (cluster == label[lay.vertex_wisp[cols]]) & factored[cluster]
        c = self._to_owners(rows[inside], cols[inside], vals[inside], owner[cluster[inside]])
        return tuple(np.concatenate([a[k], c[k]]) for k in range(3))

    def _setup_clusters(self, A, A_loc, C):
        self._destroy_cluster()
        lay = self.layout
        stats = {"clusters": 0, "wisps": 0, "largest": 0, "rows": 0, "fill": 0.0,
                 "couplings": 0, "couplings_left_out": 0, "captured": 1.0, "fallback": False,
                 "cross_rank_couplings": 0, "cross_rank_weight": 0.0, "cross_rank_clusters": 0,
                 "moved_rows": 0, "self_contact_wisps": 0, "most_blocks": 0,
                 "band_rows": 3 * int(self.offsets[-1])}
        self.stats = stats
        self.band_wisps = None
        if C is None:
            return
        (pairs, weights, counts), c_blocks, alone, own = self._couplings(C)
        stats["self_contact_wisps"] = int(alone.sum())
        cross = lay.wisp_rank[pairs[:, 0]] != lay.wisp_rank[pairs[:, 1]]
        total = float(weights.sum())
        stats.update(cross_rank_couplings=int(cross.sum()),
                     cross_rank_weight=float(weights[cross].sum()) / total if total > 0 else 0.0)
        if self.span == "rank":
            pairs, weights, counts = pairs[~cross], weights[~cross], counts[~cross]
        stats["couplings"] = len(pairs)
        label = np.arange(lay.n_wisps)          # every wisp alone unless merged below
        if len(pairs):
            merged = cluster_labels(lay.n_wisps, pairs, weights, counts, self.max_wisps, self.max_blocks,
                                    own)
            out = merged[pairs[:, 0]] != merged[pairs[:, 1]]
            total = float(weights.sum())
            stats.update(couplings_left_out=int(out.sum()),
                         captured=1.0 - float(weights[out].sum()) / total if total > 0 else 1.0)
            if stats["captured"] < self.min_captured:
                stats["fallback"] = True        # the wisps with self-contact still factored alone
            else:
                label = merged
        count = np.bincount(label, minlength=lay.n_wisps)
        # a cluster: several wisps, or one with self-contact blocks (module doc)
        factored = (count > 1) | (np.bincount(label, weights=alone, minlength=lay.n_wisps) > 0)
        clustered = np.flatnonzero(factored[label])
        if not len(clustered):
            return
        inside = label[pairs[:, 0]] == label[pairs[:, 1]]
        blocks = (np.bincount(label[pairs[inside, 0]], weights=counts[inside], minlength=lay.n_wisps)
                  + np.bincount(label, weights=own, minlength=lay.n_wisps))
        stats["most_blocks"] = int(blocks[factored].max())
        held = np.zeros((lay.n_wisps, lay.comm.size))     # vertices per (cluster, rank)
        np.add.at(held, (label[clustered], lay.wisp_rank[clustered]), lay.sizes[clustered])
        stats["cross_rank_clusters"] = int(((held > 0).sum(axis=1) > 1).sum())
        # per rank, the vertices its per-wisp blocks solve: the clustered wisps' are
        # skipped by the Cholesky (their cluster's LU overwrites them), so a rank keeps
        # its own clusters unless that leaves it above the mean (no rows cross ranks then)
        base = np.bincount(lay.wisp_rank, weights=lay.sizes, minlength=lay.comm.size)
        if self.use_cholesky:
            base -= held.sum(axis=0)
            local = lay.first_wisp + np.arange(len(self.offsets) - 1)
            self.band_wisps = np.flatnonzero(~factored[label[local]]).astype(np.int64)
            stats["band_rows"] = 3 * int(np.sum(lay.sizes[local[self.band_wisps]]))
        owner = cluster_owners(held, base)
        stats["moved_rows"] = int(3 * (held.sum(axis=1) - held[np.arange(lay.n_wisps), owner]).sum())
        # this rank's clusters, their wisps grouped by cluster, in wisp order inside one
        wisps = clustered[owner[label[clustered]] == lay.comm.rank]
        wisps = wisps[np.argsort(label[wisps], kind="stable")]
        self._factor_clusters(A, self._cluster_blocks(A_loc, c_blocks, label, owner, factored), wisps)
        if len(wisps):
            stats.update(clusters=len(np.unique(label[wisps])), wisps=len(wisps),
                         largest=int(count[label[wisps]].max()), rows=len(self.dofs))

    def _factor_clusters(self, A, blocks, wisps):
        """Factor the blocks (global rows, columns, values) of this rank's clusters
        (``wisps`` grouped by cluster) and set up the scatter of the cluster rows
        (collective)."""
        lay = self.layout
        sizes = lay.sizes[wisps]
        verts = np.repeat(lay.offsets[wisps] - np.concatenate([[0], np.cumsum(sizes)[:-1]]),
                          sizes) + np.arange(int(sizes.sum()))
        self.dofs = (3 * verts[:, None] + np.arange(3)).ravel()
        m = len(self.dofs)
        self._cx = PETSc.Vec().createSeq(m, comm=PETSc.COMM_SELF)
        self._cy = self._cx.duplicate()
        x = A.createVecRight()
        to = PETSc.IS().createGeneral(self.dofs.astype(PETSc.IntType), comm=PETSc.COMM_SELF)
        try:
            self.scatter = PETSc.Scatter().create(x, to, self._cx, None)
        finally:
            to.destroy()
            x.destroy()
        if not m:
            return
        grouped = np.full(lay.offsets[-1], -1, np.int64)      # global vertex -> cluster row
        grouped[verts] = np.arange(len(verts))
        rows, cols, vals = grouped[blocks[0]], grouped[blocks[1]], blocks[2]
        lex = np.lexsort((cols, rows))
        rows, cols, vals = rows[lex], cols[lex], vals[lex]
        # a self-contact pair's cross blocks can fall on its wisp's band (segments two
        # apart): one summed block per position (a CSR row must not repeat a column)
        first = np.flatnonzero(np.r_[True, (rows[1:] != rows[:-1]) | (cols[1:] != cols[:-1])])
        if len(first) < len(rows):
            rows, cols, vals = rows[first], cols[first], np.add.reduceat(vals, first, axis=0)
        indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=len(verts)))])
        self.cluster_mat, self.cluster = factor_cluster_matrix(indptr, cols, vals, self.ordering)
        self.stats["fill"] = float(self.cluster.getFactorMatrix().getInfo()["nz_used"]
                                   / self.cluster_mat.getInfo()["nz_used"])

    def left_out(self):
        """For a failed solve's message: the contact couplings between wisps the last
        set-up left out of P (all of them under the fallback) and what to change, or ''
        when the clusters held every one (docs/contact_solver.md, "When CG fails")."""
        st = self.stats
        if st.get("fallback"):
            what = (f"could put only {st['captured']:.0%} of the contact coupling weight into clusters "
                    f"(below -lc_cluster_min_captured {self.min_captured:g}), so it kept per-wisp blocks "
                    f"and left all {st['couplings']} coupled wisp pairs out")
        elif st.get("couplings_left_out"):
            what = (f"left {st['couplings_left_out']} of {st['couplings']} coupled wisp pairs out "
                    f"({1.0 - st['captured']:.0%} of the coupling weight)")
        else:
            return ""
        return (f"; the contact preconditioner {what} at the caps -lc_cluster_max_wisps {self.max_wisps} "
                f"-lc_cluster_max_blocks {self.max_blocks}: CG alone must resolve the contact between "
                f"those wisps; larger caps put it into the clusters' exact solves (their memory and set-up "
                f"time grow with the caps)")

    def apply(self, pc, x, y):
        """y = P^-1 x: the per-wisp LUs, then the cluster rows by the clusters' LU
        (gathered from and scattered back to the ranks owning them)."""
        xa = x.getArray(readonly=True)
        ya = y.getArray()
        if self.use_cholesky:
            self.cholesky.apply(xa, ya, self.band_wisps)
        else:
            self._x.placeArray(xa)
            self._y.placeArray(ya)
            try:
                self.band.apply(self._x, self._y)
            finally:
                self._x.resetArray()
                self._y.resetArray()
        if self.scatter is not None:
            self.scatter.scatter(x, self._cx, PETSc.InsertMode.INSERT_VALUES, PETSc.ScatterMode.FORWARD)
            if self.cluster is not None:
                self.cluster.apply(self._cx, self._cy)
            self.scatter.scatter(self._cy, y, PETSc.InsertMode.INSERT_VALUES, PETSc.ScatterMode.REVERSE)

    def _destroy_cluster(self):
        for obj in (self.cluster, self.cluster_mat, self.scatter, self._cx, self._cy):
            if obj is not None:
                obj.destroy()
        self.cluster = self.cluster_mat = self.scatter = self._cx = self._cy = None
        self.dofs = np.zeros(0, np.int64)

    def destroy(self, pc=None):
        """Destroy the inner PETSc objects (PETSc calls this when the PC is destroyed)."""
        self._destroy_cluster()
        for obj in (self.band, self._x, self._y):
            if obj is not None:
                obj.destroy()
        self.band = self._x = self._y = None
