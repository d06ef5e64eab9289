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
``iterations`` steps at a safe t).  This vectorised version is the tested reference of
the compiled one the limiter of :mod:`lc_petsc.contact` runs
(:mod:`lc_petsc.elements.compiled_ccd`, pair by pair, up to 10,000 steps).  The crossing
counter (:mod:`lc_petsc.crossings`) checks paths with IPC Toolkit's Tight-Inclusion CCD
(:func:`tight_inclusion_toi`, min distance 0), independently of this advancement.
"""

from __future__ import annotations

import numpy as np

from lc_petsc.elements.common import check_positions
from lc_petsc.elements.segment_contact import closest_points, distance

__all__ = ["relative_motion", "safe_fraction", "exact_distance", "tight_inclusion_toi", "affine_sums",
           "affine_field", "field_boxes"]


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


def _point_segment(x, a, d):
    """Distances (n,) of points x (n, 3) from the segments a + s d, s in [0, 1]."""
    dd = np.einsum("ij,ij->i", d, d)
    s = np.clip(np.einsum("ij,ij->i", x - a, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    return np.linalg.norm(x - a - s[:, None] * d, axis=1)


def exact_distance(x):
    """Segment-segment distances (n,) of the pairs x (n, 4, 3), exact also for nearly
    parallel pairs: :func:`segment_contact.distance` where it solves its 2x2 system;
    where it takes the parallel rule (an upper bound: 1e-6 for two segments 1e-6 rad
    apart crossing at their middles) the least of it, the four endpoint-to-segment
    distances and the interior solution along n = d1 x d2 (the NumPy reference of
    ``compiled_ccd._vdistance_exact``)."""
    x = np.asarray(x, float)
    _, _, _, d, _, _, parallel = closest_points(x)
    k = np.flatnonzero(parallel)
    if len(k):
        x0, x1, x2, x3 = x[k, 0], x[k, 1], x[k, 2], x[k, 3]
        d1, d2 = x1 - x0, x3 - x2
        ends = np.stack([_point_segment(x0, x2, d2), _point_segment(x1, x2, d2),
                         _point_segment(x2, x0, d1), _point_segment(x3, x0, d1)], axis=1)
        dk = np.minimum(d[k], ends.min(axis=1))
        n = np.cross(d1, d2)
        nn = np.einsum("ij,ij->i", n, n)
        r = x2 - x0
        safe = np.where(nn > 0, nn, 1.0)
        s = np.einsum("ij,ij->i", np.cross(r, d2), n) / safe
        u = np.einsum("ij,ij->i", np.cross(r, d1), n) / safe
        inner = (nn > 0) & (s >= 0) & (s <= 1) & (u >= 0) & (u <= 1)
        dk[inner] = np.minimum(dk[inner], np.abs(np.einsum("ij,ij->i", r, n))[inner] / np.sqrt(nn[inner]))
        d = d.copy()
        d[k] = dk
    return d


def tight_inclusion_toi(start, end, min_distance, tolerance=1e-6, max_iterations=10000):
    """(hit (n,) bool, t (n,)) by IPC Toolkit's Tight-Inclusion edge-edge CCD (one
    ``ipctk`` call per pair: 10-50 us each, hence only for pairs that the motion bound
    cannot settle): ``hit`` where the pair comes within ``min_distance`` (scalar or
    (n,)) on its path, t the first time it does (1 where it does not).  Pairs already
    that close at the start hit at t = 0 (Tight-Inclusion was measured to hang on
    touching pairs); pairs the motion bound shows never come that close are not passed
    to ipctk.  Tight-Inclusion's time is a lower bound, also when it stops after
    ``max_iterations`` interval splits, which bounds each pair's time (then it reports a
    hit, often at t = 0: conservative; ipctk's
    default of 1e7 took seconds for single grazing pairs and ran out of memory on one
    degenerate pair; 2,000 ran out of memory too, on pairs of tests/test_ccd.py that
    10,000 settles in milliseconds)."""
    import ipctk
    S = check_positions(start, 4, "segment_ccd")
    E = check_positions(end, 4, "segment_ccd")
    n = len(S)
    m = np.broadcast_to(np.asarray(min_distance, float), (n,))
    hit, out = np.zeros(n, bool), np.ones(n)
    if not n:
        return hit, out
    scale = np.abs(np.concatenate([S, E], axis=1)).reshape(n, -1).max(axis=1) + 1.0
    d_start = exact_distance(S)       # the parallel rule's upper bound skipped crossings
    touch = d_start <= m + 1e-12 * scale
    hit[touch], out[touch] = True, 0.0
    # the floor also here: a pair arriving head-on, touching at t = 1, has d_start = rel
    # up to round-off
    maybe = np.flatnonzero(~touch & (d_start - m <= relative_motion(S, E) + 1e-12 * scale))
    for k in maybe:
        a, b = S[k], E[k]
        # Tight-Inclusion's own entry with ipctk.TightInclusionCCD's tolerance (at most
        # half the start distance), not that class: after an answer t < 1e-6 (the
        # undecided answer is often t = 0) the class runs it again with no iteration
        # limit, and a pair coinciding along its length at t = 1/2 kept that busy for minutes
        h, toi, _ = ipctk.tight_inclusion.edge_edge_ccd(
            a[0], a[1], a[2], a[3], b[0], b[1], b[2], b[3], min_distance=float(m[k]), tmax=1.0,
            tolerance=min(0.5 * float(d_start[k]), tolerance), max_iterations=max_iterations, no_zero_toi=False)
        if h:
            hit[k], out[k] = True, toi
    return hit, out


# ---------------------------------------------------------------- relative broad phase
def affine_sums(x, displacement):
    """Least-squares sums (4, 4), (4, 3) of an affine fit u(x) = A x + b to the
    ``displacement`` (n, 3) of the points ``x`` (n, 3): summed over ranks, they give
    :func:`affine_field`."""
    X1 = np.concatenate([np.asarray(x, float), np.ones((len(x), 1))], axis=1)
    return X1.T @ X1, X1.T @ np.asarray(displacement, float)


def affine_field(M, R, max_lipschitz=0.5):
    """(A (3, 3), b (3,), L) of the affine field u(x) = A x + b fitted by the sums
    ``M``, ``R`` of :func:`affine_sums`, scaled down (A and b alike) so that its
    Lipschitz constant L = ||A||_2 is at most ``max_lipschitz``.  No points, or points
    on a plane: the minimum-norm fit (lstsq); u = 0 when nothing moves."""
    M, R = np.asarray(M, float), np.asarray(R, float)
    if M[3, 3] <= 0.0:
        return np.zeros((3, 3)), np.zeros(3), 0.0
    mean = M[3, :3] / M[3, 3]                  # centred for conditioning
    C = M[:3, :3] / M[3, 3] - np.outer(mean, mean)
    Dm = R[3] / M[3, 3]
    CD = R[:3] / M[3, 3] - np.outer(mean, Dm)
    At = np.linalg.lstsq(C, CD, rcond=1e-10)[0]              # (3, 3): u = x At + b
    A = At.T
    b = Dm - A @ mean
    L = float(np.linalg.norm(A, 2))
    if L > max_lipschitz:
        A, b = A * (max_lipschitz / L), b * (max_lipschitz / L)
        L = float(max_lipschitz)
    return A, b, L


def field_boxes(start, residual, lipschitz, min_distance):
    """Boxes (lo, hi) (m, 3) of segments for the relative broad phase: two segments can
    come within ``min_distance`` on a path whose vertex displacements are
    u(x_start) + beta f, beta in [0, 1] per vertex (any fractions), u affine with
    Lipschitz constant ``lipschitz`` L < 1, f the ``residual`` (m, 2, 3) of the
    segments' vertices, only if their boxes overlap.  ``start`` (m, 2, 3).

    Proof.  Point p of segment A (parameter s) is at p0 + t (A p0 + b) + t r_p at time
    t, r_p = (1 - s) beta_0 f_0 + s beta_1 f_1, so with y_p = p0 + t r_p (a convex
    combination of points of [x_v, x_v + f_v]: y_p lies in the convex hull K_A of the
    segment's two vertices and their residual ends) p - q = y_p - y_q + t A (p0 - q0).
    As |p0 - q0| <= |y_p - y_q| + rho_A + rho_B (rho = the segment's largest |f|),
    |p - q| >= (1 - L) |y_p - y_q| - L (rho_A + rho_B): the pair comes within m only if
    dist(K_A, K_B) < sum over the two of (m / 2 + L rho) / (1 - L).  The box is K's
    bounding box grown by that term (boxes apart along an axis by more than the sum
    are that far apart).  Hair swinging with the bulk moves by u and sweeps nothing:
    the boxes are set by how far a segment moves relative to the fitted field, and
    stretch along that motion only."""
    S = np.asarray(start, float)
    f = np.asarray(residual, float)
    E = S + f
    # elementwise over the four corners (reductions over a middle axis of 4 are slow)
    lo = np.minimum(np.minimum(S[:, 0], S[:, 1]), np.minimum(E[:, 0], E[:, 1]))
    hi = np.maximum(np.maximum(S[:, 0], S[:, 1]), np.maximum(E[:, 0], E[:, 1]))
    rho = np.sqrt(np.maximum(np.einsum("mc,mc->m", f[:, 0], f[:, 0]), np.einsum("mc,mc->m", f[:, 1], f[:, 1])))
    L = float(lipschitz)
    grow = ((0.5 * float(min_distance) + L * rho) / (1.0 - L))[:, None]
    return lo - grow, hi + grow
