"""Render hairs interpolated from the simulated wisps (export only: the simulation never
sees them).

Each wisp stands for a clump of hairs whose cross-section is the wisp's radius.  A
render hair follows its guide wisp vertex by vertex at a fixed offset in the wisp's
rotation-minimising frame (RMF):

    p_hj = x_j + spread * r_j * (a_h u_j + b_h v_j),

with x_j the guide's vertices, r_j its radii, (u_j, v_j) the RMF's two normals at vertex
j and (a_h, b_h) a point drawn uniformly in the unit disc for hair h.  The RMF turns as
little as possible about the tangent, so the offset does not spin around the guide: a
hair keeps the guide's coil (same turns and pitch, coil radius within ``spread * r`` of
the guide's) and never leaves the clump's cross-section (|p_hj - x_j| <= spread * r_j).

The RMF is computed by double reflection (Wang, Juettler, Zheng, Liu, "Computation of
rotation minimizing frames", ACM TOG 27(1), 2008) from the vertices and their tangents
(central differences; one-sided at the ends).  Its first normal at the root is a
vector fixed in the head (``root_normals``, carried by the head's rotation), so the
hairs turn with the head and do not slide around the root from frame to frame.

Offsets are seeded: hair h of wisp w draws from ``numpy.random.default_rng([seed, w])``
(the first ``n_hairs`` pairs of that stream), so they depend on neither the frame nor
the rank count nor the other wisps.
"""

from __future__ import annotations

import numpy as np

# rows of wisps rendered at once: bounds the float32 temporaries (rows * hairs * n * 3)
_CHUNK_POINTS = 1 << 22


def vertex_tangents(x, offsets):
    """Unit tangents (n_vertices, 3) of the polylines ``x`` (n_vertices, 3) split by
    ``offsets`` (n_wisps + 1,): central differences inside a wisp, one-sided at its
    ends; a zero central difference (a hairpin) falls back to the edge ahead."""
    x = np.asarray(x, float)
    nv = len(x)
    nxt = np.arange(1, nv + 1)
    prv = np.arange(-1, nv - 1)
    first, last = offsets[:-1], offsets[1:] - 1
    nxt[last] = last
    prv[first] = first
    nxt = np.minimum(nxt, nv - 1)
    prv = np.maximum(prv, 0)
    t = x[nxt] - x[prv]
    n = np.linalg.norm(t, axis=1)
    flat = n <= 1e-12 * max(1.0, float(np.abs(x).max(initial=0.0)))
    if flat.any():
        ahead = np.minimum(np.arange(nv) + 1, nv - 1)
        ahead[last] = last
        back = np.arange(nv)
        back[last] = np.maximum(last - 1, 0)
        t[flat] = x[ahead[flat]] - x[back[flat]]
        n[flat] = np.linalg.norm(t[flat], axis=1)
    return t / np.where(n > 0, n, 1.0)[:, None]


def perpendicular(t):
    """A unit vector perpendicular to each unit vector of ``t`` (n, 3)."""
    t = np.asarray(t, float)
    ref = np.zeros_like(t)
    use_x = np.abs(t[:, 2]) > 0.9
    ref[~use_x, 2] = 1.0
    ref[use_x, 0] = 1.0
    u = np.cross(t, ref)
    return u / np.linalg.norm(u, axis=1)[:, None]


def double_reflection(x, t, offsets, r0):
    """Rotation-minimising frames of the polylines ``x`` (n_vertices, 3) with unit
    tangents ``t`` (n_vertices, 3), split by ``offsets``; ``r0`` (n_wisps, 3): each
    wisp's first normal at its root (projected off the root tangent here).

    Returns (u, v), each (n_vertices, 3): u_j the transported normal, v_j = t_j x u_j.
    Vectorised over wisps, sequential along them (Wang et al. 2008, algorithm 1)."""
    x, t = np.asarray(x, float), np.asarray(t, float)
    offsets = np.asarray(offsets, np.int64)
    sizes = np.diff(offsets)
    nw, nmax = len(sizes), int(sizes.max(initial=0))
    u = np.zeros_like(x)
    if nw == 0 or nmax == 0:
        return u, u.copy()
    first = offsets[:-1]
    r = np.asarray(r0, float).reshape(nw, 3).copy()
    t0 = t[first]
    r -= np.sum(r * t0, axis=1)[:, None] * t0
    nr = np.linalg.norm(r, axis=1)
    bad = nr < 1e-9
    if bad.any():
        r[bad] = perpendicular(t0[bad])
        nr[bad] = 1.0
    r /= nr[:, None]
    u[first] = r
    for j in range(nmax - 1):
        act = sizes > j + 1
        i = first[act] + j
        ri = r[act]
        ti = t[i]
        v1 = x[i + 1] - x[i]
        c1 = np.sum(v1 * v1, axis=1)
        s1 = np.divide(2.0, c1, out=np.zeros_like(c1), where=c1 > 0)
        rl = ri - (s1 * np.sum(v1 * ri, axis=1))[:, None] * v1
        tl = ti - (s1 * np.sum(v1 * ti, axis=1))[:, None] * v1
        v2 = t[i + 1] - tl
        c2 = np.sum(v2 * v2, axis=1)
        s2 = np.divide(2.0, c2, out=np.zeros_like(c2), where=c2 > 0)
        rn = rl - (s2 * np.sum(v2 * rl, axis=1))[:, None] * v2
        # re-orthonormalise against round-off drift along long wisps
        rn -= np.sum(rn * t[i + 1], axis=1)[:, None] * t[i + 1]
        rn /= np.linalg.norm(rn, axis=1)[:, None]
        r[act] = rn
        u[i + 1] = rn
    return u, np.cross(t, u)


def root_normals(x_rest, offsets):
    """Each wisp's first RMF normal at rest (n_wisps, 3): a unit vector perpendicular
    to the rest root tangent (:func:`perpendicular`)."""
    t = vertex_tangents(x_rest, offsets)
    return perpendicular(t[np.asarray(offsets[:-1], np.int64)])


def hair_offsets(n_wisps, n_hairs, seed=0, first_wisp=0):
    """Disc coordinates (a, b), each (n_wisps, n_hairs), uniform in the unit disc; wisp
    w draws from ``default_rng([seed, first_wisp + w])``, hair h the stream's pair h
    (radius sqrt(q0), angle 2 pi q1): adding hairs keeps the first ones."""
    a = np.empty((n_wisps, n_hairs))
    b = np.empty((n_wisps, n_hairs))
    for w in range(n_wisps):
        rng = np.random.default_rng([int(seed), int(first_wisp + w)])
        q = rng.uniform(size=(n_hairs, 2))        # hair h: the stream's pair h
        rho, phi = np.sqrt(q[:, 0]), 2.0 * np.pi * q[:, 1]
        a[w], b[w] = rho * np.cos(phi), rho * np.sin(phi)
    return a, b


class RenderHairs:
    """``n_hairs`` render hairs per wisp of a scene with vertex ``offsets`` (n_wisps + 1,)
    and ``radius`` (n_vertices,); ``spread`` scales the clump radius (1: the hairs fill
    the wisp's cross-section).  Curve order: wisp by wisp, the wisp's hairs in turn;
    hair h of wisp w is curve ``w * n_hairs + h`` with the guide's vertex count."""

    def __init__(self, offsets, radius, n_hairs, seed=0, spread=1.0):
        self.offsets = np.asarray(offsets, np.int64)
        self.sizes = np.diff(self.offsets)
        self.n_hairs, self.seed, self.spread = int(n_hairs), int(seed), float(spread)
        self.radius = np.asarray(radius, float)
        self.a, self.b = hair_offsets(len(self.sizes), self.n_hairs, self.seed)
        # runs of consecutive wisps of equal size: one broadcast each
        change = np.flatnonzero(np.diff(self.sizes)) + 1
        self.runs = list(zip(np.concatenate([[0], change]), np.concatenate([change, [len(self.sizes)]])))

    @property
    def n_curves(self):
        """Number of render hairs (curves)."""
        return len(self.sizes) * self.n_hairs

    @property
    def n_points(self):
        """Number of render-hair vertices."""
        return int(self.offsets[-1]) * self.n_hairs

    def curve_vertex_counts(self):
        """Vertices per render hair (n_curves,) int32, for USD's ``curveVertexCounts``."""
        return np.repeat(self.sizes, self.n_hairs).astype(np.int32)

    def guide_wisp(self):
        """The guide wisp of each render hair (n_curves,) int32."""
        return np.repeat(np.arange(len(self.sizes)), self.n_hairs).astype(np.int32)

    def widths(self):
        """Per-vertex widths (n_points,): N hairs of radius r / sqrt(N) have the wisp's
        cross-section area."""
        w = np.empty(self.n_points, np.float32)
        h = self.n_hairs
        for w0, w1 in self.runs:
            n = int(self.sizes[w0])
            r = self.radius[self.offsets[w0]:self.offsets[w1]].reshape(w1 - w0, 1, n)
            seg = w[h * self.offsets[w0]:h * self.offsets[w1]].reshape(w1 - w0, h, n)
            seg[...] = 2.0 * r / np.sqrt(h)
        return w

    def points(self, x, root_normal, out=None):
        """Render-hair vertices (n_points, 3) float32 for guide vertices ``x``
        (n_vertices, 3) whose RMFs start from ``root_normal`` (n_wisps, 3)."""
        x = np.asarray(x, float)
        t = vertex_tangents(x, self.offsets)
        u, v = double_reflection(x, t, self.offsets, root_normal)
        s = (self.spread * self.radius)[:, None]
        us, vs = (u * s).astype(np.float32), (v * s).astype(np.float32)
        x32 = x.astype(np.float32)
        out = np.empty((self.n_points, 3), np.float32) if out is None else out
        h = self.n_hairs
        for w0, w1 in self.runs:
            n = int(self.sizes[w0])
            step = max(1, _CHUNK_POINTS // max(1, h * n))
            for c0 in range(int(w0), int(w1), step):
                c1 = min(c0 + step, int(w1))
                a0, a1 = self.offsets[c0], self.offsets[c1]
                dst = out[h * a0:h * a1].reshape(c1 - c0, h, n, 3)
                a = self.a[c0:c1, :, None, None].astype(np.float32)
                b = self.b[c0:c1, :, None, None].astype(np.float32)
                np.multiply(a, us[a0:a1].reshape(c1 - c0, 1, n, 3), out=dst)
                dst += b * vs[a0:a1].reshape(c1 - c0, 1, n, 3)
                dst += x32[a0:a1].reshape(c1 - c0, 1, n, 3)
        return out
