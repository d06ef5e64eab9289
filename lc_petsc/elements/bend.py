"""Bending energy of three consecutive vertices (SPEC sections 2 and 3).

Both edges leave the centre vertex: e0 = x0 - x1, e1 = x2 - x1, T = [e0 | e1]. theta is
the angle between them (pi for a straight strand), computed with atan2:

    Psi_b = 1/2 k (theta - thetabar)^2,   k = k_b = E I / l_i.

The Hessian in T is S Hhat S (S = diag(I/|e0|, I/|e1|)), Hhat having the closed-form
eigensystem of :mod:`lc_petsc.elements.angle`; the vertex Hessian is D^T H D with
D = [[I, -I, 0], [0, -I, I]].

Filters: "analytic" keeps the positive closed-form eigenpairs, S Hhat^+ S. It is the exact
PSD projection of the Hessian in T when |e0| = |e1|; otherwise it is PSD but not the
nearest PSD matrix (documented and measured in docs/elements.md). "numerical" projects
the exact 6x6 Hessian in T with numpy.linalg.eigh (the paper's baseline). "abs" keeps all
closed-form eigenpairs with their eigenvalues' absolute values, S |Hhat| S: PSD, the exact
Hessian wherever that is PSD (Sylvester), |H_T| itself when |e0| = |e1|. At a straight or
folded bend (sin theta < STRAIGHT_TOL) the degenerate rule of the angle module applies:
zero gradient, isotropic PSD Hessian, the same for every filter.

Shapes: x (n, 3, 3); rest_angle, stiffness (n,) or scalars; energy (n,); gradient
(n, 3, 3); hessian (n, 9, 9), vertex-major.
"""

import numpy as np

from lc_petsc.elements.angle import STRAIGHT_TOL, AngleFrame
from lc_petsc.elements.common import (check_filter, check_finite, check_per_element,
                                      check_positions, coordinate_scale, edge_lengths, gram,
                                      run_chunked)

__all__ = ["energy", "gradient", "hessian", "gradient_hessian", "angle", "theta_eigensystem",
           "eigensystem", "STRAIGHT_TOL"]

TERM = "bend"


def _inputs(x, rest_angle, stiffness):
    x = check_positions(x, 3, TERM)
    n = x.shape[0]
    return (x, check_finite(rest_angle, n, TERM, "rest angle"),
            check_per_element(stiffness, n, TERM, "stiffness"))


def _frame(x, offset=0):
    xs = x.transpose(1, 2, 0)                 # (vertex, component, element)
    e0 = xs[0] - xs[1]
    e1 = xs[2] - xs[1]
    scale = coordinate_scale(x)
    l0 = edge_lengths(e0, scale, TERM, "x0 - x1", offset)
    l1 = edge_lengths(e1, scale, TERM, "x2 - x1", offset)
    return AngleFrame(e0, e1, l0, l1)


def angle(x):
    """Bend angle theta in [0, pi] between e0 and e1, shape (n,)."""
    return _frame(check_positions(x, 3, TERM)).theta


def energy(x, rest_angle, stiffness):
    """Psi_b per element, shape (n,)."""
    x, rest_angle, k = _inputs(x, rest_angle, stiffness)
    return 0.5 * k * (_frame(x).theta - rest_angle) ** 2


def theta_eigensystem(x):
    """Eigenpairs of the unit-column Hessian of theta in T: lam (n, 6), q (n, 6, 6)."""
    return _frame(check_positions(x, 3, TERM)).theta_eigensystem()


def eigensystem(x, rest_angle, stiffness):
    """Eigenpairs of the unit-column Hessian of Psi_b in T: lam (n, 6), q (n, 6, 6)."""
    x, rest_angle, k = _inputs(x, rest_angle, stiffness)
    frame = _frame(x)
    return frame.eigensystem(k * (frame.theta - rest_angle), k)


def _to_vertices(top, bot, frame):
    """Map T-space vectors [top; bot] at unit columns, (3, r, n) each, to vertices (9, r, n).

    Applies S (column scaling) then D^T: [u, -u - v, v] with u = top/L0, v = bot/L1.
    """
    u = top / frame.lu
    v = bot / frame.lv
    return np.concatenate([u, -u - v, v], axis=0)


def _kernel(filter):
    def kernel(lo, inputs, g, h):
        x, rest_angle, k = inputs
        frame = _frame(x, lo)
        d = k * (frame.theta - rest_angle)
        if g is not None:
            gu, gv = frame.theta_gradient()
            gu *= d
            gv *= d
            g[:, 0] = gu.T
            g[:, 2] = gv.T
            g[:, 1] = (-gu - gv).T
        if h is None:
            return
        if filter == "analytic":
            lam, top, bot, _ = frame.positive_part(d, k)
            root = np.sqrt(lam)
            gram(_to_vertices(top * root, bot * root, frame), out=h)
            return
        lam, q = frame.eigensystem(d, k)
        qs = q.transpose(1, 2, 0)
        if filter in ("none", "abs"):
            gram(_to_vertices(qs[:3], qs[3:], frame), lam if filter == "none" else np.abs(lam),
                 out=h)
            return
        # Numerical: the exact Hessian in T (S Hhat S), projected with eigh.
        lam_t, q_t = np.linalg.eigh(gram(np.concatenate([qs[:3] / frame.lu, qs[3:] / frame.lv]),
                                         lam))
        qt = q_t.transpose(1, 2, 0)
        gram(np.concatenate([qt[:3], -qt[:3] - qt[3:], qt[3:]]), np.maximum(lam_t, 0.0), out=h)
    return kernel


def gradient(x, rest_angle, stiffness):
    """dPsi_b/dx, shape (n, 3, 3) (zero at a straight or folded bend)."""
    inputs = _inputs(x, rest_angle, stiffness)
    return run_chunked(_kernel("none"), inputs[0].shape[0], 3, inputs, True, False)[0]


def hessian(x, rest_angle, stiffness, filter="analytic", out=None):
    """d2Psi_b/dx2 (n, 9, 9) with ``filter`` in FILTERS (see module doc)."""
    check_filter(filter)
    inputs = _inputs(x, rest_angle, stiffness)
    return run_chunked(_kernel(filter), inputs[0].shape[0], 3, inputs, False, True, out)[1]


def gradient_hessian(x, rest_angle, stiffness, filter="analytic", out=None):
    """(gradient (n, 3, 3), hessian (n, 9, 9)) in one pass over the elements."""
    check_filter(filter)
    inputs = _inputs(x, rest_angle, stiffness)
    return run_chunked(_kernel(filter), inputs[0].shape[0], 3, inputs, True, True, out)
