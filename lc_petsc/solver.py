"""Linear solver: the KSP of the Newton systems, built from a :class:`SolverPlan`.

The plan (lc_petsc/solver_plan.py) layers the options and makes lc_petsc's own choices;
this module creates the KSP with the code defaults, which the options override
(``setFromOptions`` last, inside the plan's scope):

* ``-ksp_type cg -ksp_max_it 1000``, ``-ksp_rtol`` 1e-4 for the fixed-count Newton (the
  paper's 3 iterations, whose truncation error is 10-25x the linear error that leaves,
  measured) and 1e-6 when Newton converges to ``time.newton_tol`` or
  ``newton_increment_tol`` (lc_petsc/solver_plan.py, :data:`KSP_RTOL_FIXED_COUNT`);
* ``-pc_type bjacobi`` with **one exact block per wisp** (the paper's preconditioner).
  The preconditioning matrix never couples two wisps (strand-contact cross blocks live
  in a separate matrix C of the operator, see lc_petsc/contact.py; only
  ``-lc_contact_pc coupled`` puts them in), so its rank-local
  diagonal block is block diagonal by wisp, and *one* factorisation of that rank block
  is the set of per-wisp factorisations.  Hence two ways to build the same
  preconditioner, chosen by ``-lc_wisp_blocks``:

  - ``fused`` (default): one block-Jacobi block per rank (``PCBJacobiSetLocalBlocks``
    with one block), one factorisation per Newton iteration and one pair of
    triangular solves per application;
  - ``separate``: PETSc's own block per wisp (``PCBJacobiSetLocalBlocks`` with the
    3 n_w rows of each local wisp): one sub-KSP, sub-matrix and factorisation per
    wisp (about 1,000 per rank of the 2,000-wisp hairball; several times slower).

  ``PCBJacobiSetLocalBlocks`` is called through ctypes (lc_petsc/petsc_capi.py; petsc4py 3.18
  has no binding), before ``setFromOptions``.  Each wisp is solved exactly: the default
  sub-solver ``-sub_pc_type ilu`` (ILU(0), natural ordering) on a full band has no fill
  outside the band, so it *is* the LU factorisation (SPEC 1); and a factorisation of a
  block-diagonal matrix never mixes its blocks, so fused and separate agree to
  round-off for any factorisation sub-solver (tests/sim/test_sim_wisp_blocks.py).  PETSc's
  own default for a symmetric matrix, ICC(0) with a Manteuffel shift, is *not* exact
  here (measured: CG stalls at 1000 iterations on a 4C wisp), and PETSc's native SBAIJ
  (bs 3) Cholesky/ICC were also measured to be inexact on these matrices, so for
  ``-mat_type sbaij`` the sub-solver defaults to MUMPS Cholesky
  (``-sub_pc_type cholesky -sub_pc_factor_mat_solver_type mumps``): with ``fused`` one
  MUMPS factorisation of the rank's block-diagonal matrix, exact as well.
  ``-pc_bjacobi_blocks`` / ``-pc_bjacobi_local_blocks`` (e.g.
  configs/solvers/bjacobi_rank.opts) replace the per-wisp blocks altogether.

With strand contact, ``-lc_contact_pc clusters`` (the default there) grows the fused per-wisp
blocks into clusters of wisps coupled by contact (across ranks by default), each solved
exactly (lc_petsc/contact_pc.py, a ``PCPYTHON`` set up here after ``setFromOptions``: the
options select it, so no ``-pc_type`` can undo it; docs/contact_solver.md).  MUMPS
(``-pc_factor_mat_solver_type mumps``) gets the AMF ordering ``-mat_mumps_icntl_7 2``
as a code default (the plan's sub-solver layer: the options win).

Matrix type: MUMPS refuses BAIJ and GAMG refuses BAIJ, so when such a solver is asked
for without ``-mat_type``, the plan picks ``sbaij`` (MUMPS Cholesky) or ``aij``; an
explicit ``-mat_type baij`` with them is a configuration error naming the options to use.

Every solve's converged reason is checked; a diverged solve raises :class:`SolverError`
naming frame, Newton iteration, reason and the options and carrying PETSc's reason
code (no retry).  A solve that
reports CONVERGED_ITS ran no residual test (``-ksp_type preonly``, ``-ksp_norm_type
none``): its true residual is computed (one matrix product) and a solve above
``-ksp_rtol`` is recorded in ``not_reduced`` (the job then reports the run as not
converged).
"""

from __future__ import annotations

import numpy as np
from petsc4py import PETSc

from lc_petsc.contact_pc import ClusterPC
from lc_petsc.errors import SolverError
from lc_petsc.petsc_capi import bjacobi_set_local_blocks
from lc_petsc.solver_plan import DEFAULTS, SolverPlan

_REASONS = {getattr(PETSc.KSP.ConvergedReason, n): n for n in dir(PETSc.KSP.ConvergedReason)
            if n.isupper() or n.startswith(("CONVERGED", "DIVERGED", "ITERATING"))}


def ksp_solve(ksp, b, x):
    """``ksp.solve(b, x)``, its divergence left to ``getConvergedReason()`` also under
    ``-ksp_error_if_not_converged``, which makes it a PETSc error (on every rank: the
    reason is collective) that aborted the job as an internal error.  Other PETSc
    errors pass."""
    try:
        ksp.solve(b, x)
    except PETSc.Error:
        if ksp.getConvergedReason() >= 0:
            raise


def reason_name(r: int) -> str:
    """PETSc's name of the KSP converged reason ``r`` (its number if unknown)."""
    return _REASONS.get(r, str(r))


#: what to try when an iterative solve fails, each checked on a barrier scene whose CG
#: stalled (docs/contact_solver.md, "When CG fails"; not -ksp_norm_type unpreconditioned:
#: it stops at the same -ksp_rtol with a 10-100x larger error in the Newton step)
ITERATIVE_WAY_OUT = ("; to go on: a direct solve (the options of configs/solvers/mumps_cholesky.opts: "
                     "-ksp_type preonly -pc_type cholesky -pc_factor_mat_solver_type mumps -mat_type "
                     "sbaij, in [solver] options or after the config on the command line), a larger "
                     "-ksp_max_it, a smaller time.dt, or with strand_contact_potential = \"barrier\" a "
                     "smaller physics.strand_barrier_stiffness (docs/contact_solver.md, \"When CG fails\")")


class LinearSolver:
    """The KSP of the Newton systems.  ``P`` (default: ``A``) must not couple two wisps
    when the per-wisp block Jacobi is ``fused`` (see the module doc); with strand
    contact and ``-lc_contact_pc coupled`` it does, and the fused block is then an
    ILU(0) of the coupled rank matrix, not per-wisp LUs (docs/contact.md).  With
    ``-lc_contact_pc clusters``, ``clusters`` is the :class:`ClusterPC` context (None
    otherwise)."""

    def __init__(self, A, wisp_rows, plan: SolverPlan, P=None):
        self.plan = plan
        self.wisp_blocks = plan.wisp_blocks
        self.ksp = ksp = PETSc.KSP().create(comm=A.getComm())
        if plan.prefix:
            ksp.setOptionsPrefix(plan.prefix)
        ksp.setOperators(A, A if P is None else P)
        with plan.active():
            ksp.setType(DEFAULTS["ksp_type"])
            ksp.setTolerances(rtol=float(plan.ksp_rtol), max_it=int(DEFAULTS["ksp_max_it"]))
            pc = ksp.getPC()
            pc.setType(DEFAULTS["pc_type"])
            if self.wisp_blocks == "separate":
                bjacobi_set_local_blocks(pc, wisp_rows)
            elif self.wisp_blocks == "fused":
                bjacobi_set_local_blocks(pc, [int(np.sum(wisp_rows))])
            ksp.setFromOptions()
            self.clusters: ClusterPC | None = None
            if plan.cluster_caps is not None:     # the per-wisp blocks grown into clusters
                self.clusters = ClusterPC(wisp_rows, *plan.cluster_caps)
                pc.setType(PETSc.PC.Type.PYTHON)
                pc.setPythonContext(self.clusters)
        self.iterations: list[int] = []
        self.reasons: list[str] = []
        self.rtol = float(ksp.getTolerances()[0])
        self.not_reduced: list[tuple[int, float]] = []    # (solve index, true rel. residual), unchecked solves

    def describe(self):
        """The solver in use, for messages and summary.json: KSP, PC, matrix types and options."""
        pc = self.ksp.getPC()
        A, P = self.ksp.getOperators()
        blocks = f" -lc_wisp_blocks {self.wisp_blocks}" if self.wisp_blocks else ""
        if self.clusters is not None:
            blocks = " -lc_contact_pc clusters (lc_petsc/contact_pc.py)"
        return (f"-ksp_type {self.ksp.getType()} -ksp_rtol {self.rtol:g} -pc_type {pc.getType()}{blocks} "
                f"-mat_type {A.getType()} (preconditioner built from {P.getType()}) "
                f"(options: {self.plan.effective()})")

    def set_rtol(self, rtol):
        """Solve to the relative tolerance ``rtol`` from the next solve on (the start
        frames of ``time.start_increment_tol`` and the frames after them)."""
        self.ksp.setTolerances(rtol=float(rtol))
        self.rtol = float(rtol)

    def destroy(self):
        """Destroy the KSP (collective); the matrices belong to their owners."""
        self.ksp.destroy()

    def forget_last(self):
        """Drop the last solve's record (a solve the caller replaces by another one)."""
        self.iterations.pop()
        self.reasons.pop()

    def _true_residual(self, b, x):
        """||b - A x|| / ||b|| (0 for b = 0)."""
        A, _ = self.ksp.getOperators()
        r = b.duplicate()
        try:
            A.mult(x, r)
            r.aypx(-1.0, b)
            nb = b.norm()
            return float(r.norm() / nb) if nb > 0 else 0.0
        finally:
            r.destroy()

    def solve(self, b, x, frame, newton_it):
        """Solve A x = b; records iterations and reason, raises :class:`SolverError` on divergence."""
        with self.plan.active():
            ksp_solve(self.ksp, b, x)
        r = self.ksp.getConvergedReason()
        its = self.ksp.getIterationNumber()
        self.iterations.append(int(its))
        self.reasons.append(reason_name(r))
        if r == PETSc.KSP.ConvergedReason.CONVERGED_ITS:
            # no residual test ran (preonly, -ksp_norm_type none): check the true residual
            ratio = self._true_residual(b, x)
            if not ratio <= self.rtol:
                self.not_reduced.append((len(self.reasons) - 1, ratio))
        if r < 0:
            raise SolverError(
                f"linear solve failed at frame {frame}, Newton iteration {newton_it}: "
                f"{reason_name(r)} ({r}) after {its} iterations; solver {self.describe()}"
                + (self.clusters.left_out() if self.clusters is not None else "")
                + (ITERATIVE_WAY_OUT if self.ksp.getType() != "preonly" else ""),
                reason=int(r))
        return its
