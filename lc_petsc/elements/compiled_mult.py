"""The product of a sequential BAIJ matrix with 3x3 blocks and a vector, compiled (Numba).

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


def warm_up():
    """Compile (or load from the cache) the kernel, for PETSc's 32-bit indices."""
    indptr, indices = np.array([0, 1], np.int32), np.array([0], np.int32)
    y = np.zeros(3)
    for add in (False, True):
        bsr3_mult(indptr, indices, np.ones(9), np.ones(3), y, add)
