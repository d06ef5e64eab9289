"""A per-wisp trust region for the shifted fallback's exact steps (``solver.wisp_trust``,
docs/newton.md "A trust region per wisp").

Without strand contact the exact steps of ``solver.exact_fallback = "shifted"`` are
searched wisp by wisp (each wisp's own Armijo alpha on its own share of G).  A wisp's
mass shift tau (units of M/dt^2) then works as its trust region: the larger the shift,
the shorter and the more gradient-like its step.  This module carries each wisp's shift
from one exact step to the next, as a Levenberg-Marquardt parameter: a wisp whose step
was cut starts its next step already shortened, instead of taking the long step again
and halving it; a wisp whose step decreased its share of G as its quadratic model
predicted drops its shift.  Pure NumPy, per wisp; the integrator reduces nothing here.
"""

from __future__ import annotations

import numpy as np

from lc_petsc.newton_stop import EXACT_BELOW

#: an uncut step whose model ratio rho is within this of 1 (its decrease of the wisp's
#: share of G as predicted) drops the wisp's shift: the quadratic model holds there
MODEL_EXACT = 0.1
#: an uncut step with its model off by more keeps a quarter of its shift
SHIFT_DECAY = 0.25
#: shifts below this (units of M/dt^2) are dropped: they shorten a step little, and a
#: shifted step is no Newton step for the stopping rule
SHIFT_FLOOR = 0.2
#: ``solver.wisp_trust``: exact steps start once the relative increment is below this
#: (the filter's EXACT_BELOW is 3e-3; measured side by side, docs/newton.md)
WISP_TRUST_BELOW = 1e-2
#: ... but right after a solve's first (filtered) step only below this (the filter's own
#: switch, the same value by design): a frame's first two steps from the inertial first
#: iterate undo each other, and exact steps from the iterate between them met blocks that needed shifts of
#: 30-480 M/dt^2 and cuts to alpha 1/32 (the 300-wisp demo's slow frames, docs/newton.md
#: "The whole runs")
FIRST_STEP_BELOW = EXACT_BELOW
#: ... and after two steps only if the second was at most this times the first (it did
#: not undo it); from the third step on the increment alone decides
UNDONE_RATIO = 0.5


def model_ratio(decrease, slope, curvature, alpha, share, floor):
    """Per wisp, rho = actual / predicted decrease of its share of G for the step
    alpha dx: predicted -(alpha g.dx + alpha^2 / 2 dx^T H dx).  ``decrease`` G_w(x) -
    G_w(x + step), ``slope`` g_w . dx_w, ``curvature`` dx_w^T H_w dx_w (the unshifted
    Hessian), ``share`` |G_w| for the round-off test: where the predicted decrease is
    below ``floor`` times it, rho is noise and is returned as 1."""
    predicted = -(alpha * slope + 0.5 * alpha ** 2 * curvature)
    noise = np.abs(predicted) <= floor * np.abs(share)
    return np.where(noise, 1.0, decrease / np.where(noise, 1.0, predicted))


def next_shifts(tau, alpha, slope, mass_norm, rho):
    """Each wisp's shift for its next exact step (units of M/dt^2), from the last one's
    ``tau`` (the shift its block was solved with), its Armijo factor ``alpha``, slope
    g_w . dx_w, mass norm dx_w^T M/dt^2 dx_w and model ratio ``rho``:

    * a cut step (alpha < 1): the shift that would have made the step alpha times as
      long along its own direction, tau + q (1 / alpha - 1), with q = -g.dx / dx^T M
      dx / dt^2 the Rayleigh quotient of the shifted block along the step;
    * an uncut step whose model held (|rho - 1| < :data:`MODEL_EXACT`): 0;
    * another uncut step: tau times :data:`SHIFT_DECAY`;

    and 0 below :data:`SHIFT_FLOOR`.  Where the block is still indefinite at that shift
    the integrator adds its least definite shift on top, as for any exact step."""
    tau, alpha, slope, mass_norm, rho = (np.asarray(a, float) for a in (tau, alpha, slope, mass_norm, rho))
    has_norm = mass_norm > 0.0
    q = np.where(has_norm, -slope / np.where(has_norm, mass_norm, 1.0), 0.0)
    cut = alpha < 1.0
    shift = np.where(np.abs(rho - 1.0) < MODEL_EXACT, 0.0, SHIFT_DECAY * tau)
    shift = np.where(cut, tau + q * (1.0 / np.where(cut, alpha, 1.0) - 1.0), shift)
    return np.where(shift < SHIFT_FLOOR, 0.0, shift)


def exact_switch(measures):
    """Whether exact steps may start after this solve's steps of relative increments
    ``measures`` (in order; the last below :data:`WISP_TRUST_BELOW`): after one step
    only below :data:`FIRST_STEP_BELOW`, after two only if the second is below
    :data:`UNDONE_RATIO` times the first, after more always."""
    if len(measures) == 1:
        return measures[0] < FIRST_STEP_BELOW
    if len(measures) == 2:
        return measures[1] < UNDONE_RATIO * measures[0]
    return len(measures) > 2
