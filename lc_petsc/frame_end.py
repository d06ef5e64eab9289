"""A step's end: what keeps the hair out of the head and the strands apart after
Newton (``physics.head_push_out``, ``physics.strand_separation``, the ccd mode's path
check of the frame; docs/contact.md "Hair and the head", "Over a whole run").

:class:`FrameEnd`, owned by :class:`lc_petsc.integrator.Integrator`, pushes out the
vertices deeper in the head sphere than allowed, lifts the straight paths from the last
frame that cut under the scalp (by at most :data:`head_contact.LIFT_RADII` strand radii
over all of a step's rounds), sets the moved wisps back to their rest lengths, and
alternates the strand separation with the path check.  Its head sphere is the step's end
(:meth:`FrameEnd.begin_step`, called at each backward-Euler step's start).  The moves it
returns separately are those the velocity leaves out (a lift's outward speed would kick
the hair off the scalp)."""

from __future__ import annotations

import numpy as np

from lc_petsc.elements import head_contact
from lc_petsc.parallel import global_reduce
from lc_petsc.predictors import project_rest_lengths

#: strand contact: Jacobi rounds of the end-of-frame separation in all (FrameEnd.separate)
SEPARATION_ROUNDS = 60
#: strand contact, ccd mode: rounds of separation + frame-path check at a frame's end
#: (FrameEnd.collision_free_end, docs/contact.md "Over a whole run")
FRAME_END_ROUNDS = 4


class FrameEnd:
    """The frame end of one integrator (rank-local data, collective calls where noted).

    ``comm``; ``head`` (:class:`~lc_petsc.scene.head.HeadMotion`); ``strand`` (the
    :class:`~lc_petsc.contact.StrandContact`, None without strand contact); ``free``
    (nv,) the free vertices; ``offsets``, ``mass``, ``radius``: this rank's wisps'
    offsets, vertex masses and strand radii; ``rest_edge`` (nv - 1,) rest length of edge
    (v, v + 1); ``vertex_wisp`` (nv,) each vertex's local wisp.  ``head_collision``:
    the term is on (the head sphere of radius ``head.radius`` + ``margin``);
    ``push_out``: and ``physics.head_push_out``; ``separation``:
    ``physics.strand_separation``; ``length_projection``: ``time.length_projection``
    (moved wisps are set back to their rest lengths only then)."""

    def __init__(self, comm, head, strand, free, offsets, mass, radius, rest_edge, vertex_wisp, *,
                 head_collision, margin, push_out, separation, length_projection):
        self.comm, self.head, self.strand = comm, head, strand
        self.free, self.offsets, self.mass, self.radius = free, offsets, mass, radius
        self.rest_edge, self.vertex_wisp = rest_edge, vertex_wisp
        self.margin = margin
        self.push_out = head_collision and push_out
        self.separation = separation
        self.length_projection = length_projection
        #: per vertex: how deep the head's push-out lets it rest (physics.head_push_out)
        self.allowed_depth = head_contact.allowed_depth(
            radius, rest_edge, offsets, head.radius + margin) if head_collision else None
        self.t_next = None              # the step's end (begin_step)
        # per vertex: its distance from the head's centre before the step's first path
        # lift, at least the sphere's radius (None until then): what bounds the step's
        # lifts (:meth:`lift_room`)
        self.lift_base = None

    def begin_step(self, t_next):
        """A backward-Euler step to ``t_next`` starts: its head sphere is the one at
        ``t_next`` and its lifts are bounded afresh (:meth:`lift_room`)."""
        self.t_next = t_next
        self.lift_base = None

    def head_sphere(self):
        """(centre, radius, allowed depth (n,)) of the head sphere at the step's end: its
        radius + margin, and per vertex how deep the push-out lets it rest
        (:func:`head_contact.allowed_depth`)."""
        return (self.head.sphere_center(self.t_next), self.head.radius + self.margin,
                self.allowed_depth)

    def push_out_of_head(self, x, deep=None):
        """``x`` with every free vertex deeper in the head sphere (radius + margin) than
        allowed (its strand radius less its edges' sagitta on the sphere,
        :func:`head_contact.allowed_depth`) moved radially onto it.  The penalty sees a vertex only once an
        iterate is inside: at a fixed Newton count the last step can carry one in
        unopposed (a soft hairball's tips 1.06 cm deep; 0.048 with 10 iterations,
        docs/contact.md "Hair and the head").  A vertex resting on the head sinks by its
        push over the stiffness, far less than its radius, and is left alone, so a run
        whose hair never sinks that deep keeps its bits.  ``deep``: those vertices'
        indices when the caller has them (:meth:`sunk`)."""
        c, R, _ = self.head_sphere()
        if deep is None:
            deep = np.flatnonzero(self.sunk(x))
        if len(deep):
            y = x[deep] - c
            x = x.copy()
            x[deep] = c + y * (R / np.sqrt(np.einsum("ij,ij->i", y, y)))[:, None]
        return x

    def sunk(self, x):
        """Per vertex (n,): a free vertex deeper in the head sphere (radius + margin, at
        the step's end) than the push-out allows (:meth:`push_out_of_head`)."""
        c, R, allow = self.head_sphere()
        y = x - c
        dist = np.sqrt(np.einsum("ij,ij->i", y, y))
        return self.free & (R - dist > allow) & (dist > 0)

    def lift_room(self, x):
        """Per vertex (n,): how much farther out the path lift may still move it in this
        step: up to :data:`head_contact.LIFT_RADII` strand radii above its distance from
        the head's centre before the step's first lift round (set by that round), or above
        the sphere when it was under it (a later push-out's rise onto the sphere is not a
        lift: counted, it refused a tip pushed up from 0.84 radii deep the 3.2 radii its
        path needed).  Each round used to allow that much from where the vertex then was,
        so the rounds of the lift and of the frame end added up (8.2 radii in one frame)."""
        c, R, _ = self.head_sphere()
        y = x - c
        dist = np.sqrt(np.einsum("ij,ij->i", y, y))
        if self.lift_base is None:
            self.lift_base = np.maximum(dist, R)
        return self.lift_base + head_contact.LIFT_RADII * self.radius - dist

    def lift_head_paths(self, x_old, x, t_old):
        """``x`` (the step's end, at t_next) with each free vertex whose straight path from
        ``x_old`` (at ``t_old``), relative to the moving centre, goes deeper in the head
        sphere than allowed lifted straight out just enough for the path to stay that
        shallow, if that keeps it within :data:`head_contact.LIFT_RADII` strand radii of its
        height before the step's first lift (:meth:`lift_room`; all rounds together)
        (:func:`head_contact.lift_paths`): both ends on the scalp, the chord of a vertex
        sliding along it cuts under it (soft hairball: tips sliding 3.4 cm a frame,
        chords 0.10-0.12 cm deep past their 0.07 cm radius).  The lifted wisps' rest
        lengths are set again (:meth:`keep_lengths`).  Returns (x, the move (n, 3), which
        the velocity leaves out: an outward speed of lift / dt would kick the hair off
        the scalp; None when nothing moved)."""
        c0 = self.head.sphere_center(t_old)
        c1, R, allow = self.head_sphere()
        lifted = x
        # the length projection of a lifted wisp moves its lifted vertices back a little
        # (gravity 5000: 18 paths through after 1 round, 6 after 3)
        for _ in range(head_contact.LIFT_ROUNDS):
            p1, moved = head_contact.lift_paths(x_old - c0, lifted - c1, R, allow, self.lift_room(lifted),
                                                self.free)
            if not len(moved):
                break
            lifted = lifted.copy()
            lifted[moved] = c1 + p1[moved]
            lifted = self.keep_lengths(lifted, moved)
        if lifted is x:
            return x, None
        return lifted, lifted - x

    def head_end(self, x_old, x, t_old, lifted=None):
        """The head's part of the frame end on ``x``: the vertices deeper than allowed
        pushed out (:meth:`push_out_of_head`) with their wisps' rest lengths set
        (:meth:`keep_lengths`: a push alone left an edge 12.7% long), then the paths from
        ``x_old`` lifted (:meth:`lift_head_paths`).  Returns (x, ``lifted`` plus the
        lift's move: what the velocity leaves out; None while nothing was lifted); ``x``
        itself when nothing moved."""
        pushed = np.flatnonzero(self.sunk(x))
        if len(pushed):
            x = self.keep_lengths(self.push_out_of_head(x, pushed), pushed)
        x, move = self.lift_head_paths(x_old, x, t_old)
        if move is not None:
            lifted = move if lifted is None else lifted + move
        return x, lifted

    def head_left(self, x_old, x, t_old):
        """Whether a free vertex anywhere (collective) is deeper in the head than allowed
        or has a path from ``x_old`` that :meth:`lift_head_paths` would lift."""
        c0 = self.head.sphere_center(t_old)
        c1, R, allow = self.head_sphere()
        left = self.sunk(x).any() or len(head_contact.lift_paths(
            x_old - c0, x - c1, R, allow, self.lift_room(x), self.free)[1]) > 0
        return bool(global_reduce(self.comm, [float(left)], "max")[0])

    def keep_lengths(self, x, moved):
        """``x`` with the wisps of the vertices ``moved`` (indices) set back to their rest
        lengths around the head (the frame's length projection, when on; other wisps keep
        their bits): a vertex lifted or pushed out alone stretches its edges (a lift of
        2 radii: 3.0%; a push-out after the strand path check: 12.7%).  Only those
        wisps' vertices go through the projection (a wisp's walk depends on its own
        vertices alone: the same bits as projecting all)."""
        if not self.length_projection:
            return x
        touched = np.zeros(len(self.offsets) - 1, bool)
        touched[self.vertex_wisp[moved]] = True
        idx = np.flatnonzero(touched[self.vertex_wisp])
        sizes = np.diff(self.offsets)[touched]
        offsets = np.concatenate([[0], np.cumsum(sizes)])
        # edge k of the subset joins idx[k] and idx[k + 1]: within a wisp idx[k] + 1 (its
        # rest length rest_edge[idx[k]]); across two wisps unused
        c, R, allow = self.head_sphere()
        projected = project_rest_lengths(x[idx], self.free[idx], offsets, self.rest_edge[idx[:-1]],
                                         self.mass[idx], (c, R, allow[idx]))
        x = x.copy()
        x[idx] = projected
        return x

    def lift_frame_path(self, x_frame, x, t_frame):
        """After step cutback: ``x`` (the frame's end) with the frame's path x_n -> x_{n+1}
        from ``x_frame`` (at ``t_frame``; what a viewer interpolates), the chord of the
        substeps' chain, lifted out of the head too (:meth:`lift_head_paths`; the velocity
        leaves the move out, as a step's does)."""
        return self.lift_head_paths(x_frame, x, t_frame)[0]

    def collision_free_frame_path(self, x_frame, t_frame, x, t, contact):
        """ccd mode after step cutback: each substep's straight path is collision-free,
        but the frame's, x_n -> x_{n+1} (from ``x_frame`` at ``t_frame`` to ``x`` at
        ``t``: the path between the rows of frames.h5 that a viewer and the end-of-run
        check interpolate), is the chord of their chain and can cross (60 soft wisps with
        self-contact, 8 substeps a frame: 180 crossings between wisps and 51 within over
        30 frames, none on any substep's path).  The frame's path gets the frame end's
        path check and separation (:meth:`collision_free_end`, with the head's rigid
        motion over the whole frame).  ``contact``: the last substep's figures (pairs,
        deep, min distance, pairs separated).  Returns (the new end, what the velocity
        loses of its move: all but the head lift's kept part, the contact figures at the
        new end)."""
        motion = self.head.rigid_motion(t_frame, t)
        y, pairs, deep, dmin, n_sep, lifted = self.collision_free_end(x_frame, x, motion, contact[1], t_frame)
        moved = y - x if lifted is None else y - x - lifted
        return y, moved, (pairs, deep, dmin, max(n_sep, contact[3]))

    def collision_free_end(self, x_old, x, motion, deep, t_old, lifted=None):
        """ccd mode, the frame's end: the path check (the straight path x_old -> x must
        not cross, :meth:`StrandContact.collision_free_frame`) and the separation
        alternate, at most :data:`FRAME_END_ROUNDS` rounds after a first separation of the
        ``deep`` pairs of the Newton iterate, the path check last: a pair
        the path check holds back ends where its path stopped (at its floor, 0.05 d0),
        and the separation pushes it apart again before the next frame starts from it
        (one round halved such a pair's distance every frame, docs/contact.md).  Stops
        early once no pair is deep after a path check (the separation calls are not
        followed by a measure of their own: the one after the path check finds what
        they left, from the path check's candidates, without a broad phase).  With the
        head's push-out, each round's path check is preceded by the head's frame end
        (:meth:`head_end`, paths from ``x_old`` at ``t_old``), and a round follows while
        a vertex is left too deep or with a path to lift (:meth:`head_left`).
        ``lifted``: the head lift's move in ``x`` so far (or None); each path check keeps
        the fraction beta of it (:attr:`StrandContact.path_fraction`).  Returns (x, pairs,
        deep, min distance, pairs separated, the lift's move kept in x or None)."""
        strand = self.strand
        separation = self.separation
        push = self.push_out
        n_sep = 0
        head_left = False
        for rnd in range(FRAME_END_ROUNDS):
            if rnd > 0 and (not separation or deep == 0) and not head_left:
                break
            if separation and deep:
                # one call of all the rounds; no measure of its own (see above)
                x, n, _ = strand.separate(x, max_iterations=SEPARATION_ROUNDS)
                n_sep = max(n_sep, n)
            if push:
                # the path check holds a vertex back on its straight path, which can cut
                # under the scalp, and the separation can push it in (soft hairball,
                # gravity 5000: a tip 0.044 -> 0.119 -> 0.152 cm deep, radius 0.101);
                # lifted again here, the path check below keeps the lifted path's end
                x, lifted = self.head_end(x_old, x, t_old, lifted)
            x = strand.collision_free_frame(x_old, x, motion)[0]
            if lifted is not None:
                # a held-back vertex keeps beta of its lift: only that is left out of v
                lifted = lifted * strand.path_fraction[:, None]
            pairs, deep, dmin = strand.measure(x)
            head_left = push and self.head_left(x_old, x, t_old)
        return x, pairs, deep, dmin, n_sep, lifted

    def strand_end(self, x_old, x, motion, t_old, lifted=None):
        """Strand contact's part of a step's end on ``x`` (collective): its measure, then
        in ccd mode the path check and separation (:meth:`collision_free_end`), in
        penalty mode the separation (:meth:`separate`) and the head after it
        (:meth:`head_after_separation`).  ``x_old`` at ``t_old``: the step's start;
        ``motion``: the head's rigid motion over the step; ``lifted``: the head lift's
        move in ``x`` so far (or None).  Returns (x, the lift's move kept in x or None,
        (pairs, deep pairs, min distance, pairs separated))."""
        strand = self.strand
        pairs, deep, dmin = strand.measure(x)
        n_sep = 0
        strand.last_separation = (0, 0, 0)
        if strand.mode == "ccd":
            x, pairs, deep, dmin, n_sep, lifted = self.collision_free_end(x_old, x, motion, deep, t_old, lifted)
        elif self.separation:
            x, pairs, deep, dmin, n_sep = self.separate(x, pairs, deep, dmin)
            if self.push_out:
                y, lifted = self.head_after_separation(x_old, x, t_old, lifted)
                if global_reduce(self.comm, [float(y is not x)], "max")[0]:
                    pairs, deep, dmin = strand.measure(y)
                x = y
        return x, lifted, (pairs, deep, dmin, n_sep)

    def head_after_separation(self, x_old, x, t_old, lifted):
        """Penalty mode, after the separation: the head's end (:meth:`head_end`) in at
        most :data:`FRAME_END_ROUNDS` rounds, until no vertex is left too deep or with a
        path to lift (:meth:`head_left`).  The separation moves lifted vertices, their
        paths cut under the scalp again (soft hairball, gravity 5000: 22 paths through in
        8 steps, 14 of them mendable); penalty mode keeps no crossing guarantee, so the
        head goes last, in rounds: the projection moves a lifted vertex back.  Returns
        (x, ``lifted`` plus the lifts' moves); ``x`` itself when nothing moved."""
        y = x
        for _ in range(FRAME_END_ROUNDS):
            y, lifted = self.head_end(x_old, y, t_old, lifted)
            if not self.head_left(x_old, y, t_old):
                break
        return y, lifted

    def separate(self, x, pairs, deep, dmin):
        """The separation of the pairs closer than d0 / 2 (``deep`` of them): at most
        :data:`SEPARATION_ROUNDS` Jacobi rounds in all, over at most 3 calls of
        :meth:`StrandContact.separate`, each followed by a measure.  A call works on
        the pairs closer than d0 at its start and stops when none of them is deep; its
        corrections can bring pairs it did not see within d0 / 2, which the measure
        finds and the next call takes (3 calls of 20 rounds each paid a broad phase
        per call for a few stubborn pairs, docs/contact.md).  Penalty mode; ccd mode
        separates inside :meth:`collision_free_end`.  Returns (x, pairs, deep, min
        distance, pairs separated)."""
        n_sep = 0
        budget = SEPARATION_ROUNDS
        for _ in range(3):
            if deep == 0 or budget <= 0:
                break
            x, n, rounds = self.strand.separate(x, max_iterations=budget)
            n_sep = max(n_sep, n)
            budget -= max(rounds, 1)
            pairs, deep, dmin = self.strand.measure(x)
        return x, pairs, deep, dmin, n_sep
