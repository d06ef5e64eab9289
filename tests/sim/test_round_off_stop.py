"""Newton's stop at the positions' round-off (docs/newton.md "Stops at round-off"):
an iterate whose steps are round-off is converged, whatever their rate and their line
searches say."""

import io

import numpy as np
from mpi4py import MPI

from lc_petsc.integrator import Integrator
from lc_petsc.newton_stop import ENERGY_FLOOR, ROUND_OFF_STEPS, round_off_floor
from lc_petsc.simulator import build_simulator
from sim_helpers import small_hairball_config


def _two_wisps(tol, cap):
    """Two hairball wisps, one frame, the recommended converging path with a line search
    on every step, tight linear solves."""
    cfg = small_hairball_config(n_wisps=2, frames=1, newton_increment_tol=tol, newton_iterations=cap,
                                max_substeps=1, options="-ksp_rtol 1e-14")
    cfg.solver.filter, cfg.solver.exact_fallback, cfg.solver.exact_stay = "exact_or_analytic", "shifted", True
    cfg.time.newton_update, cfg.time.line_search = "corotational", True
    return cfg.validate()


def _run(cfg, monkeypatch=None, first=None):
    """(positions, summary, monitor lines, wisp length per vertex) of ``cfg`` on this rank
    alone; ``first``: Newton's first iterate instead of the step's own."""
    if first is not None:
        step_start = Integrator._first_iterate
        monkeypatch.setattr(Integrator, "_first_iterate",
                            lambda self, dt, t_next: step_start(self, dt, t_next)[:1] + (first.copy(),)
                            + step_start(self, dt, t_next)[2:])
    sim = build_simulator(cfg, MPI.COMM_SELF)
    try:
        sim.integrator.monitor = io.StringIO()
        sim.run()
        return (sim.integrator.x.copy(), sim.summary(), sim.integrator.monitor.getvalue().splitlines(),
                sim.integrator.wisp_length)
    finally:
        sim.close()


def test_the_floor_is_epsilons_of_the_largest_coordinate():
    assert round_off_floor(26.4) == ROUND_OFF_STEPS * np.finfo(float).eps * 26.4
    assert round_off_floor(0.0) == 0.0


def test_a_newton_at_round_off_stops_though_its_line_searches_halve_at_noise(monkeypatch):
    """Newton started at its step's solution (a solve to 1e-12): every step is round-off.
    On the 2K hairball's frame 10 (docs/newton.md) such steps' line searches halved at
    the noise of G (alpha 0.25-0.5) and their increments bounced (5.2e-16 to 6.1e-16):
    main refused every claim at 1e-4 (a damped step is off its model, a rate that does
    not shrink is inf) for 14 iterations and cut the step back.  Here the line search's
    verdict is made that noise's (halved wherever the predicted decrease is below
    ENERGY_FLOOR |G|): main refused the first step's stop (damped: off its model), then
    bounced at 2.0e-16 to 4.9e-16 for six exact steps (no rate) and stopped at the eighth;
    the stop at round-off ends it after the first step, within 1e-14 of the tight solve."""
    reference, ref, _, length = _run(_two_wisps(1e-12, 60))
    assert ref["newton_converged"] == [True]
    search = Integrator._line_search

    def noisy(self, x, g, dx, *args, **kwargs):
        alpha = search(self, x, g, dx, *args, **kwargs)
        G0, slope = self._probe
        at_noise = abs(0.5 * slope) <= ENERGY_FLOOR * abs(G0)
        return 0.5 * alpha if at_noise and alpha is not None else alpha

    monkeypatch.setattr(Integrator, "_line_search", noisy)
    X, s, lines, _ = _run(_two_wisps(1e-4, 30), monkeypatch, first=reference)
    assert s["newton_converged"] == [True], lines
    assert s["newton_iterations"] == [1], lines                 # main: [8]
    assert "at round-off" in lines[0] and "alpha 0.5" in lines[0], lines
    assert (np.linalg.norm(X - reference, axis=1) / length).max() < 1e-14
