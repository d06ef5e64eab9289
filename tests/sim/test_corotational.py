"""The corotational Newton update (``time.newton_update = "corotational"``: the exact
steps of ``exact_or_analytic`` turned, docs/newton.md "Sixth round"): exact rigid
rotations, momentum of a free wisp, degenerate (straight) wisps, and convergence-rate
bounds on smash and a small hairball that the edge retraction fails.  Its definition and
second-order agreement with x + dx: tests/sim/test_newton_convergence.py."""

from pathlib import Path

import numpy as np
from mpi4py import MPI

from lc_petsc.config import load_config
from lc_petsc.predictors import corotational_update, retract_edge_lengths
from lc_petsc.studies.newton import configure, iterations_to, parse_variant, run_history
from sim_helpers import chains as _chains
from sim_helpers import rotate as _rotate

COMM = MPI.COMM_WORLD


def _comm(n_wisps):
    """COMM_WORLD if every rank gets a wisp, else each rank runs the scene alone (whole
    wisps are distributed; these scenes have 1-2): the figures do not depend on the
    rank count."""
    return COMM if COMM.size <= n_wisps else MPI.COMM_SELF
ROOT = Path(__file__).resolve().parents[2]


def test_corotational_turns_a_rigid_rotation_exactly():
    """The linearised rotation of a wisp about its pinned root, by 0.7 rad: the update
    gives the rotated wisp (to the fit's regularisation, 1e-10), the edge retraction
    is 0.2 away (its bend and twist angles distorted: the hairball's slow mode)."""
    rng = np.random.default_rng(3)
    x, off, free = _chains(rng)
    u = (x[1] - x[0]) / np.linalg.norm(x[1] - x[0])
    w = 0.7 * u
    dx = np.zeros_like(x)
    dx[2:6] = np.cross(w, x[2:6] - x[1])
    want = x.copy()
    want[2:6] = x[1] + np.array([_rotate(w, p - x[1]) for p in x[2:6]])
    assert np.abs(corotational_update(x, dx, free, off)[:6] - want[:6]).max() < 1e-8
    assert np.abs(retract_edge_lengths(x, dx, free, off)[:6] - want[:6]).max() > 0.1


def test_corotational_free_wisp_keeps_the_momentum_of_x_plus_dx():
    rng = np.random.default_rng(4)
    off = np.array([0, 7])
    x = np.cumsum(rng.normal(size=(7, 3)), axis=0)
    free = np.ones(7, bool)
    mass = rng.uniform(0.5, 2.0, size=7)
    dx = 0.3 * rng.normal(size=x.shape)
    got = corotational_update(x, dx, free, off, mass)
    assert np.allclose(mass @ got, mass @ (x + dx), rtol=0, atol=1e-12)
    assert not np.allclose(got, x + dx)      # the update did change the positions


def test_corotational_straight_wisp_is_finite_and_second_order():
    """A straight wisp (every neighbourhood collinear: the rotation about the line is
    free, the regularisation picks none) stays finite and agrees with x + dx."""
    rng = np.random.default_rng(5)
    off = np.array([0, 8])
    x = np.zeros((8, 3))
    x[:, 0] = np.arange(8) * 0.6
    free = np.ones(8, bool)
    free[:2] = False
    dx = 1e-2 * rng.normal(size=x.shape)
    dx[~free] = 0.0
    got = corotational_update(x, dx, free, off)
    assert np.isfinite(got).all()
    errs = [np.abs(corotational_update(x, h * dx, free, off) - (x + h * dx)).max() for h in (1.0, 0.5)]
    assert 3.6 < errs[0] / errs[1] < 4.4
    assert np.array_equal(corotational_update(x, 0 * dx, free, off), x)


def _iterations(cfg, spec, frames, tol=1e-6, cap=30):
    rows, _ = run_history(configure(cfg, parse_variant(spec), cap, frames), _comm(cfg.scene.n_wisps))
    return [i or cap + 1 for i in iterations_to(rows, tol)]


EOA = "filter=exact_or_analytic,update="


def test_convergence_rate_smash_corotational():
    """configs/smash.toml frame 0 (the 60% compression's release), exact_or_analytic:
    1e-6 wisp lengths in at most 14 iterations with the corotational update (measured
    13); the edge retraction takes 20."""
    cfg = load_config(ROOT / "configs" / "smash.toml")
    assert _iterations(cfg, EOA + "corotational", 1)[0] <= 14
    assert _iterations(cfg, EOA + "edge_retraction", 1)[0] > 15


def test_convergence_rate_hairball_corotational():
    """The demo hairball cut to 2 wisps without strand contact, frames 1-3 (frame 0 is
    the head's impulsive start), exact_or_analytic: each within 11 iterations to 1e-6
    wisp lengths with the corotational update (measured 11 10 11); the edge retraction's
    frame 1 takes 18."""
    cfg = load_config(ROOT / "configs" / "hairball_demo.toml")
    cfg.scene.n_wisps = 2
    cfg.physics.terms = tuple(t for t in cfg.physics.terms if t != "strand_collision")
    cfg.time.initial_guess = "inertial"     # as measured (the demo sets FTL for its ccd contact)
    cfg.time.length_projection = False      # likewise
    cfg.time.carry_with_head = False        # likewise (carried, frame 0 lands elsewhere)
    its = _iterations(cfg, EOA + "corotational", 4)
    assert max(its[1:]) <= 11, its
    assert _iterations(cfg, EOA + "edge_retraction", 2)[1] > 15


def test_error_history_locates_the_slow_vertex():
    """scripts/newton_errors.py's study on smash frame 0 (20 iterations to 1e-6 with the
    edge retraction): the first iterate's error is the release's (> 1e-2 wisp lengths),
    it falls to round-off by iteration 25, the last iterate is the reference (0), and
    the profile is the wisp's per-vertex distance (cm)."""
    from lc_petsc.studies.newton import error_history
    cfg = load_config(ROOT / "configs" / "smash.toml")
    cfg.solver.filter = "exact_or_analytic"
    rows = error_history(cfg, _comm(cfg.scene.n_wisps), 1, 30, wisp=0)
    assert [r["iteration"] for r in rows] == list(range(-1, 30))
    assert rows[0]["error"] > 1e-2 and rows[0]["increment"] is None
    assert rows[26]["error"] < 1e-12 and rows[-1]["error"] == 0.0
    assert all(0 <= r["vertex"] < len(r["profile"]) for r in rows)
    # one wisp: its largest distance (cm) over the error is its length, in every row
    lengths = [max(r["profile"]) / r["error"] for r in rows[:15]]
    assert np.allclose(lengths, lengths[0], rtol=1e-12) and lengths[0] > 1.0


def test_ccd_mode_without_strand_contact_keeps_the_configured_update():
    """ccd forces the linear update only where the limiter runs: a ccd scene with
    strand_collision dropped (the shipped demo's mode, contact off) keeps its
    corotational update (the merge that made ccd the demo's default forced linear here,
    and this scene's Newton then never converged: 31 iterations at the cap)."""
    from lc_petsc.simulator import build_simulator
    cfg = load_config(ROOT / "configs" / "hairball_demo.toml")
    assert cfg.physics.strand_contact_mode == "ccd"
    cfg.scene.n_wisps = 2
    cfg.physics.terms = tuple(t for t in cfg.physics.terms if t != "strand_collision")
    cfg.time.newton_update = "corotational"
    sim = build_simulator(cfg, comm=_comm(cfg.scene.n_wisps))
    try:
        assert sim.integrator.retract and sim.integrator.turn_exact
    finally:
        sim.close()
    cfg.physics.terms = cfg.physics.terms + ("strand_collision",)
    sim = build_simulator(cfg, comm=_comm(cfg.scene.n_wisps))
    try:
        assert not sim.integrator.retract and not sim.integrator.turn_exact
    finally:
        sim.close()
