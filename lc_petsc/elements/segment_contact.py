"""Penalty contact between two segments (edge-edge); pure NumPy, batch-first.

A pair is four points ``x`` of shape (n, 4, 3): segment A = (x0, x1), segment B =
(x2, x3).  With p(s) = x0 + s (x1 - x0), q(t) = x2 + t (x3 - x2) and (s, t) the closest
parameters in [0, 1]^2, the distance is d = |p - q| and the energy

    Psi = 1/2 k (d0 - d)^2   for d < d0 (the contact thickness),   0 otherwise

(k in dyn/cm, d0 in cm; C1 at d = d0).  With u = p - q, n = u / d and the weights
w = (1 - s, s, -(1 - t), -t), the gradient of d is w (x) n (envelope theorem: the
parameters are optimal), so

    grad Psi = -k (d0 - d) w (x) n           (n, 4, 3)

Closest points (:func:`closest_points`) follow the clamped algorithm of Ericson
(Real-Time Collision Detection, 5.1.9): s from the unconstrained 2x2 solution, clamped
to [0, 1], t optimal for that s, clamped, then s re-optimised when t was clamped.  When
the segments are parallel or nearly so (sin^2 of their angle below
:data:`PARALLEL_TOL`) the 2x2 system is singular; s = 0 is taken instead and the rest of
the algorithm proceeds, so no division by the vanishing determinant ever happens.  Any
minimiser of a parallel pair gives the same distance; only the split of the force
between the vertices (w) depends on the choice.  Intersecting segments (d = 0, a
configuration a penalty should never reach) get n = unit(d1 x d2) or, if that vanishes
too, a unit vector perpendicular to segment A: finite values by rule.

Hessian filters (``filter=``; same names as the element kernels):

* ``"analytic"`` (default, what the simulator uses): the Gauss-Newton part
  k (w w^T) (x) (n n^T), closed form, rank one, PSD and bounded by k |w|^2 <= 4 k for
  every geometry (parallel, nearly parallel, intersecting).  It drops the curvature term
  psi'(d) Hess d, whose tangential part -|psi'|/d (w w^T) (x) (I - n n^T) is negative
  (a PSD filter clamps it anyway) and whose parameter-coupling part grows like
  1 / sin^2(angle) for nearly parallel pairs.
* ``"none"``: the exact Hessian k grad d grad d^T + psi'(d) Hess d, with
  Hess d = (Hess F - grad d grad d^T) / d, F = d^2 / 2 and
  Hess F = J^T J - B_f M_f^{-1} B_f^T the Hessian of the minimum value, a Schur
  complement over the *free* (strictly interior) parameters: J = w^T (x) I (3x12), M the
  2x2 Hessian of F in (s, t), B the mixed derivatives.  Clamped parameters are constant
  locally and drop out; a nearly parallel pair (s fixed at 0 by the rule above) keeps
  only t.  Exact where the closest points are unique and strict complementarity holds
  (checked against finite differences in tests/test_contact_kernel.py); finite everywhere
  but huge for pairs just above the parallel threshold, and for intersecting pairs
  (d -> 0, where d is not differentiable) the curvature term uses max(d, 1e-8 d0).
* ``"numerical"``: the exact Hessian with its negative eigenvalues clamped to 0 (batched
  ``eigh``): the nearest PSD matrix, the reference.
* ``"abs"``: the exact Hessian with its eigenvalues replaced by their absolute values
  (batched ``eigh``).

Hessians are (n, 12, 12) in vertex-major order (row 3 v + c: coordinate c of point v).
"""

from __future__ import annotations

import numpy as np

from lc_petsc.elements.common import FILTERS, check_filter, check_per_element, check_positions

#: sin^2 of the angle between the segments below which they count as parallel.
PARALLEL_TOL = 1e-10
#: a distance below this (relative to the pair's coordinate scale) counts as intersecting
_ZERO_DIST = 1e-14

__all__ = ["FILTERS", "PARALLEL_TOL", "closest_points", "distance", "energy", "gradient",
           "hessian", "gradient_hessian", "potential_gradient_hessian", "separation"]


def _dot(a, b):
    """Row dot products (n,) of a, b (n, 3), summed left to right: the order of the
    compiled kernel (:mod:`compiled_contact`), which then agrees to the bit (einsum's
    order differs)."""
    return (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]) + a[:, 2] * b[:, 2]


def closest_points(x):
    """Closest parameters of the pairs x (n, 4, 3).

    Returns (s, t, u, d, free_s, free_t, parallel): parameters (n,), the vector
    u = p(s) - q(t) (n, 3), the distance d (n,), which parameters are strictly interior
    (free), and which pairs took the parallel rule.
    """
    x = np.asarray(x, float)
    x0, x1, x2, x3 = x[:, 0], x[:, 1], x[:, 2], x[:, 3]
    d1, d2, r = x1 - x0, x3 - x2, x0 - x2
    a, e = _dot(d1, d1), _dot(d2, d2)
    b, c, f = _dot(d1, d2), _dot(d1, r), _dot(d2, r)
    tiny = np.finfo(float).tiny
    a_s, e_s = np.maximum(a, tiny), np.maximum(e, tiny)
    denom = np.maximum(a * e - b * b, 0.0)
    parallel = denom <= PARALLEL_TOL * a * e
    s = np.where(parallel, 0.0, np.clip((b * f - c * e) / np.where(parallel, 1.0, denom), 0.0, 1.0))
    t = (b * s + f) / e_s
    lo, hi = t < 0.0, t > 1.0
    s = np.where(lo, np.clip(-c / a_s, 0.0, 1.0), np.where(hi, np.clip((b - c) / a_s, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    u = (x0 + s[:, None] * d1) - (x2 + t[:, None] * d2)
    d = np.sqrt(_dot(u, u))
    free_s = (s > 0.0) & (s < 1.0)
    free_t = (t > 0.0) & (t < 1.0)
    return s, t, u, d, free_s, free_t, parallel


def _normal(x, u, d):
    """Unit n = u / d, with the intersecting-segment rule of the module doc."""
    scale = np.abs(x.reshape(len(x), 12)).max(axis=1, initial=0.0)
    hit = d <= _ZERO_DIST * np.maximum(scale, 1.0)
    n = np.empty_like(u)
    ok = ~hit
    n[ok] = u[ok] / d[ok, None]
    if hit.any():
        xh = x[hit]
        d1, d2 = xh[:, 1] - xh[:, 0], xh[:, 3] - xh[:, 2]
        m = np.cross(d1, d2)
        mn = np.linalg.norm(m, axis=1)
        bad = mn <= 1e-12 * np.linalg.norm(d1, axis=1) * np.linalg.norm(d2, axis=1)
        if bad.any():   # parallel and touching: any perpendicular of d1
            ax = np.eye(3)[np.argmin(np.abs(d1[bad]), axis=1)]
            m[bad] = np.cross(d1[bad], ax)
            mn[bad] = np.linalg.norm(m[bad], axis=1)
        n[hit] = m / np.maximum(mn, np.finfo(float).tiny)[:, None]
    return n


def _weights(s, t):
    return np.stack([1.0 - s, s, -(1.0 - t), -t], axis=1)


def _prepare(x, thickness, stiffness, name="segment_contact"):
    x = check_positions(x, 4, name)
    n = len(x)
    d0 = check_per_element(thickness, n, name, "thickness", positive=True)
    k = check_per_element(stiffness, n, name, "stiffness")
    return x, d0, k


def distance(x):
    """Segment-segment distance (n,)."""
    return closest_points(np.asarray(x, float))[3]


def energy(x, thickness, stiffness):
    """Psi = 1/2 k (d0 - d)^2 where d < d0, else 0: shape (n,)."""
    x, d0, k = _prepare(x, thickness, stiffness)
    d = closest_points(x)[3]
    gap = np.maximum(d0 - d, 0.0)
    return 0.5 * k * gap * gap


def gradient(x, thickness, stiffness):
    """grad Psi = -k (d0 - d) w (x) n: shape (n, 4, 3)."""
    return gradient_hessian(x, thickness, stiffness, hessian=False)[0]


def hessian(x, thickness, stiffness, filter="analytic"):
    """Hessian (n, 12, 12) with the chosen filter (see the module doc)."""
    return gradient_hessian(x, thickness, stiffness, filter=filter)[1]


def gradient_hessian(x, thickness, stiffness, filter="analytic", hessian=True):
    """(gradient (n, 4, 3), Hessian (n, 12, 12) or None) in one pass."""
    check_filter(filter)
    x, d0, k = _prepare(x, thickness, stiffness)

    def derivatives(d, active):
        gap = np.where(active, d0 - d, 0.0)
        kk = np.where(active, k, 0.0)
        return -(kk * gap), kk

    return potential_gradient_hessian(x, d0, derivatives, filter=filter, hessian=hessian)


def potential_gradient_hessian(x, d0, derivatives, filter="analytic", hessian=True):
    """Gradient (n, 4, 3) and Hessian (n, 12, 12) (or None) of a potential Psi(d) of the
    segment-segment distance d that vanishes for d >= d0 (n,): the chain rule
    psi'(d) grad d and psi''(d) grad d grad d^T + psi'(d) Hess d, with the filters of the
    module doc (``analytic``: the first Hessian term only, PSD when psi'' >= 0).

    ``derivatives(d, active)`` gets the distances (n,) and the mask d < d0 and returns
    (psi', psi'') (n,), zero where not active.  Shared by this penalty and the barrier
    of :mod:`lc_petsc.elements.segment_barrier`; x must be validated already."""
    check_filter(filter)
    n_pairs = len(x)
    s, t, u, d, free_s, free_t, parallel = closest_points(x)
    nrm = _normal(x, u, d)
    w = _weights(s, t)
    active = d < d0
    psi1, psi2 = derivatives(d, active)
    gd = w[:, :, None] * nrm[:, None, :]                      # grad d, (n, 4, 3)
    g = psi1[:, None, None] * gd
    if not hessian:
        return g, None
    gdf = gd.reshape(n_pairs, 12)
    H = psi2[:, None, None] * (gdf[:, :, None] * gdf[:, None, :])      # exactly symmetric
    if filter == "analytic" or not active.any():
        return g, H
    # exact curvature part, only for active pairs
    ia = np.flatnonzero(active)
    xa, ua, da = x[ia], u[ia], d[ia]
    wa, gda = w[ia], gdf[ia]
    d1, d2 = xa[:, 1] - xa[:, 0], xa[:, 3] - xa[:, 2]
    a, e, b = _dot(d1, d1), _dot(d2, d2), _dot(d1, d2)
    m = len(ia)
    eye = np.eye(3)
    JtJ = (wa[:, :, None, None, None] * wa[:, None, :, None, None] * eye).transpose(0, 1, 3, 2, 4)
    JtJ = JtJ.reshape(m, 12, 12)
    # mixed derivatives of F in x and (s, t): B = [b_s, b_t] (m, 12, 2)
    Jt_d1 = (wa[:, :, None] * d1[:, None, :]).reshape(m, 12)
    Jt_d2 = (wa[:, :, None] * d2[:, None, :]).reshape(m, 12)
    zero = np.zeros_like(ua)
    bs = Jt_d1 + np.concatenate([-ua, ua, zero, zero], axis=1)
    bt = -Jt_d2 + np.concatenate([zero, zero, ua, -ua], axis=1)
    B = np.stack([bs, bt], axis=2)
    fs, ft = free_s[ia], free_t[ia]
    both = fs & ft & ~parallel[ia]
    Minv = np.zeros((m, 2, 2))
    det = np.where(both, a * e - b * b, 1.0)
    Minv[both, 0, 0] = (e / det)[both]
    Minv[both, 1, 1] = (a / det)[both]
    Minv[both, 0, 1] = Minv[both, 1, 0] = (b / det)[both]
    only_s = fs & ~both & ~ft
    only_t = ft & ~both
    Minv[only_s, 0, 0] = 1.0 / a[only_s]
    Minv[only_t, 1, 1] = 1.0 / e[only_t]
    hessF = JtJ - B @ Minv @ B.transpose(0, 2, 1)
    dsafe = np.maximum(da, 1e-8 * d0[ia])      # intersecting pairs: bounded by rule
    hessd = (hessF - gda[:, :, None] * gda[:, None, :]) / dsafe[:, None, None]
    Hx = H[ia] + psi1[ia][:, None, None] * hessd
    Hx = 0.5 * (Hx + Hx.transpose(0, 2, 1))
    if filter in ("numerical", "abs"):
        lam, V = np.linalg.eigh(Hx)
        lam = np.maximum(lam, 0.0) if filter == "numerical" else np.abs(lam)
        Hx = (V * lam[:, None, :]) @ V.transpose(0, 2, 1)
    H[ia] = Hx
    return g, H


def separation(x, inverse_mass, target):
    """Displacements (n, 4, 3) that take each pair closer than ``target`` to distance
    ``target`` to first order: the mass-weighted projection of position-based dynamics
    onto d = target,

        dx_a = (target - d) m_a^-1 w_a n / sum_b m_b^-1 w_b^2     (w, n as in grad d),

    zero for pairs at or beyond ``target`` and for pairs whose four inverse masses
    (n, 4) are zero (pinned).  Sum_a m_a dx_a = 0 when no vertex is pinned (sum w = 0):
    no momentum is created.  ``target`` scalar or (n,)."""
    x = check_positions(x, 4, "segment_contact.separation")
    n = len(x)
    im = np.asarray(inverse_mass, float)
    if im.shape != (n, 4) or not np.all(np.isfinite(im)) or np.any(im < 0):
        raise ValueError(f"segment_contact.separation: inverse_mass must be finite, >= 0 and of "
                         f"shape ({n}, 4), got shape {im.shape}")
    tgt = check_per_element(target, n, "segment_contact.separation", "target", positive=True)
    s, t, u, d, *_ = closest_points(x)
    nrm = _normal(x, u, d)
    w = _weights(s, t)
    denom = np.einsum("ij,ij->i", im, w * w)
    lam = np.where((d < tgt) & (denom > 0), (tgt - d) / np.where(denom > 0, denom, 1.0), 0.0)
    return (lam[:, None] * im * w)[:, :, None] * nrm[:, None, :]
