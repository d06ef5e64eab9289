"""Newton's stopping arithmetic (docs/newton.md "Stopping rule"): pure functions of a
solve's step measures that :class:`lc_petsc.integrator.Integrator` asks whether an
iterate may stop.  The contraction factor that turns the last increment into an error
bound (:func:`contraction_factor`, :func:`step_contraction`) and the positions' round-off
below which a step needs no bound (:func:`round_off_floor`), the loose-tolerance rule
(:func:`confirms_stop`, :func:`model_agrees`), and the estimates of
``time.newton_stop``: ``"quadratic_estimate"`` (:func:`quadratic_error_estimate`) and
``"chord_estimate"`` (:func:`chord_basis`, :func:`chord_stop`), with their constants; and
the notes on stops for the monitor and a missed tolerance's message (:func:`unconfirmed_note`)."""

from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np


class StepRecord(NamedTuple):
    """One Newton step as the stop test reads it (:func:`step_contraction`): its relative
    increment ``measure`` (the full step's where the step was damped or cut), whether it
    was ``whole`` (alpha 1, unshifted, not cut, no exact attempt rejected), of the
    ``exact`` Hessian, and a ``newton`` step (unshifted, not after an indefinite exact
    matrix)."""

    measure: float
    whole: bool
    exact: bool
    newton: bool


class SolveRecord(NamedTuple):
    """One backward-Euler step's Newton: iterations, converged (None without a
    tolerance), the last relative increment, exact Hessians replaced by filtered ones,
    chord checks (``time.newton_stop = "chord_estimate"``), with strand contact (pairs,
    deep pairs, min distance, pairs separated), and whether the cap ended it on a stop
    awaiting its confirmation (:func:`confirms_stop`: an increment below the tolerance,
    yet not converged) or on one refused for steps off their quadratic model
    (:meth:`lc_petsc.integrator.Integrator._loose_verdict`; the same), or whether its stop was refused on a
    saddle of G (:meth:`lc_petsc.integrator.Integrator._at_saddle`: ended there, not converged)."""

    iterations: int
    converged: Optional[bool]
    increment: float
    fallbacks: int
    chord_checks: int
    contact: Optional[tuple]
    unconfirmed: bool = False
    refused: bool = False
    saddle: bool = False


class NewtonState:
    """A backward-Euler step's Newton state (:meth:`lc_petsc.integrator.Integrator._newton`),
    updated by its iterations: the iterate and what the stop rules read across them."""

    def __init__(self, x, loose, region, floor=0.0):
        self.x = x                      # the iterate
        self.floor = floor              # the positions' round-off, cm (round_off_floor)
        self.round_off = False          # this iteration's step is at it
        self.n_it = 0
        self.converged = None
        self.increment = self.reported = np.inf     # the last step's; what newton_increment reports
        self.fallbacks = self.chord_checks = 0
        self.steps = []                 # this solve's steps (StepRecord), in order
        self.region = region            # the trust region's (trust_region.Region) or None
        self.quadratic = []             # the increments of the last full exact steps in a row
        self.modelled = []              # and whether each agreed with its quadratic model
        self.claimed_before = False     # the last iteration's stop (to be confirmed)
        self.unbased_claim = False      # ... made by a chord check without chord_basis
        self.loose = loose              # a loose tolerance (confirms_stop)
        self.last_step = self.prior_step = None     # the last two iterations' steps (_model_agrees)
        self.unconfirmed = False        # this iteration's stop awaits the next
        self.off_model = False          # this iteration's stop was refused (_loose_verdict)
        self.saddle = False             # this iteration's stop is on a saddle (_at_saddle)
        self.pending = None             # a refused stop's verifying exact step (_verify_stop)
        self.last = False               # a fixed count (or its extension) ends here (_ends_count)

    def settle(self, claim, step, confirmed, refused):
        """After an iteration's stop test: its claim and step become the last ones."""
        self.claimed_before, self.last_step, self.prior_step = claim, step, self.last_step
        self.unconfirmed, self.off_model = claim and not confirmed, refused


def chord_stop(chord, increment, tol):
    """``time.newton_stop = "chord_estimate"``: whether the chord step's relative
    increment ``chord``, measured after a full exact step of ``increment``, certifies the
    iterate.  It must show the step converging (``chord`` below :data:`CHORD_CONTRACTION`
    times ``increment``: an iteration crawling at 0.5 per step had chord steps below a
    loose tolerance while its next Newton increment was 3-8x above it, docs/newton.md
    "Eleventh round") and lie below ``tol`` with the margin 1 + :data:`CHORD_MARGIN`
    ``increment`` (the chord and Newton steps differ by the change of the Hessian over
    the last step: measured at a tolerance of 3e-4 up to 31%, within 2% at 1e-6)."""
    return chord < CHORD_CONTRACTION * increment and chord * (1.0 + CHORD_MARGIN * increment) < tol


def chord_basis(increments, modelled):
    """``time.newton_stop = "chord_estimate"``: whether the last full exact steps in a
    row (their ``increments``, oldest first, and per step whether it ``modelled``: G's
    decrease agreed with its quadratic model) let a chord step measure the next
    increment: two of them, the last shorter, both on their model (at a loose tolerance
    a check without them may claim, confirmed only by the next iterate's check with
    them).  The chord step uses
    the Hessian of the iterate before the last step; where that Hessian changes over a
    step the chord step is no Newton step (the stiff smash at 1e-6: chord increments
    3-40x below the next Newton increment while the iterate was 200-20000x the
    tolerance away; a stop 2170x away after a damped step, 242x after the first exact
    step; docs/newton.md "Tight tolerances")."""
    return len(increments) >= 2 and increments[-1] < increments[-2] and all(modelled[-2:])


def confirms_stop(tol, absolute=None, length=None):
    """Whether a stop at the relative increment tolerance ``tol`` (None: unset) must be
    confirmed by the next step: above :data:`LOOSE_TOLERANCE`.  Without ``tol``, the
    absolute tolerance ``absolute`` (``time.newton_tol``, cm; None: unset) is taken
    relative to ``length``, the shortest wisp's rest length (alone it had been outside the
    rule: the stiff smash stopped 14x and 138x its 1e-2 and 1e-3 cm away).  There an increment below
    the tolerance, after a sequence that looks quadratic, left frames of crushed curls at
    dt 0.1-0.2 up to 16x the tolerance from their solution (docs/newton.md "Stopping
    rule"); at 1e-6 every stop measured was within 0.33x of it."""
    if tol is None and absolute is not None and length:
        tol = absolute / length
    return tol is not None and tol > LOOSE_TOLERANCE


def model_agrees(decrease, predicted, energy):
    """Whether a whole Newton step's decrease of G, ``decrease``, agrees with the
    quadratic model's prediction ``predicted`` (-g . dx / 2 for a step solving H dx = -g)
    within :data:`MODEL_AGREEMENT`, or the prediction is below round-off
    (:data:`ENERGY_FLOOR` times ``energy``, |G|: there G cannot tell).  Where the model is
    off along a step (the exact Hessian changing faster than the step is long, or a filter
    stiffening it), the step's size does not bound the distance to the solution: at a
    loose tolerance such stops had been claimed 2.4-30x the tolerance from the step's
    solution with |ratio - 1| of 0.25-1.0, while every honest stop on the recommended path
    at dt 1/30 agreed within 0.09 (docs/newton.md "Stopping rule")."""
    if abs(predicted) <= ENERGY_FLOOR * abs(energy):
        return True
    return predicted > 0.0 and abs(decrease / predicted - 1.0) <= MODEL_AGREEMENT



def round_off_floor(scale):
    """The size (cm) below which a Newton step is round-off of the positions: the
    largest coordinate ``scale`` (cm) of the iterate, times the machine epsilon, times
    :data:`ROUND_OFF_STEPS`.  A step of that size carries no information: the gradient
    it solves for is the round-off of G's terms, its increments bounce rather than
    shrink (:func:`contraction_factor` is inf) and its line search halves at noise.  An
    iterate whose step is below it (and below the tolerance) has converged as far as
    the arithmetic allows (docs/newton.md "Stops at round-off")."""
    return ROUND_OFF_STEPS * np.finfo(float).eps * scale


def contraction_factor(increments, whole=None, exact=None, newton=None):
    """What the last of ``increments`` (a Newton solve's relative increments, oldest
    first) must be multiplied by to bound the iterate's remaining error: max(1, q / (1 -
    q)), q the contraction per step over the last two steps, sqrt(d_k / d_{k-2}) (d_k /
    d_{k-1} after two steps): an iteration contracting by q per step has d q / (1 - q)
    still to go after a step of d.  Over two steps because the filtered iterations
    alternate, and because an exact step after a filtered one that grew shows its
    quadratic rate already.  1 after a single step (no rate yet: the increment alone, the
    rule before) or a zero step (a rejected trust-region step), and whenever q <= 1/2
    (fast convergence: the increment bounds the error); inf when the increments did not
    shrink.  The analytic filter crawls at q ~ 0.97 (factor ~ 35: its increment test had
    stopped frames 35-42x the tolerance from the solution, docs/newton.md "Twelfth
    round").

    Per step (None: all True, resp. all False for ``exact``): ``newton``, a Newton step
    of the configured kind (unshifted, no exact attempt rejected before it), ``whole``,
    a Newton step taken whole (alpha 1, not cut), ``exact``, of the exact Hessian.  The
    last step must be a Newton step (a filtered step after a rejected exact attempt had
    stopped the stiff smash 242x the tolerance away), and a rate whose base is a step
    not taken whole measures nothing (a damped step's full measure as its base: 155x),
    so both are inf (the last step may be damped: the caller measures it by its full
    step); over three exact
    steps q is the larger of the two ratios (a Newton iteration in its quadratic basin
    shrinks at every step: 3.2e-6 after 1.5e-6 then 5.5e-7 had stopped the stiff smash
    1.7x away at 1e-6; docs/newton.md "Stopping rule")."""
    moved = [k for k, d in enumerate(increments) if d > 0.0]
    if newton is not None and increments[-1] > 0.0 and not newton[-1]:
        return float("inf")
    if len(moved) < 2 or increments[-1] == 0.0:
        return 1.0
    window = moved[-3:]
    # the last step may be damped: its measure is already its full step's
    if whole is not None and not all(whole[k] for k in window[:-1]):
        return float("inf")
    d = [increments[k] for k in window]
    if len(d) == 2:
        q = d[1] / d[0]
    elif exact is not None and all(exact[k] for k in window):
        q = max(d[1] / d[0], d[2] / d[1])
    else:
        q = float(np.sqrt(d[2] / d[0]))
    if q >= 1.0:
        return float("inf")
    return max(1.0, q / (1.0 - q))


def step_contraction(steps):
    """:func:`contraction_factor` of a solve's :class:`StepRecord` records."""
    return contraction_factor([s.measure for s in steps], [s.whole for s in steps],
                              [s.exact for s in steps], [s.newton for s in steps])


def quadratic_error_estimate(increments, modelled=None):
    """``time.newton_stop = "quadratic_estimate"``: the relative error of the iterate
    after the last of ``increments`` (those of the last full, unshifted exact steps in a
    row, oldest first), estimated from quadratic convergence.  A step's increment d_k is
    the error of the iterate before it, to leading order, and e_{k+1} = C e_k^2, so the
    error after the last step is C d_k^2.  C is measured twice, C = d_k / d_{k-1}^2 and
    d_{k-1} / d_{k-2}^2, and the larger taken: three such steps in a row, each shorter
    than the one before, the middle one below :data:`EXACT_BELOW` (C measured from a
    step above it was 60x too small: a stop 1.3x above the tolerance on the demo
    hairball, docs/newton.md "Eighth round"), and the last two decreasing G as their
    quadratic model predicts (``modelled``, per step; None: all did).  inf otherwise:
    one pair of steps that looks quadratic can be a lull of a wandering iteration (the
    stiff smash at 1e-5: 3.0e-5 then 8.5e-6 after a step that grew, a claimed stop 230x
    the tolerance away; 1.1e-3 then 5.7e-5, a next step of 7.4e-4, 150x away), and a
    step off its model can end a quadratic-looking run that then only halves (jitter
    at 1e-8: 30x; docs/newton.md "Tight tolerances")."""
    if len(increments) < 3 or not increments[-2] < EXACT_BELOW:
        return np.inf
    d0, d1, d = increments[-3:]
    if not d < d1 < d0 or (modelled is not None and not all(modelled[-2:])):
        return np.inf
    return max(d / d1 ** 2, d1 / d0 ** 2) * d ** 2


def stop_note(unconfirmed, refused):
    """The monitor's note on a loose-tolerance stop
    (:meth:`lc_petsc.integrator.Integrator._loose_verdict`)."""
    if unconfirmed:
        return ", stop to be confirmed"
    return ", stop refused: G's decrease off its quadratic model" if refused else ""


def verify_note(verdict, length):
    """The monitor's note on a stop checked by an exact step
    (:meth:`lc_petsc.integrator.Integrator._verify_stop`)."""
    if verdict == "kept":
        return f", stop verified: exact step {length:.3e}"
    if verdict == "far":
        return f", stop refused: the exact step at the stop is {length:.3e} (taken next)"
    if verdict == "off_model":
        return f", stop refused: the exact step at the stop ({length:.3e}) is off its quadratic model (taken next)"
    if verdict in ("indefinite", "short"):
        why = "the exact Hessian is indefinite" if verdict == "indefinite" else "its solve missed -ksp_rtol"
        return f", stop refused: no exact step to verify it ({why})"
    return ""


def saddle_note(wisps):
    """The monitor's note on a stop refused on a saddle of G (:meth:`lc_petsc.integrator.Integrator._at_saddle`):
    the wisps (global indices) whose exact Hessian is not positive definite."""
    more = " ..." if len(wisps) > 8 else ""
    return f", stop refused: a saddle of G (wisps {', '.join(map(str, wisps[:8]))}{more})"


def unconfirmed_note(steps, refused=0, saddles=0):
    """For a missed tolerance's message: why ``steps`` (kept steps the cap ended on an
    unconfirmed stop, :func:`confirms_stop`), ``refused`` (kept steps it ended on a
    stop refused by :meth:`lc_petsc.integrator.Integrator._loose_verdict`) and ``saddles`` (kept steps whose
    stop was refused on a saddle of G, :meth:`lc_petsc.integrator.Integrator._at_saddle`) missed it although
    their last increment is below the tolerance; '' for none."""
    note = ""
    if saddles:
        note += (f"; {saddles} Newton stop(s) refused on a saddle of the step's potential G, not a minimum "
                 f"(an exact Hessian with a negative eigenvalue where the increment passed "
                 f"time.newton_increment_tol): such a stop is refused; step cutback (time.max_substeps "
                 f">= 2) redoes the step in smaller ones, which add inertia (docs/newton.md, "
                 f"\"Saddles of G\")")
    if steps:
        note += (f"; {steps} step(s) ended on an increment below time.newton_increment_tol at the cap: "
                 f"above {LOOSE_TOLERANCE:g} a stop must be confirmed by the next iteration, which "
                 f"time.newton_iterations left out (docs/newton.md, \"Stopping rule\")")
    if refused:
        note += (f"; {refused} step(s) ended on an increment below time.newton_increment_tol whose "
                 f"stop was refused: above {LOOSE_TOLERANCE:g} the last two steps must decrease G as "
                 f"their quadratic model predicts, and where they do not their size says nothing of "
                 f"the distance to the solution (filtered steps rarely do: use solver.filter = "
                 f"\"exact_or_analytic\"; docs/newton.md, \"Stopping rule\")")
    return note


#: time.newton_increment_tol above this: a stop needs two iterations in a row that pass
#: the tolerance, or one whose increment (times the contraction factor) is below this
#: (:func:`confirms_stop`, docs/newton.md "Stopping rule")
LOOSE_TOLERANCE = 1e-5
#: above LOOSE_TOLERANCE a stop also needs its step and the one before it to decrease G
#: as their quadratic model predicts, within this fraction (:func:`model_agrees`;
#: measured: wandering stops 0.25-1.0 off, honest ones on the recommended path <= 0.09)
MODEL_AGREEMENT = 0.1
#: :func:`model_agrees`: a predicted decrease below this times |G| is round-off (the
#: ratio was noise, off by 1.5 to 6e3, below 1e-12 |G| on smash and 1e-15 |G| on the
#: hairball)
ENERGY_FLOOR = 1e-10
#: :func:`round_off_floor`: a step no larger than this many epsilons of the largest
#: coordinate is round-off (the 2K hairball's frame 10 at dt/4 bounced at 5.2e-16 to
#: 6.1e-16 of its 59.6 cm wisps, 5.3-6.2 eps x 26.4 cm; docs/newton.md "Stops at round-off")
ROUND_OFF_STEPS = 256.0
#: solver.filter "exact_or_analytic": the exact Hessian is tried once the last relative
#: increment is below EXACT_BELOW, and its step kept if Armijo's condition holds within
#: EXACT_HALVINGS halvings (lc_petsc/integrator.py; measured, docs/newton.md: 3e-3 and 6
#: reach 1e-6 in the fewest iterations of 1e-2 / 3e-3 / always and 2 / 6 halvings on the
#: hairball and smash); :func:`quadratic_error_estimate` measures C only below it.
EXACT_BELOW = 3e-3
#: ``time.newton_stop = "chord_estimate"`` measures the chord step after a full exact step
#: of increment d when CHORD_TRY_C d^2 < tol: a quadratic step's constant e_{k+1} / e_k^2
#: had quartiles 7.8 and 18 on the 10-wisp hairball (docs/newton.md, "Seventh round"), so
#: from there the next increment may be below the tolerance; farther out the check
#: would fail and cost a solve (measured: 16 checks in 30 frames, 11 stops)
CHORD_TRY_C = 10.0
#: :func:`chord_stop`: the chord step must be this much shorter than the step before it
CHORD_CONTRACTION = 0.1
#: :func:`chord_stop`: the chord increment times 1 + CHORD_MARGIN d must be below the
#: tolerance (d the last increment; 2 C with C up to ~50, the quadratic constants measured)
CHORD_MARGIN = 100.0
#: ``time.newton_stop = "quadratic_estimate"`` stops once the estimated error is below
#: the tolerance / QUADRATIC_SAFETY (C varies between steps; with this factor every stop
#: on the 10-wisp demo hairball and smash was within the tolerance of the converged
#: solution, the worst at 0.58 of it, docs/newton.md "Eighth round")
QUADRATIC_SAFETY = 10.0
