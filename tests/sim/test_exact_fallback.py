"""``solver.exact_fallback = "shifted"`` (docs/newton.md "Seventh round"): a failed exact
step of ``exact_or_analytic`` (CG finds the matrix indefinite, or Armijo fails within
its halvings, e.g. an ascent direction) is retried with the exact Hessian + tau M/dt^2
before the analytic filter's step: the shifted matrix, the config errors and a
convergence bound that the analytic fallback fails.  Rank invariance:
tests/sim/test_mpi_sim.py."""

import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.config import ConfigError, SolverConfig
from lc_petsc.integrator import EXACT_SHIFTS
from lc_petsc.simulator import build_simulator
from sim_helpers import small_hairball_config

COMM = MPI.COMM_WORLD


def _dense(it):
    A = it.asm.mat
    rows = np.arange(A.getSize()[0], dtype=np.int32)
    return A.getValues(rows, rows)


def test_shifted_matrix_is_exact_plus_tau_mass():
    """The shifted Newton matrix is the exact one plus tau M/dt^2 on the free vertices'
    diagonal, and nothing else (the pinned rows stay identity); the gradient is the
    same.  (No shift is promised to make the matrix positive definite: after this
    frame's 3 iterations its smallest eigenvalue is -1.5e6, against M/dt^2 ~ 2e3; a
    shifted step that CG or Armijo rejects is followed by the next shift, then by the
    analytic step.)"""
    cfg = small_hairball_config(n_wisps=2, frames=1)
    cfg.solver.filter = "exact_or_analytic"
    sim = build_simulator(cfg.validate(), COMM)
    try:
        sim.step()
        it = sim.integrator
        g0 = it._assemble_system(it.x, 0, filter="none")
        A0 = _dense(it)
        g1 = it._assemble_system(it.x, 0, filter="none", shift=2.5)
        A1 = _dense(it)
        d = np.repeat(np.where(it.free, 2.5 * sim.scene.mass / it.dt ** 2, 0.0), 3)
        assert np.abs(A1 - A0 - np.diag(d)).max() <= 1e-9 * np.abs(A0).max()
        assert np.array_equal(g0, g1)
        pin = np.repeat(~it.free, 3)
        assert np.array_equal(A1[np.ix_(pin, pin)], np.eye(pin.sum()))
    finally:
        sim.close()


def test_exact_fallback_config_errors():
    with pytest.raises(ConfigError, match="solver.exact_fallback must be one of"):
        SolverConfig(filter="exact_or_analytic", exact_fallback="filtered").validate()
    with pytest.raises(ConfigError, match="set that filter or drop solver.exact_fallback"):
        SolverConfig(filter="analytic", exact_fallback="shifted").validate()
    SolverConfig(filter="exact_or_analytic", exact_fallback="shifted").validate()


def _run(fallback):
    cfg = small_hairball_config(n_wisps=5, frames=4, newton_iterations=30,
                                newton_increment_tol=1e-6, newton_update="corotational",
                                max_substeps=1, carry_with_head=False)   # the frame 0 measured
    cfg.solver.filter = "exact_or_analytic"
    cfg.solver.exact_fallback = fallback
    sim = build_simulator(cfg.validate(), COMM)
    sim.integrator.history = rows = []
    try:
        for _ in range(4):
            sim.step()
        return sim.summary(), rows
    finally:
        sim.close()


def test_shifted_fallback_converges_where_the_analytic_one_stalls():
    """The 5-wisp shaking hairball, exact_or_analytic + corotational, 1e-6 wisp lengths,
    cap 30, no cutback.  With the analytic fallback frame 0 (the head's impulsive start)
    misses the tolerance: from iteration 10 on every exact step fails Armijo and the
    filtered steps converge linearly (measured: 30 iterations, 20 fallbacks; frames 1-3
    13 11 16).  One exact step shifted by M/dt^2 (tau = 1, iteration 10) had got it
    back to the quadratic phase, frame 0 in 18 and frames 1-3 in 11 11 13, but frame 0's
    point was a saddle of G (lowest eigenvalue -1.89), refused.  Now the wisps whose exact
    block is indefinite get their own shift (1.5x the least that makes the block definite),
    and every frame converges, frame 0 in 21 at the step's minimum (G 5.833e5 against the
    saddle's 6.067e5; lowest eigenvalue 0.27).  With exact steps searched wisp by wisp
    (and an exact step after every exact one kept) two shifted steps (3.07 and 1.18
    M/dt^2 at iterations 10 and 12; before it three, and frames 1-3 in 12 17 13), frames
    1-3 in 12 11 13 from its state (bounds 22 and 13)."""
    summ, rows = _run("shifted")
    assert summ["newton_converged"] == [True] * 4 and summ["newton_saddle"] == [0] * 4
    assert summ["newton_increment"][0] < 1e-6
    assert summ["newton_iterations"][0] <= 22 and max(summ["newton_iterations"][1:]) <= 13
    shifted = [(r["frame"], r["exact_shift"]) for r in rows if r["exact_shift"]]
    # per-wisp shifts, not the fallback ladder's: no exact step failed
    assert [f for f, _ in shifted] == [0, 0] and not any(tau in EXACT_SHIFTS for _, tau in shifted)
    assert summ["newton_exact_fallbacks"] == [0] * 4
    ref, _ = _run("analytic")
    assert ref["newton_converged"][0] is False and ref["newton_exact_fallbacks"][0] >= 10
    assert summ["newton_iterations"][0] < ref["newton_iterations"][0] == 30
    assert sum(summ["newton_iterations"]) < sum(ref["newton_iterations"])


@pytest.mark.mpi
def test_an_exact_solve_stopped_at_its_cap_is_a_failed_exact_step_not_the_end_of_the_run():
    """An exact attempt whose CG stops at its iteration cap (DIVERGED_MAX_IT) falls back as
    one CG finds indefinite does (the shift ladder, then the filtered step): it had ended
    the run with a SolverError (scripts/extremes.py's stiffness ratio 1e6 to 1e-6, frame 7:
    1000 CG iterations on a shifted block barely definite).  Here every unshifted exact
    solve is made to stop so (the real solve run, its reason replaced); the 3-wisp shake
    still converges every frame, and the stopped solves are not recorded."""
    from lc_petsc.errors import SolverError
    cfg = small_hairball_config(n_wisps=3, frames=2, newton_iterations=30, newton_increment_tol=1e-6,
                                newton_update="corotational")
    cfg.solver.filter, cfg.solver.exact_fallback = "exact_or_analytic", "shifted"
    sim = build_simulator(cfg.validate(), COMM)
    it = sim.integrator
    real_system, real_solve = it._exact_system, it.solver.solve
    flag, stopped = [False], []

    def exact_system(x, i, shift):
        flag[0] = np.ndim(shift) == 0 and shift == 0.0
        return real_system(x, i, shift)

    def solve(b, x, frame, newton_it):
        stop, flag[0] = flag[0], False
        its = real_solve(b, x, frame, newton_it)
        if stop:
            it.solver.reasons[-1] = "DIVERGED_MAX_IT"
            stopped.append(frame)
            raise SolverError("stopped at the cap (emulated)", reason=-3)
        return its

    it._exact_system, it.solver.solve = exact_system, solve
    try:
        sim.run(2)
        summ = sim.summary()
    finally:
        sim.close()
    assert sorted(set(stopped)) == [0, 1] and len(stopped) >= 4
    assert summ["newton_converged"] == [True, True]
    assert "DIVERGED_MAX_IT" not in it.solver.reasons


def test_newton_frames_study_starts_every_variant_from_the_reference_states():
    """scripts/newton_frames.py's study (lc_petsc/studies/newton_frames.py) on 2 frames of
    the 5-wisp hairball: the reference converges, both variants restart frame 1 from the
    reference's state (so the analytic fallback's stall in frame 0 does not reach it),
    the iterate is within the tolerance of the reference solution one iteration before
    the increment test says so (quadratic phase: the test's step certifies the previous
    iterate), and only the shifted variant takes shifted steps (frame 0)."""
    from lc_petsc.studies.newton_frames import compare
    cfg = small_hairball_config(n_wisps=5, frames=2)
    spec = "filter=exact_or_analytic,update=corotational"
    res = compare(cfg, [("analytic", spec), ("shifted", spec + ",fallback=shifted")], COMM, 2)
    # frame 0 (from rest): the shifted fallback's reference and variant had stopped on a
    # saddle of G (lowest eigenvalue -1.78), refused; with the indefinite wisps shifted
    # they reach the step's minimum (docs/newton.md "Avoiding the saddle")
    assert res["reference_saddle"] == [False, False] and res["reference_converged"]
    a, s = res["analytic"], res["shifted"]
    assert not a[0]["converged"] and not a[0]["saddle"] and s[0]["converged"] and not s[0]["saddle"]
    assert s[1]["converged"] and a[1]["converged"]
    assert a[1]["iterations"] == s[1]["iterations"] and a[1]["errors"] == s[1]["errors"]
    for r in (a[1], s[0], s[1]):
        assert r["true"] == r["iterations"] - 1, r
        assert r["errors"][-1] < 1e-9 and r["first_error"] > 1e-3
    assert s[0]["shifted_steps"] >= 1 and a[0]["shifted_steps"] == 0 == s[1]["shifted_steps"]
