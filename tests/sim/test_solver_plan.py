"""The solver plan (lc_petsc/solver_plan.py): options layered once, derived choices, no
option leaking from one scope (a run, a solver set) into the next, options prefixes."""

import dataclasses
import os

import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc

from lc_petsc import simulator as simmod
from lc_petsc.batch import main
from lc_petsc.errors import ConfigError, SolverError
from lc_petsc.solver import LinearSolver
from lc_petsc.solver_plan import SolverPlan, command_line_options
from sim_helpers import hairball_toml, small_hairball_config, touching_wisps_config, touching_wisps_source


def _identity(n=6):
    A = PETSc.Mat().createAIJ((n, n), nnz=1, comm=MPI.COMM_SELF)
    for i in range(n):
        A.setValue(i, i, 2.0)
    A.assemble()
    return A


def test_a_run_in_process_leaves_the_options_database_as_it_found_it(tmp_path):
    """A command-line option that overrides one already in the database (PETSC_OPTIONS,
    an earlier init) is restored after the run, and one it adds is removed: a second run
    in the same process never inherits the first one's options."""
    opts = PETSc.Options()
    opts.setValue("ksp_rtol", "1e-9")
    try:
        before = opts.getAll()
        (tmp_path / "s.toml").write_text(hairball_toml(n_wisps=2, frames=1))
        cwd = os.getcwd()
        try:
            os.chdir(tmp_path)
            code = main(["s.toml", "--out", "o", "--quiet", "--frames", "0",
                         "-ksp_rtol", "1e-3", "-ksp_atol", "1e-40"], comm=MPI.COMM_SELF)
        finally:
            os.chdir(cwd)
        assert code == 0
        assert opts.getAll() == before
        assert opts.getString("ksp_rtol") == "1e-9"
    finally:
        opts.delValue("ksp_rtol")


def test_command_line_layer_restores_changed_and_removes_added_values():
    opts = PETSc.Options()
    opts.setValue("ksp_max_it", "7")
    try:
        with command_line_options({"ksp_max_it": "9", "ksp_atol": "1e-40"}) as given:
            assert opts.getString("ksp_max_it") == "9" and opts.getString("ksp_atol") == "1e-40"
            assert given["ksp_max_it"] == "9" and given["ksp_atol"] == "1e-40"
        assert opts.getString("ksp_max_it") == "7"
        assert not opts.hasName("ksp_atol")
    finally:
        opts.delValue("ksp_max_it")


def test_one_solver_set_never_sees_the_previous_sets_options():
    """Two sets one after the other (as in drivers/compare_solvers.py): the first set's
    options are in the database only while its solver reads them."""
    A = _identity()
    db_before = PETSc.Options().getAll()
    first = SolverPlan.resolve("-ksp_type gmres -pc_type jacobi -lc_pmat_type same")
    ls1 = LinearSolver(A, [6], first)
    assert ls1.ksp.getType() == "gmres" and ls1.ksp.getPC().getType() == "jacobi"
    assert first.wisp_blocks is None
    assert PETSc.Options().getAll() == db_before
    second = SolverPlan.resolve("")
    ls2 = LinearSolver(A, [6], second)
    assert ls2.ksp.getType() == "cg" and ls2.ksp.getPC().getType() == "bjacobi"
    assert second.wisp_blocks == "fused" and second.pc_type == "bjacobi"
    assert second.options_used({}, "baij")["ksp_type"] == "cg"
    for ls in (ls1, ls2):
        ls.destroy()
    A.destroy()


def test_plan_is_frozen_and_derives_the_choices():
    p = SolverPlan.resolve("-pc_type cholesky -pc_factor_mat_solver_type mumps -ksp_type preonly")
    assert (p.mat_type, p.pmat_type, p.wisp_blocks, p.contact_pc) == ("sbaij", None, None, None)
    assert dict(p.sub_solver) == {"sub_pc_type": "cholesky", "sub_pc_factor_mat_solver_type": "mumps"}
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.mat_type = "aij"
    with pytest.raises(TypeError):
        p.options["ksp_type"] = "gmres"
    s = SolverPlan.resolve("-lc_wisp_blocks separate", strand_contact=True)
    assert (s.mat_type, s.pmat_type, s.wisp_blocks, s.contact_pc) == ("baij", "aij", "separate", "strands")
    g = SolverPlan.resolve("-pc_type gamg", strand_contact=True)
    assert (g.mat_type, g.pmat_type, g.contact_pc) == ("aij", None, "coupled")
    # the command line (the database) wins over the config
    PETSc.Options().setValue("pc_type", "gamg")
    try:
        assert SolverPlan.resolve("-pc_type bjacobi").mat_type == "aij"
    finally:
        PETSc.Options().delValue("pc_type")


@pytest.mark.parametrize("options, message", [
    ("-lc_pmat_type dense", r"-lc_pmat_type 'dense': use aij or same"),
    ("-lc_wisp_blocks merged", r"-lc_wisp_blocks 'merged': use fused"),
    ("-pc_type gamg -mat_type baij", r"GAMG does not accept BAIJ"),
    ("ksp_type cg", r"expected an option starting with '-'"),
])
def test_option_errors_are_configuration_errors(options, message):
    with pytest.raises(ConfigError, match=message):
        SolverPlan.resolve(options)


def test_contact_option_errors_only_with_strand_contact():
    with pytest.raises(ConfigError, match=r"-lc_contact_pc 'both'"):
        SolverPlan.resolve("-lc_contact_pc both", strand_contact=True)
    with pytest.raises(ConfigError, match=r"-ksp_type preonly would not solve"):
        SolverPlan.resolve("-ksp_type preonly", strand_contact=True)
    assert SolverPlan.resolve("-lc_contact_pc both").contact_pc is None


def test_prefixed_plan_reads_and_writes_only_its_own_options():
    """With a prefix the KSP (and the plan's choices) read ``-<prefix>...`` options; the
    config options go in under the prefix and the unprefixed ones stay untouched."""
    opts = PETSc.Options()
    opts.setValue("cmp_ksp_type", "gmres")
    opts.setValue("ksp_type", "bicg")
    A = _identity()
    try:
        plan = SolverPlan.resolve("-pc_type jacobi -ksp_max_it 17", prefix="cmp_")
        assert plan.pc_type == "jacobi" and plan.wisp_blocks is None
        ls = LinearSolver(A, [6], plan)
        assert ls.ksp.getOptionsPrefix() == "cmp_"
        assert ls.ksp.getType() == "gmres" and ls.ksp.getPC().getType() == "jacobi"
        assert ls.ksp.getTolerances()[3] == 17
        assert not opts.hasName("cmp_pc_type") and opts.getString("ksp_type") == "bicg"
        assert plan.unused_options(["cmp_ksp_type"]) == []
        ls.destroy()
    finally:
        opts.delValue("cmp_ksp_type")
        opts.delValue("ksp_type")
        A.destroy()


def test_solver_error_carries_the_converged_reason():
    cfg = small_hairball_config(n_wisps=2, frames=1, options="-pc_type none -ksp_max_it 2 -ksp_rtol 1e-14")
    sim = simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
    try:
        with pytest.raises(SolverError) as e:
            sim.run()
        assert e.value.reason == PETSc.KSP.ConvergedReason.DIVERGED_MAX_IT
    finally:
        sim.close()


@pytest.mark.parametrize("time, options, rtol", [
    ({}, "", 1e-4),                                   # the paper's fixed count: truncated
    ({"newton_increment_tol": 1e-6}, "", 1e-6),       # Newton asked to converge
    ({"newton_tol": 1e-7}, "", 1e-6),
    ({}, "-ksp_rtol 1e-8", 1e-8),                     # the options win either way
    ({"newton_increment_tol": 1e-6}, "-ksp_rtol 1e-3", 1e-3),
])
def test_default_ksp_rtol_follows_the_newton_stopping_rule(time, options, rtol):
    sim = simmod.build_simulator(small_hairball_config(n_wisps=2, frames=1, options=options, **time),
                                 comm=MPI.COMM_SELF)
    try:
        assert sim.solver.ksp.getTolerances()[0] == rtol
        assert float(sim.plan.options_used({}, "baij")["ksp_rtol"]) == rtol
        assert f"-ksp_rtol {rtol:g} " in sim.solver.describe()      # the run's log and summary say it
    finally:
        sim.close()


def test_truncated_newton_loose_default_solve_costs_less_accuracy_than_its_truncation(monkeypatch):
    """One frame of the touching wisps (strand contact, the per-wisp blocks blind to it,
    so CG iterates): the fixed-count default -ksp_rtol (1e-4) lies far closer to the
    frame solved to 1e-12 than a fourth Newton iteration moves it, so the linear error
    is not what limits a truncated Newton's accuracy.  Measured when written: 2.9e-3
    against 0.23 cm; -ksp_rtol 1e-2 (0.27 cm) and 1e-1 (0.33 cm) break the bound."""
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: touching_wisps_source())

    def positions(options, newton_iterations=3):
        cfg = touching_wisps_config(1, "-lc_contact_pc strands " + options)
        cfg = dataclasses.replace(cfg, time=dataclasses.replace(cfg.time, newton_iterations=newton_iterations))
        sim = simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
        try:
            sim.run()
            return sim.gather_positions(), sim.solver.iterations
        finally:
            sim.close()

    tight, tight_its = positions("-ksp_rtol 1e-12 -ksp_max_it 5000")
    loose, loose_its = positions("")
    one_more, _ = positions("-ksp_rtol 1e-12 -ksp_max_it 5000", newton_iterations=4)
    linear_error = np.abs(loose - tight).max()
    truncation = np.abs(one_more - tight).max()
    assert max(loose_its) > 10                      # CG really iterates here
    assert sum(loose_its) < sum(tight_its)          # ... and the default saves iterations
    assert linear_error < 0.1 * truncation, (linear_error, truncation)
