"""The product of a sequential BAIJ matrix with 3x3 blocks and a vector, compiled (Numba):
:func:`bsr3_mult` on PETSc's value array, and :func:`bsr3_sym_mult` on a copy of the
upper triangle of an exactly symmetric one (:func:`bsr3_upper_pattern`,
:func:`bsr3_upper_values`), which reads about half the bytes for the same result.

With strand contact CG multiplies by the Python shell A x + C x every iteration
(:class:`lc_petsc.contact.SumOperator`); A's rank-local block (the per-wisp bands) is
most of the bytes read.  Measured on the 2,000-wisp hairball's A on one core (100 MB of
values, 2026-12-05, ``scripts/bench_product.py``): Debian PETSc 3.18's
``MatMult_SeqBAIJ_3`` 20.8-21.0 ms, this loop 12.3-13.6 ms (0.59-0.65x; a NumPy sum of
the same values: 7.3-8.1 ms), and later that day 17.4-17.9 against 14.4 ms (0.81-0.83x;
the sum 9.3-9.7 ms); in the 2K and 8K runs on 2 ranks, 9.4 -> ~6 ms and
33 -> 24 ms per product (docs/contact_solver.md, "The strand product compiled").  It is
PETSc's loop, term by term and in its order (no fused multiply-adds: strict IEEE,
:func:`lc_petsc.elements.compiled._jit`), so the product equals ``MatMult``'s to the
bit (``tests/contact/test_cluster_span.py``) and no trajectory changes.
"""

from __future__ import annotations

import numpy as np

from lc_petsc.elements.compiled import _jit


@_jit
def bsr3_mult(indptr, indices, values, x, y, add):
    """y = M x (``add`` False) or y = y + M x (``add`` True) for a sequential BAIJ matrix M
    with 3x3 blocks, in PETSc's storage: block rows ``indptr`` (nb + 1,), block columns
    ``indices`` (k,), ``values`` (9 k,) block by block, each block column-major; ``x``
    (3 * block columns,), ``y`` (3 nb,).  The arithmetic of PETSc 3.18's
    ``MatMult_SeqBAIJ_3`` / ``MatMultAdd_SeqBAIJ_3``: per block row, from 0 or from y,
    sum_i += (v[i] x0 + v[i + 3] x1) + v[i + 6] x2, block after block (a row without
    blocks keeps y, as PETSc's compressed rows do)."""
    for i in range(len(indptr) - 1):
        s0 = y[3 * i] if add else 0.0
        s1 = y[3 * i + 1] if add else 0.0
        s2 = y[3 * i + 2] if add else 0.0
        for k in range(indptr[i], indptr[i + 1]):
            c = 3 * indices[k]
            b = 9 * k
            x0 = x[c]
            x1 = x[c + 1]
            x2 = x[c + 2]
            s0 += values[b] * x0 + values[b + 3] * x1 + values[b + 6] * x2
            s1 += values[b + 1] * x0 + values[b + 4] * x1 + values[b + 7] * x2
            s2 += values[b + 2] * x0 + values[b + 5] * x1 + values[b + 8] * x2
        y[3 * i] = s0
        y[3 * i + 1] = s1
        y[3 * i + 2] = s2


@_jit
def bsr3_upper_pattern(indptr, indices):
    """The upper triangle (diagonal blocks included) of a square sequential BAIJ
    pattern (block rows ``indptr`` (nb + 1,), sorted block columns ``indices`` (k,)):
    (upper block rows (nb + 1,), their columns (u,), ``source`` (u,) each upper block's
    index in the full storage, ``lower`` (l,) the full storage's blocks below the
    diagonal, ``mirror`` (l,) the index of each one's transpose position (block (j, i) of
    a block (i, j)), -1 where the pattern has none; whether the pattern is symmetric: every
    block below the diagonal has its mirror and there are as many above)."""
    nb = len(indptr) - 1
    n_upper = 0
    n_diagonal = 0
    for i in range(nb):
        for k in range(indptr[i], indptr[i + 1]):
            if indices[k] >= i:
                n_upper += 1
            if indices[k] == i:
                n_diagonal += 1
    n_lower = indptr[nb] - n_upper
    upper_indptr = np.empty(nb + 1, indptr.dtype)
    upper_indices = np.empty(n_upper, indices.dtype)
    source = np.empty(n_upper, np.int64)
    lower = np.empty(n_lower, np.int64)
    mirror = np.empty(n_lower, np.int64)
    u = 0
    m = 0
    upper_indptr[0] = 0
    for i in range(nb):
        for k in range(indptr[i], indptr[i + 1]):
            j = indices[k]
            if j >= i:
                upper_indices[u] = j
                source[u] = k
                u += 1
            else:
                lower[m] = k
                mirror[m] = -1
                for t in range(indptr[j], indptr[j + 1]):   # row j's block in column i
                    if indices[t] == i:
                        mirror[m] = t
                        break
                m += 1
        upper_indptr[i + 1] = u
    # (i, j) -> (j, i) is one to one: all mirrors found and as many blocks above as below
    symmetric = n_lower == n_upper - n_diagonal
    for m in range(n_lower):
        if mirror[m] < 0:
            symmetric = False
    return upper_indptr, upper_indices, source, lower, mirror, symmetric


@_jit
def bsr3_upper_values(values, bits, source, lower, mirror, out):
    """Copy the upper blocks ``source`` of the BAIJ value array ``values`` (9 k,) into
    ``out`` (9 u,); returns whether every block ``lower`` equals the transpose of its
    ``mirror`` block bit for bit (``bits``: ``values`` viewed as int64, so -0.0 and 0.0
    differ) and holds no NaN (a matrix with one takes the full product)."""
    for u in range(len(source)):
        b = 9 * source[u]
        for t in range(9):
            out[9 * u + t] = values[b + t]
    same = True
    for m in range(len(lower)):
        b = 9 * lower[m]
        c = 9 * mirror[m]
        for r in range(3):
            for s in range(3):          # column-major: block[r, s] = values[b + 3 s + r]
                same &= (bits[b + 3 * s + r] == bits[c + 3 * r + s]) & \
                    (values[b + 3 * s + r] == values[b + 3 * s + r])
    return same


@_jit
def bsr3_sym_mult(indptr, indices, values, x, y, add):
    """y = M x (``add`` False) or y = y + M x for the symmetric BAIJ matrix M given by its
    upper triangle (:func:`bsr3_upper_pattern`, :func:`bsr3_upper_values`): each block
    (i, j > i) is read once and applied as itself to row i and as its transpose to row j,
    so the product reads about half the bytes of :func:`bsr3_mult`.  Row j's sum takes
    its blocks in column order (the transposes from the rows above it as they come, then
    its own), each block's three terms grouped as there, so for an exactly symmetric M
    the result equals :func:`bsr3_mult`'s (and ``MatMult``'s) bit for bit."""
    nb = len(indptr) - 1
    if not add:
        for i in range(3 * nb):
            y[i] = 0.0
    for i in range(nb):
        x0 = x[3 * i]
        x1 = x[3 * i + 1]
        x2 = x[3 * i + 2]
        s0 = y[3 * i]
        s1 = y[3 * i + 1]
        s2 = y[3 * i + 2]
        for k in range(indptr[i], indptr[i + 1]):
            c = 3 * indices[k]
            b = 9 * k
            z0 = x[c]
            z1 = x[c + 1]
            z2 = x[c + 2]
            s0 += values[b] * z0 + values[b + 3] * z1 + values[b + 6] * z2
            s1 += values[b + 1] * z0 + values[b + 4] * z1 + values[b + 7] * z2
            s2 += values[b + 2] * z0 + values[b + 5] * z1 + values[b + 8] * z2
            if c != 3 * i:
                y[c] += values[b] * x0 + values[b + 1] * x1 + values[b + 2] * x2
                y[c + 1] += values[b + 3] * x0 + values[b + 4] * x1 + values[b + 5] * x2
                y[c + 2] += values[b + 6] * x0 + values[b + 7] * x1 + values[b + 8] * x2
        y[3 * i] = s0
        y[3 * i + 1] = s1
        y[3 * i + 2] = s2


def warm_up():
    """Compile (or load from the cache) the kernels, for PETSc's 32-bit indices."""
    indptr, indices = np.array([0, 1], np.int32), np.array([0], np.int32)
    y = np.zeros(3)
    for add in (False, True):
        bsr3_mult(indptr, indices, np.ones(9), np.ones(3), y, add)
        bsr3_sym_mult(indptr, indices, np.ones(9), np.ones(3), y, add)
    upper_indptr, upper_indices, source, lower, mirror, _ = bsr3_upper_pattern(indptr, indices)
    values = np.ones(9)
    bsr3_upper_values(values, values.view(np.int64), source, lower, mirror, np.empty(9))
