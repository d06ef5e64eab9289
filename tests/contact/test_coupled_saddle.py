"""A Newton stop on a saddle of G whose negative mode spreads over wisps coupled by strand
contact, every wisp's own block definite, is refused (lc_petsc/contact_curvature.py,
docs/newton.md "A saddle over contact-coupled wisps").  The scene: the six touching
wisps in phase in ccd mode (tests/contact/test_mpi_ccd.py), on the recommended path to
1e-6, whose frame 0 had been called converged after 12 iterations on a saddle (lowest
eigenvalue of dt^2 M^-1/2 (A + C) M^-1/2: -0.517, over wisps 1-3 of the scene)."""

import numpy as np
import pytest
import scipy.linalg
from mpi4py import MPI

import lc_petsc.simulator as simmod
from sim_helpers import touching_wisps_config, touching_wisps_source

comm = MPI.COMM_WORLD


def six_wisps(monkeypatch, frames, max_substeps, c=comm):
    monkeypatch.setattr(simmod, "source_from_config",
                        lambda *a: touching_wisps_source(spin_step=0.0, n_pinned=3))
    cfg = touching_wisps_config(frames)
    cfg.physics.strand_contact_mode = "ccd"
    cfg.solver.filter, cfg.solver.exact_fallback, cfg.solver.exact_stay = "exact_or_analytic", "shifted", True
    cfg.time.newton_update = "corotational"
    cfg.time.newton_increment_tol, cfg.time.newton_iterations = 1e-6, 100
    cfg.time.max_substeps = max_substeps
    return simmod.build_simulator(cfg.validate(), comm=c)


def frame_zero(monkeypatch):
    """(simulator, summary) of the six wisps' frame 0 without cutback on every rank."""
    sim = six_wisps(monkeypatch, 1, 1)
    try:
        sim.run(1)
        return sim, sim.summary()
    finally:
        sim.close()


@pytest.mark.mpi
def test_a_saddle_over_contact_coupled_wisps_is_refused_on_every_rank(monkeypatch):
    """Frame 0 stops after 12 iterations as on main, but on a saddle: refused (main:
    converged, newton_saddle 0).  Lanczos finds the negative mode in 3 iterations (Ritz
    value of B^-1 (A + C) -0.3335; its Rayleigh quotient -0.287 M/dt^2), the same on 1, 2
    and 3 ranks (the wisps spread over the ranks), and names the three wisps holding it."""
    sim, summary = frame_zero(monkeypatch)
    assert list(summary["newton_iterations"]) == [12]
    assert summary["newton_converged"] == [False]
    assert summary["newton_saddle"] == [1]
    checks = sim.integrator.coupled_checks
    assert len(checks) == 1 and checks[0].negative
    assert checks[0].iterations == 3
    assert checks[0].lowest == pytest.approx(-0.33347, abs=1e-4)
    assert checks[0].curvature == pytest.approx(-0.28679, abs=1e-4)
    assert len(checks[0].wisps) == 3
    verdicts = comm.allgather((checks[0].lowest, checks[0].wisps))
    assert all(v[1] == verdicts[0][1] and abs(v[0] - verdicts[0][0]) < 1e-9 for v in verdicts)


def test_cutback_reaches_minima_the_check_confirms_densely(monkeypatch):
    """With step cutback the refused frame 0 is redone as 2 x dt/2 and the next three
    frames converge: every later check is on a minimum, confirmed by the dense
    generalised eigenvalues of ((A + C), B) on the free DoFs (no false positive; the
    Lanczos estimate within 0.5% of the dense lowest), and the refused stop was a saddle
    of the dense matrix too."""
    sim = six_wisps(monkeypatch, 4, 8, c=MPI.COMM_SELF)
    it = sim.integrator
    dense = []
    checked = it._at_coupled_saddle

    def with_dense(exact):
        verdict = checked(exact)
        if exact and it.strand.C is not None:
            op, A = it.solver.ksp.getOperators()[0], it.asm.mat
            xv, yv = A.createVecs()
            free = np.flatnonzero(np.repeat(it.free, 3))
            H, B = np.zeros((len(free),) * 2), np.zeros((len(free),) * 2)
            for j, c in enumerate(free):
                xv.zeroEntries()
                xv.array[c] = 1.0
                op.mult(xv, yv)
                H[:, j] = yv.array[free]
                A.mult(xv, yv)
                B[:, j] = yv.array[free]
            dense.append(scipy.linalg.eigh(0.5 * (H + H.T), 0.5 * (B + B.T), eigvals_only=True)[0])
        return verdict

    it._at_coupled_saddle = with_dense
    try:
        sim.run(4)
        summary = sim.summary()
    finally:
        sim.close()
    assert summary["newton_converged"] == [True] * 4
    assert summary["newton_saddle"] == [1, 0, 0, 0]
    checks = it.coupled_checks
    assert len(checks) == len(dense) == 5
    assert [c.negative for c in checks] == [True, False, False, False, False]
    assert dense[0] == pytest.approx(-0.50925, abs=1e-4)
    assert min(dense[1:]) > 0.005
    for c, d in zip(checks[1:], dense[1:]):
        assert c.lowest == pytest.approx(d, rel=5e-3)


def _diagonal_check(d, steps, monkeypatch):
    """The check's verdict on diag(``d``) (one wisp of len(d) / 3 vertices, none pinned,
    its own blocks the identity: B^-1 (A + C) = diag(d), plain Lanczos) with the cap
    ``steps``."""
    from petsc4py import PETSc

    from lc_petsc import contact_curvature as cc
    monkeypatch.setattr(cc, "STEPS", steps)
    nv = len(d) // 3
    op = PETSc.Mat().createAIJ((3 * nv, 3 * nv), nnz=1, comm=PETSc.COMM_SELF)
    for i, v in enumerate(d):
        op.setValue(i, i, v)
    op.assemble()
    blocks = (np.arange(nv + 1), np.arange(nv), np.tile(np.eye(3).ravel(), nv))
    check = cc.CoupledCurvature(np.array([0, nv]), 0, np.ones(nv, bool), MPI.COMM_SELF)
    try:
        return check.check(blocks, op, np.ones(nv), op)
    finally:
        op.destroy()


def test_an_unconverged_lanczos_says_unknown_not_minimum(monkeypatch):
    """300 eigenvalues evenly spread over [0.01, 2] (a cluster at the bottom, as the contact
    pairs' joint motion makes one at the six wisps' minima): the lowest Ritz value has not
    converged after 20 iterations (0.0116 against 0.0100), so the verdict is unknown; with
    200 it converges to 0.0100, a minimum.  Shifted down by 0.011 (one eigenvalue -0.001,
    a shallow saddle) the cap of 20 finds no negative Ritz value: unknown, not minimum
    (main called both minima); the saddle shows at 23."""
    d = np.linspace(0.01, 2.0, 300)
    short = _diagonal_check(d, 20, monkeypatch)
    assert not short.negative and short.unknown and not short.converged
    assert short.lowest == pytest.approx(0.011610, rel=1e-4)     # 16% above 0.01
    full = _diagonal_check(d, 200, monkeypatch)
    assert not full.negative and not full.unknown
    assert full.lowest == pytest.approx(0.01, rel=1e-2)
    saddle = d - 0.011
    hidden = _diagonal_check(saddle, 20, monkeypatch)
    assert not hidden.negative and hidden.unknown
    assert hidden.lowest == pytest.approx(0.000610, rel=1e-3)     # Lanczos is shift-invariant
    found = _diagonal_check(saddle, 200, monkeypatch)
    assert found.negative and found.lowest < 0.0 and found.iterations == 23


@pytest.mark.mpi
def test_a_check_cut_short_keeps_the_stop_as_unknown(monkeypatch):
    """The six wisps' frame-0 saddle needs 3 Lanczos iterations; with the cap at 2 the
    check finds no negative Ritz value and has not converged: the verdict is unknown, the
    stop kept (the integrator refuses only a proven saddle) and counted in summary.json
    ``newton_coupled_unknown`` (main: kept as a minimum, uncounted), on 1, 2 and 3 ranks."""
    from lc_petsc import contact_curvature as cc
    monkeypatch.setattr(cc, "STEPS", 2)
    sim, summary = frame_zero(monkeypatch)
    assert list(summary["newton_iterations"]) == [12]
    assert summary["newton_converged"] == [True]
    assert summary["newton_saddle"] == [0]
    assert summary["newton_coupled_unknown"] == [1]
    checks = sim.integrator.coupled_checks
    assert len(checks) == 1 and checks[0].unknown and checks[0].iterations == 2
    assert checks[0].lowest == pytest.approx(0.43381, abs=1e-4)     # the dense lowest: -0.509
    assert all(abs(v - checks[0].lowest) < 1e-9 for v in comm.allgather(checks[0].lowest))
