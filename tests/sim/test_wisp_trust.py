"""``solver.wisp_trust``: a trust region per wisp on the shifted fallback's exact steps
(lc_petsc/wisp_trust.py, docs/newton.md "A trust region per wisp")."""

from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc import wisp_trust
from lc_petsc.config import load_config
from lc_petsc.errors import ConfigError
from lc_petsc.simulator import build_simulator

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def test_a_cut_step_raises_the_shift_and_a_step_on_its_model_drops_it():
    """Per wisp: cut to alpha 1/4 at tau 0.5 along a step of Rayleigh quotient q = -g.dx /
    dx^T M dx / dt^2 = 2: 0.5 + 2 (4 - 1) = 6.5; uncut on its model (rho 1.05): 0; uncut
    off it (rho 0.5) at tau 2: 0.5, at tau 0.4: 0.1, below the floor 0.2: 0."""
    tau = np.array([0.5, 3.0, 2.0, 0.4])
    alpha = np.array([0.25, 1.0, 1.0, 1.0])
    slope = np.array([-2.0, -1.0, -1.0, -1.0])
    mass_norm = np.array([1.0, 1.0, 1.0, 1.0])
    rho = np.array([0.3, 1.05, 0.5, 0.5])
    assert wisp_trust.next_shifts(tau, alpha, slope, mass_norm, rho).tolist() == [6.5, 0.0, 0.5, 0.0]
    # a pinned-only wisp (no mass norm) keeps no shift
    assert wisp_trust.next_shifts([1.0], [0.5], [0.0], [0.0], [1.0]).tolist() == [1.0]


def test_the_model_ratio_of_a_damped_step_and_of_round_off():
    """rho = decrease / -(alpha g.dx + alpha^2 / 2 dx^T H dx): slope -4, curvature 4,
    alpha 1/2: predicted 2 - 0.5 = 1.5, a decrease of 0.75 gives 0.5; a predicted
    decrease below 1e-10 of the wisp's share is round-off: 1."""
    rho = wisp_trust.model_ratio(np.array([0.75, 1e-9]), np.array([-4.0, -1e-8]), np.array([4.0, 1e-8]),
                                 np.array([0.5, 1.0]), np.array([10.0, 1e3]), 1e-10)
    assert rho.tolist() == [0.5, 1.0]


def test_exact_steps_wait_for_filtered_steps_that_do_not_undo_each_other():
    """The switch to exact steps (increments below 1e-2): after one step only below 3e-3,
    after two only if the second is below half the first (a frame's first two steps from
    the inertial first iterate undo each other: 6.0e-2, 4.8e-2 on the demo), after more
    always."""
    assert [wisp_trust.exact_switch(m) for m in ([], [5e-3], [2e-3], [6e-2, 4.8e-2], [6e-2, 1.3e-2],
                                                 [1e-2, 9e-3, 8e-3])] == [False, False, True, False, True, True]


def _hairball10(tol=1e-6, cap=30, trust=True):
    """configs/hairball_demo.toml cut to 10 wisps without strand contact (hairball10 of
    docs/newton.md), frame 0 from rest on the recommended path (exact_or_analytic,
    corotational, shifted fallback, exact_stay) at full dt, with ``solver.wisp_trust``."""
    cfg = load_config(CONFIGS / "hairball_demo.toml")
    cfg.scene.n_wisps = 10
    cfg.physics.terms = tuple(t for t in cfg.physics.terms if t != "strand_collision")
    cfg.time.initial_guess, cfg.time.length_projection = "inertial", False
    cfg.time.frames, cfg.time.max_substeps, cfg.time.newton_iterations = 1, 1, cap
    cfg.time.newton_increment_tol = tol
    cfg.solver.filter, cfg.time.newton_update = "exact_or_analytic", "corotational"
    cfg.solver.exact_fallback, cfg.solver.exact_stay, cfg.solver.wisp_trust = "shifted", True, trust
    cfg.output.usd = False
    return cfg.validate()


def _frame_0(cfg, comm):
    sim = build_simulator(cfg, comm)
    try:
        sim.run()
        it = sim.integrator
        # the step's potential at the end state, from the same start (from rest: xhat = x_0)
        it.xhat, it.dt, it.t_next = sim.scene.x_rest.copy(), cfg.time.dt, cfg.time.dt
        return sim.summary(), it.x.copy(), it.incremental_potential(it.x), it.wisp_length
    finally:
        sim.close()


@pytest.mark.mpi
def test_hairball10_frame_0_reaches_its_minimum_in_15_iterations():
    """hairball10's frame 0 from rest, the worst frame of the recommended path (21
    iterations without the option: damped and shifted exact steps, each followed by
    filtered ones): 15, the same minimum (G 1.1388833574e6), within 1e-6 wisp lengths
    of the same step solved to 1e-10, the same on 1, 2 and 3 ranks."""
    comm = MPI.COMM_WORLD
    s, x, G, length = _frame_0(_hairball10(), comm)
    assert s["newton_converged"] == [True] and s["newton_saddle"] == [0] and s["newton_substeps"] == [1]
    assert s["newton_iterations"] == [15]
    assert abs(G - 1.1388833574e6) < 1.0
    ref, x_ref, G_ref, _ = _frame_0(_hairball10(tol=1e-10, cap=60), comm)
    assert ref["newton_converged"] == [True] and ref["newton_saddle"] == [0]
    error = comm.allreduce(float(np.max(np.linalg.norm(x - x_ref, axis=1) / length)), MPI.MAX)
    assert error < 1e-6
    assert abs(G - G_ref) < 1e-6 * abs(G_ref)
    assert comm.allgather(s["newton_iterations"]) == [[15]] * comm.size


def test_wisp_trust_needs_the_shifted_fallback_and_no_strand_contact():
    """The option carries the shifted fallback's per-wisp shifts of exact steps searched
    wisp by wisp: refused with the analytic fallback, with strand contact (which couples
    the wisps), and for a value that is not a boolean."""
    cfg = _hairball10()
    cfg.solver.exact_fallback = "analytic"
    with pytest.raises(ConfigError, match="solver.wisp_trust = true carries the per-wisp shifts"):
        cfg.validate()
    cfg = _hairball10()
    cfg.physics.terms = cfg.physics.terms + ("strand_collision",)
    with pytest.raises(ConfigError, match="strand contact couples; remove strand_collision"):
        cfg.validate()
    cfg = _hairball10()
    cfg.solver.wisp_trust = "yes"
    with pytest.raises(ConfigError, match="solver.wisp_trust must be true or false, got 'yes'"):
        cfg.validate()


def test_hairball10_50_frames_exact_steps_start_after_steps_that_are_not_undone():
    """hairball10 over its first 50 frames to 1e-6 with ``solver.wisp_trust`` and the chord
    stop (a trajectory; the head slows down in frames 40-50): no exact step starts right
    after the first filtered step above 3e-3, nor after a second step that undid the first
    (main: from frame 10 on, e.g. after 1.1e-2 and 9.3e-3); every frame converged at
    full dt; 337 iterations in all (main 340; one round-off flip allowed)."""
    cfg = _hairball10()
    cfg.time.frames, cfg.time.newton_stop = 50, "chord_estimate"
    sim = build_simulator(cfg.validate(), MPI.COMM_WORLD)
    sim.integrator.history = rows = []
    try:
        sim.run()
        s = sim.summary()
    finally:
        sim.close()
    assert all(s["newton_converged"]) and s["newton_substeps"] == [1] * 50
    for f in range(50):
        steps = [r for r in rows if r["frame"] == f]
        k = next(i for i, r in enumerate(steps) if r["exact"])
        measures = [r["increment"] for r in steps[:k]]
        assert k >= 3 or (k == 1 and measures[0] < 3e-3) or (k == 2 and measures[1] < 0.5 * measures[0]), (f, measures)
    assert sum(s["newton_iterations"]) <= 338
