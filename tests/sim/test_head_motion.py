"""The head's prescribed motion (lc_petsc/scene/kinematics.py): the shake's angle and
its angular velocity, with and without ``physics.head_smooth``."""

import numpy as np
import pytest

from lc_petsc.config import PhysicsConfig
from lc_petsc.scene.kinematics import SMOOTH_PEAK, HeadMotion

A, T = 0.5, 1.0


def _head(smooth):
    return HeadMotion(PhysicsConfig(head_motion="shake", head_amplitude=A, head_period=T,
                                    head_smooth=smooth))


def _omega(head, t, h=1e-7):
    """Angular velocity (3,) at t from the rotation over [t, t + h]."""
    R0, R1 = head.transform(t)[0], head.transform(t + h)[0]
    W = (R1 @ R0.T - R1.T @ R0) / (2 * h)          # skew part of dR R^T
    return np.array([W[2, 1], W[0, 2], W[1, 0]])


def _angle(head, t):
    R = head.transform(t)[0]
    return np.arctan2(np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2,
                      (np.trace(R) - 1) / 2)


def test_sine_shake_is_amplitude_times_sine():
    head = _head(False)
    for t in (0.1, 0.37, 1.2, 2.9):
        assert _angle(head, t) == pytest.approx(abs(A * np.sin(2 * np.pi * t / T)), abs=1e-12)


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
    head = _head(True)
    t = np.linspace(0.0, T, 20001)
    signed = A * np.sin(2 * np.pi * t / T) * np.sin(np.pi * t / T) / SMOOTH_PEAK
    assert signed.max() == pytest.approx(A, rel=1e-6) and signed.min() == pytest.approx(-A, rel=1e-6)
    for ti in (0.2, 0.61, 0.9):
        assert _angle(head, ti) == pytest.approx(abs(A * np.sin(2 * np.pi * ti) * np.sin(np.pi * ti))
                                                 / SMOOTH_PEAK, abs=1e-12)
