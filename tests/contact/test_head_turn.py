"""ccd strand contact refuses a head that turns by more than the limiter's
MAX_RIGID_DEGREES in one step (beyond it the demo's wisps crossed and its root edges
stretched 8x, docs/contact.md "The head's turn per step"), and says which dt works."""

import re
from pathlib import Path

import numpy as np
import pytest

from lc_petsc.config import ConfigError, load_config
from lc_petsc.contact import MAX_RIGID_DEGREES
from lc_petsc.scene.kinematics import HeadMotion
from lc_petsc.simulator import check_head_turn

DEMO = Path(__file__).resolve().parents[2] / "configs" / "hairball_demo.toml"


def _demo(dt, amplitude=1.0, period=1.0, mode="ccd", frames=30):
    cfg = load_config(DEMO)
    cfg.time.dt, cfg.time.frames = dt, frames
    cfg.physics.head_amplitude, cfg.physics.head_period = amplitude, period
    cfg.physics.strand_contact_mode = mode
    return cfg


def test_largest_turn_is_the_steps_angle_change_within_an_axis():
    cfg = _demo(0.01, amplitude=0.4, period=2.0, frames=150)     # z only (t < period)
    turn, step = HeadMotion(cfg.physics).largest_turn(0.01, 150)
    t = np.arange(151) * 0.01
    angle = 0.4 * np.sin(2 * np.pi * t / 2.0)
    steps = np.degrees(np.abs(np.diff(angle)))
    assert turn == pytest.approx(steps.max(), rel=1e-9)
    assert step == int(np.argmax(steps)) == 0


def test_largest_turn_across_changes_of_axis_is_the_relative_rotations_angle():
    from scipy.spatial.transform import Rotation
    cfg = _demo(0.13, amplitude=0.7, period=1.0, frames=40)        # z, y, x, z, ...
    head = HeadMotion(cfg.physics)
    turn, step = head.largest_turn(0.13, 40)
    R = [head.transform(0.13 * k)[0] for k in range(41)]
    angles = [np.degrees(Rotation.from_matrix(R[k + 1] @ R[k].T).magnitude()) for k in range(40)]
    assert turn == pytest.approx(max(angles), rel=1e-9) and step == int(np.argmax(angles))


def test_static_and_translating_heads_do_not_turn():
    cfg = _demo(0.1)
    cfg.physics.head_motion = "translate"
    assert HeadMotion(cfg.physics).largest_turn(0.1, 30) == (0.0, 0)


def test_a_head_turning_too_far_per_step_is_refused_with_a_dt_that_works():
    cfg = _demo(0.1)
    with pytest.raises(ConfigError) as e:
        check_head_turn(cfg)
    msg = str(e.value)
    assert "time.dt = 0.1" in msg and f"{MAX_RIGID_DEGREES:.2f} degrees" in msg, msg
    dt = float(re.search(r"use time\.dt <= ([0-9.e-]+)", msg).group(1))
    assert 0.07 < dt < 0.1
    check_head_turn(_demo(dt, frames=int(np.ceil(3.0 / dt))))          # the advice holds
    with pytest.raises(ConfigError):
        check_head_turn(_demo(1.1 * dt, frames=int(np.ceil(3.0 / dt))))    # and is tight


@pytest.mark.parametrize("change", ["penalty", "no contact"])
def test_only_ccd_contact_is_limited(change):
    cfg = _demo(0.1, mode="penalty" if change == "penalty" else "ccd")
    if change == "no contact":
        cfg.physics.terms = tuple(t for t in cfg.physics.terms if t != "strand_collision")
    check_head_turn(cfg)


def test_the_job_refuses_it_before_building_anything(tmp_path, capsys):
    from mpi4py import MPI
    from lc_petsc.batch import main
    text = DEMO.read_text().replace("head_amplitude = 0.5", "head_amplitude = 1.0")
    text = re.sub(r"(?m)^dt = .*$", "dt = 0.1", text)
    cfg = DEMO.parent / "test_head_turn_tmp.toml"           # beside solvers/ (a relative path)
    cfg.write_text(text)
    try:
        code = main([str(cfg), "--out", str(tmp_path / "o"), "--quiet"], comm=MPI.COMM_SELF)
    finally:
        cfg.unlink()
    assert code == 2
    err = capsys.readouterr().err
    assert re.search(r"the head turns by 3\d\.\d degrees in step \d+ \(time\.dt = 0\.1,", err), err
    assert not (tmp_path / "o").exists()


def test_pairs_the_limiter_left_unresolved_are_reported(tmp_path, monkeypatch):
    """Whatever the cause, frames where the limiter could not keep a pair apart are
    named in a warning (they were only a per-frame count in summary.json)."""
    import json
    from mpi4py import MPI
    from lc_petsc.batch import main
    from lc_petsc.contact import StrandContact
    from sim_helpers import hairball_toml
    text = hairball_toml(n_wisps=3, frames=3).replace(
        '"head_collision"]', '"head_collision", "strand_collision"]\nstrand_contact_mode = "ccd"')
    text = text.replace("[time]\n", '[time]\ninitial_guess = "follow_the_leader"\n')
    (tmp_path / "s.toml").write_text(text)
    safe = StrandContact._safe_fractions

    def one_stuck_pair_in_frame_1(self, *args, **kw):
        out = safe(self, *args, **kw)
        if len(self.unresolved_pairs.sums) == 3:        # frame 1 (entry 0 is before frame 0)
            self.unresolved_pairs.add(1)
        return out
    monkeypatch.setattr(StrandContact, "_safe_fractions", one_stuck_pair_in_frame_1)
    assert main([str(tmp_path / "s.toml"), "--out", str(tmp_path / "o"), "--quiet"], comm=MPI.COMM_SELF) == 0
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    stuck = s["contact"]["ccd_unresolved_pairs_per_frame"]
    assert stuck[1] > 0 and stuck[0] == stuck[2] == 0, stuck
    w = [m for m in s["warnings"] if "could not resolve" in m]
    assert len(w) == 1 and f"in 1 frame(s) (first: 1; {stuck[1]} over its calls" in w[0], w


def _no_step_by_step_scan(monkeypatch, limit=10_000):
    """HeadMotion.transform raising after ``limit`` calls: a scan of every step's
    rotation one by one (which held the set-up for hours) fails the test instead."""
    calls = [0]
    transform = HeadMotion.transform

    def counted(self, t):
        calls[0] += 1
        if calls[0] > limit:
            raise RuntimeError(f"more than {limit} head rotations computed one by one")
        return transform(self, t)
    monkeypatch.setattr(HeadMotion, "transform", counted)


def test_a_long_run_of_a_slow_head_is_checked_without_scanning_its_steps(monkeypatch):
    """time.frames = 1e8 of the demo's head: its top speed times dt is within the limit."""
    _no_step_by_step_scan(monkeypatch)
    cfg = _demo(1.0 / 30.0, amplitude=0.5, frames=10 ** 8)
    head = HeadMotion(cfg.physics)
    assert np.degrees(head.max_angular_speed()) / 30.0 == pytest.approx(6.0)     # 2 pi 0.5 rad/s
    check_head_turn(cfg)


@pytest.mark.parametrize("amplitude, period", [(1e308, 1.0), (0.5, 1e-300), (1e6, 1.0)])
def test_a_head_too_fast_for_any_dt_is_refused_saying_so(monkeypatch, amplitude, period):
    """The dt search used to shrink dt for ever (head_amplitude = 1e308: a hung set-up)."""
    _no_step_by_step_scan(monkeypatch)
    cfg = _demo(1.0 / 30.0, amplitude=amplitude, period=period, frames=90)
    with pytest.raises(ConfigError) as e:
        check_head_turn(cfg)
    assert "no time.dt >= 1e-06 s keeps it within that: slow the head" in str(e.value), e.value


def test_the_chunked_scan_matches_the_step_by_step_rotations():
    cfg = _demo(0.07, amplitude=0.9, period=0.8, frames=200)
    for smooth in (False, True):
        cfg.physics.head_smooth = smooth
        head = HeadMotion(cfg.physics)
        R = np.array([head.transform(0.07 * k)[0] for k in range(201)])
        cos = (np.einsum("nij,nij->n", R[1:], R[:-1]) - 1.0) / 2.0
        turns = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        turn, step = head.largest_turn(0.07, 200, chunk=16)
        assert turn == pytest.approx(turns.max(), rel=1e-12) and step == int(np.argmax(turns))
        assert turns.max() <= np.degrees(head.max_angular_speed()) * 0.07       # the bound holds
