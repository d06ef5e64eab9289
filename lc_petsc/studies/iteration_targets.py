"""Issue 14's iteration targets on whole runs: each scene run to a tolerance on a Newton
path (a variant SPEC as in scripts/newton_history.py), per frame its iterations,
whether it converged and the substeps kept; and, on a sample of frames, the distance of
the run's stop from the same step solved to a much tighter tolerance from the same start
state (the check that every claimed stop is within the tolerance of the step's solution,
docs/newton.md "Every stop at the step's solution").  Used by
``scripts/iteration_targets.py``; findings in docs/newton.md "Targets of the issue".
"""

from __future__ import annotations

import copy
import statistics
import time

import numpy as np
from mpi4py import MPI

from lc_petsc.simulator import build_simulator
from lc_petsc.studies.newton import configure, parse_variant

#: the recommended path for a tolerance (docs/newton.md): the exact Hessian once close,
#: corotational exact steps, the shifted fallback, exact steps kept after a whole one
RECOMMENDED = "filter=exact_or_analytic,update=corotational,fallback=shifted,stay=1"
#: the reference that solves a sampled frame again from its start state (the inertial
#: first iterate, the increment stop, no cutback)
REFERENCE = RECOMMENDED + ",guess=inertial"


def tolerance_config(base_cfg, spec, tol, cap, frames, max_substeps):
    """``base_cfg`` on the path ``spec`` ("" keeps the config's own solver settings, those
    its file's tolerance resolved included, ``solver_path_defaulted``; the key ``stop``
    sets ``time.newton_stop``), to ``tol`` with ``cap`` iterations and up to
    ``max_substeps`` substeps of step cutback, ``frames`` frames."""
    variant = parse_variant(spec)
    stop = variant.pop("stop", "increment")
    cfg = configure(base_cfg, variant, cap, frames)
    cfg = copy.deepcopy(cfg)
    cfg.time.newton_increment_tol = tol
    cfg.time.newton_stop = stop
    if not spec:
        # the config's own path is the one its file's tolerance resolved (drivers/simulate.py's),
        # which configure drops (without_tolerance_defaults): it ran the analytic filter, 450
        # iterations a frame where the file runs 15-29 (review61)
        for name in base_cfg.solver_path_defaulted:
            table, key = name.split(".")
            setattr(getattr(cfg, table), key, getattr(getattr(base_cfg, table), key))
    cfg.time.max_substeps = max_substeps
    return cfg.validate()


def run_path(cfg, comm):
    """Run ``cfg`` (:func:`tolerance_config`) for its frames.  Returns (rows, states):
    per frame a dict (iterations, converged, substeps, increment, chord checks, CPU
    seconds of the step summed over the ranks) and its start state (x, v, t, rest edge
    lengths) with the positions it ended at."""
    sim = build_simulator(cfg, comm)
    it = sim.integrator
    rows, states = [], []
    try:
        for f in range(cfg.time.frames):
            start = (it.x.copy(), it.v.copy(), it.t, it.rest_edge.copy())
            cpu = time.process_time()
            sim.step()
            cpu = comm.allreduce(time.process_time() - cpu)
            rows.append({"frame": f, "iterations": int(it.newton_iterations[-1]), "cpu_s": cpu,
                         "converged": bool(it.newton_converged[-1]),
                         "substeps": int(it.newton_substeps[-1]),
                         "increment": float(it.newton_increment[-1]),
                         "chord_checks": int(it.chord_checks[-1])})
            states.append(start + (it.x.copy(),))
    finally:
        sim.close()
    return rows, states


def stop_distances(ref_cfg, comm, states, frames, tol=1e-10, cap=80):
    """Each of ``frames`` of ``states`` (:func:`run_path`) solved again by ``ref_cfg`` from its
    start state to ``tol`` (``cap`` iterations, no cutback).  Returns per frame the largest
    vertex distance between the run's stop and that solution relative to the wisp length
    (all ranks), and whether the reference converged there."""
    cfg = copy.deepcopy(ref_cfg)
    cfg.time.newton_increment_tol = tol
    cfg.time.newton_iterations = cap
    cfg.time.max_substeps = 1
    sim = build_simulator(cfg.validate(), comm)
    it = sim.integrator
    out = {}
    try:
        for f in sorted(frames):
            x, v, t, rest_edge, stop = states[f]
            it.x, it.v, it.t, it.frame, it.rest_edge = x.copy(), v.copy(), t, f, rest_edge.copy()
            sim.step()
            local = np.linalg.norm(it.x - stop, axis=1) / it.wisp_length
            out[f] = {"distance": comm.allreduce(float(local.max(initial=0.0)), op=MPI.MAX),
                      "reference_converged": bool(it.newton_converged[-1])}
    finally:
        sim.close()
    return out


def summarize(rows, first=30):
    """Median (all frames and the first ``first``), worst, total, frames converged and
    cut back of one run's rows; a frame not converged counts with its iterations."""
    its = [r["iterations"] for r in rows]
    return {"frames": len(rows), "median": statistics.median(its),
            f"median_first{first}": statistics.median(its[:first]), "worst": max(its),
            "worst_frame": its.index(max(its)), "total": sum(its),
            "converged": sum(r["converged"] for r in rows),
            "cut_back": sum(r["substeps"] > 1 for r in rows),
            "chord_checks": sum(r["chord_checks"] for r in rows),
            "cpu_s": sum(r["cpu_s"] for r in rows)}
