"""Twisting energy (discrete geometric torsion) of four consecutive vertices (SPEC 2, 3).

e0 = x0 - x1, e1 = x2 - x1 (middle edge), e2 = x3 - x2. The outer edges projected off the
middle one: a = e0 - alpha e1, b = e2 - beta e1 with alpha = e0.e1/|e1|^2,
beta = e2.e1/|e1|^2, and W = [a | b | e1]. phi is the signed dihedral angle between a and
b about e1, phi = atan2(e1h . (a x b), a . b) in (-pi, pi]:

    Psi_t = 1/2 k wrap(phi - phibar)^2,   k = k_t = G J / Lbar_mid.

In W, phi = sigma theta(a, b) with sigma = sign(e1h . (a x b)) locally constant, so Psi_t
is the bending form of :mod:`lc_petsc.elements.angle` in the columns (a, b) with
d = sigma k wrap(phi - phibar); the e1 column carries zero eigenvalues.

Derivatives in x: P = the simplified dW/dx of the supplement (eq. 46, alpha and beta held
constant), J the exact one, Dt = P - J (blocks e1 v^T / |e1|^2). P gives the exact
gradient (P^T g_W = J^T g_W), but the exact Hessian is P^T H_W P - Dt^T H_W Dt. Dt sees a
and b only through e1.a and e1.b, so of the six eigenpairs of H_W only the two
out-of-plane ones ([n; +-n], n parallel to e1) reach it. For those the exact contribution
lam (A A^T - B B^T) (A = P^T S q, B = Dt^T S q) is evaluated in a cancellation-free closed
form (lam ~ 1/sin(theta) is singular at planar stencils, phi = 0 or pi, while A - B ~
sin(theta)); see :func:`_out_of_plane`.

Filters:

* "none": the exact Hessian.
* "analytic": the in-plane eigenpairs with positive eigenvalue (always 2 of 4), plus the
  PSD part of each out-of-plane contribution, a symmetric rank-2 matrix whose PSD part is
  rank 1 in closed form. Rank <= 4, PSD, bounded at planar stencils. (The split
  P^T H_W^+ P - Dt^T H_W^- Dt suggested in SPEC section 2 is also PSD, but its out-of-plane
  term grows like 1/sin(theta) near phi = 0, pi: at phi = 1e-4 it is ~2000x the exact
  Hessian. See docs/elements.md.)
* "numerical": the exact 12x12 Hessian projected onto the PSD cone with numpy.linalg.eigh
  (the exact projection; the W-space split has no exact projection to compare with).
* "abs": the exact Hessian's pieces with absolute weights: the four in-plane pairs with
  |eigenvalue| and each out-of-plane rank-2 term as its PSD part plus its negated
  negative part (the two are orthogonal). PSD and rank <= 8; like "analytic" it equals
  the exact Hessian at rest, not wherever that is PSD.

Degenerate rule: when |a| < DEGENERATE_TOL |e0| or |b| < DEGENERATE_TOL |e2| an outer edge
is collinear with the middle one and the torsion is undefined; such elements contribute
zero energy, gradient and Hessian. Where a and b are parallel (phi = 0 or pi) the angle
frame turns about e1 (see :mod:`lc_petsc.elements.angle`); the closed forms above stay
finite there.

Shapes: x (n, 4, 3); rest_angle, stiffness (n,) or scalars; energy (n,); gradient
(n, 4, 3); hessian (n, 12, 12), vertex-major.
"""

import numpy as np

from lc_petsc.elements import bend
from lc_petsc.elements.angle import (AngleFrame, any_perpendicular, cross3, dot3, norm3,
                                     wrap_angle)
from lc_petsc.elements.common import (check_filter, check_finite, check_per_element,
                                      check_positions, coordinate_scale, edge_lengths, gram,
                                      run_chunked)

__all__ = ["energy", "gradient", "hessian", "gradient_hessian", "angle", "eigensystem",
           "w_matrix", "w_jacobians", "w_gradient", "rest_weight", "DEGENERATE_TOL"]

TERM = "twist"

#: Relative size of a (or b) below which the twist element is dropped (module doc).
DEGENERATE_TOL = 1e-6

_SQRT_HALF = np.sqrt(0.5)


class _TwistGeometry:
    """Edges, projections and the (a, b) angle frame of n validated twist elements.

    Vectors are component-major (3, n), as in :mod:`lc_petsc.elements.angle`.
    """

    def __init__(self, x, offset=0):
        xs = x.transpose(1, 2, 0)             # (vertex, component, element)
        self.e0 = xs[0] - xs[1]
        self.e1 = xs[2] - xs[1]
        self.e2 = xs[3] - xs[2]
        scale = coordinate_scale(x)
        l0 = edge_lengths(self.e0, scale, TERM, "x0 - x1", offset)
        l1 = edge_lengths(self.e1, scale, TERM, "x2 - x1", offset)
        l2 = edge_lengths(self.e2, scale, TERM, "x3 - x2", offset)
        self.inv_l1_sq = 1.0 / (l1 * l1)
        self.alpha = dot3(self.e0, self.e1) * self.inv_l1_sq
        self.beta = dot3(self.e2, self.e1) * self.inv_l1_sq
        self.a = self.e0 - self.alpha * self.e1
        self.b = self.e2 - self.beta * self.e1
        la, lb = norm3(self.a), norm3(self.b)
        self.active = (la >= DEGENERATE_TOL * l0) & (lb >= DEGENERATE_TOL * l2)
        # Inactive elements get a harmless stand-in frame; their stiffness is zeroed.
        if not self.active.all():
            off = ~self.active
            la, lb = np.where(off, 1.0, la), np.where(off, 1.0, lb)
            self.a[:, off] = any_perpendicular(self.e1[:, off])
            self.b[:, off] = self.a[:, off]
        self.sigma = np.where(dot3(cross3(self.a, self.b), self.e1) < 0.0, -1.0, 1.0)
        # Where a and b are parallel, n = (a x b)/|a x b| = sigma e1h is the limit.
        axis = self.e1 * (self.sigma * np.sqrt(self.inv_l1_sq))
        self.frame = AngleFrame(self.a, self.b, la, lb, axis=axis)
        self.phi = np.where(self.active, self.sigma * self.frame.theta, 0.0)

    def params(self, rest_angle, k):
        """(k, wrap(phi - phibar), d = dPsi/dtheta) with k zeroed on inactive elements."""
        k = np.where(self.active, k, 0.0)
        dphi = wrap_angle(self.phi - rest_angle)
        return k, dphi, self.sigma * k * dphi

    def simplified_transpose(self, u, v, w=None):
        """P^T [u; v; w] for W-space vectors (3, r, n) each -> vertex space (12, r, n)."""
        al, be = self.alpha, self.beta
        x1 = (al - 1.0) * u + be * v
        x2 = -al * u - (1.0 + be) * v
        if w is not None:
            x1 -= w
            x2 += w
        return np.concatenate([u, x1, x2, v], axis=0)

    def variation_transpose(self, u, v):
        """Dt^T [u; v; 0] for W-space vectors (3, r, n) each -> vertex space (12, r, n).

        Dt's blocks are e1 w^T / |e1|^2, so only e1.u and e1.v matter.
        """
        e0, e1, e2 = self.e0[:, None], self.e1[:, None], self.e2[:, None]
        al, be = self.alpha, self.beta
        pu = dot3(e1, u) * self.inv_l1_sq
        pv = dot3(e1, v) * self.inv_l1_sq
        x1 = ((2.0 * al - 1.0) * e1 - e0) * pu + (2.0 * be * e1 - e2) * pv
        x2 = (e0 - 2.0 * al * e1) * pu - ((2.0 * be + 1.0) * e1 - e2) * pv
        return np.concatenate([e1 * pu, x1, x2, e1 * pv], axis=0)


def _inputs(x, rest_angle, stiffness):
    x = check_positions(x, 4, TERM)
    n = x.shape[0]
    return (x, check_finite(rest_angle, n, TERM, "rest angle"),
            check_per_element(stiffness, n, TERM, "stiffness"))


def rest_weight(x, sine):
    """Weight (n,) of each twist element's stiffness from its rest stencil x (n, 4, 3).

    The torsion of a straight stencil is undefined, and near it the angle turns by O(1)
    when a vertex moves by O(s |e|), s = min(|a| / |e0|, |b| / |e2|) (the sine of the
    smaller bend angle): a stencil straight at rest has no rest torsion to return to, and
    one nearly straight at rest has a rest angle that its noise decides, and passes
    through straight (where the energy jumps, module doc) whenever it bends by its
    noise.  The weight is 0 for s <= ``sine`` / 2, the smooth step t^2 (3 - 2 t) of t =
    2 s / ``sine`` - 1 up to s = ``sine``, and exactly 1 from there on (so curled
    stencils keep their stiffness bit for bit).  ``sine`` = 0: every element weighs 1
    (the paper's rule alone: elements degenerate in the current stencil are dropped, see
    the module doc).  docs/elements.md."""
    x = check_positions(x, 4, TERM)
    if not (np.isfinite(sine) and 0.0 <= sine < 1.0):
        raise ValueError(f"twist rest sine {sine!r} must be in [0, 1): the sine of the bend "
                         "angle below which a straight rest stencil's torsion is faded out")
    if sine == 0.0:
        return np.ones(x.shape[0])
    # |a| / |e0| and |b| / |e2| are the sines of the bend angles at x1 and x2
    s = np.minimum(np.sin(bend.angle(x[:, 0:3])), np.sin(bend.angle(x[:, 1:4])))
    t = np.clip(2.0 * s / sine - 1.0, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def angle(x):
    """Signed twist angle phi in (-pi, pi], shape (n,) (0 for degenerate elements)."""
    return _TwistGeometry(check_positions(x, 4, TERM)).phi


def energy(x, rest_angle, stiffness):
    """Psi_t per element, shape (n,)."""
    x, rest_angle, k = _inputs(x, rest_angle, stiffness)
    k, dphi, _ = _TwistGeometry(x).params(rest_angle, k)
    return 0.5 * k * dphi * dphi


def w_matrix(x):
    """W = [a | b | e1] per element, shape (n, 3, 3) (columns)."""
    geo = _TwistGeometry(check_positions(x, 4, TERM))
    return np.stack([geo.a.T, geo.b.T, geo.e1.T], axis=2)


def w_jacobians(x):
    """(P, J): simplified and exact dW/dx, each (n, 9, 12); rows vec(W) = [a; b; e1]."""
    geo = _TwistGeometry(check_positions(x, 4, TERM))
    n = geo.phi.shape[0]
    basis = np.broadcast_to(np.eye(9)[:, :, None], (9, 9, n))   # (W row, column, element)
    # P^T and Dt^T applied to the 9 unit vectors of W-space give P^T and Dt^T.
    pt = geo.simplified_transpose(basis[:3], basis[3:6], basis[6:])
    dtt = geo.variation_transpose(basis[:3], basis[3:6])
    p = pt.transpose(2, 1, 0)
    return p, p - dtt.transpose(2, 1, 0)


def w_gradient(x, rest_angle, stiffness):
    """dPsi_t/dvec(W), shape (n, 9) ordered [a; b; e1]."""
    x, rest_angle, k = _inputs(x, rest_angle, stiffness)
    geo = _TwistGeometry(x)
    _, _, d = geo.params(rest_angle, k)
    ga, gb = geo.frame.theta_gradient()
    return np.concatenate([(d * ga).T, (d * gb).T, np.zeros((d.shape[0], 3))], axis=1)


def eigensystem(x, rest_angle, stiffness):
    """Eigenpairs of the unit-column Hessian of Psi_t in (a, b): lam (n, 6), q (n, 6, 6)."""
    x, rest_angle, k = _inputs(x, rest_angle, stiffness)
    geo = _TwistGeometry(x)
    k, _, d = geo.params(rest_angle, k)
    return geo.frame.eigensystem(d, k)


def _out_of_plane(geo, d):
    """The out-of-plane pairs j = 0, 1 ([n; n] and [n; -n] / sqrt 2, n = sigma e1h).

    Their exact contribution lam_j (A A^T - B B^T), A = P^T S q_j, B = Dt^T S q_j, is
    1/2 (p m^T + m p^T) with m = A + B = 2 A - J^T S q_j and p = lam_j J^T S q_j. With
    mu = sigma / (sqrt 2 |a|), nu = +-sigma / (sqrt 2 |b|) (S q_j = [mu e1h; nu e1h]):
    J^T S q_j = [0; w; -w; 0] / |e1| with w = mu a + nu b = sigma (ah +- bh) / sqrt 2, and
    lam_j ~ 1/sin(theta) is singular at planar stencils while w vanishes; lam_j w has the
    cancellation-free forms d (-s ah + (1 - c) b0) and d (s ah + (1 + c) b0) (times
    sigma / sqrt 2). Returns p, m: (12, 2, n) each.
    """
    frame = geo.frame
    inv_l1 = np.sqrt(geo.inv_l1_sq)
    e1h = geo.e1 * inv_l1
    al, be = geo.alpha, geo.beta
    scale = geo.sigma * _SQRT_HALF
    mu = scale / frame.lu
    m = np.empty((12, 2, d.shape[0]))
    p = np.zeros((12, 2, d.shape[0]))
    st0 = frame.s * frame.t0
    for j, eps in enumerate((1.0, -1.0)):
        nu = eps * scale / frame.lv
        w = (frame.t0 + eps * frame.t1) * (scale * inv_l1)
        m[0:3, j] = (2.0 * mu) * e1h
        m[3:6, j] = (2.0 * ((al - 1.0) * mu + be * nu)) * e1h - w
        m[6:9, j] = (-2.0 * (al * mu + (1.0 + be) * nu)) * e1h + w
        m[9:12, j] = (2.0 * nu) * e1h
        cs = (1.0 - frame.c) if eps > 0 else (1.0 + frame.c)
        lw = (cs * frame.b0 - eps * st0) * (d * scale * inv_l1)
        p[3:6, j] = lw
        p[6:9, j] = -lw
    return p, m


def _balanced_columns(p, m):
    """Columns z+, z- (12, r, n) with z+ z+^T - z- z-^T = 1/2 (p m^T + m p^T) per column.

    z+- = (p / g +- g m) / 2 with g = sqrt(|p| / |m|), so both have the same size and the
    difference loses nothing to cancellation (p and m carry different units). z+ z+^T is
    also the PSD part of 1/2 (p m^T + m p^T), whose eigenvalues are (p.m +- |p||m|)/2.
    """
    norm_p, norm_m = np.sqrt((p * p).sum(axis=0)), np.sqrt((m * m).sum(axis=0))
    both = (norm_p > 0) & (norm_m > 0)
    inv_g = np.sqrt(np.divide(norm_m, norm_p, out=np.zeros_like(norm_p), where=both))
    g = np.sqrt(np.divide(norm_p, norm_m, out=np.zeros_like(norm_m), where=both))
    return 0.5 * (p * inv_g + m * g), 0.5 * (p * inv_g - m * g)


def _exact_columns(geo, d, k):
    """Columns and weights of the exact Hessian: K = sum_j w_j c_j c_j^T, c (12, 8, n)."""
    frame = geo.frame
    lam, q = frame.eigensystem(d, k)
    qs = q.transpose(1, 2, 0)[:, 2:]          # in-plane pairs 2..5: Dt^T vanishes on them
    in_plane = geo.simplified_transpose(qs[:3] / frame.lu, qs[3:] / frame.lv)
    plus, minus = _balanced_columns(*_out_of_plane(geo, d))
    one = np.ones((d.shape[0], 2))
    return (np.concatenate([in_plane, plus, minus], axis=1),
            np.concatenate([lam[:, 2:], one, -one], axis=1))


def _kernel(filter):
    def kernel(lo, inputs, g, h):
        x, rest_angle, k = inputs
        geo = _TwistGeometry(x, lo)
        k, _, d = geo.params(rest_angle, k)
        frame = geo.frame
        if g is not None:
            ga, gb = frame.theta_gradient()
            gx = geo.simplified_transpose((d * ga)[:, None], (d * gb)[:, None])
            g[:] = gx[:, 0].T.reshape(-1, 4, 3)
        if h is None:
            return
        if filter == "analytic":
            lam, top, bot, _ = frame.positive_part(d, k)
            keep = [0, 2]                     # the in-plane pairs; out-of-plane below
            root = np.sqrt(lam[keep])
            in_plane = geo.simplified_transpose(top[:, keep] * (root / frame.lu),
                                                bot[:, keep] * (root / frame.lv))
            plus, _ = _balanced_columns(*_out_of_plane(geo, d))
            gram(np.concatenate([in_plane, plus], axis=1), out=h)
        elif filter == "abs":
            columns, weights = _exact_columns(geo, d, k)
            gram(columns, np.abs(weights), out=h)
        else:
            gram(*_exact_columns(geo, d, k), out=h)
            if filter == "numerical":
                lam_x, q_x = np.linalg.eigh(h)
                gram(q_x.transpose(1, 2, 0), np.maximum(lam_x, 0.0), out=h)
        if not geo.active.all():
            h[~geo.active] = 0.0              # dropped elements: exactly zero
    return kernel


def gradient(x, rest_angle, stiffness):
    """dPsi_t/dx = P^T dPsi_t/dW, shape (n, 4, 3)."""
    inputs = _inputs(x, rest_angle, stiffness)
    return run_chunked(_kernel("none"), inputs[0].shape[0], 4, inputs, True, False)[0]


def hessian(x, rest_angle, stiffness, filter="analytic", out=None):
    """d2Psi_t/dx2 (n, 12, 12) with ``filter`` in FILTERS (see module doc)."""
    check_filter(filter)
    inputs = _inputs(x, rest_angle, stiffness)
    return run_chunked(_kernel(filter), inputs[0].shape[0], 4, inputs, False, True, out)[1]


def gradient_hessian(x, rest_angle, stiffness, filter="analytic", out=None):
    """(gradient (n, 4, 3), hessian (n, 12, 12)) in one pass over the elements."""
    check_filter(filter)
    inputs = _inputs(x, rest_angle, stiffness)
    return run_chunked(_kernel(filter), inputs[0].shape[0], 4, inputs, True, True, out)
