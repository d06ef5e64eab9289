"""Prescribed kinematics: the head (a rigid motion about its centre) carries the pinned
roots and the head sphere.

x(t) = c + T(t) + R(t) (x_rest - c) for pinned vertices; sphere centre c + T(t).
``static``: R = I, T = 0.  ``shake``: rotation back and forth about z, then y, then x
(each axis for one ``period``, angle ``amplitude * sin(2 pi tau)``, tau = t / period
within the axis's period), repeating.  Its angular velocity is largest where the angle
is 0, so it jumps from 0 at t = 0 and turns by 90 degrees at every change of axis: the
roots are kicked to full speed in one step.  With ``smooth`` the angle is
``amplitude * sin(2 pi tau) sin(pi tau) / SMOOTH_PEAK`` (the same extremes, reached
later): every swing starts and ends at rest, so the angular velocity is continuous.
``translate``: R = I, T = ``velocity`` * t.
"""

from __future__ import annotations

import numpy as np

_AXES = (np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0]))

#: max over tau of sin(2 pi tau) sin(pi tau) = 2 s^2 c at c = cos(pi tau) = 1 / sqrt(3)
SMOOTH_PEAK = 4.0 / (3.0 * np.sqrt(3.0))
#: how many times' transforms and sphere centres a HeadMotion keeps (a step's start, end,
#: the step before it, and a cut-back step's midpoint)
TIMES_KEPT = 4


def _rotation(axis, angle):
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


class HeadMotion:
    """The head's rigid motion over time (``physics.head_motion``: static, shake or translate) and its sphere."""

    def __init__(self, physics):
        self.kind = physics.head_motion
        self.center = np.asarray(physics.head_center, float)
        self.radius = float(physics.head_radius)
        self.amplitude = float(physics.head_amplitude)
        self.period = float(physics.head_period)
        self.smooth = bool(physics.head_smooth)
        self.velocity = np.asarray(physics.head_velocity, float)
        # {t: (R, T)} and {t: centre} of the last few times asked (:meth:`transform`)
        self._transforms: dict = {}
        self._centres: dict = {}
        self._motions: dict = {}        # {(t0, t1): (Q, q)}, :meth:`rigid_motion`

    def transform(self, t):
        """The head's rotation (3, 3) and translation (3,) at time ``t`` (read-only
        arrays).  A step asks for the same few times (its start, its end, the step before)
        a dozen times over (the Newton iterations' head passes, the first iterate, the
        frame end), so the last :data:`TIMES_KEPT` times' are kept."""
        return _kept(self._transforms, t, lambda: tuple(_read_only(a) for a in self._transform(t)))

    def _transform(self, t):
        """:meth:`transform` computed."""
        if self.kind == "shake":
            k = np.floor(t / self.period)
            axis = _AXES[int(k) % 3]
            if self.smooth:
                tau = t / self.period - k
                ang = self.amplitude * np.sin(2.0 * np.pi * tau) * np.sin(np.pi * tau) / SMOOTH_PEAK
            else:
                ang = self.amplitude * np.sin(2.0 * np.pi * t / self.period)
            return _rotation(axis, ang), np.zeros(3)
        if self.kind == "translate":
            return np.eye(3), self.velocity * t
        return np.eye(3), np.zeros(3)

    def max_angular_speed(self):
        """An upper bound of the head's angular speed (rad/s).  Each axis's angle is 0 at
        its period's ends, so a step across a change of axis turns by at most this times
        the step too (its two rotations' angles add up to at most that)."""
        if self.kind != "shake":
            return 0.0
        # d/dtau sin(2 pi tau) sin(pi tau) = 2 pi cos(2 pi tau) sin(pi tau) + pi sin(2 pi tau)
        # cos(pi tau), at most 3 pi
        peak = 3.0 * np.pi / SMOOTH_PEAK if self.smooth else 2.0 * np.pi
        return peak * abs(self.amplitude) / self.period

    def velocity_jumps(self, t0, t1):
        """Whether the head's velocity jumps at a time in [t0, t1) (the times taken to
        round-off: a millionth of the step): the start from rest at t = 0 of a head that
        moves at once (``shake`` without ``smooth``, ``translate`` with a velocity) and
        each change of axis of a ``shake`` without ``smooth`` (t = k ``period``: its
        angular velocity turns by 90 degrees).  A ``smooth`` shake starts and changes
        axis at rest and a static head never moves: never.  A pure function of the
        scene's motion (the same on every rank and after a restart);
        ``time.jolt_first_iterate`` (``Integrator._first_iterate``, with the start's
        weights of lc_petsc/predictors.py ``start_carry_weight``).  Not :meth:`jolt` (a
        change of acceleration above ``time.jolt_above``, which also finds a smooth shake's
        changes of axis): at those the velocity is continuous and the carried first
        iterate did as well (docs/newton.md "The head's jolts' first iterate", review60)."""
        slack = 1e-6 * (float(t1) - float(t0))
        if self.kind == "translate":
            jump_times = [0.0] if np.any(self.velocity != 0.0) else []
        elif self.kind == "shake" and not self.smooth and self.amplitude != 0.0:
            jump_times = [np.ceil((float(t0) - slack) / self.period) * self.period]
        else:
            jump_times = []
        return any(t0 - slack <= s < t1 - slack for s in jump_times)

    def _rotations(self, t):
        """The rotations (n, 3, 3) of :meth:`transform` at the times ``t`` (n,), shake only."""
        k = np.floor(t / self.period)
        if self.smooth:
            tau = t / self.period - k
            ang = self.amplitude * np.sin(2.0 * np.pi * tau) * np.sin(np.pi * tau) / SMOOTH_PEAK
        else:
            ang = self.amplitude * np.sin(2.0 * np.pi * t / self.period)
        axes = np.array(_AXES)[np.fmod(k, 3).astype(int)]
        K = np.zeros((len(t), 3, 3))
        K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axes[:, 2], axes[:, 1], -axes[:, 0]
        K -= K.transpose(0, 2, 1)
        return np.eye(3) + np.sin(ang)[:, None, None] * K + (1.0 - np.cos(ang))[:, None, None] * (K @ K)

    def largest_turn(self, dt, frames, above=None, chunk=1 << 14):
        """(degrees, step): the largest rotation of the head over one step of ``dt`` among
        the first ``frames`` steps from t = 0, and the first step that turns by it.  With
        ``above``: the steps are looked at in chunks (of ``chunk``, in time order) and the
        largest of those up to the first chunk holding a turn beyond ``above`` degrees is
        returned (the steps were a Python list of every rotation: time.frames = 1e8 hung
        the set-up)."""
        if self.kind != "shake" or frames <= 0:
            return 0.0, 0
        best, where = 1.0, 0          # the cosine of the largest turn, and its step
        for k0 in range(0, frames, chunk):
            k = np.arange(k0, min(k0 + chunk, frames) + 1, dtype=float)
            R = self._rotations(k * dt)
            cos = (np.einsum("nij,nij->n", R[1:], R[:-1]) - 1.0) / 2.0
            j = int(np.argmin(cos))
            if cos[j] < best:
                best, where = float(cos[j]), k0 + j
            if above is not None and np.degrees(np.arccos(np.clip(best, -1.0, 1.0))) > above:
                break
        return float(np.degrees(np.arccos(np.clip(best, -1.0, 1.0)))), where

    def jolt(self, dt, frame, reach):
        """How much the head's acceleration changes from frame ``frame - 1`` to frame
        ``frame`` (cm/s^2; frame k is the step from k dt to (k + 1) dt): the third difference
        of its motion over the times (frame - 2 .. frame + 1) dt, at rest before t = 0 (a
        run starts at rest), divided by dt^2, at its largest over the points at distance
        ``reach`` (cm) from the centre (a bound: the translation's plus ``reach`` times the
        rotation's spectral norm).  A pure function of the scene's motion: the same on
        every rank and after a restart.  Frames 0 and 1 of a moving head and the frames
        at and after a shake's change of axis are its jolts (docs/newton.md, "Twenty-third
        round")."""
        times = [max(frame + j, 0) * float(dt) for j in (-2, -1, 0, 1)]
        motions = [self._transform(t) for t in times]
        weights = (-1.0, 3.0, -3.0, 1.0)
        d3_rot = sum(w * R for w, (R, _) in zip(weights, motions))
        d3_shift = sum(w * T for w, (_, T) in zip(weights, motions))
        change = np.linalg.norm(d3_shift) + float(reach) * np.linalg.norm(d3_rot, 2)
        return float(change) / float(dt) ** 2

    def pinned_positions(self, x_rest, t):
        """Positions (n, 3) of pinned vertices at rest positions ``x_rest`` carried by the head to time ``t``."""
        R, T = self.transform(t)
        return self.center + T + (x_rest - self.center) @ R.T

    def carry(self, x, t0, t1):
        """Positions ``x`` (n, 3) at t0 moved rigidly with the head to t1: where
        :meth:`pinned_positions` takes pinned vertices."""
        R0, T0 = self.transform(t0)
        R1, T1 = self.transform(t1)
        return self.center + T1 + (x - self.center - T0) @ R0 @ R1.T

    def rigid_motion(self, t0, t1):
        """(Q (3, 3), q (3,)): the head's rigid motion from t0 to t1 as x -> Q x + q, so
        that :meth:`carry` is ``x @ Q.T + q`` (to round-off).  Read-only arrays, kept for
        the last :data:`TIMES_KEPT` pairs of times (a step asks for its own three times:
        the first iterate's carry, the limiter's field, the frame end; and the next step
        for the one before it)."""
        return _kept(self._motions, (t0, t1), lambda: self._rigid_motion(t0, t1))

    def _rigid_motion(self, t0, t1):
        """:meth:`rigid_motion` computed."""
        R0, T0 = self.transform(t0)
        R1, T1 = self.transform(t1)
        Q = R1 @ R0.T
        return _read_only(Q), _read_only(self.center + T1 - (self.center + T0) @ Q.T)

    def sphere_center(self, t):
        """Centre (3,) of the head sphere at time ``t`` (a read-only array, kept for the
        last :data:`TIMES_KEPT` times as :meth:`transform`)."""
        return _kept(self._centres, t, lambda: _read_only(self.center + self.transform(t)[1]))


def _read_only(a):
    """``a`` (a new array) made read-only: a kept result is shared by its callers."""
    a.flags.writeable = False
    return a


def _kept(kept, t, compute):
    """``kept[t]`` (``t``: a time or a pair of times), made by ``compute()`` and kept if
    new, the oldest dropped beyond :data:`TIMES_KEPT` (dicts keep their insertion order)."""
    value = kept.get(t)
    if value is None:
        value = compute()
        if len(kept) >= TIMES_KEPT:
            del kept[next(iter(kept))]
        kept[t] = value
    return value
