"""Continuous collision detection of segment pairs on linear paths; pure NumPy, batch-first.

A pair moves from ``start`` (n, 4, 3) to ``end`` (n, 4, 3) (segment A = points 0, 1,
segment B = points 2, 3) along the straight path X(t) = start + t (end - start),
t in [0, 1].

Motion bound.  A point of A minus a point of B, (1 - s) a0 + s a1 - (1 - t) b0 - t b1,
is a convex combination of the four corner differences a_i - b_j, so its displacement
along the path is at most ``rel = max_ij |D a_i - D b_j|`` (D = end - start): the
distance d(t) of the pair is 1-Lipschitz in t up to the factor rel,

    d(t') >= d(t) - |t' - t| rel.

A common translation of the pair gives rel = 0 (the distance is constant), so hair
swinging together is not limited, unlike per-vertex displacement bounds.

:func:`safe_fraction` is conservative advancement on that bound: from t = 0, step
t += (d(t) - m) / rel while the gap to the minimum distance ``m`` is positive.  Every
t it reaches is safe (d >= m on [0, t]); it reaches 1 when the pair never comes within
m, and converges to the first time d = m otherwise (linearly; it stops after
``iterations`` steps at a safe t).  Used by :mod:`lc_petsc.contact` to limit every
position update, with IPC Toolkit's Tight-Inclusion CCD (:func:`tight_inclusion_toi`)
for the pairs it leaves unresolved.  The crossing counter (:mod:`lc_petsc.crossings`)
checks paths with Tight-Inclusion at min distance 0 and the NumPy reference of the
tests, independently of this advancement.
"""

from __future__ import annotations

import numpy as np

from lc_petsc.elements.common import check_positions
from lc_petsc.elements.segment_contact import distance

__all__ = ["relative_motion", "safe_fraction", "tight_inclusion_toi"]


def relative_motion(start, end):
    """rel (n,): the largest displacement of a point of A relative to a point of B."""
    D = np.asarray(end, float) - np.asarray(start, float)
    out = np.zeros(len(D))
    for i in (0, 1):
        for j in (2, 3):
            r = D[:, i] - D[:, j]
            out = np.maximum(out, np.sqrt(np.einsum("ij,ij->i", r, r)))
    return out


def safe_fraction(start, end, min_distance, iterations=30, rtol=1e-3):
    """(t (n,), unresolved (n,) bool): the largest path fraction t in [0, 1] found
    such that the pair stays at least ``min_distance`` (scalar or (n,)) apart on
    [0, t].  A pair already closer than ``min_distance`` at the start gets t = 0.
    Advancement stops once the gap is below ``rtol`` min_distance (the pair is then
    within (1 + rtol) min_distance: t is its time of impact to that accuracy) or after
    ``iterations`` steps: those pairs are ``unresolved`` (typically pairs sliding along
    each other close by, for which the bound is far from tight)."""
    S = check_positions(start, 4, "segment_ccd")
    E = check_positions(end, 4, "segment_ccd")
    if S.shape != E.shape:
        raise ValueError(f"segment_ccd: start {S.shape} and end {E.shape} differ in shape")
    n = len(S)
    m = np.broadcast_to(np.asarray(min_distance, float), (n,)).copy()
    if np.any(~np.isfinite(m)) or np.any(m < 0):
        raise ValueError("segment_ccd: min_distance must be finite and >= 0")
    D = E - S
    rel = relative_motion(S, E)
    d_start = distance(S) if n else np.zeros(0)
    t = np.zeros(n)
    unresolved = np.zeros(n, bool)
    gap = d_start - m
    done = gap >= rel                      # never within m (rel = 0 included)
    t[done] = 1.0
    act = np.flatnonzero(~done & (gap > rtol * m))
    tol = np.maximum(rtol * m, 1e-300)
    for _ in range(iterations):
        if len(act) == 0:
            break
        t_new = t[act] + gap[act] / rel[act]
        reach = t_new >= 1.0
        t[act[reach]] = 1.0
        act, t_new = act[~reach], t_new[~reach]
        t[act] = t_new
        if len(act) == 0:
            break
        X = S[act] + t_new[:, None, None] * D[act]
        gap[act] = distance(X) - m[act]
        act = act[gap[act] > tol[act]]
    unresolved[act] = True
    return t, unresolved


def tight_inclusion_toi(start, end, min_distance, tolerance=1e-6, max_iterations=10000):
    """Times of impact t (n,) by IPC Toolkit's Tight-Inclusion edge-edge CCD (one
    ``ipctk`` call per pair: 10-50 us each, hence only for the pairs that
    :func:`safe_fraction` leaves unresolved): 1 where the pair stays ``min_distance``
    (scalar or (n,)) apart on the whole path, else the first time it comes that close
    (Tight-Inclusion's time is a lower bound, also when it stops after
    ``max_iterations`` interval splits: ipctk's default of 1e7 took seconds for single
    grazing pairs)."""
    import ipctk
    S = check_positions(start, 4, "segment_ccd")
    E = check_positions(end, 4, "segment_ccd")
    m = np.broadcast_to(np.asarray(min_distance, float), (len(S),))
    ccd = ipctk.TightInclusionCCD(tolerance=tolerance, max_iterations=max_iterations,
                                  conservative_rescaling=1.0)
    out = np.ones(len(S))
    scale = np.abs(np.concatenate([S, E], axis=1)).reshape(len(S), -1).max(axis=1) + 1.0
    d_start = distance(S) if len(S) else np.zeros(0)
    for k in range(len(S)):
        if d_start[k] <= m[k] + 1e-12 * scale[k]:
            out[k] = 0.0            # already that close (Tight-Inclusion hangs on touching pairs)
            continue
        a, b = S[k], E[k]
        hit, toi = ccd.edge_edge_ccd(a[0], a[1], a[2], a[3], b[0], b[1], b[2], b[3], float(m[k]), 1.0)
        if hit:
            out[k] = toi
    return out
