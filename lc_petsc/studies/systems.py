"""Record a simulator's Newton systems once; replay them with any named solver set.

:class:`SystemRecorder` wraps ``sim.solver.solve`` from outside (no core change): at
every Newton solve it copies the operator (``sim.assembler.mat``, the recorded matrix
type, BAIJ by default) and the right-hand side, plus the frame's start positions (for
GAMG's rigid-body near-null space) and, with strand contact, the strand matrix A and the
contact matrix C apart (besides their assembled sum).  :func:`replay` then solves exactly those systems
with one option set (``configs/solvers/*.opts``), timing setup and solve separately,
so that differences between sets are the solver's alone.

Each set gets its own solver plan, as a simulator does (:class:`lc_petsc.solver_plan.SolverPlan`:
code defaults < the set's options < the command line; the set's options are in the
database only while its solver uses them, so no set sees another's), the KSP is
:class:`lc_petsc.solver.LinearSolver` itself (per-wisp block Jacobi blocks included) and
the matrix types are the plan's.  One persistent
operator per set is refilled for each system (``MatCopy`` with the same nonzero
pattern), so a direct solver's symbolic factorisation is reused across systems as it
would be in a run.  With strand contact the replay builds the operators the simulator
builds (:meth:`lc_petsc.contact.StrandContact.system`): for ``-lc_contact_pc strands``
and ``clusters`` the Python-shell operator A x + C x over the strand matrix A, which is
also the preconditioning matrix (or its AIJ copy); for ``coupled`` the assembled sum.
"""

from __future__ import annotations

import ctypes
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from petsc4py import PETSc

from lc_petsc.contact import SumOperator
from lc_petsc.parallel import global_max, global_min
from lc_petsc.solver import LinearSolver, reason_name
from lc_petsc.solver_plan import SolverPlan, base_type


@dataclass
class RecordedSystem:
    """One recorded Newton system: operator, right-hand side, start positions, strand matrix."""

    A: PETSc.Mat
    b: PETSc.Vec
    coords: np.ndarray          # (local vertices, 3): positions at the frame's start
    frame: int
    newton_it: int
    coupled: bool = False       # strand contact couples wisps: the pattern varies
    # coupled systems: the strand matrix without the contact matrix C, i.e. the
    # simulator's preconditioning matrix (no entry couples two wisps), and C
    wisp_local: PETSc.Mat | None = None
    C: PETSc.Mat | None = None


class SystemRecorder:
    """Copy every Newton system ``sim`` solves (up to ``max_systems``) from frame
    ``first_frame`` on."""

    def __init__(self, sim, max_systems=None, first_frame=0):
        self.sim = sim
        self.max_systems = max_systems
        self.first_frame = int(first_frame)
        self.systems: list[RecordedSystem] = []
        self.wisp_rows = 3 * np.diff(sim.scene.offsets)
        self._orig = sim.solver.solve

        def solve(b, x, frame, newton_it):
            if frame >= self.first_frame and (self.max_systems is None
                                              or len(self.systems) < self.max_systems):
                A = sim.assembler.mat.copy()
                # strand contact: the simulator's operator is the shell A + C (C the
                # contact matrix, coupling wisps); record the assembled sum, and A alone
                # for the per-wisp block Jacobi (built from A in the simulator too)
                C = getattr(getattr(sim, "strand", None), "C", None)
                wisp_local = None
                if C is not None:
                    wisp_local = A.copy()
                    A.axpy(1.0, C, structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
                    C = C.copy()
                self.systems.append(RecordedSystem(
                    A, b.copy(), np.array(sim.integrator.x, float), int(frame), int(newton_it),
                    coupled=C is not None, wisp_local=wisp_local, C=C))
            return self._orig(b, x, frame, newton_it)

        sim.solver.solve = solve

    def detach(self):
        """Stop recording: restore the simulator's own solve."""
        self.sim.solver.solve = self._orig

    def destroy(self):
        """Destroy the recorded systems' PETSc objects."""
        destroy_systems(self.systems)
        self.systems = []


def destroy_systems(systems):
    """Destroy the PETSc objects of ``systems``."""
    for s in systems:
        for m in (s.A, s.b, s.wisp_local, s.C):
            if m is not None:
                m.destroy()


def option_sets(folder, names=None) -> dict:
    """``{name: options string}`` of ``folder/*.opts`` (``names``: a subset, in order)."""
    from lc_petsc.config import read_options_file
    found = {p.stem: read_options_file(p, "option set ") for p in sorted(Path(folder).glob("*.opts"))}
    if not found:
        raise ValueError(f"no option sets (*.opts files) in {folder}; give a folder of PETSc "
                         "options files such as configs/solvers")
    if names is None:
        order = ["default"] + [n for n in found if n != "default"]
        return {n: found[n] for n in order if n in found}
    missing = [n for n in names if n not in found]
    if missing:
        raise ValueError(f"no option set(s) {missing} in {folder}; available: {sorted(found)}")
    return {n: found[n] for n in names}


def current_rss_mib() -> float:
    """Resident set size of this process now (MiB), from /proc/self/statm."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
    except OSError:   # pragma: no cover - non-Linux
        return float("nan")


def start_memory_window() -> bool:
    """Make the next RSS growth and peak a set's own: give freed heap pages back to the
    OS (glibc ``malloc_trim``), so that memory an earlier set freed is not silently
    reused, and reset the peak RSS (``VmHWM``: 5 written to /proc/self/clear_refs,
    Linux >= 4.0).  False where either is unavailable: the figures are then lower bounds."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:   # pragma: no cover - not Linux/glibc, or not permitted
        return False


def window_peak_rss_mib() -> float:
    """Peak RSS (MiB) since the last :func:`start_memory_window` (``VmHWM``)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:   # pragma: no cover - non-Linux
        pass
    return float("nan")


class BudgetExceeded(Exception):
    """Raised from a KSP monitor when a set has used up its time budget."""


def _convert(A, mat_type):
    base, cur = base_type(mat_type), base_type(A.getType())
    # NB petsc4py's A.convert(t) without ``out`` converts IN PLACE: pass a new Mat
    return A.copy() if base == cur else A.convert(mat_type, PETSc.Mat())


#: a direct reference whose true relative residual is above this is no reference
DIRECT_RESIDUAL_TOL = 1e-8


def direct_solutions(systems, comm):
    """Reference solutions x* = A^-1 b (MUMPS LU on AIJ) of every recorded system.  Each
    is checked (its converged reason and true relative residual ||b - A x|| / ||b|| below
    :data:`DIRECT_RESIDUAL_TOL`): a failed factorisation would make every "error vs
    direct" of the study meaningless, so it raises RuntimeError naming the system."""
    out = []
    for i, s in enumerate(systems):
        A = _convert(s.A, "aij")
        ksp = PETSc.KSP().create(comm=A.getComm())
        ksp.setOperators(A)
        ksp.setType("preonly")
        pc = ksp.getPC()
        pc.setType("lu")
        pc.setFactorSolverType("mumps")
        x = s.b.duplicate()
        try:
            ksp.solve(s.b, x)
            reason = ksp.getConvergedReason()
            r = s.b.duplicate()
            A.mult(x, r)
            r.aypx(-1.0, s.b)
            residual = r.norm() / max(s.b.norm(), 1e-300)
            r.destroy()
        finally:
            ksp.destroy()
            A.destroy()
        if reason <= 0 or not residual <= DIRECT_RESIDUAL_TOL:
            x.destroy()
            raise RuntimeError(f"the direct reference solve (MUMPS LU) of recorded system {i} failed: "
                               f"{reason_name(reason)}, true relative residual {residual:.2e} (above "
                               f"{DIRECT_RESIDUAL_TOL:g}); its errors vs direct would be meaningless: "
                               "run without it (compare_solvers.py --no-reference) or check the system")
        out.append(x)
    return out


def replay(systems, wisp_rows, name, options, comm, budget_s=60.0, references=None,
           check_every=10):
    """Solve ``systems`` with the option set ``options``; one row (dict) per system.

    Times are maxima over ranks.  When the set's accumulated setup + solve time passes
    ``budget_s`` (checked inside the Krylov loop every ``check_every`` iterations and
    between systems, collectively), the current solve is stopped and it and every
    remaining system get ``status = "budget"``: reported, not dropped.
    """
    rows = []
    base = {"set": name, "options": options}
    try:        # as the simulator does
        plan = SolverPlan.resolve(options, strand_contact=any(s.coupled for s in systems))
    except ValueError as e:
        return [dict(base, system=i, status="error", message=str(e)) for i in range(len(systems))]

    comm.Barrier()
    exact_memory = global_min(comm, int(start_memory_window())) == 1
    rss0_local = current_rss_mib()
    rss0 = global_max(comm, rss0_local)
    A, P, owned = _operators(systems[0], plan)
    ls = None
    spent = 0.0
    t_start = [0.0]
    try:
        near_null = None
        if plan.pc_type == "gamg":
            c = PETSc.Vec().createMPI((systems[0].coords.size, PETSc.DECIDE), bsize=3,
                                      comm=A.getComm())
            c.array[:] = systems[0].coords.ravel()
            near_null = PETSc.NullSpace().createRigidBody(c)
            (A if P is None else P).setNearNullSpace(near_null)
            c.destroy()
        t0 = time.perf_counter()
        try:
            ls = LinearSolver(A, wisp_rows, plan, P=P)
        except (PETSc.Error, ValueError) as e:
            msg = f"cannot create the solver: {type(e).__name__} {getattr(e, 'ierr', e)}"
            return [dict(base, system=i, status="error", message=msg) for i in range(len(systems))]
        t_create = global_max(comm, time.perf_counter() - t0)
        ksp = ls.ksp

        def monitor(k, its, rnorm):
            if its and its % check_every == 0:
                over = spent + time.perf_counter() - t_start[0] > budget_s
                if comm.allreduce(int(over)):
                    raise BudgetExceeded(f"time budget {budget_s:g} s used up at Krylov iteration {its}")

        ksp.setMonitor(monitor)
        x = systems[0].b.duplicate()
        stopped = None
        for i, s in enumerate(systems):
            row = dict(base, system=i, frame=s.frame, newton_it=s.newton_it,
                       mat_type=(P if A.getType() == PETSc.Mat.Type.PYTHON else A).getType(),
                       dofs=A.getSize()[0])
            if stopped is not None:
                rows.append(dict(row, status="budget", message=stopped))
                continue
            if i > 0 and any(x.coupled for x in systems):
                # contact changes the pattern from system to system: new operators
                # (direct solvers redo their symbolic factorisation, as they must)
                newA, newP, new_owned = _operators(s, plan)
                if near_null is not None:
                    (newA if newP is None else newP).setNearNullSpace(near_null)
                ksp.setOperators(newA, newA if newP is None else newP)
                for M in owned:
                    M.destroy()
                A, P, owned = newA, newP, new_owned
            elif i > 0:   # refill the persistent operator(s): same pattern, new values
                for M, t in ((A, plan.mat_type), (P, plan.pmat_type)):
                    if M is not None:
                        src = _convert(s.A, t)
                        src.copy(M, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
                        src.destroy()
                # mark the operators as changed so that KSPSetUp (timed as setup) redoes
                # the preconditioner; otherwise KSPSolve would do it inside the solve time
                ksp.setOperators(A, A if P is None else P)
            x.set(0.0)
            comm.Barrier()
            t_start[0] = time.perf_counter()
            try:
                with plan.active():
                    ksp.setUp()
                    ksp.getPC().setUpOnBlocks()   # block Jacobi factors its blocks here
                    t_setup = global_max(comm, time.perf_counter() - t_start[0])
                    t1, c1 = time.perf_counter(), time.process_time()
                    ksp.solve(s.b, x)
                t_solve = global_max(comm, time.perf_counter() - t1)
                c_solve = global_max(comm, time.process_time() - c1)
            except BudgetExceeded as e:
                stopped = str(e)
                spent += global_max(comm, time.perf_counter() - t_start[0])
                rows.append(dict(row, status="budget", message=stopped,
                                 iterations=int(ksp.getIterationNumber())))
                continue
            except PETSc.Error as e:
                rows.append(dict(row, status="error", message=f"PETSc error {e.ierr}"))
                stopped = f"stopped after a PETSc error in system {i}"
                continue
            spent += t_setup + t_solve
            reason = ksp.getConvergedReason()
            r = s.b.duplicate()
            s.A.mult(x, r)
            r.aypx(-1.0, s.b)
            bn = s.b.norm()
            true_res = r.norm() / bn if bn > 0 else 0.0
            rtol = ls.rtol
            status = "ok" if reason > 0 else "diverged"
            # CONVERGED_ITS (preonly, or no convergence test) certifies nothing: as in the
            # simulator (LinearSolver.not_reduced) only the true residual says whether it
            # solved the system (an inexact preconditioner applied once did not, however fast)
            if reason == PETSc.KSP.ConvergedReason.CONVERGED_ITS and not true_res <= rtol:
                status = "inaccurate"
            row.update(status=status,
                       setup_s=t_setup, solve_s=t_solve, total_s=t_setup + t_solve, solve_cpu_s=c_solve,
                       create_s=t_create if i == 0 else 0.0,
                       iterations=int(ksp.getIterationNumber()), reason=reason_name(reason),
                       true_rel_residual=true_res)
            r.destroy()
            if ls.clusters is not None:     # what the contact preconditioner made of this system
                st = ls.clusters.stats
                row.update(cluster_fallback=bool(st.get("fallback")), cluster_captured=st.get("captured"),
                           cluster_couplings=st.get("couplings"),
                           cluster_rows=int(comm.allreduce(st.get("rows", 0))))
            if reason <= 0:
                row["message"] = f"{reason_name(reason)} in system {i}"
            elif status == "inaccurate":
                row["message"] = (f"{reason_name(reason)} (no convergence test) in system {i} with "
                                  f"true relative residual {true_res:.3g} > rtol {rtol:g}")
            if references is not None:
                d = x.duplicate()
                d.waxpy(-1.0, references[i], x)
                xn = references[i].norm()
                row["rel_error_vs_direct"] = d.norm() / xn if xn > 0 else d.norm()
                d.destroy()
            row["rss_delta_mib"] = global_max(comm, current_rss_mib()) - rss0
            row["peak_rss_mib"] = global_max(comm, window_peak_rss_mib())
            # the set's own peak above what the process held before it (max over ranks)
            row["set_peak_mib"] = global_max(comm, window_peak_rss_mib() - rss0_local)
            row["memory_window"] = exact_memory
            rows.append(row)
            if spent > budget_s and i + 1 < len(systems):
                stopped = f"time budget {budget_s:g} s used up after system {i}"
        x.destroy()
    finally:
        if ls is not None:
            ls.destroy()
        for M in owned:
            M.destroy()
    return rows


def _operators(s, plan):
    """(operator, preconditioning matrix or None for the operator, matrices to destroy)
    of the recorded system ``s`` as the simulator builds them (module doc)."""
    if s.coupled and plan.contact_pc in ("strands", "clusters"):
        A = _convert(s.wisp_local, plan.mat_type)
        ctx = SumOperator(A)
        ctx.C = _convert(s.C, plan.mat_type)
        op = PETSc.Mat().createPython(A.getSizes(), context=ctx, comm=A.getComm())
        op.setUp()
        P = _convert(s.wisp_local, plan.pmat_type) if plan.pmat_type else A
        return op, P, [op, A, ctx.C] + ([P] if P is not A else [])
    op = _convert(s.A, plan.mat_type)
    P = _convert(s.A, plan.pmat_type) if plan.pmat_type else None
    return op, P, [op] + ([P] if P is not None else [])
