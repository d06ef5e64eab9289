"""``-lc_newton_monitor``: a line per Newton iteration on rank 0 (like ``-snes_monitor``),
with the stopping measure the run uses, and nothing that changes the run."""

import re

import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.config import SolverConfig
from lc_petsc.errors import ConfigError
from lc_petsc.solver_plan import SolverPlan
from sim_helpers import run_positions, small_hairball_config

LINE = re.compile(r"  Newton frame (\d+) \(dt [0-9.e+-]+\) iteration (\d+): increment ([0-9.e+-]+)"
                  r"(?:, estimate ([0-9.e+-]+))?, (filtered|exact)")
END = re.compile(r"  frame (\d+): (converged|NOT converged) after (\d+) iteration\(s\), measure ([0-9.e+-]+)")


@pytest.mark.parametrize("options, on", [
    ("", False), ("-lc_newton_monitor", True), ("-lc_newton_monitor true", True),
    ("-lc_newton_monitor 0", False), ("-lc_newton_monitor false", False),
])
def test_the_flag(options, on):
    assert SolverPlan.resolve(options).newton_monitor is on


def test_a_bad_value_names_the_option():
    with pytest.raises(ConfigError, match=r"-lc_newton_monitor 'maybe'.*without a value.*true or false"):
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
    # and the monitor changes nothing
    np.testing.assert_array_equal(X, X0)


@pytest.mark.mpi
def test_to_a_tolerance_each_frame_ends_with_its_verdict(capsys):
    time = dict(newton_iterations=30, newton_increment_tol=1e-6, newton_update="corotational",
                max_substeps=1)
    config = small_hairball_config(n_wisps=3, frames=3, options="-lc_newton_monitor", **time)
    config.solver = SolverConfig(options="-lc_newton_monitor", filter="exact_or_analytic",
                                 exact_fallback="shifted", exact_stay=True)
    capsys.readouterr()
    _, summary = run_positions(config, comm=MPI.COMM_WORLD)
    lines = capsys.readouterr().out.splitlines()
    if MPI.COMM_WORLD.rank != 0:
        assert lines == []
        return
    ends = [END.fullmatch(line) for line in lines if line.startswith("  frame")]
    assert all(ends) and [int(m[1]) for m in ends] == [0, 1, 2]
    assert [m[2] == "converged" for m in ends] == summary["newton_converged"] == [True] * 3
    assert [int(m[3]) for m in ends] == summary["newton_iterations"]
    np.testing.assert_allclose([float(m[4]) for m in ends], summary["newton_increment"], rtol=1e-3)
    assert all(float(m[4]) < 1e-6 for m in ends)
    kinds = [LINE.match(line)[5] for line in lines if line.startswith("  Newton")]
    assert len(kinds) == sum(summary["newton_iterations"])
    assert "exact" in kinds and kinds[0] == "filtered"       # the switch to exact steps is shown
