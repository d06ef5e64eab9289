"""The per-wisp exact factorisation of the strand matrix's band as a block Cholesky,
compiled (Numba): what ``-lc_band_factor cholesky`` (the default of the contact
preconditioner, lc_petsc/contact_pc.py) applies instead of PETSc's ILU(0) of the band.

The strand matrix A is symmetric positive definite (filtered Hessians plus M / dt^2),
block banded with 3x3 blocks, and every wisp's band lies on one rank, decoupled from the
others.  Per wisp, A = L L^T with L block lower triangular within the band (half
bandwidth b blocks; no fill outside it), its diagonal blocks lower triangular.  What is
stored per vertex i is one row of L: its b blocks left of the diagonal and the inverse
of its diagonal block, (b + 1) blocks, about half the bytes of PETSc's L and U factors
(2 b + 1 blocks).  A solve runs wisp by wisp, the backward sweep right after the forward
one, so the wisp's factor (~30 kB for 101 vertices) is read from memory once and from
the cache the second time: PETSc's ILU apply streams L over all rows, then U.

Cholesky, not a block LDL^T: on a chain of stiff springs (a rank-one 1e9 stiffness per
edge over a unit mass) the block LDL^T's Schur complements lose their soft direction
(residual 1e2 on 101 vertices, against 6e-7 for this factorisation and 4e-7 for LU with
partial pivoting; tests/contact/test_band_cholesky.py).  A that is not positive definite
(an exact Hessian's negative curvature) stops the factorisation at its first
non-positive pivot, and the caller falls back to PETSc's LU of the band.
"""

from __future__ import annotations

import numpy as np

from lc_petsc.elements.compiled import _jit, _sqrt


@_jit
def band_layout(indptr, indices, offsets):
    """(b, pos, inside) of a square sequential BAIJ pattern (block rows ``indptr``
    (n + 1,), block columns ``indices``) whose rows are grouped into wisps ``offsets``
    (w + 1,): the half bandwidth b (largest |column - row|), ``pos`` (n, 2 b + 1) the
    storage index of block (i, i - b + k), -1 where the pattern has none, and whether
    every block lies inside its row's wisp (if not, b = 0 and ``pos`` is empty: nothing
    the size of the band is allocated for a matrix that cannot be factored)."""
    n = len(indptr) - 1
    b = 0
    for w in range(len(offsets) - 1):
        for i in range(offsets[w], offsets[w + 1]):
            for t in range(indptr[i], indptr[i + 1]):
                j = indices[t]
                if j < offsets[w] or j >= offsets[w + 1]:
                    return 0, np.full((0, 1), -1, np.int64), False
                b = max(b, abs(j - i))
    pos = np.full((n, 2 * b + 1), -1, np.int64)
    for i in range(n):
        for t in range(indptr[i], indptr[i + 1]):
            pos[i, indices[t] - i + b] = t
    return b, pos, True


@_jit
def band_cholesky(values, pos, offsets, b, F):
    """Factor each wisp's band of the BAIJ values ``values`` (9 k,; blocks column-major;
    only the blocks left of the diagonal and the diagonal blocks' lower halves are
    read, A being symmetric) into ``F`` (n, b + 1, 3, 3): F[i, b - d] = L[i, i - d]
    (d = 1..b), F[i, b] = the inverse of L[i, i].  Returns -1, or the first row whose
    pivot is not positive (A not positive definite there; F is then incomplete)."""
    T = np.empty((3, 3))
    for w in range(len(offsets) - 1):
        s, e = offsets[w], offsets[w + 1]
        for i in range(s, e):
            j0 = max(s, i - b)
            for j in range(j0, i + 1):
                p = pos[i, j - i + b]
                for r in range(3):
                    for c in range(3):
                        T[r, c] = values[9 * p + 3 * c + r] if p >= 0 else 0.0
                for m in range(j0, j):          # T -= L[i, m] L[j, m]^T
                    Li = F[i, m - i + b]
                    Lj = F[j, m - j + b]
                    for r in range(3):
                        for c in range(3):
                            T[r, c] -= Li[r, 0] * Lj[c, 0] + Li[r, 1] * Lj[c, 1] + Li[r, 2] * Lj[c, 2]
                if j < i:                       # L[i, j] = T L[j, j]^-T
                    C = F[j, b]
                    L = F[i, j - i + b]
                    for r in range(3):
                        for c in range(3):
                            L[r, c] = T[r, 0] * C[c, 0] + T[r, 1] * C[c, 1] + T[r, 2] * C[c, 2]
                    continue
                # the diagonal block: its 3x3 Cholesky factor's inverse (lower)
                a00 = T[0, 0]
                if not a00 > 0.0:
                    return i
                l00 = _sqrt(a00)
                l10 = T[1, 0] / l00
                l20 = T[2, 0] / l00
                a11 = T[1, 1] - l10 * l10
                if not a11 > 0.0:
                    return i
                l11 = _sqrt(a11)
                l21 = (T[2, 1] - l20 * l10) / l11
                a22 = T[2, 2] - l20 * l20 - l21 * l21
                if not a22 > 0.0:
                    return i
                l22 = _sqrt(a22)
                C = F[i, b]
                C[0, 0] = 1.0 / l00
                C[1, 1] = 1.0 / l11
                C[2, 2] = 1.0 / l22
                C[1, 0] = -l10 * C[0, 0] * C[1, 1]
                C[2, 1] = -l21 * C[1, 1] * C[2, 2]
                C[2, 0] = -(l20 * C[0, 0] + l21 * C[1, 0]) * C[2, 2]
                C[0, 1] = 0.0
                C[0, 2] = 0.0
                C[1, 2] = 0.0
    return -1


@_jit
def band_solve(F, offsets, b, x, y, wisps):
    """y = A^-1 x (x, y (3 n,), distinct) from the factor of :func:`band_cholesky` on the
    rows of the wisps ``wisps`` (the other rows of y are left as they are): per wisp,
    L z = x, then L^T y = z."""
    for w in wisps:
        s, e = offsets[w], offsets[w + 1]
        for i in range(s, e):
            z0 = x[3 * i]
            z1 = x[3 * i + 1]
            z2 = x[3 * i + 2]
            for j in range(max(s, i - b), i):
                L = F[i, j - i + b]
                u0 = y[3 * j]
                u1 = y[3 * j + 1]
                u2 = y[3 * j + 2]
                z0 -= L[0, 0] * u0 + L[0, 1] * u1 + L[0, 2] * u2
                z1 -= L[1, 0] * u0 + L[1, 1] * u1 + L[1, 2] * u2
                z2 -= L[2, 0] * u0 + L[2, 1] * u1 + L[2, 2] * u2
            C = F[i, b]
            y[3 * i] = C[0, 0] * z0
            y[3 * i + 1] = C[1, 0] * z0 + C[1, 1] * z1
            y[3 * i + 2] = C[2, 0] * z0 + C[2, 1] * z1 + C[2, 2] * z2
        for i in range(e - 1, s - 1, -1):
            z0 = y[3 * i]
            z1 = y[3 * i + 1]
            z2 = y[3 * i + 2]
            for j in range(i + 1, min(e, i + b + 1)):
                L = F[j, i - j + b]             # L[j, i]^T
                u0 = y[3 * j]
                u1 = y[3 * j + 1]
                u2 = y[3 * j + 2]
                z0 -= L[0, 0] * u0 + L[1, 0] * u1 + L[2, 0] * u2
                z1 -= L[0, 1] * u0 + L[1, 1] * u1 + L[2, 1] * u2
                z2 -= L[0, 2] * u0 + L[1, 2] * u1 + L[2, 2] * u2
            C = F[i, b]                         # y_i = L[i, i]^-T z
            y[3 * i + 2] = C[2, 2] * z2
            y[3 * i + 1] = C[1, 1] * z1 + C[2, 1] * z2
            y[3 * i] = C[0, 0] * z0 + C[1, 0] * z1 + C[2, 0] * z2


class BandCholesky:
    """The band factor of one sequential BAIJ matrix (3x3 blocks) whose rows are the
    vertices of whole wisps (``offsets`` (w + 1,), the first vertex of each and the total).
    :meth:`factor` returns None when it holds, else why it cannot (the pattern leaves a
    wisp, or A is not positive definite); :meth:`apply` solves with it."""

    def __init__(self, offsets):
        self.offsets = np.asarray(offsets, np.int64)
        self.pattern = None             # (block rows, block columns) the layout is for
        self.b, self.pos, self.inside, self.F = 0, None, False, None
        self.every_wisp = np.arange(len(self.offsets) - 1, dtype=np.int64)

    def factor(self, indptr, indices, values):
        """Factor A given by its block CSR (``values`` (9 k,) column-major blocks)."""
        if len(indptr) - 1 != self.offsets[-1]:
            return f"the matrix has {len(indptr) - 1} block rows, the wisps {self.offsets[-1]} vertices"
        if self.pattern is None or not (np.array_equal(self.pattern[0], indptr)
                                        and np.array_equal(self.pattern[1], indices)):
            self.b, self.pos, self.inside = band_layout(indptr, indices, self.offsets)
            self.pattern = (indptr.copy(), indices.copy())
            self.F = np.empty((len(indptr) - 1, self.b + 1, 3, 3)) if self.inside else None
        if not self.inside:
            return "the matrix couples two wisps"
        row = band_cholesky(values, self.pos, self.offsets, self.b, self.F)
        if row >= 0:
            return f"not positive definite (block row {row})"
        return None

    def apply(self, x, y, wisps=None):
        """y = A^-1 x (arrays (3 n,)) on the rows of ``wisps`` (int64 wisp indices; default
        every wisp; y's other rows are left as they are)."""
        band_solve(self.F, self.offsets, self.b, x, y, self.every_wisp if wisps is None else wisps)


def warm_up():
    """Compile (or load from the cache) the kernels, for PETSc's 32-bit indices."""
    indptr, indices = np.array([0, 1], np.int32), np.array([0], np.int32)
    chol = BandCholesky([0, 1])
    chol.factor(indptr, indices, np.eye(3).ravel())
    chol.apply(np.ones(3), np.empty(3))
