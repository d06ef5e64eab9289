"""BDF-1 (backward Euler) Newton on the incremental potential (SPEC 4).

Each frame solves  G(x) = 1/(2 dt^2) (x - xhat)^T M (x - xhat) + V(x) - f_ext^T x
(+ the head-sphere penalty), xhat = x_n + dt v_n, by Newton steps
(M/dt^2 + K^+) dx = -grad G with K^+ the filtered element Hessians.

* Initial iterate: xhat for free vertices; pinned vertices are moved to their prescribed
  position at t_{n+1} first, so their Newton increments are zero (identity rows/cols,
  zero right-hand side) and the prescribed motion enters through the elements.
* Initial iterate ``time.initial_guess``: ``inertial`` (the above) or
  ``follow_the_leader`` (projected onto the rest edge lengths, :func:`follow_the_leader`).
* Update ``time.newton_update``: ``linear`` (x + alpha dx) or ``edge_retraction``
  (default; :func:`retract_edge_lengths`: a linearised rotation does not stretch the
  stiff edges, the oscillation that kept the paper's Newton from converging,
  docs/newton.md) or ``corotational`` (the same for filtered steps; the exact steps of
  ``exact_or_analytic`` with each edge also turned by the rotation of its neighbourhood,
  :func:`corotational_update`, so a linearised rotation of a coil does not distort its
  bend and twist angles either).
* Termination: ``newton_iterations`` steps (default 3, the paper) or, when a tolerance
  is set, as soon as the last step's largest vertex increment relative to its wisp's
  rest length is below ``newton_increment_tol`` (and/or the absolute one below
  ``newton_tol`` cm), and so is the error it implies at the iteration's observed
  contraction (:func:`contraction_factor`: an iteration contracting by q per step is
  still about d q / (1 - q) from its solution after a step of d; the analytic filter
  crawling at q ~ 0.97 had stopped 40x the tolerance from it, docs/newton.md "Twelfth
  round"); per frame ``newton_converged`` and ``newton_increment`` record it.  A step
  at the positions' round-off (:func:`round_off_floor`) needs no contraction factor,
  and above :data:`LOOSE_TOLERANCE` no confirmation and no model check: its
  increments bounce and its line search halves at noise.
  Above :data:`LOOSE_TOLERANCE` a stop must be confirmed by the next iteration
  (:func:`confirms_stop`), and the stopping step and the one before it must be whole
  steps whose decrease of G agrees with their quadratic model (:func:`model_agrees`:
  where it does not, a step's size says nothing of the distance left); so must the step
  before a claim that the next step confirms (a two-step lull, docs/newton.md).
  ``time.newton_stop = "quadratic_estimate"`` also stops once three full exact steps in
  a row, each shorter and the last two on their quadratic model, estimate the error
  below the tolerance / :data:`QUADRATIC_SAFETY` (:func:`quadratic_error_estimate`);
  ``newton_increment`` is then that estimate.  ``time.newton_stop = "chord_estimate"``
  does that too, and after two full exact steps in a row that contract on their model
  (:func:`chord_basis`; at a loose tolerance after one, a claim then confirmed only by the
  next iterate's check with that basis), the last of increment d predicting the tolerance
  (:data:`CHORD_TRY_C` d^2 below it), measures
  the next increment instead of taking the step: the step a solve with the last exact
  matrix (a chord step, its factorisation reused) would take from the new iterate;
  when it shows the iteration converging and lies below the tolerance with a margin
  (:func:`chord_stop`), Newton stops with that iterate (``newton_increment`` is then the
  chord step's increment; ``newton_chord_checks`` counts these solves per frame,
  cut-back attempts included).  Not with strand contact (refused by the configuration).
  ``solver.exact_stay``: after a full, unshifted exact step the next one is exact too.
  At any tolerance a stop whose last step was exact is refused when a wisp's exact
  Hessian is not positive definite (:meth:`Integrator._at_saddle`: a saddle of G, not the
  step's solution), and with strand contact when the whole A + C has negative curvature
  (:meth:`Integrator._at_coupled_saddle`: a mode over contact-coupled wisps whose own
  blocks are definite, found by Lanczos); the solve then ends unconverged, for step
  cutback to redo it (``newton_saddle`` per frame).  With an element filter alone (not
  ``exact_or_analytic``) at a tolerance of :data:`VERIFY_FROM` or tighter, a stop after a
  filtered step is checked by an exact Newton step at its iterate
  (:meth:`Integrator._verify_stop`): kept when that step is within the tolerances and on
  its quadratic model, and the step taken (it lands 1e2-1e6x closer), else refused and
  the step taken next (the analytic filter's stops on the stiff smash had been 1.6-238x
  away).  A coupled check whose Lanczos did not converge keeps the stop as unknown.
  Per frame: ``newton_verified``, ``newton_verify_refused``, ``newton_stops_refused``,
  ``newton_coupled_unknown``.
* Step cutback (``time.max_substeps``, only with a tolerance): a frame whose Newton
  misses it within the cap is redone from its start state as two backward-Euler steps
  of dt / 2 (head, pins and head sphere at their own times), each cut again if it
  fails, up to ``max_substeps`` steps in the frame (:meth:`Integrator._advance`); every
  frame starts at the full dt again, so frames, checkpoints and restarts stay at frame
  times.  Strand contact's per-step hooks (ccd first iterate and frame path,
  separation, measures) run per substep, its statistics' entries per frame; in ccd
  mode the frame's own path x_n -> x_{n+1} is then checked too (the chord of the
  substeps' chain can cross, :meth:`Integrator._collision_free_frame_path`).  A frame
  still short of the tolerance is kept (``time.unconverged = "accept"``) or ends the
  run (``"error"``: :class:`SimulationError`).
* ``solver.filter = "exact_or_analytic"``: once the relative increment is below
  :data:`EXACT_BELOW` the exact Hessian is assembled and its step kept when CG finds no
  indefiniteness and Armijo holds within :data:`EXACT_HALVINGS` halvings; otherwise the
  iteration re-assembles with the analytic filter (``exact_hessian_fallbacks``).
  With ``solver.exact_fallback = "shifted"`` the exact Hessian plus tau M/dt^2, tau in
  :data:`EXACT_SHIFTS` (smallest first), is tried before that (docs/newton.md "Seventh
  round": an exact step that is an ascent direction near the solution had left the
  iteration at the analytic filter's linear rate), and a wisp whose exact block is
  indefinite gets its own shift before the solve (:meth:`Integrator._exact_system`:
  exact steps on indefinite blocks had led Newton to saddles of G).  ``solver.wisp_trust``
  carries each wisp's shift to its next exact step (:mod:`lc_petsc.wisp_trust`), starts
  exact steps at 1e-2 and keeps them once one was kept.
* Optional Armijo backtracking on G (``line_search``): alpha halves from 1 until
  G(update(x, alpha dx)) <= G(x) + 1e-4 alpha grad G . dx, at most 20 halvings.
* ``time.length_projection``: the final iterate is projected onto the rest edge lengths
  (:func:`project_rest_lengths`; the strain the few Newton iterations leave, measured
  to leave the trajectory error unchanged, docs/newton.md) before the strand-contact
  measures and the velocity.
* v_{n+1} = (x_{n+1} - x_n) / dt.
* Strand-strand contact (``strand``, a :class:`lc_petsc.contact.StrandContact`, set by
  the simulator when ``strand_collision`` is on) adds its penalty to G, its gradient,
  its band blocks to the Newton matrix and rebuilds the contact matrix every Newton
  iteration; its calls are collective, so they run outside the rank-local guarded
  blocks.  After the Newton iterations the active pairs and the minimum segment
  distance are measured; pairs closer than half the thickness are pushed apart
  (``physics.strand_separation``, :meth:`StrandContact.separate`, at most
  :data:`lc_petsc.frame_end.SEPARATION_ROUNDS` Jacobi rounds over at most 3 calls, each followed by a
  measure; the pairs found are counted in ``contact_separated``), and the
  figures at the final positions are recorded (``contact_pairs``,
  ``contact_deep_pairs`` closer than half the thickness, ``contact_min_distance``: the
  smallest distance of any two segments that may be in contact, not only of the
  candidates, :meth:`StrandContact.min_distance`).
* ``physics.strand_contact_mode = "ccd"``: the first iterate, every Newton update
  (``StrandContact.limit_step``: per-vertex fractions of the path to the update) and the frame's end
  (``StrandContact.collision_free_frame``) are limited so that no two segments of
  different wisps meet on the straight path (docs/contact.md); in ``penalty`` mode
  these calls change nothing.

The stop arithmetic, the loop's state and the notes on stops are in
:mod:`lc_petsc.newton_stop`, the first-iterate predictors and the edge-length walks in
:mod:`lc_petsc.predictors`, the step's end (head push-out and path lift, strand
separation, ccd frame path) in :class:`lc_petsc.frame_end.FrameEnd`.
"""

from __future__ import annotations

import numpy as np

from lc_petsc import contact_curvature, curvature, wisp_trust
from lc_petsc.config import element_filter
from lc_petsc.elements import compiled_turn, head_contact
from lc_petsc.frame_end import FrameEnd
from lc_petsc.newton_stop import (CHORD_TRY_C, ENERGY_FLOOR, EXACT_BELOW, LOOSE_TOLERANCE, QUADRATIC_SAFETY,
                                  NewtonState, SolveRecord, StepRecord, chord_basis, chord_stop, confirms_stop,
                                  model_agrees, quadratic_error_estimate, round_off_floor, saddle_note,
                                  step_contraction, stop_note, unconfirmed_note, verify_note)
from lc_petsc.parallel import collectively, global_reduce
from lc_petsc.root_rotation import RootRotation
from lc_petsc.solver_plan import default_ksp_rtol
from lc_petsc.predictors import (corotational_update, follow_the_leader, head_motion_change, project_rest_lengths,
                                 retract_edge_lengths, start_carry_weight)
from lc_petsc.scene.state import vertex_wisp_length
from lc_petsc.errors import SimulationError, SolverError
from lc_petsc.trust_region import ETA, TRUST_RETRIES, Region, ratio, update_radius


class Integrator:
    """Backward-Euler time stepping of one simulator: per frame, Newton iterations of
    assembly, linear solve, line search and update, with pinned roots and the head.

    ``x0``: this rank's initial positions (n_local, 3); ``strand``: the strand contact
    (:class:`~lc_petsc.contact.StrandContact`), None without it."""

    def __init__(self, scene, assembler, solver, comm, timers, config, head, x0, strand=None,
                 trust=None):
        self.scene, self.asm, self.solver, self.comm = scene, assembler, solver, comm
        self.trust = trust              # the TrustRegionSolver (time.newton = "trust_region")
        self.timers, self.cfg, self.head = timers, config, head
        terms = set(config.physics.terms)
        self.gravity = np.asarray(config.physics.gravity, float) if "gravity" in terms else np.zeros(3)
        self.contact = "head_collision" in terms
        self.free = ~scene.pinned
        self.f_ext = scene.mass[:, None] * self.gravity[None, :]
        self.x = np.array(x0, float)
        if self.x.shape != scene.x_rest.shape:
            raise ValueError(f"Integrator: initial positions of shape {self.x.shape}, expected "
                             f"{scene.x_rest.shape} (this rank's vertices, 3)")
        self.v = np.zeros_like(self.x)
        self.t = 0.0
        self.frame = 0
        self.dt = config.time.dt        # the current step's (a substep's with cutback)
        self.newton_iterations = []     # per frame: every attempt's iterations (the cost)
        self.newton_substeps = []       # per frame: the backward-Euler steps kept (1: no cutback)
        self.newton_substep_iterations = []   # per frame: the kept steps' iterations
        self._discarded = 0             # the frame's iterations of attempts cut back
        self._discarded_checks = 0      # and their chord checks
        self.xv, self.bv = assembler.mat.createVecs()
        self.strand = strand
        self.contact_pairs = []
        self.contact_deep_pairs = []
        self.contact_min_distance = []
        self.contact_separated = []
        # the update (x, step) -> next iterate (see update); ccd mode at a fixed count:
        # linear (the limiter would cut most nonlinear updates of a large scene, and each
        # cut costs a second limiter call); the mode means nothing without strand contact
        #: the run's configuration; with time.start_increment_tol the start frames' (step)
        self.run_config = config
        self.start_config = config.start_config() if config.time.start_increment_tol is not None else None
        self._use(config)
        # time.jolt_above: the head's jolts measured at its farthest root (all ranks')
        self.jolt_reach = None
        if config.time.jolt_above is not None and head.kind != "static":
            reach = np.linalg.norm(scene.x_rest[scene.pinned] - head.center, axis=1)
            self.jolt_reach = float(global_reduce(comm, [reach.max(initial=0.0)], "max")[0])
        # the start frames' -ksp_rtol: a converging Newton's default unless the options set one
        given = solver.rtol != float(solver.plan.ksp_rtol)
        self._rtols = (solver.rtol, solver.rtol if given else float(default_ksp_rtol(True)))
        self.wisp_length = vertex_wisp_length(scene.x_rest, scene.offsets)
        # the shortest wisp (all ranks): time.newton_tol (cm) alone is loose relative to it
        self.shortest_wisp = float(global_reduce(comm, [self.wisp_length.min(initial=np.inf)], "min")[0])
        # the free vertices of wisps held by the head (a pinned vertex), which the first
        # iterate carries with the head's change of motion (time.carry_with_head)
        self.vertex_wisp = np.repeat(np.arange(len(scene.offsets) - 1), np.diff(scene.offsets))
        self.carried = None
        if config.time.carry_with_head and head.kind != "static":
            wisp = self.vertex_wisp
            held = np.bincount(wisp[scene.pinned], minlength=len(scene.offsets) - 1) > 0
            carried = self.free & held[wisp]
            self.carried = carried if carried.any() else None
        self.rest_edge = np.linalg.norm(np.diff(scene.x_rest, axis=0), axis=1)
        #: time.root_rotation: each root-held wisp turned after a fixed count (_last_turn)
        self.root_turn = RootRotation(scene.offsets, scene.pinned, assembler.elements,
                                      {n: t.k for n, t in scene.terms.items()},
                                      kernels=assembler.kernels) \
            if config.time.root_rotation else None
        #: the step's end: head push-out and path lift, strand separation, ccd frame path
        self.frame_end = FrameEnd(comm, head, strand, self.free, scene.offsets, scene.mass, scene.radius,
                                  self.rest_edge, self.vertex_wisp, head_collision=self.contact,
                                  margin=config.physics.head_margin, push_out=config.physics.head_push_out,
                                  separation=config.physics.strand_separation,
                                  length_projection=config.time.length_projection)
        if self.carried is not None:
            self.start_weight = start_carry_weight(self.rest_edge, scene.offsets, scene.pinned)
        self.newton_increment = []      # per frame: the last step's relative increment
        self.newton_converged = []      # per frame: met the tolerances (None: none set)
        self.newton_capped = []         # per frame: a start/jolt frame ended by its cap (_capped)
        self.newton_unconfirmed = []    # per frame: kept steps the cap ended on an unconfirmed stop
        self.newton_refused = []        # per frame: kept steps the cap ended on a refused stop
        self.newton_saddle = []         # per frame: stops refused on a saddle of G (all attempts)
        self._saddles = 0               # the frame's so far
        # per frame, all attempts (cutback's discarded ones included), as newton_saddle:
        self.newton_verified = []       # stops after filtered steps checked by an exact step
        self.newton_verify_refused = []     # ... of them refused (_verify_stop)
        self.newton_stops_refused = []      # claimed stops refused by any rule
        self.newton_coupled_unknown = []    # coupled-saddle checks whose Lanczos did not converge
        self.root_turns_reduced = []    # wisps whose root turn raised their share of G (RootRotation.step)
        self.newton_extend_capped = []  # solves time.newton_extend_cap ended above newton_extend_above
        self.newton_jolt_starts = []    # steps started from time.jolt_first_iterate's first iterate
        self._counts = dict.fromkeys(FRAME_COUNTS, 0)   # the frame's so far
        self.verifications = []         # every verification: (frame, iteration, verdict, step length)
        self._saddle_wisps = []         # the last saddle's wisps (the scene's numbers; for the monitor)
        # the scene's number of internal wisp i (-lc_wisp_order; set by the Simulator):
        # the monitor names wisps as the user's scene and frames.h5 number them
        self.wisp_order = None
        self._coupled = None            # the check over contact-coupled wisps (_at_coupled_saddle)
        self.coupled_checks = []        # its verdicts (contact_curvature.Verdict), one per check
        self.history = None             # a list: per-iteration measures are appended
        self.monitor = None             # a stream: a line per Newton iteration (rank 0)
        self._fallback = ""            # why the last exact step was rejected (history)
        self._shift = 0.0              # the mass shift of the last exact step (history)
        self._tried_shift = 0.0        # the largest of the last exact assembly's (_exact_system)
        self._wisp_tau = None          # per wisp: the last exact assembly's shifts (_exact_system)
        self._kept_system = None       # the last exact assembly's x, matrix and parts (_exact_assembly)
        self._inertia = None           # (matrix, its wisps not positive definite) (_negative_wisps)
        self._kept_shares = None       # (x, the wisps' shares of G at x) (_wisp_step)
        self._wisp_alpha = None        # per vertex: its wisp's alpha (_wisp_line_search) or None
        # solver.wisp_trust (lc_petsc/wisp_trust.py): per local wisp the shift its next exact
        # step starts from, and whether this solve has kept an exact step (then it stays exact)
        self._wisp_mu = np.zeros(len(scene.offsets) - 1)
        self._kept_exact = False
        self._searched = None          # the last accepted line search's (G0, G, g . dx)
        self._probe = None             # the last line search's (G0, g . dx), found or not
        self._region_record = {}        # the last trust-region step's rho, radius (history)
        self._verifying = np.inf        # the last verifying exact step's relative increment
        self._force_scale = 0.0         # the frame's force scale (with a history only)
        self.exact_hessian_fallbacks = []     # per frame: exact Hessians replaced by filtered ones
        self.chord_checks = []          # per frame: chord steps measured (newton_stop = "chord_estimate")
        self.length_projection_move = []    # per frame: time.length_projection's largest move / wisp length
        self._projection_move = 0.0
        self.newton_start = []          # per frame: run to time.start_increment_tol (a start frame)
        self.newton_jolt = []           # per frame: run to it for a head jolt (time.jolt_above)

    def _use(self, config):
        """Run the next frames with ``config`` (the run's or its start frames'): it and the
        Newton path's flags it decides.  ``converging``: a tolerance is set (Newton runs to
        convergence, not a fixed count); ``retract`` / ``turn_exact``: the nonlinear
        updates (ccd mode at a fixed count: linear, the limiter would cut most nonlinear
        updates of a large scene, and each cut costs a second limiter call; the mode
        means nothing without strand contact); ``wisp_trust``: solver.wisp_trust where
        exact steps are searched wisp by wisp."""
        self.cfg = config
        self.converging = config.time.newton_converges
        nonlinear = self.converging or not (self.strand is not None and config.physics.strand_contact_mode == "ccd")
        self.retract = nonlinear and config.time.newton_update in ("edge_retraction", "corotational")
        self.turn_exact = nonlinear and config.time.newton_update == "corotational"
        self.wisp_trust = config.solver.wisp_trust and self._per_wisp_search()
        self.asm.filter = element_filter(config.solver.filter)
        if self.strand is not None:
            self.strand.filter = self.asm.filter

    # -------------------------------------------------------------- potential
    def _contact_terms(self, x, need_hessian, per_vertex=False):
        """The head sphere's penalty at x: (energy (per active vertex with
        ``per_vertex``), the active free vertices, (gradient, Hessian or None)); (0.0,
        None, None) without head collision."""
        if not self.contact:
            return 0.0, None, None
        with self.timers("collision"):
            return self._head_terms(x, need_hessian, per_vertex)

    def _head_terms(self, x, need_hessian, per_vertex=False):
        """:meth:`_contact_terms` with head collision on, untimed (the root turn times
        its passes with the turn, :meth:`_last_turn`)."""
        c = self.head.sphere_center(self.t_next)      # kept per time by the HeadMotion
        R, k = self.head.radius + self.cfg.physics.head_margin, self.cfg.physics.head_stiffness
        idx = np.flatnonzero(self.free & head_contact.active(x, c, R))
        if len(idx) == 0:
            return 0.0, idx, None
        xi = x[idx]
        e = head_contact.energy(xi, c, R, k)
        e = e if per_vertex else float(e.sum())
        g = head_contact.gradient(xi, c, R, k)
        # the exact Newton matrix needs the exact head Hessian too (its negative
        # curvature is what lets a sliding vertex converge quadratically)
        H = head_contact.hessian(xi, c, R, k, filter="none" if self.asm.filter == "none"
                                 else "analytic") if need_hessian else None
        return e, idx, (g, H)

    def incremental_potential(self, x):
        """G(x), summed over all ranks."""
        dt = self.dt
        with collectively(self.comm, f"frame {self.frame}: incremental potential"):
            d = (x - self.xhat)[self.free]
            m = self.scene.mass[self.free]
            local = 0.5 / dt ** 2 * float(np.sum(m[:, None] * d * d))
            local += self.asm.energy(x)
            local -= float(np.sum(self.f_ext[self.free] * x[self.free]))
            local += self._contact_terms(x, False)[0]
        total = self.comm.allreduce(local)
        if self.strand is not None:
            total += self.strand.energy(x)
        return total

    def wisp_potentials(self, x):
        """Each of this rank's wisps' share of G at x (n_local_wisps,): its inertia,
        elastic, gravity and head-penalty terms (their sum over all ranks is G without
        strand contact, up to round-off).  Rank-local, no collective; a wisp's share
        depends on that wisp alone."""
        per = self._vertex_potentials(x) + self.asm.vertex_energy(x)
        return self._wisp_sum(per)

    def _wisp_sum(self, per_vertex):
        """Per local wisp, the sum of ``per_vertex`` (nv,) over its vertices."""
        return np.bincount(self.vertex_wisp, per_vertex, minlength=len(self.scene.offsets) - 1)

    def _mass_unit(self):
        """Per vertex, the unit of the mass shifts: M/dt^2 on free vertices, 0 on pinned ones."""
        return np.where(self.free, self.scene.mass / self.dt ** 2, 0.0)

    def gradient(self, x, elastic=None, head=None):
        """grad G at x (pinned rows zeroed); ``elastic`` reuses an elastic gradient,
        ``head`` the head's terms at x (:meth:`_contact_terms`' last two)."""
        dt = self.dt
        if elastic is None:
            elastic = self.asm.gradient(x)
        g = self.scene.mass[:, None] * (x - self.xhat) / dt ** 2 + elastic - self.f_ext
        idx, cg = self._contact_terms(x, False)[1:] if head is None else head
        if cg is not None:
            g[idx] += cg[0]
        g[~self.free] = 0.0
        return g

    # -------------------------------------------------------------- one frame
    def step(self):
        """Advance one frame (collective): one backward-Euler step of ``time.dt``, with
        step cutback when a tolerance is set (:meth:`_advance`).  Per frame: the Newton
        iterations of every attempt, the substeps kept, whether all of them converged
        and their largest final increment.  The first ``time.start_frames`` frames run
        with the start configuration when ``time.start_increment_tol`` is set, and so do
        later frames where the head jolts (``time.jolt_above``, :meth:`_jolt`)."""
        start = self.start_config is not None and self.frame < self.run_config.time.start_frames
        jolt = self.start_config is not None and not start and self._jolt() is not None
        self.newton_start.append(start)
        self.newton_jolt.append(jolt)
        if not (start or jolt):
            self._frame()
            return
        if self.monitor is not None:
            why = (f"a head jolt ({self._jolt():.4g} cm/s^2 > time.jolt_above)" if jolt else "a start frame")
            self._say(f"  frame {self.frame}: {why}, to time.start_increment_tol = "
                      f"{self.run_config.time.start_increment_tol:g} on the converging path")
        self._use(self.start_config)
        self.solver.set_rtol(self._rtols[1])
        try:
            self._frame()
        finally:
            self._use(self.run_config)
            self.solver.set_rtol(self._rtols[0])

    def _jolt(self):
        """The largest change of the head's acceleration at its farthest root (cm/s^2,
        :meth:`HeadMotion.jolt`) into this frame or the ``time.jolt_frames - 1`` before it
        when it is above ``time.jolt_above``, else None (also without the key or with a
        static head)."""
        if self.jolt_reach is None:
            return None
        t = self.run_config.time
        change = max(self.head.jolt(t.dt, f, self.jolt_reach)
                     for f in range(self.frame - t.jolt_frames + 1, self.frame + 1))
        return change if change > t.jolt_above else None

    def _capped(self, converged, iterations):
        """Whether a frame's Newton that ended after ``iterations`` (``converged`` False:
        above its tolerance) ended by the start/jolt cap the user set: a start or jolt frame
        (the start configuration in use) that took all of ``time.start_iterations`` with
        ``time.max_substeps = 1`` (no cutback), i.e. a larger fixed count on the converging
        path, not a missed tolerance (docs/newton.md "A capped start/jolt frame").  A stop
        refused on a saddle before the cap is a miss."""
        t = self.cfg.time
        return (converged is False and self.cfg is self.start_config and t.max_substeps == 1
                and iterations >= t.newton_iterations)

    def _frame(self):
        """:meth:`step` with the configuration in use."""
        cfg = self.cfg
        if self.strand is not None:             # per frame: the statistics' entries
            self.strand.start_frame()
        self._discarded = self._discarded_checks = self._saddles = 0
        self._counts = dict.fromkeys(FRAME_COUNTS, 0)
        self._projection_move = 0.0
        # the solves' solution vector is CG's first iterate under -ksp_initial_guess_nonzero:
        # it would carry the last frame's last Newton step, which no checkpoint holds, so a
        # restart would start its first solve elsewhere; every frame starts from zero
        self.xv.zeroEntries()
        x_frame, t_frame = self.x, self.t      # replaced by the step, never changed in place
        solves = self._advance(cfg.time.dt, self.t + cfg.time.dt, cfg.time.max_substeps)
        if len(solves) > 1 and self.contact and cfg.physics.head_push_out:
            self.x = self.frame_end.lift_frame_path(x_frame, self.x, t_frame)
        if len(solves) > 1 and self.strand is not None and self.strand.mode == "ccd":
            solves[-1] = self._collision_free_frame_path(x_frame, t_frame, solves[-1])
        conv = [s.converged for s in solves]
        converged = None if conv[0] is None else all(conv)
        unconfirmed = sum(s.unconfirmed for s in solves)
        refused = sum(s.refused for s in solves)
        saddles = sum(s.saddle for s in solves)     # kept ones (cutback discards the others)
        capped = self._capped(converged, sum(s.iterations for s in solves))
        if converged is False and not capped and cfg.time.unconverged == "error":
            raise SimulationError(
                f"frame {self.frame}: Newton did not reach the tolerance within time.newton_iterations = "
                f"{cfg.time.newton_iterations} in {len(solves)} substep(s) (time.max_substeps = "
                f"{cfg.time.max_substeps}; largest final relative increment "
                f"{max(s.increment for s in solves):.3g}{unconfirmed_note(unconfirmed, refused, saddles)}); raise "
                f"time.newton_iterations or time.max_substeps, loosen the tolerance, or set "
                f"time.unconverged = \"accept\"")
        self.newton_iterations.append(self._discarded + sum(s.iterations for s in solves))
        self.newton_substeps.append(len(solves))
        self.newton_substep_iterations.append([s.iterations for s in solves])
        self.newton_increment.append(max(s.increment for s in solves))
        self.newton_converged.append(converged)
        self.newton_capped.append(capped)
        self.newton_unconfirmed.append(unconfirmed)
        self.newton_refused.append(refused)
        self.newton_saddle.append(self._saddles)
        for name in FRAME_COUNTS:
            getattr(self, name).append(self._counts[name])
        self.exact_hessian_fallbacks.append(sum(s.fallbacks for s in solves))
        self.chord_checks.append(self._discarded_checks + sum(s.chord_checks for s in solves))
        self.length_projection_move.append(self._projection_move if cfg.time.length_projection else None)
        if self.strand is not None:             # the figures at the frame's end
            pairs, deep, dmin, _ = solves[-1].contact
            self.contact_pairs.append(pairs)
            self.contact_deep_pairs.append(deep)
            # the frame's true minimum, not only its contact candidates' (measure's)
            last = self.contact_min_distance[-1] if self.contact_min_distance else np.inf
            self.contact_min_distance.append(self.strand.min_distance(self.x, dmin, hint=last))
            if cfg.physics.strand_separation:
                self.contact_separated.append(max(s.contact[3] for s in solves))
        self.frame += 1

    def _advance(self, dt, t_next, substeps):
        """Backward-Euler steps from (x, v, t) to ``t_next`` (collective).  Step cutback:
        when this step's Newton misses the tolerance within the cap and ``substeps``
        (the most this step may be split into) is at least 2, its result is discarded
        (its iterations counted in ``_discarded``) and the step redone from its start
        state as two steps of dt / 2, each cut again if it fails (up to ``substeps``
        in all).  The decision is the same on every rank (the increments are reduced).
        Returns the kept steps' :class:`~lc_petsc.newton_stop.SolveRecord` records, in time order."""
        start = self.x, self.v, self.t
        move = self._projection_move
        solve = self._backward_euler(dt, t_next)
        if solve.converged is not False or substeps < 2:
            return [solve]
        self._projection_move = move          # a discarded attempt's frame is not written
        self._discarded += solve.iterations
        self._discarded_checks += solve.chord_checks
        if self.monitor is not None:
            self._say(f"  frame {self.frame}: the step of dt {dt:.4g} is discarded and redone as "
                      f"2 steps of dt {0.5 * dt:.4g} (step cutback)")
        self.x, self.v, self.t = start
        half = substeps // 2
        return self._advance(0.5 * dt, start[2] + 0.5 * dt, half) + self._advance(0.5 * dt, t_next, half)

    def _backward_euler(self, dt, t_next):
        """One backward-Euler step of ``dt`` from (x, v, t) to ``t_next`` (head and
        pinned vertices at ``t_next``): the first iterate (:meth:`_first_iterate`),
        Newton (:meth:`_newton`), the step's end (:meth:`_end_step`), then x, v and t
        are updated (collective).  Returns its :class:`~lc_petsc.newton_stop.SolveRecord` record."""
        x_old, x, motion = self._first_iterate(dt, t_next)
        s = self._newton(x)
        x, lifted, contact = self._end_step(x_old, s.x, motion)
        self.v = (x - x_old) / dt
        if lifted is not None:
            self.v -= lifted / dt
        self.x = x
        self.t = self.t_next
        return SolveRecord(s.n_it, s.converged, s.reported, s.fallbacks, s.chord_checks, contact, s.unconfirmed,
                      s.off_model, s.saddle)

    def _first_iterate(self, dt, t_next):
        """The step's set-up and Newton's first iterate: pinned vertices at ``t_next``,
        the head's carry, follow-the-leader (with ``time.jolt_first_iterate``, at a jump
        of the head's velocity in the step: the carry near the roots only, as at the
        start from rest, then follow-the-leader), in ccd mode no crossing on the path from
        x_n.  Returns (x_n, the first iterate, the head's rigid motion over the step)."""
        cfg, sc = self.cfg, self.scene
        self.dt = dt
        self.t_next = t_next
        self.frame_end.begin_step(t_next)
        x_old = self.x.copy()
        self.xhat = self.x + dt * self.v
        x = self.xhat.copy()
        pin = ~self.free
        if pin.any():
            x[pin] = self.head.pinned_positions(sc.x_rest[pin], self.t_next)
        # time.jolt_first_iterate: at a jump of the head's velocity the start's first iterate
        jolt = cfg.time.jolt_first_iterate and self.head.velocity_jumps(self.t, t_next)
        self._counts["newton_jolt_starts"] += jolt
        if self.carried is not None:
            change = head_motion_change(self.head, x_old[self.carried], self.t, dt, t_next)
            if self.t == 0.0 or jolt:   # a velocity jump (the start from rest): felt near the roots
                change *= self.start_weight[self.carried, None]
            x[self.carried] += change
        if cfg.time.initial_guess == "follow_the_leader" or jolt:
            x = follow_the_leader(x, self.free, sc.offsets, self.rest_edge)
        # the head's rigid motion over the step: the limiter's field on the frame paths
        motion = self.head.rigid_motion(self.t, self.t_next)
        if self.strand is not None:             # ccd mode: no crossing on x_old -> first iterate
            x = self.strand.collision_free_frame(x_old, x, motion, reuse=False)[0]
        return x_old, x, motion

    def _newton(self, x):
        """Newton's iterations from the first iterate ``x`` until a stop or the cap
        (collective).  Returns their :class:`~lc_petsc.newton_stop.NewtonState` state (the last iterate in ``x``)."""
        cfg = self.cfg
        if self.history is not None:
            self._force_scale = self.frame_force_scale()
        # the positions' round-off, from the first iterate's largest coordinate
        floor = round_off_floor(float(global_reduce(self.comm, [np.abs(x).max(initial=0.0)], "max")[0])) \
            if cfg.time.newton_converges else 0.0
        s = NewtonState(x, confirms_stop(cfg.time.newton_increment_tol, cfg.time.newton_tol, self.shortest_wisp),
                        Region() if self.trust is not None else None, floor)
        self._wisp_mu = np.zeros(len(self.scene.offsets) - 1)
        self._kept_exact = False
        extend = cfg.time.newton_extend_above is not None
        for it in range(cfg.time.newton_extend_cap if extend else cfg.time.newton_iterations):
            s.n_it += 1
            s.unconfirmed = s.off_model = s.saddle = False
            if s.region is not None and it > 0:     # after a filtered first step: lc_petsc/trust_region.py
                self._trust_iteration(s, it)
            else:
                self._newton_iteration(s, it)
            if s.converged or s.saddle or s.last:
                break
        if extend and self.monitor is not None and s.n_it > cfg.time.newton_iterations:
            self._say(f"  frame {self.frame} (dt {self.dt:.4g}): fixed count extended to {s.n_it} iteration(s) "
                      f"(time.newton_extend_above = {cfg.time.newton_extend_above:g})")
        if self.monitor is not None and s.converged is not None:
            ended = (f"capped at {s.n_it} (start/jolt cap, time.start_iterations)" if self._capped(s.converged, s.n_it)
                     else f"{'converged' if s.converged else 'NOT converged'} after {s.n_it} iteration(s)")
            self._say(f"  frame {self.frame} (dt {self.dt:.4g}): {ended}, measure {s.reported:.3e}"
                      + (" (a stop the cap left unconfirmed)" if s.unconfirmed else "")
                      + (" (a stop refused: G's decrease off its quadratic model)" if s.off_model else "")
                      + (" (a stop refused: a saddle of G)" if s.saddle else ""))
        return s

    def _trust_iteration(self, s, it):
        """One trust-region Newton iteration (``time.newton = "trust_region"``, after the
        first) and its stop test, on the state ``s``."""
        region = s.region
        g, dx, exact = self._trust_region_step(s.x, it, region)
        y = self.update(s.x, dx)
        s.last = self._ends_count(it, s.x, y)
        x_prev, s.x = s.x, self._last_turn(s.last, y)
        s.increment, absolute = self.increments(s.x - x_prev)
        s.steps.append(StepRecord(s.increment, region.interior, False, True))   # a boundary step is a cut one
        s.reported = s.increment
        if self.history is not None:
            self._record_iteration(it, x_prev, s.x, g, s.increment, 1.0, exact)
        s.round_off = absolute <= s.floor
        s.converged = self._newton_converged(s.steps, absolute, s.round_off)
        if s.converged is not None:         # a short step is not convergence
            s.converged = s.converged and region.interior
        # the loose-tolerance rule below, with the trust region's own rho (smash at
        # E = 1e12, dt 0.2, 1e-3: a stop 2.5x the tolerance away)
        claim = bool(s.converged)
        step = dict(agrees=region.agrees)
        confirmed, refused = self._loose_verdict(s.loose, claim, s.claimed_before, s.increment, s.steps,
                                                 (step, s.last_step, s.prior_step), round_off=s.round_off)
        s.converged = s.converged and confirmed and not refused
        s.settle(claim, step, confirmed, refused)
        self._counts["newton_stops_refused"] += refused
        if self.monitor is not None:
            self._monitor(it, s.increment, self._step_kind(exact, region=True)
                          + stop_note(s.unconfirmed, refused), 1.0, self.trust.iterations[-1], cut=False)

    def _newton_iteration(self, s, it):
        """One Newton iteration with a line search on the state ``s``: the step
        (:meth:`_direction`), the update and its measures (:meth:`_take_step`), the stop
        estimates (:meth:`_estimate_stop`) and the checks of a claimed stop
        (:meth:`_check_stop`)."""
        cfg = self.cfg
        unreduced = len(self.solver.not_reduced)    # solves short of -ksp_rtol so far
        g, dx, alpha, exact, rejected = self._direction(s, it)
        step_ksp = self.solver.iterations[-1]     # the step taken (before a chord check)
        if cfg.time.line_search and not exact:
            alpha = self._line_search(s.x, g, dx, 20, give_up=False)
        x_prev = s.x
        s.x, s.increment, measure, absolute = self._take_step(s, it, s.x, dx, alpha, exact, rejected)
        s.reported = measure
        if self.history is not None:
            self._record_iteration(it, x_prev, s.x, g, s.increment, alpha, exact)
        whole = alpha == 1.0 and self._shift == 0.0 and not (
            self.strand is not None and self.strand.last_cut)
        # the contraction is measured over whole Newton steps only: a damped step's
        # full measure taken as the rate's base let the stiff smash (E = 1e12, dt 0.2)
        # stop 155x the tolerance away at 1e-5 (docs/newton.md "Stopping rule"); a
        # step after an exact attempt Armijo rejected is a damped one (measured above),
        # a shifted one or one after an indefinite exact matrix no Newton step at all
        round_off = self._at_round_off()
        newton = (self._shift == 0.0 and self._fallback in ("", "armijo")) or round_off
        s.steps.append(StepRecord(measure, (whole and newton) or round_off,
                                  exact or cfg.solver.filter == "none", newton))
        s.round_off = absolute <= s.floor
        s.converged = self._newton_converged(s.steps, absolute, s.round_off)
        chord_claim, based = self._estimate_stop(s, it, exact and whole)
        # a step (or chord check) whose solve ran no residual test and missed -ksp_rtol
        # is not a Newton step: its small increment certifies nothing (Jacobi's steps
        # left the cantilever 39x the tolerance away, docs/newton.md "Stopping rule")
        short_of_rtol = len(self.solver.not_reduced) > unreduced
        s.converged = s.converged and not short_of_rtol
        # (a rejected exact attempt shows the quadratic model failing here: smash at
        # E = 1e12 stopped 2.4x away on the tiny filtered step that followed one)
        whole = whole and not self._fallback
        # the step's arrays are kept one more iteration only where the rule reads them
        step = dict(before=x_prev, after=s.x, g=g, dx=dx, whole=whole,
                    searched=self._searched if whole else None) if s.loose else None
        verdict, refused = self._check_stop(s, it, step, measure, chord_claim, based)
        if self.monitor is not None:
            short = ", solve short of -ksp_rtol" if short_of_rtol else ""
            short += ", at round-off" if s.round_off else ""
            short += stop_note(s.unconfirmed, refused) + (saddle_note(self._saddle_wisps) if s.saddle else "")
            short += verify_note(verdict, self._verifying)
            self._monitor(it, measure, self._step_kind(exact) + short, alpha, step_ksp,
                          cut=self.strand is not None and self.strand.last_cut, estimate=s.reported)

    def _direction(self, s, it):
        """This iteration's Newton step at ``s.x``: a refused stop's verifying exact step
        (``s.pending``), an exact one (:meth:`_exact_attempts`) or a filtered one.
        Returns (grad G, dx, alpha, whether exact, the exact step Armijo rejected or
        None)."""
        cfg, x = self.cfg, s.x
        exact = self._exact_hessian(s, (bool(s.quadratic) and cfg.solver.exact_stay) or self._kept_exact)
        self._shift, self._fallback, self._searched, self._probe = 0.0, "", None, None
        rejected = None                     # the exact step Armijo rejected
        if s.pending is not None:           # taken now: its assembly and solve are done
            exact, (g, dx, known), s.pending = True, s.pending, None
            alpha = self._line_search(x, g, dx, EXACT_HALVINGS, exact=True, known=known)
            if alpha is None:
                self._fallback, rejected = "armijo", dx
                exact, s.fallbacks = False, s.fallbacks + 1
        elif exact:
            g, dx, alpha, rejected = self._exact_attempts(x, it)
            if dx is None or alpha is None:     # no exact Newton step: a filtered one
                exact = False
                s.fallbacks += 1
            else:       # solver.wisp_trust: the wisps' shifts carry the damping from here on
                self._kept_exact = self.wisp_trust
        if not exact:
            self._wisp_alpha = None
            g = self._assemble_system(x, it)
            dx = self._solve_step(g, it)
            alpha = 1.0
            self._searched = None
        return g, dx, alpha, exact, rejected

    def _exact_attempts(self, x, it):
        """The exact step at x (:meth:`_exact_step`), then with ``solver.exact_fallback =
        "shifted"`` the :data:`EXACT_SHIFTS` ladder until one is kept.  Returns (grad G,
        dx, alpha, the first attempt's dx when it was rejected, else None); dx or alpha
        None when none was kept."""
        g, dx, alpha = self._exact_step(x, it, 0.0)
        if dx is not None and alpha is not None:
            self._shift = self._tried_shift     # > 0: some wisp's block was shifted
            return g, dx, alpha, None
        self._fallback = "indefinite" if dx is None else "armijo"
        rejected = dx
        for tau in EXACT_SHIFTS if self.cfg.solver.exact_fallback == "shifted" else ():
            g, dx, alpha = self._exact_step(x, it, tau)
            if dx is not None and alpha is not None:
                self._shift = self._tried_shift
                break
        return g, dx, alpha, rejected

    def _take_step(self, s, it, x, dx, alpha, exact, rejected):
        """The iterate after the step dx at ``alpha`` from x (in ccd mode limited) and the
        step's measures: (iterate, relative increment of the step taken, the stop's
        measure, its absolute size in cm); ``s.last``: whether a fixed count ends here
        (:meth:`_ends_count`).  Collective."""
        y = self.update(x, self._scaled(alpha, dx), exact)
        s.last = self._ends_count(it, x, y)
        y = self._last_turn(s.last, y)
        if self.strand is not None:         # ccd mode: per vertex, collision-free path
            nonlinear = self.retract or (exact and self.turn_exact)
            y = self.strand.limit_step(x, y, x + alpha * dx if nonlinear else None)
        increment, absolute = self.increments(y - x)
        measure = increment
        if self.converging and (alpha < 1.0 or (self.strand is not None and self.strand.mode == "ccd")):
            # a damped or limiter-cut step is short without the iterate being close:
            # the full step measures it for the stop and newton_increment (docs/newton.md
            # "Twelfth round"; the exact switch keeps the step taken: switching on the
            # full step cost smash's frame 0 a cutback, 28 -> 72 iterations)
            whole, whole_absolute = self.increments(dx)
            measure, absolute = max(increment, whole), max(absolute, whole_absolute)
        if self.converging and rejected is not None:
            # the step after an exact step Armijo rejected (alpha 0, as it were) is
            # measured by that step too: a filtered 8e-6 after a rejected 1e-3 had
            # stopped the stiff smash 242x the tolerance away (docs/newton.md)
            whole, whole_absolute = self.increments(rejected)
            measure, absolute = max(measure, whole), max(absolute, whole_absolute)
        return y, increment, measure, absolute

    def _estimate_stop(self, s, it, full):
        """The stop estimates after a step (``full``: a whole exact one): the quadratic
        one (``time.newton_stop`` other than ``"increment"``) and the chord check
        (``"chord_estimate"``), each of which can claim the stop in ``s``.  Returns
        (whether a chord check claimed it, whether the steps are its basis)."""
        cfg = self.cfg
        s.quadratic = s.quadratic + [s.increment] if full else []
        # whether the full exact step decreased G as its model predicts (the line
        # search's energies: free): off it, the step is no quadratic one
        s.modelled = s.modelled + [full and self._searched is not None and model_agrees(
            self._searched[0] - self._searched[1], -0.5 * self._searched[2],
            max(abs(self._searched[0]), abs(self._searched[1])))] if full else []
        if not s.converged and cfg.time.newton_stop != "increment":
            estimate = quadratic_error_estimate(s.quadratic, s.modelled)
            if estimate < cfg.time.newton_increment_tol / QUADRATIC_SAFETY:
                s.converged, s.reported = True, estimate
        # a chord check needs two full exact steps that contract (chord_basis); at a
        # loose tolerance it is also made after one, but that claim only counts as the
        # first of two: the next iterate's check, with the basis, must claim too (it had
        # confirmed the increment it predicted: the stiff smash at 1e-4 stopped 21x away)
        based = chord_basis(s.quadratic, s.modelled)
        chord_claim = False
        if (cfg.time.newton_stop == "chord_estimate" and full and (based or s.loose)
                and CHORD_TRY_C * s.increment ** 2 < cfg.time.newton_increment_tol
                and (not s.converged or (s.unbased_claim and based))):
            s.chord_checks += 1
            chord = self._chord_increment(s.x, it)
            chord_claim = chord_stop(chord, s.increment, cfg.time.newton_increment_tol)
            if chord_claim and not s.converged:
                s.converged, s.reported = True, chord
        return chord_claim, based

    def _check_stop(self, s, it, step, measure, chord_claim, based):
        """The checks of the stop claimed in ``s``: at a loose tolerance its confirmation
        and model agreement (:meth:`_loose_verdict`), then a saddle of G
        (:meth:`_at_saddle`, :meth:`_at_coupled_saddle`), then after filtered steps the
        verifying exact step (:meth:`_verify_stop`; a kept one taken).  ``step``: this
        iteration's step for :meth:`_model_agrees`.  Returns (the verification's verdict
        or '', whether the stop was refused off its model).  Collective."""
        # at a loose tolerance one small increment can be a lull, not convergence
        # (compression_40 at dt 0.2: a stop 16x the tolerance away): the next step
        # must confirm it, unless the step already passes LOOSE_TOLERANCE
        claim = bool(s.converged)
        if s.unbased_claim and not (chord_claim and based):
            s.claimed_before = False
        s.unbased_claim = claim and chord_claim and not based
        confirmed, refused = self._loose_verdict(s.loose, claim, s.claimed_before, measure, s.steps,
                                                 (step, s.last_step, s.prior_step), chord_claim and based,
                                                 s.round_off)
        s.converged = s.converged and confirmed and not refused
        # a stop on a saddle of G ends the solve unconverged (step cutback redoes it)
        checked = s.steps[-1].exact and self._shift == 0.0
        s.saddle = bool(s.converged) and (self._at_saddle(checked) or self._at_coupled_saddle(checked))
        s.converged = s.converged and not s.saddle
        # a stop after filtered steps is checked by an exact Newton step at the iterate
        # (the stiff smash's analytic stops were 15-238x away at 1e-4, 1e-5)
        verdict = ""
        if s.converged and not s.steps[-1].exact and self._verifies(self.cfg.time.newton_increment_tol):
            verdict, s.pending = self._verify_stop(s.x, it)
            s.saddle = verdict == "saddle"
            s.converged = verdict == "kept"
            if s.converged:
                # the verifying step is taken: it lands 1e2-1e6x closer to the step's
                # solution than the filtered iterate (docs/newton.md "Taking the
                # verifying step"); its length is then the last increment
                s.x, s.pending = self._take_verified(s.x, s.pending), None
                s.reported = self._verifying
        s.settle(claim, step, confirmed, refused)
        self._counts["newton_stops_refused"] += bool(refused or s.saddle or (verdict and not s.converged))
        return verdict, refused

    def _end_step(self, x_old, x, motion):
        """The step's end after Newton (collective): a non-finite position is an error;
        the head's push-out, the projection onto the rest lengths, the head's path lift,
        then strand contact's (:meth:`FrameEnd.strand_end`).  Returns (the step's end, the
        lift's move the velocity leaves out or None, the contact figures or None)."""
        cfg, sc = self.cfg, self.scene
        badv = np.flatnonzero(~np.isfinite(x).all(axis=1))
        first_bad = sc.first_vertex + int(badv[0]) if len(badv) else -1
        bad_any = self.comm.allgather(first_bad)
        if max(bad_any) >= 0:
            raise FloatingPointError(f"frame {self.frame}: non-finite position at global vertex "
                                     f"{min(b for b in bad_any if b >= 0)}")
        push = self.contact and cfg.physics.head_push_out
        if push:
            # before the length projection, which takes back the edge strain it makes
            # (after it: edges 22% long on a soft hairball)
            x = self.frame_end.push_out_of_head(x)
        if cfg.time.length_projection:
            with self.timers("update"):
                # around the head: without, it pulled pushed vertices back in (the soft
                # hairball 0.11 cm deep, 1.63 strand radii)
                projected = project_rest_lengths(x, self.free, sc.offsets, self.rest_edge, sc.mass,
                                                 self.frame_end.head_sphere() if push else None)
            # how far the frame written is from Newton's iterate (reported: with a
            # tolerance it can exceed it, docs/newton.md "Stopping rule")
            self._projection_move = max(self._projection_move, self.increments(projected - x)[0])
            x = projected
        lifted = None
        if push:        # last: the strand path check below keeps to the path it leaves
            x, lifted = self.frame_end.lift_head_paths(x_old, x, self.t)
        if self.strand is None:
            return x, lifted, None
        return self.frame_end.strand_end(x_old, x, motion, self.t, lifted)

    def _ends_count(self, it, x, y):
        """Whether iteration ``it``, whose update takes x to y (before the root turn and
        the ccd limiter), is the last of a fixed count: the ``time.newton_iterations``-th,
        or with ``time.newton_extend_above`` the first from there whose relative
        increment is at or below it, at most the ``time.newton_extend_cap``-th (a jolt
        frame left 3 iterations from its solution injects momentum that a free mode
        keeps: docs/newton.md "Eighteenth round").  Collective from the count on."""
        cfg = self.cfg.time
        if it < cfg.newton_iterations - 1:
            return False
        if cfg.newton_extend_above is None:
            return True
        below = self.increments(y - x)[0] <= cfg.newton_extend_above
        if it >= cfg.newton_extend_cap - 1:
            # the cap ends the frame still above the bound: counted, warned at the end
            self._counts["newton_extend_capped"] += not below
            return True
        return below

    def _last_turn(self, last, x):
        """``time.root_rotation``: after the last iteration's update x (``last``), each
        root-held wisp turned about its root by the Newton step of G over the turn's angles
        (lc_petsc/root_rotation.py); in ccd mode the step's limiter then takes the update
        and the turn together (a limiter call of its own cost the 60-wisp demo 1.2-1.4x
        its collision time).  Other iterations: x."""
        if self.root_turn is None or not last or not self.cfg.time.root_rotation:     # not in start frames
            return x
        unit = self._mass_unit()
        # one phase entry for the whole turn, its head passes untimed inside: a timer
        # entry per pass had been a fifth to a quarter of those small passes' samples
        # (docs/newton.md "Twentieth round")
        with self.timers("update"):
            y = self.root_turn.step(x, self._turn_terms, unit, self._turn_potentials)
        # every rank turns at the same iteration (a fixed count): the counts summed over all
        turned, reduced = global_reduce(self.comm, [self.root_turn.turned, self.root_turn.reduced], "sum")
        self._counts["root_turns_reduced"] += int(reduced)
        if self.monitor is not None:
            self._say(f"  frame {self.frame}: root turn of {int(turned)} wisp(s) ({int(reduced)} halved or "
                      f"dropped), largest move {self.increments(y - x)[0]:.3e} wisp lengths")
        return y

    def _vertex_potentials(self, x, head=None):
        """Per vertex its inertia, gravity and head-penalty terms of G at x (zero on
        pinned vertices); ``head`` reuses the head's per-vertex energies and their
        vertices at x (:meth:`_contact_terms` with ``per_vertex``, its first two)."""
        per = self._vertex_terms(x)[0]
        e, idx = self._contact_terms(x, False, per_vertex=True)[:2] if head is None else head
        if idx is not None and len(idx):
            per[idx] += e
        return per

    def _vertex_terms(self, x):
        """Per vertex the inertia and gravity terms of G at x, (potentials (nv,), gradient
        (nv, 3)), zero on pinned vertices, in one compiled pass
        (:func:`compiled_turn.vertex_terms`; in NumPy with the NumPy element kernels)."""
        terms = compiled_turn.vertex_terms if self.asm.kernels == "compiled" else compiled_turn.vertex_terms_numpy
        return terms(x, self.xhat, self.scene.mass, self.f_ext, self.free, self.dt)

    def _turn_terms(self, x):
        """(grad G without the elastic terms, the head's active vertices and their
        Hessians or None, :meth:`_vertex_potentials`) at x, for the root turn: one pass
        of the head's penalty for all three (the turn's guard starts from the last),
        timed with the turn."""
        e, idx, head = self._head_terms(x, True, per_vertex=True) if self.contact else (0.0, None, None)
        per, g = self._vertex_terms(x)          # :meth:`gradient`'s and :meth:`_vertex_potentials`' bits
        if head is not None:
            g[idx] += head[0]
            per[idx] += e
        return g, None if head is None else (idx, head[1]), per

    def _turn_potentials(self, y):
        """:meth:`_vertex_potentials` at y for the root turn's guard, its head pass timed
        with the turn."""
        return self._vertex_potentials(y, self._head_terms(y, False, per_vertex=True)[:2]
                                       if self.contact else (0.0, None))

    def _collision_free_frame_path(self, x_frame, t_frame, last):
        """ccd mode after step cutback: the frame's own path x_n -> x_{n+1}, the chord of
        the substeps' chain, checked (:meth:`FrameEnd.collision_free_frame_path`), and the
        velocity less what that moved over the frame's dt, as an uncut frame's end does (v
        = (x_{n+1} - x_n) / dt).  Over the last substep's dt instead (8 substeps: 8x the
        kick) 60 soft wisps with self-contact reached 45% edge strain and the limiter left
        122 pairs unresolved; leaving the velocity alone, 8.4% and 475; over dt, 2.0% and
        none (90 frames).  Returns ``last`` with the contact figures at the new end."""
        x, moved, contact = self.frame_end.collision_free_frame_path(x_frame, t_frame, self.x, self.t,
                                                                     last.contact)
        self.v = self.v + moved / self.cfg.time.dt
        self.x = x
        return last._replace(contact=contact)

    def update(self, x, step, exact=False):
        """The next Newton iterate from x and the (scaled) step: x + step, or with
        ``time.newton_update = "edge_retraction"`` the same step with each free edge's
        length set to its linearised value (:func:`retract_edge_lengths`); with
        ``"corotational"`` the same, except that an ``exact`` step (of the exact Hessian,
        ``solver.filter = "exact_or_analytic"``) has each edge also turned by its
        neighbourhood's rotation (:func:`corotational_update`; turning filtered steps
        too was measured worse, docs/newton.md "Sixth round").  With
        ``physics.strand_contact_mode = "ccd"`` the update is linear at a fixed iteration
        count; with a tolerance the limiter takes the configured update whole or, when
        it would cut any vertex's path, the linear update x + step instead
        (:meth:`StrandContact.limit_step`: its per-vertex fractions of a retracted step
        stretch the edges it cuts; docs/newton.md "Twelfth round": with the linear
        update, Newton on the demo cut to 10 wisps converged in 1 of 10 frames, with the
        corotational one in all 10; at a fixed count the second limiter call of the cut
        updates cost the 2K hairball 13% more per frame)."""
        with self.timers("update"):
            if exact and self.turn_exact:
                return corotational_update(x, step, self.free, self.scene.offsets, self.scene.mass)
            if self.retract:
                return retract_edge_lengths(x, step, self.free, self.scene.offsets, self.scene.mass)
            return x + step

    # -------------------------------------------------------------- Newton system
    def _assemble_system(self, x, it, filter=None, shift=0.0, keep=False):
        """Fill the Newton matrix at x (element and strand-contact Hessians with
        ``filter``, default the configured one; the mass term (1 + ``shift``) M/dt^2);
        returns grad G.  ``keep``: the elements' diagonal blocks are kept for
        :meth:`_exact_assembly` (the mass added after them: the same bits)."""
        asm, sc, dt = self.asm, self.scene, self.dt
        mass = (1.0 + shift) * sc.mass / dt ** 2
        chosen = asm.filter
        if filter is not None:
            asm.filter = filter
            if self.strand is not None:
                self.strand.filter = filter
        try:
            with collectively(self.comm, f"frame {self.frame}, Newton iteration {it}"):
                elastic = asm.assemble(x, None if keep else mass)
                if keep:
                    diagonal = asm.diagonal_blocks()
                    with self.timers("assembly"):
                        asm.add_mass(mass)
                # one head pass for the gradient and the matrix, one phase entry with its
                # blocks (the gradient had its own pass: the same values, twice the work)
                idx, cg = None, None
                if self.contact:
                    with self.timers("collision"):
                        _, idx, cg = self._head_terms(x, True)
                        if cg is not None:
                            asm.add_diagonal(idx, cg[1])
                g = self.gradient(x, elastic=elastic, head=(idx, cg))
            if self.strand is not None:
                g += self.strand.assemble(x, asm)
        finally:
            asm.filter = chosen
            if self.strand is not None:
                self.strand.filter = chosen
        asm.commit()
        if self.strand is not None:         # the Newton matrix is A + C (contact.py)
            self.solver.ksp.setOperators(*self.strand.system(asm.mat, asm.pmat, asm.local_block_csr))
        if keep:
            self._kept_system = (x, asm.commits, g, diagonal, idx, cg)
        return g

    def _exact_assembly(self, x, it, shift):
        """The exact Hessian + ``shift`` M/dt^2 at x committed (returns grad G).  At the x
        of the last exact assembly, its matrix still the committed one, only the mass term
        changes: the elements' diagonal blocks kept from it, the new mass and the head's
        blocks added in :meth:`_assemble_system`'s order (the same bits), without the
        elements' pass (the wisps' own shifts of :meth:`_exact_system`, the retries of
        :meth:`_wisp_step` and the :data:`EXACT_SHIFTS` ladder are all at one x).  With
        strand contact, whose blocks go on the diagonal too in its own order, the whole
        system is assembled again.  Collective."""
        kept, asm = self._kept_system, self.asm
        if kept is None or kept[0] is not x or kept[1] != asm.commits:
            keep = self.strand is None and self.cfg.solver.exact_fallback == "shifted"
            return self._assemble_system(x, it, filter="none", shift=shift, keep=keep)
        _, _, g, diagonal, idx, cg = kept
        with self.timers("assembly"):
            asm.set_diagonal_blocks(diagonal)
            asm.add_mass((1.0 + shift) * self.scene.mass / self.dt ** 2)
        if cg is not None:
            with self.timers("collision"):
                asm.add_diagonal(idx, cg[1])
        asm.commit()
        self._kept_system = (x, asm.commits, g, diagonal, idx, cg)
        return g

    def _trust_region_step(self, x, it, region):
        """One trust-region iteration at x (``time.newton = "trust_region"``): the exact
        Newton matrix and the filtered preconditioner are assembled once, then the step
        within ``region.radius`` is solved, rho measured and the radius updated until a
        step is kept (a rejected step shrinks the radius and is solved again, as the
        line search halves a step: at most :data:`TRUST_RETRIES` times; then the zero
        step).  Returns (grad G, the step, whether a step was kept)."""
        tr = self.trust
        self._assemble_system(x, it)            # filtered: the preconditioner
        self.asm.mat.copy(tr.P, structure=tr.P.Structure.SAME_NONZERO_PATTERN)
        g = self._assemble_system(x, it, filter="none")
        G = self.incremental_potential(x)
        self.bv.array[:] = -g.ravel()
        if region.radius is None:               # the filtered Newton step's length
            region.radius = tr.filtered_step_norm(self.bv)
        for retry in range(TRUST_RETRIES + 1):
            with self.timers("solve"):
                predicted, norm_d, boundary = tr.solve(self.bv, self.xv, region.radius, self.frame, it)
            dx = self.xv.array.reshape(-1, 3).copy()
            dx[~self.free] = 0.0
            decrease = G - self.incremental_potential(self.update(x, dx))
            rho = ratio(decrease, predicted, G)
            region.radius = update_radius(region.radius, rho, norm_d, boundary)
            if rho > ETA:
                break
        else:
            dx = np.zeros_like(dx)
        kept = rho > ETA
        region.interior = kept and not boundary
        # for the loose-tolerance rule (_loose_verdict): a kept interior step whose
        # decrease agrees with the model's
        region.agrees = region.interior and model_agrees(decrease, predicted, G)
        self._fallback = "" if kept else "rejected"
        self._region_record = dict(rho=rho, radius=region.radius, step_norm=norm_d,
                                   boundary=bool(boundary), retries=retry)
        return g, dx, kept

    def _exact_step(self, x, it, shift):
        """An exact Newton step at x: the exact Hessian plus ``shift`` M/dt^2, its solve
        and the Armijo search along the (exact) update.  Returns (grad G, dx or None when
        CG finds the matrix indefinite, alpha or None when Armijo fails).  With
        ``solver.wisp_trust`` the first attempt (``shift`` 0) starts from each wisp's
        carried shift (:meth:`_wisp_step`)."""
        if self.wisp_trust and np.ndim(shift) == 0 and shift == 0.0:
            shift = self._wisp_mu
        g = self._exact_system(x, it, shift)
        dx = self._solve_step(g, it, may_fail=True)
        self._wisp_alpha = None
        if dx is None:
            return g, dx, None
        if not self._per_wisp_search():
            return g, dx, self._line_search(x, g, dx, EXACT_HALVINGS, exact=True)
        return g, dx, self._wisp_step(x, it, g, dx)

    def _exact_system(self, x, it, shift):
        """Assemble the exact Hessian + ``shift`` M/dt^2 at x (returns grad G).  With
        ``solver.exact_fallback = "shifted"``, a wisp whose block is not positive definite
        there gets its own shift, :data:`WISP_SHIFT_FACTOR` times the least that makes it
        so (:func:`lc_petsc.curvature.least_definite_shifts`), and the matrix's mass term
        is replaced (:meth:`_exact_assembly`): an exact step on an indefinite block heads
        for a stationary point, often a saddle of G (hairball10's frame 0 from rest: the
        step's solution found in 21 iterations instead of a saddle refused after 20 and
        cut back, 39; docs/newton.md "Avoiding the saddle").  ``shift`` is a number or one per local wisp (the retries
        of :meth:`_wisp_step`); a wisp's least shift is on top of the shift assembled (it
        had replaced it: the ladder's steps at 0.1 and 1 left blocks indefinite).  Per wisp
        and rank-local (the shifts in ``_wisp_tau``); one reduction of the largest shift
        (``_tried_shift``, the same on every rank: a shifted step is no Newton step)."""
        offsets = self.scene.offsets
        sizes = np.diff(offsets)
        base = np.broadcast_to(np.asarray(shift, float), sizes.shape)   # per wisp
        g = self._exact_assembly(x, it, shift if np.ndim(shift) == 0 else np.repeat(base, sizes))
        self._wisp_tau = base.copy()
        # per-wisp shifts differ by rank (the retries of _wisp_step): their largest gathered
        self._tried_shift = float(shift) if np.ndim(shift) == 0 else \
            float(global_reduce(self.comm, [base.max(initial=0.0)], "max")[0])
        if self.cfg.solver.exact_fallback != "shifted":
            return g
        unit = self._mass_unit()
        negative = np.zeros(len(sizes), bool)
        with self.timers("solve"):
            least = curvature.least_definite_shifts(self.asm, offsets, unit, negative)
        self._inertia = self.asm.commits, np.flatnonzero(negative)     # for _at_saddle
        # beyond the searched range no shift of a wisp's own helps: the uniform ladder
        # (and CG, Armijo) decide as before.  ``least`` is on top of the shift assembled
        tau = np.where(np.isfinite(least), base + WISP_SHIFT_FACTOR * least, base)
        self._wisp_tau = tau
        tried = float(global_reduce(self.comm, [tau.max(initial=0.0)], "max")[0])
        if tried > self._tried_shift:       # collective: every rank commits its shifts
            g = self._exact_assembly(x, it, np.repeat(tau, sizes))
        self._tried_shift = tried
        return g

    def _exact_hessian(self, s, stay=False):
        """Whether this iteration assembles the exact Hessian: ``solver.filter =
        "exact_or_analytic"`` once the last relative increment (of the solve ``s``) is
        below :data:`EXACT_BELOW` (near the solution, where it is mostly positive
        definite; with ``solver.wisp_trust`` :data:`~lc_petsc.wisp_trust.WISP_TRUST_BELOW`
        and not between two steps that undo each other,
        :func:`~lc_petsc.wisp_trust.exact_switch`), or whatever the increment when
        ``stay`` (``solver.exact_stay`` after a full, unshifted exact step;
        ``solver.wisp_trust`` after any kept exact step)."""
        if self.cfg.solver.filter != "exact_or_analytic":
            return False
        if stay:
            return True
        if not self.wisp_trust:
            return s.increment < EXACT_BELOW
        return s.increment < wisp_trust.WISP_TRUST_BELOW and wisp_trust.exact_switch([r.measure for r in s.steps])

    def _line_search(self, x, g, dx, halvings, give_up=True, exact=False, known=None):
        """Armijo backtracking on G along update(x, alpha dx, exact): alpha halves from 1
        until G(update(x, alpha dx)) <= G(x) + 1e-4 alpha grad G . dx.  After ``halvings``
        halvings, or for an ascent direction, returns None (``give_up``) or the last
        alpha.  ``known``: (G(x), G at alpha 1, grad G . dx) when already computed (a
        refused verifying step's, :meth:`_verification`), else None.  Collective; the
        alphas are recorded."""
        slope = self.comm.allreduce(float(np.sum(g * dx))) if known is None else known[2]
        if give_up and slope >= 0.0:
            return None
        G0 = self.incremental_potential(x) if known is None else known[0]
        self._probe = (G0, slope)               # for _at_round_off, found or not
        alpha = 1.0
        for k in range(halvings):
            G = known[1] if known is not None and k == 0 else \
                self.incremental_potential(self.update(x, alpha * dx, exact))
            if G <= G0 + 1e-4 * alpha * slope:
                self._searched = (G0, G, slope)     # for _model_agrees (alpha 1 only)
                break
            alpha *= 0.5
        else:
            if give_up:
                return None
        return alpha

    def _per_wisp_search(self):
        """Whether exact steps are searched wisp by wisp (:meth:`_wisp_step`): with
        ``solver.exact_fallback = "shifted"`` (whose shifts are per wisp too) and without
        strand contact, the only term that couples wisps (with it, the global search)."""
        return self.strand is None and self.cfg.solver.exact_fallback == "shifted"

    def _wisp_step(self, x, it, g, dx):
        """The per-wisp line search of an exact step (:meth:`_wisp_line_search`); a wisp
        it fails on (an ascent direction, or no decrease within :data:`EXACT_HALVINGS`
        halvings) gets its own larger shift, :data:`WISP_RETRY_FACTOR` times its last (at
        least the ladder's first), and the system is solved again for it, at most :data:`WISP_RETRIES` times (the other
        wisps keep their steps and factors: no term couples them).  ``dx`` is updated in
        place.  Returns the smallest alpha (all ranks) or None (then the uniform ladder
        decides, as for the global search).  With ``solver.wisp_trust`` each wisp's shift
        for the next exact step is set from this one's (:func:`lc_petsc.wisp_trust.next_shifts`).
        Collective."""
        wisp = self.vertex_wisp
        # the EXACT_SHIFTS ladder searches at the same x: its shares kept
        known = self._kept_shares[1] if self._kept_shares is not None and self._kept_shares[0] is x else None
        alpha, bad, shares, taken = self._wisp_line_search(x, g, dx, np.ones(len(self.scene.offsets) - 1, bool),
                                                           shares=known)
        self._kept_shares = x, shares
        for _ in range(WISP_RETRIES):
            if not global_reduce(self.comm, [float(bad.any())], "max")[0]:
                break
            tau = self._wisp_tau.copy()
            tau[bad] = np.maximum(WISP_RETRY_FACTOR * tau[bad], EXACT_SHIFTS[0])
            self._exact_system(x, it, tau)
            again = self._solve_step(g, it, may_fail=True)
            if again is None:
                return None
            moved = bad[wisp]
            dx[moved] = again[moved]
            alpha_again, bad_again, _, taken = self._wisp_line_search(x, g, dx, bad, alpha, shares)
            alpha[bad], bad = alpha_again[bad], bad & bad_again
        failed, least = global_reduce(self.comm, [float(bad.any()), -alpha.min(initial=1.0)], "max")
        if not failed:
            self._wisp_alpha = alpha[wisp]
            if taken is None:       # no wisp was searched: the shares at the step taken
                taken = self.wisp_potentials(self.update(x, self._scaled(1.0, dx), True))
        # G before and after the step from the wisps' shares the search computed (no
        # coupling term without strand contact), instead of two more passes over the
        # elements; the same figures to round-off (docs/newton.md "A trust region per wisp")
        G0, G1, slope = global_reduce(self.comm, [shares.sum(), 0.0 if failed else taken.sum(),
                                                  float(np.sum(g * dx))], "sum")
        self._probe = (G0, slope)
        if failed:
            return None
        self._searched = (G0, G1, slope)
        if self.wisp_trust:
            self._carry_shifts(x, g, dx, alpha, shares, taken)
        return -least

    def _carry_shifts(self, x, g, dx, alpha, shares, taken):
        """``solver.wisp_trust``: each wisp's shift for the next exact step from this
        step's shift (``_wisp_tau``), alpha and model ratio (:mod:`lc_petsc.wisp_trust`).
        ``shares``: the wisps' shares of G at x; ``taken``: at the step taken.  The step
        was solved on H + tau M/dt^2 wisp by wisp, so dx^T H dx = -g.dx - tau dx^T M/dt^2 dx.  Rank-local."""
        slope = self._wisp_sum(np.sum(g * dx, axis=1))
        unit = self._mass_unit()
        mass_norm = self._wisp_sum(unit * np.sum(dx * dx, axis=1))
        curvature = -slope - self._wisp_tau * mass_norm
        rho = wisp_trust.model_ratio(shares - taken, slope, curvature, alpha, shares, ENERGY_FLOOR)
        self._wisp_mu = wisp_trust.next_shifts(self._wisp_tau, alpha, slope, mass_norm, rho)

    def _wisp_line_search(self, x, g, dx, search, alpha=None, shares=None):
        """Armijo backtracking per wisp along the exact update, for the wisps ``search``
        (the others at their factors ``alpha``): each wisp's alpha halves from 1 until
        its share of G (:meth:`wisp_potentials`) satisfies Armijo with its own slope
        g_w . dx_w.  G is a sum of the wisps' shares (no term couples them without
        strand contact, and the update moves each wisp by its own step alone), so the
        wisps' decreases add up to G's.  A wisp whose predicted decrease is below
        round-off of its share keeps alpha 1 (noise would decide otherwise).  Returns
        per wisp (alpha, failed, share of G at x, share at alpha): failed where the step
        is an ascent direction or found no decrease within :data:`EXACT_HALVINGS`
        halvings; the last None when no wisp was searched (a failed wisp's share is not
        at its alpha).  ``shares``: the wisps' shares at x when known (a retry's: x is
        the same).  Rank-local."""
        wisp = self.vertex_wisp
        slope = self._wisp_sum(np.sum(g * dx, axis=1))
        G0 = self.wisp_potentials(x) if shares is None else shares
        alpha = np.ones_like(slope) if alpha is None else np.where(search, 1.0, alpha)
        noise = np.abs(0.5 * slope) <= ENERGY_FLOOR * np.abs(G0)
        ascent = search & ~noise & (slope >= 0.0)
        pending = search & ~noise & ~ascent
        G = None
        for _ in range(EXACT_HALVINGS):
            if not pending.any():
                break
            G = self.wisp_potentials(self.update(x, alpha[wisp, None] * dx, True))
            pending &= ~(G <= G0 + 1e-4 * alpha * slope)
            alpha[pending] *= 0.5
        return alpha, ascent | pending, G0, G

    def _scaled(self, alpha, dx):
        """The step taken: ``alpha`` dx, or each wisp's own factor times its step after
        :meth:`_wisp_line_search`."""
        return alpha * dx if self._wisp_alpha is None else self._wisp_alpha[:, None] * dx

    def _solve_step(self, g, it, may_fail=False):
        """The Newton step dx (pinned rows zero).  With ``may_fail`` (the exact Hessian)
        returns None instead when its linear solve fails: CG finds the matrix or
        preconditioner indefinite, or stops at its iteration cap on a shifted block barely
        definite, whose factorisation without pivoting CG cannot use (the extremes' stiffness
        ratio 1e6 to a tolerance ended on DIVERGED_MAX_IT at frame 7, docs/studies.md); that
        solve is then not recorded: another one replaces it."""
        with self.timers("solve"):
            self.bv.array[:] = -g.ravel()
            try:
                self.solver.solve(self.bv, self.xv, self.frame, it)
            except SolverError:
                if not may_fail:
                    raise
                self.solver.forget_last()
                return None
            dx = self.xv.array.reshape(-1, 3).copy()
        dx[~self.free] = 0.0
        return dx

    # -------------------------------------------------------------- convergence
    def increments(self, dx):
        """(max_i |dx_i| / rest length of vertex i's wisp, max |dx| in cm) over all ranks,
        in one reduction."""
        local = np.array([(np.linalg.norm(dx, axis=1) / self.wisp_length).max(initial=0.0),
                          np.abs(dx).max(initial=0.0)])
        total = global_reduce(self.comm, local, "max")
        return float(total[0]), float(total[1])

    def _step_kind(self, exact, region=False):
        """The kind of the step taken, for :meth:`_monitor` (``region``: a trust-region
        step, with its rho and radius)."""
        if region:
            r = self._region_record
            rejected = ", rejected: zero step" if self._fallback == "rejected" else ""
            return (f"trust region{' (exact)' if exact else ''}, rho {r['rho']:.3g}, "
                    f"radius {r['radius']:.3g}{rejected}")
        if exact:
            return f"exact + {self._shift:g} M/dt^2" if self._shift else "exact"
        return f"filtered (exact rejected: {self._fallback})" if self._fallback else "filtered"

    def _monitor(self, it, measure, kind, alpha, ksp, cut, estimate=None):
        """``-lc_newton_monitor``: one line for iteration ``it`` (0-based) on rank 0 of
        what is already known on every rank (no extra collective): the stopping
        measure ``measure`` (with a tolerance, the full step's where the step was damped
        or, in ccd mode, larger than the step taken), the step's ``kind``, its Armijo
        factor ``alpha``, the KSP iterations ``ksp`` of the step's solve, whether the
        contact limiter cut it, and ``estimate`` where that certified the iterate."""
        extra = f", estimate {estimate:.3e}" if estimate is not None and estimate != measure else ""
        self._say(f"  Newton frame {self.frame} (dt {self.dt:.4g}) iteration {it + 1}: "
                  f"increment {measure:.3e}{extra}, {kind}, alpha {alpha:g}, KSP {ksp}"
                  f"{', limiter cut' if cut else ''}")

    def _say(self, line):
        """Print ``line`` to the monitor's stream on rank 0."""
        if self.comm.rank == 0:
            print(line, file=self.monitor, flush=True)

    def _chord_increment(self, x, it):
        """``time.newton_stop = "chord_estimate"``: the relative increment of the step from
        x on the last Newton matrix (the exact Hessian at the previous iterate; its
        factorisation reused), i.e. the next Newton increment to first order in the last
        one, which is the error of x to leading order (collective; inf when CG finds
        the matrix indefinite for this right-hand side).  Not with strand contact, whose
        gradient only its assembly computes (the configuration refuses the option)."""
        dx = self._solve_step(self.gradient(x), it, may_fail=True)
        return np.inf if dx is None else self.increments(dx)[0]

    def _verifies(self, tol):
        """Whether a stop after a filtered step at the relative tolerance ``tol`` (None:
        ``time.newton_tol`` alone, taken relative to the shortest wisp) is checked by
        :meth:`_verify_stop`: with an element filter (not ``exact_or_analytic``, whose
        filtered stops are a frame's first step or measured by a rejected exact attempt)
        at or below :data:`VERIFY_FROM`."""
        if tol is None:
            tol = self.cfg.time.newton_tol / self.shortest_wisp
        return self.cfg.solver.filter != "exact_or_analytic" and tol <= VERIFY_FROM

    def _verify_stop(self, x, it):
        """Check a stop claimed after filtered steps by one exact Newton step at its iterate
        x (collective: one assembly, the per-wisp inertia pass, one solve).  The filtered
        steps' sizes and rate do not bound the distance left (the stiff smash, analytic
        filter: stops 15.7x to 238x the tolerance away, docs/newton.md "Verifying a stop
        after filtered steps"); the exact step's length does, to first order, where the
        exact Hessian is definite.  Returns (verdict, step): ``"kept"`` (the exact step
        within the tolerances), ``"saddle"`` (a wisp's exact block is indefinite:
        :meth:`_at_saddle`), ``"indefinite"`` (CG found A + C indefinite) or ``"short"``
        (the solve missed -ksp_rtol), both step None, or with the step (grad G, dx, the
        line search's known energies or None, :meth:`_line_search`): the
        kept stop's (taken by :meth:`_take_verified`), or that of a refused stop, which the
        next iteration takes instead of a filtered one (the work kept): ``"far"`` (the
        exact step exceeds a tolerance) or ``"off_model"`` (within them, but G's decrease
        along it is off its quadratic model, :func:`model_agrees`: two energies more, which
        the next iteration's line search reuses).
        Counted per frame (``newton_verified``, ``newton_verify_refused``) and recorded in
        ``verifications``."""
        verdict, step = self._verification(x, it)
        self._counts["newton_verified"] += 1
        self._counts["newton_verify_refused"] += verdict != "kept"
        self.verifications.append((self.frame, it, verdict, self._verifying))
        return verdict, step

    def _verification(self, x, it):
        """The verdict and step of :meth:`_verify_stop` (collective)."""
        g = self._assemble_system(x, it, filter="none")
        self._verifying = np.inf
        if self._at_saddle(True):
            return "saddle", None
        unreduced = len(self.solver.not_reduced)
        dx = self._solve_step(g, it, may_fail=True)
        if dx is None:
            return "indefinite", None
        if len(self.solver.not_reduced) > unreduced:
            return "short", None
        self._verifying, absolute = self.increments(dx)
        t = self.cfg.time
        within = ((t.newton_increment_tol is None or self._verifying < t.newton_increment_tol)
                  and (t.newton_tol is None or absolute < t.newton_tol))
        if within:
            # and on its quadratic model: where G's decrease along it is off the model's
            # the Hessian changes over the step and its length is no bound (the stiff
            # smash at 1e-3: an exact step of 3.0e-4 where the solution was 1.6e-3 away,
            # taken at alpha 1/16)
            slope = self.comm.allreduce(float(np.sum(g * dx)))
            G0, G1 = self.incremental_potential(x), self.incremental_potential(self.update(x, dx, True))
            within = model_agrees(G0 - G1, -0.5 * slope, max(abs(G0), abs(G1)))
            if not within:      # its energies are the next iteration's line search's first
                return "off_model", (g, dx, (G0, G1, slope))
        return ("kept" if within else "far"), (g, dx, None)

    def _take_verified(self, x, step):
        """The iterate after a kept stop's verifying exact step ``step`` (grad G, dx, _) from
        x: that step taken whole (on its quadratic model, within the tolerances: 1e2-1e6x
        closer to the step's solution than x on the stiff smashes, docs/newton.md "Taking
        the verifying step"); x itself where the ccd limiter would cut it (a cut step is
        no Newton step; the filtered iterate is verified).  Collective."""
        dx = step[1]
        y = self.update(x, dx, True)
        if self.strand is not None:
            y = self.strand.limit_step(x, y, x + dx if self.retract or self.turn_exact else None)
            if self.strand.last_cut:
                return x
        return y

    def _loose_verdict(self, loose, claim, claimed_before, measure, steps, recent, measured=False,
                       round_off=False):
        """(confirmed, refused) for this iteration's stop ``claim`` at a ``loose``
        tolerance (:func:`confirms_stop`; else (True, False)).  Confirmed: the last
        iteration claimed a stop too (``claimed_before``), or ``measure`` times the
        contraction factor of ``steps`` (the solve's :class:`StepRecord` records,
        :func:`step_contraction`) is below :data:`LOOSE_TOLERANCE` (one
        small increment can be a lull: compression_40 at dt 0.2 stopped 16x the tolerance
        away).  Refused: a confirmed stop whose steps ``recent`` (this iteration's, the
        last one's and the one before, None before the first) fail :meth:`_model_agrees`:
        where the quadratic model is off, the steps' size says nothing of the distance
        left (smash at E = 1e12: 200 steps of 1e-5 drifting 2.4e-3; docs/newton.md
        "Stopping rule").  This step and the last one must agree; a stop confirmed by the
        last iteration's claim (not by its own measure below LOOSE_TOLERANCE, nor
        ``measured``: by a chord check with its basis, which measures the next step)
        needs the step before that claim on its model too: a claim made by the first
        step out of an off-model run, confirmed by one more step, had stopped two-step
        lulls of the crushed coil 1.6x and of the stiff smash 2.4x the tolerance away
        (docs/newton.md "The two-step lull").  A step at the positions' round-off
        (``round_off``: :func:`round_off_floor`) is confirmed and agrees: its size, its
        rate and its line search are noise, and nothing is left to converge (the 2K
        hairball's frame 10 refused such stops for 14 iterations and cut back,
        docs/newton.md "Stops at round-off").  Collective."""
        if round_off:
            return True, False
        shortcut = measure * step_contraction(steps) < LOOSE_TOLERANCE
        confirmed = not loose or claimed_before or shortcut
        needed = recent[:2] if shortcut or measured else recent
        refused = loose and claim and confirmed and not all(
            s is None or self._model_agrees(s) for s in needed)
        return confirmed, refused

    def _at_saddle(self, exact):
        """Whether this iteration's stop is on a saddle of G: a wisp's diagonal block of
        the Newton matrix, the exact Hessian of the stopping step (``exact``: the last step
        was an exact, unshifted one; else nothing is checked), is not positive definite
        (:func:`lc_petsc.curvature.negative_wisps`; the Hessian at the iterate before the
        stopping step, whose increment is below the tolerance).  Per-wisp block Jacobi is
        the exact inverse of an uncoupled wisp's block, so Newton stops on a saddle as on
        a minimum (the demo cut to 10 wisps at full dt: coils spun ~167 degrees about
        their roots, docs/newton.md "Saddles of G").  Collective when ``exact`` (one
        gather, at stops only); counted in ``newton_saddle``."""
        if not exact:
            return False
        local = self._negative_wisps() + self.scene.first_wisp
        found = [int(w) for part in self.comm.allgather(local.tolist()) for w in part]
        if not found:
            return False
        self._saddles += 1
        self._saddle_wisps = self._scene_wisps(found)
        return True

    def _negative_wisps(self):
        """The local wisps whose block of the committed matrix is not positive definite
        (:func:`lc_petsc.curvature.negative_wisps`), counted once per matrix: the shifted
        fallback's :meth:`_exact_system` counts them in its own pass, and a verifying
        step's matrix (:meth:`_verification`) is the next iteration's when it is taken."""
        if self._inertia is None or self._inertia[0] != self.asm.commits:
            with self.timers("solve"):
                self._inertia = self.asm.commits, curvature.negative_wisps(self.asm, self.scene.offsets)
        return self._inertia[1]

    def _at_coupled_saddle(self, exact):
        """Whether this iteration's stop is on a saddle of G that only the coupling of
        wisps by strand contact makes one: A + C has negative curvature although every
        wisp block passed :meth:`_at_saddle` (the six touching wisps in phase stopped so
        at -0.517 M/dt^2 over three wisps whose own blocks are definite; docs/newton.md
        "A saddle over contact-coupled wisps").  Lanczos on A + C preconditioned by the
        wisp blocks (:mod:`lc_petsc.contact_curvature`); only at an ``exact`` stop (as
        :meth:`_at_saddle`) with contact cross blocks.  Collective; counted in
        ``newton_saddle`` like a wisp's saddle.  A check whose Lanczos did not converge
        within its cap (:attr:`~lc_petsc.contact_curvature.Verdict.unknown`) found no
        saddle and proved no minimum: the stop is kept (Newton's tolerance is met, every
        wisp block is definite, and refusing would cut back where no saddle was seen), but
        counted (``newton_coupled_unknown``) and named by the monitor."""
        if not exact or self.strand is None or self.strand.C is None:
            return False
        if self._coupled is None:
            self._coupled = contact_curvature.CoupledCurvature(
                self.scene.offsets, self.asm.mat.getOwnershipRange()[0] // 3, self.free, self.comm)
        with self.timers("solve"):
            verdict = self._coupled.check(self.asm.local_block_csr(), self.solver.ksp.getOperators()[0],
                                          self._mass_unit(), self.asm.mat)
        self.coupled_checks.append(verdict)
        if verdict.unknown:
            self._counts["newton_coupled_unknown"] += 1
            if self.monitor is not None:
                self._say(f"  frame {self.frame}: the stop's curvature over contact-coupled wisps is unknown "
                          f"(Lanczos' lowest Ritz value {verdict.lowest:.4g} unconverged after "
                          f"{verdict.iterations} iterations): the stop is kept")
        if not verdict.negative:
            return False
        self._saddles += 1
        self._saddle_wisps = self._scene_wisps(verdict.wisps)
        return True

    def _scene_wisps(self, internal):
        """The scene's (user's) numbers of the internal global wisps ``internal``, sorted
        (the partition renumbers wisps along a space-filling curve, -lc_wisp_order)."""
        order = self.wisp_order
        return sorted(int(w) if order is None else int(order[w]) for w in internal)

    def _model_agrees(self, step):
        """Whether Newton step ``step`` (a dict: the iterates ``before`` and ``after``, the
        gradient ``g`` at ``before``, the solve's ``dx``, whether it was taken ``whole``
        (alpha 1, unshifted, not cut by the limiter, no exact attempt rejected) and the
        line search's ``searched`` (G before, G after, g . dx) or None) is one whose size
        measures the distance left:
        taken whole, with G's decrease within :data:`MODEL_AGREEMENT` of the quadratic
        model's prediction -g . dx / 2 (:func:`model_agrees`).  Collective (two energies
        and a reduction unless the line search has them); the verdict is cached in
        ``step`` (a trust-region step comes with it: its rho, kept and interior)."""
        if "agrees" not in step:
            if not step["whole"]:
                step["agrees"] = False
            else:
                if step["searched"] is not None:
                    G0, G1, slope = step["searched"]
                else:
                    slope = self.comm.allreduce(float(np.sum(step["g"] * step["dx"])))
                    G0, G1 = self.incremental_potential(step["before"]), self.incremental_potential(step["after"])
                step["agrees"] = model_agrees(G0 - G1, -0.5 * slope, max(abs(G0), abs(G1)))
        return step["agrees"]

    def _newton_converged(self, steps, absolute, round_off=False):
        """True/False against the tolerances that are set (both when both are), None
        when neither is (a fixed iteration count).  ``steps``: this solve's steps so far
        (:class:`StepRecord`; the last one's absolute size ``absolute`` cm); the last one's
        measure, times the iteration's contraction factor (:func:`step_contraction`),
        must be below each; the measure alone where the step is at the positions'
        round-off (``round_off``, :func:`round_off_floor`: increments of noise bounce, so
        their factor is inf although nothing is left to converge)."""
        t = self.cfg.time
        if not t.newton_converges:
            return None
        factor = 1.0 if round_off else step_contraction(steps)
        ok = True
        if t.newton_increment_tol is not None:
            ok = steps[-1].measure * factor < t.newton_increment_tol
        if t.newton_tol is not None:
            ok = ok and absolute * factor < t.newton_tol
        return bool(ok)

    def _at_round_off(self):
        """Whether this iteration's last line search (of the step taken or of a rejected
        exact attempt) predicted a decrease of G below round-off (-g . dx / 2 under
        :data:`ENERGY_FLOOR` |G|): Armijo's verdict is noise there (the hairball's 1e-10
        steps were halved, two crossing wisps' exact 1e-9 steps rejected), so a damped,
        shifted or fallback step then still counts as a whole Newton step for
        :func:`contraction_factor`."""
        if self._probe is None:
            return False
        G0, slope = self._probe
        return abs(0.5 * slope) <= ENERGY_FLOOR * abs(G0)

    def frame_force_scale(self):
        """The frame's force scale |f_ext| + |M v_n| / dt + |grad V(x_n)| (2-norms over
        the free vertices of all ranks): external, inertial and elastic forces at the
        start of the frame, the yardstick of :meth:`relative_residual`."""
        f = self.free
        elastic = self.asm.gradient(self.x)
        parts = np.array([np.sum(self.f_ext[f] ** 2),
                          np.sum((self.scene.mass[f, None] * self.v[f]) ** 2) / self.dt ** 2,
                          np.sum(elastic[f] ** 2)])
        return float(np.sqrt(self.comm.allreduce(parts)).sum())

    def relative_residual(self, g):
        """|grad G| (2-norm, all ranks) relative to the frame's force scale."""
        norm = np.sqrt(self.comm.allreduce(float(np.sum(g * g))))
        return norm / self._force_scale if self._force_scale > 0 else norm

    def _record_iteration(self, it, x_old, x_new, g, increment, alpha, exact):
        """Append iteration ``it``'s measures to ``self.history`` (diagnostics: costs a
        residual reduction and two evaluations of G)."""
        G_old, G_new = self.incremental_potential(x_old), self.incremental_potential(x_new)
        solver = self.trust if self.trust is not None else self.solver
        self.history.append(dict(
            frame=self.frame, dt=self.dt, iteration=it, increment=increment, alpha=alpha,
            residual=self.relative_residual(g), energy=G_new,
            energy_decrease=G_old - G_new, exact=bool(exact),
            ksp_reason=solver.reasons[-1] if solver.reasons else "",
            ksp_iterations=solver.iterations[-1] if solver.iterations else 0,
            exact_rejected=self._fallback, exact_shift=self._shift, **self._region_record))


#: A stop after filtered steps (an element filter, not exact_or_analytic) at a relative
#: tolerance at or below this is checked by an exact Newton step at its iterate
#: (Integrator._verify_stop; docs/newton.md "Verifying a stop after filtered steps")
VERIFY_FROM = 1e-3
#: the per-frame counts of the stop's checks (Integrator attributes, summary.json keys)
FRAME_COUNTS = ("newton_verified", "newton_verify_refused", "newton_stops_refused",
                "newton_coupled_unknown", "root_turns_reduced", "newton_extend_capped",
                "newton_jolt_starts")


#: ``solver.exact_fallback = "shifted"``: the shifts tau of the exact Hessian + tau M/dt^2
#: tried, in order, when the exact step fails (measured on the hairball: tau = 0.1 gave
#: no step, 1 and 10 did; starting at 10 kept accepting steps too short to converge,
#: docs/newton.md "Seventh round")
EXACT_SHIFTS = (0.1, 1.0, 10.0, 100.0)
#: ``solver.exact_fallback = "shifted"``: a wisp whose exact block is indefinite is
#: shifted by this times the least shift making it positive definite (hairball10's frame
#: 0 at 1e-6: 1.1 -> 22 iterations, 1.25 -> 23, 1.5 -> 21, 2 -> 25; each reached the
#: step's minimum; docs/newton.md "Avoiding the saddle")
WISP_SHIFT_FACTOR = 1.5
WISP_RETRY_FACTOR = 10.0
WISP_RETRIES = 3
EXACT_HALVINGS = 6

