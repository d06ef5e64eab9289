"""Newton variants frame by frame from the same start states (docs/newton.md, seventh
round): a converged reference trajectory gives every frame's start state and solution;
each variant then solves each frame from that start state with a tolerance, so a
variant's count in frame n does not depend on where its own frame n - 1 ended (in a
trajectory run one frame ending elsewhere changes every later frame).  Per frame and
variant: the Newton iterations to the tolerance (the integrator's increment test), the
first iteration whose iterate is within the tolerance of the reference solution (the
true error, relative to the wisp length), the exact steps taken and the first iterate's
error.  Used by ``scripts/newton_frames.py``.  One rank.
"""

from __future__ import annotations

import copy

import numpy as np

from lc_petsc.simulator import build_simulator
from lc_petsc.studies.newton import configure, parse_variant, watch_iterates


def _tolerance(cfg, tol, cap, stop="increment"):
    cfg = copy.deepcopy(cfg)
    cfg.time.newton_stop = stop
    cfg.time.newton_increment_tol = tol
    cfg.time.newton_iterations = cap
    cfg.time.max_substeps = 1
    return cfg.validate()


def reference_states(cfg, comm, frames, tol=1e-9, cap=60):
    """The start state (x, v, t) of frames 0..frames-1 and the final positions of a run
    of ``cfg`` converged to ``tol`` (``cap`` iterations, no cutback): ``frames + 1``
    entries, entry n + 1's positions being frame n's solution.  Also returns whether every
    frame converged and, per frame, whether its stop was refused on a saddle of G (then
    that frame's solution is the saddle, a stationary point but not a minimum:
    docs/newton.md "Saddles of G")."""
    sim = build_simulator(_tolerance(cfg, tol, cap), comm)
    it = sim.integrator
    states = []
    try:
        for _ in range(frames):
            states.append((it.x.copy(), it.v.copy(), it.t))
            sim.step()
        states.append((it.x.copy(), it.v.copy(), it.t))
        converged = all(bool(c) for c in it.newton_converged)
        saddles = [bool(n) for n in it.newton_saddle]
    finally:
        sim.close()
    return states, converged, saddles


def frame_iterations(cfg, comm, states, tol=1e-6, cap=30, stop="increment"):
    """Each frame of ``states`` (:func:`reference_states`) solved by ``cfg`` from its start
    state to ``tol`` (``time.newton_stop`` ``stop``), cap ``cap``, no cutback.  Rows (dicts) per frame: iterations,
    converged, ``true`` (first iteration, 1-based, whose iterate is within ``tol`` of the
    reference solution; None: none), exact steps, the first iterate's error and the
    errors after each iteration (relative to the wisp length), and ``saddle``: its stop was
    refused on a saddle of G (docs/newton.md "Saddles of G")."""
    if comm.size != 1:
        raise ValueError("frame_iterations runs on one rank")
    sim = build_simulator(_tolerance(cfg, tol, cap, stop), comm)
    it = sim.integrator
    it.history = hist = []
    errors: list = []
    watch_iterates(it, lambda x: errors.append(
        float(np.max(np.linalg.norm(x - states[it.frame + 1][0], axis=1) / it.wisp_length))))
    rows = []
    try:
        for f in range(len(states) - 1):
            x, v, t = states[f]
            it.x, it.v, it.t, it.frame = x.copy(), v.copy(), t, f
            errors.clear()
            sim.step()
            within = [k for k, e in enumerate(errors) if k > 0 and e < tol]
            rows.append({"frame": f, "iterations": it.newton_iterations[-1],
                         "converged": bool(it.newton_converged[-1]), "saddle": bool(it.newton_saddle[-1]),
                         "true": within[0] if within else None,
                         "exact_steps": sum(r["exact"] for r in hist if r["frame"] == f),
                         "shifted_steps": sum(r["exact_shift"] > 0 for r in hist if r["frame"] == f),
                         "first_error": errors[0], "errors": errors[1:]})
    finally:
        sim.close()
    return rows


def compare(base_cfg, variants, comm, frames, tol=1e-6, cap=30, reference="filter=exact_or_analytic,"
            "update=corotational,fallback=shifted"):
    """:func:`frame_iterations` for each (name, SPEC) of ``variants`` (SPEC as in
    scripts/newton_history.py, and ``stop=quadratic_estimate`` or ``stop=chord_estimate``: ``time.newton_stop``,
    which needs the tolerance) from the states of the ``reference`` SPEC's converged run.
    Returns {"reference_converged": bool, "reference_saddle": per frame, whether the
    reference's stop was refused on a saddle of G, name: rows}."""
    ref = configure(base_cfg, parse_variant(reference), 1, frames)
    states, ok, saddles = reference_states(ref, comm, frames)
    out: dict = {"reference_converged": ok, "reference_saddle": saddles}
    for name, spec in variants:
        variant = parse_variant(spec)
        stop = variant.pop("stop", "increment")
        out[name] = frame_iterations(configure(base_cfg, variant, cap, frames),
                                     comm, states, tol, cap, stop)
    return out
