"""Stretching energy of an edge (SPEC section 2).

Edge e = x1 - x0 with length L = |e| and rest length Lbar:

    Psi_s = 1/2 k (L - Lbar)^2,   k = k_s = E A / Lbar.

Hessian in e: k eh eh^T + k (1 - Lbar/L) (I - eh eh^T). The perpendicular eigenvalue
k (1 - Lbar/L) (multiplicity 2) is negative under compression; the filters clamp it at 0
("analytic" in closed form, "numerical" through numpy.linalg.eigh of the 3x3 Hessian in
e; both are the exact projection); "abs" replaces it by its absolute value
k |1 - Lbar/L| (Chen et al. 2024), the exact Hessian wherever that is PSD. The vertex
Hessian is D^T H D with D = [-I, I], i.e. [[H, -H], [-H, H]].

Shapes: x (n, 2, 3); rest_length, stiffness (n,) or scalars; energy (n,); gradient
(n, 2, 3); hessian (n, 6, 6), vertex-major.
"""

import numpy as np

from lc_petsc.elements.common import (check_filter, check_per_element, check_positions,
                                      coordinate_scale, edge_lengths, run_chunked)

__all__ = ["energy", "gradient", "hessian", "gradient_hessian", "length"]

TERM = "stretch"


def _inputs(x, rest_length, stiffness):
    x = check_positions(x, 2, TERM)
    n = x.shape[0]
    rest_length = check_per_element(rest_length, n, TERM, "rest length", positive=True)
    stiffness = check_per_element(stiffness, n, TERM, "stiffness")
    return x, rest_length, stiffness


def length(x):
    """Current edge lengths (n,) of x (n, 2, 3)."""
    x = check_positions(x, 2, TERM)
    return np.linalg.norm(x[:, 1] - x[:, 0], axis=1)


def energy(x, rest_length, stiffness):
    """Psi_s per edge, shape (n,)."""
    x, rest_length, k = _inputs(x, rest_length, stiffness)
    e = (x[:, 1] - x[:, 0]).T
    return 0.5 * k * (edge_lengths(e, coordinate_scale(x), TERM, "x1 - x0") - rest_length) ** 2


def _kernel(filter):
    def kernel(lo, inputs, g, h):
        x, rest_length, k = inputs
        e = (x[:, 1] - x[:, 0]).T              # component-major (3, n)
        L = edge_lengths(e, coordinate_scale(x), TERM, "x1 - x0", offset=lo)
        if g is not None:
            ge = (e * (k * (L - rest_length) / L)).T
            g[:, 0] = -ge
            g[:, 1] = ge
        if h is None:
            return
        eh = (e / L).T
        perp = k * (1.0 - rest_length / L)
        if filter == "analytic":
            perp = np.maximum(perp, 0.0)
        elif filter == "abs":
            perp = np.abs(perp)
        he = (k - perp)[:, None, None] * (eh[:, :, None] * eh[:, None, :])
        he[:, [0, 1, 2], [0, 1, 2]] += perp[:, None]
        if filter == "numerical":
            lam, q = np.linalg.eigh(he)
            he = np.matmul(q * np.maximum(lam, 0.0)[:, None, :], q.transpose(0, 2, 1))
        h[:, :3, :3] = he
        h[:, 3:, 3:] = he
        np.negative(he, out=h[:, :3, 3:])
        h[:, 3:, :3] = h[:, :3, 3:]
    return kernel


def gradient(x, rest_length, stiffness):
    """dPsi_s/dx, shape (n, 2, 3)."""
    inputs = _inputs(x, rest_length, stiffness)
    return run_chunked(_kernel("none"), inputs[0].shape[0], 2, inputs, True, False)[0]


def hessian(x, rest_length, stiffness, filter="analytic", out=None):
    """d2Psi_s/dx2, shape (n, 6, 6), with ``filter`` in FILTERS."""
    check_filter(filter)
    inputs = _inputs(x, rest_length, stiffness)
    return run_chunked(_kernel(filter), inputs[0].shape[0], 2, inputs, False, True, out)[1]


def gradient_hessian(x, rest_length, stiffness, filter="analytic", out=None):
    """(gradient (n, 2, 3), hessian (n, 6, 6)) in one pass over the elements."""
    check_filter(filter)
    inputs = _inputs(x, rest_length, stiffness)
    return run_chunked(_kernel(filter), inputs[0].shape[0], 2, inputs, True, True, out)
