"""The contact-aware preconditioner ``-lc_contact_pc clusters`` (docs/contact_solver.md).

With strand contact the Newton operator is A + C: A the strand matrix (one band per
wisp, with the contact blocks that fall on it) and C the contact cross blocks between
wisps (lc_petsc/contact.py).  The per-wisp block Jacobi factors A alone and cannot see C:
CG then needs tens of iterations per solve.  This preconditioner groups the wisps of a
rank that C couples into **clusters** and solves each cluster's block of A + C exactly:

1. **Clusters.**  From the rank-local diagonal block of C (couplings between two wisps
   of this rank; couplings to other ranks' wisps stay outside, as in block Jacobi), the
   coupling weight of two wisps is the summed Frobenius norm of their cross blocks;
   wisp pairs are merged by union-find in order of decreasing weight (ties by wisp
   index), a merge being refused when the cluster would hold more than
   ``max_wisps`` wisps (``-lc_cluster_max_wisps``) or more than ``max_blocks`` cross
   blocks (``-lc_cluster_max_blocks``; the cost cap: the fill of a cluster's LU comes
   from its cross blocks, docs/contact_solver.md).  The couplings left out (refused
   merges) are dropped from the preconditioner like the cross-rank ones.
   **Fallback**: when the clusters hold less than ``min_captured``
   (``-lc_cluster_min_captured``) of the rank's coupling weight, the contact is too
   dense for exact clusters to pay (measured on the 4K hairball: clusters holding 89%
   of it still left CG 75 of its 150 iterations, for a factorisation 50x the per-wisp
   one), and the set-up keeps the per-wisp blocks alone.
2. **Singletons** (wisps in no cluster): the exact per-wisp factorisation of the
   default, ILU(0) of the rank's block of A on a full band (= LU; lc_petsc/solver.py).
3. **Clusters**: one sequential BAIJ matrix holding every multi-wisp cluster's block
   of A + C (clusters contiguous, so the matrix is block diagonal by cluster), factored
   by PETSc's LU with the quotient-minimum-degree ordering (``-lc_cluster_ordering
   qmd``, the default; ``rcm``, ``nd`` accepted; an ordering never mixes the
   clusters).  On the 2K hairball's cluster matrices (28k-303k rows) RCM's fill is
   1.1-1.4x qmd's but its set-up (ordering + factorisation) takes 0.4-0.6x qmd's
   (qmd's ordering alone is up to half of its set-up); not the default because it
   moves the ccd rank-invariance test past its bound (docs/contact_solver.md, "Where
   the 2K frame goes").

The preconditioning matrix is therefore P = A + (the cross blocks of C inside a
cluster): every dropped block belongs to a whole contact pair's cross block, and a
pair's Hessian without its cross blocks keeps its (PSD) diagonal blocks, so P is
symmetric positive definite like A + C, and applying P^-1 exactly keeps CG valid.  A
cluster never spans ranks, so the preconditioner (not the solution) depends on the
partition.

The context is PETSc's ``PCPYTHON`` (set up by :class:`lc_petsc.solver.LinearSolver`).
It reads C from the operator: the Python-shell matrix of lc_petsc/contact.py
(:class:`lc_petsc.contact.SumOperator`, attributes ``A`` and ``C``); for any other
operator it uses the preconditioning matrix alone (all wisps singletons).
"""

from __future__ import annotations

import numpy as np
from petsc4py import PETSc

from lc_petsc.petsc_capi import value_array

#: ``-lc_cluster_max_wisps`` default
MAX_WISPS = 64
#: ``-lc_cluster_max_blocks`` default (cross blocks, one per vertex pair A x B, inside one cluster)
MAX_BLOCKS = 1024
#: ``-lc_cluster_min_captured`` default (share of the coupling weight the clusters must hold)
MIN_CAPTURED = 0.9
#: ``-lc_cluster_ordering`` default: the PETSc ordering of the clusters' LU
ORDERING = "qmd"
#: the orderings ``-lc_cluster_ordering`` accepts (the first is the default)
ORDERINGS = (ORDERING, "rcm", "nd")


def block_rows(M, rows=None):
    """Block rows of the sequential BAIJ (bs 3) matrix ``M``: (row of each block (k,),
    as a position in ``rows`` (default: every row), column (k,), block (k, 3, 3)
    row-major).  Only the selected blocks are copied out of PETSc's (column-major)
    value array."""
    ia, ja = M.getRowIJ(compressed=True)
    ia, ja = ia.astype(np.int64), ja.astype(np.int64)
    if rows is None:
        rows = np.arange(len(ia) - 1)
    counts = ia[rows + 1] - ia[rows]
    first = np.repeat(ia[rows] - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    idx = first + np.arange(int(counts.sum()))
    with value_array(M, 9 * len(ja)) as v:
        blocks = v.reshape(-1, 3, 3)[idx].transpose(0, 2, 1)
    return np.repeat(np.arange(len(rows)), counts), ja[idx], blocks


def local_block(M):
    """The rank-local diagonal block of ``M`` (the matrix itself when sequential)."""
    return M if M.getComm().getSize() == 1 else M.getDiagonalBlock()


def wisp_couplings(rows, cols, blocks, vertex_wisp):
    """Coupled wisp pairs of the blocks (``rows``, ``cols``: vertices (k,); ``blocks``
    (k, 3, 3)) of a cross-block matrix: (pairs (m, 2) with a < b, weights (m,) the summed
    Frobenius norms of their blocks, counts (m,) their blocks), pairs sorted by (a, b)."""
    a, b = vertex_wisp[rows], vertex_wisp[cols]
    keep = a < b                            # each coupling once (C is symmetric)
    n = int(vertex_wisp.max(initial=-1)) + 1
    key, inverse, count = np.unique(a[keep] * n + b[keep], return_inverse=True,
                                    return_counts=True)
    weight = np.bincount(inverse, weights=np.linalg.norm(blocks[keep], axis=(1, 2)),
                         minlength=len(key))
    return np.stack([key // max(n, 1), key % max(n, 1)], axis=1), weight, count


def cluster_labels(n_wisps, pairs, weights, counts, max_wisps=MAX_WISPS, max_blocks=MAX_BLOCKS):
    """Cluster of every wisp (n_wisps,): the smallest wisp index of its cluster.

    Union-find over ``pairs`` (m, 2) in order of decreasing ``weights`` (ties: the
    order of ``pairs``); a merge is refused if the cluster would exceed ``max_wisps``
    wisps or ``max_blocks`` cross blocks inside it (``counts`` per pair: those of the
    pairs merged so far and of the pairs found inside on the way; a refused pair stays
    outside)."""
    parent = np.arange(n_wisps)
    size = np.ones(n_wisps, np.int64)
    inner = np.zeros(n_wisps, np.int64)          # cross blocks inside, at the root

    def find(w):
        while parent[w] != w:
            parent[w] = parent[parent[w]]
            w = parent[w]
        return w

    for e in np.argsort(-np.asarray(weights), kind="stable"):
        ra, rb = find(pairs[e, 0]), find(pairs[e, 1])
        if ra == rb:
            inner[ra] += counts[e]
            continue
        if size[ra] + size[rb] > max_wisps or inner[ra] + inner[rb] + counts[e] > max_blocks:
            continue
        if rb < ra:
            ra, rb = rb, ra
        parent[rb] = ra
        size[ra] += size[rb]
        inner[ra] += inner[rb] + counts[e]
    roots = np.array([find(w) for w in range(n_wisps)], np.int64)
    smallest = np.full(n_wisps, n_wisps, np.int64)
    np.minimum.at(smallest, roots, np.arange(n_wisps))
    return smallest[roots]


class ClusterPC:
    """``PCPYTHON`` context of the cluster preconditioner (see the module doc).

    ``wisp_rows``: matrix rows (3 x vertices) of each local wisp, in order;
    ``max_wisps``, ``max_blocks``: the cluster caps; ``min_captured``: the fallback's
    threshold.  After each set-up, ``stats`` holds the clusters' figures (clusters,
    wisps in clusters, largest cluster, cluster rows, factor over matrix entries, coupled
    wisp pairs, those left out, share of the coupling weight held, fallback taken) and
    ``history`` keeps them per set-up."""

    def __init__(self, wisp_rows, max_wisps=MAX_WISPS, max_blocks=MAX_BLOCKS,
                 min_captured=MIN_CAPTURED, ordering=ORDERING):
        sizes = np.asarray(wisp_rows, np.int64) // 3
        self.vertex_wisp = np.repeat(np.arange(len(sizes)), sizes)
        self.offsets = np.concatenate([[0], np.cumsum(sizes)])
        self.max_wisps, self.max_blocks = int(max_wisps), int(max_blocks)
        self.min_captured = float(min_captured)
        if ordering not in ORDERINGS:
            raise ValueError(f"cluster LU ordering {ordering!r}: use one of {', '.join(ORDERINGS)}")
        self.ordering = ordering
        self.band = self.cluster = self.cluster_mat = None
        self.dofs = np.zeros(0, np.int64)
        self._x = self._y = self._cx = self._cy = None
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
        if self.band is None:
            self.band = PETSc.PC().create(comm=PETSc.COMM_SELF)
            self.band.setType(PETSc.PC.Type.ILU)       # ILU(0) of a full band = LU
        self.band.setOperators(A_loc, A_loc)
        self.band.setUp()
        n = A_loc.getSize()[0]
        if self._x is None or self._x.getSize() != n:
            self._x = PETSc.Vec().createWithArray(np.zeros(n), comm=PETSc.COMM_SELF)
            self._y = PETSc.Vec().createWithArray(np.zeros(n), comm=PETSc.COMM_SELF)
        self._setup_clusters(A_loc, None if C is None else local_block(C))
        self.history.append(dict(self.stats))

    def _setup_clusters(self, A_loc, C_loc):
        self._destroy_cluster()
        n_w = len(self.offsets) - 1
        stats = {"clusters": 0, "wisps": 0, "largest": 0, "rows": 0, "fill": 0.0,
                 "couplings": 0, "couplings_left_out": 0, "captured": 1.0, "fallback": False}
        self.stats = stats
        if C_loc is None or n_w < 2:
            return
        rc, cc, vc = block_rows(C_loc)
        pairs, weights, counts = wisp_couplings(rc, cc, vc, self.vertex_wisp)
        stats["couplings"] = len(pairs)
        if not len(pairs):
            return
        label = cluster_labels(n_w, pairs, weights, counts, self.max_wisps, self.max_blocks)
        out = label[pairs[:, 0]] != label[pairs[:, 1]]
        total = float(weights.sum())
        stats.update(couplings_left_out=int(out.sum()),
                     captured=1.0 - float(weights[out].sum()) / total if total > 0 else 1.0)
        if stats["captured"] < self.min_captured:
            stats["fallback"] = True
            return
        count = np.bincount(label, minlength=n_w)
        multi = count[label] > 1                                  # per wisp
        if not multi.any():
            return
        # clustered wisps, grouped by cluster (stable: wisp order inside a cluster)
        wisps = np.flatnonzero(multi)
        wisps = wisps[np.argsort(label[wisps], kind="stable")]
        sizes = np.diff(self.offsets)[wisps]
        verts = np.repeat(self.offsets[wisps] - np.concatenate([[0], np.cumsum(sizes)[:-1]]),
                          sizes) + np.arange(int(sizes.sum()))
        pos = np.full(len(self.vertex_wisp), -1, np.int64)
        pos[verts] = np.arange(len(verts))
        ra, ca, va = block_rows(A_loc, verts)
        keep = (pos[rc] >= 0) & (label[self.vertex_wisp[rc]] == label[self.vertex_wisp[cc]])
        rows = np.concatenate([ra, pos[rc[keep]]])
        cols = np.concatenate([pos[ca], pos[cc[keep]]])
        vals = np.concatenate([va, vc[keep]])
        order = np.lexsort((cols, rows))
        rows, cols, vals = rows[order], cols[order], vals[order]
        # a self-contact pair's cross blocks can fall on its wisp's band (segments two
        # apart): one summed block per position (a CSR row must not repeat a column)
        first = np.flatnonzero(np.r_[True, (rows[1:] != rows[:-1]) | (cols[1:] != cols[:-1])])
        if len(first) < len(rows):
            rows, cols, vals = rows[first], cols[first], np.add.reduceat(vals, first, axis=0)
        indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=len(verts)))])
        m = 3 * len(verts)
        M = PETSc.Mat().createBAIJ(size=(m, m), bsize=3, comm=PETSc.COMM_SELF,
                                   csr=(indptr.astype(PETSc.IntType), cols.astype(PETSc.IntType),
                                        np.ascontiguousarray(vals).ravel()))
        self.cluster_mat = M
        self.cluster = PETSc.PC().create(comm=PETSc.COMM_SELF)
        self.cluster.setType(PETSc.PC.Type.LU)
        self.cluster.setFactorOrdering(self.ordering)
        self.cluster.setOperators(M, M)
        self.cluster.setUp()
        self.dofs = (3 * verts[:, None] + np.arange(3)).ravel()
        self._cx = PETSc.Vec().createSeq(m, comm=PETSc.COMM_SELF)
        self._cy = self._cx.duplicate()
        n_clusters = len(np.unique(label[wisps]))
        stats.update(clusters=n_clusters, wisps=len(wisps), largest=int(count.max()), rows=m,
                     fill=float(self.cluster.getFactorMatrix().getInfo()["nz_used"]
                                / M.getInfo()["nz_used"]))

    def apply(self, pc, x, y):
        """y = P^-1 x: the per-wisp LUs, then the cluster rows by the clusters' LU."""
        xa = x.getArray(readonly=True)
        ya = y.getArray()
        self._x.placeArray(xa)
        self._y.placeArray(ya)
        try:
            self.band.apply(self._x, self._y)
        finally:
            self._x.resetArray()
            self._y.resetArray()
        if self.cluster is not None:
            self._cx.array[:] = xa[self.dofs]
            self.cluster.apply(self._cx, self._cy)
            ya[self.dofs] = self._cy.array_r

    def _destroy_cluster(self):
        for obj in (self.cluster, self.cluster_mat, self._cx, self._cy):
            if obj is not None:
                obj.destroy()
        self.cluster = self.cluster_mat = self._cx = self._cy = None
        self.dofs = np.zeros(0, np.int64)

    def destroy(self, pc=None):
        """Destroy the inner PETSc objects (PETSc calls this when the PC is destroyed)."""
        self._destroy_cluster()
        for obj in (self.band, self._x, self._y):
            if obj is not None:
                obj.destroy()
        self.band = self._x = self._y = None
