"""The compiled element kernels seen through the NumPy kernels' per-element API.

:mod:`lc_petsc.elements.compiled` works on a rank's vertex array and writes into the
band storage of the assembler; for the element tests every element gets its own
vertices (element e owns vertices k e .. k e + k - 1), so its Hessian is the band's
diagonal blocks read back. ``module(term)`` returns an object with ``energy``,
``gradient``, ``hessian`` and ``gradient_hessian`` shaped like the NumPy kernels'.
"""

from types import SimpleNamespace

import numpy as np

from lc_petsc.elements import compiled

K = {"stretch": 2, "bend": 3, "twist": 4}


def _layout(term, x):
    k = K[term]
    x = np.asarray(x, np.float64)
    n = x.shape[0]
    return k, n, np.ascontiguousarray(x.reshape(n * k, 3)), np.arange(n, dtype=np.int64) * k


def _per_element(term, rest, stiffness, n):
    rest = np.broadcast_to(np.asarray(rest, np.float64), (n,))
    stiffness = np.broadcast_to(np.asarray(stiffness, np.float64), (n,))
    return compiled.check_term(term, rest, stiffness)


def energy(term, x, rest, stiffness):
    k, n, xv, start = _layout(term, x)
    rest, stiffness = _per_element(term, rest, stiffness, n)
    return np.array([compiled.energy({term: (start[e:e + 1], rest[e:e + 1], stiffness[e:e + 1])}, xv)
                     for e in range(n)])


def vertex_energy(term, x, rest, stiffness):
    """Per element its energy from one :func:`compiled.vertex_energy` pass over all
    elements (each element's energy at its first vertex, k e)."""
    k, n, xv, start = _layout(term, x)
    rest, stiffness = _per_element(term, rest, stiffness, n)
    return compiled.vertex_energy({term: (start, rest, stiffness)}, xv)[start]


def gradient(term, x, rest, stiffness):
    k, n, xv, start = _layout(term, x)
    rest, stiffness = _per_element(term, rest, stiffness, n)
    g = np.zeros_like(xv)
    compiled.add_gradient({term: (start, rest, stiffness)}, xv, g)
    return g.reshape(n, k, 3)


def band_to_dense(band, b, upper=False):
    """Dense (3 nv, 3 nv) matrix of band storage (nv, 3, 3 (2 b + 1))."""
    nv = band.shape[0]
    A = np.zeros((3 * nv, 3 * nv))
    for i in range(nv):
        for d in range(-b, b + 1):
            j = i + d
            if 0 <= j < nv:
                A[3 * i:3 * i + 3, 3 * j:3 * j + 3] = band[i, :, 3 * (d + b):3 * (d + b) + 3]
    if upper:
        A = np.triu(A) + np.triu(A, 1).T
    return A


def gradient_hessian(term, x, rest, stiffness, filter="analytic", upper=False):
    k, n, xv, start = _layout(term, x)
    rest, stiffness = _per_element(term, rest, stiffness, n)
    g = np.zeros_like(xv)
    b = k - 1
    band = np.zeros((n * k, 3, 3 * (2 * b + 1)))
    compiled.add_gradient_hessian({term: (start, rest, stiffness)}, xv, g, band, b, upper, filter)
    A = band_to_dense(band, b, upper)
    m = 3 * k
    H = np.stack([A[m * e:m * e + m, m * e:m * e + m] for e in range(n)]) if n else np.zeros((0, m, m))
    return g.reshape(n, k, 3), H


def module(term):
    return SimpleNamespace(
        energy=lambda x, rest, stiffness: energy(term, x, rest, stiffness),
        gradient=lambda x, rest, stiffness: gradient(term, x, rest, stiffness),
        hessian=lambda x, rest, stiffness, filter="analytic", out=None: gradient_hessian(
            term, x, rest, stiffness, filter)[1],
        gradient_hessian=lambda x, rest, stiffness, filter="analytic": gradient_hessian(
            term, x, rest, stiffness, filter))
