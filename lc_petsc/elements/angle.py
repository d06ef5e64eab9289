"""The angle between two vectors and its analytic eigensystem (SPEC section 3).

Both bending (columns e0, e1 of T) and twisting (columns a, b of W) are energies
Psi = f(theta) of the unsigned angle theta in [0, pi] between two vectors u, v. This
module holds what they share: theta, its gradient, and the closed-form eigensystem of the
Hessian of Psi with respect to [u; v] at unit-length columns (t0, t1). For columns of
lengths L0, L1 the Hessian is S Hhat S with S = diag(I/L0, I/L1), because theta is
scale-invariant in each column.

Layout: internally component-major ("SoA"): a batch of n vectors is a (3, n) array, so
every arithmetic step runs over contiguous memory (about 2x faster than (n, 3) here).

Notation: t0, t1 unit columns, c = t0.t1, s = |t0 x t1|, n = t0 x t1 / s,
b0 = t0 x n = (c t0 - t1)/s, b1 = t1 x n = (t0 - c t1)/s.
Gradient of theta: d theta/du = b0 / L0, d theta/dv = -b1 / L1.

Eigenpairs of the unit-column Hessian of Psi, d = dPsi/dtheta, k = d2Psi/dtheta2 (SPEC
section 3, with the errata of the printed eqs. 6-7 and 41-42 applied):
    0: d (c-1)/s            on [n; n] / sqrt 2
    1: d (c+1)/s            on [n; -n] / sqrt 2
    2: k + sqrt(k^2 + d^2)  on [d t0 - lam b0; d t1 + lam b1] (normalised)
    3: k - sqrt(k^2 + d^2)  on the same form with its own lam
    4: -d                   on [t0 + b0; -t1 + b1] / 2
    5: +d                   on [t0 - b0; -t1 - b1] / 2

Degenerate rule for bending (straight, theta = pi, or folded back, theta = 0;
s < STRAIGHT_TOL), where no axis is given: theta is a cone point and n is undefined. We
keep the smooth, isotropic second-order part of the energy and drop the cone: the
gradient of theta is taken as 0, and the Hessian is 2k on [m; -c m] / sqrt 2 for the two
unit directions m perpendicular to t0 (c = +-1), 0 on the rest. This equals the exact
Hessian when the rest angle is pi (a straight rest shape), is PSD, and makes every filter
agree. For twisting the columns turn about a known axis (the middle edge, passed as
``axis``), so n is that axis, the gradient is kept, and the two out-of-plane eigenpairs
(one of them singular) are dropped.
"""

import numpy as np

#: Below this sin(theta) a bend counts as exactly straight (or folded): see module doc.
STRAIGHT_TOL = 1e-8

_SQRT_HALF = np.sqrt(0.5)


def cross3(u, v):
    """Cross product of component-major vectors u, v (3, ...)."""
    out = np.empty(np.broadcast_shapes(u.shape, v.shape))
    np.multiply(u[1], v[2], out=out[0])
    out[0] -= u[2] * v[1]
    np.multiply(u[2], v[0], out=out[1])
    out[1] -= u[0] * v[2]
    np.multiply(u[0], v[1], out=out[2])
    out[2] -= u[1] * v[0]
    return out


def dot3(u, v):
    """Dot product of component-major vectors (3, ...) -> (...)."""
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def norm3(u):
    """Euclidean norms of the columns of u (3, m)."""
    return np.sqrt(dot3(u, u))


def any_perpendicular(v):
    """A unit vector perpendicular to each column of v (3, m)."""
    pick = np.zeros_like(v)
    pick[np.argmin(np.abs(v), axis=0), np.arange(v.shape[1])] = 1.0
    p = cross3(v, pick)
    return p / norm3(p)


class AngleFrame:
    """Geometry of the angle between component-major columns u, v (3, n) of lengths lu, lv."""

    def __init__(self, u, v, lu, lv, axis=None):
        self.lu, self.lv = lu, lv
        self.t0 = u / lu
        self.t1 = v / lv
        tx = cross3(self.t0, self.t1)
        self.c = dot3(self.t0, self.t1)
        self.s = norm3(tx)
        self.theta = np.arctan2(self.s, self.c)
        self.degenerate = self.s < STRAIGHT_TOL
        # With an axis (twist: the middle edge), u and v turn about a known axis and the
        # signed angle stays smooth where they are parallel; without one (bend), the
        # degenerate point is a cone (module doc).
        self.cone = axis is None
        self.any_degenerate = bool(self.degenerate.any())
        if self.any_degenerate:
            deg = self.degenerate
            # Any unit normal of t0 will do for the cone rule: it is isotropic about t0.
            tx[:, deg] = any_perpendicular(self.t0[:, deg]) if self.cone else axis[:, deg]
            self.s_safe = np.where(deg, 1.0, self.s)
        else:
            self.s_safe = self.s
        self.n = tx / self.s_safe
        self.b0 = cross3(self.t0, self.n)
        self.b1 = cross3(self.t1, self.n)

    def theta_gradient(self):
        """d theta / d[u, v]: two (3, n) arrays; zero at degenerate (cone) points."""
        gu = self.b0 / self.lu
        gv = self.b1 / -self.lv
        if self.cone and self.any_degenerate:
            gu[:, self.degenerate] = 0.0
            gv[:, self.degenerate] = 0.0
        return gu, gv

    def _one_minus_plus(self, sc):
        """(1 + sc, 1 - sc) for sc = +-c, without cancellation: 1 - c^2 = s^2."""
        # 1 + |sc| is the denominator of whichever branch is taken, and never 0.
        small = self.s * self.s / (1.0 + np.abs(sc))
        one_plus = np.where(sc < 0, small, 1.0 + sc)
        one_minus = np.where(sc > 0, small, 1.0 - sc)
        return one_plus, one_minus

    @staticmethod
    def _ratio(d, k):
        """(lam_2, r) with lam_2 = k + sqrt(k^2 + d^2) and r = d / lam_2 (0 if k = d = 0)."""
        lam2 = k + np.sqrt(k * k + d * d)
        return lam2, np.divide(d, lam2, out=np.zeros_like(d), where=lam2 > 0)

    def theta_eigensystem(self):
        """Eigenpairs of the unit-column Hessian of theta: lam (n, 6), q (n, 6, 6) columns.

        Only defined away from degenerate points (NaN there).
        """
        s = np.where(self.degenerate, np.nan, self.s)
        one = np.ones_like(s)
        lam = np.stack([(self.c - 1) / s, (self.c + 1) / s, -one, one, -one, one], axis=1)
        z = np.zeros_like(self.t0)
        n, t0, t1, b0, b1 = self.n, self.t0, self.t1, self.b0, self.b1
        cols = [(n, n), (n, -n), (t0 + b0, z), (t0 - b0, z), (z, t1 - b1), (z, t1 + b1)]
        return lam, _as_columns(cols, [_SQRT_HALF] * 6)

    def eigensystem(self, d, k):
        """All six eigenpairs of the unit-column Hessian of Psi(theta).

        d = dPsi/dtheta, k = d2Psi/dtheta2 (n,). Returns lam (n, 6) and unit eigenvectors
        q (n, 6, 6) as columns, in the order of the module docstring.
        """
        t0, t1, b0, b1, n = self.t0, self.t1, self.b0, self.b1, self.n
        one_plus, one_minus = self._one_minus_plus(self.c)
        lam2, r = self._ratio(d, k)
        lam = np.stack([-d * one_minus / self.s_safe, d * one_plus / self.s_safe,
                        lam2, -d * r, -d, d], axis=1)
        # [d t0 - lam b0; d t1 + lam b1] divided by lam_2 (resp. d) so that d -> 0 is
        # smooth; both halves have squared norm r^2 + 1 since t0 _|_ b0 and t1 _|_ b1.
        sc = 1.0 / np.sqrt(2.0 * (1.0 + r * r))
        cols = [(n, n), (n, -n), (r * t0 - b0, r * t1 + b1), (t0 + r * b0, t1 - r * b1),
                (t0 + b0, b1 - t1), (t0 - b0, -t1 - b1)]
        q = _as_columns(cols, [_SQRT_HALF, _SQRT_HALF, sc, sc, 0.5, 0.5])
        if self.any_degenerate:
            deg = self.degenerate
            if self.cone:
                lam_d, q_d = self._cone_eigensystem(k[deg])
                lam[deg], q[deg] = lam_d, q_d
            else:
                # Parallel columns turning about a given axis: (c -+ 1)/s is 0 for one of
                # the two out-of-plane pairs and singular for the other; both are dropped.
                lam[deg, :2] = 0.0
        return lam, q

    def positive_part(self, d, k):
        """The eigenpairs of the unit-column Hessian that the analytic filter keeps.

        lam_2 = k + sqrt(k^2 + d^2) is always >= 0 and lam_3 <= 0; of the pairs (0, 1) and
        (4, 5) exactly one member is >= 0, chosen by the sign of d. Returns
        ``lam (3, n)``, ``top (3, 3, n)``, ``bottom (3, 3, n)`` (component, column,
        element; column j is the unit eigenvector [top_j; bottom_j]) and the out-of-plane
        pair that is dropped, ``(lam_neg (n,), sign (n,))``: eigenvalue lam_neg <= 0 on
        [n; sign n] / sqrt 2.
        """
        t0, t1, b0, b1, n = self.t0, self.t1, self.b0, self.b1, self.n
        sd = np.where(d >= 0.0, 1.0, -1.0)
        ad = np.abs(d)
        lam2, r = self._ratio(d, k)
        one_plus, one_minus = self._one_minus_plus(sd * self.c)
        m = d.shape[0]
        lam = np.empty((3, m))
        top = np.empty((3, 3, m))
        bot = np.empty((3, 3, m))
        lam[0] = lam2
        lam[1] = ad * one_plus / self.s_safe
        lam[2] = ad
        sc = 1.0 / np.sqrt(2.0 * (1.0 + r * r))
        rs = r * sc
        np.subtract(rs * t0, sc * b0, out=top[:, 0])
        np.add(rs * t1, sc * b1, out=bot[:, 0])
        np.multiply(n, _SQRT_HALF, out=top[:, 1])
        np.multiply(n, -_SQRT_HALF * sd, out=bot[:, 1])
        hsd = 0.5 * sd
        np.subtract(0.5 * t0, hsd * b0, out=top[:, 2])
        np.add(-0.5 * t1, -hsd * b1, out=bot[:, 2])
        lam_neg = -ad * one_minus / self.s_safe
        if self.any_degenerate:
            deg = self.degenerate
            lam_neg[deg] = 0.0
            if self.cone:
                lam_d, q_d = self._cone_eigensystem(k[deg])
                lam[:, deg] = lam_d[:, :3].T
                top[:, :, deg] = q_d[:, :3, :3].transpose(1, 2, 0)
                bot[:, :, deg] = q_d[:, 3:, :3].transpose(1, 2, 0)
            else:
                lam[1, deg] = 0.0
        return lam, top, bot, (lam_neg, sd)

    def _cone_eigensystem(self, k_deg):
        """Isotropic rule of the module doc for the degenerate elements: (m, 6), (m, 6, 6)."""
        deg = self.degenerate
        m1, m2, t0 = self.n[:, deg], self.b0[:, deg], self.t0[:, deg]
        c = np.sign(self.c[deg])
        z = np.zeros_like(t0)
        lam = np.zeros((k_deg.shape[0], 6))
        lam[:, 0] = lam[:, 1] = 2.0 * k_deg
        cols = [(m1, -c * m1), (m2, -c * m2), (m1, c * m1), (m2, c * m2), (t0, z), (z, t0)]
        return lam, _as_columns(cols, [_SQRT_HALF] * 4 + [1.0, 1.0])


def _as_columns(cols, scales):
    """Stack component-major (top, bottom) pairs into eigenvector columns q (n, 6, r)."""
    q = np.empty((cols[0][0].shape[1], 6, len(cols)))
    for j, ((top, bot), scale) in enumerate(zip(cols, scales)):
        q[:, :3, j] = (top * scale).T
        q[:, 3:, j] = (bot * scale).T
    return q


def wrap_angle(a):
    """Wrap angles into (-pi, pi]."""
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)
