"""The root turn (``time.root_rotation``): a coarse Newton step after a fixed count.

After the filtered iterations of a fixed count, 86-94% of what a frame leaves unsolved is
a rigid turn of each held wisp about its root, and the analytic filter makes that turn
25-130x stiffer than it is, so each filtered step takes a few percent of it
(docs/newton.md, "Fourteenth round").  Here each wisp whose pinned vertices are its first
ones is turned about its last pinned vertex by the Newton step of G over the three angles
of that turn, solved by conjugate gradients preconditioned by the turn's inertia.  G's
curvature along the turns is cheap: an element whose vertices all turn only turns its
gradient with them, so only the few elements across the root (central differences of
their gradients), the inertia, the head's penalty (its Hessian) and the bending of the
rotation curve (the gradient's own term) are evaluated.  One elastic gradient; no
assembly, no solve.  Rank-local (a wisp is whole on one rank); pure NumPy around the
compiled element kernels.
"""

from __future__ import annotations

import numpy as np

from lc_petsc.elements import compiled, compiled_turn
from lc_petsc.elements.angle import cross3

#: the angle (rad) of the central differences of the root elements' gradients along the
#: turns: their error is about this squared (1e-8 of the curvature), their round-off about
#: 1e-16 of the gradient over it (1e-6 with one-sided differences at 1e-6 amplified the
#: partition's round-off to 2-4e-9 of the positions on 2-3 ranks after 6 frames, against
#: 1e-13 without the turn)
ANGLE_STEP = 1e-4

def _turn_numpy(x, idx, pivot, axis, c, s):
    """:func:`compiled_turn.turn_vertices` by :func:`rotate`'s arithmetic (the reference)."""
    y = x.copy()
    y[idx] = x[pivot] + _rodrigues(x[idx] - x[pivot], axis, c, s)
    return y


#: the turn's fixed per-frame work (:mod:`lc_petsc.elements.compiled_turn`): the model's
#: per-vertex sums and curvature, the conjugate gradients, the turn of the vertices, the
#: central differences' turned copies; compiled (the default) or the NumPy references (the
#: same bits)
KERNELS = {"compiled": (compiled_turn.turn_sums, compiled_turn.turn_curvature, compiled_turn.turn_pcg,
                        compiled_turn.turn_vertices, compiled_turn.turn_copies),
           "numpy": (compiled_turn.turn_sums_numpy, compiled_turn.turn_curvature_numpy, compiled_turn.turn_pcg_numpy,
                     _turn_numpy, compiled_turn.turn_copies_numpy)}

#: a wisp whose share of G a turn raised has its turn halved this many times, then
#: dropped (:meth:`RootRotation.step`)
HALVINGS = 2

def root_pivots(offsets, pinned):
    """(n_wisps,) the last pinned vertex of each wisp whose pinned vertices are its first
    ones and which has a free vertex (a root-held wisp), else -1: a wisp pinned elsewhere
    cannot turn rigidly about one vertex."""
    out = np.full(len(offsets) - 1, -1)
    for w, (a, b) in enumerate(zip(offsets[:-1], offsets[1:])):
        k = int(np.argmin(pinned[a:b])) if not pinned[a:b].all() else b - a
        if 0 < k < b - a and not pinned[a + k:b].any():
            out[w] = a + k - 1
    return out


def axis_angle(theta):
    """(unit axis (n, 3) (0 for no turn), cos, sin (n,)) of rotation vectors (n, 3)."""
    angle = np.linalg.norm(theta, axis=1)
    return theta / np.where(angle > 0.0, angle, 1.0)[:, None], np.cos(angle), np.sin(angle)


def rotate(v, theta):
    """The vectors v (n, 3) turned by the rotation vectors ``theta`` (n, 3) (Rodrigues)."""
    return _rodrigues(v, *axis_angle(theta))


def _rodrigues(v, axis, c, s):
    """v (n, 3) turned about the unit ``axis`` (n, 3) by the angles of cosines ``c`` and
    sines ``s`` (n,)."""
    c, s = c[:, None], s[:, None]
    return v * c + cross(axis, v) * s + axis * (np.sum(axis * v, axis=1)[:, None] * (1.0 - c))


def cross(a, c):
    """Row-wise a x c of (n, 3) arrays: :func:`lc_petsc.elements.angle.cross3` on their
    transposes (np.cross's axis handling costs more here)."""
    return cross3(a.T, c.T).T


def skew(v):
    """(n, 3, 3) the matrices [v]x with [v]x c = v x c."""
    S = np.zeros((len(v), 3, 3))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return S


def turn(x, theta, pivot, idx):
    """x with the vertices ``idx`` turned about the vertices ``pivot`` (one per index) by
    the rotation vectors ``theta`` (one per index)."""
    return _turn_numpy(x, idx, pivot, *axis_angle(theta))


class RootRotation:
    """The root turn of one rank's wisps (:meth:`step`).  ``elements``: the compiled
    kernels' element arrays per term (:func:`lc_petsc.elements.compiled.element_arrays`),
    ``stencils``: each term's vertices per element; ``kernels``: the turn's fixed work
    compiled or in NumPy (:data:`KERNELS`)."""

    def __init__(self, offsets, pinned, elements, stencils, kernels="compiled"):
        if kernels not in KERNELS:
            raise ValueError(f"root turn: kernels {kernels!r}: use one of {', '.join(KERNELS)}")
        self._turn_sums, self._curvature, self._pcg, self._turn_vertices, self._copies = KERNELS[kernels]
        self.offsets = np.asarray(offsets)
        self.pivot = root_pivots(self.offsets, np.asarray(pinned, bool))
        sizes = np.diff(self.offsets)
        self.wisp = np.repeat(np.arange(len(sizes)), sizes)
        self.pivot_of = np.where(self.pivot >= 0, self.pivot, 0)[self.wisp]     # 0: not turned
        vertex = np.arange(len(self.wisp))
        self.moved = (self.pivot[self.wisp] >= 0) & (vertex > self.pivot[self.wisp])
        self.idx = np.flatnonzero(self.moved)
        self.mask = self.moved.astype(float)
        # the elements across a root (a vertex that stays and one that turns; elements
        # stay inside their wisp), whose gradients are not turned copies: on their own
        # vertices only (``near``, sorted: an element's consecutive vertices stay so)
        across = {}
        for name, (start, rest, stiffness) in elements.items():
            k = stencils[name]
            sel = self.moved[start + k - 1] & ~self.moved[start] if len(start) else np.zeros(0, bool)
            across[name] = (start[sel], rest[sel], stiffness[sel], k)
        self.near = np.unique(np.concatenate([s[:, None] + np.arange(k) for s, _, _, k in across.values()]
                                             + [np.zeros((0, 1), int)], axis=None)).astype(np.int64)
        self.across = {name: compiled.element_arrays(name, np.searchsorted(self.near, s), rest, stiff)
                       for name, (s, rest, stiff, _) in across.items()}
        # copies of them for one kernel call each (copy j's vertices after the j - 1
        # before it): two, after and before a turn (share_change); seven, one per turn and
        # sign of the central differences and the vertices unturned (_model)
        n = len(self.near)
        self.across2, self.across7 = (
            {name: compiled.element_arrays(name, np.concatenate([s + j * n for j in range(c)]),
                                           np.concatenate([r] * c), np.concatenate([k] * c))
             for name, (s, r, k) in self.across.items()} for c in (2, 7))
        self.near_wisp = self.wisp[self.near]
        self.near_moved = self.moved[self.near]
        self.layout = compiled_turn.turn_layout(self.mask, self.pivot_of, self.offsets, self.near,
                                                self.near_moved)
        self.idx_wisp, self.idx_pivot = self.wisp[self.idx], self.pivot_of[self.idx]
        self.held = self.pivot >= 0
        # the six turns of the central differences (+-ANGLE_STEP about each axis) as
        # matrices acting on row vectors: one product instead of six Rodrigues turns
        eye = np.eye(3)
        self.turns6 = np.stack([rotate(eye, np.broadcast_to(sign * ANGLE_STEP * e, (3, 3)))
                                for sign in (1, -1) for e in eye])
        self.turned = 0          # wisps turned by the last step
        self.reduced = 0         # ... of them with their turn halved or dropped (share_change)

    def _sums(self, a):
        """Per wisp sums over the vertices of ``a`` (n, ...)."""
        return np.add.reduceat(a, self.offsets[:-1], axis=0)

    def model(self, x, terms, unit):
        """(b, A, P) per wisp at x (zeros for a wisp not held at its root): b the
        gradient of G along the three turns (the torque of grad G about the pivot), A
        G's curvature along them (its Hessian in the angles of the turn), P the turn's
        inertia about the pivot over dt^2.  ``terms``: x -> (grad G without the elastic
        terms, the head's active vertices and their Hessians or None, per vertex the
        terms of one vertex of G (not used here: :meth:`step`'s guard)); ``unit``: per
        vertex the mass over dt^2.

        An element whose vertices all turn exerts no torque about the pivot and turns its
        gradient with them: it drops out of b, and of A but for the rotation curve's
        bending, which cancels it there too.  So with q the gradient of G without those
        elements (inertia, gravity, the head, the elements across the root) b = sum r x q
        and A = sum (r . u) I - sym(r u^T), u = m r - q (m the mass over dt^2; -q the
        curve's term g . d2x / dtheta_k dtheta_l, without which the turn overshoots:
        hairball10 7.3e-3 against 5.0e-3, the demo cut to 10 wisps 1.37e-2 against
        9.6e-3, docs/newton.md "Fourteenth round"), plus the across elements' and the
        head's curvature.  The elastic gradient's large, cancelling terms never enter."""
        return self._model(x, *terms(x)[:2], unit)

    def _model(self, x, outer, head, unit):
        """:meth:`model` from the terms at x."""
        # the elements across the root, their gradients at x and at the six turns of the
        # central differences in one kernel call (an element's gradient is the same bits
        # alone or among copies: each copy has vertices of its own)
        turned = self._copies(self.layout, x, self.turns6)
        g7 = np.zeros_like(turned)
        compiled.add_gradient(self.across7, turned, g7)
        n = len(self.near)
        # b = sum r x q: d G / d theta_k = sum (e_k x r) . g; T = sum r (m r - q)^T, M =
        # sum (m r) r^T (one compiled pass, NumPy's sums bit for bit)
        r, b, T, M = self._turn_sums(self.layout, x, outer, unit, g7[6 * n:])
        g6 = g7[:6 * n].reshape(2, 3, n, 3)
        HJ = (g6[0] - g6[1]) / (2 * ANGLE_STEP)          # (turn k, vertex, 3)
        # A = tr(T) I - sym(T) + the across elements' sum r x HJ; P = tr(M) I - M
        A, P = self._curvature(T, M, HJ, r[self.near], self.near_wisp)
        if head is not None:                     # the head's penalty: sum [r]x^T H [r]x
            hidx, H = head
            S = skew(r[hidx])
            np.add.at(A, self.wisp[hidx], np.einsum("nji,njk,nkl->nil", S, H, S))
        A = 0.5 * (A + A.transpose(0, 2, 1))
        return b, A, P

    def share_change(self, x, y, change):
        """Per wisp the change of its share of G from x to y, x with its wisps turned
        about their pivots: ``change`` (x, y) -> per vertex the change of the terms of
        one vertex (inertia, gravity, the head), plus the energies of the elements across
        the root.  An element whose vertices all turn keeps its energy (stretch, bend and
        twist depend on lengths and angles only), so this is the change of
        :meth:`Integrator.wisp_potentials` without evaluating the wisps' elements."""
        d = self._sums(change(x, y) * self.mask)
        # all terms' elements after and before in one compiled pass (the NumPy kernels'
        # three calls were a quarter of the turn's time on hairball10), each element's
        # energy at its first vertex
        e = compiled.vertex_energy(self.across2, np.concatenate([y[self.near], x[self.near]]))
        n = len(self.near)
        return d + np.bincount(self.near_wisp, e[:n] - e[n:], minlength=len(d))

    def _turned(self, x, theta):
        """x with each held wisp turned about its pivot by its rotation vector ``theta``
        (n_wisps, 3) (:func:`turn`'s arithmetic)."""
        axis, c, s = axis_angle(theta)
        w = self.idx_wisp
        return self._turn_vertices(x, self.idx, self.idx_pivot, axis[w], c[w], s[w])

    def step(self, x, terms, unit, potentials=None):
        """x after the root turn (a new array).  Per held wisp the turn theta solves
        A theta = -b (:meth:`model`) by three conjugate-gradient steps preconditioned by
        P (exact where A is positive definite); a direction of curvature that is not
        positive ends a wisp's iteration, keeping its turn so far (on hairball10 that
        gives 4.5e-3 against 5.0e-3 for the Newton step in the span of A's positive
        eigenvalues).  With ``potentials`` (y -> per vertex the terms of one vertex of G,
        as ``terms``' last at x) a wisp whose share of G the turn raised
        (:meth:`share_change`) has it halved, up to :data:`HALVINGS` times, then
        dropped: the model is G's along the turn at x only, and a large turn or the
        head's contact switching on or off over it can make the step climb."""
        held = self.held
        self.turned = self.reduced = 0
        if not held.any():
            return x.copy()
        outer, head, at_x = terms(x)
        b, A, P = self._model(x, outer, head, unit)
        eye = np.eye(3)
        P[~held] = eye
        # a wisp on one line (hanging straight) has no inertia about that line: P is
        # singular there (np.linalg.solve raised).  A turn about the line moves nothing, so
        # a small multiple of P's trace there only keeps the preconditioner invertible
        tr = np.einsum("wkk->w", P)
        line = np.linalg.det(P) <= 1e-12 * tr ** 3
        P[line] += (1e-6 * tr[line])[:, None, None] * eye
        theta = self._pcg(A, P, b, held)
        y = self._turned(x, theta)
        moving = np.any(theta != 0.0, axis=1)
        self.turned = int(np.count_nonzero(moving))
        reduced = np.zeros(len(held), bool)
        for halving in range(HALVINGS + 1) if potentials is not None else ():
            rose = moving & (self.share_change(x, y, lambda _, y: potentials(y) - at_x) > 0.0)
            if not rose.any():
                break
            reduced |= rose
            theta[rose] *= 0.5 if halving < HALVINGS else 0.0
            moving &= np.any(theta != 0.0, axis=1)
            y = self._turned(x, theta)
        self.reduced = int(np.count_nonzero(reduced))
        return y
