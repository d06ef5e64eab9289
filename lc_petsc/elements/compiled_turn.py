"""The root turn's fixed per-frame work compiled (Numba): its model's per-vertex sums
(:func:`turn_sums`) and curvature (:func:`turn_curvature`), its preconditioned conjugate
gradients per wisp (:func:`turn_pcg`) and the Rodrigues turn of its vertices
(:func:`turn_vertices`), for
:class:`lc_petsc.root_rotation.RootRotation`.

In NumPy these were ~80 operations on small per-vertex and per-wisp arrays each frame, a
fixed cost that weighed on small scenes (hairball10: ~12% of a step, docs/newton.md
"Nineteenth round").  Each kernel does NumPy's arithmetic in NumPy's order (strict IEEE,
:func:`lc_petsc.elements.compiled._jit`), so the results equal the NumPy references
(``*_numpy`` here, the tested reference) bit for bit and no trajectory changes
(``tests/elements/test_compiled_turn.py``, ``tests/sim/test_root_rotation.py``): a
wisp's sums as ``np.add.reduceat`` on axis 0 adds them (its first row plus NumPy's
pairwise sum of the rest: :func:`_pairwise_sum`), three-term sums along a row as
``np.sum`` ((a0 + a1) + a2) and ``np.einsum("wkl,wl->wk")`` ((a0 + a2) + a1) add them,
and the 3x3 solves by LAPACK's ``dgesv`` as ``np.linalg.solve`` calls it.
"""

from __future__ import annotations

import numpy as np

from lc_petsc.elements.angle import cross3
from lc_petsc.elements.compiled import _jit

#: columns of :func:`turn_sums`' per-wisp output: b, then T and M row-major
_COLUMNS = 21
#: conjugate-gradient steps of the turn (:func:`turn_pcg`)
PCG_STEPS = 3


@_jit
def _pairwise_sum(a, lo, hi, c):
    """sum of a[lo:hi, c] as NumPy's ``pairwise_sum`` adds it (numpy/core/src/umath/
    loops_utils.h): below 8 terms in order from 0.0, up to 128 in eight interleaved
    accumulators then the remainder, above that its two halves (the first a multiple of
    8 long)."""
    n = hi - lo
    if n < 8:
        res = 0.0
        for i in range(lo, hi):
            res += a[i, c]
        return res
    if n <= 128:
        r0, r1, r2, r3 = a[lo, c], a[lo + 1, c], a[lo + 2, c], a[lo + 3, c]
        r4, r5, r6, r7 = a[lo + 4, c], a[lo + 5, c], a[lo + 6, c], a[lo + 7, c]
        i = lo + 8
        end = hi - n % 8
        while i < end:
            r0 += a[i, c]
            r1 += a[i + 1, c]
            r2 += a[i + 2, c]
            r3 += a[i + 3, c]
            r4 += a[i + 4, c]
            r5 += a[i + 5, c]
            r6 += a[i + 6, c]
            r7 += a[i + 7, c]
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < hi:
            res += a[i, c]
            i += 1
        return res
    n2 = n // 2
    n2 -= n2 % 8
    return _pairwise_sum(a, lo, lo + n2, c) + _pairwise_sum(a, lo + n2, hi, c)


@_jit
def _turn_sums(x, outer, unit, mask, pivot_of, offsets, near, gnear, near_moved, r, out):
    nv = x.shape[0]
    per = np.empty((nv, _COLUMNS))
    q = np.empty((nv, 3))
    for v in range(nv):
        for k in range(3):
            r[v, k] = (x[v, k] - x[pivot_of[v], k]) * mask[v]
            q[v, k] = outer[v, k] * mask[v]
    for j in range(near.shape[0]):
        for k in range(3):
            q[near[j], k] += gnear[j, k] * near_moved[j]
    for v in range(nv):
        r0, r1, r2 = r[v, 0], r[v, 1], r[v, 2]
        q0, q1, q2 = q[v, 0], q[v, 1], q[v, 2]
        per[v, 0] = r1 * q2 - r2 * q1
        per[v, 1] = r2 * q0 - r0 * q2
        per[v, 2] = r0 * q1 - r1 * q0
        m = unit[v] * mask[v]
        for k in range(3):
            for col in range(3):
                per[v, 3 + 3 * k + col] = r[v, k] * (m * r[v, col] - q[v, col])
                per[v, 12 + 3 * k + col] = (m * r[v, k]) * r[v, col]
    for w in range(offsets.shape[0] - 1):
        a, b = offsets[w], offsets[w + 1]
        for c in range(_COLUMNS):
            out[w, c] = per[a, c] + _pairwise_sum(per, a + 1, b, c)


def _vertex_array(a, nv, name, width=3):
    a = np.ascontiguousarray(a, np.float64)
    if a.shape != ((nv, width) if width else (nv,)):
        raise ValueError(f"root turn: {name} must have shape {(nv, width) if width else (nv,)}, got {a.shape}")
    return a


def turn_layout(mask, pivot_of, offsets, near, near_moved):
    """The turn's fixed arrays for :func:`turn_sums`, validated once: ``mask`` (nv,) 1 on
    turned vertices, else 0; ``pivot_of`` (nv,) each vertex's wisp's pivot (any vertex
    where the mask is 0); ``offsets`` (n_wisps + 1,) the wisps' first vertices; ``near``
    (k,) sorted distinct vertices of the elements across the roots, ``near_moved`` (k,)
    the mask there."""
    offsets = np.ascontiguousarray(offsets, np.int64)
    if offsets.ndim != 1 or len(offsets) < 1 or offsets[0] != 0 or np.any(np.diff(offsets) < 1):
        raise ValueError(f"root turn: offsets must rise from 0, every wisp at least one vertex, got {offsets}")
    nv = int(offsets[-1])
    mask = _vertex_array(mask, nv, "mask", 0)
    pivot_of, near = (np.ascontiguousarray(a, np.int64) for a in (pivot_of, near))
    if pivot_of.shape != (nv,) or near.ndim != 1:
        raise ValueError(f"root turn: pivot_of must have shape ({nv},) and near be 1-d, got {pivot_of.shape}, "
                         f"{near.shape}")
    for name, idx in (("pivot_of", pivot_of), ("near", near)):
        if len(idx) and (idx.min() < 0 or idx.max() >= nv):
            raise ValueError(f"root turn: {name} must index the {nv} vertices")
    if np.any(np.diff(near) < 1):
        raise ValueError("root turn: near must be sorted and distinct")
    return mask, pivot_of, offsets, near, _vertex_array(near_moved, len(near), "near_moved", 0)


def turn_sums(layout, x, outer, unit, gnear):
    """(r, b, T, M) of the root turn's model: with ``layout`` (:func:`turn_layout`'s
    mask, pivot_of, offsets, near, near_moved), r (nv, 3) each vertex from its wisp's
    pivot times the mask; with q = ``outer`` (nv, 3) times the mask, plus ``gnear`` (the
    across elements' gradient at the vertices ``near``) times ``near_moved`` there, per
    wisp b = sum r x q (n_wisps, 3), T = sum r (m r - q)^T and M = sum (m r) r^T
    (n_wisps, 3, 3), m = ``unit`` (nv,) times the mask.  :func:`turn_sums_numpy` bit for
    bit."""
    mask, pivot_of, offsets, near, near_moved = layout
    nv = len(mask)
    x, outer = _vertex_array(x, nv, "x"), _vertex_array(outer, nv, "outer")
    unit, gnear = _vertex_array(unit, nv, "unit", 0), _vertex_array(gnear, len(near), "gnear")
    r = np.empty_like(x)
    out = np.empty((len(offsets) - 1, _COLUMNS))
    _turn_sums(x, outer, unit, mask, pivot_of, offsets, near, gnear, near_moved, r, out)
    return r, out[:, :3], out[:, 3:12].reshape(-1, 3, 3), out[:, 12:].reshape(-1, 3, 3)


def turn_sums_numpy(layout, x, outer, unit, gnear):
    """:func:`turn_sums` in NumPy (the reference)."""
    mask, pivot_of, offsets, near, near_moved = layout
    r = (x - x[pivot_of]) * mask[:, None]
    q = outer * mask[:, None]
    q[near] += gnear * near_moved[:, None]
    mr = (unit * mask)[:, None] * r
    sums = [np.add.reduceat(a, offsets[:-1], axis=0) for a in
            (cross3(r.T, q.T).T, r[:, :, None] * (mr - q)[:, None, :], mr[:, :, None] * r[:, None, :])]
    return r, *sums


@_jit
def _turn_copies(x, pivot_of, near, near_moved, turns, out):
    k = near.shape[0]
    for j in range(turns.shape[0]):
        for i in range(k):
            v, p = near[i], pivot_of[near[i]]
            for c in range(3):
                if near_moved[i] != 0.0:
                    d0, d1, d2 = x[v, 0] - x[p, 0], x[v, 1] - x[p, 1], x[v, 2] - x[p, 2]
                    out[j * k + i, c] = x[p, c] + ((d0 * turns[j, 0, c] + d1 * turns[j, 1, c]) + d2 * turns[j, 2, c])
                else:
                    out[j * k + i, c] = x[v, c]
    for i in range(k):
        for c in range(3):
            out[turns.shape[0] * k + i, c] = x[near[i], c]


def turn_copies(layout, x, turns):
    """(J + 1) copies of the vertices ``near`` of ``layout`` (:func:`turn_layout`) stacked
    ((J + 1) k, 3): copy j < J those where ``near_moved`` turned about their pivots by the
    matrix ``turns``[j] (J, 3, 3) acting on row vectors, the others as they are; the last
    copy as they are (the central differences' turns and the unturned vertices, for one
    element pass).  :func:`turn_copies_numpy` bit for bit (``np.einsum``'s order,
    (a0 + a1) + a2)."""
    mask, pivot_of, _, near, near_moved = layout
    x = _vertex_array(x, len(mask), "x")
    turns = np.ascontiguousarray(turns, np.float64)
    if turns.ndim != 3 or turns.shape[1:] != (3, 3):
        raise ValueError(f"root turn: turns must have shape (J, 3, 3), got {turns.shape}")
    out = np.empty(((len(turns) + 1) * len(near), 3))
    _turn_copies(x, pivot_of, near, near_moved, turns, out)
    return out


def turn_copies_numpy(layout, x, turns):
    """:func:`turn_copies` in NumPy (the reference)."""
    _, pivot_of, _, near, near_moved = layout
    xs, pn = x[near], x[pivot_of[near]]
    turned = np.where(near_moved[None, :, None] != 0.0, pn + np.einsum("nl,jlk->jnk", xs - pn, turns), xs)
    return np.concatenate([turned.reshape(-1, 3), xs])


@_jit
def _turn_curvature(T, M, HJ, rn, wn, A, P):
    for w in range(T.shape[0]):
        trT = (T[w, 0, 0] + T[w, 1, 1]) + T[w, 2, 2]
        trM = (M[w, 0, 0] + M[w, 1, 1]) + M[w, 2, 2]
        for k in range(3):
            for col in range(3):
                e = 1.0 if k == col else 0.0
                A[w, k, col] = trT * e - 0.5 * (T[w, k, col] + T[w, col, k])
                P[w, k, col] = trM * e - M[w, k, col]
    for j in range(wn.shape[0]):
        w = wn[j]
        r0, r1, r2 = rn[j, 0], rn[j, 1], rn[j, 2]
        for k in range(3):
            h0, h1, h2 = HJ[k, j, 0], HJ[k, j, 1], HJ[k, j, 2]
            A[w, 0, k] += r1 * h2 - r2 * h1
            A[w, 1, k] += r2 * h0 - r0 * h2
            A[w, 2, k] += r0 * h1 - r1 * h0


def _curvature_arrays(T, M, HJ, rn, wn):
    T, M, HJ, rn = (np.ascontiguousarray(a, np.float64) for a in (T, M, HJ, rn))
    wn = np.ascontiguousarray(wn, np.int64)
    n, k = len(T), len(wn)
    if T.shape != (n, 3, 3) or M.shape != (n, 3, 3) or HJ.shape != (3, k, 3) or rn.shape != (k, 3) or (
            k and (wn.min() < 0 or wn.max() >= n)):
        raise ValueError(f"root turn: T, M (n, 3, 3), HJ (3, k, 3), rn (k, 3) and wn (k,) indexing the n wisps "
                         f"must match, got {T.shape}, {M.shape}, {HJ.shape}, {rn.shape}, {wn.shape}")
    return T, M, HJ, rn, wn


def turn_curvature(T, M, HJ, rn, wn):
    """(A, P) (n, 3, 3) of the turn's model from :func:`turn_sums`' T and M: A = tr(T) I
    - sym(T) plus, per vertex j of the elements across the roots (its wisp ``wn``[j],
    its arm ``rn``[j] (k, 3)), column k += rn[j] x ``HJ``[k, j] (the central difference
    of their gradient along turn k, (3, k, 3)); P = tr(M) I - M.
    :func:`turn_curvature_numpy` bit for bit."""
    T, M, HJ, rn, wn = _curvature_arrays(T, M, HJ, rn, wn)
    A, P = np.empty_like(T), np.empty_like(M)
    _turn_curvature(T, M, HJ, rn, wn, A, P)
    return A, P


def turn_curvature_numpy(T, M, HJ, rn, wn):
    """:func:`turn_curvature` in NumPy (the reference)."""
    T, M, HJ, rn, wn = _curvature_arrays(T, M, HJ, rn, wn)
    eye = np.eye(3)
    A = np.einsum("wkk->w", T)[:, None, None] * eye - 0.5 * (T + T.transpose(0, 2, 1))
    np.add.at(A, wn, np.stack([cross3(rn.T, HJ[k].T).T for k in range(3)], axis=2))
    return A, np.einsum("wkk->w", M)[:, None, None] * eye - M


@_jit
def _turn_pcg(A, P, b, held, theta):
    for w in range(A.shape[0]):
        theta[w, 0] = theta[w, 1] = theta[w, 2] = 0.0
        if not held[w]:
            continue
        res = -b[w]
        z = np.linalg.solve(P[w], res)
        d = z.copy()
        Ad = np.empty(3)
        for _ in range(PCG_STEPS):
            for k in range(3):
                Ad[k] = (A[w, k, 0] * d[0] + A[w, k, 2] * d[2]) + A[w, k, 1] * d[1]
            dAd = (d[0] * Ad[0] + d[1] * Ad[1]) + d[2] * Ad[2]
            if not dAd > 0.0:
                break
            rz = (res[0] * z[0] + res[1] * z[1]) + res[2] * z[2]
            alpha = rz / dAd
            for k in range(3):
                theta[w, k] += alpha * d[k]
            res = res - alpha * Ad
            z = np.linalg.solve(P[w], res)
            beta = ((res[0] * z[0] + res[1] * z[1]) + res[2] * z[2]) / (rz if rz != 0.0 else 1.0)
            d = z + beta * d


def _wisp_arrays(A, P, b, held):
    A, P, b = (np.ascontiguousarray(a, np.float64) for a in (A, P, b))
    held = np.ascontiguousarray(held, np.bool_)
    n = len(held)
    if A.shape != (n, 3, 3) or P.shape != (n, 3, 3) or b.shape != (n, 3) or held.ndim != 1:
        raise ValueError(f"root turn: A, P (n, 3, 3), b (n, 3) and held (n,) must match, got {A.shape}, "
                         f"{P.shape}, {b.shape}, {held.shape}")
    return A, P, b, held


def turn_pcg(A, P, b, held):
    """theta (n, 3): per wisp ``held`` (n,), :data:`PCG_STEPS` conjugate-gradient steps
    on A theta = -b preconditioned by P (n, 3, 3, invertible where held) from 0, a
    direction of curvature that is not positive ending the wisp's iteration (its turn so
    far kept); 0 where not held.  :func:`turn_pcg_numpy` bit for bit."""
    A, P, b, held = _wisp_arrays(A, P, b, held)
    theta = np.empty_like(b)
    _turn_pcg(A, P, b, held, theta)
    return theta


def turn_pcg_numpy(A, P, b, held):
    """:func:`turn_pcg` in NumPy, all wisps at once (the reference)."""
    A, P, b, held = _wisp_arrays(A, P, b, held)
    P = np.where(held[:, None, None], P, np.eye(3))
    theta = np.zeros((len(held), 3))
    res = -b
    z = np.linalg.solve(P, res[:, :, None])[:, :, 0]
    d = z.copy()
    active = held.copy()
    for _ in range(PCG_STEPS):
        Ad = np.einsum("wkl,wl->wk", A, d)
        dAd = np.sum(d * Ad, axis=1)
        active &= dAd > 0.0
        if not active.any():
            break
        rz = np.sum(res * z, axis=1)
        alpha = np.where(active, rz / np.where(active, dAd, 1.0), 0.0)
        theta += alpha[:, None] * d
        res = res - alpha[:, None] * Ad
        z = np.linalg.solve(P, res[:, :, None])[:, :, 0]
        beta = np.sum(res * z, axis=1) / np.where(rz != 0.0, rz, 1.0)
        d = z + beta[:, None] * d
    return theta


@_jit
def _turn_vertices(x, idx, pivot, axis, c, s, y):
    for j in range(idx.shape[0]):
        i, p = idx[j], pivot[j]
        v0, v1, v2 = x[i, 0] - x[p, 0], x[i, 1] - x[p, 1], x[i, 2] - x[p, 2]
        a0, a1, a2 = axis[j, 0], axis[j, 1], axis[j, 2]
        dot = (a0 * v0 + a1 * v1) + a2 * v2
        cj, sj = c[j], s[j]
        y[i, 0] = x[p, 0] + ((v0 * cj + (a1 * v2 - a2 * v1) * sj) + a0 * (dot * (1.0 - cj)))
        y[i, 1] = x[p, 1] + ((v1 * cj + (a2 * v0 - a0 * v2) * sj) + a1 * (dot * (1.0 - cj)))
        y[i, 2] = x[p, 2] + ((v2 * cj + (a0 * v1 - a1 * v0) * sj) + a2 * (dot * (1.0 - cj)))


def turn_vertices(x, idx, pivot, axis, c, s):
    """x (nv, 3) with the vertices ``idx`` (k,) turned about the vertices ``pivot`` (k,)
    by the rotation of unit ``axis`` (k, 3) (0 for none), cosine ``c`` and sine ``s``
    (k,) (Rodrigues, :func:`lc_petsc.root_rotation.rotate`'s arithmetic): a new array."""
    x = np.ascontiguousarray(x, np.float64)
    idx, pivot = (np.ascontiguousarray(a, np.int64) for a in (idx, pivot))
    k = len(idx)
    axis, c, s = _vertex_array(axis, k, "axis"), _vertex_array(c, k, "c", 0), _vertex_array(s, k, "s", 0)
    if x.ndim != 2 or x.shape[1] != 3 or pivot.shape != (k,) or (
            k and (min(idx.min(), pivot.min()) < 0 or max(idx.max(), pivot.max()) >= len(x))):
        raise ValueError(f"root turn: x must be (nv, 3) and idx, pivot ({k},) index it, got {x.shape}, "
                         f"{pivot.shape}")
    y = x.copy()
    _turn_vertices(x, idx, pivot, axis, c, s, y)
    return y


@_jit
def _vertex_terms(x, xhat, mass, f_ext, free, dt2, potentials, gradient):
    scale = 0.5 / dt2
    for v in range(x.shape[0]):
        if not free[v]:
            potentials[v] = 0.0
            gradient[v, 0] = gradient[v, 1] = gradient[v, 2] = 0.0
            continue
        d0, d1, d2 = x[v, 0] - xhat[v, 0], x[v, 1] - xhat[v, 1], x[v, 2] - xhat[v, 2]
        potentials[v] = (scale * mass[v]) * ((d0 * d0 + d1 * d1) + d2 * d2) - (
            (f_ext[v, 0] * x[v, 0] + f_ext[v, 1] * x[v, 1]) + f_ext[v, 2] * x[v, 2])
        gradient[v, 0] = ((mass[v] * d0) / dt2 + 0.0) - f_ext[v, 0]
        gradient[v, 1] = ((mass[v] * d1) / dt2 + 0.0) - f_ext[v, 1]
        gradient[v, 2] = ((mass[v] * d2) / dt2 + 0.0) - f_ext[v, 2]


def vertex_terms(x, xhat, mass, f_ext, free, dt):
    """Per vertex the terms of one vertex of G, inertia and gravity (the head's penalty
    aside): (potentials (nv,), gradient (nv, 3)), zero on the vertices not ``free``:
    potential (0.5 / dt^2) m |x - xhat|^2 - f_ext . x, gradient m (x - xhat) / dt^2 -
    f_ext (with the elastic gradient 0 added, as :meth:`lc_petsc.integrator.Integrator.
    gradient` adds it).  :func:`vertex_terms_numpy` bit for bit, in one pass (NumPy's
    row sums ``np.sum(..., axis=1)`` on (nv, 3) arrays were the larger part of the root
    turn's guard on hairball10)."""
    x = np.ascontiguousarray(x, np.float64)
    nv = len(x)
    xhat, f_ext = _vertex_array(xhat, nv, "xhat"), _vertex_array(f_ext, nv, "f_ext")
    mass = _vertex_array(mass, nv, "mass", 0)
    free = np.ascontiguousarray(free, np.bool_)
    if x.shape != (nv, 3) or free.shape != (nv,):
        raise ValueError(f"root turn: x (nv, 3) and free (nv,) must match, got {x.shape}, {free.shape}")
    potentials, gradient = np.empty(nv), np.empty((nv, 3))
    _vertex_terms(x, xhat, mass, f_ext, free, float(dt) ** 2, potentials, gradient)
    return potentials, gradient


def vertex_terms_numpy(x, xhat, mass, f_ext, free, dt):
    """:func:`vertex_terms` in NumPy (the reference)."""
    d = x - xhat
    potentials = np.where(free, 0.5 / dt ** 2 * mass * np.sum(d * d, axis=1) - np.sum(f_ext * x, axis=1), 0.0)
    gradient = mass[:, None] * (x - xhat) / dt ** 2 + np.zeros_like(x) - f_ext
    gradient[~free] = 0.0
    return potentials, gradient


def warm_up():
    """Compile (or load from the cache) the turn's kernels (:func:`lc_petsc.elements.
    compiled.warm_up` runs this: in turn over the ranks, before the first frame)."""
    layout = turn_layout(np.array([0.0, 1.0]), np.zeros(2, np.int64), np.array([0, 2]), np.arange(2),
                         np.array([0.0, 1.0]))
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    turn_sums(layout, x, x, np.ones(2), x)
    turn_curvature(np.eye(3)[None], np.eye(3)[None], np.ones((3, 1, 3)), np.ones((1, 3)), np.zeros(1, np.int64))
    turn_pcg(np.eye(3)[None], np.eye(3)[None], np.ones((1, 3)), np.ones(1, bool))
    turn_vertices(x, np.array([1]), np.array([0]), np.array([[0.0, 0.0, 1.0]]), np.ones(1), np.zeros(1))
    turn_copies(layout, x, np.eye(3)[None])
    vertex_terms(x, x, np.ones(2), x, np.ones(2, bool), 1.0)
