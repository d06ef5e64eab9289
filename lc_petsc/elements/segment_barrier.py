"""Barrier contact between two segments (edge-edge), IPC-style; pure NumPy, batch-first.

A pair is four points ``x`` of shape (n, 4, 3): segment A = (x0, x1), segment B =
(x2, x3), as in :mod:`lc_petsc.elements.segment_contact`, whose closest points and
distance derivatives this module reuses.  With d the segment-segment distance and
dhat the contact thickness d0, the energy is the log barrier of Incremental Potential
Contact (Li et al. 2020, eq. 6)

    b(d) = -kappa (d - dhat)^2 ln(d / dhat)     for 0 < d < dhat,   0 for d >= dhat,

with the derivatives (y = d - dhat, r = d / dhat)

    b'(d)  = -kappa (2 y ln r + y^2 / d)                      (< 0: repulsive)
    b''(d) = -kappa (2 ln r + 4 y / d - y^2 / d^2)             (> 0: convex in d)

b, b' and b'' all vanish at d = dhat (C2 there, unlike the penalty 1/2 k (d0 - d)^2,
whose second derivative jumps from k to 0), and b grows without bound as d -> 0: a
Newton step on the barrier cannot push a pair through itself as long as the step is
kept collision-free (the ccd limiter, :meth:`lc_petsc.contact.StrandContact.limit_step`).
kappa is in dyn/cm like the penalty's k (b has units kappa cm^2 = erg); the
simulator's default kappa = k / (1 + 2 ln 2) makes the barrier's force equal the
penalty's at d = dhat / 2 (docs/contact.md, "Barrier").

The barrier is infinite at d <= 0.  :func:`energy` returns +inf there (a line search
trial point that reaches an intersection is rejected by it); the gradient and Hessian
raise :class:`~lc_petsc.errors.ElementError`, since an assembled iterate with
intersecting segments means the step limiter was bypassed.

Hessian filters (``filter=``), as in segment_contact: ``analytic`` (default) the
Gauss-Newton part b''(d) grad d grad d^T, rank one and PSD (b'' > 0); ``none`` the exact
Hessian (the curvature term b'(d) Hess d added); ``numerical`` / ``abs`` the exact
Hessian with negative eigenvalues clamped to 0 / replaced by their absolute values.
Hessians are (n, 12, 12) in vertex-major order.
"""

from __future__ import annotations

import numpy as np

from lc_petsc.elements.common import FILTERS, check_filter, check_per_element, check_positions
from lc_petsc.elements.segment_contact import closest_points, potential_gradient_hessian
from lc_petsc.errors import ElementError

__all__ = ["FILTERS", "barrier", "energy", "gradient", "hessian", "gradient_hessian",
           "penalty_matched_stiffness"]

_NAME = "segment_barrier"


def _prepare(x, thickness, stiffness):
    x = check_positions(x, 4, _NAME)
    n = len(x)
    dhat = check_per_element(thickness, n, _NAME, "thickness", positive=True)
    kappa = check_per_element(stiffness, n, _NAME, "stiffness")
    return x, dhat, kappa


def barrier(d, dhat, kappa):
    """(b, b', b'') (each (n,)) of the scalar barrier at distances d (n,) > 0, zero where
    d >= dhat; dhat, kappa scalars or (n,)."""
    d = np.asarray(d, float)
    dhat = np.broadcast_to(np.asarray(dhat, float), d.shape)
    kappa = np.broadcast_to(np.asarray(kappa, float), d.shape)
    on = d < dhat
    dd = np.where(on, d, dhat)
    y = dd - dhat
    lr = np.log(dd / dhat)
    k = np.where(on, kappa, 0.0)
    b = -k * y * y * lr
    b1 = -k * (2.0 * y * lr + y * y / dd)
    b2 = -k * (2.0 * lr + 4.0 * y / dd - y * y / (dd * dd))
    return b, b1, b2


def penalty_matched_stiffness(k):
    """kappa whose barrier force |b'(dhat / 2)| = kappa dhat (ln 2 + 1/2) equals the
    penalty 1/2 k (dhat - d)^2's force k dhat / 2 at half the thickness:
    k / (1 + 2 ln 2) = 0.419 k.  Beyond dhat / 2 the barrier pushes less than the
    penalty, below it more, without bound (8.5 k dhat at dhat / 20)."""
    return float(k) / (1.0 + 2.0 * np.log(2.0))


def _check_apart(d, dhat):
    """ElementError if a pair of d (n,) is at distance <= 0 (the barrier is infinite)."""
    bad = d <= 0.0
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ElementError(
            f"{_NAME}: {int(bad.sum())} segment pair(s) intersect (distance 0, pair {i}), where "
            f"the barrier (thickness {float(dhat[i])!r}) is infinite; the barrier needs "
            f"collision-free steps: use physics.strand_contact_mode = \"ccd\" (its limiter keeps "
            f"every pair apart), or physics.strand_contact_potential = \"penalty\"")


def energy(x, thickness, stiffness):
    """b(d) (n,): -kappa (d - dhat)^2 ln(d / dhat) where d < dhat, 0 beyond, +inf where
    the segments intersect (d = 0)."""
    x, dhat, kappa = _prepare(x, thickness, stiffness)
    d = closest_points(x)[3]
    e = barrier(np.where(d > 0.0, d, dhat), dhat, kappa)[0]
    return np.where(d > 0.0, e, np.inf)


def gradient(x, thickness, stiffness):
    """grad b = b'(d) w (x) n: shape (n, 4, 3) (w, n as in segment_contact)."""
    return gradient_hessian(x, thickness, stiffness, hessian=False)[0]


def hessian(x, thickness, stiffness, filter="analytic"):
    """Hessian (n, 12, 12) with the chosen filter (see the module doc)."""
    return gradient_hessian(x, thickness, stiffness, filter=filter)[1]


def gradient_hessian(x, thickness, stiffness, filter="analytic", hessian=True):
    """(gradient (n, 4, 3), Hessian (n, 12, 12) or None) in one pass; ElementError if a
    pair intersects."""
    check_filter(filter)
    x, dhat, kappa = _prepare(x, thickness, stiffness)

    def derivatives(d, active):
        _check_apart(d, dhat)
        return barrier(d, dhat, kappa)[1:]

    return potential_gradient_hessian(x, dhat, derivatives, filter=filter, hessian=hessian)
