"""``time.jolt_above``: the frames where the head's acceleration jumps (a shake's change
of axis) run to ``time.start_increment_tol`` like the start frames, the others keep the
fixed count (docs/newton.md "Twenty-third round").  The collective test (marked ``mpi``)
also runs on 2 and 3 ranks through tests/test_mpi_launch.py."""

import json

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.batch import main
from lc_petsc.config import PhysicsConfig, TimeConfig, config_from_dict
from lc_petsc.errors import ConfigError
from lc_petsc.scene.kinematics import HeadMotion
from sim_helpers import assert_follows_serial, hairball_toml, jolt_hairball_config, run_positions

comm = MPI.COMM_WORLD
TOL = 1e-6
#: dt 1/30 and a period of 0.2 s: the head switches its axis at frame 6 (t = 0.2 s)
PERIOD, AMPLITUDE = 0.2, 0.1
#: the hairball's farthest root from the head's centre (cm)
REACH = 16.8
#: between the smooth swing's largest change of acceleration there and the switch's (below)
JOLT = 2000.0


def _config(frames=9, **time):
    """3 wisps of :func:`jolt_hairball_config` under a shake of 0.1 rad switching axis every 0.2 s."""
    cfg = jolt_hairball_config(frames=frames, **time)
    cfg.physics.head_amplitude, cfg.physics.head_period = AMPLITUDE, PERIOD
    return cfg.validate()


def test_the_jolt_is_the_change_of_acceleration():
    """A head translated at a constant speed from rest jolts in frames 0 and 1 only
    (the third difference of its positions, at rest before t = 0: v dt, then -v dt;
    divided by dt^2); the shake of these tests jolts in frames 0-1 (the start) and 6-7
    (the switch of axis), 1.3-3.0e3 cm/s^2 at the roots' 16.8 cm from the centre, against
    at most 1.32e3 in between (these scenes' farthest root); a static head never."""
    dt = 1.0 / 30.0
    move = HeadMotion(PhysicsConfig(head_motion="translate", head_velocity=(3.0, 4.0, 0.0)))
    assert np.allclose([move.jolt(dt, k, 10.0) for k in range(4)], [5.0 / dt, 5.0 / dt, 0.0, 0.0],
                       rtol=1e-9, atol=1e-6)
    shake = HeadMotion(PhysicsConfig(head_motion="shake", head_amplitude=AMPLITUDE, head_period=PERIOD))
    jolts = np.array([shake.jolt(dt, k, REACH) for k in range(9)])
    assert list(np.flatnonzero(jolts > JOLT)) == [1, 6, 7]
    turn = AMPLITUDE * np.sin(2.0 * np.pi * dt / PERIOD)        # frame 0: |R(dt) - I| = 2 sin(turn / 2)
    assert jolts[0] == pytest.approx(REACH * 2.0 * np.sin(turn / 2.0) / dt ** 2, rel=1e-12)
    assert np.allclose(jolts[[0, 1, 6, 7]], [1309.02, 2618.04, 2961.56, 2961.56], rtol=1e-5)
    assert jolts[[2, 3, 4, 5, 8]].max() < 1320.0
    still = HeadMotion(PhysicsConfig(head_motion="static"))
    assert [still.jolt(dt, k, 10.0) for k in range(3)] == [0.0, 0.0, 0.0]


@pytest.mark.mpi
def test_jolt_frames_converge_then_the_count_resumes():
    """The plain count leaves the switch's frames 6 and 7 above 100x the tolerance; with
    ``time.jolt_above`` they run to ``start_increment_tol = 1e-6`` (``newton_jolt`` True
    on exactly them, converged below it in more iterations) besides the two start
    frames, and every other frame takes the count of 3 (``newton_converged`` None); every
    rank count takes the same iterations and follows the serial run within 1e-10."""
    plain = run_positions(_config(), comm=comm)[1]
    cfg = _config(start_increment_tol=TOL, jolt_above=JOLT)
    X, summ = run_positions(cfg, comm=comm)
    its, inc = summ["newton_iterations"], summ["newton_increment"]
    jolts = [False] * 6 + [True, True, False]
    ok = plain["newton_iterations"] == [3] * 9 and min(plain["newton_increment"][6:8]) > 100 * TOL
    msg = f"plain run: iterations {plain['newton_iterations']}, increments {plain['newton_increment']}"
    if ok:
        ok = (summ["newton_jolt"] == jolts and summ["newton_start"] == [True, True] + [False] * 7
              and summ["newton_converged"] == [True, True, None, None, None, None, True, True, None]
              and max(inc[k] for k in (0, 1, 6, 7)) < TOL and min(its[k] for k in (0, 1, 6, 7)) > 3
              and [its[k] for k in (2, 3, 4, 5, 8)] == [3] * 5)
        msg = (f"{comm.size} ranks: jolt {summ['newton_jolt']}, converged {summ['newton_converged']}, "
               f"iterations {its}, last increments {inc}")
    assert_follows_serial(cfg, X, its, ok, msg, comm)


def test_jolt_frames_widen_each_window():
    """``time.jolt_frames = 2``: each frame above the bound and the frame after it; the
    start's jolts (frames 0 and 1, start frames anyway) add frame 2, the switch's (6, 7)
    add frame 8; all of them below the tolerance, the others at the count of 3."""
    X, summ = run_positions(_config(start_increment_tol=TOL, jolt_above=JOLT, jolt_frames=2), comm=MPI.COMM_SELF)
    windows = [2, 6, 7, 8]
    assert summ["newton_jolt"] == [k in windows for k in range(9)]
    assert max(summ["newton_increment"][k] for k in [0, 1] + windows) < TOL
    assert [summ["newton_iterations"][k] for k in (3, 4, 5)] == [3, 3, 3]
    assert min(summ["newton_iterations"][k] for k in windows) > 3


def test_a_restart_inside_the_jolt_window_continues_bit_for_bit(tmp_path):
    """A checkpoint after frame 6, between the switch's two jolt frames: the restarted run
    converges frame 7 as the uninterrupted one did and writes its frames bit for bit."""
    text = hairball_toml(n_wisps=2, frames=9, output="previews = false\nxdmf = false\ncheckpoint_every = 1") \
        .replace("head_period = 0.4", f"head_period = {PERIOD}\nhead_amplitude = {AMPLITUDE}") \
        .replace("[time]\n", f"[time]\nstart_increment_tol = {TOL}\njolt_above = {JOLT}\n") \
        .replace("[output]", '[solver]\noptions = "-ksp_rtol 1e-12"\n[output]')
    cfg = tmp_path / "s.toml"
    cfg.write_text(text)
    ref, out = tmp_path / "ref", tmp_path / "out"
    assert main([str(cfg), "--out", str(ref), "--quiet"]) == 0
    assert main([str(cfg), "--out", str(out), "--quiet", "--frames", "7"]) == 0
    assert main([str(cfg), "--out", str(out), "--quiet", "--restart",
                 str(out / "checkpoints" / "checkpoint_000007.h5")]) == 0
    whole, rest = (json.loads((d / "summary.json").read_text()) for d in (ref, out))
    assert whole["newton_jolt"] == [False] * 6 + [True, True, False]
    assert rest["newton_jolt"] == [True, False] and rest["newton_converged"] == [True, None]
    assert rest["newton_iterations"] == whole["newton_iterations"][7:] and rest["newton_iterations"][0] > 3
    with h5py.File(ref / "frames.h5") as a, h5py.File(out / "frames.h5") as b:
        assert np.array_equal(a["time"][...], b["time"][...])
        assert np.array_equal(a["positions"][...], b["positions"][...])


@pytest.mark.parametrize("fields, words", [
    (dict(start_increment_tol=1e-3, jolt_above=-1.0), "time.jolt_above must be a finite positive number"),
    (dict(start_increment_tol=1e-3, jolt_above=0.0), "time.jolt_above must be a finite positive number"),
    (dict(start_increment_tol=1e-3, jolt_above="500"), "time.jolt_above must be a number"),
    (dict(start_increment_tol=1e-3, jolt_above=float("nan")), "time.jolt_above must be a finite positive"),
    (dict(jolt_above=500.0), "time.jolt_above = 500.0 converges the frames where the head jolts to "
                             "time.start_increment_tol, which is not set"),
    # with a tolerance: drop it (setting start_increment_tol, as the message above says, is refused too)
    (dict(newton_increment_tol=1e-4, jolt_above=500.0), "with time.newton_tol or time.newton_increment_tol set "
                                                        "every frame already converges: drop time.jolt_above"),
    (dict(newton_tol=1e-4, jolt_above=500.0), "already converges: drop time.jolt_above"),
    (dict(start_increment_tol=1e-3, jolt_above=500.0, jolt_frames=0), "time.jolt_frames must be an integer >= 1"),
    (dict(start_increment_tol=1e-3, jolt_above=500.0, jolt_frames=1.5), "time.jolt_frames must be an integer >= 1"),
    (dict(start_increment_tol=1e-3, jolt_above=500.0, jolt_frames=101), "time.jolt_frames = 101 is more than 100"),
])
def test_bad_jolt_settings_are_refused(fields, words):
    with pytest.raises(ConfigError, match=words.replace("(", r"\(").replace(".", r"\.")):
        TimeConfig(**fields).validate()


def test_the_jolt_key_with_a_still_head_is_warned():
    """``time.jolt_above`` with a static head, ``time.jolt_frames`` without
    ``time.jolt_above``, change nothing: the configuration says so, naming the key."""
    time = {"start_increment_tol": 1e-3, "jolt_above": 500.0, "jolt_frames": 2}
    cfg = config_from_dict({"time": time, "physics": {"head_motion": "static"}})
    assert [w.split(" is set")[0] for w in cfg.key_warnings] == ["time.jolt_above"]
    assert config_from_dict({"time": time, "physics": {"head_motion": "shake"}}).key_warnings == []
    cfg = config_from_dict({"time": {"start_increment_tol": 1e-3, "jolt_frames": 2}})
    assert [w.split(" is set")[0] for w in cfg.key_warnings] == ["time.jolt_frames"]
    assert "time.jolt_above set" in cfg.key_warnings[0]
