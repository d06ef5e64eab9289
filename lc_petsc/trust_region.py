"""Trust-region Newton (``time.newton = "trust_region"``, docs/newton.md, fifth round).

Each Newton iteration minimises the quadratic model of the incremental potential G,

    q(d) = g . d + 1/2 d^T H d,   H = M/dt^2 + the exact (unfiltered) Hessian,

within a trust region ||d||_2 <= radius (cm, over all free coordinates of all ranks),
preconditioned by P = M/dt^2 + the filtered Hessian (``solver.filter``, positive
definite): PETSc's trust-region CG (KSPSTCG, KSPNASH or KSPGLTR, Steihaug-Toint CG and
its variants) stops on the region's boundary or along a direction of negative curvature
of H, so the exact Hessian's indefiniteness far from the solution costs a shorter step
instead of a discarded solve.  With the per-wisp exact block Jacobi, P^-1 g is the
filtered Newton step.  (Measured with PETSc 3.18: ``KSPCGGetNormD`` after a STCG solve
is the Euclidean norm of the step, not its P-norm, and ``KSPCGGetObjFcn`` equals
g . d + 1/2 d^T H d to round-off; ``tests/sim/test_trust_region.py``.)

* KSP: options prefix ``tr_`` (``-tr_ksp_type stcg|nash``, ``-tr_ksp_rtol`` ...);
  the code defaults (:data:`DEFAULTS`, the per-wisp block Jacobi and its exact
  sub-solver) are put into the options database, the command line and the config's
  options win, and ``setFromOptions`` is called last: no KSP type is set in code.
  The radius is set by ``KSPCGSetRadius`` and the model's value read by
  ``KSPCGGetObjFcn`` and ``KSPCGGetNormD`` (lc_petsc/petsc_capi.py; petsc4py 3.18 has
  no binding).  A KSP type that is not a trust-region CG is a configuration error.
* First radius of each backward-Euler step: ||P^-1 g||_2, the length of the filtered
  Newton step (one preconditioner application), so nothing is carried between frames
  (restarts and cutback substeps start alike).
* Radius update (Nocedal & Wright, Algorithm 4.1): rho = actual / predicted decrease of
  G (actual along the configured update, the edge retraction by default); rho < 1/4:
  radius = ||d|| / 4; rho > 3/4 with the step on the boundary: radius doubled; the
  step is kept if rho > :data:`ETA`.  When both decreases are at the round-off of G
  the step is kept (rho is noise there, and the step is then tiny anyway).
"""

from __future__ import annotations

from types import MappingProxyType

import numpy as np
from petsc4py import PETSc

from lc_petsc.errors import ConfigError, SolverError
from lc_petsc.petsc_capi import (bjacobi_set_local_blocks, cg_get_norm_d, cg_get_obj_fcn,
                                 cg_set_radius)
from lc_petsc.solver import ksp_solve, reason_name

#: KSP types with a trust region (the ``tr_`` prefixed KSP's ``-tr_ksp_type``).  KSPGLTR
#: is refused: with PETSc 3.18 it aborted the process ("double free or corruption") on
#: the 10-wisp hairball (docs/newton.md, fifth round)
TRUST_REGION_KSPS = ("stcg", "nash")
#: code defaults of the ``tr_`` KSP (options database; the options win)
DEFAULTS = MappingProxyType({"tr_ksp_type": "stcg", "tr_ksp_rtol": "1e-6",
                             "tr_ksp_max_it": "1000", "tr_pc_type": "bjacobi"})
#: a step is kept when rho = actual / predicted decrease exceeds ETA
ETA = 1e-4
#: a rejected step is solved again with the shrunk radius at most this many times per
#: Newton iteration (each shrinks it by 4 or more: 4^-10 of the first radius)
TRUST_RETRIES = 10
#: decreases below this times |G| are round-off: the step is kept
ROUNDOFF = 1e-13


class Region:
    """A backward-Euler step's trust-region state: the radius (None before the first
    iterate), whether the last step was kept and interior (not on the boundary) and
    whether its decrease of G agreed with the model's
    (:func:`lc_petsc.newton_stop.model_agrees`)."""

    def __init__(self):
        self.radius = None
        self.interior = False
        self.agrees = False             # and its decrease agreed with the model (model_agrees)


class TrustRegionSolver:
    """The trust-region KSP: operator the exact Newton matrix ``A`` (the assembler's),
    preconditioner built from :attr:`P`, a copy this class owns that the integrator
    fills with the filtered matrix.  ``wisp_rows`` (n_local_wisps,) rows per wisp."""

    def __init__(self, A, wisp_rows, plan):
        self.plan = plan
        self.P = A.duplicate()
        self.ksp = ksp = PETSc.KSP().create(comm=A.getComm())
        ksp.setOptionsPrefix(plan.prefix + "tr_")
        ksp.setOperators(A, self.P)
        self._defaults = {**DEFAULTS, **{f"tr_{k}": v for k, v in plan.sub_solver.items()}}
        with plan.active(self._defaults):
            pc = ksp.getPC()
            pc.setFromOptions()
            if plan.wisp_blocks == "separate":
                bjacobi_set_local_blocks(pc, wisp_rows)
            elif plan.wisp_blocks == "fused":
                bjacobi_set_local_blocks(pc, [int(np.sum(wisp_rows))])
            ksp.setFromOptions()
        kind = ksp.getType()
        if kind not in TRUST_REGION_KSPS:
            self.destroy()
            why = " (gltr aborts the process with PETSc 3.18)" if kind == "gltr" else ""
            raise ConfigError(f"time.newton = \"trust_region\" needs a trust-region CG, got "
                              f"-tr_ksp_type {kind}{why}; use one of {', '.join(TRUST_REGION_KSPS)}")
        self.type = kind
        self.iterations: list[int] = []
        self.reasons: list[str] = []
        self._z = A.createVecs()[0]

    def destroy(self):
        """Destroy the KSP and the preconditioning matrix (collective)."""
        self.ksp.destroy()
        self.P.destroy()
        if hasattr(self, "_z"):
            self._z.destroy()

    def filtered_step_norm(self, b):
        """||P^-1 b||_2 (all ranks): the length of the filtered Newton step (with the
        per-wisp exact block Jacobi), the first radius.  ``b`` = -grad G (PETSc Vec);
        P must be filled."""
        with self.plan.active(self._defaults):
            self.ksp.setUp()
            self.ksp.getPC().apply(b, self._z)
        return float(self._z.norm())

    def solve(self, b, x, radius, frame, newton_it):
        """The trust-region step for right-hand side ``b`` = -grad G into ``x``, within
        ``radius``.  Returns (model decrease -q(x), ||x||_2, on the boundary or along
        negative curvature).  Records iterations and reason; raises
        :class:`SolverError` when the KSP diverges (P indefinite: a filter that is not
        positive semi-definite)."""
        cg_set_radius(self.ksp, radius)
        with self.plan.active(self._defaults):
            ksp_solve(self.ksp, b, x)
        r = self.ksp.getConvergedReason()
        its = self.ksp.getIterationNumber()
        self.iterations.append(int(its))
        self.reasons.append(reason_name(r))
        if r < 0:
            raise SolverError(
                f"trust-region solve failed at frame {frame}, Newton iteration {newton_it}: "
                f"{reason_name(r)} ({r}) after {its} iterations (-tr_ksp_type {self.type}, "
                f"radius {radius:.3g})", reason=int(r))
        boundary = r in (PETSc.KSP.ConvergedReason.CONVERGED_CG_NEG_CURVE,
                         PETSc.KSP.ConvergedReason.CONVERGED_CG_CONSTRAINED)
        return -cg_get_obj_fcn(self.ksp), cg_get_norm_d(self.ksp), boundary


def update_radius(radius, rho, norm_d, boundary):
    """The next trust radius after a step of length ``norm_d`` with ratio ``rho``
    (Nocedal & Wright, Algorithm 4.1)."""
    if rho < 0.25:
        return 0.25 * norm_d
    if rho > 0.75 and boundary:
        return 2.0 * radius
    return radius


def ratio(actual, predicted, G):
    """rho = actual / predicted decrease; 1 when both are at the round-off of G."""
    tiny = ROUNDOFF * max(abs(G), 1.0)
    if abs(actual) <= tiny and abs(predicted) <= tiny:
        return 1.0
    return actual / predicted if predicted > 0 else -np.inf
