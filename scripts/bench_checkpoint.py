"""Benchmark restart checkpoints of the 2,000-wisp hairball (configs/hairball_2k.toml):
checkpoint write and read (load + checksum verification) time and file size, against
the time of one frame.

  mpiexec -n 1 .venv/bin/python scripts/bench_checkpoint.py [--config configs/hairball_2k.toml] [--repeat 3]
  mpiexec -n 2 .venv/bin/python scripts/bench_checkpoint.py

One frame is run first (its time, and the time of a second frame, are printed: the
target is a checkpoint write under 10% of one frame); then ``--repeat`` checkpoints are
written into a temporary folder next to the working directory (``--dir``) and read
back; medians (maximum over ranks) are printed.  The temporary folder is removed also
when a write or read fails (exit 3, the error printed).
"""

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import petsc4py

petsc4py.init(sys.argv[:1])
from mpi4py import MPI  # noqa: E402

from lc_petsc import __version__  # noqa: E402
from lc_petsc.config import load_config  # noqa: E402
from lc_petsc.errors import CheckpointError, OutputError  # noqa: E402
from lc_petsc.io.checkpoint import load_checkpoint, write_checkpoint  # noqa: E402
from lc_petsc.simulator import build_simulator  # noqa: E402
from lc_petsc.studies.command_line import bad_input, integer_at_least  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _write_and_read(comm, sim, cfg, a, d):
    """``a.repeat`` checkpoints of ``sim``'s state written into ``d`` and read back: the
    write and read times (maximum over the ranks) and the file size."""
    it = sim.integrator
    w, r, size = [], [], 0
    for k in range(a.repeat):
        comm.Barrier()
        t0 = time.perf_counter()
        path, _, size = write_checkpoint(
            d, comm, frame=it.frame + k, t=it.t, x=it.x, v=it.v, scene=sim.scene, n_wisps=sim.n_wisps,
            n_vertices=sim.n_vertices, head=sim.head, dt=cfg.time.dt, every=cfg.output.every,
            config_dict=cfg.to_dict(), config_toml=Path(a.config).read_text(), petsc_options={},
            keep=a.repeat + 1, version=__version__)
        w.append(comm.allreduce(time.perf_counter() - t0, op=MPI.MAX))
        comm.Barrier()
        t0 = time.perf_counter()
        ck = load_checkpoint(path, comm, sim.scene, sim.n_wisps, sim.n_vertices, sim.head)
        r.append(comm.allreduce(time.perf_counter() - t0, op=MPI.MAX))
        same = comm.allreduce(bool((ck["x"] == it.x).all() and (ck["v"] == it.v).all()), op=MPI.LAND)
        if not same:
            raise RuntimeError(f"{path}: the checkpoint read back differs from the state written")
    return w, r, size


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("--config", default=str(ROOT / "configs" / "hairball_2k.toml"))
    p.add_argument("--repeat", type=integer_at_least(1), default=3)
    p.add_argument("--dir", default=".")
    a = p.parse_args(argv)
    comm = MPI.COMM_WORLD
    try:
        cfg = load_config(a.config)
        if not Path(a.dir).is_dir():
            raise ValueError(f"--dir {a.dir}: no such folder (the checkpoints' temporary folder goes there)")
    except (ValueError, OSError) as e:          # ConfigError is a ValueError
        return bad_input(comm, "bench_checkpoint.py", e)
    sim = build_simulator(cfg, comm=comm)
    frame_times = []
    for _ in range(2):
        comm.Barrier()
        t0 = time.perf_counter()
        sim.step()
        comm.Barrier()
        frame_times.append(time.perf_counter() - t0)
    d = comm.bcast(tempfile.mkdtemp(prefix="bench_ckpt_", dir=a.dir) if comm.rank == 0 else None)
    try:
        w, r, size = _write_and_read(comm, sim, cfg, a, d)
    except (OSError, OutputError, CheckpointError, RuntimeError) as e:     # raised on every rank
        if comm.rank == 0:
            print(f"bench_checkpoint.py: error: {e}", file=sys.stderr)
        sim.close()
        return 3
    finally:            # a failed write or read (a full disk, a bad read-back) left the folder
        comm.Barrier()
        if comm.rank == 0:
            shutil.rmtree(d, ignore_errors=True)
    if comm.rank == 0:
        fw, fr = statistics.median(w), statistics.median(r)
        print(f"checkpoint benchmark: {a.config}  ({sim.n_wisps} wisps, {sim.n_vertices} vertices, "
              f"{comm.size} rank(s))")
        print(f"  frame time: first {frame_times[0]:.3f} s, second {frame_times[1]:.3f} s")
        print(f"  checkpoint write: median {fw:.3f} s over {a.repeat} ({100 * fw / frame_times[1]:.1f}% "
              f"of the second frame); all: {', '.join(f'{x:.3f}' for x in w)}")
        print(f"  checkpoint read + verify: median {fr:.3f} s; all: {', '.join(f'{x:.3f}' for x in r)}")
        print(f"  size: {size / 1e6:.1f} MB ({size / sim.n_vertices:.1f} bytes per vertex)")
    sim.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
