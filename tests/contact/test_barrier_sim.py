"""The barrier potential (physics.strand_contact_potential = "barrier") in the simulator:
a wisp pressed onto another with three times the penalty's largest force (k d0) keeps
its distance with the barrier, while with the penalty in ccd mode the limiter lets the
gap shrink towards zero (the control); Newton converges in the frames where crossing
wisps come into contact, where it cycles with the penalty (the control); the config
refuses the barrier without ccd.
The barrier run is collective (1 rank here, 2 under tests/test_mpi_launch.py, one
wisp per rank)."""

import numpy as np
import pytest
from mpi4py import MPI

import lc_petsc.simulator as simmod
from lc_petsc.config import (ConfigError, MaterialConfig, PhysicsConfig, SceneConfig, SimConfig,
                             SolverConfig, TimeConfig)
from lc_petsc.crossings import count_crossings
from lc_petsc.scene.sources import ArraySource
from test_contact_sim import D0 as CROSS_D0, crossing_config, crossing_separation, crossing_source

N, D0, K = 21, 0.2, 1.0e3      # vertices per wisp, contact thickness (cm), penalty k (dyn/cm)
FRAMES = 6
LOAD = 3.0                     # the weight of the free vertices over the penalty's k d0


def pressed_source():
    """Wisp A along x, pinned except its 8 middle vertices; wisp B free, along z, 1.2 d0
    above A's middle: under gravity B lies across A's free part."""
    s = (np.arange(N) - (N - 1) / 2) * 0.5
    A = np.stack([s, np.zeros(N), np.zeros(N)], 1)
    B = np.stack([np.full(N, 0.13), np.full(N, 1.2 * D0), s], 1)
    pin = np.zeros(2 * N, bool)
    pin[:7] = pin[15:N] = True
    return ArraySource(np.concatenate([A, B]), [0, N, 2 * N], pinned=pin, root_radius=0.05,
                       tip_radius=0.05)


def pressed_config(potential, g=981.0, frames=FRAMES, mode="ccd", guess="inertial"):
    return SimConfig(
        scene=SceneConfig(kind="straight"), material=MaterialConfig(youngs_modulus=1e9),
        physics=PhysicsConfig(terms=("stretch", "bend", "gravity", "strand_collision"),
                              gravity=(0.0, -g, 0.0), strand_thickness=D0, strand_stiffness=K,
                              strand_contact_mode=mode, strand_separation=False,
                              strand_contact_potential=potential),
        time=TimeConfig(frames=frames, initial_guess=guess),
        solver=SolverConfig(options="-ksp_rtol 1e-12 -ksp_max_it 5000"))


def press(c, potential, guess="inertial"):
    """(crossings per frame step, min distance per frame / d0) on rank 0 of ``c``."""
    probe = simmod.build_simulator(pressed_config(potential), comm=c)
    m_free = c.allreduce(float(probe.scene.mass[~probe.scene.pinned].sum()))
    probe.close()
    sim = simmod.build_simulator(pressed_config(potential, g=LOAD * K * D0 / m_free, guess=guess), comm=c)
    try:
        X = [sim.gather_positions()]
        for _ in range(FRAMES):
            sim.step()
            X.append(sim.gather_positions())
        summ = sim.summary()
    finally:
        sim.close()
    if c.rank != 0:
        return None, None
    cross = [count_crossings(X[k], X[k + 1], [0, N, 2 * N])["crossings"] for k in range(FRAMES)]
    dmin = np.array([np.inf if v is None else v for v in summ["contact"]["min_distance_per_frame"]])
    return cross, dmin / D0


@pytest.fixture
def pressed(monkeypatch):
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: pressed_source())


@pytest.mark.mpi
@pytest.mark.parametrize("guess", ["inertial", "follow_the_leader"])
def test_barrier_keeps_a_pressed_pair_apart(pressed, guess):
    """Either first iterate (time.initial_guess).  Follow the leader leaves B, a wisp
    without a pinned root, at its prediction: walked from its first vertex it was dragged
    along itself over A every frame, and the straight path of that slide, cut short by
    the ccd path check, left the pair at the check's floor, 0.05 d0 (docs/contact.md,
    "Follow the leader in ccd mode")."""
    comm = MPI.COMM_WORLD
    sub = comm.Split(0 if comm.rank < 2 else MPI.UNDEFINED)   # two wisps: at most 2 ranks
    if sub == MPI.COMM_NULL:
        comm.Barrier()
        return
    try:
        cross, dmin = press(sub, "barrier", guess)
        if sub.rank == 0:
            print(f"\nbarrier, {guess}, {sub.size} rank(s): crossings {cross}, min distance / d0 per frame "
                  f"{np.round(dmin, 4).tolist()}")
            assert sum(cross) == 0
            assert np.all(np.isfinite(dmin))          # in contact every frame
            assert dmin.min() > 0.15                 # measured 0.27 (frame 2), 0.34-0.36 after
    finally:
        sub.Free()
        comm.Barrier()


def test_penalty_in_ccd_mode_lets_the_pressed_pair_close_in(pressed):
    """The control: the same load on the penalty, whose force cannot exceed k d0; the
    limiter keeps the steps collision-free but each frame closes part of the gap."""
    cross, dmin = press(MPI.COMM_SELF, "penalty")
    print(f"\npenalty (ccd): crossings {cross}, min distance / d0 per frame {np.round(dmin, 4).tolist()}")
    assert sum(cross) == 0
    assert dmin.min() < 0.05                         # measured 0.008 (frame 4)


def converge_crossing(potential, frames=8, cap=20, speed=2.5):
    """Newton to a relative increment of 1e-6 (at most ``cap`` iterations) on the crossing
    wisps of test_contact_sim (A up, B down at ``speed``; contact from frame 4): (iterations
    per frame, converged per frame, minimum separation at the crossing / d0)."""
    cfg = crossing_config(frames, strand_contact_mode="ccd", strand_contact_potential=potential)
    cfg.time.newton_iterations, cfg.time.newton_increment_tol = cap, 1e-6
    cfg.time.max_substeps = 1       # Newton of one step: cutback would hide the cycling
    sim = simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
    try:
        n = sim.scene.nv // 2
        sim.integrator.v[:n, 1], sim.integrator.v[n:, 1] = speed, -speed
        X = [sim.x.copy()]
        for _ in range(frames):
            sim.step()
            X.append(sim.x.copy())
        summ = sim.summary()
    finally:
        sim.close()
    return summ["newton_iterations"], summ["newton_converged"], crossing_separation(X).min() / CROSS_D0


def test_barrier_newton_converges_where_the_penalty_cycles(monkeypatch):
    """docs/newton.md: with the penalty (psi'' jumps at d0) the frames where the pairs
    come into contact do not converge; the C2 barrier converges in every frame."""
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: crossing_source())
    its, conv, sep = converge_crossing("barrier")
    print(f"\nbarrier: Newton iterations {its}, converged {conv}, min separation {sep:.3f} d0")
    assert all(conv) and max(its) <= 12 and sep > 0.5            # measured max 11, 0.985 d0
    its, conv, sep = converge_crossing("penalty")
    print(f"penalty (ccd): Newton iterations {its}, converged {conv}, min separation {sep:.3f} d0")
    assert not all(conv) and max(its) == 20                     # frames 5, 6 hit the cap


def test_barrier_needs_ccd_mode():
    with pytest.raises(ConfigError, match="strand_contact_mode"):
        pressed_config("barrier", mode="penalty").validate()
    with pytest.raises(ConfigError, match="strand_contact_potential"):
        pressed_config("log").validate()
    cfg = pressed_config("barrier")
    cfg.physics.strand_barrier_stiffness = -1.0
    with pytest.raises(ConfigError, match="strand_barrier_stiffness"):
        cfg.validate()
