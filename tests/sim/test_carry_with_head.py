"""Newton's first iterate carried with the head's change of motion (``time.carry_with_head``,
lc_petsc/predictors.py ``head_motion_change``; docs/newton.md, "Tenth round")."""

import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.config import ConfigError, PhysicsConfig, SolverConfig, TimeConfig
from lc_petsc.predictors import START_CARRY_LENGTH, head_motion_change, start_carry_weight
from lc_petsc.scene import geometry
from lc_petsc.scene.kinematics import HeadMotion
from lc_petsc.scene.sources import ArraySource
from lc_petsc.simulator import build_simulator
from tests.sim_helpers import run_positions, small_hairball_config

SELF = MPI.COMM_SELF


def _integrator_change(kind, t, dt, x, **physics):
    """head_motion_change of an integrator whose head has ``physics`` at time t."""
    cfg = small_hairball_config(n_wisps=1, frames=1)
    cfg.physics.head_motion = kind
    for key, value in physics.items():
        setattr(cfg.physics, key, value)
    sim = build_simulator(cfg.validate(), comm=SELF)
    try:
        it = sim.integrator
        it.t = t
        return head_motion_change(it.head, x, t, dt, t + dt), it.head
    finally:
        sim.close()


def test_change_of_motion_is_the_difference_of_the_two_steps_rigid_motions():
    rng = np.random.default_rng(0)
    x = rng.normal(scale=20.0, size=(50, 3))
    t, dt = 0.37, 1.0 / 30.0
    change, head = _integrator_change("shake", t, dt, x, head_amplitude=0.5, head_period=1.0)
    expected = head.carry(x, t, t + dt) - head.carry(x, t - dt, t)
    assert np.abs(change - expected).max() < 1e-12 * np.abs(x).max()
    # second order in dt away from the start and the axis switches: dt^2 times the
    # head's acceleration field, so halving dt quarters it
    half, _ = _integrator_change("shake", t, dt / 2, x, head_amplitude=0.5, head_period=1.0)
    ratio = np.linalg.norm(change) / np.linalg.norm(half)
    assert 3.9 < ratio < 4.1


def test_a_start_from_rest_carries_the_whole_first_step_of_the_head():
    x = np.array([[0.0, 30.0, 5.0], [-4.0, 2.0, 1.0]])
    velocity = np.array([3.0, -1.0, 2.0])
    dt = 0.05
    at_start, _ = _integrator_change("translate", 0.0, dt, x, head_velocity=tuple(velocity))
    assert np.allclose(at_start, dt * velocity, rtol=0, atol=1e-14)
    # a constant velocity afterwards: no change of motion, nothing added
    later, _ = _integrator_change("translate", 0.4, dt, x, head_velocity=tuple(velocity))
    assert np.abs(later).max() < 1e-14
    # the shake from rest: the head's own first step
    x2 = np.array([[3.0, 25.0, -2.0]])
    shake, head = _integrator_change("shake", 0.0, dt, x2, head_amplitude=0.5, head_period=1.0)
    assert np.allclose(shake, head.carry(x2, 0.0, dt) - x2, rtol=0, atol=1e-12)
    assert np.linalg.norm(shake) > 0.1


def test_only_the_free_vertices_of_wisps_the_head_holds_are_carried(monkeypatch):
    """A wisp with no pinned vertex is not carried by the head: its run is the same with
    and without the carry (to the round-off of the shared CG scalars), while the held
    wisp's first iterate, hence its frame, changes."""
    held = geometry.wisp4c(30, root=(0.0, 16.0, 0.0))
    loose = geometry.wisp4c(30, root=(6.0, 16.0, 0.0))
    pos = np.concatenate([held, loose])
    pin = np.zeros(len(pos), bool)
    pin[:4] = True
    source = ArraySource(pos, np.array([0, 30, 60]), pinned=pin, root_radius=0.08, tip_radius=0.05)
    monkeypatch.setattr("lc_petsc.simulator.source_from_config", lambda *a, **k: source)
    runs = {}
    for carry in (True, False):
        cfg = small_hairball_config(frames=2, terms=("stretch", "bend", "twist", "gravity"),
                                    carry_with_head=carry)
        cfg.scene.kind = "straight"
        cfg.solver = SolverConfig(options="-ksp_rtol 1e-12")
        sim = build_simulator(cfg.validate(), comm=SELF)
        try:
            if carry:
                carried = sim.integrator.carried
                assert carried is not None
                assert carried[4:30].all() and not carried[:4].any() and not carried[30:].any()
            sim.run(2)
            runs[carry] = sim.gather_positions()
        finally:
            sim.close()
    on, off = runs[True], runs[False]
    assert np.abs(on[30:] - off[30:]).max() < 1e-9
    assert np.abs(on[:30] - off[:30]).max() > 1e-3


def test_a_static_head_changes_nothing_bit_for_bit():
    runs = []
    for carry in (True, False):
        cfg = small_hairball_config(n_wisps=2, frames=3, carry_with_head=carry)
        cfg.physics.head_motion = "static"
        runs.append(run_positions(cfg.validate(), comm=SELF)[0])
    assert np.array_equal(runs[0], runs[1])


def test_carried_first_iterate_lowers_the_fixed_count_error():
    """The default 3 filtered iterations on a shaking hairball (4 wisps, head period 0.5 s),
    carried and not, against the converged trajectory after 8 frames: RMS distance
    0.84 cm carried against 2.24 cm (0.38x, measured); the bound is half."""
    frames = 8
    ref_cfg = small_hairball_config(frames=frames, newton_iterations=100, newton_tol=1e-9)
    ref_cfg.solver = SolverConfig(filter="exact_or_analytic", options="-ksp_rtol 1e-12")
    ref = run_positions(ref_cfg.validate(), comm=SELF)[0]
    errors = {}
    for carry in (True, False):
        cfg = small_hairball_config(frames=frames, carry_with_head=carry)
        X = run_positions(cfg.validate(), comm=SELF)[0]
        errors[carry] = np.sqrt(np.mean(np.sum((X - ref) ** 2, axis=1)))
    assert errors[True] < 0.5 * errors[False]


@pytest.mark.parametrize("value", ["yes", 1, None])
def test_carry_with_head_must_be_a_boolean(value):
    with pytest.raises(ConfigError, match="time.carry_with_head must be true or false"):
        TimeConfig(carry_with_head=value).validate()


def test_the_step_before_the_start_is_no_motion():
    # the head starts from rest: the carry of the first step takes its whole motion
    head = HeadMotion(PhysicsConfig(head_motion="shake"))
    Q, q = head.rigid_motion(0.0, 0.0)
    assert np.array_equal(Q, np.eye(3)) and np.array_equal(q, np.zeros(3))


def test_start_weight_decays_along_the_free_arclength():
    """1 up to the last pinned vertex, then exp(-s / (0.3 S)) in the rest arclength s from
    it (S: to the tip), per wisp; 1 on a wisp without pins (it is not carried)."""
    x = np.c_[np.arange(14.0) ** 1.5, np.zeros(14), np.zeros(14)]      # uneven edges
    pinned = np.zeros(14, bool)
    pinned[[0, 1, 6]] = True
    offsets = [0, 6, 11, 14]
    w = start_carry_weight(np.linalg.norm(np.diff(x, axis=0), axis=1), offsets, pinned)
    for a, b in ((0, 6), (6, 11)):
        last = a + np.flatnonzero(pinned[a:b]).max()
        s = x[last:b, 0] - x[last, 0]
        expected = np.exp(-s / (START_CARRY_LENGTH * s[-1]))
        assert np.allclose(w[last:b], expected, rtol=1e-14, atol=0)
        assert np.all(w[a:last + 1] == 1.0)
    assert np.all(w[11:] == 1.0)


def test_the_start_from_rest_carries_its_first_step_near_the_roots_only(monkeypatch):
    """A head translating at constant velocity u from rest: the first iterate of frame 0
    is x_0 + dt u times the start weight on the held wisp's free vertices (the tips lag
    by inertia within a step); frame 1's adds nothing (no change of motion)."""
    velocity = np.array([4.0, -2.0, 1.0])
    cfg = small_hairball_config(n_wisps=2, frames=2, terms=("stretch", "bend", "twist", "gravity"))
    cfg.physics.head_motion = "translate"
    cfg.physics.head_velocity = tuple(velocity)
    sim = build_simulator(cfg.validate(), comm=SELF)
    try:
        it = sim.integrator
        firsts = []
        assemble = it._assemble_system

        def record(x, k, *args, **kwargs):
            if k == 0:
                firsts.append((x.copy(), it.xhat.copy()))
            return assemble(x, k, *args, **kwargs)

        monkeypatch.setattr(it, "_assemble_system", record)
        x0 = it.x.copy()
        sim.run(2)
        free = it.free
        weight = start_carry_weight(it.rest_edge, sim.scene.offsets, sim.scene.pinned)
        first, xhat = firsts[0]
        expected = x0[free] + it.dt * weight[free, None] * velocity
        assert np.abs(first[free] - expected).max() < 1e-12
        assert np.array_equal(xhat, x0)                # the inertia target is untouched
        assert weight[free].min() < 0.1 and weight[free].max() > 0.9
        first1, xhat1 = firsts[1]
        assert np.abs(first1[free] - xhat1[free]).max() < 1e-12
    finally:
        sim.close()
