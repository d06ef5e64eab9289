"""Dump a run's Newton systems with strand contact as .npz files readable without PETSc
(for preconditioner prototypes in SciPy: scripts/pc_prototype.py; docs/contact_solver.md,
"Preconditioner prototypes on a dumped system").

  python scripts/dump_system.py CONFIG.toml --restart CHECKPOINT.h5 --out DIR [--frames 1]
      [--systems N] [PETSc options ...]

Restarts from the checkpoint (drivers/simulate.py's, written with CONFIG), runs the next
``--frames`` frames with the run's own solver (the default: CG and ``-lc_contact_pc
clusters``) while recording every Newton system as it is built
(lc_petsc.studies.compare.record), and writes ``DIR/system_FFFFF_I.npz`` per system:

* ``A``: the strand matrix (each wisp's band with the contact blocks that fall on it),
  ``C``: the contact cross blocks between wisps (and within a wisp with self-contact),
  both as ``scipy.sparse`` BSR (3x3 blocks) in the arrays ``A_data``, ``A_indices``,
  ``A_indptr``, ``A_shape`` (and ``C_...``): :func:`load_system` rebuilds them;
* ``b``: the right-hand side; ``x``: the vertices' positions at the frame's start
  (vertices, 3; for rotations in a coarse space); ``wisp_rows``: the rows of each wisp (3 per vertex, in the
  matrix's order); ``iterations``: the run's CG iterations on this system; ``frame``,
  ``newton_it``.

Run it on one rank (the system is then the whole scene, rows in the scene's wisp order);
on more ranks it refuses.
"""

import argparse
import sys
from pathlib import Path

import numpy as np
import petsc4py

if __name__ == "__main__":
    petsc4py.init(sys.argv)

from mpi4py import MPI  # noqa: E402
from scipy import sparse  # noqa: E402


def to_bsr(M):
    """The sequential (1-rank) PETSc matrix ``M`` as a scipy BSR matrix with 3x3 blocks,
    explicit zeros kept (the pattern is PETSc's)."""
    if M.getComm().getSize() != 1:
        raise ValueError("to_bsr needs a matrix on one rank: run dump_system.py without mpiexec "
                         "(or with -n 1)")
    from petsc4py import PETSc
    # a new matrix (petsc4py's convert without one converts M in place)
    P = M.convert("aij", PETSc.Mat()) if M.getType() not in ("seqaij", "mpiaij") else M
    indptr, indices, data = P.getValuesCSR()
    if P is not M:
        P.destroy()
    csr = sparse.csr_matrix((data, indices, indptr), shape=M.getSize())
    return csr.tobsr(blocksize=(3, 3))


def save_system(path, A, C, b, x, wisp_rows, iterations, frame, newton_it):
    """Write one system (A, C scipy BSR; b array; x the vertices' positions at the
    frame's start, (vertices, 3)) as ``path`` (.npz)."""
    arrays = {}
    for name, M in (("A", A), ("C", C)):
        arrays.update({f"{name}_data": M.data, f"{name}_indices": M.indices,
                       f"{name}_indptr": M.indptr, f"{name}_shape": np.array(M.shape)})
    np.savez(path, b=np.asarray(b, float), x=np.asarray(x, float).reshape(-1, 3),
             wisp_rows=np.asarray(wisp_rows, np.int64), iterations=int(iterations), frame=int(frame),
             newton_it=int(newton_it), **arrays)


def load_system(path):
    """dict with ``A``, ``C`` (scipy BSR), ``b``, ``x``, ``wisp_rows``, ``iterations``, ``frame``,
    ``newton_it`` from a file of :func:`save_system`."""
    z = np.load(path)
    out = {k: z[k] for k in ("b", "x", "wisp_rows")}
    out.update({k: int(z[k]) for k in ("iterations", "frame", "newton_it")})
    for name in ("A", "C"):
        out[name] = sparse.bsr_matrix((z[f"{name}_data"], z[f"{name}_indices"], z[f"{name}_indptr"]),
                                      shape=tuple(z[f"{name}_shape"]))
    return out


def dump(config, out, restart=None, frames=1, max_systems=None, comm=MPI.COMM_WORLD):
    """Record ``frames`` frames of ``config`` (from the checkpoint ``restart``) and write
    every coupled Newton system into the folder ``out``; returns the written paths."""
    from lc_petsc.studies.compare import record
    from lc_petsc.studies.systems import destroy_systems
    if comm.size != 1:
        raise ValueError("dump_system.py runs on one rank (the dumped system is the whole scene)")
    systems, wisp_rows, info = record(config, comm, frames=frames, max_systems=max_systems,
                                      restart=restart)
    try:
        if not systems or any(not s.coupled for s in systems):
            raise ValueError("the recorded systems have no contact matrix C: the config needs "
                             "strand contact (physics.terms with strand_collision)")
        its = info["sim_ksp_iterations"][-len(systems):]
        Path(out).mkdir(parents=True, exist_ok=True)
        paths = []
        for s, n in zip(systems, its):
            p = Path(out) / f"system_{s.frame:05d}_{s.newton_it}.npz"
            save_system(p, to_bsr(s.wisp_local), to_bsr(s.C), s.b.getArray(), s.coords, wisp_rows, n,
                        s.frame, s.newton_it)
            paths.append(p)
    finally:
        destroy_systems(systems)
    return paths


def main(argv=None):
    from lc_petsc.config import load_config
    from lc_petsc.studies.command_line import integer_at_least, parse_args
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", help="scene TOML (the one the checkpoint ran with)")
    ap.add_argument("--restart", default=None, metavar="CHECKPOINT", help="start from this checkpoint")
    ap.add_argument("--frames", type=integer_at_least(1), default=1)
    ap.add_argument("--systems", type=integer_at_least(1), default=None, help="only the first N systems")
    ap.add_argument("--out", required=True)
    args = parse_args(ap, argv)
    for p in dump(load_config(args.config), args.out, args.restart, args.frames, args.systems):
        z = load_system(p)
        print(f"{p}: {z['A'].shape[0]} rows, {len(z['wisp_rows'])} wisps, A {z['A'].nnz} / "
              f"C {z['C'].nnz} entries, run's CG {z['iterations']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
