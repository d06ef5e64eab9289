"""The paper's per-wisp block Jacobi, built fused (one factorisation of all of a rank's
wisps, the default) or separate (one PETSc block per wisp): the same preconditioner.

The premise of ``fused`` is that the preconditioning matrix never couples two wisps (the
strand-contact cross blocks live in the contact matrix C of the operator only); it is
checked here on a scene where contact couples wisps and CG needs tens of iterations."""

import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc

import lc_petsc.simulator as simmod
from lc_petsc.solver import LinearSolver
from lc_petsc.solver_plan import SolverPlan
from sim_helpers import small_hairball_config, touching_wisps_config, touching_wisps_source

N_WISPS = 6      # touching_wisps_source


@pytest.fixture
def touching(monkeypatch):
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: touching_wisps_source())


def run_recording(options, frames=10):
    """Run the touching wisps with strand contact; return (the solution of every linear
    solve, the KSP iterations per solve, contact pairs per frame, -ksp_view text)."""
    cfg = touching_wisps_config(frames, options)
    cfg.time.carry_with_head = False    # the frames measured (carried: 88 pairs, not > 100)
    sim = simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
    solutions = []
    solve = sim.solver.solve

    def recording_solve(b, x, frame, newton_it):
        its = solve(b, x, frame, newton_it)
        solutions.append(x.array.copy())
        return its

    sim.solver.solve = recording_solve
    try:
        sim.run()
        summ = sim.summary()
        view = ksp_view(sim.solver.ksp)
    finally:
        sim.close()
    return solutions, summ["ksp_iterations"], summ["contact"]["pairs_per_frame"], view


def ksp_view(ksp):
    viewer = PETSc.Viewer().createASCII("ksp_view.txt", comm=PETSc.COMM_SELF)
    ksp.view(viewer)
    viewer.destroy()
    with open("ksp_view.txt") as f:
        return f.read()


@pytest.mark.parametrize("pmat", ["same", "aij"])
def test_fused_and_separate_give_the_same_cg_iterations_and_iterates(touching, tmp_path,
                                                                      monkeypatch, pmat):
    """Same preconditioning matrix (the BAIJ operator's strand part, or its AIJ copy):
    the CG iteration counts are equal solve by solve and every solution agrees to
    round-off (they are bitwise equal in practice), over 30 contact-coupled solves."""
    monkeypatch.chdir(tmp_path)
    # the per-wisp blocks themselves (the default with contact grows them into clusters)
    opts = f"-ksp_rtol 1e-10 -ksp_max_it 5000 -lc_pmat_type {pmat} -lc_contact_pc strands"
    fused, its_f, pairs, view_f = run_recording(opts + " -lc_wisp_blocks fused")
    separate, its_s, pairs_s, view_s = run_recording(opts + " -lc_wisp_blocks separate")
    assert sum(pairs) > 100 and pairs == pairs_s
    assert len(its_f) == 30 and max(its_f) > 50 and sum(its_f) > 800, its_f
    assert its_f == its_s
    for a, b in zip(fused, separate):
        assert np.abs(a - b).max() <= 1e-12 * np.abs(b).max()
    # what -ksp_view shows: one block per rank (fused) or per wisp (separate)
    assert "type: bjacobi" in view_f and "number of blocks = 1" in view_f, view_f
    assert "number of blocks = 6" in view_s, view_s


def test_default_is_fused_on_the_operator_itself(touching, tmp_path, monkeypatch):
    """The default: fused blocks factored from the BAIJ operator's strand matrix (no AIJ
    copy) without strand contact, from its AIJ copy with strand contact and
    ``-lc_contact_pc strands`` (the per-wisp blocks without clusters; round-off of
    the block ILU, see lc_petsc.solver_plan._pmat_type); separate blocks get the AIJ copy (PETSc's
    BAIJ block extraction is quadratic in the wisp count).  Both reach the same
    trajectory to the CG tolerance."""
    monkeypatch.chdir(tmp_path)
    sims = [simmod.build_simulator(touching_wisps_config(3, "-ksp_rtol 1e-12 -ksp_max_it 5000 "
                                                         "-lc_contact_pc strands"
                                                         + extra), comm=MPI.COMM_SELF)
            for extra in ("", " -lc_wisp_blocks separate")]
    try:
        default, separate = sims
        assert default.solver.wisp_blocks == "fused" and default.assembler.pmat is not None
        assert "-lc_wisp_blocks fused" in default.solver.describe()
        assert default.solver.ksp.getOperators()[1].getType() == "seqaij"
        assert separate.solver.ksp.getOperators()[1].getType() == "seqaij"
        cfg = touching_wisps_config(1)
        cfg.physics.terms = tuple(t for t in cfg.physics.terms if t != "strand_collision")
        plain = simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
        try:
            assert plain.assembler.pmat is None
            assert plain.solver.ksp.getOperators()[1].getType() == "seqbaij"
        finally:
            plain.close()
        for sim in sims:
            sim.run()
        assert default.summary()["ksp_iterations"] == pytest.approx(
            separate.summary()["ksp_iterations"], abs=2)
        moved = np.abs(default.x - touching_wisps_source().load(0, N_WISPS).positions).max()
        assert moved > 0.1
        assert np.abs(default.x - separate.x).max() <= 1e-8 * moved
    finally:
        for sim in sims:
            sim.close()


def test_preconditioning_matrix_never_couples_two_wisps(touching):
    """The premise of ``fused``: with contact pairs between wisps, the operator couples
    wisps (C has blocks) but the preconditioning matrix has no entry outside the wisps'
    own diagonal blocks."""
    sim = simmod.build_simulator(touching_wisps_config(3), comm=MPI.COMM_SELF)
    try:
        sim.run()
        C = sim.strand.C
        assert C is not None and C.getInfo()["nz_used"] > 0
        P = sim.solver.ksp.getOperators()[1].convert("aij", PETSc.Mat())
        rowptr, cols, _ = P.getValuesCSR()
        P.destroy()
        wisp_of_dof = np.repeat(np.arange(N_WISPS), 3 * np.diff(sim.scene.offsets))
        rows = np.repeat(np.arange(len(rowptr) - 1), np.diff(rowptr))
        assert np.array_equal(wisp_of_dof[rows], wisp_of_dof[cols])
        rowptr, cols, _ = C.convert("aij", PETSc.Mat()).getValuesCSR()
        rows = np.repeat(np.arange(len(rowptr) - 1), np.diff(rowptr))
        assert np.any(wisp_of_dof[rows] != wisp_of_dof[cols])
    finally:
        sim.close()


def test_every_block_variant_applies_the_same_preconditioner():
    """One assembled Newton matrix (10-wisp hairball): the preconditioner applied to one
    vector by fused and separate blocks on BAIJ, AIJ and SBAIJ (MUMPS Cholesky
    sub-solves) agrees to round-off, and it is the exact inverse (A z = v)."""
    sim = simmod.build_simulator(small_hairball_config(n_wisps=10, frames=1), comm=MPI.COMM_SELF)
    try:
        sim.run()
        A = sim.assembler.mat
        rows = 3 * np.diff(sim.scene.offsets)
        v = A.createVecLeft()
        v.array[:] = np.cos(np.arange(v.getSize()))
        outputs = {}
        for mat_type in ("baij", "aij", "sbaij"):
            M = A.copy() if mat_type == "baij" else A.convert(mat_type, PETSc.Mat())
            for mode in ("fused", "separate"):
                plan = SolverPlan.resolve(f"-lc_wisp_blocks {mode} -mat_type {mat_type}")
                ls = LinearSolver(M, rows, plan)
                pc = ls.ksp.getPC()
                with plan.active():
                    ls.ksp.setUp()
                z = v.duplicate()
                pc.apply(v, z)
                outputs[mat_type, mode] = z.array.copy()
                ls.ksp.destroy()
            M.destroy()
        ref = outputs["baij", "separate"]
        diffs = {key: np.abs(z - ref).max() / np.abs(ref).max() for key, z in outputs.items()}
        assert max(diffs.values()) <= 1e-12, diffs
        Az = v.duplicate()
        z = v.duplicate()
        z.array[:] = ref
        A.mult(z, Az)
        # exact solve: normwise backward error at round-off
        backward = np.abs(Az.array - v.array).max() / (A.norm(PETSc.NormType.INFINITY)
                                                        * np.abs(ref).max())
        assert backward <= 1e-14
    finally:
        sim.close()


def test_unknown_wisp_block_mode_is_refused_with_the_choices():
    cfg = small_hairball_config(n_wisps=2, frames=1, options="-lc_wisp_blocks merged")
    with pytest.raises(ValueError, match=r"-lc_wisp_blocks 'merged': use fused .* or separate"):
        simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
