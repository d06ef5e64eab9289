"""Compiled (Numba) conservative advancement of segment pairs for the ccd step limiter.

The same advancement as :func:`lc_petsc.elements.segment_ccd.safe_fraction` (the tested
NumPy reference; ``tests/contact/test_ccd.py`` checks this against it and against
sampled paths), pair by pair in a compiled loop, so a pair may take up to
``max_steps`` (default 10,000) steps instead of a vectorised pass of 100: pairs sliding
along each other close by, for which the motion bound is far from tight, are resolved
here instead of by Tight-Inclusion (which the limiter no longer uses: at a positive
minimum distance it is not a safe bound, see docs/contact.md).  A pair that runs out of
steps keeps the last t reached, which is safe (d >= m on [0, t]).

Compiled on first use and cached on disk like :mod:`lc_petsc.elements.compiled`
(strict IEEE arithmetic).  No PETSc, no MPI.

Layout: pairs index four points of vertex arrays (``inv`` (k, 4) into ``S``, ``E``
(nv, 3): segment A = points 0, 1, segment B = points 2, 3), so the limiter never
builds per-pair copies of its positions.
"""

from __future__ import annotations

import math

import numpy as np

from lc_petsc.elements.compiled import _jit, _vcross, _vdot, _vnorm, _vsub
from lc_petsc.elements.segment_contact import PARALLEL_TOL

#: steps of conservative advancement per pair (and per call)
MAX_STEPS = 10000

_TINY = float(np.finfo(np.float64).tiny)
#: boxes touching more grid cells than this are tested against all boxes (box_pairs)
BIG_CELLS = 512
#: box_pairs' grid cell: this many times the median box extent
CELL_FACTOR = 2.0
#: box_pairs pairs runs of up to this many consecutive boxes of one group (a strand's
#: consecutive segments) as one box first, then their members (1: no runs)
CHUNK = 8


@_jit
def _vlerp(S, E, i, t):
    """S[i] + t (E[i] - S[i])."""
    return (S[i, 0] + t * (E[i, 0] - S[i, 0]), S[i, 1] + t * (E[i, 1] - S[i, 1]),
            S[i, 2] + t * (E[i, 2] - S[i, 2]))


@_jit
def _vclip01(v):
    """v clipped to [0, 1] as np.clip does it (-0.0 -> +0.0, NaN stays NaN)."""
    return 0.0 if v <= 0.0 else (1.0 if v >= 1.0 else v)


@_jit
def _vclosest(x0, x1, x2, x3):
    """(s, t, d1, d2): the closest parameters of segments x0 x1 and x2 x3, the clamped
    algorithm (and parallel rule) of :func:`segment_contact.closest_points`, and the
    segments' vectors d1 = x1 - x0, d2 = x3 - x2."""
    d1, d2, r = _vsub(x1, x0), _vsub(x3, x2), _vsub(x0, x2)
    a, e = _vdot(d1, d1), _vdot(d2, d2)
    b, c, f = _vdot(d1, d2), _vdot(d1, r), _vdot(d2, r)
    a_s, e_s = max(a, _TINY), max(e, _TINY)
    denom = max(a * e - b * b, 0.0)
    s = 0.0
    if not denom <= PARALLEL_TOL * a * e:
        s = _vclip01((b * f - c * e) / denom)
    t = (b * s + f) / e_s
    if t < 0.0:
        s = _vclip01(-c / a_s)
    elif t > 1.0:
        s = _vclip01((b - c) / a_s)
    return s, _vclip01(t), d1, d2


@_jit
def _vdistance(x0, x1, x2, x3):
    """Segment-segment distance (:func:`_vclosest`)."""
    s, t, d1, d2 = _vclosest(x0, x1, x2, x3)
    return _vnorm((x0[0] + s * d1[0] - x2[0] - t * d2[0], x0[1] + s * d1[1] - x2[1] - t * d2[1],
                   x0[2] + s * d1[2] - x2[2] - t * d2[2]))


@_jit
def _vpoint_segment(x, a, d):
    """Distance of point x from the segment a + s d, s in [0, 1]."""
    r = _vsub(x, a)
    dd = _vdot(d, d)
    s = _vclip01(_vdot(r, d) / dd) if dd > 0.0 else 0.0
    return _vnorm((r[0] - s * d[0], r[1] - s * d[1], r[2] - s * d[2]))


@_jit
def _vdistance_exact(x0, x1, x2, x3):
    """Segment-segment distance, exact also for nearly parallel pairs: :func:`_vdistance`
    (the same bits) where the clamped algorithm solves its 2x2 system; where it takes the
    parallel rule (s = 0, an upper bound: nearly parallel segments crossing at their
    middles, 1e-6 rad apart, gave 1e-6 instead of 0, and the crossing counter missed
    their crossing) the least of it, the four endpoint-to-segment distances and the
    interior solution along n = d1 x d2 (no cancellation in n, unlike a e - b^2)."""
    d = _vdistance(x0, x1, x2, x3)
    d1, d2 = _vsub(x1, x0), _vsub(x3, x2)
    a, e, b = _vdot(d1, d1), _vdot(d2, d2), _vdot(d1, d2)
    if not max(a * e - b * b, 0.0) <= PARALLEL_TOL * a * e:
        return d
    d = min(d, _vpoint_segment(x0, x2, d2), _vpoint_segment(x1, x2, d2),
            _vpoint_segment(x2, x0, d1), _vpoint_segment(x3, x0, d1))
    n = _vcross(d1, d2)
    nn = _vdot(n, n)
    if nn > 0.0:
        r = _vsub(x2, x0)
        s, u = _vdot(_vcross(r, d2), n) / nn, _vdot(_vcross(r, d1), n) / nn
        if 0.0 <= s <= 1.0 and 0.0 <= u <= 1.0:
            d = min(d, abs(_vdot(r, n)) / math.sqrt(nn))
    return d


@_jit
def _vpair_distance(S, E, p, t, exact=False):
    """Distance of the pair of points p (4,) of the path S -> E at time t
    (:func:`_vdistance`; with ``exact`` :func:`_vdistance_exact`: the crossing counter's)."""
    x0, x1, x2, x3 = _vlerp(S, E, p[0], t), _vlerp(S, E, p[1], t), _vlerp(S, E, p[2], t), _vlerp(S, E, p[3], t)
    return _vdistance_exact(x0, x1, x2, x3) if exact else _vdistance(x0, x1, x2, x3)


@_jit
def _vrel(S, E, p):
    """The motion bound rel = max_ij |D a_i - D b_j| (segment_ccd.relative_motion)."""
    out = 0.0
    for i in range(2):
        for j in range(2, 4):
            a, b = p[i], p[j]
            r = ((E[a, 0] - S[a, 0]) - (E[b, 0] - S[b, 0]), (E[a, 1] - S[a, 1]) - (E[b, 1] - S[b, 1]),
                 (E[a, 2] - S[a, 2]) - (E[b, 2] - S[b, 2]))
            out = max(out, _vnorm(r))
    return out


@_jit
def _vadvance(S, E, p, m, d_start, rel, max_steps, rtol, exact=False):
    """Conservative advancement of pair p at min distance m from its distance d_start
    at t = 0: the largest t in [0, 1] reached with d >= m on [0, t] (see
    segment_ccd.safe_fraction; ``exact``: :func:`_vpair_distance`'s)."""
    gap = d_start - m
    if gap >= rel:
        return 1.0
    tol = max(rtol * m, 1e-300)
    if not gap > rtol * m:
        return 0.0
    t = 0.0
    for _ in range(max_steps):
        t_new = t + gap / rel
        if t_new >= 1.0:
            return 1.0
        t = t_new
        gap = _vpair_distance(S, E, p, t, exact) - m
        if not gap > tol:
            break
    return t


@_jit
def _safe_fraction(S, E, inv, m, max_steps, rtol, exact, out):
    for k in range(inv.shape[0]):
        p = inv[k]
        d = _vpair_distance(S, E, p, 0.0, exact)
        out[k] = _vadvance(S, E, p, m[k], d, _vrel(S, E, p), max_steps, rtol, exact)


@_jit
def _half_gap(X, p, c):
    """Coordinate c of the difference of pair p's segment centres in X."""
    return 0.5 * (X[p[0], c] + X[p[1], c] - X[p[2], c] - X[p[3], c])


#: the limiter's floor for a pair already closer than the floor m at the path's start is
#: half its distance d, but never below HOLD_FLOOR m, nor above d: a pair pushed together
#: in every call (a tangle that the elastic forces pull through itself) was halved in each
#: until round-off let it pass (jitter with self-contact: 0.007 cm at frame 1, 1.6e-16 at
#: frame 45, then crossings); now it is held at HOLD_FLOOR m
HOLD_FLOOR = 1e-3


@_jit
def _limit_pairs(S, E, inv, redo, md, scale, max_steps, rtol, tau, factor, start_distance):
    for q in range(redo.shape[0]):
        k = redo[q]
        p = inv[k]
        tau[k] = 1.0
        factor[k] = 1.0
        # swept spheres: segment X(t) lies within h(t) <= max(h(0), h(1)) of its centre
        # c(t) = c(0) + t Dc, so d(t) >= min_t |cA(t) - cB(t)| - hA - hB (scalars, not
        # lists: a list per pair is a heap allocation, 2.5x the whole test's time)
        w0, w1, w2 = _half_gap(S, p, 0), _half_gap(S, p, 1), _half_gap(S, p, 2)
        v0, v1, v2 = _half_gap(E, p, 0) - w0, _half_gap(E, p, 1) - w1, _half_gap(E, p, 2) - w2
        vv = v0 * v0 + v1 * v1 + v2 * v2
        ts = 0.0
        if vv > 0.0:
            ts = _vclip01(-(w0 * v0 + w1 * v1 + w2 * v2) / vv)
        gc = math.sqrt((w0 + ts * v0) ** 2 + (w1 + ts * v1) ** 2 + (w2 + ts * v2) ** 2)
        h = 0.0
        for a, b in ((p[0], p[1]), (p[2], p[3])):
            hs = math.sqrt((S[b, 0] - S[a, 0]) ** 2 + (S[b, 1] - S[a, 1]) ** 2 + (S[b, 2] - S[a, 2]) ** 2)
            he = math.sqrt((E[b, 0] - E[a, 0]) ** 2 + (E[b, 1] - E[a, 1]) ** 2 + (E[b, 2] - E[a, 2]) ** 2)
            h += 0.5 * max(hs, he)
        if gc - h >= 0.5 * md:
            continue
        # the start S is the same in every round: its distance is kept after the first
        d = start_distance[k]
        if not d >= 0.0:
            d = _vpair_distance(S, E, p, 0.0)
            start_distance[k] = d
        m = min(md, max(0.5 * d, min(d, HOLD_FLOOR * md)))
        rel = _vrel(S, E, p)
        tau[k] = _vadvance(S, E, p, 0.5 * m, d, rel, max_steps, rtol)
        if tau[k] < 1.0:
            factor[k] = _vadvance(S, E, p, m, d, rel, max_steps, rtol) if scale else 0.0


def safe_fraction(start, end, min_distance, max_steps=MAX_STEPS, rtol=1e-3, exact=False):
    """t (n,): the safe path fractions of :func:`segment_ccd.safe_fraction` for pairs
    ``start``, ``end`` (n, 4, 3) at ``min_distance`` (scalar or (n,)), with up to
    ``max_steps`` steps per pair; ``exact``: on :func:`_vdistance_exact` (the crossing
    counter's proof that a pair stays apart)."""
    S = np.ascontiguousarray(start, np.float64).reshape(-1, 3)
    E = np.ascontiguousarray(end, np.float64).reshape(-1, 3)
    if S.shape != E.shape or S.shape[0] % 4:
        raise ValueError(f"compiled_ccd: start {np.shape(start)} and end {np.shape(end)} must both be (n, 4, 3)")
    n = S.shape[0] // 4
    m = np.ascontiguousarray(np.broadcast_to(np.asarray(min_distance, np.float64), (n,)))
    out = np.empty(n)
    _safe_fraction(S, E, np.arange(4 * n, dtype=np.int64).reshape(n, 4), m, int(max_steps), float(rtol), bool(exact),
                   out)
    return out


def limit_pairs(S, E, inv, redo, min_distance, scale, tau, factor, start_distance=None, *, max_steps=MAX_STEPS,
                rtol=1e-3):
    """The limiter's pair test (:meth:`lc_petsc.contact.StrandContact._safe_fractions`)
    on the pairs ``inv[redo]`` (points into the vertex positions ``S`` at the path's
    start and ``E`` at its end, (nv, 3)), written into ``tau`` and ``factor`` (k,) at
    ``redo``: with the pair's floor m = min(``min_distance``, max(d(S) / 2, min(d(S),
    :data:`HOLD_FLOOR` ``min_distance``))), ``tau`` is its
    safe fraction at m / 2 and, where that is below 1, ``factor`` its safe fraction at
    m if ``scale``, else 0 (1 elsewhere).  Pairs whose swept spheres (centre paths,
    radius the larger half length at the ends) stay ``min_distance`` / 2 apart get 1
    without a distance computation.  ``start_distance`` (k,), kept by the caller across
    the rounds of one start S: the pairs' distances d(S), NaN (or negative) where not
    known yet; filled in where computed (the rounds after the first test the same
    pairs from the same start, 0.83x a round's time at 8K)."""
    if start_distance is None:
        start_distance = np.full(len(inv), np.nan)
    if start_distance.shape != (len(inv),) or start_distance.dtype != np.float64:
        raise ValueError(f"limit_pairs: start_distance must be float64 ({len(inv)},), one per pair; "
                         f"got {start_distance.dtype} {start_distance.shape}")
    _limit_pairs(S, E, inv, redo, float(min_distance), bool(scale), int(max_steps), float(rtol), tau, factor,
                 start_distance)


@_jit
def _changed_pairs(inv, changed, out):
    k = 0
    for p in range(inv.shape[0]):
        q = inv[p]
        if changed[q[0]] or changed[q[1]] or changed[q[2]] or changed[q[3]]:
            out[k] = p
            k += 1
    return k


def changed_pairs(inv, changed):
    """Indices (ascending) of the pairs ``inv`` (k, 4) with a point flagged in
    ``changed`` (n,) bool: ``np.flatnonzero(changed[inv].any(axis=1))`` without the
    (k, 4) temporaries."""
    out = np.empty(len(inv), np.int64)
    k = _changed_pairs(np.ascontiguousarray(inv, np.int64), np.ascontiguousarray(changed, np.bool_), out)
    return out[:k]


@_jit
def _point_pairs(inv, start, pairs):
    for k in range(inv.shape[0]):
        for c in range(4):
            start[inv[k, c] + 1] += 1
    for v in range(len(start) - 1):
        start[v + 1] += start[v]
    fill = start[:-1].copy()
    for k in range(inv.shape[0]):
        for c in range(4):
            v = inv[k, c]
            pairs[fill[v]] = k
            fill[v] += 1


def point_pairs(inv, n_points):
    """(start (n_points + 1,), pairs (4k,)): the pairs of ``inv`` (k, 4) (points < n_points)
    at point v are pairs[start[v]:start[v + 1]] (a counting sort; a pair once per
    occurrence), for :func:`pairs_at_points`."""
    inv = np.ascontiguousarray(inv, np.int64)
    start = np.zeros(int(n_points) + 1, np.int64)
    pairs = np.empty(inv.size, np.int64)
    _point_pairs(inv, start, pairs)
    return start, pairs


@_jit
def _pairs_at_points(start, pairs, points, seen, out):
    k = 0
    for v in points:
        for q in range(start[v], start[v + 1]):
            p = pairs[q]
            if not seen[p]:
                seen[p] = True
                out[k] = p
                k += 1
    for q in range(k):
        seen[out[q]] = False
    return k


def pairs_at_points(incidence, points, seen):
    """The pairs (each once, in no set order) with one of ``points`` (int array) among
    their points, from the ``incidence`` (start, pairs) of :func:`point_pairs`: the work
    is the points' pairs, not all pairs (:func:`changed_pairs`).  ``seen`` (k,) bool all
    False, a work array (left all False)."""
    start, pairs = incidence
    points = np.ascontiguousarray(points, np.int64)
    out = np.empty(min(len(seen), int(np.sum(start[points + 1] - start[points]))), np.int64)
    return out[:_pairs_at_points(start, pairs, points, seen, out)]


@_jit
def _pair_rows(g, H, owner_a, owner_b, rows):
    m = g.shape[0]
    for side in range(2):
        o = 2 * side
        for p in range(m):
            r = side * m + p
            for a in range(2):
                for c in range(3):
                    rows[r, 3 * a + c] = g[p, o + a, c]
            for c in range(3):
                for k in range(3):
                    rows[r, 6 + 3 * c + k] = H[p, 3 * o + c, 3 * o + k]
                    rows[r, 15 + 3 * c + k] = H[p, 3 * o + c, 3 * o + 3 + k]
                    rows[r, 24 + 3 * c + k] = H[p, 3 * o + 3 + c, 3 * o + 3 + k]
            same = owner_a[p] == owner_b[p]
            rows[r, 33] = 2.0 if same else 0.0
            rows[r, 34] = 0.0 if same else 2.0


def pair_rows(g, H, owner_a, owner_b):
    """The contact assembly's per-segment rows (2m, 35) of m pairs: row p (segment A of
    pair p) and m + p (segment B), each its gradient (6: its two vertices' of g (m, 4,
    3)), its own blocks of the pair Hessian H (m, 12, 12): (0, 0), (0, 1), (1, 1) (9
    each, row-major), and the preallocation counts 2, 0 (both segments on one rank,
    ``owner_a`` == ``owner_b`` (m,)) or 0, 2."""
    m = len(g)
    rows = np.empty((2 * m, 35))
    _pair_rows(np.ascontiguousarray(g, np.float64), np.ascontiguousarray(H, np.float64),
               np.ascontiguousarray(owner_a, np.int64), np.ascontiguousarray(owner_b, np.int64), rows)
    return rows


#: conservative-advancement steps of the crossing counter's screen before a pair is
#: left to Tight-Inclusion
SCREEN_STEPS = 64


@_jit
def _screen_paths(S, E, a, b, keep, d_end):
    for k in range(len(a)):
        p = (a[k], a[k] + 1, b[k], b[k] + 1)
        d_end[k] = _vpair_distance(S, E, p, 1.0, True)
        scale = 0.0
        for q in range(4):
            for c in range(3):
                scale = max(scale, abs(S[p[q], c]), abs(E[p[q], c]))
        floor = 1e-12 * (scale + 1.0)          # closer than this counts as touching
        rel = _vrel(S, E, p)
        # conservative advancement at distance 0: d(t') >= d(t) - rel (t' - t) on the
        # straight paths, so a pair whose steps reach t = 1 never touches; each step is a
        # hair shorter than the bound allows, and a pair that gets within the floor or
        # runs out of steps goes to Tight-Inclusion, which decides; the floor in the proof
        # covers d's round-off near t = 1, where rel (1 - t) is as small (a vertex arriving
        # head-on at the other segment's vertex at t = 1 was dropped)
        t, d, keep[k] = 0.0, _vpair_distance(S, E, p, 0.0, True), True
        for _ in range(SCREEN_STEPS):
            if d <= floor:
                break
            if d - floor >= rel * (1.0 - t) * (1.0 + 1e-9):
                keep[k] = False
                break
            t += d / rel * (1.0 - 1e-9)
            d = _vpair_distance(S, E, p, t, True)


def screen_paths(start, end, pairs):
    """(may_meet (k,) bool, end distance (k,)) of the segment pairs ``pairs`` (k, 2) of
    first vertices (segments (a, a + 1), (b, b + 1)) on the straight paths start -> end
    (n, 3): ``may_meet`` is False where conservative advancement at distance 0 (the
    motion bound of :func:`segment_ccd.tight_inclusion_toi`'s first test, applied step
    by step, up to SCREEN_STEPS steps) proves the pair never touches, without per-pair
    copies of the points.  Only the others need Tight-Inclusion (1M candidate pairs of
    a 2K hairball step: 2.6 s in NumPy with the first test alone)."""
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    keep, d_end = np.empty(len(pairs), np.bool_), np.empty(len(pairs))
    _screen_paths(np.ascontiguousarray(start, np.float64), np.ascontiguousarray(end, np.float64),
                  np.ascontiguousarray(pairs[:, 0]), np.ascontiguousarray(pairs[:, 1]), keep, d_end)
    return keep, d_end


@_jit
def _quad_distance(Y, q):
    """Distance of the segments of rows q[0], q[1] and q[2], q[3] of Y (first 3 columns)."""
    return _vdistance((Y[q[0], 0], Y[q[0], 1], Y[q[0], 2]), (Y[q[1], 0], Y[q[1], 1], Y[q[1], 2]),
                      (Y[q[2], 0], Y[q[2], 1], Y[q[2], 2]), (Y[q[3], 0], Y[q[3], 1], Y[q[3], 2]))


@_jit
def _segment_distance(P, a, b):
    """Distance of segments a and b of P (m, 2, 3) (:func:`_vdistance`)."""
    return _vdistance((P[a, 0, 0], P[a, 0, 1], P[a, 0, 2]), (P[a, 1, 0], P[a, 1, 1], P[a, 1, 2]),
                      (P[b, 0, 0], P[b, 0, 1], P[b, 0, 2]), (P[b, 1, 0], P[b, 1, 1], P[b, 1, 2]))


@_jit
def _pair_distances(P, i, j, out):
    for k in range(len(i)):
        out[k] = _segment_distance(P, i[k], j[k])


def pair_distances(P, i, j):
    """Distances (k,) of the segment pairs (i[k], j[k]) of P (m, 2, 3): the arithmetic of
    the separation's :class:`PairDistances` on P's points 2i, 2i + 1, 2j, 2j + 1, without
    a (k, 4) index array (building one took as long as the distances at 8K)."""
    out = np.empty(len(i))
    _pair_distances(np.ascontiguousarray(P, np.float64), np.ascontiguousarray(i, np.int64),
                    np.ascontiguousarray(j, np.int64), out)
    return out


@_jit
def _near_pair_distances(P, lo, hi, i, j, grow, ki, kj, d):
    k = 0
    for q in range(len(i)):
        a, b = i[q], j[q]
        if _grown_overlap(lo, hi, a, b, grow):
            ki[k], kj[k], d[k] = a, b, _segment_distance(P, a, b)
            k += 1
    return k


def near_pair_distances(P, lo, hi, i, j, grow):
    """(i, j, d) of the pairs (i[k], j[k]) whose boxes lo, hi (m, 3) grown by ``grow``
    overlap (the grown-box test of :func:`order_candidates`), in their order, with their
    segments' distances in P (m, 2, 3) (:func:`pair_distances`): one pass instead of a
    mask, two gathers and a distance pass."""
    n = len(i)
    ki, kj, d = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n)
    k = _near_pair_distances(np.ascontiguousarray(P, np.float64), np.ascontiguousarray(lo, np.float64),
                             np.ascontiguousarray(hi, np.float64), np.ascontiguousarray(i, np.int64),
                             np.ascontiguousarray(j, np.int64), float(grow), ki, kj, d)
    return ki[:k], kj[:k], d[:k]


@_jit
def _segment_ends(x, seg, out):
    for s in range(seg.shape[0]):
        for e in range(2):
            for c in range(3):
                out[s, e, c] = x[seg[s] + e, c]


def segment_ends(x, seg):
    """(m, 2, 3): the end points x[seg], x[seg + 1] of the segments starting at vertices
    ``seg`` (m,) of x (nv, 3); one pass (NumPy's gather by a (m, 2) index took 9 ms per
    array at 8K)."""
    seg = np.ascontiguousarray(seg, np.int64)
    if len(seg) and (seg.min() < 0 or seg.max() >= len(x) - 1):    # the pass reads without bounds checks
        raise ValueError(f"segment_ends: segment first vertices must lie in [0, {len(x) - 1}), "
                         f"got [{seg.min()}, {seg.max()}]")
    out = np.empty((len(seg), 2, 3))
    _segment_ends(np.ascontiguousarray(x, np.float64), seg, out)
    return out


@_jit
def _segment_points(sv, PS, PT, PH, free, SV, TV, HV, fV):
    for s in range(sv.shape[0]):
        for e in range(2):
            v = sv[s, e]
            for c in range(3):
                SV[v, c], TV[v, c], HV[v, c] = PS[s, e, c], PT[s, e, c], PH[s, e, c]
            fV[v] = free[s, e]


def segment_points(sv, n, PS, PT, PH, free):
    """(SV, TV, HV, fV): the segments' end points by point, for ``sv`` (m, 2) each
    segment end's index among n points and PS, PT, PH (m, 2, 3), free (m, 2) per
    segment end (a point shared by two segments holds the same values in both); one
    pass (NumPy's three fancy assignments per end took 47 ms a call at 8K)."""
    sv = np.ascontiguousarray(sv, np.int64)
    if sv.size and (sv.min() < 0 or sv.max() >= n):          # the pass writes without bounds checks
        raise ValueError(f"segment_points: point indices must lie in [0, {n}), got [{sv.min()}, {sv.max()}]")
    SV, TV, HV = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
    fV = np.empty(n, np.bool_)
    _segment_points(sv, np.ascontiguousarray(PS, np.float64),
                    np.ascontiguousarray(PT, np.float64), np.ascontiguousarray(PH, np.float64),
                    np.ascontiguousarray(free, np.bool_), SV, TV, HV, fV)
    return SV, TV, HV, fV


@_jit
def _refresh_distances(Y, Yp, inv, d, moved, hit_below, count_below, hits):
    for v in range(len(Yp)):
        if Y[v, 0] != Yp[v, 0] or Y[v, 1] != Yp[v, 1] or Y[v, 2] != Yp[v, 2]:
            moved[v] = True
            Yp[v, 0], Yp[v, 1], Yp[v, 2] = Y[v, 0], Y[v, 1], Y[v, 2]
        else:
            moved[v] = False
    n_hit = n_below = 0
    for p in range(len(inv)):
        q = inv[p]
        if moved[q[0]] or moved[q[1]] or moved[q[2]] or moved[q[3]]:
            d[p] = _quad_distance(Y, q)
        if d[p] < hit_below:
            hits[n_hit] = p
            n_hit += 1
        if d[p] < count_below:
            n_below += 1
    return n_hit, n_below


class PairDistances:
    """The separation's pair distances between rounds: per round, the distances of the
    pairs ``inv`` (k, 4) with a point that moved are recomputed
    (:func:`pair_distances`' arithmetic, so the same values to the bit), in one
    compiled pass that also lists the pairs below one threshold and counts those below
    another."""

    def __init__(self, inv, n_points):
        self.inv = np.ascontiguousarray(inv, np.int64).reshape(-1, 4)
        self.d = np.empty(len(inv))
        self.last = np.full((int(n_points), 3), np.nan)     # every point "moved" first
        self.moved = np.empty(int(n_points), np.bool_)
        self.hits = np.empty(len(inv), np.int64)

    def refresh(self, Y, hit_below, count_below):
        """(pairs with d < ``hit_below`` (ascending), number with d < ``count_below``) at the
        points' positions Y (n_points, c >= 3)."""
        if np.ndim(Y) != 2 or len(Y) != len(self.last) or np.shape(Y)[1] < 3:
            raise ValueError(f"PairDistances.refresh: Y must be ({len(self.last)}, >= 3), got {np.shape(Y)}")
        n_hit, n_below = _refresh_distances(np.ascontiguousarray(Y, np.float64), self.last, self.inv, self.d,
                                            self.moved, float(hit_below), float(count_below), self.hits)
        return self.hits[:n_hit].copy(), int(n_below)


@_jit
def _grown_overlap(lo, hi, a, b, grow):
    """Closed boxes a and b of lo, hi, each grown by ``grow`` (< 0: shrunk), overlap."""
    for c in range(3):
        if hi[a, c] + grow < lo[b, c] - grow or hi[b, c] + grow < lo[a, c] - grow:
            return False
    return True


@_jit
def _field_boxes(S, F, seg, lipschitz, m, lo, hi):
    for k in range(seg.shape[0]):
        a, b = seg[k], seg[k] + 1
        ra = F[a, 0] * F[a, 0] + F[a, 1] * F[a, 1] + F[a, 2] * F[a, 2]
        rb = F[b, 0] * F[b, 0] + F[b, 1] * F[b, 1] + F[b, 2] * F[b, 2]
        grow = (0.5 * m + lipschitz * math.sqrt(max(ra, rb))) / (1.0 - lipschitz)
        for c in range(3):
            ea, eb = S[a, c] + F[a, c], S[b, c] + F[b, c]
            lo[k, c] = min(min(S[a, c], S[b, c]), min(ea, eb)) - grow
            hi[k, c] = max(max(S[a, c], S[b, c]), max(ea, eb)) + grow


def field_boxes(S, F, seg, lipschitz, min_distance):
    """:func:`lc_petsc.elements.segment_ccd.field_boxes` (the reference, with the proof)
    of the segments (seg[k], seg[k] + 1) of the vertex positions ``S`` and residuals
    ``F`` (nv, 3), without per-segment copies: (lo, hi) (len(seg), 3)."""
    lo, hi = np.empty((len(seg), 3)), np.empty((len(seg), 3))
    _field_boxes(np.ascontiguousarray(S, np.float64), np.ascontiguousarray(F, np.float64),
                 np.ascontiguousarray(seg, np.int64), float(lipschitz), float(min_distance), lo, hi)
    return lo, hi


@_jit
def _hull_gap(PS, PF, a, b):
    """(gap, slack, rho_a + rho_b, d): a lower bound of the distance between the hulls of
    segments a and b, each the hull of its ends at S (PS) and at S + f (PF, the residual
    T - H), from their projections on the axis of the segments' closest points at S
    (the segments' own distance when f = 0; 0 when they touch), its round-off scale,
    rho the segment's largest |f|, and d the segments' distance at S (:func:`_vdistance`'s
    arithmetic, so equal to the pair test's d(S) bit for bit)."""
    x0 = (PS[a, 0, 0], PS[a, 0, 1], PS[a, 0, 2])
    x1 = (PS[a, 1, 0], PS[a, 1, 1], PS[a, 1, 2])
    x2 = (PS[b, 0, 0], PS[b, 0, 1], PS[b, 0, 2])
    x3 = (PS[b, 1, 0], PS[b, 1, 1], PS[b, 1, 2])
    s, t, d1, d2 = _vclosest(x0, x1, x2, x3)
    n = (x0[0] + s * d1[0] - x2[0] - t * d2[0], x0[1] + s * d1[1] - x2[1] - t * d2[1],
         x0[2] + s * d1[2] - x2[2] - t * d2[2])
    low_a, high_b, rho_a, rho_b, scale = np.inf, -np.inf, 0.0, 0.0, 0.0
    for e in range(2):
        for g in (a, b):
            f = (PF[g, e, 0], PF[g, e, 1], PF[g, e, 2])
            p = _vdot(n, (PS[g, e, 0], PS[g, e, 1], PS[g, e, 2]))
            q = p + _vdot(n, f)
            scale = max(scale, abs(p), abs(q))
            if g == a:
                low_a, rho_a = min(low_a, p, q), max(rho_a, _vnorm(f))
            else:
                high_b, rho_b = max(high_b, p, q), max(rho_b, _vnorm(f))
    nn = _vnorm(n)
    if not nn > 0.0:
        return 0.0, 0.0, rho_a + rho_b, nn
    return (low_a - high_b) / nn, scale / nn, rho_a + rho_b, nn


@_jit
def _order_candidates(ij, n_local, gv, lo, hi, shrink, free, PS, PF, lipschitz, reach, ci, cj, near, dist):
    k = 0
    for q in range(ij.shape[0]):
        a, b = ij[q, 0], ij[q, 1]
        if a >= n_local and b >= n_local:
            continue
        if gv[a] > gv[b]:
            a, b = b, a
        ci[k], cj[k] = a, b
        rigid = not (free[a, 0] or free[a, 1] or free[b, 0] or free[b, 1])
        near[k] = not rigid and _grown_overlap(lo, hi, a, b, -shrink)
        if reach > 0.0:
            dist[k] = np.nan
        if near[k] and reach > 0.0:
            # the boxes are axis-aligned: most of the pairs they keep are segments lying
            # side by side at an angle, whose hulls a separating axis proves farther
            # apart than the reach on every path of the call (segment_ccd.field_boxes'
            # bound, with the hull distance instead of the boxes'); a hair of margin so
            # that round-off cannot drop a pair that comes within reach
            gap, slack, rho, dist[k] = _hull_gap(PS, PF, a, b)
            near[k] = (1.0 - lipschitz) * gap <= (reach + lipschitz * rho) * (1.0 + 1e-9) + 1e-12 * slack
        k += 1
    return k


@_jit
def _kept_pair_points(ci, cj, keep, sv, i, j, inv):
    k = 0
    for q in range(len(ci)):
        if keep[q]:
            i[k], j[k] = ci[q], cj[q]
            inv[k, 0], inv[k, 1], inv[k, 2], inv[k, 3] = sv[ci[q], 0], sv[ci[q], 1], sv[cj[q], 0], sv[cj[q], 1]
            k += 1


def kept_pair_points(ci, cj, keep, sv):
    """(i, j, inv): the candidates ci, cj (k,) where ``keep``, and their points (n, 4):
    the rows of sv (m, 2) (each segment's two points) of i, then of j; one pass (the
    NumPy gathers and concatenation took 0.1 s per call on the 8K hairball)."""
    n = int(np.count_nonzero(keep))
    i, j, inv = np.empty(n, np.int64), np.empty(n, np.int64), np.empty((n, 4), np.int64)
    _kept_pair_points(np.ascontiguousarray(ci, np.int64), np.ascontiguousarray(cj, np.int64),
                      np.ascontiguousarray(keep, np.bool_), np.ascontiguousarray(sv, np.int64), i, j, inv)
    return i, j, inv


@_jit
def _ascending_segment_vertices(gv, V, sv):
    n = 0
    for e in range(len(gv)):
        if e > 0 and gv[e] <= gv[e - 1]:
            return -1
        for c in range(2):
            v = gv[e] + c
            if n == 0 or V[n - 1] != v:
                V[n] = v
                n += 1
            sv[e, c] = n - 1
    return n


def segment_vertices(gv):
    """(V, sv): the segments' vertices gv, gv + 1 (gv (m,) first global vertices) as sorted
    distinct V and each segment's two indices into it, sv (m, 2); ``np.unique(..,
    return_inverse=True)``'s result.  One pass when gv ascends (a rank's segments, then
    its ghosts from the ranks after it: 20 ms of sorting a call at 8K), else NumPy's
    sort."""
    gv = np.ascontiguousarray(gv, np.int64)
    V, sv = np.empty(2 * len(gv), np.int64), np.empty((len(gv), 2), np.int64)
    n = _ascending_segment_vertices(gv, V, sv)
    if n < 0:
        V, sv = np.unique(np.stack([gv, gv + 1], axis=1), return_inverse=True)
        return V, sv.reshape(-1, 2)
    return V[:n].copy(), sv


def order_candidates(ij, n_local, gv, lo, hi, shrink, free, hulls=None):
    """The limiter's candidates from the box pairs ``ij`` (k, 2) of local + ghost segments:
    (ci, cj, near): the pairs with a local segment (index < ``n_local``), the smaller
    first global vertex ``gv`` first, and ``near`` where their boxes lo, hi shrunk by
    ``shrink`` still overlap and a segment has a free vertex (``free`` (m, 2)).
    ``hulls`` (PS, PT, PH, L, reach): the segments' ends (m, 2, 3) at the path's start,
    end and fallback, the field's Lipschitz constant and the pair test's reach m; then
    ``near`` also needs the hulls of the ends at S and S + (T - H) closer than (m + L
    (rho_a + rho_b)) / (1 - L) along the axis of the segments' closest points at S: a
    farther pair stays m apart on every path of the call (the bound of
    :func:`segment_ccd.field_boxes`), so the pair test would give it 1.  Returns (ci, cj,
    near, dist): dist the segments' distance at S where the hulls were tested (the pair
    test's start distance bit for bit, for :func:`limit_pairs`), else NaN."""
    n = len(ij)
    ci, cj, near = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.bool_)
    dist = np.empty(n if hulls is not None else 0)      # a frame end's reused pairs: 7M at 8K
    if hulls is None:
        PS = PT = PH = np.zeros((0, 2, 3))
        lipschitz, reach = 0.0, 0.0
    else:
        PS, PT, PH = (np.ascontiguousarray(a, np.float64) for a in hulls[:3])
        lipschitz, reach = float(hulls[3]), float(hulls[4])
        if not (PS.shape == PT.shape == PH.shape == (len(gv), 2, 3)) or not 0.0 <= lipschitz < 1.0 or not reach > 0.0:
            raise ValueError(f"order_candidates: hulls need PS, PT, PH ({len(gv)}, 2, 3), 0 <= L < 1 and reach > 0; "
                             f"got {PS.shape} {PT.shape} {PH.shape}, L {lipschitz}, reach {reach}")
    # the residuals in one array: the hull test reads each pair's segments at random
    PF = PT - PH
    k = _order_candidates(np.ascontiguousarray(ij, np.int64), int(n_local), np.ascontiguousarray(gv, np.int64),
                          np.ascontiguousarray(lo, np.float64), np.ascontiguousarray(hi, np.float64),
                          float(shrink), np.ascontiguousarray(free, np.bool_), PS, PF, lipschitz, reach,
                          ci, cj, near, dist)
    return ci[:k], cj[:k], near[:k], (dist[:k] if hulls is not None else np.full(k, np.nan))


def warm_up():
    """Compile (or load from the cache) the kernels."""
    S = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 1], [1, 1, 1]])
    safe_fraction(S[None], S[None] + 0.1, 0.01)
    limit_pairs(S, S + 0.1, np.arange(4, dtype=np.int64).reshape(1, 4), np.zeros(1, np.int64), 0.01,
                True, np.ones(1), np.ones(1))
    box_pairs(S, S + 1.0, np.arange(4))
    box_pairs(S, S + 1.0, np.zeros(4, np.int64), np.zeros((4, 2)), 0.0, n_local=2)     # one run, self pairs
    seg = np.array([0, 2])
    lo, hi = field_boxes(S, S, seg, 0.1, 0.01)
    order_candidates(np.array([[0, 1]]), 1, seg, lo, hi, 0.0, np.ones((2, 2), bool))
    P2 = S.reshape(2, 2, 3)
    order_candidates(np.array([[0, 1]]), 1, seg, lo, hi, 0.0, np.ones((2, 2), bool), (P2, P2, P2, 0.1, 0.01))
    pair_distances(P2, seg[:1] // 2, seg[1:] // 2)
    screen_paths(S, S + 0.1, np.array([[0, 2]]))
    segment_points(np.arange(4, dtype=np.int64).reshape(2, 2), 4, P2, P2, P2, np.ones((2, 2), bool))
    near_pair_distances(P2, lo, hi, seg[:1] // 2, seg[1:] // 2, 0.01)
    segment_ends(S, seg[:1])
    changed_pairs(np.arange(4, dtype=np.int64).reshape(1, 4), np.ones(4, bool))
    pair_rows(np.zeros((1, 4, 3)), np.zeros((1, 12, 12)), seg[:1], seg[:1])
    corner_cells(S, S + 1.0, np.zeros(3), 0.5, np.array([4, 4, 4]))
    state = np.zeros((4, 5))
    shift_and_bound(state[:, :3], state[:, 1:], seg, np.zeros(2, np.int64), np.ones(2), np.ones(2), np.ones(4),
                    False, 1)
    shift_and_bound(state[:, :3], np.zeros((4, 4)), seg, np.zeros(2, np.int64), np.ones(2), np.ones(2),
                    np.ones(4), False, 1, EdgeWork(seg, 4))
    PairDistances(np.arange(4, dtype=np.int64).reshape(1, 4), 4).refresh(state, 0.1, 0.1)
    smooth_fractions(np.ones(4), S, seg, np.ones(2), np.ones(4, bool), 0.02)
    shrink_and_smooth(np.ones(4), np.zeros(4), np.zeros(4, bool), edge_slack(S, seg, np.ones(2), 0.02), seg,
                      np.array([0, 2]), np.zeros(4, np.int64), np.ones(4, bool))
    bound_edge_lengths(S, seg, np.zeros(2, np.int64), np.ones(2), np.ones(2), np.ones(4), None, 1)
    quad = np.arange(4, dtype=np.int64).reshape(1, 4)
    pairs_at_points(point_pairs(quad, 4), np.arange(2), np.zeros(1, bool))
    kept_pair_points(np.zeros(1, np.int64), np.ones(1, np.int64), np.ones(1, bool), quad.reshape(2, 2))
    segment_vertices(seg)


@_jit
def _cell_of(p, i, origin, cell, dims):
    """The cell (3 ints) holding point p[i], clamped to the grid."""
    return (min(max(int(math.floor((p[i, 0] - origin[0]) / cell)), 0), dims[0] - 1),
            min(max(int(math.floor((p[i, 1] - origin[1]) / cell)), 0), dims[1] - 1),
            min(max(int(math.floor((p[i, 2] - origin[2]) / cell)), 0), dims[2] - 1))


@_jit
def _corner_cells(lo, hi, origin, cell, dims, out):
    for i in range(lo.shape[0]):
        a0, a1, a2 = _cell_of(lo, i, origin, cell, dims)
        b0, b1, b2 = _cell_of(hi, i, origin, cell, dims)
        for c in range(8):
            v0 = b0 if c & 1 else a0
            v1 = b1 if c & 2 else a1
            v2 = b2 if c & 4 else a2
            out[i, c] = (v0 * dims[1] + v1) * dims[2] + v2


def corner_cells(lo, hi, origin, cell, dims):
    """Flat ids (n, 8) of the grid cells holding the 8 corners of the boxes lo, hi (n, 3)
    (corner c takes hi on axis k where bit k of c is set), on the grid of cubic cells of
    side ``cell`` from ``origin`` (3,), ``dims`` (3,) cells per axis, clamped to it."""
    lo = np.ascontiguousarray(lo, np.float64)
    out = np.empty((len(lo), 8), np.int64)
    _corner_cells(lo, np.ascontiguousarray(hi, np.float64), np.ascontiguousarray(origin, np.float64),
                  float(cell), np.ascontiguousarray(dims, np.int64), out)
    return out


# ---------------------------------------------------------------- broad phase
@_jit
def _box_cells(lo, hi, origin, cell, dims):
    """Per box the first and last cell index per axis (n, 6) and its number of cells."""
    n = lo.shape[0]
    rng = np.empty((n, 6), np.int64)
    count = np.empty(n, np.int64)
    for i in range(n):
        c = 1
        for a in range(3):
            x0 = int(math.floor((lo[i, a] - origin[a]) / cell))
            x1 = int(math.floor((hi[i, a] - origin[a]) / cell))
            x0 = min(max(x0, 0), dims[a] - 1)
            x1 = min(max(x1, x0), dims[a] - 1)
            rng[i, a], rng[i, 3 + a] = x0, x1
            c *= x1 - x0 + 1
        count[i] = c
    return rng, count


@_jit
def _arc_gap(arc, i, j):
    """The length of strand between segments i and j of one wisp (< 0 for one segment)."""
    return max(arc[j, 0] - arc[i, 1], arc[i, 0] - arc[j, 1])


@_jit
def _radix_order(keys, bits):
    """Stable argsort of non-negative int keys < 2**bits: LSD radix sort, 15-bit digits
    (Numba's argsort took 0.16 s for the 480k cell entries of the 2K hairball)."""
    n = keys.shape[0]
    order = np.arange(n)
    tmp = np.empty(n, np.int64)
    shift = 0
    while shift < bits:
        cnt = np.zeros(32769, np.int64)
        for k in range(n):
            cnt[((keys[order[k]] >> shift) & 32767) + 1] += 1
        for d in range(32768):
            cnt[d + 1] += cnt[d]
        for k in range(n):
            o = order[k]
            d = (keys[o] >> shift) & 32767
            tmp[cnt[d]] = o
            cnt[d] += 1
        order, tmp = tmp, order
        shift += 15
    return order


@_jit
def _grid_entries(lo, hi, group, origin, cell, dims):
    """The grid of the broad phase: each box listed in every cell it touches, in cell
    order (a cell's boxes by ascending index: listed in index order, and the radix sort
    is stable): (keys, ids, B (6, entries) their boxes (one row per bound and axis),
    R (3, entries) their lower cells, G their groups, big (n,)): boxes touching more
    than BIG_CELLS cells are not listed (big, tested against every box instead)."""
    rng, count = _box_cells(lo, hi, origin, cell, dims)
    n = count.shape[0]
    big = count > BIG_CELLS
    total = 0
    for i in range(n):
        if big[i]:
            count[i] = 0
        total += count[i]
    keys = np.empty(total, np.int64)
    ids = np.empty(total, np.int64)
    k = 0
    for i in range(n):
        if big[i]:
            continue
        for x in range(rng[i, 0], rng[i, 3] + 1):
            for y in range(rng[i, 1], rng[i, 4] + 1):
                for z in range(rng[i, 2], rng[i, 5] + 1):
                    keys[k] = (x * dims[1] + y) * dims[2] + z
                    ids[k] = i
                    k += 1
    bits = 1
    while (1 << bits) < dims[0] * dims[1] * dims[2]:
        bits += 1
    order = _radix_order(keys, bits)
    # the entries' boxes, lower cells and groups copied in cell order: the pair loop
    # streams memory, and its overlap test vectorises
    keys, ids = keys[order], ids[order]
    B = np.empty((6, total))
    R = np.empty((3, total), np.int64)
    G = np.empty(total, np.int64)
    for k in range(total):
        i = ids[k]
        for a in range(3):
            B[a, k], B[3 + a, k], R[a, k] = lo[i, a], hi[i, a], rng[i, a]
        G[k] = group[i]
    return keys, ids, B, R, G, big


@_jit
def _cell_pairs(keys, ids, B, R, G, arc, min_gap, n_local, dims, p, budget, hit, out, found):
    """The overlapping pairs (i < j) of the grid's cells (:func:`_grid_entries`), from
    entry ``p`` on (a cell's first, or one inside a cell to resume it) until about
    ``budget`` box tests are done: pairs are tested within a cell and reported once, in
    the cell holding the lower corner of their intersection.  Pairs of one group are
    skipped unless their gap along the strand (``arc``, see box_pairs) is at least
    ``min_gap``, and pairs of two boxes at or after ``n_local`` always.  Returns (out,
    found, the entry to resume from: len(keys) when done); ``out`` holds the pairs in
    its first ``found`` rows (grown when full), ``hit`` is scratch (entries,)."""
    total = keys.shape[0]
    lx, ly, lz, hx, hy, hz = B[0], B[1], B[2], B[3], B[4], B[5]
    skip_runs = min_gap == np.inf   # no pair of one group at all
    work = 0
    while p < total and work < budget:
        key = keys[p]
        stop = p + 1
        while stop < total and keys[stop] == key:
            stop += 1
        cx, cy, cz = key // (dims[1] * dims[2]), (key // dims[2]) % dims[1], key % dims[2]
        while p < stop and work < budget:
            i = ids[p]
            if i >= n_local:        # the rest of the cell are ghosts too
                p = stop
                break
            q0 = p + 1
            if skip_runs:           # skip the run of p's group
                while q0 < stop and G[q0] == G[p]:
                    q0 += 1
            work += stop - q0 + 1
            plx, ply, plz, phx, phy, phz = lx[p], ly[p], lz[p], hx[p], hy[p], hz[p]
            hits = 0
            for q in range(q0, stop):   # closed boxes overlap: the entries listed, no branch
                hit[hits] = q
                hits += not ((phx < lx[q]) | (hx[q] < plx) | (phy < ly[q]) | (hy[q] < ply) |
                             (phz < lz[q]) | (hz[q] < plz))
            work += hits            # each candidate's cell test (and a pair's writing)
            r0, r1, r2 = R[0, p], R[1, p], R[2, p]
            for h in range(hits):
                q = hit[h]
                # report in the cell of the intersection's lower corner only
                if max(r0, R[0, q]) != cx or max(r1, R[1, q]) != cy or max(r2, R[2, q]) != cz:
                    continue
                j = ids[q]
                if G[p] == G[q] and _arc_gap(arc, i, j) < min_gap:
                    continue
                if found == out.shape[0]:
                    out = _push_pair(out, found, i, j)
                else:   # written here: a call per pair cost 30 ns (the returned array's refcount)
                    out[found, 0], out[found, 1] = min(i, j), max(i, j)
                found += 1
            p += 1
    return out, found, p


@_jit
def _big_pairs(lo, hi, group, arc, min_gap, n_local, big, i, budget, out, found):
    """The pairs of the big boxes (a wild iterate's segment) against all boxes, each pair
    once, from box ``i`` on until about ``budget`` box tests are done: (out, found, the
    box to resume from: n when done)."""
    n = lo.shape[0]
    work = 0
    while i < n and work < budget:
        work += 1
        if big[i]:
            work += n
            for j in range(n):
                if j == i or (big[j] and j < i) or (i >= n_local and j >= n_local) or \
                        (group[i] == group[j] and _arc_gap(arc, i, j) < min_gap):
                    continue
                if _grown_overlap(lo, hi, i, j, 0.0):
                    out = _push_pair(out, found, i, j)
                    found += 1
        i += 1
    return out, found, i


@_jit
def _push_pair(out, found, i, j):
    """``out`` (k, 2) with row ``found`` set to (min(i, j), max(i, j)), copied into an
    array twice as long first when full (one pass: a second pass with room cost 0.7 s
    when the 8K hairball's frame path check found 5M pairs for 430k boxes)."""
    if found == out.shape[0]:
        grown = np.empty((2 * out.shape[0] + 16, 2), np.int64)
        grown[:found] = out
        out = grown
    out[found, 0], out[found, 1] = min(i, j), max(i, j)
    return out


@_jit
def _run_starts(group, n_local, size):
    """Starts (c + 1,) of the runs of up to ``size`` consecutive boxes of one group, none
    across ``n_local``; the last entry is the number of boxes."""
    n = group.shape[0]
    start = np.empty(n + 1, np.int64)
    c, i = 0, 0
    while i < n:
        start[c] = i
        j = i + 1
        while j < n and j - i < size and group[j] == group[i] and j != n_local:
            j += 1
        c += 1
        i = j
    start[c] = n
    return start[:c + 1].copy()


@_jit
def _run_boxes(lo, hi, arc, start):
    """Per run: its members' bounding box (lo, hi) (c, 3) (a NaN bound propagates) and
    (the latest start, the earliest end) of their arcs, so that _arc_gap of two runs is
    the largest gap of a pair of their members ((inf, -inf) if an arc is NaN: its pairs
    are kept, as a NaN gap keeps a pair)."""
    c = start.shape[0] - 1
    clo, chi, carc = np.empty((c, 3)), np.empty((c, 3)), np.empty((c, 2))
    for r in range(c):
        f = start[r]
        for a in range(3):
            lo_a, hi_a = lo[f, a], hi[f, a]
            for i in range(f + 1, start[r + 1]):     # a NaN, once taken, stays
                if lo_a == lo_a and not lo[i, a] >= lo_a:
                    lo_a = lo[i, a]
                if hi_a == hi_a and not hi[i, a] <= hi_a:
                    hi_a = hi[i, a]
            clo[r, a], chi[r, a] = lo_a, hi_a
        a0, a1 = -np.inf, np.inf
        for i in range(f, start[r + 1]):
            if not (arc[i, 0] == arc[i, 0] and arc[i, 1] == arc[i, 1]):
                a0, a1 = np.inf, -np.inf        # a NaN gap keeps a pair: so does the run's
                break
            a0, a1 = max(a0, arc[i, 0]), min(a1, arc[i, 1])
        carc[r, 0], carc[r, 1] = a0, a1
    return clo, chi, carc


@_jit
def _runs_by_first(cp, n_runs):
    """The run pairs cp (k, 2) ordered by their first run (counting sort, stable)."""
    count = np.zeros(n_runs + 1, np.int64)
    for q in range(cp.shape[0]):
        count[cp[q, 0] + 1] += 1
    for r in range(n_runs):
        count[r + 1] += count[r]
    out = np.empty_like(cp)
    for q in range(cp.shape[0]):
        a = cp[q, 0]
        out[count[a]] = cp[q]
        count[a] += 1
    return out


@_jit
def _vbox_overlap(l0, l1, l2, h0, h1, h2, Q, b):
    """The closed box lo (l0, l1, l2), hi (h0, h1, h2) and Q[b] (a row lo then hi)
    overlap; no branch."""
    return not ((h0 < Q[b, 0]) | (Q[b, 3] < l0) | (h1 < Q[b, 1]) | (Q[b, 4] < l1) | (h2 < Q[b, 2]) | (Q[b, 5] < l2))


@_jit
def _vrows_overlap(P, a, Q, b):
    """Closed boxes P[a] and Q[b] (rows lo then hi) overlap; no branch."""
    return _vbox_overlap(P[a, 0], P[a, 1], P[a, 2], P[a, 3], P[a, 4], P[a, 5], Q, b)


@_jit
def _member_pairs(cp, start, box, run_box, group, arc, min_gap, q, budget, out, found):
    """The overlapping member pairs (i < j) of the run pairs cp (k, 2) (first run
    ascending) from run pair ``q`` on until about ``budget`` box tests are done (pairs of
    one group with an arc gap of at least ``min_gap``): each run's members are first
    tested against the other run's box.  ``box`` (n, 6) and ``run_box`` (c, 6): lo then
    hi.  Returns (out, found, the run pair to resume from: k when done), ``out`` grown
    when full."""
    width = 0
    for r in range(start.shape[0] - 1):
        width = max(width, start[r + 1] - start[r])
    ia, jb = np.empty(width, np.int64), np.empty(width, np.int64)
    work = 0
    while q < cp.shape[0] and work < budget:
        A, B = cp[q, 0], cp[q, 1]
        q += 1
        work += 1 + start[A + 1] - start[A]
        na = 0
        for i in range(start[A], start[A + 1]):
            ia[na] = i
            na += _vrows_overlap(box, i, run_box, B)
        if na == 0:
            continue
        nb = 0
        for j in range(start[B], start[B + 1]):
            jb[nb] = j
            nb += _vrows_overlap(box, j, run_box, A)
        work += start[B + 1] - start[B] + na * nb
        if found + na * nb > out.shape[0]:     # room for all, checked once per run pair
            grown = np.empty((2 * out.shape[0] + na * nb, 2), np.int64)
            grown[:found] = out[:found]
            out = grown
        one_group = group[start[A]] == group[start[B]]
        for a in range(na):
            i = ia[a]
            l0, l1, l2, h0, h1, h2 = box[i, 0], box[i, 1], box[i, 2], box[i, 3], box[i, 4], box[i, 5]
            for b in range(nb):
                j = jb[b]
                out[found, 0], out[found, 1] = i, j      # runs ascending: i < j
                # written first, kept without a branch if the boxes overlap and, in one
                # group, not gap < min_gap (as the grid's loop: a NaN gap keeps the pair)
                found += _vbox_overlap(l0, l1, l2, h0, h1, h2, box, j) \
                    and (not one_group or not _arc_gap(arc, i, j) < min_gap)
    return out, found, q


@_jit
def _run_self_pairs(start, box, arc, min_gap, n_local, out, found):
    """The overlapping pairs (i < j) inside each run before ``n_local`` with an arc gap
    of at least ``min_gap`` (a run has at most CHUNK members): (out, found)."""
    for r in range(start.shape[0] - 1):
        if start[r] >= n_local:         # a run of ghosts: another rank has it
            break
        for i in range(start[r], start[r + 1]):
            for j in range(i + 1, start[r + 1]):
                if not _arc_gap(arc, i, j) < min_gap and _vrows_overlap(box, i, box, j):
                    out = _push_pair(out, found, i, j)
                    found += 1
    return out, found


#: box tests (and candidates found) between two looks at box_pairs' ``stop``: 0.02-0.2 s
#: a part on this machine (a shuffled 80-wisp step, 11.5M pairs, 12 parts); a wild
#: step's broad phase, one compiled call before, took 83 s (shuffled 200-wisp file)
BOX_TESTS = 1 << 22


def _grid_pairs(lo, hi, group, arc, min_gap, n_local, stop=None):
    """(pairs, their number) of the boxes through a uniform grid fitted to them
    (:func:`_cell_pairs`, then :func:`_big_pairs`), in parts of about BOX_TESTS box
    tests; None once ``stop()`` (looked at before each part) is true."""
    n = len(lo)
    ext = hi - lo
    origin, top = lo.min(axis=0), hi.max(axis=0)
    span = float((top - origin).max())
    cell = max(CELL_FACTOR * float(np.median(np.maximum(np.maximum(ext[:, 0], ext[:, 1]), ext[:, 2]))),
               span / 1024.0, 1e-12)
    dims = (np.floor((top - origin) / cell).astype(np.int64) + 1)
    keys, ids, B, R, G, big = _grid_entries(lo, hi, group, origin, cell, dims)
    out, found, p = np.empty((8 * n, 2), np.int64), 0, 0
    hit = np.empty(len(keys), np.int64)
    min_gap, n_local = float(min_gap), int(n_local)
    while p < len(keys):
        if stop is not None and stop():
            return None
        out, found, p = _cell_pairs(keys, ids, B, R, G, arc, min_gap, n_local, dims, p, BOX_TESTS, hit, out, found)
    i = int(np.argmax(big)) if big.any() else n
    while i < n:
        if stop is not None and stop():
            return None
        out, found, i = _big_pairs(lo, hi, group, arc, min_gap, n_local, big, i, BOX_TESTS, out, found)
    return out, found


def box_pairs(lo, hi, group=None, arc=None, min_gap=0.0, n_local=None, stop=None):
    """Index pairs (k, 2), i < j, of the axis-aligned boxes lo, hi (n, 3) that overlap
    (closed boxes), exact, in an order that is the same for the same input; with
    ``group`` (n,) only pairs of different groups, and with ``arc`` (n, 2) (the rest arc
    length along its wisp at each end of a box's segment) also pairs of one group with
    at least ``min_gap`` of strand between them (self-contact: neighbours along the
    strand are skipped inside the loop, so they cost nothing).  With ``n_local``, only
    pairs with a box before ``n_local`` (a rank's own segments, then its ghosts: no
    ghost-ghost pair, which another rank finds).
    A uniform grid (cell: twice the median box extent, at most 1024 cells per axis) in
    a compiled loop: the cost is the boxes' cell entries and the pairs sharing a cell;
    a box over more than :data:`BIG_CELLS` cells (one wild segment, say) is tested
    against all boxes rather than listed in all its cells.  Runs of up to :data:`CHUNK`
    consecutive boxes of one group (a strand's segments) go through the grid as one box,
    then their members are tested (0.60x the time on the 8K hairball's limiter boxes:
    a strand's neighbouring segments share most cells); the pairs then come run pair by
    run pair.
    The loops run in parts of about :data:`BOX_TESTS` box tests (the same pairs in the
    same order); ``stop`` (callable or None) is looked at before each part, and None is
    returned once it is true (a signal during the end-of-run check: a wild step's boxes
    overlap nearly all others)."""
    lo = np.ascontiguousarray(lo, np.float64)
    hi = np.ascontiguousarray(hi, np.float64)
    n = len(lo)
    if n < 2:
        return np.zeros((0, 2), np.int64)
    g = np.arange(n, dtype=np.int64) if group is None else np.ascontiguousarray(group, np.int64)
    if g.shape != (n,):
        raise ValueError(f"box_pairs: group must be (n_boxes,) = ({n},), got {g.shape}")
    if arc is None:                     # one group: no pair of it
        arc, min_gap = np.zeros((n, 2)), np.inf
    arc = np.ascontiguousarray(arc, np.float64)
    if arc.shape != (n, 2):
        raise ValueError(f"box_pairs: arc must be (n_boxes, 2) = ({n}, 2), got {arc.shape}")
    n_local = n if n_local is None else int(n_local)
    start = _run_starts(g, n_local, CHUNK) if CHUNK > 1 else None
    if start is None or len(start) - 1 > n // 2:        # short runs: the boxes themselves
        grid = _grid_pairs(lo, hi, g, arc, min_gap, n_local, stop)
        return None if grid is None else grid[0][:grid[1]]
    clo, chi, carc = _run_boxes(lo, hi, arc, start)
    first = start[:-1]
    grid = _grid_pairs(clo, chi, g[first], carc, min_gap, int(np.searchsorted(first, n_local)), stop)
    if grid is None:
        return None
    cp = _runs_by_first(grid[0][:grid[1]], len(first))
    box, run_box = np.concatenate([lo, hi], axis=1), np.concatenate([clo, chi], axis=1)
    out, found, q = np.empty((2 * len(cp) + 16, 2), np.int64), 0, 0
    while q < len(cp):
        if stop is not None and stop():
            return None
        out, found, q = _member_pairs(cp, start, box, run_box, g, arc, float(min_gap), q, BOX_TESTS, out, found)
    if not min_gap == np.inf:
        out, found = _run_self_pairs(start, box, arc, float(min_gap), n_local, out, found)
    return out[:found]


# ---------------------------------------------------------------- passes along strands
@_jit
def _edge_slack(F, seg, rest_length, strain):
    """Per edge, the largest difference of its two ends' fractions: strain L / max(|f_i|,
    |f_j|) (inf when neither moves)."""
    m = len(seg)
    c = np.empty(m)
    for e in range(m):
        a = seg[e]
        fmax = max(_vnorm((F[a, 0], F[a, 1], F[a, 2])), _vnorm((F[a + 1, 0], F[a + 1, 1], F[a + 1, 2])))
        c[e] = strain * rest_length[e] / fmax if fmax > 0.0 else np.inf
    return c


@_jit
def _smooth_span(out, c, seg, free, e0, e1, lowered):
    """The min-plus transform of ``out`` in place along the edges e0 .. e1 - 1 (whole
    strands); ``lowered`` is set where a value went down."""
    # a chain's shortest paths are monotone: one pass from each end settles every vertex
    for e in range(e0, e1):
        b = seg[e] + 1
        if free[b] and out[b - 1] + c[e] < out[b]:
            out[b] = out[b - 1] + c[e]
            lowered[b] = True
    for e in range(e1 - 1, e0 - 1, -1):
        a = seg[e]
        if free[a] and out[a + 1] + c[e] < out[a]:
            out[a] = out[a + 1] + c[e]
            lowered[a] = True


@_jit
def _smooth_fractions(beta, F, seg, rest_length, free, strain, out):
    c = _edge_slack(F, seg, rest_length, strain)
    for i in range(len(beta)):
        out[i] = beta[i]
    _smooth_span(out, c, seg, free, 0, len(seg), np.zeros(len(beta), np.bool_))


def smooth_fractions(beta, F, seg, rest_length, free, strain):
    """The largest fractions b <= beta (nv,) with |b_i - b_j| <= strain L / max(|f_i|, |f_j|)
    on every strand edge (i, j) = seg (m,), seg + 1 of rest length L = rest_length (m,),
    F (nv, 3) the vertices' residual motions f; pinned vertices (free (nv,) False) keep
    beta.  Then x_j - x_i = (1 - b_i) (H_j - H_i) + b_i (T_j - T_i) + (b_j - b_i) f_j:
    an edge is no longer than the longer of its two ends' edges plus strain L.  A min-plus
    distance transform along each strand (the fixed point of b_i = min(beta_i,
    b_j + c_ij) over its edges), exact in one forward and one backward pass; ``seg``
    ascending (each strand's edges in order).  Each vertex depends on its own strand only,
    so the result does not depend on the partition.  Returns (nv,)."""
    out = np.empty(len(beta))
    _smooth_fractions(np.ascontiguousarray(beta, np.float64), np.ascontiguousarray(F, np.float64),
                      np.ascontiguousarray(seg, np.int64), np.ascontiguousarray(rest_length, np.float64),
                      np.ascontiguousarray(free, np.bool_), float(strain), out)
    return out


def edge_slack(F, seg, rest_length, strain):
    """(m,): :func:`smooth_fractions`' largest difference of fractions along each edge
    seg (m,), seg + 1, for the residual motions F (nv, 3) (one call's, for
    :func:`shrink_and_smooth`)."""
    return _edge_slack(np.ascontiguousarray(F, np.float64), np.ascontiguousarray(seg, np.int64),
                       np.ascontiguousarray(rest_length, np.float64), float(strain))


def strand_edge_offsets(offsets):
    """(n_strands + 1,): strand w's edges are w's part of the edge list of strands of
    vertices offsets (n_strands + 1,), edges[k[w]:k[w + 1]] (a strand of n > 0 vertices
    has n - 1 edges, an empty one none)."""
    return np.concatenate([[0], np.cumsum(np.maximum(np.diff(offsets), 1) - 1)]).astype(np.int64)


@_jit
def _shrink_and_smooth(beta, shrink, limited, slack, seg, seg_offsets, vertex_wisp, free):
    touched = np.zeros(len(seg_offsets) - 1, np.bool_)
    for v in range(len(beta)):
        if shrink[v] > 0.0:
            beta[v] *= 1.0 - shrink[v]
            limited[v] = True
            touched[vertex_wisp[v]] = True
    for w in range(len(touched)):
        if touched[w]:
            _smooth_span(beta, slack, seg, free, seg_offsets[w], seg_offsets[w + 1], limited)


def shrink_and_smooth(beta, shrink, limited, slack, seg, seg_offsets, vertex_wisp, free):
    """The limiter's round update, in place: beta (nv,) *= 1 - ``shrink`` (nv, >= 0),
    ``limited`` (nv,) bool set where that or the smoothing lowers a fraction, then
    :func:`smooth_fractions` (with the edges' ``slack`` of :func:`edge_slack`) on the
    strands with a vertex shrunk (``vertex_wisp`` (nv,) local strand index, strand w's
    edges seg_offsets[w] .. seg_offsets[w + 1] - 1 of ``seg``).  The other strands are
    left alone: their fractions are unchanged since their last smoothing, and the
    transform is idempotent to the bit (adding a slack >= 0 never rounds below a
    value), so the result is smooth_fractions' on every strand."""
    _shrink_and_smooth(beta, np.ascontiguousarray(shrink, np.float64), limited, np.ascontiguousarray(slack),
                       np.ascontiguousarray(seg, np.int64), np.ascontiguousarray(seg_offsets, np.int64),
                       np.ascontiguousarray(vertex_wisp, np.int64), np.ascontiguousarray(free, np.bool_))


@_jit
def _flag_edge(e, check, todo, n_todo, colour):
    """Queue edge e on its colour's list (once)."""
    if not check[e]:
        check[e] = True
        c = colour[e]
        todo[c, n_todo[c]] = e
        n_todo[c] += 1


@_jit
def _sweep_edges(x, seg, colour, lo, hi, inverse_mass, check, todo, n_todo, max_sweeps):
    """The sweeps of :func:`bound_edge_lengths` from the queued edges ``todo`` (2, m),
    ``n_todo`` (2,) per colour, ``check`` flagging them; ``check`` is left all False."""
    m = len(seg)
    sweeps = 0
    while sweeps < max_sweeps and n_todo[0] + n_todo[1] > 0:
        for c in (0, 1):
            # the edges of one colour share no vertex (their order does not matter), and
            # a projection queues edges of the other colour only: this list stays put
            for k in range(n_todo[c]):
                e = todo[c, k]
                check[e] = False
                a = seg[e]
                d = (x[a + 1, 0] - x[a, 0], x[a + 1, 1] - x[a, 1], x[a + 1, 2] - x[a, 2])
                length = _vnorm(d)
                if not ((length > hi[e] * (1.0 + 1e-12) or length < lo[e] * (1.0 - 1e-12)) and length > 0.0):
                    continue
                wa, wb = inverse_mass[a], inverse_mass[a + 1]
                s = (length - min(max(length, lo[e]), hi[e])) / (length * (wa + wb))
                for k3 in range(3):
                    x[a, k3] += wa * (d[k3] * s)
                    x[a + 1, k3] -= wb * (d[k3] * s)
                # only the edges before and after along the wisp (the other colour) moved
                if e > 0 and seg[e - 1] == a - 1 and inverse_mass[a - 1] + inverse_mass[a] > 0.0:
                    _flag_edge(e - 1, check, todo, n_todo, colour)
                if e + 1 < m and seg[e + 1] == a + 1 and inverse_mass[a + 1] + inverse_mass[a + 2] > 0.0:
                    _flag_edge(e + 1, check, todo, n_todo, colour)
            n_todo[c] = 0
        sweeps += 1
    for c in (0, 1):            # queued when the sweeps ran out
        for k in range(n_todo[c]):
            check[todo[c, k]] = False
    return sweeps


@_jit
def _bound_edge_lengths(x, seg, colour, lo, hi, inverse_mass, check, max_sweeps):
    m = len(seg)
    # work lists per colour: a half sweep visits the edges queued for it, not all m
    todo = np.empty((2, m), np.int64)
    n_todo = np.zeros(2, np.int64)
    for e in range(m):
        if check[e]:
            c = colour[e]
            todo[c, n_todo[c]] = e
            n_todo[c] += 1
    return _sweep_edges(x, seg, colour, lo, hi, inverse_mass, check, todo, n_todo, max_sweeps)


@_jit
def _shift_and_bound(x, shift, edge_at, seg, colour, lo, hi, inverse_mass, all_edges, check, todo, max_sweeps):
    n_todo = np.zeros(2, np.int64)
    for v in range(len(x)):
        if shift[v, 0] != 0.0 or shift[v, 1] != 0.0 or shift[v, 2] != 0.0:
            for k in range(3):
                x[v, k] += shift[v, k]
            if not all_edges:       # the edges ending and starting at v
                for e in (edge_at[v - 1] if v > 0 else -1, edge_at[v]):
                    if e >= 0 and inverse_mass[seg[e]] + inverse_mass[seg[e] + 1] > 0.0:
                        _flag_edge(e, check, todo, n_todo, colour)
    if all_edges:
        for e in range(len(seg)):
            if inverse_mass[seg[e]] + inverse_mass[seg[e] + 1] > 0.0:
                _flag_edge(e, check, todo, n_todo, colour)
    return _sweep_edges(x, seg, colour, lo, hi, inverse_mass, check, todo, n_todo, max_sweeps)


def edge_starts(seg, nv):
    """(nv,): the index of the strand edge that starts at each vertex (edges seg (m,),
    seg + 1), -1 at a strand's last vertex."""
    out = np.full(int(nv), -1, np.int64)
    out[np.asarray(seg, np.int64)] = np.arange(len(seg))
    return out


class EdgeWork:
    """Work arrays of :func:`shift_and_bound`'s moved-vertex form, kept between the
    separation's rounds: per vertex its edge (:func:`edge_starts`), per edge a queued flag
    (all False between calls) and the two colours' queues."""

    def __init__(self, seg, nv):
        self.edge_at = edge_starts(seg, nv)
        self.check = np.zeros(len(seg), np.bool_)
        self.todo = np.empty((2, len(seg)), np.int64)


def shift_and_bound(x, shift, seg, colour, lo, hi, inverse_mass, all_edges, max_sweeps, work=None):
    """The separation's round update, in place: x (nv, 3) += shift (nv, >= 3; its first
    three columns), then :func:`bound_edge_lengths` over every movable edge
    (``all_edges``) or those at a vertex the shift moved.  x may be a strided view (the
    first columns of the separation's state array).  Without ``all_edges`` the edges are
    queued from the moved vertices, not found by a pass over all edges (edges of one
    colour share no vertex, so the queue's order changes no bit).  ``work``: an
    :class:`EdgeWork` of these edges kept between calls (else one is built).  Returns
    the sweeps."""
    if x.dtype != np.float64 or x.ndim != 2 or x.shape[1] != 3 or len(shift) != len(x):
        raise TypeError("shift_and_bound: x must be a float64 (nv, 3) array, shift (nv, >= 3)")
    seg, colour = np.ascontiguousarray(seg, np.int64), np.ascontiguousarray(colour, np.int64)
    lo, hi = np.ascontiguousarray(lo, np.float64), np.ascontiguousarray(hi, np.float64)
    inverse_mass = np.ascontiguousarray(inverse_mass, np.float64)
    if work is None:
        work = EdgeWork(seg, len(x))
    elif len(work.edge_at) != len(x) or len(work.check) != len(seg):
        raise ValueError(f"shift_and_bound: work is for {len(work.edge_at)} vertices and {len(work.check)} "
                         f"edges, not these {len(x)} and {len(seg)}; build EdgeWork(seg, nv) for them")
    return _shift_and_bound(x, shift, work.edge_at, seg, colour, lo, hi, inverse_mass, bool(all_edges),
                            work.check, work.todo, int(max_sweeps))


def bound_edge_lengths(x, seg, colour, lo, hi, inverse_mass, check, max_sweeps):
    """(positions, sweeps): x (nv, 3) with every strand edge (i, j) = seg (m,), seg + 1
    whose length left [lo, hi] (m,) projected back onto the nearer bound, the mass-weighted
    projection of position-based dynamics (inverse_mass (nv,), 0 for pinned vertices,
    which do not move; an edge between two pinned vertices, or of zero length, is left
    alone): each end moves along the edge by its share w_i / (w_i + w_j) of the excess,
    so sum m dx = 0.  Red-black: the edges of one ``colour`` (m,) (their index along the
    wisp, mod 2) share no vertex, so each half sweep is a Jacobi step over that colour;
    after the first, only the neighbours along the wisp of the edges just projected are
    looked at again (no other edge moved).  ``check`` (m,) bool: the edges that may be
    out of their bounds (None: all).  Sweeps until no edge is beyond its bound by more
    than 1e-12 of it, at most ``max_sweeps``.  Each wisp's result depends on that wisp
    alone (the same on any partition)."""
    x = np.array(x, np.float64)
    seg = np.ascontiguousarray(seg, np.int64)
    inverse_mass = np.ascontiguousarray(inverse_mass, np.float64)
    movable = inverse_mass[seg] + inverse_mass[seg + 1] > 0.0
    check = movable if check is None else np.asarray(check, np.bool_) & movable
    sweeps = _bound_edge_lengths(x, seg, np.ascontiguousarray(colour, np.int64),
                                 np.ascontiguousarray(lo, np.float64), np.ascontiguousarray(hi, np.float64),
                                 inverse_mass, check, int(max_sweeps))
    return x, sweeps
