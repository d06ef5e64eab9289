"""``-lc_newton_monitor``: a line per Newton iteration on rank 0 (like ``-snes_monitor``),
with the stopping measure the run uses, and nothing that changes the run."""

import re

import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.config import SolverConfig
from lc_petsc.errors import ConfigError
from lc_petsc.solver_plan import SolverPlan
from lc_petsc.simulator import build_simulator
from sim_helpers import run_positions, small_hairball_config

LINE = re.compile(r"  Newton frame (\d+) \(dt [0-9.e+-]+\) iteration (\d+): increment ([0-9.e+-]+)"
                  r"(?:, estimate ([0-9.e+-]+))?, (filtered|exact|trust region)[^,]*(?:, [^,]+)*, "
                  r"alpha ([0-9.e+-]+), KSP (\d+)(, limiter cut)?")
END = re.compile(r"  frame (\d+) \(dt ([0-9.e+-]+)\): (converged|NOT converged) after (\d+) iteration\(s\), "
                 r"measure ([0-9.e+-]+)(?: \(a stop [^)]*\))?")


@pytest.mark.parametrize("options, on", [
    ("", False), ("-lc_newton_monitor", True), ("-lc_newton_monitor true", True),
    ("-lc_newton_monitor 0", False), ("-lc_newton_monitor false", False),
])
def test_the_flag(options, on):
    assert SolverPlan.resolve(options).newton_monitor is on


def test_a_bad_value_names_the_option():
    with pytest.raises(ConfigError, match=r"-lc_newton_monitor 'maybe'.*without a value.*true / false"):
        SolverPlan.resolve("-lc_newton_monitor maybe")


def _monitored(capsys, options="-lc_newton_monitor", **time):
    config = small_hairball_config(n_wisps=3, frames=3, options=options, **time)
    capsys.readouterr()
    X, summary = run_positions(config, comm=MPI.COMM_WORLD)
    return X, summary, capsys.readouterr().out.splitlines()


@pytest.mark.mpi
def test_fixed_count_one_line_per_iteration_on_rank_0_only(capsys):
    X, summary, lines = _monitored(capsys)
    X0, _ = run_positions(small_hairball_config(n_wisps=3, frames=3), comm=MPI.COMM_WORLD)
    if MPI.COMM_WORLD.rank != 0:
        assert lines == []
        return
    parsed = [LINE.match(line) for line in lines if line.startswith("  Newton")]
    assert all(parsed) and len(parsed) == sum(summary["newton_iterations"]) == 9
    assert [(int(m[1]), int(m[2])) for m in parsed] == [(f, i) for f in range(3) for i in (1, 2, 3)]
    assert not any(END.fullmatch(line) for line in lines)    # no tolerance: no verdict
    # the last iteration's increment is what the summary reports for the frame
    last = [float(m[3]) for m in parsed if m[2] == "3"]
    np.testing.assert_allclose(last, summary["newton_increment"], rtol=1e-3)
    assert [int(m[7]) for m in parsed] == summary["ksp_iterations"]
    # and the monitor changes nothing
    np.testing.assert_array_equal(X, X0)


@pytest.mark.mpi
def test_to_a_tolerance_each_frame_ends_with_its_verdict(capsys):
    time = dict(newton_iterations=30, newton_increment_tol=1e-6, newton_update="corotational",
                max_substeps=1)
    config = small_hairball_config(n_wisps=3, frames=3, options="-lc_newton_monitor", **time)
    # the analytic fallback: the shifted one no longer stops on frame 0's saddle of G
    # (docs/newton.md "Avoiding the saddle"), whose refusal is shown here
    config.solver = SolverConfig(options="-lc_newton_monitor", filter="exact_or_analytic", exact_stay=True)
    capsys.readouterr()
    _, summary = run_positions(config, comm=MPI.COMM_WORLD)
    lines = capsys.readouterr().out.splitlines()
    if MPI.COMM_WORLD.rank != 0:
        assert lines == []
        return
    ends = [END.fullmatch(line) for line in lines if line.startswith("  frame")]
    assert all(ends) and [int(m[1]) for m in ends] == [0, 1, 2]
    # frame 0 (from rest) reaches the tolerance on a saddle of G: its stop is refused
    assert [m[3] == "converged" for m in ends] == summary["newton_converged"] == [False, True, True]
    assert summary["newton_saddle"] == [1, 0, 0] and ends[0][0].endswith("(a stop refused: a saddle of G)")
    last = [line for line in lines if line.startswith("  Newton frame 0 ")][-1]
    assert ", stop refused: a saddle of G (wisps " in last, last
    assert [int(m[4]) for m in ends] == summary["newton_iterations"]
    np.testing.assert_allclose([float(m[5]) for m in ends], summary["newton_increment"], rtol=1e-3)
    assert all(float(m[5]) < 1e-6 for m in ends)
    kinds = [LINE.match(line)[5] for line in lines if line.startswith("  Newton")]
    assert len(kinds) == sum(summary["newton_iterations"])
    assert "exact" in kinds and kinds[0] == "filtered"       # the switch to exact steps is shown



@pytest.mark.mpi
def test_a_saddles_wisps_are_named_in_the_scenes_order(capsys):
    """The partition renumbers wisps along a space-filling curve (-lc_wisp_order spatial,
    the default; the 3-wisp hairball's internal order is 2, 1, 0): the refused saddle's
    note named the internal numbers (wisps 1, 2 where the scene's, as in frames.h5, are
    0, 1)."""
    named = {}
    for order in ("input", "spatial"):
        options = f"-lc_newton_monitor -lc_wisp_order {order}"
        config = small_hairball_config(n_wisps=3, frames=1, options=options, newton_iterations=30,
                                       newton_increment_tol=1e-6, newton_update="corotational",
                                       max_substeps=1)
        config.solver = SolverConfig(options=options, filter="exact_or_analytic", exact_stay=True)
        capsys.readouterr()
        _, summary = run_positions(config, comm=MPI.COMM_WORLD)
        lines = capsys.readouterr().out.splitlines()
        assert summary["newton_saddle"] == [1]
        if MPI.COMM_WORLD.rank == 0:
            notes = [line for line in lines if "a saddle of G (wisps " in line]
            named[order] = notes[-1].split("(wisps ")[1].split(")")[0]
    if MPI.COMM_WORLD.rank == 0:
        assert named["spatial"] == named["input"] == "0, 1", named

def _run_lines(capsys, solver=None, **time):
    config = small_hairball_config(n_wisps=3, frames=2, options="-lc_newton_monitor", **time)
    if solver is not None:
        config.solver = solver
    capsys.readouterr()
    sim = build_simulator(config, comm=MPI.COMM_SELF)
    try:
        sim.run()
        return sim.summary(), list(sim.solver.iterations), capsys.readouterr().out.splitlines()
    finally:
        sim.close()


def test_a_certifying_estimate_is_shown(capsys):
    """With ``time.newton_stop = "chord_estimate"`` the certifying line shows the chord
    estimate, which the frame's verdict reports."""
    summary, ksp, lines = _run_lines(
        capsys, SolverConfig(options="-lc_newton_monitor", filter="exact_or_analytic",
                             exact_fallback="shifted", exact_stay=True),
        newton_iterations=30, newton_increment_tol=1e-6, newton_update="corotational",
        max_substeps=1, newton_stop="chord_estimate")
    parsed = [LINE.match(line) for line in lines if line.startswith("  Newton")]
    ends = [END.fullmatch(line) for line in lines if line.startswith("  frame")]
    assert all(parsed) and all(ends) and len(ends) == 2
    assert sum(summary["newton_chord_checks"]) >= 1
    estimates = [float(m[4]) for m in parsed if m[4] is not None]
    assert estimates == [float(m[5]) for m in ends] == pytest.approx(summary["newton_increment"], rel=1e-3)
    # every solve is a step's or a chord check's
    assert len(ksp) == len(parsed) + sum(summary["newton_chord_checks"])


def test_trust_region_steps_and_cutback_are_named(capsys):
    summary, _, lines = _run_lines(capsys, newton="trust_region", newton_iterations=30,
                                   newton_increment_tol=1e-6, max_substeps=1)
    kinds = [(LINE.match(line)[2], LINE.match(line)[5]) for line in lines if line.startswith("  Newton")]
    assert len(kinds) == sum(summary["newton_iterations"]) > 2
    # each frame's first step is filtered, the trust region takes over from the second
    assert all((k == "filtered") == (i == "1") for i, k in kinds) and ("2", "trust region") in kinds
    # a cap too small for frame 0 cuts it back: the discarded step is said, and every
    # kept step has its verdict with its own dt
    summary, _, lines = _run_lines(capsys, newton_iterations=2, newton_increment_tol=1e-9,
                                   max_substeps=2)
    discarded = [line for line in lines if "is discarded and redone as 2 steps of dt" in line]
    ends = [END.fullmatch(line) for line in lines if line.startswith("  frame") and line not in discarded]
    assert len(discarded) >= 1 and all(ends)
    assert len(ends) == len(discarded) + sum(summary["newton_substeps"])   # every attempt's verdict
    assert {float(m[2]) for m in ends} == {0.03333, 0.01667}
