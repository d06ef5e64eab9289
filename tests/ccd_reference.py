"""Brute-force NumPy reference for edge-edge crossings (tests only).

Two segments can meet only when their four points are coplanar: the triple product
f(t) = (x1 - x0) x (x2 - x0) . (x3 - x0) along the linear path is a cubic in t; at every
real root in [0, 1] the pair meets iff the segment distance vanishes there.  A pair
whose cubic vanishes identically (coplanar motion) is sampled densely instead.
"""

import numpy as np

# exact also for nearly parallel pairs (segment_contact.distance's parallel rule is an upper
# bound there, so the reference missed their crossings as the counter did)
from lc_petsc.elements.segment_ccd import exact_distance as distance


def _triple(X):
    a, b, c = X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]
    return np.einsum("ij,ij->i", np.cross(a, b), c)


def crossing_reference(S, E, tol=1e-9, samples=20001):
    """Boolean (k,): pairs (k, 4, 3) meeting on the linear path S -> E."""
    S, E = np.asarray(S, float), np.asarray(E, float)
    ts = np.array([0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0])
    F = np.stack([_triple(S + t * (E - S)) for t in ts], axis=1)
    V = np.vander(ts, 4)                              # cubic coefficients, highest first
    coef = np.linalg.solve(V, F.T).T
    scale = np.abs(np.concatenate([S, E], axis=1)).reshape(len(S), -1).max(axis=1) + 1.0
    out = np.zeros(len(S), bool)
    for k in range(len(S)):
        c = coef[k]
        if np.abs(c).max() <= 1e-12 * scale[k] ** 3:
            t = np.linspace(0.0, 1.0, samples)
            X = S[k] + t[:, None, None] * (E[k] - S[k])
            out[k] = distance(X).min() <= 1e-6 * scale[k]
            continue
        r = np.roots(np.trim_zeros(c, "f"))
        r = r[np.abs(r.imag) <= 1e-9].real
        r = r[(r >= -1e-12) & (r <= 1.0 + 1e-12)]
        if len(r):
            X = S[k] + np.clip(r, 0, 1)[:, None, None] * (E[k] - S[k])
            out[k] = distance(X).min() <= tol * scale[k]
    return out


# ------------------------------------------------------------------ independent of lc_petsc
def lstsq_distances(X):
    """Segment-segment distances (n,) of the pairs X (n, 4, 3), written independently of
    lc_petsc: the least of the four endpoint-to-segment distances and, where the
    least-squares solution (s, u) of x0 + s d1 = x2 + u d2 (SVD, also for nearly
    parallel pairs) lies in [0, 1]^2, its residual."""
    X = np.asarray(X, float)
    x0, x1, x2, x3 = X[:, 0], X[:, 1], X[:, 2], X[:, 3]
    d1, d2 = x1 - x0, x3 - x2
    best = np.full(len(X), np.inf)
    for p, a, d in ((x0, x2, d2), (x1, x2, d2), (x2, x0, d1), (x3, x0, d1)):
        dd = np.einsum("ij,ij->i", d, d)
        s = np.clip(np.einsum("ij,ij->i", p - a, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(p - a - s[:, None] * d, axis=1))
    su = (np.linalg.pinv(np.stack([d1, -d2], axis=2)) @ (x2 - x0)[:, :, None])[:, :, 0]
    inner = np.all((su >= 0.0) & (su <= 1.0), axis=1)
    r = x0 + su[:, :1] * d1 - x2 - su[:, 1:] * d2
    best[inner] = np.minimum(best[inner], np.linalg.norm(r[inner], axis=1))
    return best


def _golden(S, E, lo, hi, iterations):
    """(d, t) of golden-section searches of the distance of the pairs S -> E (c, 4, 3) on
    the intervals [lo, hi] (c,), all at once."""
    g = 0.5 * (np.sqrt(5.0) - 1.0)
    D = E - S
    dist = lambda t: lstsq_distances(S + t[:, None, None] * D)   # noqa: E731
    for _ in range(iterations):
        m1, m2 = hi - g * (hi - lo), lo + g * (hi - lo)
        left = dist(m1) < dist(m2)
        hi, lo = np.where(left, m2, hi), np.where(left, lo, m1)
    t = 0.5 * (lo + hi)
    return dist(t), t


def path_min_distance(S, E, samples=401, iterations=80):
    """(d (n,), t (n,)): the smallest distance of each pair (n, 4, 3) on its linear path
    S -> E and when it is reached, by brute force independent of lc_petsc: the distance
    (:func:`lstsq_distances`) at ``samples`` equal steps, then golden-section searches
    around every sampled local minimum (within a step each side) and every real root in
    [0, 1] of the coplanarity cubic (within 1e-3: two segments meet only where their
    four points are coplanar).  Parallel pairs are always coplanar (their cubic vanishes),
    and the sampled minima cover them."""
    S, E = np.asarray(S, float), np.asarray(E, float)
    n = len(S)
    ts = np.linspace(0.0, 1.0, samples)
    h = ts[1]
    d = lstsq_distances((S[:, None] + ts[None, :, None, None] * (E - S)[:, None]).reshape(-1, 4, 3)).reshape(n, -1)
    pad = np.full((n, 1), np.inf)
    k, i = np.nonzero((d <= np.hstack([pad, d[:, :-1]])) & (d <= np.hstack([d[:, 1:], pad])))
    who, lo, hi = [k], [np.clip(ts[i] - h, 0, 1)], [np.clip(ts[i] + h, 0, 1)]
    F = np.stack([_triple(S + t * (E - S)) for t in (0.0, 1 / 3, 2 / 3, 1.0)], axis=1)
    coef = np.linalg.solve(np.vander([0.0, 1 / 3, 2 / 3, 1.0], 4), F.T).T
    for k in np.flatnonzero(np.abs(coef).max(axis=1) > 0.0):
        r = np.roots(np.trim_zeros(coef[k], "f"))
        r = r[(np.abs(r.imag) <= 1e-4) & (r.real >= -1e-3) & (r.real <= 1.0 + 1e-3)].real
        who.append(np.full(len(r), k))
        lo.append(np.clip(r - 1e-3, 0, 1))
        hi.append(np.clip(r + 1e-3, 0, 1))
    who = np.concatenate(who)
    dg, tg = _golden(S[who], E[who], np.concatenate(lo), np.concatenate(hi), iterations)
    j = np.argmin(d, axis=1)
    out_d, out_t = d[np.arange(n), j], ts[j]
    for c in np.argsort(-dg):         # the smallest last: it wins
        if dg[c] < out_d[who[c]]:
            out_d[who[c]], out_t[who[c]] = dg[c], tg[c]
    return out_d, out_t


#: the brute force's classes of a pair, from its smallest distance on the path relative to
#: scale = largest |coordinate| + 1: a crossing at or below MEETS, clear above APART, in
#: between neither (a checker may answer either way: the counter counts as crossing what
#: it cannot prove to stay 1e-9 x scale apart)
MEETS, APART = 1e-12, 1e-7


def classify(S, E):
    """(meets (n,) bool, apart (n,) bool, d (n,)) of pairs (n, 4, 3) on S -> E by
    :func:`path_min_distance` and the bands MEETS, APART (relative to the pair's scale)."""
    d = path_min_distance(S, E)[0]
    scale = np.abs(np.concatenate([S, E], axis=1)).reshape(len(S), -1).max(axis=1) + 1.0
    return d <= MEETS * scale, d > APART * scale, d
