"""A step's positions besides the linear solve: the first iterate's predictions
(``time.carry_with_head``: :func:`head_motion_change`, the head's change of motion the
first iterate carries, and :func:`start_carry_weight`, how much of the head's first step
the start from rest carries along a wisp; :func:`follow_the_leader`,
``time.initial_guess``) and the walks that keep the edge lengths: the Newton updates of
``time.newton_update`` (:func:`retract_edge_lengths`, :func:`corotational_update`) and
the frame's projection onto the rest lengths (:func:`project_rest_lengths`,
``time.length_projection``).  Each wisp's result depends on that wisp alone (the same
bits on any partition); the walks are compiled (:mod:`lc_petsc.elements.compiled`)."""

from __future__ import annotations

import numpy as np

from lc_petsc.elements import compiled


#: The start from rest's carry decays along a wisp as exp(-s / (START_CARRY_LENGTH * S)),
#: s the rest arclength from the wisp's last pinned vertex, S that of its free part
#: (docs/newton.md, "Tenth round": 0.3 measured against 0.03, 0.1 and the whole wisp)
START_CARRY_LENGTH = 0.3


def start_carry_weight(rest_edge, offsets, pinned, length=START_CARRY_LENGTH):
    """Per-vertex weights (nv,) of the head's first step in the first iterate of the
    start from rest: 1 up to each wisp's last pinned vertex, then exp(-s / (length S))
    with s the rest arclength from that vertex and S the arclength from it to the tip
    (1 on a wisp without pinned vertices, which is not carried).  A head starting from
    rest jumps to its velocity; within one step only the part of a wisp near its roots
    follows (the tips lag by inertia), while a smooth acceleration later is followed by
    the whole wisp.  ``rest_edge`` (nv - 1,) rest length of edge (v, v + 1) (edges
    across wisps unused), ``offsets`` (n_wisps + 1,), ``pinned`` (nv,)."""
    off = np.asarray(offsets, np.int64)
    nv, sizes = len(pinned), np.diff(off)
    edge = np.zeros(nv)                 # edge[v]: the rest length of edge (v - 1, v)
    edge[1:] = rest_edge[:max(nv - 1, 0)]
    arc = np.zeros(nv)
    for j in range(1, int(sizes.max(initial=0))):      # along each wisp from its root: the
        v = off[:-1][sizes > j] + j                     # same sums on any partition
        arc[v] = arc[v - 1] + edge[v]
    wisp = np.repeat(np.arange(len(sizes)), sizes)
    last = np.full(len(sizes), -1, np.int64)
    np.maximum.at(last, wisp[pinned], np.flatnonzero(pinned))
    anchor = last[wisp]
    held = anchor >= 0
    tip = off[1:][wisp] - 1
    s = np.where(held, arc - arc[np.maximum(anchor, 0)], 0.0)
    S = np.where(held, arc[tip] - arc[np.maximum(anchor, 0)], 0.0)
    w = np.ones(nv)
    decay = held & (s > 0.0) & (S > 0.0)
    w[decay] = np.exp(-s[decay] / (length * S[decay]))
    return w


def head_motion_change(head, x, t, dt, t_next):
    """The change of ``head``'s rigid motion at positions ``x`` (n, 3) between the last
    step and this one (from ``t`` to ``t_next`` = t + ``dt``): u_now(x) - u_last(x),
    u_now the motion from t to ``t_next``, u_last the one from t - ``dt`` to t (none
    before t = 0: the head starts from rest).  For a smooth motion it is second order in
    dt: the change of the head's step displacement field (its angular and linear
    acceleration times dt^2; zero for a steady rotation, whose centripetal term it leaves
    out, as x_n + dt v_n does); at a start, the head's whole first step.  Both fields are
    taken at x_n (u_last maps positions at t - dt; the difference is second order in the
    step's rotation).  With step cutback ``dt`` is the substep's, while v_n spans the
    last step's: the carry is then only roughly the rigid-consistent one.  Added to
    x_n + dt v_n for the free vertices of the wisps the head holds, it makes Newton's
    first iterate move them as the roots must move (``time.carry_with_head``, measured in
    docs/newton.md, "Tenth round")."""
    Q, q = head.rigid_motion(t, t_next)
    Qp, qp = head.rigid_motion(max(t - dt, 0.0), t)
    D = Q - Qp
    # row by row in a fixed order (not a BLAS product, whose summation order may
    # depend on the number of rows): the same bits on any partition
    return x[:, 0:1] * D[:, 0] + x[:, 1:2] * D[:, 1] + x[:, 2:3] * D[:, 2] + (q - qp)


def follow_the_leader(x, free, offsets, rest_edge):
    """Length-preserving prediction (Mueller et al. 2012): walking from each wisp's root,
    every free vertex is put at its rest edge length from its predecessor, in the
    direction of its predicted position.  Only wisps whose root (first vertex) is pinned
    have a leader: on a wisp with a free root the walk would start at an arbitrary end
    and drag the whole strand along itself towards it (the corrections accumulate), a
    slide that costs no energy where the strand lies across another (so Newton does not
    undo it) and whose straight path cuts the corner through what it lies on; such wisps
    keep their prediction (measured: a free wisp draped over another slid 0.39 d0 per
    frame at its far end, and the ccd path check then held the pair at its floor,
    docs/contact.md "Follow the leader in ccd mode").  x (nv, 3) predicted positions,
    free (nv,) bool, offsets (n_wisps + 1,), rest_edge (nv - 1,) rest length of edge
    (v, v + 1) (edges across wisps unused).  Returns the new positions (nv, 3)."""
    x = x.copy()
    off = np.asarray(offsets)
    sizes = np.diff(off)
    rooted = np.zeros(len(sizes), bool)
    rooted[sizes > 0] = ~free[off[:-1][sizes > 0]]
    for j in range(1, int(sizes.max(initial=0))):
        v = off[:-1][(sizes > j) & rooted] + j
        v = v[free[v]]
        d = x[v] - x[v - 1]
        n = np.linalg.norm(d, axis=1)
        ok = n > 0
        x[v[ok]] = x[v[ok] - 1] + d[ok] * (rest_edge[v[ok] - 1] / n[ok])[:, None]
    return x


def retract_edge_lengths(x, dx, free, offsets, mass=None):
    """x + dx with the length of every edge that ends at a free vertex set to its
    first-order value |e| + eh . de (direction that of e + de), the corrections
    accumulated from the root (or the last pinned vertex) outwards.  A linearised step
    that turns an edge by an angle phi lengthens it by |e| phi^2 / 2, which the stiff
    stretch term pulls back in the next iteration; this update keeps the step's rotation
    and its first-order length change only.  It equals x + dx to second order in dx (so
    Newton's convergence rate is kept) and has the same fixed points.  On a wisp with no
    pinned vertex the mass-weighted mean correction is removed (``mass`` given): the
    step then changes the wisp's momentum as x + dx does.  Each wisp's result depends on
    that wisp alone (rank-count invariant to the last bit).  One compiled pass
    (:func:`lc_petsc.elements.compiled.edge_lengths`).
    x, dx (nv, 3), free (nv,) bool, offsets (n_wisps + 1,), mass (nv,) or None.
    Returns (nv, 3)."""
    return compiled.edge_lengths(x, dx, None, free, offsets, mass)


def corotational_update(x, dx, free, offsets, mass=None):
    """``time.newton_update = "corotational"``, the update of the exact steps: like
    :func:`retract_edge_lengths` (each
    free edge gets its first-order length |e| + eh . de, built from the root or the last
    pinned vertex outwards), but each edge is first *turned* by the rotation w fitted to
    the increments of the edges around it (itself and its two neighbours in the wisp:
    least squares of w x e_k = de_k), R(w) e + (de - w x e), instead of moved to e + de.
    A rigid rotation of a stretch of the wisp is then applied exactly, so the bend and
    twist angles a linearised rotation of a coil distorts at second order (the slow mode
    of the hairball's Newton, docs/newton.md "Sixth round") are kept.  Equal to x + dx to
    second order in dx (Newton's rate and fixed points are kept).  On a wisp with no
    pinned vertex the mass-weighted mean is that of x + dx (``mass`` given), so the step
    changes its momentum as x + dx does.  Each wisp's result depends on that wisp alone.
    Two compiled passes (:func:`lc_petsc.elements.compiled.corotate`).
    x, dx (nv, 3), free (nv,) bool, offsets (n_wisps + 1,), mass (nv,) or None.
    Returns (nv, 3)."""
    return compiled.corotate(x, dx, free, offsets, mass)


def _set_edge_lengths(x, length, free, offsets, mass=None, head=None):
    """x with every edge (v - 1, v) that ends at a free vertex v of the same wisp given
    the length ``length[v - 1]`` (> 0; its direction kept), the corrections accumulated
    from the root (or the last pinned vertex) outwards; edges of zero length or with a
    length <= 0 are left alone.  On a wisp with no pinned vertex the mass-weighted mean
    of the corrections is removed (``mass`` given): the wisp's momentum (of the velocity
    (x - x_n) / dt) is then unchanged.  One compiled pass
    (:func:`lc_petsc.elements.compiled.edge_lengths`).  x (nv, 3), length (nv - 1,),
    free (nv,) bool, offsets (n_wisps + 1,), mass (nv,) or None.  Returns (nv, 3)."""
    return compiled.edge_lengths(x, None, length, free, offsets, mass, head)


def project_rest_lengths(x, free, offsets, rest_edge, mass, head=None):
    """``time.length_projection``: the frame's final positions with every edge that ends
    at a free vertex set to its rest length, its direction kept, from each wisp's root
    (or last pinned vertex) outwards (:func:`_set_edge_lengths`, one compiled pass);
    on a wisp with no pinned vertex the mass-weighted mean of the corrections is
    removed, so its momentum is kept (its lengths too: a uniform shift).  ``head``:
    None or (centre (3,), radius, allowed depth (nv,)): on a wisp with a pinned vertex,
    a vertex the walk would leave deeper in that sphere than allowed is put on it
    instead, at its edge's rest length from its predecessor (the vertices after it
    follow); a wisp with no pinned vertex that the mean shift leaves with a vertex that
    deep gets a second walk around the head from its first vertex (pushed onto the
    sphere if it is that deep), without the shift: the head's push is an outside force
    (its mean shift took pushed vertices back in: a free strand dropped on the head 3.9
    strand radii deep).  x (nv, 3), free (nv,) bool, offsets (n_wisps + 1,), rest_edge
    (nv - 1,), mass (nv,).  Returns (nv, 3)."""
    out = _set_edge_lengths(x, rest_edge, free, offsets, mass, head)
    if head is None:
        return out
    off = np.asarray(offsets, np.int64)
    sizes = np.diff(off)
    wisp = np.repeat(np.arange(len(sizes)), sizes)
    loose = np.bincount(wisp[~free], minlength=len(sizes)) == 0
    c, R, allow = head
    y = out - c
    dist = np.sqrt(np.einsum("ij,ij->i", y, y))
    sunk = loose[wisp] & (R - dist > allow) & (dist > 0)
    if not sunk.any():
        return out
    again = np.bincount(wisp[sunk], minlength=len(sizes)) > 0
    first = off[:-1][again & (sizes > 0)]
    out = out.copy()
    deep = first[R - dist[first] > allow[first]]
    out[deep] = c + y[deep] * (R / dist[deep])[:, None]
    anchored = free.copy()
    anchored[first] = False             # the walk starts from it and shifts nothing
    second = _set_edge_lengths(out, rest_edge, anchored, offsets, None, head)
    mask = again[wisp]
    out[mask] = second[mask]
    return out
