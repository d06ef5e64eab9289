"""What one CG iteration with strand contact costs, part by part, against the bytes each
part must read (docs/contact_solver.md, "One CG iteration against the memory bandwidth").

  # once: record a frame's Newton systems (A, C, b apart) into DIR, on P ranks
  mpiexec -n P python scripts/bench_cg_iteration.py record DIR --config CONFIG.toml \
      [--restart CHECKPOINT] [--frames 1]
  # then, on the same P ranks: solve them with the default solver, every part timed
  mpiexec -n P python scripts/bench_cg_iteration.py solve DIR [--repeats 3] [--options "PETSc options"]
  # and each kernel alone on the rank's arrays, warm and with the caches flushed
  mpiexec -n P python scripts/bench_cg_iteration.py kernels DIR [--system 0] [--repeats 20]

``record`` writes each system's strand matrix A, contact matrix C and right-hand side b
in PETSc's binary format with the rank partition of the run (``layout.json``), so later
runs load them in seconds instead of replaying the frame.  ``solve`` builds the
operator and preconditioner as the simulator does (the Python shell A x + C x,
``-lc_contact_pc clusters``), solves every system ``--repeats`` times and reports per CG
iteration, as medians over the solves of each rank's CPU time (``time.thread_time``)
and wall: A's product, C's diagonal block, C's off-rank block, the rest of the shell's
callback (ghost scatter, Python), the per-wisp band solve, the clusters' solve and the
rest of the PC callback, and what KSP does besides (its vector operations and
reductions: PETSc's log events ``VecDot``, ``VecNorm``, ``VecAXPY``, ``VecAYPX``).
``kernels`` times the compiled kernels alone on the same arrays: the symmetric band
product, C's products, the band solve, NumPy's ``a = b + c`` for the stream rate, all
ranks at once (a barrier before each call), with the bytes each reads at least once.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import petsc4py

petsc4py.init([sys.argv[0]])
from mpi4py import MPI  # noqa: E402
from petsc4py import PETSc  # noqa: E402

FLUSH_BYTES = 512 * 2 ** 20     # written between cold calls: beyond this machine's caches


def _save(comm, path, obj):
    viewer = PETSc.Viewer().createBinary(str(path), "w", comm=comm)
    obj.view(viewer)
    viewer.destroy()


def record(args, comm):
    """Run the frame(s) and write every system's A, C and b into ``args.dir``."""
    from lc_petsc.config import load_config
    from lc_petsc.studies.compare import record as record_frames
    config = load_config(args.config)
    systems, wisp_rows, info = record_frames(config, comm, frames=args.frames, restart=args.restart)
    write_systems(Path(args.dir), systems, wisp_rows, info, comm)


def write_systems(out, systems, wisp_rows, info, comm):
    """Write the recorded systems with contact (:func:`lc_petsc.studies.compare.record`'s;
    one without contact pairs is left out) into ``out``."""
    keep = [i for i, s in enumerate(systems) if s.coupled]
    if not keep:
        raise SystemExit("no recorded system has a contact matrix: record a frame with strand contact")
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    comm.Barrier()
    systems = [systems[i] for i in keep]
    for i, s in enumerate(systems):
        _save(comm, out / f"A{i}.bin", s.wisp_local)
        _save(comm, out / f"C{i}.bin", s.C)
        _save(comm, out / f"b{i}.bin", s.b)
    rows = comm.gather([int(r) for r in wisp_rows])
    if comm.rank == 0:
        layout = {"ranks": comm.size, "wisp_rows": rows, "systems": len(systems),
                  "frames": [int(s.frame) for s in systems],
                  "run_ksp_iterations": [int(info["sim_ksp_iterations"][i]) for i in keep],
                  "info": {k: info[k] for k in ("wisps", "dofs", "start_frame", "strand_contact_pairs")}}
        (out / "layout.json").write_text(json.dumps(layout, indent=1))
        print(f"{len(systems)} systems in {out}; CG per solve in the run {layout['run_ksp_iterations']}")


def load(folder, comm):
    """(wisp rows of this rank, [(A, C, b) per system]) from a ``record`` folder."""
    folder = Path(folder)
    layout = json.loads((folder / "layout.json").read_text())
    if layout["ranks"] != comm.size:
        raise SystemExit(f"{folder} was recorded on {layout['ranks']} ranks: run on as many (now {comm.size})")
    rows = np.asarray(layout["wisp_rows"][comm.rank], np.int64)
    n = int(rows.sum())
    out = []
    for i in range(layout["systems"]):
        mats = []
        for name in ("A", "C"):
            viewer = PETSc.Viewer().createBinary(str(folder / f"{name}{i}.bin"), "r", comm=comm)
            M = PETSc.Mat().create(comm=comm)
            M.setType(PETSc.Mat.Type.BAIJ)
            M.setSizes(((n, PETSc.DETERMINE), (n, PETSc.DETERMINE)), bsize=3)
            M.load(viewer)
            viewer.destroy()
            mats.append(M)
        viewer = PETSc.Viewer().createBinary(str(folder / f"b{i}.bin"), "r", comm=comm)
        b = PETSc.Vec().create(comm=comm)
        b.setSizes((n, PETSc.DETERMINE), bsize=3)
        b.load(viewer)
        viewer.destroy()
        out.append((mats[0], mats[1], b))
    return rows, out


class Clock:
    """CPU (this thread) and wall seconds per named part, one list entry per call."""

    def __init__(self):
        self.cpu: dict[str, list[float]] = {}
        self.wall: dict[str, list[float]] = {}

    def wrap(self, name, fn):
        cpu, wall = self.cpu.setdefault(name, []), self.wall.setdefault(name, [])

        def timed(*a, **k):
            c0, w0 = time.thread_time(), time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                cpu.append(time.thread_time() - c0)
                wall.append(time.perf_counter() - w0)
        return timed

    def clear(self):
        for d in (self.cpu, self.wall):
            for v in d.values():
                v.clear()


VEC_EVENTS = ("VecDot", "VecNorm", "VecAXPY", "VecAYPX", "VecTDot", "VecSet", "VecCopy")


def _instrument(op, pc, clock):
    """Wrap the shell's products and the PC's parts (after the set-up, which made them)."""
    ctx = op.getPythonContext()
    for name in ("mult",):
        setattr(ctx, name, clock.wrap("shell mult", getattr(ctx, name)))
    if ctx._band:
        ctx._band = clock.wrap("A product", ctx._band)
    if ctx._contact:
        parts = ctx._contact[0]
        parts[0] = clock.wrap("C diagonal block", parts[0])
        if len(parts) > 1:
            parts[1] = clock.wrap("C off-rank block", parts[1])
    cl = pc.getPythonContext()
    cl.apply = clock.wrap("PC apply", cl.apply)
    if cl.cholesky is not None:
        cl.cholesky.apply = clock.wrap("band solve", cl.cholesky.apply)
    if cl.cluster is not None:
        cl.cluster = _Timed(cl.cluster, clock.wrap("cluster solve", cl.cluster.apply))


class _Timed:
    """A PETSc object (whose methods cannot be replaced) with a timed ``apply``."""

    def __init__(self, obj, apply):
        self.obj, self.apply = obj, apply

    def destroy(self):
        self.obj.destroy()


def solve(args, comm):
    """Solve every recorded system with the default solver, parts timed per iteration."""
    from lc_petsc.contact import SumOperator
    from lc_petsc.solver import LinearSolver
    from lc_petsc.solver_plan import SolverPlan
    rows, systems = load(args.dir, comm)
    plan = SolverPlan.resolve(args.options, strand_contact=True)
    PETSc.Log.begin()
    clock = Clock()
    per_iter: dict[str, list[float]] = {}
    its_all = []
    stats = []
    whole: dict[int, list] = {}     # per system: (setup CPU, setup wall, solve CPU, solve wall) per repeat
    for repeat in range(args.repeats):
        for i, (A, C, b) in enumerate(systems):
            ctx = SumOperator(A)
            ctx.C = C
            op = PETSc.Mat().createPython(A.getSizes(), context=ctx, comm=comm)
            op.setUp()
            ls = LinearSolver(op, rows, plan, P=A)
            ksp = ls.ksp
            x = b.duplicate()
            x.set(0.0)
            comm.Barrier()
            s0, t0 = time.thread_time(), time.perf_counter()
            with plan.active():
                ksp.setUp()
                ksp.getPC().setUpOnBlocks()
                setup = (time.thread_time() - s0, time.perf_counter() - t0)
                y = b.duplicate()
                op.mult(b, y)       # reads the products' patterns (as the first CG product does)
                y.destroy()
                pc = ksp.getPC()
                inner = pc if pc.getType() == PETSc.PC.Type.PYTHON else None
                if inner is None:
                    raise SystemExit(f"the preconditioner is {pc.getType()}: this benchmark times "
                                     "-lc_contact_pc clusters (the default)")
                _instrument(op, inner, clock)
                clock.clear()
                events = {e: PETSc.Log.Event(e).getPerfInfo() for e in VEC_EVENTS}
                comm.Barrier()
                c0, w0 = time.thread_time(), time.perf_counter()
                ksp.solve(b, x)
                cpu, wall = time.thread_time() - c0, time.perf_counter() - w0
            reason = ksp.getConvergedReason()
            if reason <= 0:
                raise SystemExit(f"system {i}: CG did not converge ({reason})")
            its = ksp.getIterationNumber()
            its_all.append(its)
            st = inner.getPythonContext().stats
            stats.append({k: st.get(k) for k in ("fallback", "captured", "rows", "clusters", "band_factor")})
            vec = sum(PETSc.Log.Event(e).getPerfInfo()["time"] - events[e]["time"] for e in VEC_EVENTS)
            sums = {k: sum(v) for k, v in clock.cpu.items()}
            walls = {k: sum(v) for k, v in clock.wall.items()}
            n_mult, n_apply = len(clock.cpu["shell mult"]), len(clock.cpu["PC apply"])
            entry = {
                "solve (CPU)": cpu / its, "solve (wall)": wall / its,
                "shell mult (CPU)": sums["shell mult"] / n_mult,
                "shell mult (wall)": walls["shell mult"] / n_mult,
                "PC apply (CPU)": sums["PC apply"] / n_apply,
                "PC apply (wall)": walls["PC apply"] / n_apply,
                "KSP vector events (wall)": vec / its,
            }
            for k in ("A product", "C diagonal block", "C off-rank block", "band solve", "cluster solve"):
                if k in sums:
                    entry[f"{k} (CPU)"] = sums[k] / len(clock.cpu[k])
            entry["shell rest: scatter, Python (CPU)"] = entry["shell mult (CPU)"] - sum(
                entry.get(f"{k} (CPU)", 0.0) for k in ("A product", "C diagonal block", "C off-rank block"))
            entry["PC rest: Python, cluster scatter (CPU)"] = entry["PC apply (CPU)"] - sum(
                entry.get(f"{k} (CPU)", 0.0) for k in ("band solve", "cluster solve"))
            entry["KSP rest (CPU)"] = (cpu - sums["shell mult"] - sums["PC apply"]) / its
            for k, v in entry.items():
                per_iter.setdefault(k, []).append(v)
            whole.setdefault(i, []).append((setup[0], setup[1], cpu, wall))
            for obj in (x, ls, op, ctx):
                obj.destroy()
    table = comm.gather({k: statistics.median(v) for k, v in per_iter.items()})
    # per repeat, the sums over the systems (s): setup and solve, CPU and wall
    sums = [[sum(whole[i][r][c] for i in whole) for c in range(4)] for r in range(args.repeats)]
    sums = comm.gather(sums)
    stats = comm.gather(stats[:len(systems)])
    if comm.rank == 0:
        for r, st in enumerate(stats):
            print(f"rank {r}, the preconditioner per system: {st}")
        print(f"CG per solve: {its_all} ({args.repeats} repeats of {len(systems)} systems); "
              f"ms per CG iteration, median over the solves, per rank")
        for k in table[0]:
            print(f"  {k:42s} " + "  ".join(f"{1e3 * t[k]:8.3f}" for t in table))
        print("the systems together, s per repeat (setup CPU, setup wall, solve CPU, solve wall), per rank:")
        for r, rep in enumerate(sums):
            print(f"  rank {r}: " + "; ".join(", ".join(f"{v:.3f}" for v in t) for t in rep))
        wall = [max(rep[r][1] + rep[r][3] for rep in sums) for r in range(args.repeats)]
        print(f"setup + solve wall, max over ranks, per repeat: {', '.join(f'{w:.3f}' for w in wall)} "
              f"(median {statistics.median(wall):.3f} s)")


def _timed_all(comm, fn, repeats, flush):
    """Median CPU seconds (``time.thread_time``: a loaded machine's preemptions left out)
    of ``repeats`` calls of ``fn`` started together on every rank (the caches flushed
    before each call with ``flush``, a large array, when given)."""
    times = []
    for _ in range(repeats):
        if flush is not None:
            flush += 1.0
        comm.Barrier()
        t0 = time.thread_time()
        fn()
        times.append(time.thread_time() - t0)
    return statistics.median(times)


def kernels(args, comm):
    """Each compiled kernel of a CG iteration alone, on this rank's arrays of one system."""
    from lc_petsc.contact import SumOperator
    from lc_petsc.contact_pc import local_block
    from lc_petsc.elements.compiled_band import BandCholesky
    from lc_petsc.petsc_capi import block_pattern, value_array
    rows, systems = load(args.dir, comm)
    A, C, b = systems[args.system]
    ctx = SumOperator(A)
    ctx.C = C
    y = b.duplicate()
    ctx.mult(None, b, y)                    # builds the compiled products
    band = ctx._band
    diag, off = ctx._contact[0][0], ctx._contact[0][1] if len(ctx._contact[0]) > 1 else None
    ghosts = ctx._contact[2]
    A_loc = local_block(A)
    offsets = np.concatenate([[0], np.cumsum(rows // 3)])
    chol = BandCholesky(offsets)
    indptr, indices = block_pattern(A_loc)
    with value_array(A_loc, 9 * len(indices)) as values:
        why = chol.factor(indptr, indices, values)
    if why is not None:
        raise SystemExit(f"the band Cholesky does not hold: {why}")
    xa = b.getArray(readonly=True).copy()
    ya = np.empty_like(xa)
    n = len(xa)
    vec = 8 * n
    flush = np.zeros(FLUSH_BYTES // 8)
    ga = ghosts.getArray(readonly=True).copy() if ghosts is not None else np.zeros(0)
    # the bytes each kernel must read at least once (values, indices, vectors in and out)
    b_up = band.upper_values.nbytes + band.upper[0].nbytes + band.upper[1].nbytes
    cases = {
        "A product (symmetric, upper copy)": (lambda: band(xa, ya, False), b_up + 2 * vec),
        "band solve (Cholesky, every wisp)": (lambda: chol.apply(xa, ya), chol.F.nbytes + 2 * vec),
    }
    if diag.symmetric:
        d_up = diag.upper_values.nbytes + diag.upper[0].nbytes + diag.upper[1].nbytes
        cases["C diagonal block (symmetric)"] = (lambda: diag(xa, ya, True), d_up + 2 * vec)
    if off is not None:
        cases["C off-rank block"] = (lambda: off(ga, ya, True),
                                     9 * 8 * len(off.indices) + off.indices.nbytes + off.indptr.nbytes + ga.nbytes
                                     + 2 * vec)
    cl, pc, lu, cx, cy = _clusters(comm, rows, A, ctx)
    if cl.cluster is not None:          # the clusters' factor, and PETSc's LU of the same matrix
        m = cl.cluster_mat.getSize()[0]
        print(f"rank {comm.rank}: clusters' factor {cl.cluster.getType()}, {m} rows", flush=True)
        factors = (("clusters' factor (factor_cluster_matrix)", cl.cluster), ("  the same matrix, PETSc's LU", lu))
        cy_lu = cy.duplicate()
        cl.cluster.apply(cx, cy)
        lu.apply(cx, cy_lu)
        cy_lu.axpy(-1.0, cy)
        print(f"rank {comm.rank}: the two factors' solves differ by {cy_lu.norm() / cy.norm():.2e} (relative)",
              flush=True)
        cy_lu.destroy()
        for what, f in factors:
            cases[what] = ((lambda f=f: f.apply(cx, cy)),
                           12 * int(f.getFactorMatrix().getInfo()["nz_used"]) + 4 * m + 16 * m)
    a1, a2, a3 = np.empty(n), np.random.default_rng(1).random(n), np.random.default_rng(2).random(n)
    cases["NumPy a = b + c on CG vectors"] = (lambda: np.add(a2, a3, out=a1), 3 * vec)
    big = 4_000_000
    s1, s2, s3 = np.empty(big), np.ones(big), np.ones(big)
    cases["NumPy a = b + c, 32 MB arrays (stream)"] = (lambda: np.add(s2, s3, out=s1), 3 * 8 * big)
    out = {}
    for name, (fn, nbytes) in cases.items():
        fn()
        warm = _timed_all(comm, fn, args.repeats, None)
        cold = _timed_all(comm, fn, args.repeats, flush)
        out[name] = (warm, cold, nbytes)
    table = comm.gather(out)
    if comm.rank == 0:
        print("(a factor's bytes: 12 per stored entry, its row starts, the vectors in and out)")
        print(f"system {args.system}: each kernel alone, all {comm.size} ranks at once, median of "
              f"{args.repeats}; CPU ms (GB/s of the bytes it must read) per rank, warm | cold caches")
        for name in table[0]:
            cells = []
            for t in table:
                warm, cold, nbytes = t[name]
                cells.append(f"{1e3 * warm:7.3f} ({nbytes / warm / 1e9:5.1f}) | {1e3 * cold:7.3f} "
                             f"({nbytes / cold / 1e9:5.1f}) [{nbytes / 1e6:.1f} MB]")
            print(f"  {name:40s} " + "   ".join(cells))
    for obj in (y, ctx, pc, lu, cx, cy):
        if obj is not None:
            obj.destroy()


def _clusters(comm, rows, A, ctx):
    """The cluster preconditioner set up on the shell A + C (``ctx``), PETSc's LU (RCM) of
    its cluster matrix beside its own factor, and two vectors of the cluster rows."""
    from lc_petsc.contact_pc import ClusterPC
    op = PETSc.Mat().createPython(A.getSizes(), context=ctx, comm=comm)
    op.setUp()
    cl = ClusterPC(rows)
    pc = PETSc.PC().create(comm=comm)
    pc.setType(PETSc.PC.Type.PYTHON)
    pc.setPythonContext(cl)
    pc.setOperators(op, A)
    pc.setUp()
    if cl.cluster is None:
        return cl, pc, None, None, None
    lu = PETSc.PC().create(comm=PETSc.COMM_SELF)
    lu.setType(PETSc.PC.Type.LU)
    lu.setFactorOrdering(cl.ordering)
    lu.setOperators(cl.cluster_mat, cl.cluster_mat)
    lu.setUp()
    cx, cy = cl.cluster_mat.createVecs()
    cx.setRandom()
    return cl, pc, lu, cx, cy


def main(argv=None) -> int:
    """Dispatch the three commands."""
    ap = argparse.ArgumentParser(prog="bench_cg_iteration.py", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    r = sub.add_parser("record")
    r.add_argument("dir")
    r.add_argument("--config", required=True)
    r.add_argument("--restart")
    r.add_argument("--frames", type=int, default=1)
    s = sub.add_parser("solve")
    s.add_argument("dir")
    s.add_argument("--repeats", type=int, default=3)
    s.add_argument("--options", default="", help="PETSc options of the solver (default: the code's)")
    k = sub.add_parser("kernels")
    k.add_argument("dir")
    k.add_argument("--system", type=int, default=0)
    k.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args(argv)
    comm = MPI.COMM_WORLD
    {"record": record, "solve": solve, "kernels": kernels}[args.command](args, comm)
    return 0


if __name__ == "__main__":
    sys.exit(main())
