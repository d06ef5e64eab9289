"""Whether a Newton stop is a saddle of the incremental potential G (docs/newton.md,
"Saddles of G").

Backward Euler is a minimisation: the step's solution is a minimum of G, whose Hessian
there is positive definite.  Newton only finds a point where grad G vanishes, and its
increment test cannot tell a saddle from a minimum.  The per-wisp block Jacobi
preconditioner is the exact inverse of each wisp's block, so CG takes one step on an
uncoupled wisp and never meets the negative curvature either (the demo cut to 10 wisps,
frame 0 at full dt: three stops on saddles, lowest eigenvalues of dt^2 M^-1/2 H M^-1/2
of -1.15, -0.29 and -1.32, coils spun ~167 degrees about their straight pinned roots).

The check: the inertia of each wisp's diagonal block of the assembled Newton matrix
(the exact Hessian), from an LDL^T factorisation of its band without pivoting (by
Sylvester's law of inertia the negative pivots count the negative eigenvalues).  A
wisp's block is a principal submatrix of the whole Hessian (strand contact couples wisps
only through its own matrix), so one negative eigenvalue in it proves the whole matrix
indefinite (Cauchy interlacing); a negative mode spread over several wisps coupled by
contact is not seen here (lc_petsc/contact_curvature.py checks the whole A + C).
Rank-local and per wisp: the same answer on any partition.

The same kernel with a trial diagonal finds, per indefinite wisp, the least mass shift
that makes its block definite (:func:`least_definite_shifts`): the shifted fallback's
exact steps shift such wisps before the solve, so Newton does not walk into the saddle
(docs/newton.md "Avoiding the saddle").
"""

from __future__ import annotations

import numpy as np

from lc_petsc.elements.compiled import _jit


@_jit
def _negative_pivots(rowptr, cols, values, first, offsets, b, diag, active, counts):
    """Per wisp w, ``counts[w]`` = the number of pivots <= 0 of the LDL^T factorisation
    without pivoting of its diagonal block (its inertia's negative and zero part).
    Block-CSR rows ``rowptr`` (nb + 1,), global block columns ``cols``, 3x3 blocks
    row-major in ``values`` (9 k,), the rank's first global block row ``first``, local
    wisp vertex ``offsets``, half bandwidth ``b`` vertices.  Only blocks on or above the
    diagonal are read (the matrix is symmetric; SBAIJ stores no others).  ``diag`` (one
    per local vertex) is added to the vertex's three diagonal entries first (a trial
    shift, without reassembling); wisps with ``active[w]`` false are skipped (count 0)."""
    w = 3 * b + 2                       # scalar half bandwidth
    for wisp in range(len(offsets) - 1):
        if not active[wisp]:
            counts[wisp] = 0
            continue
        v0, v1 = offsets[wisp], offsets[wisp + 1]
        n = 3 * (v1 - v0)
        L = np.zeros((n, w + 1))        # L[i, k]: entry (i, i - k); k = 0: A's diagonal, then D
        for bi in range(v0, v1):
            for p in range(rowptr[bi], rowptr[bi + 1]):
                bj = cols[p] - first
                if bj < bi or bj >= v1:
                    continue
                for r in range(3):
                    for c in range(3):
                        i, j = 3 * (bj - v0) + c, 3 * (bi - v0) + r     # lower: row i >= col j
                        if i >= j and i - j <= w:
                            L[i, i - j] = values[9 * p + 3 * r + c]
            for r in range(3):
                L[3 * (bi - v0) + r, 0] += diag[bi]
        negative = 0
        u = np.empty(w)                 # u[j - k] = L[j, k] D[k]: row j's products, once
        for j in range(n):
            lo = max(0, j - w)
            d = L[j, 0]
            for k in range(lo, j):
                u[j - k - 1] = L[j, j - k] * L[k, 0]
                d -= L[j, j - k] * u[j - k - 1]
            if not d > 0.0:
                negative += 1
                if d == 0.0 or d != d:      # singular or NaN: no pivot to divide by
                    break
            L[j, 0] = d
            for i in range(j + 1, min(n, j + w + 1)):
                t = L[i, i - j]
                for k in range(max(0, i - w), j):
                    t -= L[i, i - k] * u[j - k - 1]
                L[i, i - j] = t / d
        counts[wisp] = negative


def negative_wisps(assembler, offsets):
    """Local indices of the wisps whose diagonal block of ``assembler``'s committed matrix
    is not positive definite (rank-local, no communication).  ``offsets``: the rank's
    local wisp vertex offsets (n_wisps + 1,)."""
    return np.flatnonzero(_Blocks(assembler, offsets).counts(np.zeros(offsets[-1]), np.ones(len(offsets) - 1, bool)))


def least_definite_shifts(assembler, offsets, unit, negative=None):
    """Per local wisp, the least s >= 0 (to a ratio of :data:`SHIFT_RESOLUTION` above it)
    for which its diagonal block of ``assembler``'s committed matrix plus s ``unit``
    (one diagonal entry per local vertex: M/dt^2 on the free vertices, 0 on pinned ones)
    is positive definite: 0 where the block already is, inf where not even s =
    :data:`SHIFT_RANGE`[1] makes it so.  A bisection in log s of the inertia, the
    indefinite wisps only (docs/newton.md "Avoiding the saddle"); rank-local, per wisp,
    so the same on any partition.  ``negative``: None or a bool array (n_wisps,) set to
    the wisps whose unshifted block is not positive definite (:func:`negative_wisps`'
    answer, from the same pass)."""
    blocks = _Blocks(assembler, offsets)
    n = len(offsets) - 1
    least = np.zeros(n)
    bad = blocks.counts(np.zeros(offsets[-1]), np.ones(n, bool)) > 0
    if negative is not None:
        negative[:] = bad
    if not bad.any():
        return least
    lo, hi = np.log(SHIFT_RANGE[0]), np.full(n, np.log(SHIFT_RANGE[1]))
    reach = blocks.counts(unit * SHIFT_RANGE[1], bad) == 0
    least[bad & ~reach] = np.inf
    bad &= reach
    low = np.full(n, lo)
    for _ in range(int(np.ceil(np.log2((hi[0] - lo) / np.log(SHIFT_RESOLUTION))))):
        mid = 0.5 * (low + hi)
        negative = blocks.counts(unit * np.repeat(np.exp(mid), np.diff(offsets)), bad) > 0
        low, hi = np.where(negative, mid, low), np.where(negative, hi, mid)
    least[bad] = np.exp(hi[bad])
    return least


class _Blocks:
    """The committed matrix's local block CSR, for :func:`_negative_pivots`."""

    def __init__(self, assembler, offsets):
        rowptr, cols, values = assembler.local_block_csr()
        self.args = (np.asarray(rowptr, np.int64), np.asarray(cols, np.int64), np.asarray(values, np.float64),
                     int(assembler.mat.getOwnershipRange()[0] // 3), np.asarray(offsets, np.int64),
                     int(assembler.b))

    def counts(self, diag, active):
        """Per local wisp, the pivots <= 0 of its block + ``diag`` (0 where not ``active``)."""
        counts = np.zeros(len(self.args[4]) - 1, np.int64)
        _negative_pivots(*self.args, np.asarray(diag, np.float64), np.asarray(active, np.bool_), counts)
        return counts


#: :func:`least_definite_shifts`: the range of shifts searched (in units of M/dt^2; the
#: hairball's frame 0 needed 0.3-2.5) and the resolution of the bisection
SHIFT_RANGE = (1e-3, 1e3)
SHIFT_RESOLUTION = 1.02


def warm_up():
    """Compile (or load from the cache) the kernel."""
    counts = np.zeros(1, np.int64)
    _negative_pivots(np.array([0, 1], np.int64), np.zeros(1, np.int64), np.eye(3).ravel(), 0,
                     np.array([0, 1], np.int64), 0, np.zeros(1), np.ones(1, np.bool_), counts)
