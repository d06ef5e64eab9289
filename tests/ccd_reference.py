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
