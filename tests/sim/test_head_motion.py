"""The head's prescribed motion (lc_petsc/scene/kinematics.py): the shake's angle and
its angular velocity, with and without ``physics.head_smooth``."""

import numpy as np
import pytest

from lc_petsc.config import PhysicsConfig
from lc_petsc.scene.kinematics import _AXES, SMOOTH_PEAK, HeadMotion, _rotation

A, T = 0.5, 1.0


def _head(smooth):
    return HeadMotion(PhysicsConfig(head_motion="shake", head_amplitude=A, head_period=T,
                                    head_smooth=smooth))


def _omega(head, t, h=1e-7):
    """Angular velocity (3,) at t from the rotation over [t, t + h]."""
    R0, R1 = head.transform(t)[0], head.transform(t + h)[0]
    W = (R1 @ R0.T - R1.T @ R0) / (2 * h)          # skew part of dR R^T
    return np.array([W[2, 1], W[0, 2], W[1, 0]])


def _expected(t, smooth):
    """The head's rotation at t from the documented formulas (signed angle, axis z, y, x)."""
    k = int(np.floor(t / T))
    tau = t / T - k
    angle = (A * np.sin(2 * np.pi * tau) * np.sin(np.pi * tau) / SMOOTH_PEAK if smooth
             else A * np.sin(2 * np.pi * t / T))
    return _rotation(_AXES[k % 3], angle)


TIMES = (0.1, 0.37, 0.9, 1.2, 1.61, 2.25, 2.9, 3.4)


@pytest.mark.parametrize("smooth", [False, True])
def test_shake_rotation_is_the_documented_one(smooth):
    """Both profiles, signed, on each axis in turn (z, y, x, then z again)."""
    head = _head(smooth)
    for t in TIMES:
        np.testing.assert_allclose(head.transform(t)[0], _expected(t, smooth), rtol=0, atol=1e-13)
    if smooth:      # a different rotation from the sine's away from the swings' ends
        assert all(np.abs(head.transform(t)[0] - _expected(t, False)).max() > 1e-3 for t in TIMES)


@pytest.mark.parametrize("switch", [0.0, 1.0, 2.0])
def test_smooth_shake_starts_and_ends_each_swing_at_rest(switch):
    """At t = 0 and at each change of axis the sine shake's angular velocity jumps by
    A 2 pi / T (from rest) or sqrt(2) A 2 pi / T (turning by 90 degrees); the smooth
    one's is 0 on both sides."""
    h = 1e-5
    jump = lambda head: np.linalg.norm(_omega(head, switch + h) - (_omega(head, switch - 2 * h)
                                                                   if switch > 0 else 0.0))
    full = A * 2 * np.pi / T
    assert jump(_head(False)) == pytest.approx(full * (np.sqrt(2) if switch > 0 else 1), rel=1e-3)
    assert jump(_head(True)) < 1e-3 * full


def test_smooth_shake_reaches_the_amplitude_both_ways():
    """On every axis the smooth swing reaches +A and -A (the head's rotation there is
    exactly the rotation by +-A about that axis)."""
    head = _head(True)
    c = 1 / np.sqrt(3)                                     # cos(pi tau) at the extremes
    tau_pos, tau_neg = np.arccos(c) / np.pi, np.arccos(-c) / np.pi
    for k in range(3):
        for tau, sign in ((tau_pos, 1.0), (tau_neg, -1.0)):
            np.testing.assert_allclose(head.transform((k + tau) * T)[0], _rotation(_AXES[k], sign * A),
                                       rtol=0, atol=1e-12)


def test_head_smooth_must_be_a_boolean():
    from lc_petsc.config import ConfigError
    with pytest.raises(ConfigError, match="physics.head_smooth must be true or false, got 'false'"):
        PhysicsConfig(head_motion="shake", head_smooth="false").validate()


def test_a_time_asked_again_is_not_computed_again(monkeypatch):
    """A step asks the head for the same few times a dozen times (hairball10: 20 rotations
    computed per frame); the last four times' transforms and sphere centres are kept:
    each time's rotation is computed once, the kept arrays are read-only and equal to
    fresh ones, and a fifth time drops the oldest."""
    from lc_petsc.scene import kinematics
    head = HeadMotion(PhysicsConfig(head_motion="shake", head_amplitude=A, head_period=T,
                                    head_center=(0.5, -1.0, 2.0)))
    fresh = HeadMotion(PhysicsConfig(head_motion="shake", head_amplitude=A, head_period=T,
                                     head_center=(0.5, -1.0, 2.0)))
    expected = {t: fresh.transform(t) for t in TIMES[:5]}
    calls = []
    real = kinematics._rotation
    monkeypatch.setattr(kinematics, "_rotation", lambda *a: calls.append(a) or real(*a))
    for _ in range(3):
        for t in TIMES[:4]:
            R, Tr = head.transform(t)
            c = head.sphere_center(t)
            assert np.array_equal(R, expected[t][0]) and np.array_equal(Tr, expected[t][1])
            assert np.array_equal(c, head.center + expected[t][1])
    assert len(calls) == 4
    R, Tr = head.transform(TIMES[0])
    with pytest.raises(ValueError, match="read-only"):
        R[0, 0] = 2.0
    with pytest.raises(ValueError, match="read-only"):
        head.sphere_center(TIMES[0])[0] = 2.0
    head.transform(TIMES[4])                 # a fifth time: TIMES[0] is dropped
    head.transform(TIMES[1])
    assert len(calls) == 5
    assert np.array_equal(head.transform(TIMES[0])[0], expected[TIMES[0]][0])
    assert len(calls) == 6


def test_a_pair_of_times_asked_again_is_not_computed_again():
    """A step asks for its rigid motion (t, t + dt) three times (the first iterate's carry,
    the limiter's field, the frame end) and the next step for it once more; the last four
    pairs' (Q, q) are kept (hairball10: 3 computed per frame, now 1.1), read-only and equal
    to the formula's bit for bit."""
    head = HeadMotion(PhysicsConfig(head_motion="shake", head_amplitude=A, head_period=T,
                                    head_center=(0.5, -1.0, 2.0)))
    fresh = HeadMotion(PhysicsConfig(head_motion="shake", head_amplitude=A, head_period=T,
                                     head_center=(0.5, -1.0, 2.0)))
    pairs = [(0.1, 0.2), (0.2, 0.3), (0.0, 0.1), (0.3, 0.4)]
    for t0, t1 in pairs * 2:
        Q, q = head.rigid_motion(t0, t1)
        (R0, T0), (R1, T1) = fresh.transform(t0), fresh.transform(t1)
        assert np.array_equal(Q, R1 @ R0.T) and np.array_equal(q, fresh.center + T1 - (fresh.center + T0) @ Q.T)
        assert head.rigid_motion(t0, t1) is head.rigid_motion(t0, t1)
    with pytest.raises(ValueError, match="read-only"):
        head.rigid_motion(*pairs[0])[0][0, 0] = 2.0
    with pytest.raises(ValueError, match="read-only"):
        head.rigid_motion(*pairs[0])[1][0] = 2.0
    kept = head.rigid_motion(*pairs[0])
    head.rigid_motion(0.4, 0.5)              # a fifth pair: the oldest, pairs[0], is dropped
    assert head.rigid_motion(*pairs[0]) is not kept
