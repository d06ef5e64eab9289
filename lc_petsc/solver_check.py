"""The main job's check of its linear solver before frame 0 (exit 2 instead of a run
that writes frame 0 and then fails).

PETSc accepts option values that only fail at the first solve: ``-ksp_max_it -5``
(DIVERGED_MAX_IT at frame 0), ``-ksp_rtol 1`` (every solve "converges" before its first
iteration: a zero Newton step, no error at all), a ``-pc_type`` this PETSc cannot set
up for the operator's matrix type or on several ranks (``ilu`` on MPIBAIJ), a MUMPS
control out of range, a Krylov method or preconditioner that breaks down on a symmetric
positive definite system.  Two checks, both asking PETSc, not a list of solvers:

* :func:`tolerance_problems`: the tolerances the simulator's KSP read from the options
  (``KSPGetTolerances`` after ``setFromOptions``) against what a solve to a relative
  tolerance needs;
* :func:`trial_solve`: the simulator's own solver (:class:`LinearSolver` of the same
  plan) set up and run on a small SPD system of the same matrix type and layout (a few
  4-vertex "wisps" per rank), under a copy of the options with their own prefix (so the
  run's options are not marked used by it and monitors and views are left out).  A
  PETSc error, or a solve that ends with a divergence other than the iteration cap
  (which says nothing about the real system, a different size), refuses the run.
"""

from __future__ import annotations

import dataclasses
import difflib
import re
import shlex
from pathlib import Path

import numpy as np
from petsc4py import PETSc

from lc_petsc.errors import ConfigError
from lc_petsc.options import diagnostic_option

#: the options prefix of the trial solver's copy of the options
TRIAL_PREFIX = "lc_trial_"
#: the trial system: wisps per rank, vertices per wisp
TRIAL_WISPS, TRIAL_VERTICES = 2, 4
#: PETSc's default absolute tolerance (``-ksp_atol``): a relative tolerance of 0 with it
#: never stops a solve by its residual
PETSC_ATOL = 1e-50


def _where(name, command_line):
    return "on the command line" if name in command_line else "in the config's [solver] options"


def tolerance_problems(ksp, prefix, command_line):
    """Problems (messages) of the tolerances ``ksp`` read from the options (its prefix
    ``prefix``; ``command_line``: the options given there, for saying where a value
    came from)."""
    rtol, atol, dtol, max_it = ksp.getTolerances()
    out = []

    def bad(key, value, why):
        name = prefix + key
        out.append(f"-{name} {value:g} ({_where(name, command_line)}): {why}")
    if max_it < 1:
        bad("ksp_max_it", max_it, "the cap of Krylov iterations per linear solve must be a whole "
                                  "number >= 1 (lc_petsc's default is 1000); PETSc accepts it, but "
                                  "the first solve would fail at frame 0")
    if not 0.0 <= rtol < 1.0 or (rtol == 0.0 and atol <= PETSC_ATOL):
        bad("ksp_rtol", rtol, "a solve stops once its residual is below rtol times the right-hand "
                              "side's, so it must be between 0 and 1 (e.g. 1e-6): >= 1 stops before "
                              "the first iteration (a zero Newton step, no error), <= 0 never stops "
                              "(0 only with an absolute tolerance -ksp_atol)")
    if atol < 0.0:
        bad("ksp_atol", atol, "an absolute residual tolerance must be >= 0")
    if dtol <= 1.0:
        bad("ksp_divtol", dtol, "a solve is called diverged once its residual grows this many times "
                                "the first; it must be > 1 (PETSc's default is 1e4)")
    return out


def _trial_matrix(mat_type, n_local, prefix, comm):
    """A small SPD matrix (bs 3, block tridiagonal within each wisp of TRIAL_VERTICES
    vertices) of type ``mat_type`` with ``n_local`` rows on this rank."""
    A = PETSc.Mat().create(comm=comm)
    A.setSizes(((n_local, PETSc.DECIDE), (n_local, PETSc.DECIDE)))
    A.setBlockSize(3)
    A.setOptionsPrefix(prefix)
    A.setType(mat_type)
    A.setFromOptions()
    A.setUp()
    A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    if "sbaij" in A.getType():
        A.setOption(PETSc.Mat.Option.IGNORE_LOWER_TRIANGULAR, True)
    # anisotropic diagonal blocks, so a wrong block solve is not the identity's
    diag = np.array([[4.0, 1.0, 0.0], [1.0, 5.0, 1.0], [0.0, 1.0, 6.0]])
    first = A.getOwnershipRange()[0] // 3
    for v in range(n_local // 3):
        g = first + v
        A.setValuesBlocked([g], [g], diag)
        if v % TRIAL_VERTICES:
            A.setValuesBlocked([g], [g - 1], -np.eye(3))
            A.setValuesBlocked([g - 1], [g], -np.eye(3))
    A.assemble()
    return A


def trial_solve(plan, comm):
    """Set up and run ``plan``'s linear solver on a small SPD system (see the module
    doc); raises :class:`ConfigError` naming PETSc's reason (collective)."""
    from lc_petsc.job import petsc_error_text
    from lc_petsc.solver import LinearSolver, reason_name
    from lc_petsc.solver_plan import SolverPlan
    pcomm = PETSc.Comm(comm)
    opts = PETSc.Options()
    copied = []
    for name, value in opts.getAll().items():
        if name.startswith(plan.prefix) and not name.startswith(TRIAL_PREFIX) \
                and not diagnostic_option(name):
            opts.setValue(TRIAL_PREFIX + name, value)
            copied.append(TRIAL_PREFIX + name)
    A = P = solver = None
    try:
        trial = SolverPlan.resolve(_config_options(plan), strand_contact=plan.contact_pc is not None,
                                   prefix=TRIAL_PREFIX + plan.prefix)
        trial = dataclasses.replace(trial, ksp_rtol=plan.ksp_rtol)
        rows = 3 * TRIAL_VERTICES * TRIAL_WISPS
        with trial.active():
            A = _trial_matrix(trial.mat_type, rows, TRIAL_PREFIX + plan.prefix, pcomm)
            if trial.pmat_type is not None:
                P = A.convert(trial.pmat_type)
        solver = LinearSolver(A, [3 * TRIAL_VERTICES] * TRIAL_WISPS, trial, P=P)
        # the cap may be too small for a test system of another size (not refused below);
        # -ksp_error_if_not_converged would raise it as an error here
        solver.ksp.setErrorIfNotConverged(False)
        x, b = A.createVecs()
        x.setArray(np.linspace(1.0, 2.0, rows))
        A.mult(x, b)
        x.set(0.0)
        try:
            with trial.active():
                solver.ksp.solve(b, x)
        except PETSc.Error as e:
            raise ConfigError(f"the linear solver fails to set up or solve a small symmetric positive "
                              f"definite test system: {petsc_error_text(e)}; solver "
                              f"{solver.describe()}; choose options this PETSc supports for that "
                              f"matrix type on {comm.size} rank(s) (e.g. an option set of "
                              f"configs/solvers/*.opts)") from None
        reason = solver.ksp.getConvergedReason()
        if reason < 0 and reason != PETSc.KSP.ConvergedReason.DIVERGED_MAX_IT:
            raise ConfigError(f"the linear solver fails on a small symmetric positive definite test "
                              f"system ({reason_name(reason)} after {solver.ksp.getIterationNumber()} "
                              f"iterations): the Newton systems are symmetric positive definite, so "
                              f"use a Krylov method and preconditioner for those (e.g. -ksp_type cg "
                              f"with the default per-wisp block Jacobi); solver {solver.describe()}")
    except PETSc.Error as e:
        raise ConfigError(f"PETSc rejected the solver set-up: {petsc_error_text(e)}") from None
    finally:
        for obj in (solver, P, A):
            if obj is not None:
                obj.destroy()
        for name in copied:
            opts.delValue(name)


def _config_options(plan):
    """The plan's config options as an options string (values quoted)."""
    return " ".join(f"-{k} {shlex.quote(v)}" if v else f"-{k}" for k, v in plan.options.items())


def petsc_option_names():
    """(names, patterns): the option names this PETSc library knows (without the dash),
    read from its string literals (``"-ksp_rtol"``: PETSc queries its options by
    literal names), and the formatted ones (``-pc_fieldsplit_%d_fields``) as regular
    expressions.  Options of packages this PETSc was built without are not among them."""
    path = next((line.split()[-1] for line in Path("/proc/self/maps").read_text().splitlines()
                 if "/libpetsc" in line), None)
    if path is None:
        return None
    data = Path(path).read_bytes()
    # (PETSc's option names are case-insensitive)
    names = {m.decode().lower() for m in re.findall(rb"-([A-Za-z][A-Za-z0-9_]{1,80})\x00", data)}
    patterns = [re.compile(re.sub(r"%[-0-9.l]*[sdD]", "[a-z0-9_]+", m.decode().lower()) + "$")
                for m in re.findall(rb"\x00-([A-Za-z][A-Za-z0-9_]*%[-0-9.l]*[sdD][A-Za-z0-9_%]*)\x00", data)]
    return names, patterns


def unknown_options(given, known=None):
    """Problems (messages) of the options ``given`` ({name: where}, without dashes) that
    neither this PETSc (:func:`petsc_option_names`, behind any prefix: ``sub_pc_type``
    is ``pc_type``) nor lc_petsc (:data:`LC_OPTIONS`) knows: typos, which PETSc would
    only list at the end with ``-options_left``."""
    from lc_petsc.solver_plan import LC_OPTIONS
    given = {k: w for k, w in given.items() if k not in LC_OPTIONS}
    if not given:
        return []
    known = petsc_option_names() if known is None else known
    if known is None:
        return []
    names, patterns = known
    out = []
    for name, where in sorted(given.items()):
        name = name.lower()
        tails = [name] + [name[i + 1:] for i, ch in enumerate(name) if ch == "_"]
        if any(t in names or any(p.match(t) for p in patterns) for t in tails):
            continue
        if name.startswith("lc_"):
            close = difflib.get_close_matches(name, LC_OPTIONS, n=1)
        else:
            close = difflib.get_close_matches(name, names, n=1)
            if not close:       # a prefix (sub_, tr_) kept in front of the suggestion
                for i in (i for i, ch in enumerate(name) if ch == "_"):
                    close = [name[:i + 1] + c for c in difflib.get_close_matches(name[i + 1:], names, n=1)]
                    if close:
                        break
        hint = f": did you mean -{close[0]}?" if close else ""
        out.append(f"-{name} ({where}) is not an option of this PETSc or of lc_petsc (a typo, or an "
                   f"option of a package this PETSc was built without){hint} PETSc would ignore it")
    return out


def check_solver(sim, command_line):
    """Refuse (:class:`ConfigError`) a simulator ``sim`` whose linear solver would fail
    at the first solve: options nobody knows (:func:`unknown_options`), its tolerances
    (:func:`tolerance_problems`), then a trial solve (:func:`trial_solve`);
    ``command_line``: the PETSc options given there.  Collective."""
    given = {sim.plan.prefix + k: _where(sim.plan.prefix + k, command_line) for k in sim.plan.options}
    given.update({k: "on the command line" for k in command_line})
    problems = unknown_options(given)
    if problems:
        raise ConfigError("; ".join(problems))
    problems = tolerance_problems(sim.solver.ksp, sim.plan.prefix, command_line)
    if problems:
        raise ConfigError("; ".join(problems))
    trial_solve(sim.plan, sim.comm)
