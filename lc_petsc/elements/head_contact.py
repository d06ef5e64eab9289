"""Penalty contact of vertices with a kinematic sphere (the head); pure NumPy.

For a vertex x and a sphere of centre c and radius R, the depth is
d = max(0, R - |x - c|) and the energy Psi = 1/2 k d^2 (k in dyn/cm). With
n = (x - c)/|x - c|: gradient -k d n; exact Hessian k n n^T - k d (I - n n^T)/|x - c|.
The second term is negative semidefinite; the PSD filter drops it, leaving k n n^T
(the Gauss-Newton part), which is what :func:`hessian` returns by default; ``filter =
"none"`` returns the exact Hessian (the exact Newton steps of ``solver.filter =
"exact_or_analytic"`` and ``"none"``: with the filtered one a vertex resting on the
sphere converges only linearly, docs/newton.md).  A vertex exactly at the
centre is pushed along +y (any direction would do; the rule keeps outputs finite).

A penalty lets a vertex sink in by its pushing force / k: with the default k = 1e5 dyn/cm
a hairball vertex (~0.01-0.1 g under 981 cm/s^2) sinks in by ~1e-4..1e-3 cm.
"""

import numpy as np


def _geometry(x, center, radius):
    y = np.asarray(x, float) - np.asarray(center, float)
    dist = np.sqrt(np.einsum("ij,ij->i", y, y))
    depth = np.maximum(radius - dist, 0.0)
    n = np.zeros_like(y)
    ok = dist > 0
    n[ok] = y[ok] / dist[ok, None]
    n[~ok] = (0.0, 1.0, 0.0)
    return depth, n


def active(x, center, radius):
    """Boolean mask (n,) of vertices strictly inside the sphere."""
    depth, _ = _geometry(x, center, radius)
    return depth > 0


def energy(x, center, radius, stiffness):
    """Penalty energy (n,) of vertices x (n, 3) inside the head sphere."""
    depth, _ = _geometry(x, center, radius)
    return 0.5 * stiffness * depth ** 2


def gradient(x, center, radius, stiffness):
    """Gradient (n, 3) of :func:`energy`."""
    depth, n = _geometry(x, center, radius)
    return -(stiffness * depth)[:, None] * n


def hessian(x, center, radius, stiffness, filter="analytic"):
    """Hessian (n, 3, 3), 0 outside: the filtered (PSD) k n n^T, or with ``filter =
    "none"`` the exact k n n^T - k d (I - n n^T) / |x - c| (a vertex at the centre: the
    filtered one)."""
    if filter not in ("analytic", "none"):
        raise ValueError(f"head contact: unknown Hessian filter {filter!r}: use analytic or none")
    x = np.asarray(x, float)
    depth, n = _geometry(x, center, radius)
    w = np.where(depth > 0, stiffness, 0.0)
    nn = n[:, :, None] * n[:, None, :]
    H = w[:, None, None] * nn
    if filter == "none":
        dist = radius - depth
        c = np.divide(stiffness * depth, dist, out=np.zeros_like(depth), where=dist > 0)
        H -= c[:, None, None] * (np.eye(3)[None] - nn)
    return H
