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
contact is not seen.  Rank-local and per wisp: the same answer on any partition.
"""

from __future__ import annotations

import numpy as np

from lc_petsc.elements.compiled import _jit


@_jit
def _negative_pivots(rowptr, cols, values, first, offsets, b, counts):
    """Per wisp w, ``counts[w]`` = the number of pivots <= 0 of the LDL^T factorisation
    without pivoting of its diagonal block (its inertia's negative and zero part).
    Block-CSR rows ``rowptr`` (nb + 1,), global block columns ``cols``, 3x3 blocks
    row-major in ``values`` (9 k,), the rank's first global block row ``first``, local
    wisp vertex ``offsets``, half bandwidth ``b`` vertices.  Only blocks on or above the
    diagonal are read (the matrix is symmetric; SBAIJ stores no others)."""
    w = 3 * b + 2                       # scalar half bandwidth
    for wisp in range(len(offsets) - 1):
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
    rowptr, cols, values = assembler.local_block_csr()
    first = assembler.mat.getOwnershipRange()[0] // 3
    counts = np.zeros(len(offsets) - 1, np.int64)
    _negative_pivots(np.asarray(rowptr, np.int64), np.asarray(cols, np.int64), np.asarray(values, np.float64),
                     int(first), np.asarray(offsets, np.int64), int(assembler.b), counts)
    return np.flatnonzero(counts)


def warm_up():
    """Compile (or load from the cache) the kernel."""
    counts = np.zeros(1, np.int64)
    _negative_pivots(np.array([0, 1], np.int64), np.zeros(1, np.int64), np.eye(3).ravel(), 0,
                     np.array([0, 1], np.int64), 0, counts)
