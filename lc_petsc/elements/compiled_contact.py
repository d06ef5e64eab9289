"""The penalty contact's assembly rows, compiled (Numba): :mod:`segment_contact`'s
gradient and ``analytic`` Hessian of each pair, fused with the contact assembly's
per-segment rows (:func:`compiled_ccd.pair_rows`) and the pair's cross blocks, without
the (n, 12, 12) Hessians in between.

The NumPy kernel stays the reference.  The arithmetic is the NumPy kernel's, scalar by
scalar and in its order (closest points with left-to-right dot products, normal,
weights, psi' = -k (d0 - d), psi'' = k, the Hessian entry (psi'' g_i) g_j, pinned
vertices' entries times 0), so the values agree to the bit
(``tests/contact/test_contact_kernel.py``).  Measured on 20k random pairs: 7 ms against
72 ms for the NumPy kernel, the pinned masking and the row and block copies.
"""

from __future__ import annotations

import math

import numpy as np

from lc_petsc.elements.common import check_per_element, check_positions
from lc_petsc.elements.compiled import _jit, _vcross, _vdot, _vnorm
from lc_petsc.elements.compiled_ccd import _TINY, _vclosest
from lc_petsc.elements.segment_contact import _ZERO_DIST


@_jit
def _pair_direction(X, p, gd):
    """Closest points of pair p of X (n, 4, 3) (segment_contact.closest_points), its
    gradient of the distance gd (12,) = w (x) n, and the distance."""
    x0, x1, x2, x3 = X[p, 0], X[p, 1], X[p, 2], X[p, 3]
    s, t, d1, d2 = _vclosest(x0, x1, x2, x3)
    u = ((x0[0] + s * d1[0]) - (x2[0] + t * d2[0]), (x0[1] + s * d1[1]) - (x2[1] + t * d2[1]),
         (x0[2] + s * d1[2]) - (x2[2] + t * d2[2]))
    d = math.sqrt(_vdot(u, u))
    scale = 0.0
    for v in range(4):
        for k in range(3):
            scale = max(scale, abs(X[p, v, k]))
    if d <= _ZERO_DIST * max(scale, 1.0):
        # intersecting: unit(d1 x d2), or a perpendicular of d1 (segment_contact._normal)
        m = _vcross(d1, d2)
        mn = _vnorm(m)
        if mn <= 1e-12 * _vnorm(d1) * _vnorm(d2):
            k = 0
            for q in range(1, 3):
                if abs(d1[q]) < abs(d1[k]):
                    k = q
            ax = (1.0 if k == 0 else 0.0, 1.0 if k == 1 else 0.0, 1.0 if k == 2 else 0.0)
            m = _vcross(d1, ax)
            mn = _vnorm(m)
        mn = max(mn, _TINY)
        nrm = (m[0] / mn, m[1] / mn, m[2] / mn)
    else:
        nrm = (u[0] / d, u[1] / d, u[2] / d)
    w = (1.0 - s, s, -(1.0 - t), -t)
    for v in range(4):
        for k in range(3):
            gd[3 * v + k] = w[v] * nrm[k]
    return d


@_jit
def _penalty_rows(X, d0, stiffness, free, owner_a, owner_b, rows, cross_ab, cross_ba):
    m = X.shape[0]
    gd = np.empty(12)
    g = np.empty(12)
    H = np.empty((12, 12))
    for p in range(m):
        d = _pair_direction(X, p, gd)
        active = d < d0
        gap = d0 - d if active else 0.0
        kk = stiffness if active else 0.0
        psi1 = -(kk * gap)
        for i in range(12):
            g[i] = psi1 * gd[i]
            for j in range(12):
                # k (gd_i gd_j): H exactly symmetric, so C is (its rank-local block is
                # multiplied from its upper triangle, lc_petsc/contact.py _BlockProduct)
                H[i, j] = kk * (gd[i] * gd[j])
        if not (free[p, 0] and free[p, 1] and free[p, 2] and free[p, 3]):
            for i in range(12):
                fi = 1.0 if free[p, i // 3] else 0.0
                g[i] *= fi
                for j in range(12):
                    H[i, j] *= fi * (1.0 if free[p, j // 3] else 0.0)
        for side in range(2):
            r = side * m + p
            o = 6 * side
            for i in range(6):
                rows[r, i] = g[o + i]
            for c in range(3):
                for k in range(3):
                    rows[r, 6 + 3 * c + k] = H[o + c, o + k]
                    rows[r, 15 + 3 * c + k] = H[o + c, o + 3 + k]
                    rows[r, 24 + 3 * c + k] = H[o + 3 + c, o + 3 + k]
            same = owner_a[p] == owner_b[p]
            rows[r, 33] = 2.0 if same else 0.0
            rows[r, 34] = 0.0 if same else 2.0
        for i in range(6):
            for j in range(6):
                cross_ab[p, 6 * i + j] = H[i, 6 + j]
                cross_ba[p, 6 * i + j] = H[6 + i, j]


def penalty_rows(X, thickness, stiffness, free, owner_a, owner_b):
    """(rows (2m, 35), cross_ab (m, 36), cross_ba (m, 36)) of the m pairs X (m, 4, 3) of
    the penalty 1/2 k (d0 - d)^2 (``thickness`` d0, ``stiffness`` k, scalars) with the
    ``analytic`` Hessian H = k (grad d)(grad d)^T: the rows of
    :func:`compiled_ccd.pair_rows` (each segment's gradient and own blocks, the
    preallocation counts by ``owner_a`` == ``owner_b``) and the blocks H[0:6, 6:12] and
    H[6:12, 0:6], row-major; the entries of the pinned vertices (``free`` (m, 4) False)
    are zero."""
    X = np.ascontiguousarray(check_positions(X, 4, "segment_contact"))
    m = len(X)
    if np.shape(free) != (m, 4) or np.shape(owner_a) != (m,) or np.shape(owner_b) != (m,):
        raise ValueError(f"penalty_rows: free must be ({m}, 4) and owner_a, owner_b ({m},), got "
                         f"{np.shape(free)}, {np.shape(owner_a)}, {np.shape(owner_b)}")
    check_per_element(thickness, 1, "segment_contact", "thickness", positive=True)
    check_per_element(stiffness, 1, "segment_contact", "stiffness")
    rows, cross_ab, cross_ba = np.empty((2 * m, 35)), np.empty((m, 36)), np.empty((m, 36))
    _penalty_rows(X, float(thickness), float(stiffness), np.ascontiguousarray(free, np.bool_),
                  np.ascontiguousarray(owner_a, np.int64), np.ascontiguousarray(owner_b, np.int64),
                  rows, cross_ab, cross_ba)
    return rows, cross_ab, cross_ba


def warm_up():
    """Compile (or load from the cache) the kernels."""
    X = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 0.01, 1], [0, 0.01, -1]]])
    penalty_rows(X, 0.1, 1.0, np.ones((1, 4), bool), np.zeros(1, np.int64), np.zeros(1, np.int64))
