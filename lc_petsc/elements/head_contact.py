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
    """Boolean mask (n,) of vertices strictly inside the sphere: depth > 0 as
    :func:`_geometry` measures it (radius - dist > 0 is radius > dist in floating point),
    without the normals it would build for every vertex (run on all of them by every
    head pass, which the root turn's fixed cost on small scenes felt)."""
    y = np.asarray(x, float) - np.asarray(center, float)
    return np.sqrt(np.einsum("ij,ij->i", y, y)) < radius


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


def allowed_depth(strand_radius, rest_edge, offsets, radius):
    """Per vertex (n,): how deep in the sphere of ``radius`` a vertex may rest before the
    head's push-out moves it (``physics.head_push_out``): its strand radius less the
    sagitta L^2 / (8 R) of the longer of its edges (L their rest lengths), at least 0:
    two neighbours that deep on the sphere leave their edge's chord no deeper than the
    strand radius (at the radius itself, chords of the falling strand's 0.5 cm edges on
    a 5 cm head reached 1.12 radii).  ``rest_edge`` (n - 1,) rest length of edge
    (v, v + 1) (edges across wisps unused), ``offsets`` (n_wisps + 1,)."""
    rad = np.asarray(strand_radius, float)
    n = len(rad)
    edge = np.zeros(n + 1)                  # edge[v]: the rest length of edge (v - 1, v)
    edge[1:n] = np.asarray(rest_edge, float)[:max(n - 1, 0)]
    cut = np.asarray(offsets, np.int64)     # no edge between two wisps
    edge[cut] = 0.0
    longer = np.maximum(edge[:-1], edge[1:])
    return np.maximum(rad - longer ** 2 / (8.0 * radius), 0.0)


def segment_depth(p0, p1, radius):
    """(depth (k,), t (k,)): the deepest point of each segment p0 -> p1 (k, 3), positions
    relative to the sphere's centre, inside the sphere of ``radius`` (radius - the
    segment's distance to the centre: negative outside), at the segment's parameter t."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d = p1 - p0
    dd = np.einsum("ij,ij->i", d, d)
    t = np.clip(np.divide(-np.einsum("ij,ij->i", p0, d), dd, out=np.zeros_like(dd), where=dd > 0),
                0.0, 1.0)
    q = p0 + t[:, None] * d
    return radius - np.sqrt(np.einsum("ij,ij->i", q, q)), t


#: the integrator's path lift puts a vertex at most this many strand radii farther from
#: the head's centre than it was before the step's first lift round (or than the sphere,
#: when it was under it), all rounds together
#: (its velocity leaves the move out and its wisp's rest lengths are set again, so a
#: larger lift costs neither a kick nor strain; soft hairball with gravity 5000: paths
#: through 13 with 2 radii, 6 with 4; at 1 radius the soft hairball's 4 tips were left)
LIFT_RADII = 4.0
#: rounds of lift and length projection (the projection moves lifted vertices back a little)
LIFT_ROUNDS = 3
#: lift_paths: the lifted end's relative overshoot, so that the path's depth is below the
#: allowed depth after round-off (not exactly at it)
LIFT_ROUND_OFF = 1e-12


def lift_paths(p0, p1, radius, allow, max_lift, free):
    """The ends ``p1`` (n, 3) of straight paths from ``p0`` (both relative to the sphere's
    centre) lifted where a path goes deeper in the sphere of ``radius`` than ``allow``
    (n,) while neither end does: the end is moved straight out from the centre until the
    path's line stays at ``radius - allow`` from it (the distance |p0 x p1| / |p1 - p0|
    of the line, solved for |p1|), when that moves it by at most ``max_lift`` (n,) (a
    path the move cannot mend, one turning around the sphere, is left alone).  Only
    ``free`` vertices.  Returns (p1 with the lifted ends, their indices)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    allow = np.asarray(allow, float)
    depth, _ = segment_depth(p0, p1, radius)
    a = np.sqrt(np.einsum("ij,ij->i", p0, p0))
    b = np.sqrt(np.einsum("ij,ij->i", p1, p1))
    i = np.flatnonzero(free & (depth > allow) & (radius - a <= allow) & (radius - b <= allow) & (b > 0))
    if not len(i):
        return p1, i
    a, b, m = a[i], b[i], radius - allow[i]
    cos = np.einsum("ij,ij->i", p0[i], p1[i]) / (a * b)
    # the line's distance from the centre is m where g(rho) = rho^2 (a^2 sin^2 - m^2)
    # + 2 m^2 a cos rho - m^2 a^2 = 0 (|p1| = rho); it is below m at rho = b, so the
    # lift is to the smallest root above b (the distance rises to a maximum and falls
    # back to a sin as rho grows: two roots, or none when it never reaches m)
    A = a * a * np.maximum(1.0 - cos * cos, 0.0) - m * m
    B, C = 2.0 * m * m * a * cos, -m * m * a * a
    disc = B * B - 4.0 * A * C
    real = disc >= 0.0
    q = -0.5 * (B + np.copysign(np.sqrt(np.where(real, disc, 0.0)), B))     # stable roots q / A, C / q
    roots = np.stack([np.divide(q, A, out=np.full_like(q, np.inf), where=A != 0.0),
                      np.divide(C, q, out=np.full_like(q, np.inf), where=q != 0.0)])
    roots[:, ~real] = np.inf
    roots[roots <= b] = np.inf
    rho = roots.min(axis=0)
    ok = rho - b <= np.asarray(max_lift, float)[i]
    i, rho, b = i[ok], rho[ok], b[ok]
    p1 = p1.copy()
    p1[i] *= (rho * (1.0 + LIFT_ROUND_OFF) / b)[:, None]
    return p1, i
