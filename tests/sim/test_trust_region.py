"""Trust-region Newton (``time.newton = "trust_region"``, lc_petsc/trust_region.py,
docs/newton.md fifth round): the PETSc trust-region CG's figures the radius update
relies on, an iteration bound on the smashed wisp that the filtered Newton fails, the
rank count changing nothing, and configuration errors."""

from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.config import ConfigError, load_config
from lc_petsc.simulator import build_simulator
from lc_petsc.trust_region import ratio, update_radius
from sim_helpers import rel_diff, run_positions, serial_reference, small_hairball_config

COMM = MPI.COMM_WORLD
ROOT = Path(__file__).resolve().parents[2]
TOL = 1e-6


def _smash(newton="trust_region", filter="analytic", frames=1, cap=30):
    cfg = load_config(ROOT / "configs" / "smash.toml")
    cfg.time.frames, cfg.time.newton_iterations = frames, cap
    cfg.time.newton_increment_tol, cfg.time.max_substeps = TOL, 1
    cfg.time.newton, cfg.solver.filter = newton, filter
    return cfg.validate()


def test_stcg_figures_are_the_model_and_the_euclidean_step_length():
    """KSPCGGetObjFcn is q(d) = g . d + 1/2 d^T H d and KSPCGGetNormD the 2-norm of the
    step (PETSc 3.18), on and inside the boundary, at the smashed wisp's first iterate
    (where the exact matrix is indefinite: CG stops on the boundary)."""
    sim = build_simulator(_smash(), comm=MPI.COMM_SELF)
    try:
        I, tr = sim.integrator, sim.trust
        I.dt, I.t_next = sim.config.time.dt, sim.config.time.dt
        I.xhat = I.x + I.dt * I.v
        x = I.xhat.copy()
        I._assemble_system(x, 0)
        I.asm.mat.copy(tr.P, structure=tr.P.Structure.SAME_NONZERO_PATTERN)
        g = I._assemble_system(x, 0, filter="none")
        b, d = I.bv, I.xv
        b.array[:] = -g.ravel()
        r0 = tr.filtered_step_norm(b)
        assert r0 > 0
        Ad = d.duplicate()
        seen = set()
        for radius in (1e-3 * r0, r0, 1e6 * r0):
            predicted, norm_d, boundary = tr.solve(b, d, radius, 0, 0)
            I.asm.mat.mult(d, Ad)
            q = -b.dot(d) + 0.5 * d.dot(Ad)
            assert predicted == pytest.approx(-q, rel=1e-10)
            assert norm_d == pytest.approx(d.norm(), rel=1e-12)
            assert norm_d <= radius * (1 + 1e-12)
            if boundary:
                assert norm_d == pytest.approx(radius, rel=1e-10)
            seen.add(tr.reasons[-1])
        assert "CONVERGED_CG_CONSTRAINED" in seen
        Ad.destroy()
    finally:
        sim.close()


def test_radius_update_and_ratio():
    assert update_radius(2.0, 0.1, 1.5, True) == pytest.approx(0.375)    # shrink to |d| / 4
    assert update_radius(2.0, 0.9, 2.0, True) == 4.0                     # good, on the boundary
    assert update_radius(2.0, 0.9, 1.0, False) == 2.0                    # good, inside
    assert update_radius(2.0, 0.5, 2.0, True) == 2.0
    assert ratio(1.0, 2.0, 10.0) == 0.5
    assert ratio(-1.0, 2.0, 10.0) == -0.5
    assert ratio(1e-20, -1e-20, 1e5) == 1.0                              # round-off of G
    assert ratio(1.0, 0.0, 1e5) == -np.inf


def test_trust_region_converges_where_the_filtered_newton_does_not():
    """Smash's frame 0 (the 60% compression's release) to 1e-6 wisp lengths: the trust
    region in at most 14 iterations (measured 12); the filtered Newton of main, with the
    analytic filter never within 30, with exact_or_analytic in 20 (measured)."""
    _, tr = run_positions(_smash(), comm=MPI.COMM_SELF)
    assert tr["newton_converged"] == [True]
    assert tr["newton_iterations"][0] <= 14
    assert tr["newton_increment"][0] < TOL
    assert tr["trust_region"]["ksp_type"] == "stcg"
    assert len(tr["trust_region"]["ksp_iterations"]) >= tr["newton_iterations"][0] - 1
    for filt in ("analytic", "exact_or_analytic"):
        _, f = run_positions(_smash("filtered", filt), comm=MPI.COMM_SELF)
        assert f["newton_iterations"][0] > 14, filt
        assert "trust_region" not in f


def test_ksp_type_comes_from_the_options():
    """-tr_ksp_type nash selects PETSc's NASH (the code default is only a default in the
    options database); a KSP without a trust region is a configuration error."""
    cfg = _smash()
    cfg.solver.options = "-tr_ksp_type nash"
    _, s = run_positions(cfg.validate(), comm=MPI.COMM_SELF)
    assert s["trust_region"]["ksp_type"] == "nash"
    assert s["newton_converged"] == [True]
    cfg.solver.options = "-tr_ksp_type cg"
    with pytest.raises(ConfigError, match="tr_ksp_type cg.*stcg, nash"):
        build_simulator(cfg.validate(), comm=MPI.COMM_SELF)
    cfg.solver.options = "-tr_ksp_type gltr"      # aborts the process in PETSc 3.18
    with pytest.raises(ConfigError, match="gltr aborts the process"):
        build_simulator(cfg.validate(), comm=MPI.COMM_SELF)


@pytest.mark.parametrize("error_flag", ["", " -tr_ksp_error_if_not_converged"])
def test_a_diverged_trust_region_solve_is_a_solver_error(error_flag):
    """With or without -tr_ksp_error_if_not_converged (PETSc raises instead of returning
    the reason): the same SolverError, not a PETSc error that aborted every rank."""
    from lc_petsc.errors import SolverError
    cfg = _smash()
    cfg.solver.options = "-tr_ksp_max_it 1" + error_flag
    sim = build_simulator(cfg.validate(), comm=MPI.COMM_SELF)
    try:
        with pytest.raises(SolverError, match="DIVERGED_MAX_IT"):
            sim.run()
    finally:
        sim.close()


@pytest.mark.parametrize("change, match", [
    (dict(newton="trust"), "time.newton must be one of"),
    (dict(newton="trust_region", line_search=True), "trust region is the globalisation"),
])
def test_time_config_errors(change, match):
    cfg = _smash()
    for k, v in change.items():
        setattr(cfg.time, k, v)
    with pytest.raises(ConfigError, match=match):
        cfg.validate()


@pytest.mark.parametrize("filt", ["none", "exact_or_analytic"])
def test_trust_region_needs_a_psd_filter(filt):
    cfg = _smash()
    cfg.solver.filter = filt
    with pytest.raises(ConfigError, match="positive semi-definite"):
        cfg.validate()


def test_trust_region_refuses_strand_contact():
    cfg = small_hairball_config(n_wisps=2, frames=1, terms=("stretch", "bend", "twist",
                                                            "strand_collision"))
    cfg.time.newton = "trust_region"
    with pytest.raises(ConfigError, match="does not support strand contact"):
        cfg.validate()


@pytest.mark.mpi
def test_trust_region_rank_invariance():
    """Four shaking-head wisps, 3 frames to 1e-6 with cutback: 1, 2 and 3 ranks take the
    same iterations and reach the serial positions (one trust radius for all ranks: the
    norms and rho are reduced)."""
    cfg = small_hairball_config(n_wisps=4, frames=3, newton_iterations=30,
                                newton_increment_tol=TOL, newton="trust_region")
    X, s = run_positions(cfg.validate())
    ref, r = serial_reference(cfg)
    ok, msg = True, ""
    if COMM.rank == 0:
        ok = (s["newton_substep_iterations"] == r["newton_substep_iterations"]
              and all(s["newton_converged"]) and rel_diff(X, ref) < 1e-9)
        msg = (f"{COMM.size} ranks: {s['newton_substep_iterations']} against "
               f"{r['newton_substep_iterations']}, difference {rel_diff(X, ref):.2e}")
    if not COMM.bcast(ok):
        pytest.fail(msg if COMM.rank == 0 else "see rank 0")
