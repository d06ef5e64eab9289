"""Linear solver: a KSP from the PETSc options database, with the paper's defaults.

Defaults set in code (the options database, i.e. the config's ``solver.options`` and
then the command line, override them; the command line wins over the config):

* ``-ksp_type cg -ksp_rtol 1e-6 -ksp_max_it 1000``;
* ``-pc_type bjacobi`` with **one exact block per wisp** (the paper's preconditioner).
  The preconditioning matrix never couples two wisps (strand-contact cross blocks live
  in a separate matrix C of the operator, see lc_petsc/contact.py; only the opt-in
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
  round-off for any factorisation sub-solver (tests/test_sim_wisp_blocks.py).  PETSc's
  own default for a symmetric matrix, ICC(0) with a Manteuffel shift, is *not* exact
  here (measured: CG stalls at 1000 iterations on a 4C wisp), and PETSc's native SBAIJ
  (bs 3) Cholesky/ICC were also measured to be inexact on these matrices, so for
  ``-mat_type sbaij`` the sub-solver defaults to MUMPS Cholesky
  (``-sub_pc_type cholesky -sub_pc_factor_mat_solver_type mumps``): with ``fused`` one
  MUMPS factorisation of the rank's block-diagonal matrix, exact as well.
  ``-pc_bjacobi_blocks`` / ``-pc_bjacobi_local_blocks`` (e.g.
  configs/solvers/bjacobi_rank.opts) replace the per-wisp blocks altogether.

Matrix type: MUMPS refuses BAIJ and GAMG refuses BAIJ, so when such a solver is asked
for without ``-mat_type``, :func:`choose_mat_type` picks ``sbaij`` (MUMPS Cholesky) or
``aij``; an explicit ``-mat_type baij`` with them is an error naming the options to use.

Every solve's converged reason is checked; a diverged solve raises :class:`SolverError`
naming frame, Newton iteration, reason and the options (no retry).  A solve that
reports CONVERGED_ITS ran no residual test (``-ksp_type preonly``, ``-ksp_norm_type
none``): its true residual is computed (one matrix product) and a solve above
``-ksp_rtol`` is recorded in ``not_reduced`` (the job then reports the run as not
converged).
"""

from __future__ import annotations

import shlex
from contextlib import contextmanager

import numpy as np
from petsc4py import PETSc

from lc_petsc.options import option_pairs
from lc_petsc.petsc_capi import bjacobi_set_local_blocks, option_used

DEFAULTS = {"ksp_type": "cg", "ksp_rtol": "1e-6", "ksp_max_it": "1000", "pc_type": "bjacobi"}
WISP_BLOCK_MODES = ("fused", "separate")

_REASONS = {getattr(PETSc.KSP.ConvergedReason, n): n for n in dir(PETSc.KSP.ConvergedReason)
            if n.isupper() or n.startswith(("CONVERGED", "DIVERGED", "ITERATING"))}


class SolverError(RuntimeError):
    pass


def reason_name(r: int) -> str:
    return _REASONS.get(r, str(r))


def parse_options(text: str):
    """'-a 1 -flag -b x' -> [('a', '1'), ('flag', ''), ('b', 'x')] (leading dashes removed)."""
    return option_pairs(shlex.split(text or ""), what="solver.options")


class OptionsScope:
    """Layered options: code defaults < config options < options database (command line).

    Entering inserts the config/default options the database does not already hold;
    leaving removes exactly those again, so several simulators in one process (tests)
    do not leak options into each other.  Which of them PETSc (or :meth:`lookup`) used
    while they were in the database is recorded first, for :meth:`unused_options`.
    """

    def __init__(self, config_options: str = "", defaults=None):
        self.layers = dict(defaults or {})
        self.layers.update(dict(parse_options(config_options)))
        self.used = set()

    def lookup(self, key):
        opts = PETSc.Options()
        if opts.hasName(key):
            return opts.getString(key, "")
        if key in self.layers:
            self.used.add(key)
        return self.layers.get(key)

    def unused_options(self, given=()):
        """Options of the config (``solver.*``) and ``given`` (the command line) that
        nothing ever read: typos, or options of a solver that is not selected (PETSc's
        ``-options_left``)."""
        return sorted(k for k in set(self.layers) | set(given)
                      if k not in self.used and not option_used(k))

    def effective(self):
        """The layered options' values in effect (without marking them as used)."""
        db = PETSc.Options().getAll()
        return {k: (db[k] or "") if k in db else self.layers[k] for k in sorted(self.layers)}

    @contextmanager
    def active(self, extra=None):
        opts = PETSc.Options()
        added = []
        layers = dict(extra or {})
        layers.update(self.layers)
        for k, v in layers.items():
            if not opts.hasName(k):
                opts.setValue(k, v)
                added.append(k)
        try:
            yield
        finally:
            for k in added:
                if k not in self.used and option_used(k):    # once known used, no C call
                    self.used.add(k)
                opts.delValue(k)


def choose_mat_type(scope: OptionsScope, default="baij") -> str:
    explicit = scope.lookup("mat_type")
    pc = (scope.lookup("pc_type") or "").lower()
    package = (scope.lookup("pc_factor_mat_solver_type") or "").lower()
    mumps = package == "mumps" and pc in ("cholesky", "lu")
    gamg = pc == "gamg"
    if explicit:
        t = explicit.lower()
        if t.endswith("baij") and not t.endswith("sbaij") and (mumps or gamg):
            need = "-mat_type sbaij or -mat_type aij" if pc == "cholesky" else "-mat_type aij"
            what = "MUMPS" if mumps else "GAMG"
            raise ValueError(f"{what} does not accept BAIJ matrices (-mat_type {explicit}); "
                             f"add {need}")
        return explicit
    if mumps:
        return "sbaij" if pc == "cholesky" else "aij"
    if gamg:
        return "aij"
    return default


def choose_pmat_type(scope: OptionsScope, mat_type: str, strand_contact: bool = False):
    """Matrix type of a separate preconditioning matrix, or None to use the operator.

    ``-lc_pmat_type aij|same``; by default an AIJ copy (same values) is made only where
    block Jacobi would extract several blocks per rank from a BAIJ operator (separate
    per-wisp blocks, or blocks set by ``-pc_bjacobi_*blocks``): see
    ``Assembler._create_pmat`` for why.  The fused per-wisp blocks factor the operator's
    rank block itself (no extraction, and BAIJ's 3x3-block ILU(0) is the cheaper one),
    except with ``strand_contact``: CG then runs tens to hundreds of iterations, and
    the block ILU's explicit 3x3 pivot inverses (badly conditioned for stretch-dominated
    blocks) put enough round-off into each application that runs on different rank
    counts drift apart 30x faster (measured: 1.5e-10 vs 5.5e-12 relative after 10
    frames of tests/test_mpi_contact.py on 2 ranks) for about the same time per CG
    iteration (11.3 vs 12.5 ms per application at 606k DoFs, plus 0.45 s per frame to
    fill the copy); the point ILU of the AIJ copy is the same factorisation without
    that round-off.  (Re-measured on an AMD EPYC, 2026-12-01, the ranking reversed:
    the drift is dominated by the chaotic 3-iteration Newton map with contact, not by
    the factorisation; docs/architecture.md.)
    """
    explicit = scope.lookup("lc_pmat_type")
    if explicit:
        if explicit not in ("aij", "same"):
            raise ValueError(f"-lc_pmat_type {explicit!r}: use aij or same")
        return None if explicit == "same" else explicit
    pc = (scope.lookup("pc_type") or DEFAULTS["pc_type"]).lower()
    base = mat_type.lower().replace("mpi", "").replace("seq", "")
    extracts = pc == "bjacobi" and (wisp_block_mode(scope) != "fused" or strand_contact)
    return "aij" if extracts and base == "baij" else None


def wisp_block_mode(scope: OptionsScope):
    """``"fused"`` or ``"separate"`` (``-lc_wisp_blocks``, default fused) when the
    preconditioner is the per-wisp block Jacobi; None for another ``-pc_type`` or when
    ``-pc_bjacobi_blocks`` / ``-pc_bjacobi_local_blocks`` set the blocks instead."""
    mode = scope.lookup("lc_wisp_blocks") or WISP_BLOCK_MODES[0]
    if mode not in WISP_BLOCK_MODES:
        raise ValueError(f"-lc_wisp_blocks {mode!r}: use fused (one factorisation of all the "
                         f"rank's wisps, the default) or separate (one PETSc block per wisp)")
    pc = (scope.lookup("pc_type") or DEFAULTS["pc_type"]).lower()
    if pc != "bjacobi" or scope.lookup("pc_bjacobi_blocks") or scope.lookup("pc_bjacobi_local_blocks"):
        return None
    return mode


class LinearSolver:
    """The KSP of the Newton systems.  ``P`` (default: ``A``) must not couple two wisps
    when the per-wisp block Jacobi is ``fused`` (see the module doc); with strand
    contact and ``-lc_contact_pc coupled`` it does, and the fused block is then an
    ILU(0) of the coupled rank matrix, not per-wisp LUs (docs/contact.md)."""

    def __init__(self, A, wisp_rows, scope: OptionsScope, mat_type: str, P=None):
        self.scope = scope
        self.wisp_blocks = wisp_block_mode(scope)
        # exact per-wisp sub-solves (see module doc); PETSc would pick ICC(0) with a
        # Manteuffel shift for a symmetric matrix, which is not exact here
        if mat_type == "sbaij":
            self.extra = {"sub_pc_type": "cholesky", "sub_pc_factor_mat_solver_type": "mumps"}
        else:
            self.extra = {"sub_pc_type": "ilu"}
        self.ksp = ksp = PETSc.KSP().create(comm=A.getComm())
        ksp.setOperators(A, A if P is None else P)
        with scope.active(self.extra):
            ksp.setType(DEFAULTS["ksp_type"])
            ksp.setTolerances(rtol=float(DEFAULTS["ksp_rtol"]), max_it=int(DEFAULTS["ksp_max_it"]))
            pc = ksp.getPC()
            pc.setType(DEFAULTS["pc_type"])
            if self.wisp_blocks == "separate":
                bjacobi_set_local_blocks(pc, wisp_rows)
            elif self.wisp_blocks == "fused":
                bjacobi_set_local_blocks(pc, [int(np.sum(wisp_rows))])
            ksp.setFromOptions()
        self.iterations = []
        self.reasons = []
        self.rtol = float(ksp.getTolerances()[0])
        self.not_reduced = []        # (solve index, true relative residual) of unchecked solves

    def describe(self):
        pc = self.ksp.getPC()
        A, P = self.ksp.getOperators()
        blocks = f" -lc_wisp_blocks {self.wisp_blocks}" if self.wisp_blocks else ""
        return (f"-ksp_type {self.ksp.getType()} -pc_type {pc.getType()}{blocks} "
                f"-mat_type {A.getType()} (preconditioner built from {P.getType()}) "
                f"(options: {self.scope.effective()})")

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
        with self.scope.active(self.extra):
            self.ksp.solve(b, x)
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
                f"{reason_name(r)} ({r}) after {its} iterations; solver {self.describe()}")
        return its
