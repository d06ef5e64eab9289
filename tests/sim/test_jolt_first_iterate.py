"""``time.jolt_first_iterate``: a step across a jump of the head's velocity starts from the
start's first iterate (the head's change of motion carried near the roots only, then
follow-the-leader; docs/newton.md "The head's jolts' first iterate")."""

from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI

from test_newton_convergence import _summary
from test_wisp_trust import _hairball10

from lc_petsc.config import load_config
from lc_petsc.errors import ConfigError
from lc_petsc.scene.kinematics import HeadMotion

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _shaken_hairball10(jolt, frames=10):
    """hairball10 of test_wisp_trust (configs/hairball_demo.toml cut to 10 wisps without
    strand contact, to 1e-6 on the recommended path with ``solver.wisp_trust``, inertial
    first iterate, no cutback) with the chord stop, ``frames`` frames and its shake
    shortened to a period of 0.3 s at amplitude 0.15 rad (the demo's angular speed; the
    head changes axis at t = 0.3 s, frame 9)."""
    cfg = _hairball10()
    cfg.physics.head_period, cfg.physics.head_amplitude = 0.3, 0.15
    cfg.time.frames, cfg.time.newton_stop, cfg.time.jolt_first_iterate = frames, "chord_estimate", jolt
    return cfg.validate()


@pytest.mark.mpi
def test_the_change_of_axis_converges_in_fewer_iterations_the_same_on_any_rank_count():
    """The shortened shake changes axis at frame 9: from the carried first iterate (main)
    that frame takes 17 iterations to 1e-6, from the jolt's first iterate 14 (bound 15);
    frames 0 and 9 start from it (``newton_jolt_starts``), every frame converges at full
    dt, the run takes fewer iterations in all (110 against 114), and the counts are the
    same on 1, 2 and 3 ranks."""
    comm = MPI.COMM_WORLD
    old, new = _summary(_shaken_hairball10(False)), _summary(_shaken_hairball10(True))
    for s in (old, new):
        assert all(s["newton_converged"]) and s["newton_substeps"] == [1] * 10
    assert new["newton_jolt_starts"] == [1] + [0] * 8 + [1] and old["newton_jolt_starts"] == [0] * 10
    assert new["newton_iterations"][9] <= 15 < old["newton_iterations"][9]
    assert sum(new["newton_iterations"]) < sum(old["newton_iterations"])
    assert new["newton_iterations"] == [14, 10, 10, 15, 8, 9, 12, 10, 8, 14]
    assert comm.allgather(new["newton_iterations"]) == [new["newton_iterations"]] * comm.size


def test_the_head_velocity_jumps_at_the_start_and_at_each_change_of_axis():
    """The unsmoothed shake (period 1 s, dt 1/30): a jump in the step from t = 0 and in
    the step from t = 1 s (with t summed step by step, 30 sums of 1/30 off 1.0 by
    round-off either way), none in the steps before or after; a smooth shake and a
    static head never; a translating head at t = 0 only, and not without a velocity."""
    cfg = load_config(CONFIGS / "hairball_demo.toml")
    head = HeadMotion(cfg.physics)
    dt = 1.0 / 30.0
    t = 0.0
    jumps = []
    for k in range(62):
        jumps.append(head.velocity_jumps(t, t + dt))
        t += dt
    assert np.flatnonzero(jumps).tolist() == [0, 30, 60]
    for t30 in (1.0 - 1e-15, 1.0, 1.0 + 2e-16):
        assert head.velocity_jumps(t30, t30 + dt) and not head.velocity_jumps(t30 - dt, t30)
    cfg.physics.head_smooth = True
    assert not any(HeadMotion(cfg.physics).velocity_jumps(k * dt, (k + 1) * dt) for k in range(62))
    cfg.physics.head_motion = "static"
    assert not HeadMotion(cfg.physics).velocity_jumps(0.0, dt)
    cfg.physics.head_motion, cfg.physics.head_velocity = "translate", (1.0, 0.0, 0.0)
    head = HeadMotion(cfg.physics)
    assert head.velocity_jumps(0.0, dt) and not head.velocity_jumps(dt, 2 * dt)
    cfg.physics.head_velocity = (0.0, 0.0, 0.0)
    assert not HeadMotion(cfg.physics).velocity_jumps(0.0, dt)


def test_a_value_that_is_not_a_boolean_is_refused():
    cfg = _shaken_hairball10(True)
    cfg.time.jolt_first_iterate = "yes"
    with pytest.raises(ConfigError, match="time.jolt_first_iterate must be true or false, got 'yes'"):
        cfg.validate()


@pytest.mark.parametrize("physics, warned", [
    ({"head_motion": "static"}, True), ({"head_motion": "shake", "head_smooth": True}, True),
    ({"head_motion": "shake"}, False), ({"head_motion": "translate", "head_velocity": [1.0, 0.0, 0.0]}, False)])
def test_the_key_with_a_head_whose_velocity_never_jumps_is_warned(physics, warned):
    """A file's ``time.jolt_first_iterate`` with a static head or a smooth shake (whose
    velocity never jumps: :meth:`HeadMotion.velocity_jumps`) changes nothing: the
    configuration says so, naming the key (on main: no warning); a tolerance's default of
    it (not in the file) is not warned."""
    from lc_petsc.config import config_from_dict
    cfg = config_from_dict({"time": {"jolt_first_iterate": True}, "physics": physics})
    assert [w.split(" is set")[0] for w in cfg.key_warnings] == (["time.jolt_first_iterate"] if warned else [])
    assert all("physics.head_smooth" in w for w in cfg.key_warnings)
    cfg = config_from_dict({"time": {"newton_increment_tol": 1e-4, "newton_iterations": 30}, "physics": physics})
    assert cfg.time.jolt_first_iterate and cfg.key_warnings == []
