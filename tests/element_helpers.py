"""Independent reference implementations and utilities for the element-kernel tests.

Nothing here imports ``lc_petsc``: every quantity is recomputed from its definition in
SPEC section 2/3 so that the tests compare the kernels against something independent.
Simple, obviously-correct code is preferred over speed.
"""

from __future__ import annotations

import contextlib
import warnings

import numpy as np

TWO_PI = 2.0 * np.pi


# --------------------------------------------------------------------------- basics
def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def wrap(angle):
    """Wrap into (-pi, pi]."""
    return angle - TWO_PI * np.ceil((angle - np.pi) / TWO_PI)


def random_rotation(rng):
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def blockdiag_rot(R, nverts):
    return np.kron(np.eye(nverts), R)


@contextlib.contextmanager
def no_numpy_warnings():
    """Any NumPy floating-point warning (divide, overflow, invalid) or Python warning
    becomes an error.  Underflow is deliberately left alone: flushing a tiny number to
    zero is not a defect."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with np.errstate(divide="raise", over="raise", invalid="raise", under="ignore"):
            yield


def min_eig_ratio(H):
    """min eigenvalue / max |eigenvalue| per matrix (0 for an all-zero matrix)."""
    H = 0.5 * (H + np.swapaxes(H, -1, -2))
    w = np.linalg.eigvalsh(H)
    top = np.max(np.abs(w), axis=-1)
    return np.where(top > 0, w[..., 0] / np.where(top > 0, top, 1.0), 0.0)


def rel_fro(A, B):
    """Relative Frobenius difference per matrix, ||A - B|| / max(||A||, ||B||, tiny)."""
    num = np.linalg.norm((A - B).reshape(A.shape[0], -1), axis=1)
    den = np.maximum(
        np.maximum(
            np.linalg.norm(A.reshape(A.shape[0], -1), axis=1),
            np.linalg.norm(B.reshape(B.shape[0], -1), axis=1),
        ),
        1e-300,
    )
    return num / den


# --------------------------------------------------------------- difference operators
# Vertex-major flattening: row 3*v + c.
def stretch_D():
    """e = x1 - x0 as a 3x6 matrix."""
    I = np.eye(3)
    return np.hstack([-I, I])


def bend_D():
    """T = [e0; e1] (6) from x (9): e0 = x0 - x1, e1 = x2 - x1."""
    I, Z = np.eye(3), np.zeros((3, 3))
    return np.block([[I, -I, Z], [Z, -I, I]])


def pinv_rows(D):
    """Right inverse of a full-row-rank D: D @ Dp = I."""
    return D.T @ np.linalg.inv(D @ D.T)


# ----------------------------------------------------------------------- stretch ref
def ref_stretch_energy(x, rest_length, k):
    e = x[..., 1, :] - x[..., 0, :]
    L = np.linalg.norm(e, axis=-1)
    return 0.5 * k * (L - rest_length) ** 2


def ref_stretch_hessian_e(e, rest_length, k):
    """3x3 Hessian in e (SPEC section 2), one element."""
    L = np.linalg.norm(e)
    eh = e / L
    P = np.outer(eh, eh)
    return k * P + k * (1.0 - rest_length / L) * (np.eye(3) - P)


# -------------------------------------------------------------------------- bend ref
def ref_theta(e0, e1):
    return np.arctan2(np.linalg.norm(np.cross(e0, e1), axis=-1), np.sum(e0 * e1, axis=-1))


def ref_bend_angle(x):
    return ref_theta(x[..., 0, :] - x[..., 1, :], x[..., 2, :] - x[..., 1, :])


def ref_bend_energy(x, rest_angle, k):
    return 0.5 * k * (ref_bend_angle(x) - rest_angle) ** 2


def ref_theta_T(T, *_):
    """theta as a function of the 6-vector T = [e0; e1] (last axis)."""
    return ref_theta(T[..., :3], T[..., 3:])


def ref_psi_T(T, rest_angle, k):
    return 0.5 * k * (ref_theta(T[..., :3], T[..., 3:]) - rest_angle) ** 2


def frame(t0, t1):
    """s, c, n, b0, b1 of SPEC section 3 for unit t0, t1 (one element)."""
    cr = np.cross(t0, t1)
    s = np.linalg.norm(cr)
    c = float(np.dot(t0, t1))
    n = cr / s
    return s, c, n, np.cross(t0, n), np.cross(t1, n)


def spec_theta_eigensystem(t0, t1):
    """SPEC section 3 eigenpairs of d2 theta / dT2 at unit columns, SPEC order."""
    s, c, n, b0, b1 = frame(t0, t1)
    z = np.zeros(3)
    lam = np.array([(c - 1) / s, (c + 1) / s, -1.0, 1.0, -1.0, 1.0])
    vecs = [
        np.r_[n, n], np.r_[n, -n],
        np.r_[t0 + b0, z], np.r_[t0 - b0, z],
        np.r_[z, t1 - b1], np.r_[z, t1 + b1],
    ]
    return lam, np.stack([unit(v) for v in vecs], axis=1)


def printed_theta_eigs_6_7(t0, t1):
    """Printed supplement eqs. 6-7 (erratum 1): (lambda, q) pairs."""
    s, c, n, b0, b1 = frame(t0, t1)
    z = np.zeros(3)
    return [(-1.0, unit(np.r_[z, t1 + b1])), (1.0, unit(np.r_[z, t1 - b1]))]


def spec_psi_eigensystem(t0, t1, k, d):
    """SPEC section 3 eigenpairs of d2 Psi_b / dT2 at unit columns (d = k(theta-bar))."""
    s, c, n, b0, b1 = frame(t0, t1)
    r = np.sqrt(k * k + d * d)
    lp, lm = k + r, k - r
    lam = np.array([d * (c - 1) / s, d * (c + 1) / s, lp, lm, -d, d])
    q2 = np.r_[d * t0 - lp * b0, d * t1 + lp * b1]
    if abs(d) > 1e-300:
        q3 = np.r_[d * t0 - lm * b0, d * t1 + lm * b1]
    else:  # d -> 0 limit of the direction
        q3 = np.r_[t0, t1]
    vecs = [np.r_[n, n], np.r_[n, -n], q2, q3, np.r_[t0 + b0, -t1 + b1], np.r_[t0 - b0, -t1 - b1]]
    return lam, np.stack([unit(v) for v in vecs], axis=1)


def printed_psi_eigs_41_42(t0, t1, k, d):
    """Printed supplement eqs. 41-42 (erratum 2): +d on [t0+b0; -t1+b1], -d on [t0-b0; -t1-b1]."""
    s, c, n, b0, b1 = frame(t0, t1)
    return [(d, unit(np.r_[t0 + b0, -t1 + b1])), (-d, unit(np.r_[t0 - b0, -t1 - b1]))]


def printed_A_eigs_32_33(t0, t1):
    """Printed eqs. 32-33 (erratum 3) for A = g g^T + d2theta/dT2 (i.e. k = d = 1)."""
    s, c, n, b0, b1 = frame(t0, t1)
    out = []
    for lam in (s * s + np.sqrt(s**4 + 1), s * s - np.sqrt(s**4 + 1)):
        out.append((lam, unit(np.r_[t0 - lam * b0, t1 + lam * b1])))
    return out


# ------------------------------------------------------------------------- twist ref
def ref_twist_parts(x):
    e0 = x[..., 0, :] - x[..., 1, :]
    e1 = x[..., 2, :] - x[..., 1, :]
    e2 = x[..., 3, :] - x[..., 2, :]
    ee = np.sum(e1 * e1, axis=-1, keepdims=True)
    a = e0 - np.sum(e0 * e1, axis=-1, keepdims=True) / ee * e1
    b = e2 - np.sum(e2 * e1, axis=-1, keepdims=True) / ee * e1
    return e0, e1, e2, a, b


def ref_twist_angle(x):
    e0, e1, e2, a, b = ref_twist_parts(x)
    e1h = unit(e1)
    return np.arctan2(np.sum(e1h * np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def ref_twist_energy(x, rest_angle, k):
    return 0.5 * k * wrap(ref_twist_angle(x) - rest_angle) ** 2


def ref_w_matrix(x):
    e0, e1, e2, a, b = ref_twist_parts(x)
    return np.stack([a, b, e1], axis=-1)


def vecW(W):
    """Column-major vec of (..., 3, 3): [col0; col1; col2]."""
    return np.swapaxes(W, -1, -2).reshape(W.shape[:-2] + (9,))


def ref_psi_W(w, sign, rest_angle, k):
    """Psi_t as a function of vec(W) = [a; b; e1] with the orientation sign held fixed."""
    th = ref_theta(w[..., 0:3], w[..., 3:6])
    return 0.5 * k * wrap(sign * th - rest_angle) ** 2


def ref_twist_P(x):
    """Simplified dW/dx of supplement eq. 46 (alpha, beta frozen), 9x12, one element."""
    e0, e1, e2, a, b = ref_twist_parts(x)
    ee = e1 @ e1
    al, be = (e0 @ e1) / ee, (e2 @ e1) / ee
    M = np.array([[1.0, al - 1.0, -al, 0.0], [0.0, be, -be - 1.0, 1.0], [0.0, -1.0, 1.0, 0.0]])
    return np.kron(M, np.eye(3))


def ref_twist_J(x):
    """Exact dW/dx, 9x12, one element (derived directly, not from the supplement)."""
    e0, e1, e2, a, b = ref_twist_parts(x)
    ee = e1 @ e1
    I = np.eye(3)
    J = np.zeros((9, 12))
    # a = e0 - (e0.e1/ee) e1 ; de0 = dx0 - dx1 ; de1 = dx2 - dx1
    # da = de0 - e1 (e1^T de0 + e0^T de1)/ee - (e0.e1/ee) de1 + 2 (e0.e1) e1 e1^T de1 / ee^2
    al = (e0 @ e1) / ee
    A_e0 = I - np.outer(e1, e1) / ee
    A_e1 = -np.outer(e1, e0) / ee - al * I + 2 * al * np.outer(e1, e1) / ee
    be = (e2 @ e1) / ee
    B_e2 = I - np.outer(e1, e1) / ee
    B_e1 = -np.outer(e1, e2) / ee - be * I + 2 * be * np.outer(e1, e1) / ee
    # e0 = x0 - x1, e1 = x2 - x1, e2 = x3 - x2
    dE0 = np.hstack([I, -I, 0 * I, 0 * I])
    dE1 = np.hstack([0 * I, -I, I, 0 * I])
    dE2 = np.hstack([0 * I, 0 * I, -I, I])
    J[0:3] = A_e0 @ dE0 + A_e1 @ dE1
    J[3:6] = B_e2 @ dE2 + B_e1 @ dE1
    J[6:9] = dE1
    return J


def spec_twist_H_W(x, rest_angle, k):
    """9x9 Hessian of Psi_t in vec(W) from the SPEC bend-like eigensystem in (a, b)
    (own implementation), scaled to the actual |a|, |b|, zero on the e1 column.
    Returns (H_W, lam, Q_unit, S) for one element."""
    e0, e1, e2, a, b = ref_twist_parts(x)
    phi = ref_twist_angle(x)
    sgn = 1.0 if np.dot(unit(e1), np.cross(a, b)) >= 0 else -1.0
    d = sgn * k * wrap(phi - rest_angle)
    la, lb = np.linalg.norm(a), np.linalg.norm(b)
    lam, Q = spec_psi_eigensystem(a / la, b / lb, k, d)
    S = np.diag(np.r_[np.full(3, 1 / la), np.full(3, 1 / lb)])
    H = np.zeros((9, 9))
    H[:6, :6] = S @ ((Q * lam) @ Q.T) @ S
    return H, lam, Q, S


# ------------------------------------------------------------ finite differences
def fd_gradient(energy, x, h):
    """Central differences of energy(x) -> (n,) w.r.t. every coordinate of x (n,k,3).
    h: scalar or (n,) per-element step."""
    n, k, _ = x.shape
    h = np.broadcast_to(np.asarray(h, dtype=float), (n,))
    g = np.zeros_like(x)
    for v in range(k):
        for c in range(3):
            xp = x.copy()
            xm = x.copy()
            xp[:, v, c] += h
            xm[:, v, c] -= h
            g[:, v, c] = (energy(xp) - energy(xm)) / (2 * h)
    return g


def fd_jacobian(fun, x, h):
    """Central differences of fun(x) -> (n, m) w.r.t. x (n,k,3); returns (n, m, 3k)."""
    n, k, _ = x.shape
    h = np.broadcast_to(np.asarray(h, dtype=float), (n,))
    cols = []
    for v in range(k):
        for c in range(3):
            xp = x.copy()
            xm = x.copy()
            xp[:, v, c] += h
            xm[:, v, c] -= h
            cols.append((fun(xp) - fun(xm)) / (2 * h)[:, None])
    return np.stack(cols, axis=-1)


def fd_hessian_of_gradient(gradient, x, h):
    """Central differences of gradient(x) -> (n,k,3); returns (n, 3k, 3k)."""
    n, k, _ = x.shape
    return fd_jacobian(lambda y: gradient(y).reshape(n, 3 * k), x, h)


def fd_hessian_scalar(f, z, h):
    """Second central differences of scalar f(z) (z (n, m), f -> (n,)); (n, m, m)."""
    n, m = z.shape
    H = np.zeros((n, m, m))
    f0 = f(z)
    for i in range(m):
        zp = z.copy(); zp[:, i] += h
        zm = z.copy(); zm[:, i] -= h
        H[:, i, i] = (f(zp) - 2 * f0 + f(zm)) / h**2
        for j in range(i + 1, m):
            zpp = z.copy(); zpp[:, i] += h; zpp[:, j] += h
            zpm = z.copy(); zpm[:, i] += h; zpm[:, j] -= h
            zmp = z.copy(); zmp[:, i] -= h; zmp[:, j] += h
            zmm = z.copy(); zmm[:, i] -= h; zmm[:, j] -= h
            H[:, i, j] = H[:, j, i] = (f(zpp) - f(zpm) - f(zmp) + f(zmm)) / (4 * h**2)
    return H


def fd_gradient_scalar(f, z, h):
    n, m = z.shape
    g = np.zeros((n, m))
    for i in range(m):
        zp = z.copy(); zp[:, i] += h
        zm = z.copy(); zm[:, i] -= h
        g[:, i] = (f(zp) - f(zm)) / (2 * h)
    return g


def loglog_slope(hs, errs):
    return np.polyfit(np.log(hs), np.log(errs), 1)[0]


def assert_h2_convergence(hs, errs, what, slope_range=(1.8, 2.25), ratio_range=(3.0, 5.3),
                          final_max=None):
    """errs[j] is the error at step hs[j] (hs decreasing by halving).  Checks every halving
    ratio ~ 4 and the fitted log-log slope ~ 2."""
    hs = np.asarray(hs, float)
    errs = np.asarray(errs, float)
    assert np.all(np.isfinite(errs)), f"{what}: non-finite FD errors {errs}"
    assert np.all(errs > 0), f"{what}: FD error is exactly zero, cannot measure order {errs}"
    ratios = errs[:-1] / errs[1:]
    slope = loglog_slope(hs, errs)
    msg = f"{what}: errors {errs}, halving ratios {ratios}, slope {slope:.3f}"
    assert slope_range[0] <= slope <= slope_range[1], msg
    assert np.all((ratios >= ratio_range[0]) & (ratios <= ratio_range[1])), msg
    if final_max is not None:
        assert errs[-1] <= final_max, msg


# ----------------------------------------------------------------- configurations
def random_edge_lengths(rng, n, scale):
    return scale * rng.uniform(0.5, 2.0, n)


def random_stretch(rng, n, scale):
    """Random edges of length ~scale, rest lengths in [0.5, 1.5] x current length."""
    x0 = scale * rng.uniform(-1, 1, (n, 3))
    e = unit(rng.standard_normal((n, 3))) * random_edge_lengths(rng, n, scale)[:, None]
    x = np.stack([x0, x0 + e], axis=1)
    rest = np.linalg.norm(e, axis=1) * rng.uniform(0.5, 1.5, n)
    return x, rest


def random_bend(rng, n, scale, min_sin=0.25):
    """Random bends with sin(theta) >= min_sin (away from the cone points)."""
    out = []
    while len(out) < n:
        u0, u1 = unit(rng.standard_normal(3)), unit(rng.standard_normal(3))
        if np.linalg.norm(np.cross(u0, u1)) < min_sin:
            continue
        L0, L1 = random_edge_lengths(rng, 2, scale)
        c = scale * rng.uniform(-1, 1, 3)
        out.append([c + L0 * u0, c, c + L1 * u1])
    return np.array(out)


def bend_from_units(t0, t1, center=None, L0=1.0, L1=1.0):
    c = np.zeros(3) if center is None else center
    return np.array([c + L0 * t0, c, c + L1 * t1])


def random_twist(rng, n, scale, min_ratio=0.3, min_sin=0.25):
    """Random twist stencils with |a|/|e0|, |b|/|e2| >= min_ratio and |sin phi| >= min_sin."""
    out = []
    while len(out) < n:
        L = random_edge_lengths(rng, 3, scale)
        e = unit(rng.standard_normal((3, 3))) * L[:, None]
        x1 = scale * rng.uniform(-1, 1, 3)
        x = np.array([x1 + e[0], x1, x1 + e[1], x1 + e[1] + e[2]])
        e0, e1, e2, a, b = ref_twist_parts(x)
        if np.linalg.norm(a) / L[0] < min_ratio or np.linalg.norm(b) / L[2] < min_ratio:
            continue
        s = np.linalg.norm(np.cross(unit(a), unit(b)))
        if s < min_sin:
            continue
        out.append(x)
    return np.array(out)


def twist_from_ab(a, b, e1, x1=None):
    """A twist stencil whose projected edges are exactly a and b (requires a, b _|_ e1),
    with the outer edges given an axial component so that alpha, beta != 0."""
    x1 = np.zeros(3) if x1 is None else x1
    e0 = a + 0.3 * e1
    e2 = b - 0.2 * e1
    return np.array([x1 + e0, x1, x1 + e1, x1 + e1 + e2])


# ------------------------------------------------------- closed-form reference gradients
def ref_stretch_gradient(x, rest_length, k):
    e = x[:, 1] - x[:, 0]
    L = np.linalg.norm(e, axis=-1)
    ge = (np.asarray(k) * (L - rest_length) / L)[:, None] * e
    return np.stack([-ge, ge], axis=1)


def ref_angle_gradient(u, v):
    """d angle(u, v) / du and / dv (SPEC section 2 formula), batched."""
    lu = np.linalg.norm(u, axis=-1, keepdims=True)
    lv = np.linalg.norm(v, axis=-1, keepdims=True)
    tu, tv = u / lu, v / lv
    c = np.sum(tu * tv, axis=-1, keepdims=True)
    s = np.linalg.norm(np.cross(tu, tv), axis=-1, keepdims=True)
    return -(tv - c * tu) / (lu * s), -(tu - c * tv) / (lv * s)


def ref_bend_gradient(x, rest_angle, k):
    e0 = x[:, 0] - x[:, 1]
    e1 = x[:, 2] - x[:, 1]
    g0, g1 = ref_angle_gradient(e0, e1)
    d = (np.asarray(k) * (ref_theta(e0, e1) - rest_angle))[:, None]
    return np.stack([d * g0, -d * (g0 + g1), d * g1], axis=1)


def ref_twist_sign(x):
    e0, e1, e2, a, b = ref_twist_parts(x)
    return np.where(np.sum(e1 * np.cross(a, b), axis=-1) >= 0, 1.0, -1.0)


def ref_twist_w_gradient(x, rest_angle, k):
    """dPsi_t / dvec(W) = [d dtheta/da; d dtheta/db; 0] with d = sign k wrap(phi - bar)."""
    e0, e1, e2, a, b = ref_twist_parts(x)
    ga, gb = ref_angle_gradient(a, b)
    d = (ref_twist_sign(x) * np.asarray(k) * wrap(ref_twist_angle(x) - rest_angle))[:, None]
    return np.concatenate([d * ga, d * gb, np.zeros_like(ga)], axis=1)


def ref_twist_gradient(x, rest_angle, k):
    gW = ref_twist_w_gradient(x, rest_angle, k)
    return np.stack([ref_twist_J(x[i]).T @ gW[i] for i in range(len(x))]).reshape(len(x), 4, 3)


# -------------------------------------------------------------------- a curly wisp
def helix_wisp(nv=24, radius=0.5, turn=2 * np.pi / 5, rise=0.1):
    """The 4C helix of SPEC section 6 (no stem): 72 degrees and 0.1 cm per vertex."""
    i = np.arange(nv)
    return np.stack([radius * np.cos(i * turn), rise * i, radius * np.sin(i * turn)], axis=1)


def stencils(wisp, k):
    """Consecutive k-vertex stencils of a polyline: (nv - k + 1, k, 3)."""
    return np.stack([wisp[i:i + k] for i in range(len(wisp) - k + 1)])


# ------------------------------------------------------------ per-term test cases
TERMS = ("stretch", "bend", "twist")
NVERT = {"stretch": 2, "bend": 3, "twist": 4}
REF_ENERGY = {"stretch": ref_stretch_energy, "bend": ref_bend_energy, "twist": ref_twist_energy}
REF_GRADIENT = {"stretch": ref_stretch_gradient, "bend": ref_bend_gradient,
                "twist": ref_twist_gradient}


def random_case(term, rng, n, scale, stiffness=None):
    """Random generic (non-degenerate) elements of edge length ~scale with rest quantities
    away from the current ones (so the energy, gradient and indefinite part are nonzero)."""
    k = rng.uniform(0.5, 2.0, n) if stiffness is None else np.broadcast_to(stiffness, (n,)).copy()
    if term == "stretch":
        x, rest = random_stretch(rng, n, scale)
    elif term == "bend":
        x = random_bend(rng, n, scale)
        th = ref_bend_angle(x)
        rest = np.clip(th + rng.choice([-1, 1], n) * rng.uniform(0.2, 0.8, n), 0.05, np.pi - 0.05)
    else:
        x = random_twist(rng, n, scale)
        phi = ref_twist_angle(x)
        rest = wrap(phi + rng.choice([-1, 1], n) * rng.uniform(0.2, 1.2, n))
    return x, rest, k
