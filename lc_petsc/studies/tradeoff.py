"""Speed versus accuracy: a reference trajectory, variants along each axis,
errors at common output times, cost, Pareto front, recommendations.

Used by ``drivers/tradeoff.py`` and ``scripts/extremes.py``; see docs/studies.md.
"""

from __future__ import annotations

import copy
import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any, Optional

import numpy as np
from petsc4py import PETSc

from lc_petsc.config import SolverConfig, TimeConfig, without_tolerance_defaults
from lc_petsc.errors import ConfigError, SimulationError, SolverError
from lc_petsc.parallel import global_max
from lc_petsc.simulator import build_simulator
from lc_petsc.solver_plan import default_ksp_rtol
from lc_petsc.studies import report
from lc_petsc.studies.cost_model import COST_TIE, cheapest, modelled_costs
from lc_petsc.studies.measures import (BlowUp, TrajectoryRecorder, compare_trajectories,
                                       quality)

# What a variant's run may die of; these become results (status "unstable"), anything
# else is a bug and propagates.
FAILURES = (SimulationError, FloatingPointError, SolverError, PETSc.Error, ArithmeticError,
            RuntimeWarning, np.linalg.LinAlgError)


@dataclass(frozen=True)
class Settings:
    """One point of the speed/accuracy study: time step, Newton, Krylov and filter settings."""

    dt: float = 1.0 / 30.0
    newton_iterations: int = 3
    newton_tol: Optional[float] = None
    # None: the shipped default, which follows the stopping rule (solver_plan)
    ksp_rtol: Optional[float] = None
    filter: str = "analytic"
    line_search: bool = False
    options: str = ""               # extra PETSc options (e.g. a solver set)
    # the config's defaults
    newton_update: str = TimeConfig.newton_update
    initial_guess: str = TimeConfig.initial_guess
    carry_with_head: bool = TimeConfig.carry_with_head
    newton_increment_tol: Optional[float] = None
    length_projection: bool = TimeConfig.length_projection
    max_substeps: int = TimeConfig.max_substeps     # step cutback (with a tolerance only)
    newton: str = TimeConfig.newton                 # filtered or trust_region
    root_rotation: bool = TimeConfig.root_rotation  # the root turn after a fixed count
    # a fixed count extended on frames whose last increment is above this (None: off)
    newton_extend_above: Optional[float] = TimeConfig.newton_extend_above
    newton_extend_cap: int = TimeConfig.newton_extend_cap
    # the first start_frames frames to this tolerance on the converging path (None: off)
    start_increment_tol: Optional[float] = TimeConfig.start_increment_tol
    start_frames: int = TimeConfig.start_frames
    start_iterations: int = TimeConfig.start_iterations
    # later frames where the head jolts by more than this (cm/s^2) like the start frames (None: off)
    jolt_above: Optional[float] = TimeConfig.jolt_above
    jolt_frames: int = TimeConfig.jolt_frames
    # a step across a jump of the head's velocity starts from the start's first iterate
    jolt_first_iterate: bool = TimeConfig.jolt_first_iterate
    exact_fallback: str = SolverConfig.exact_fallback   # with exact_or_analytic only
    exact_stay: bool = SolverConfig.exact_stay
    wisp_trust: bool = SolverConfig.wisp_trust      # with the shifted fallback only
    # None: time.newton_stop as the config file names it (the dataclass default where it does
    # not); the "as configured" row's stop where the file's tolerance defaulted it
    newton_stop: Optional[str] = None

    def effective_rtol(self) -> float:
        """The Krylov tolerance the run uses: ``ksp_rtol``, or the code default for its
        stopping rule (:data:`KSP_RTOL_FIXED_COUNT` for a fixed Newton count,
        :data:`KSP_RTOL_CONVERGING` with a Newton tolerance)."""
        if self.ksp_rtol is not None:
            return float(self.ksp_rtol)
        time = TimeConfig(newton_tol=self.newton_tol, newton_increment_tol=self.newton_increment_tol)
        return float(default_ksp_rtol(time.newton_converges))

    def label(self):
        """A short human-readable name of the settings."""
        parts = [f"dt=1/{round(1 / self.dt)}", f"N={self.newton_iterations}",
                 f"rtol={self.effective_rtol():.0e}", self.filter]
        if self.newton_tol is not None:
            parts.append(f"tol={self.newton_tol:g}")
        if self.newton_increment_tol is not None:
            parts.append(f"inc<{self.newton_increment_tol:g}")
        if (self.newton_tol, self.newton_increment_tol) != (None, None) and self.max_substeps > 1:
            parts.append(f"cutback<={self.max_substeps}")
        if self.line_search:
            parts.append("LS")
        if self.newton_update != "linear":
            parts.append(self.newton_update)
        if self.initial_guess != "inertial":
            parts.append(self.initial_guess)
        if not self.carry_with_head:
            parts.append("uncarried")
        if self.newton != "filtered":
            parts.append(self.newton)
        if self.length_projection:
            parts.append("projected")
        if self.root_rotation:
            parts.append("root turn")
        if self.newton_extend_above is not None:
            parts.append(f"extend>{self.newton_extend_above:g} cap {self.newton_extend_cap}")
        if self.start_increment_tol is not None:
            parts.append(f"start {self.start_frames} to {self.start_increment_tol:g} cap {self.start_iterations}")
        if self.jolt_above is not None:
            parts.append(f"jolts>{self.jolt_above:g} x{self.jolt_frames}")
        if self.jolt_first_iterate:
            parts.append("jolt first iterate")
        if self.exact_fallback != SolverConfig.exact_fallback:
            parts.append(f"{self.exact_fallback} fallback")
        if self.exact_stay:
            parts.append("exact_stay")
        if self.wisp_trust:
            parts.append("wisp_trust")
        if self.newton_stop is not None:
            parts.append(f"stop {self.newton_stop}")
        return " ".join(parts)


BASE = Settings()


KSP_RTOLS = (1e-2, 1e-4, 1e-6, 1e-8, 1e-10)
#: a variant whose edges stretch by more than this (10%) is not recommended whatever its
#: RMS error: its curls are visibly drawn out, its stored stretch energy wrong (the
#: uncarried 2-iteration hairball: 6% strain, energy error 172x the reference's largest
#: energy; smash unfiltered 101x its length), drivers/tradeoff.py --max-strain
MAX_STRAIN = 0.1
#: a tolerance variant is not recommended when the same setting at a tighter tolerance
#: reaches the target with at most this fraction more Newton iterations (deterministic,
#: unlike the cost): since a loose stop must agree with its model (docs/newton.md,
#: twelfth round) 1e-3 takes 0.97x the iterations of 1e-6 on the 10-wisp demo and
#: hairball with the corotational update, so "inc<0.001" bought nothing and was picked
#: on the cost's noise
MIN_TOLERANCE_SAVING = 0.1


def default_variants(base: Settings = BASE, axes=None, ksp_rtols=KSP_RTOLS, configured=None):
    """[(axis, name, Settings)] along each axis of the study; the base appears once.
    ``configured``: the scene file's own settings (:func:`configured_settings`), a row
    of its own ("as configured") where they differ from the base."""
    out = [("base", "base", base)]
    if configured is not None and configured != base:
        out.append(("configured", "as configured", configured))
    ax = {
        "newton": [(f"newton {n}", replace(base, newton_iterations=n)) for n in (1, 2, 3, 6, 12)],
        "ksp_rtol": [(f"rtol {r:.0e}", replace(base, ksp_rtol=r)) for r in ksp_rtols],
        "dt": [(f"dt 1/{d}", replace(base, dt=1.0 / d)) for d in (30, 60, 120)],
        "filter": [(f"filter {f}", replace(base, filter=f)) for f in ("analytic", "numerical", "none")],
        "line_search": [("line search", replace(base, line_search=True))],
        "newton_update": [
            (f"{u} N={n}", replace(base, newton_update=u, newton_iterations=n))
            for u in ("linear", "edge_retraction") for n in (2, 3, 4, 6)]
        + [("retraction+ftl N=3", replace(base, newton_update="edge_retraction",
                                          initial_guess="follow_the_leader"))]
        + [(f"retraction+projection N={n}", replace(base, newton_update="edge_retraction",
                                                    newton_iterations=n, length_projection=True))
           for n in (2, 3)]
        + [(f"exact_or_analytic inc<{t:g}",
            replace(base, filter="exact_or_analytic", newton_update="edge_retraction",
                    newton_iterations=30, newton_increment_tol=t)) for t in (1e-3, 1e-4, 1e-6)],
        # step cutback against the cap alone (docs/newton.md, fourth round)
        "cutback": [(f"inc<{t:g} cap {n}" + (" no cutback" if m == 1 else f" cutback {m}"),
                     replace(base, filter="exact_or_analytic", newton_update="edge_retraction",
                             newton_iterations=n, newton_increment_tol=t, max_substeps=m))
                    for t in (1e-3, 1e-6) for n, m in ((30, 1), (30, 8), (10, 8))],
        # the trust region on the exact Hessian (docs/newton.md, fifth round), against
        # exact_or_analytic at the same tolerances and fixed counts
        "trust_region": [(f"{m} inc<{t:g}",
                          replace(base, filter="analytic" if m == "trust_region" else "exact_or_analytic",
                                  newton=m, newton_update="edge_retraction", newton_iterations=30,
                                  newton_increment_tol=t))
                         for t in (1e-3, 1e-6) for m in ("trust_region", "filtered")]
        + [(f"trust_region N={n}", replace(base, newton="trust_region", newton_iterations=n))
           for n in (2, 3, 4)],
        # the corotational update of the exact steps against the edge retraction
        # (docs/newton.md, sixth round); at a fixed count (filtered steps) it is the base
        "corotational": [("corotational N=3", replace(base, newton_update="corotational"))]
        + [(f"exact_or_analytic {u} inc<{t:g}",
            replace(base, filter="exact_or_analytic", newton_update=u, newton_iterations=30,
                    newton_increment_tol=t))
           for u in ("corotational", "edge_retraction") for t in (1e-3, 1e-6)],
        # the first iterate carried with the head's change of motion, or not
        # (docs/newton.md, tenth round), at fixed counts and to a tolerance
        "carry_with_head": [(f"{'carried' if c else 'uncarried'} N={n}",
                             replace(base, carry_with_head=c, newton_iterations=n))
                            for c in (True, False) for n in (2, 3, 4, 6)]
        + [(f"{'carried' if c else 'uncarried'} ftl N=3",
            replace(base, carry_with_head=c, initial_guess="follow_the_leader"))
           for c in (True, False)]
        + [(f"{'carried' if c else 'uncarried'} exact_or_analytic inc<{t:g}",
            replace(base, carry_with_head=c, filter="exact_or_analytic", newton_iterations=30,
                    newton_increment_tol=t)) for c in (True, False) for t in (1e-3, 1e-6)],
        # the root turn after a fixed count (docs/newton.md, "Fourteenth round"), against
        # the same counts without it and the paper's setting (the yardstick)
        "root_rotation": [(f"{'root turn' if t else 'plain'}{' ftl' if f else ''} N={n}",
                           replace(base, root_rotation=t, newton_iterations=n,
                                   initial_guess="follow_the_leader" if f else base.initial_guess))
                          for f in (False, True) for t in (True, False) for n in (2, 3, 4)]
        + [(f"paper setting{' ftl' if f else ''}",
            replace(base, newton_update="linear", carry_with_head=False,
                    initial_guess="follow_the_leader" if f else base.initial_guess)) for f in (False, True)],
        # the fixed count extended on frames far from converged, with and without the
        # root turn (docs/newton.md, "Eighteenth round")
        "newton_extend": [(f"{'root turn ' if t else ''}extend>{b:g}",
                           replace(base, root_rotation=t, newton_extend_above=b))
                          for t in (False, True) for b in (3e-2, 1e-2, 3e-3)]
        + [("root turn, not extended", replace(base, root_rotation=True))],
        # a trust region per wisp on the shifted fallback's exact steps (docs/newton.md "A
        # trust region per wisp"), against the recommended path without it
        "wisp_trust": [(f"{'wisp trust' if w else 'shifted'} inc<{t:g}",
                        replace(base, filter="exact_or_analytic", newton_update="corotational",
                                exact_fallback="shifted", exact_stay=True, wisp_trust=w,
                                newton_iterations=30, newton_increment_tol=t))
                       for t in (1e-3, 1e-6) for w in (True, False)],
    }
    for a in (axes or ax):
        for name, s in ax[a]:
            if s != base:
                out.append((a, name, s))
    return out


def configured_settings(cfg, options=""):
    """The study's :class:`Settings` of what ``cfg`` (a scene's config file) runs: its
    own [time] and [solver] choices, which the study's base replaces with the code's
    defaults (the demo's follow-the-leader first iterate and length projection were in
    no row of a study of it).  Its solver options stay in ``cfg`` (:func:`configure`
    appends); ``options``: the study's extra ones (``--set``)."""
    t = cfg.time
    return Settings(dt=t.dt, newton_iterations=t.newton_iterations, newton_tol=t.newton_tol,
                    filter=cfg.solver.filter, line_search=t.line_search, options=options,
                    newton_update=t.newton_update, initial_guess=t.initial_guess,
                    carry_with_head=t.carry_with_head, newton_increment_tol=t.newton_increment_tol,
                    length_projection=t.length_projection, max_substeps=t.max_substeps, newton=t.newton,
                    root_rotation=t.root_rotation, newton_extend_above=t.newton_extend_above,
                    newton_extend_cap=t.newton_extend_cap, start_increment_tol=t.start_increment_tol,
                    start_frames=t.start_frames, start_iterations=t.start_iterations, jolt_above=t.jolt_above,
                    jolt_frames=t.jolt_frames, jolt_first_iterate=t.jolt_first_iterate,
                    exact_fallback=cfg.solver.exact_fallback,
                    exact_stay=cfg.solver.exact_stay, wisp_trust=cfg.solver.wisp_trust,
                    newton_stop=t.newton_stop if "time.newton_stop" in cfg.solver_path_defaulted else None)


def reference_settings(dt=1.0 / 120.0, newton_tol=1e-9, max_newton=100, filter="none",
                       line_search=True, method="exact_or_analytic"):
    """The reference: BDF-1 solved to max|dx| < ``newton_tol`` cm, every frame in one
    step of ``dt`` (no step cutback: the variants are compared with its frames, so it
    must solve their discretisation; :func:`reference_warning` flags a frame it missed).

    The filter changes only the Newton matrix, not the solution of a frame, so the
    reference may use the exact Hessian.  ``method="exact_or_analytic"`` (default): the
    recommended converging path (docs/newton.md): the exact Hessian near the solution,
    the shifted fallback, exact steps kept once taken, the corotational update, CG.  The
    edge retraction with the analytic fallback it replaced missed 1e-9 cm in frame 0 of
    the 10-wisp hairball at dt 1/30 within 100 iterations and was cut into 2 x dt/2 (a
    solution 1.2e-2 from the whole step's in frames 0-1; docs/newton.md, "Fifteenth
    round").  ``method="unfiltered"`` (the reference before): the unfiltered Hessian
    (``filter``) with the line search, solved by GMRES (:data:`REFERENCE_KSP`) since it
    may be indefinite; it used 2,239 iterations on that run and stalled in frames where
    the line search found no decrease.  :func:`run_study` falls back to
    :func:`reference_fallback` (analytic filter, CG) if the reference fails.
    """
    if method == "exact_or_analytic":
        return Settings(dt=dt, newton_iterations=max_newton, newton_tol=newton_tol,
                        ksp_rtol=1e-12, filter="exact_or_analytic", exact_fallback="shifted",
                        exact_stay=True, newton_update="corotational", max_substeps=1)
    if method != "unfiltered":
        raise ValueError(f"reference method {method!r}: use unfiltered or exact_or_analytic")
    return Settings(dt=dt, newton_iterations=max_newton, newton_tol=newton_tol, ksp_rtol=1e-12,
                    filter=filter, line_search=line_search, options=REFERENCE_KSP, max_substeps=1)


def base_reference(base: Settings = BASE, ksp_rtol=1e-10) -> Settings:
    """A cheaper reference for large scenes, where Newton to convergence is out of reach:
    the base settings (same dt, Newton iterations and filter) with the Krylov solves
    converged to ``ksp_rtol``.  Errors against it measure the Krylov tolerance's share of
    the error only (use it with the ``ksp_rtol`` axis)."""
    return replace(base, ksp_rtol=ksp_rtol)


# The unfiltered Hessian can be indefinite: CG then stops with DIVERGED_INDEFINITE_PC
# (measured on the shaking 20-wisp hairball, frame 28 at dt 1/120).  GMRES with the
# default exact per-wisp block Jacobi converges in one iteration on any nonsingular
# system (as does MUMPS LU, measured: same Newton counts, slower).
REFERENCE_KSP = "-ksp_type gmres -ksp_max_it 200"


def tighter_reference(ref: Settings) -> Settings:
    """The reference's check: a converging reference at half its dt (its Newton error is
    nil, its time step's is not), a fixed-count one (``--ref base``) with a 100x tighter
    Krylov tolerance.  Its distance to the reference is the reference's own error."""
    if (ref.newton_tol, ref.newton_increment_tol) != (None, None):
        return replace(ref, dt=ref.dt / 2)
    return replace(ref, ksp_rtol=ref.effective_rtol() / 100)


def reference_fallback(ref: Settings) -> Settings:
    """The reference's fallback when it fails: analytic filter, many Newton iterations, default Krylov."""
    return replace(ref, filter="analytic", newton_iterations=max(ref.newton_iterations, 200),
                   newton_update="linear", exact_fallback="analytic", exact_stay=False, wisp_trust=False,
                   options=ref.options.replace(REFERENCE_KSP, "").strip())


def configure(base_cfg, s: Settings, duration):
    """A copy of ``base_cfg`` running ``duration`` seconds with the settings ``s`` (a
    file's tolerance's defaults dropped first, :func:`without_tolerance_defaults`: the
    settings name the path, and ``time.newton_stop`` stays as the file set it unless they
    hold one: the "as configured" row of a file whose tolerance defaulted it, which ran
    ``"increment"`` where the file runs ``"chord_estimate"`` before 2026-12-07, review61)."""
    cfg = without_tolerance_defaults(copy.deepcopy(base_cfg))
    cfg.time.dt = s.dt
    cfg.time.frames = int(round(duration / s.dt))
    cfg.time.newton_iterations = s.newton_iterations
    cfg.time.newton_tol = s.newton_tol
    cfg.time.line_search = s.line_search
    cfg.time.newton_update = s.newton_update
    cfg.time.initial_guess = s.initial_guess
    cfg.time.carry_with_head = s.carry_with_head
    cfg.time.newton_increment_tol = s.newton_increment_tol
    cfg.time.length_projection = s.length_projection
    cfg.time.max_substeps = s.max_substeps
    cfg.time.newton = s.newton
    cfg.time.root_rotation = s.root_rotation
    # the scene file's own extension would be refused with the reference's tolerance
    cfg.time.newton_extend_above = s.newton_extend_above
    cfg.time.newton_extend_cap = s.newton_extend_cap
    cfg.time.start_increment_tol = s.start_increment_tol
    cfg.time.start_frames = s.start_frames
    cfg.time.start_iterations = s.start_iterations
    cfg.time.jolt_above = s.jolt_above
    cfg.time.jolt_frames = s.jolt_frames
    cfg.time.jolt_first_iterate = s.jolt_first_iterate
    cfg.solver.filter = s.filter
    cfg.solver.exact_fallback = s.exact_fallback
    cfg.solver.exact_stay = s.exact_stay
    cfg.solver.wisp_trust = s.wisp_trust
    if s.newton_stop is not None:
        cfg.time.newton_stop = s.newton_stop
    rtol = "" if s.ksp_rtol is None else f"-ksp_rtol {s.ksp_rtol:g}"      # else the code default
    cfg.solver.options = " ".join(x for x in (cfg.solver.options, s.options, rtol) if x)
    return cfg


def run_trajectory(base_cfg, s: Settings, duration, out_dt, comm, blowup=5.0):
    """Run one setting; capture every ``out_dt`` seconds.  Never raises for the
    failures of :data:`FAILURES` or a blow-up: returns status ``unstable`` with when
    and how it failed (the trajectory up to then is kept)."""
    every = out_dt / s.dt
    if abs(every - round(every)) > 1e-6 or round(every) < 1:
        raise ValueError(f"dt = {s.dt:g} does not divide the output interval {out_dt:g}")
    cfg = configure(base_cfg, s, duration)
    res: dict[str, Any] = {"status": "ok", "failure": "", "failed_frame": None, "failed_time": None,
                           "message": ""}
    sim = None
    rec = None
    t0 = time.perf_counter()
    cpu = 0.0
    try:
        sim = build_simulator(cfg, comm)
        rec = TrajectoryRecorder(sim, every=int(round(every)), blowup=blowup)
        c0 = time.process_time()
        try:
            sim.run(cfg.time.frames, callback=rec)
        finally:
            cpu = time.process_time() - c0
    except FAILURES as e:
        kind = "blow-up" if isinstance(e, BlowUp) else type(e).__name__
        frame = sim.integrator.frame if sim is not None else None
        res.update(status="unstable", failure=kind, failed_frame=frame,
                   failed_time=None if frame is None else frame * s.dt,
                   message=" ".join(str(e).split())[:400])
    total = time.perf_counter() - t0
    if sim is not None:
        summ = sim.summary()
        res.update(wall_s=summ["wall_time_s"], frames_run=sim.integrator.frame,
                   newton_total=int(sum(summ["newton_iterations"])),
                   # per frame (a frame's substeps and discarded attempts included)
                   frame_iterations=list(summ["newton_iterations"]),
                   newton_converged_frames=sum(c is True for c in summ["newton_converged"]),
                   newton_unconverged_frames=sum(c is False for c in summ["newton_converged"]),
                   # frames split into substeps: not solutions of the variant's own dt
                   newton_cut_back_frames=sum(n > 1 for n in summ["newton_substeps"]),
                   # per frame: the steps kept (compared with the reference's, not_newtons_error)
                   newton_substeps=list(summ["newton_substeps"]),
                   ksp_iterations_mean=float(np.mean(summ["ksp_iterations"])) if summ["ksp_iterations"] else None,
                   ksp_iterations_max=max(summ["ksp_iterations"], default=None),
                   # Krylov work of the cost model (cost_model.work_per_sim_s), the
                   # trust region's own solves included
                   ksp_total=int(sum(summ["ksp_iterations"])
                                 + sum(summ.get("trust_region", {}).get("ksp_iterations", []))),
                   timings_s=summ["timings_s"], cpu_s=global_max(comm, cpu))
        sim.close()
    res["total_wall_s"] = total
    traj = None
    if rec is not None and comm.rank == 0:
        traj = {"times": rec.times, "positions": rec.positions, "energies": rec.energies}
    geo = (rec.rest, rec.offsets, rec.pinned) if rec is not None else None
    return res, traj, geo


COSTS = {"wall_per_sim_s": "wall time per simulated second (s)",
         "cpu_per_sim_s": "CPU time per simulated second (s, max over ranks; robust to a shared machine)"}


def run_study(base_cfg, variants, comm, out_dir, duration=1.0, out_dt=1.0 / 30.0,
              ref: Optional[Settings] = None, targets=(0.1, 0.03, 0.01, 0.003, 0.001), log=print,
              meta=None, blowup=5.0, cost="wall_per_sim_s", ref_check=True, max_strain=MAX_STRAIN,
              min_saving=MIN_TOLERANCE_SAVING):
    """Reference + variants; writes tradeoff.csv, tradeoff.json, pareto.png and
    recommendations.md to ``out_dir`` (rank 0).  Returns the rows (rank 0; None elsewhere).

    ``ref_check``: also run :func:`tighter_reference` and report the reference's distance
    to it (its own error); a target below it is not judged (a variant's error against
    the reference says nothing there).  ``max_strain``: a variant whose edges stretch
    beyond it is not recommended; ``min_saving``: a looser tolerance must save more Newton
    iterations than this fraction (:func:`recommend`)."""
    out = Path(out_dir)
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    ref = ref or reference_settings()
    unsupported = unsupported_variants(base_cfg, variants, duration)
    for name, why in unsupported.items():
        log(f"  {name}: not run, the scene does not support it ({why})")
    rres, rtraj, geo = run_trajectory(base_cfg, ref, duration, out_dt, comm, blowup)
    if rres["status"] != "ok":
        log(f"reference ({ref.label()}) failed ({rres['failure']}: {rres['message'][:100]}); "
            "falling back to the analytic filter")
        ref = reference_fallback(ref)
        rres, rtraj, geo = run_trajectory(base_cfg, ref, duration, out_dt, comm, blowup)
    if rres["status"] != "ok":
        raise RuntimeError(f"the reference trajectory ({ref.label()}) failed: {rres['message']}")
    log(f"reference ({ref.label()}): {rres['wall_s']:.2f} s, Newton iterations {rres['newton_total']} "
        f"over {rres['frames_run']} steps, {rres['newton_cut_back_frames']} frames cut back into "
        f"substeps, {rres['newton_unconverged_frames']} frames not converged "
        f"to the tolerance")
    warning = reference_warning(rres)
    if warning:
        log(f"WARNING: {warning}")
    rows = []
    rq: dict[str, Any] = {}
    if comm.rank == 0:
        rest, offsets, pinned = geo
        rq = quality(rtraj, rest, offsets, pinned)
    own = reference_error(base_cfg, ref, rtraj, geo, duration, out_dt, comm, blowup) if ref_check else None
    if own is not None:
        log(f"reference's own error (against {own['against']}): RMS {own.get('rms_rel_error', float('nan')):.2e}, "
            f"max {own.get('max_rel_error', float('nan')):.2e}, energy {own.get('energy_rel_error', float('nan')):.2e}")
    # a setting on several axes (the full study: 14 of 59 variants) runs once; its
    # other rows copy the first's figures and name it in "same_as"
    first: dict[Settings, dict] = {}
    for axis, name, s in variants:
        if name in unsupported:
            if comm.rank == 0:
                rows.append({"variant": name, "axis": axis, "label": s.label(), **asdict(s),
                             "ksp_rtol": s.effective_rtol(), "status": "unsupported", "stable": False,
                             "failure": "ConfigError", "message": unsupported[name], "same_as": None})
            continue
        if s in first:
            if comm.rank == 0:
                rows.append(dict(first[s], variant=name, axis=axis, same_as=first[s]["variant"]))
                log(f"  {name:16s} same settings as {first[s]['variant']}")
            continue
        res, traj, _ = run_trajectory(base_cfg, s, duration, out_dt, comm, blowup)
        first[s] = {"variant": name}
        if comm.rank != 0:
            continue
        row = {"variant": name, "axis": axis, "label": s.label(), **asdict(s), "ksp_rtol": s.effective_rtol(),
               **res, "same_as": None}
        row.pop("timings_s", None)
        row["stable"] = res["status"] == "ok"
        n_out = max(len(traj["times"]) - 1, 1) if traj else 1
        if res.get("wall_s") is not None and res.get("frames_run"):
            simulated = res["frames_run"] * s.dt
            row["wall_per_sim_s"] = res["wall_s"] / simulated
            row["wall_per_frame_s"] = res["wall_s"] / n_out
            row["cpu_per_sim_s"] = res["cpu_s"] / simulated
            row["cpu_per_frame_s"] = res["cpu_s"] / n_out
        if traj and len(traj["times"]) > 1:
            row.update(compare_trajectories(traj, rtraj, rest, offsets, pinned))
            row.update(quality(traj, rest, offsets, pinned))
        row["ref_max_stretch_strain"] = rq["max_stretch_strain"]
        row["ref_curl_retention"] = rq["curl_retention"]
        if not row["stable"]:   # errors of a partial trajectory are not comparable
            for k in ("rms_rel_error", "max_rel_error", "final_rms_rel_error", "energy_rel_error"):
                row[k + "_until_failure"] = row.pop(k, None)
        rows.append(row)
        first[s] = row
        log(f"  {name:16s} {res['status']:8s} {row.get('wall_per_sim_s') or float('nan'):8.3f} s/sim-s  "
            f"rms err {row.get('rms_rel_error', float('nan')):.2e}  "
            f"{res['failure']} {res['message'][:80]}")
    if comm.rank != 0:
        return None
    for row in rows:
        row["not_newtons_error"] = not_newtons_error(row, ref, rres.get("newton_substeps"))
    cols = ["variant", "axis", "label", "status", "stable", "wall_per_sim_s", "wall_per_frame_s",
            "cpu_per_sim_s", "cpu_per_frame_s", "newton_total", "ksp_total", "newton_cut_back_frames",
            "rms_rel_error", "max_rel_error", "final_rms_rel_error", "energy_rel_error",
            "max_stretch_strain", "curl_retention", "ref_max_stretch_strain",
            "ref_curl_retention", "failure", "failed_frame", "failed_time", "message", "same_as",
            "not_newtons_error"]
    report.write_csv(rows, out / "tradeoff.csv", cols)
    floor = (own or {}).get("rms_rel_error")
    recs = recommend(rows, targets, cost=cost, floor=floor, max_strain=max_strain, min_saving=min_saving)
    report.write_json({"meta": dict(meta or {}, duration=duration, out_dt=out_dt),
                       "reference": dict(asdict(ref), ksp_rtol=ref.effective_rtol(),
                                         **{k: v for k, v in rres.items() if k != "timings_s"},
                                         **rq, own_error=own, warning=warning),
                       "max_strain": max_strain, "variants": rows, "recommendations": recs},
                      out / "tradeoff.json")
    report.plot_pareto(rows, out / "pareto.png", cost=cost, cost_label=COSTS[cost], floor=floor,
                       title=f"speed vs accuracy: {(meta or {}).get('scene', '')}, {duration:g} s simulated")
    (out / "recommendations.md").write_text(markdown(rows, recs, ref, meta, cost, rres, own, max_strain,
                                                     min_saving))
    return rows


def unsupported_variants(base_cfg, variants, duration):
    """{name: the config's refusal} of the variants the scene does not support (e.g. the
    trust region with strand contact): reported as rows of status ``unsupported``
    instead of stopping the study at them, after hours of runs, with nothing written."""
    out = {}
    for _, name, s in variants:
        try:
            configure(base_cfg, s, duration).validate()
        except ConfigError as e:
            out[name] = str(e)
    return out


def reference_warning(rres) -> str:
    """What makes the reference run ``rres`` (:func:`run_trajectory`'s record) no solution
    of the variants' problem: frames cut into substeps (another discretisation than one
    step of its dt) or short of its tolerance; "" if none.  A variant's error against it
    then measures that too, not only the variant's own error."""
    cut = [f for f, n in enumerate(rres.get("newton_substeps") or []) if n > 1]
    missed = rres.get("newton_unconverged_frames") or 0
    parts = []
    if cut:
        parts.append(f"{len(cut)} frame(s) cut into substeps (frames {', '.join(map(str, cut[:5]))}"
                     f"{' ...' if len(cut) > 5 else ''}): another discretisation than the variants'")
    if missed:
        parts.append(f"{missed} frame(s) not converged to its tolerance")
    if not parts:
        return ""
    return ("the reference is not the converged solution of every step: " + "; ".join(parts)
            + ". Errors against it include its own deviation there; raise --ref-tol or use a "
            "smaller --ref-dt")


def reference_error(base_cfg, ref, rtraj, geo, duration, out_dt, comm, blowup):
    """The reference's distance to :func:`tighter_reference` (rank 0; None elsewhere), at
    the common output times, with the check's label and status."""
    tight = tighter_reference(ref)
    res, traj, _ = run_trajectory(base_cfg, tight, duration, out_dt, comm, blowup)
    if comm.rank != 0:
        return None
    out = {"against": tight.label(), "status": res["status"],
           "newton_unconverged_frames": res.get("newton_unconverged_frames")}
    if res["status"] == "ok":
        out.update(compare_trajectories(rtraj, traj, *geo))
    return out


def not_newtons_error(row, ref: Settings, ref_substeps):
    """Why a variant converged at the reference's time step is farther from it than
    Newton's error ("" if it is not, or if the row is not such a variant).  Every frame
    of it met the tolerance, so only two things move it off the reference: a frame split
    into other substeps than the reference's (step cutback: other backward-Euler steps,
    the time step's error), or a step that reached another of its solutions (a bistable
    frame, where the first iterate decides; docs/newton.md, "Two converged runs that
    disagree").  The first is named from the per-frame substep counts (equal counts can
    still hide other splits; the second test then speaks); the second is assumed when the
    RMS error exceeds the increment tolerance (both relative to the wisp length).
    Measured on the demo cut to 10 wisps: the uncarried first iterate to 1e-6 with a cap
    of 30 split frame 0 into dt/4, dt/4, dt/2 where the reference took 2 x dt/2, which is
    all of its 1.7e-3 (with a cap of 60 it takes 2 x dt/2 too and lands 9.5e-10 away)."""
    if not (row.get("stable") and converging(row) and row.get("newton_unconverged_frames") == 0
            and row.get("rms_rel_error") is not None and abs(row["dt"] - ref.dt) <= 1e-9 * ref.dt):
        return ""
    subs = row.get("newton_substeps") or []
    other = [(f, a, b) for f, (a, b) in enumerate(zip(subs, ref_substeps or [])) if a != b]
    if other:
        frames = ", ".join(f"frame {f}: {a} against {b}" for f, a, b in other[:3])
        more = f" and {len(other) - 3} more" if len(other) > 3 else ""
        return (f"frames split into other substeps than the reference's ({frames}{more}): "
                "its error is the time step's there, not Newton's")
    tol = row.get("newton_increment_tol")
    if tol is not None and row["rms_rel_error"] > tol:
        return (f"converged to {tol:g} with the reference's substeps yet {row['rms_rel_error']:.3g} "
                "from it: some frame reached another solution of its step (bistable, the first "
                "iterate decides), not Newton's error")
    return ""


def recommend(rows, targets, error="rms_rel_error", cost="wall_per_sim_s", floor=None,
              max_strain=MAX_STRAIN, min_saving=MIN_TOLERANCE_SAVING, tie=COST_TIE):
    """For each target error, the cheapest stable variant reaching it (or None), by the
    modelled cost (:mod:`lc_petsc.studies.cost_model`: deterministic work counts priced by
    the measured ``cost``; modelled costs within ``tie`` of the lowest go to the lower
    error), so two runs of a study recommend the same.  A target at or below ``floor``
    (the reference's own error) is not judged: ``below_reference``.  A variant whose
    edges stretch beyond ``max_strain`` (None: no limit) is not recommended whatever its
    error; the cheaper ones so passed over are listed under ``stretched``.  A Newton
    tolerance that saves less than ``min_saving`` of the Newton iterations of the same
    setting at a tighter tolerance that also reaches the target is replaced by the
    tightest such (it buys nothing; listed under ``looser``)."""
    model = {id(r): m for r, m in zip(rows, modelled_costs(rows, cost))}
    out = []
    for t in targets:
        below = floor is not None and t <= floor
        ok = [r for r in rows if r.get("stable") and r.get(error) is not None
              and r[error] <= t and r.get(cost)] if not below else []
        # a copy of another row (same_as) is the same setting: the original is named
        kept = [r for r in ok if not stretched(r, max_strain) and not r.get("same_as")]
        best = cheapest([(model[id(r)], r) for r in kept], error, tie)[1] if kept else None
        passed_over = [r["variant"] for r in sorted(ok, key=lambda r: (model[id(r)], r["variant"]))
                       if stretched(r, max_strain) and (best is None or model[id(r)] < model[id(best)])]
        looser = []
        if best is not None:
            tighter = [r for r in kept if saves_little(best, r, min_saving)]
            if tighter:
                looser = [best["variant"]]
                best = min(tighter, key=_tolerances)
        out.append({"target": t, "variant": best["variant"] if best else None,
                    "label": best["label"] if best else None, "below_reference": below,
                    "cost": best[cost] if best else None,
                    "modelled_cost": model[id(best)] if best else None,
                    "error": best[error] if best else None,
                    "max_stretch_strain": best.get("max_stretch_strain") if best else None,
                    "energy_rel_error": best.get("energy_rel_error") if best else None,
                    "stretched": passed_over, "looser": looser})
    return out


_TOLERANCES = ("newton_increment_tol", "newton_tol")


def _tolerances(row):
    """``row``'s Newton tolerances, a missing one as infinite (no test)."""
    return tuple(float("inf") if row.get(k) is None else row[k] for k in _TOLERANCES)


def saves_little(loose, tight, min_saving=MIN_TOLERANCE_SAVING):
    """Whether ``tight`` is ``loose``'s setting at a tighter Newton tolerance (every other
    setting equal) reached with at most ``min_saving`` more Newton iterations: the looser
    tolerance then buys nothing worth its weaker stop (None: never)."""
    if min_saving is None or not converging(loose) or not converging(tight):
        return False
    others = [f.name for f in fields(Settings) if f.name not in _TOLERANCES]
    if any(loose.get(k) != tight.get(k) for k in others):
        return False
    lt, tt = _tolerances(loose), _tolerances(tight)
    if not (all(b <= a for a, b in zip(lt, tt)) and tt != lt):
        return False
    its_loose, its_tight = loose.get("newton_total"), tight.get("newton_total")
    return bool(its_loose) and its_tight is not None and its_tight <= (1 + min_saving) * its_loose


def converging(row):
    """Whether ``row``'s variant runs Newton to a tolerance (else a fixed count)."""
    return row.get("newton_increment_tol") is not None or row.get("newton_tol") is not None


def stretched(row, max_strain):
    """Whether ``row``'s largest edge strain exceeds ``max_strain`` (None: no limit)."""
    strain = row.get("max_stretch_strain")
    return max_strain is not None and strain is not None and strain > max_strain


def markdown(rows, recs, ref, meta=None, cost="wall_per_sim_s", ref_result=None, own=None,
             max_strain=MAX_STRAIN, min_saving=MIN_TOLERANCE_SAVING):
    """The study's markdown report: recommendations, then every variant's errors and cost.
    ``ref_result``: the reference run's record (its cut-back and unconverged frames);
    ``own``: the reference's own error (:func:`reference_error`); ``max_strain``: the
    edge strain above which a variant is not recommended (None: no limit); ``min_saving``:
    the share of Newton iterations a looser tolerance must save (:func:`recommend`)."""
    lines = ["# Speed versus accuracy\n"]
    if meta and meta.get("command"):
        lines.append(f"Command: `{meta['command']}`\n")
    how = ""
    if ref_result is not None and ref_result.get("frames_run"):
        how = (f" ({ref_result.get('newton_cut_back_frames', 0)} of {ref_result['frames_run']} "
               f"frames cut back into substeps, {ref_result.get('newton_unconverged_frames', 0)} "
               "not converged)")
    lines.append(f"Reference: {ref.label()}{how}. Errors at the common output times; position "
                 f"errors relative to the wisp length; cost = {COSTS[cost]}.\n")
    warning = reference_warning(ref_result or {})
    if warning:
        lines.append(f"**WARNING: {warning}.**\n")
    if own is not None:
        lines.append(f"Reference's own error (its distance to {own['against']}): "
                     + (f"RMS {report.fmt(own.get('rms_rel_error'))}, max {report.fmt(own.get('max_rel_error'))}, "
                        f"energy {report.fmt(own.get('energy_rel_error'))}; errors below it are not "
                        "resolved, targets below it are not judged.\n"
                        if own["status"] == "ok" else f"unknown (the check was {own['status']}).\n"))
    limit = "" if max_strain is None else f", edges within {100 * max_strain:g}% of their length"
    if min_saving is not None:
        limit += (f"; a looser Newton tolerance only where it saves more than {100 * min_saving:g}% "
                  "of the Newton iterations of a tighter one")
    flagged = [r for r in rows if r.get("not_newtons_error") and not r.get("same_as")]
    if flagged:
        lines.append("Converged at the reference's time step, yet not Newton's error (table below, "
                     "last column): " + ", ".join(r["variant"] for r in flagged) + ".\n")
    lines.append(f"## Recommendations (cheapest stable setting reaching the target RMS error{limit})\n")
    lines.append("Cheapest by the modelled cost: Newton + Krylov iterations per simulated second (the "
                 "same in every run) times a price per unit, the median measured cost per unit over "
                 "the rows of the same filter, Newton method, line search and solver set; modelled "
                 f"costs within {100 * COST_TIE:g}% of the lowest go to the lower error. The measured "
                 "cost is shown beside it.\n")
    lines.append(report.markdown_table(
        ["target RMS error", "variant", "settings", f"cost ({cost})", "modelled cost", "RMS error", "max strain",
         "energy err", "cheaper, passed over (edges stretched)", "looser tolerance, passed over (saves too little)"],
        [[report.fmt(r["target"]),
          r["variant"] or ("below the reference's own error" if r.get("below_reference")
                           else "none reaches it"), r["label"] or "-",
          report.fmt(r["cost"]), report.fmt(r.get("modelled_cost")), report.fmt(r["error"]),
          report.fmt(r.get("max_stretch_strain")),
          report.fmt(r.get("energy_rel_error")), ", ".join(r.get("stretched") or ()) or "-",
          ", ".join(r.get("looser") or ()) or "-"]
         for r in recs]))
    lines.append("\n## All variants\n")
    lines.append(report.markdown_table(
        ["variant", "status", "wall s/sim-s", "wall s/frame", "CPU s/sim-s", "Newton its",
         "frames cut back", "frames not converged", "RMS err", "max err", "energy err",
         "max strain", "curl retention", "failure"],
        [[r["variant"] + (f" (= {r['same_as']})" if r.get("same_as") else ""), r["status"],
          report.fmt(r.get("wall_per_sim_s")),
          report.fmt(r.get("wall_per_frame_s")), report.fmt(r.get("cpu_per_sim_s")),
          report.fmt(r.get("newton_total")), report.fmt(r.get("newton_cut_back_frames")),
          # a fixed Newton count has no tolerance to miss: "-"
          report.fmt(r.get("newton_unconverged_frames") if converging(r) else None),
          report.fmt(r.get("rms_rel_error")),
          report.fmt(r.get("max_rel_error")), report.fmt(r.get("energy_rel_error")),
          report.fmt(r.get("max_stretch_strain")), report.fmt(r.get("curl_retention")),
          (f"not run: {r['message']}" if r["status"] == "unsupported"
           else f"{r['failure']} at frame {r['failed_frame']}" if not r["stable"]
           else "; ".join(n for n in ("edges stretched beyond the limit: not recommended"
                                       if stretched(r, max_strain) else "",
                                       r.get("not_newtons_error") or "") if n))]
         for r in rows]))
    return "\n".join(lines)
