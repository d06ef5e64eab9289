"""Builder API: ``build_simulator(config) -> Simulator`` (config -> scene -> partition ->
solver plan -> assembly + solver -> integrator)."""

from __future__ import annotations

import atexit
import sys
import time
import weakref

import numpy as np
from petsc4py import PETSc

from lc_petsc import parallel
from lc_petsc.assembly import Assembler
from lc_petsc.config import ELASTIC_TERMS, OTHER_TERMS, ConfigError, SimConfig, element_filter
from lc_petsc.diagnostics import groom_material_warnings
from lc_petsc.integrator import FRAME_COUNTS, Integrator
from lc_petsc.errors import RestPoseOverlapError, StartOverlapError
from lc_petsc.rest_pose import check_rest_pose, check_start_pose
from lc_petsc.scene.kinematics import HeadMotion
from lc_petsc.scene.outliers import displaced_vertex_problems
from lc_petsc.scene.perturbation import apply_perturbation, perturbation_problems
from lc_petsc.scene.sources import source_from_config
from lc_petsc.scene.state import LocalScene, inertia_problems
from lc_petsc.solver import LinearSolver
from lc_petsc.solver_plan import SolverPlan
from lc_petsc.trust_region import TrustRegionSolver
from lc_petsc.timing import Timers


def _mpi_comm(comm):
    from mpi4py import MPI
    return MPI.COMM_WORLD if comm is None else comm


def check_head_turn(cfg):
    """ConfigError if the head turns by more than the ccd limiter's
    :data:`~lc_petsc.contact.MAX_RIGID_DEGREES` in a step of the run: beyond it the
    limiter's fallback cannot hold wisps apart along the frame paths (measured: dt 0.1
    with head_amplitude 1.0 on the demo, 15 crossings in 30 frames and root edges
    stretched 8x, with no error)."""
    from lc_petsc.config import MIN_DT
    from lc_petsc.contact import MAX_RIGID_DEGREES
    ph, tc = cfg.physics, cfg.time
    if "strand_collision" not in ph.terms or ph.strand_contact_mode != "ccd":
        return
    head = HeadMotion(ph)
    # no step can turn by more than the head's top speed times dt: nothing to scan then
    # (a scan of time.frames = 1e8 steps held the set-up for hours)
    speed = np.degrees(head.max_angular_speed())
    if speed * tc.dt <= MAX_RIGID_DEGREES:
        return
    turn, step = head.largest_turn(tc.dt, tc.frames, above=MAX_RIGID_DEGREES)
    if turn <= MAX_RIGID_DEGREES:
        return
    duration = tc.frames * tc.dt
    dt = tc.dt * MAX_RIGID_DEGREES / turn
    # below `safe` the speed bound holds; below MIN_DT no config can go (the search ran
    # for ever for physics.head_amplitude = 1e308)
    safe = MAX_RIGID_DEGREES / speed
    while dt > max(safe, MIN_DT) and head.largest_turn(
            dt, int(np.ceil(duration / dt)), above=MAX_RIGID_DEGREES)[0] > MAX_RIGID_DEGREES:
        dt *= 0.95
    advice = (f"use time.dt <= {dt:.3g}, or a slower head" if dt >= MIN_DT else
              f"no time.dt >= {MIN_DT:g} s keeps it within that: slow the head (physics.head_amplitude "
              f"in rad, physics.head_period in s)")
    raise ConfigError(
        f"the head turns by {turn:.1f} degrees in step {step} (time.dt = {tc.dt:g}, "
        f"physics.head_amplitude = {ph.head_amplitude:g}, head_period = {ph.head_period:g}); "
        f"strand contact in \"ccd\" mode keeps wisps from passing through each other only up to "
        f"{MAX_RIGID_DEGREES:.2f} degrees per step: {advice} "
        f"(docs/contact.md, \"The head's turn per step\")")


def named_by(source, message):
    """``message`` (a problem of the scene's wisps) prefixed with the groom file it comes
    from (``source.description``), so the user knows which file to fix."""
    return f"{source.description}: {message}" if source.description else message


class Simulator:
    """One simulation on a communicator: scene, solver plan, assembler, linear solver, integrator."""

    def __init__(self, config: SimConfig, comm=None, check_start=True):
        self.config = config.validate()
        parallel.limit_blas_threads()
        self.comm = comm = _mpi_comm(comm)
        self.pcomm = PETSc.Comm(comm)
        self.timers = Timers()
        cfg = config
        check_head_turn(cfg)
        source = source_from_config(cfg.scene, cfg.material, cfg.physics)
        self.plan = plan = SolverPlan.resolve(cfg.solver.effective_options(),
                                              strand_contact="strand_collision" in cfg.physics.terms,
                                              newton_converges=cfg.time.newton_converges)
        user_sizes = np.asarray(source.sizes)
        source, self.wisp_order = parallel.order_wisps(source, plan.wisp_order)
        self.n_wisps = source.n_wisps
        self.ranges = parallel.partition(source.sizes, comm.size)
        w0, w1 = int(self.ranges[comm.rank]), int(self.ranges[comm.rank + 1])
        voff = np.concatenate([[0], np.cumsum(source.sizes)])
        self.n_vertices = int(voff[-1])
        batch = source.load(w0, w1)
        terms = [t for t in cfg.physics.terms if t in ELASTIC_TERMS]
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):     # checked there
            scene, problems = LocalScene.build(batch, cfg.material, terms, source.n_wisps,
                                               int(voff[w0]), self.n_vertices)
            if not problems and cfg.scene.kind in ("file", "usd"):    # a groom file: damage, not hair
                problems = displaced_vertex_problems(batch)
            if not problems:
                problems = inertia_problems(scene, batch, cfg)
        parallel.collective_raise(comm, [named_by(source, p) for p in problems])
        self.scene = scene
        # a strands file's moduli and densities a hair has not (warned, as the config's keys)
        self.material_warnings = groom_material_warnings(comm, batch, source.description)
        # outputs in the scene's wisp order (parallel.UserLayout)
        self.user = parallel.UserLayout(comm, self.wisp_order, user_sizes, self.ranges, scene)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):   # checked next
            x0 = apply_perturbation(batch, cfg.scene)
        parallel.collective_raise(comm, perturbation_problems(batch, x0, cfg.scene))
        with plan.active():
            self.assembler = Assembler(scene, self.pcomm, self.timers,
                                       filter=element_filter(cfg.solver.filter),
                                       mat_type=plan.mat_type, pmat_type=plan.pmat_type,
                                       options_prefix=plan.prefix, kernels=plan.element_kernels)
        self.strand = None
        if plan.contact_pc is not None:
            self.strand = _strand_contact(scene, comm, self.pcomm, self.timers, cfg, plan,
                                          self.assembler.mat_type, user=self.user, source=source,
                                          x0=x0 if check_start else None)
        self.solver = LinearSolver(self.assembler.mat, 3 * np.diff(scene.offsets), plan,
                                   P=self.assembler.pmat)
        self.trust = None
        if cfg.time.newton != "filtered":
            self.trust = TrustRegionSolver(self.assembler.mat, 3 * np.diff(scene.offsets), plan)
        self.head = HeadMotion(cfg.physics)
        self.integrator = Integrator(scene, self.assembler, self.solver, comm, self.timers, cfg,
                                     self.head, x0, strand=self.strand, trust=self.trust)
        self.integrator.wisp_order = self.wisp_order
        if plan.newton_monitor:                 # -lc_newton_monitor
            self.integrator.monitor = sys.stdout
        if self.strand is not None:
            # A Python-shell operator still alive when petsc4py finalizes crashes the
            # interpreter at exit: close a simulator that was never closed before that
            # (atexit runs handlers in reverse order; petsc4py registered earlier).
            ref = weakref.ref(self)

            def close_if_alive():
                sim = ref()
                if sim is not None:
                    sim.close()
            atexit.register(close_if_alive)
        self.wall = 0.0
        self.ksp_solves: list[int] = []     # per frame: its linear solves (its share of ksp_iterations)

    # ------------------------------------------------------------------ running
    @property
    def x(self):
        """This rank's positions (n_local, 3)."""
        return self.integrator.x

    def step(self):
        """Advance one frame (one backward-Euler step), timed into ``wall``."""
        t0, solves = time.perf_counter(), len(self.solver.iterations)
        self.integrator.step()
        self.wall += time.perf_counter() - t0
        self.ksp_solves.append(len(self.solver.iterations) - solves)

    def restore(self, state):
        """Continue from a saved state (a loaded checkpoint): ``state["x"]``,
        ``state["v"]`` this rank's positions and velocities (n_local, 3), ``state["time"]``,
        ``state["frame"]``."""
        it = self.integrator
        x, v = np.array(state["x"], float), np.array(state["v"], float)
        if x.shape != it.x.shape or v.shape != it.x.shape:
            raise ValueError(f"restore: positions {x.shape} / velocities {v.shape}, this rank "
                             f"has {it.x.shape}")
        it.x, it.v = x, v
        it.t, it.frame = float(state["time"]), int(state["frame"])

    def run(self, frames=None, callback=None):
        """Run ``frames`` frames (default ``time.frames``), calling ``callback(self)`` after each."""
        n = self.config.time.frames if frames is None else frames
        for _ in range(n):
            self.step()
            if callback is not None:
                callback(self)

    def gather_positions(self, root=0):
        """Global positions (n_vertices, 3) on ``root`` (None elsewhere), in the scene's
        wisp order."""
        parts = self.comm.gather(self.user.to_user(self.x), root=root)
        return np.concatenate(parts) if self.comm.rank == root else None

    def wisp_offsets(self):
        """Vertex offsets (n_wisps + 1,) of the wisps in the scene's order."""
        return parallel.global_wisp_offsets(self.comm, self.user.offsets)

    def terms_run(self):
        """The modelled terms: elastic terms with elements built, plus gravity and head
        contact when switched on (terms that are off are never evaluated)."""
        on = set(self.config.physics.terms)
        return list(self.scene.terms) + [t for t in OTHER_TERMS if t in on]

    def summary(self):
        """The run's figures for summary.json (DESIGN section 3), on every rank."""
        # every phase's wall and CPU seconds, max over ranks, in one reduction (one per phase
        # made the summary kept while the run goes cost 14 collective waits)
        wall, cpu_s = self.timers.as_dict(), self.timers.cpu_dict()
        most = parallel.global_reduce(self.comm, [*wall.values(), *cpu_s.values()], "max")
        tim = {k: float(v) for k, v in zip(wall, most[:len(wall)])}
        cpu = {k: float(v) for k, v in zip(cpu_s, most[len(wall):])}
        per_frame = {
            "newton_iterations": list(self.integrator.newton_iterations),
            "newton_converged": list(self.integrator.newton_converged),
            # per frame: a start frame run to time.start_increment_tol (newton_converged: whether it did)
            "newton_start": list(self.integrator.newton_start),
            # per frame: a later frame run to it because the head jolted (time.jolt_above)
            "newton_jolt": list(self.integrator.newton_jolt),
            # per frame: a start/jolt frame ended by time.start_iterations with time.max_substeps = 1
            # (newton_converged false: a cap asked for, not a missed tolerance; see missed_frames)
            "newton_capped": list(self.integrator.newton_capped),
            "newton_increment": [None if not np.isfinite(v) else float(v)
                                 for v in self.integrator.newton_increment],
            "newton_unconfirmed": list(self.integrator.newton_unconfirmed),
            "newton_refused": list(self.integrator.newton_refused),
            "newton_saddle": list(self.integrator.newton_saddle),
            # the stop's checks per frame (docs/newton.md "Taking the verifying step, ...")
            **{name: list(getattr(self.integrator, name)) for name in FRAME_COUNTS},
            "newton_exact_fallbacks": list(self.integrator.exact_hessian_fallbacks),
            "newton_chord_checks": list(self.integrator.chord_checks),
            "length_projection_move": list(self.integrator.length_projection_move),
            "newton_substeps": list(self.integrator.newton_substeps),
            "newton_substep_iterations": [list(v) for v in self.integrator.newton_substep_iterations],
            "ksp_solves": list(self.ksp_solves)}
        contact = self._contact_summary()
        return {
            "dofs": 3 * self.n_vertices,
            "wisps": self.n_wisps,
            "ranks": self.comm.size,
            "frames": self.integrator.frame,
            "wall_time_s": parallel.global_max(self.comm, self.wall),
            "timings_s": tim,
            "cpu_timings_s": cpu,
            **per_frame,
            # the lists above and contact's *_per_frame, one entry per frame of this run:
            # what scripts/join_summaries.py joins over a restarted run's summaries
            "per_frame_keys": list(per_frame) + [f"contact.{k}" for k in contact.get("contact", {})
                                                 if k.endswith("_per_frame")],
            "ksp_iterations": list(self.solver.iterations),
            "ksp_reasons": list(self.solver.reasons),
            "converged": all(not r.startswith("DIVERGED") for r in self.solver.reasons),
            "terms": self.terms_run(),
            "petsc_options": self.solver.describe(),
            "mat_type": self.assembler.mat.getType(),
            "element_kernels": self.assembler.kernels,
            "jit_compile_s": parallel.global_max(self.comm, self.assembler.compile_seconds),
            "config": self.config.to_dict(),
            **contact,
            **self._trust_summary(),
        }

    def _trust_summary(self):
        """The trust-region solves (empty with time.newton = "filtered"): their KSP type,
        iterations and reasons, one per solve (a rejected step's retry is a solve)."""
        if self.trust is None:
            return {}
        return {"trust_region": {"ksp_type": self.trust.type,
                                 "ksp_iterations": list(self.trust.iterations),
                                 "ksp_reasons": list(self.trust.reasons)}}

    def _contact_summary(self):
        """Strand contact figures (empty when strand_collision is off)."""
        if self.strand is None:
            return {}
        dmin = self.integrator.contact_min_distance
        return {"contact": {
            "thickness": self.strand.d0, "stiffness": self.strand.k,
            "jit_compile_s": parallel.global_max(self.comm, self.strand.compile_seconds),
            "pairs_per_frame": list(self.integrator.contact_pairs),
            "pairs_below_half_thickness_per_frame": list(self.integrator.contact_deep_pairs),
            "pairs_separated_per_frame": list(self.integrator.contact_separated),
            "min_distance_per_frame": [None if not np.isfinite(d) else d for d in dmin],
            "min_distance": float(min(dmin)) if dmin and np.isfinite(min(dmin)) else None,
            "mode": self.strand.mode,
            "potential": self.strand.potential,
            "barrier_stiffness": self.strand.barrier_stiffness,
            # the ccd limiter, per frame: vertices limited (summed over the limiter passes
            # of the Newton steps), most rounds of a pass, vertices held back on the frame paths, pairs left
            # unresolved, most candidate pairs of a limiter call
            "limited_vertices_per_frame": self.strand.limited_vertices.sums[1:],
            "limiter_rounds_per_frame": self.strand.limit_rounds.maxima[1:],
            # with a Newton tolerance: nonlinear updates the limiter replaced by the linear step
            "limiter_replaced_updates_per_frame": self.strand.updates_replaced.sums[1:],
            "frame_path_held_vertices_per_frame": self.strand.frame_fixes.sums[1:],
            "frame_path_checks_per_frame": self.strand.frame_fixes.counts[1:],
            "ccd_unresolved_pairs_per_frame": self.strand.unresolved_pairs.sums[1:],
            "limiter_candidates_per_frame": self.strand.limiter_candidates.maxima[1:]}}

    def close(self):
        """Destroy the PETSc objects of this simulator (collective)."""
        self.solver.destroy()
        if self.trust is not None:
            self.trust.destroy()
        self.assembler.mat.destroy()
        if self.assembler.pmat is not None:
            self.assembler.pmat.destroy()
        self.integrator.xv.destroy()
        self.integrator.bv.destroy()
        if self.strand is not None:
            self.strand.destroy()


#: perturbations whose initial state is reached from the rest pose along the straight way
#: (so the start check's crossings on that way are a tangle the perturbation made)
STRAIGHT_WAY_PERTURBATIONS = ("jitter", "smash")


def perturbation_text(scene_cfg):
    """(``scene.perturbation`` and its size, how to make it smaller: a callable of the
    fraction ``first`` of the straight way from the rest pose at which the first tangled
    pair meets), for messages about the initial state.  A jitter of j' < j (the same seed)
    starts j'/j of the way to j's start, a smash by f' between 1 and f at (1 - f') / (1 - f)
    of the way to f's (the same offsets scaled; f > 1 stretches the wisps, f < 1 squeezes
    them): so a jitter below ``first`` j, a smash within ``first`` |1 - f| of 1 meets no
    pair on its way (that distance rounded down to 3 digits: the value given stays
    between 1 and the bound, never 1 itself)."""
    smash = scene_cfg.perturbation == "smash"       # else "jitter": STRAIGHT_WAY_PERTURBATIONS
    key, now, unit = ("smash_factor", scene_cfg.smash_factor, "") if smash else ("jitter", scene_cfg.jitter, " cm")
    # the way to a smaller perturbation: a jitter down, a smash towards 1 (up from a squeeze,
    # down from a stretch)
    change, side = ("raise", "above") if smash and now < 1.0 else ("lower", "below")
    towards = " towards 1" if smash else ""

    def smaller(first):
        if not 0.0 < first < 1.0:
            return f"{change} scene.{key}{towards}"
        bound = (1.0 + np.sign(now - 1.0) * _rounded_down(first * abs(now - 1.0)) if smash
                 else _rounded_down(first * now))
        return (f"{change} scene.{key} {side} {bound:g}{unit} ({towards.strip() or 'the same seed'}: "
                f"{100 * first:.3g}% of the way from the rest pose to this start is tangle-free)")
    return f"scene.perturbation = \"{scene_cfg.perturbation}\", scene.{key} = {now:g}{unit}", smaller


def _rounded_down(value):
    """``value`` > 0 rounded down to 3 significant digits (a bound stays one)."""
    unit = 10.0 ** (np.floor(np.log10(value)) - 2)
    return float(np.floor(value / unit) * unit)


def _strand_contact(scene, comm, pcomm, timers, cfg, plan, mat_type, user, source, x0=None):
    """The strand-strand contact of ``cfg`` (docs/contact.md); thickness default: twice
    the smallest vertex radius of the scene; the preconditioner is built from the whole
    Newton matrix or the strand matrix alone as ``plan.contact_pc`` says.  In ``ccd``
    mode the rest pose is checked, and the initial positions ``x0`` (None: a restart,
    whose state is the checkpoint's) when a perturbation made them."""
    from lc_petsc.contact import StrandContact
    d0 = cfg.physics.strand_thickness
    if d0 is None:
        d0 = 2.0 * parallel.global_min(comm, float(scene.radius.min(initial=np.inf)))
    strand = StrandContact(scene, comm, pcomm, timers, d0, cfg.physics.strand_stiffness,
                           filter=element_filter(cfg.solver.filter), mat_type=mat_type,
                           coupled_pc=plan.contact_pc == "coupled", mode=cfg.physics.strand_contact_mode,
                           min_separation=cfg.physics.strand_min_separation,
                           potential=cfg.physics.strand_contact_potential,
                           barrier_stiffness=cfg.physics.strand_barrier_stiffness,
                           self_contact=cfg.physics.strand_self_contact, work=plan.contact_work)
    if cfg.physics.strand_contact_mode == "ccd":
        report = check_rest_pose(strand)
        report.thickness_default = cfg.physics.strand_thickness is None
        if report.pairs and cfg.physics.strand_rest_overlap == "error":
            if user is not None:        # name the pair in the scene's numbering
                report.worst = user.scene_numbers(report.worst)
            strand.destroy()
            raise RestPoseOverlapError(named_by(source, report.message()))
        # the initial state, checked as the rest pose is (pairs the rest check let
        # through, exempt ones, stay exempt): a perturbation can tangle what the groom had apart.
        # Only where the straight way from rest is the perturbation's own path (a jitter's
        # displacement, a smash's scaling); a straightened coil unwinds about its axis, and the
        # straight way would pass its turns through each other where the start has none
        if x0 is not None and cfg.scene.perturbation in STRAIGHT_WAY_PERTURBATIONS:
            made_by, smaller = perturbation_text(cfg.scene)
            start = check_start_pose(strand, x0, made_by=made_by, smaller=smaller)
            if start.pairs:
                if user is not None:
                    start.worst = user.scene_numbers(start.worst)
                if cfg.physics.strand_rest_overlap == "exempt":     # the user's choice: a warning
                    strand.start_warning = named_by(source, start.message(exempt=True))
                else:
                    strand.destroy()
                    raise StartOverlapError(named_by(source, start.message()))
    return strand


def build_simulator(config: SimConfig, comm=None, check_start=True) -> Simulator:
    """Build the simulator of ``config`` on ``comm`` (mpi4py; default COMM_WORLD).
    ``check_start``: check the initial state a perturbation makes (off for a restart,
    which continues from its checkpoint's state, not from the initial one)."""
    return Simulator(config, comm, check_start=check_start)
