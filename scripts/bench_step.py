"""Benchmark one frame of the 2,000-wisp hairball (head contact on, strand contact off,
dt = 1/30, 3 Newton iterations).  Run:

  mpiexec -n 1 .venv/bin/python scripts/bench_step.py [--wisps 2000] [--frames 1] [PETSc options]
  mpiexec -n 2 .venv/bin/python scripts/bench_step.py
"""

import argparse
import resource
import sys
import time

import petsc4py

petsc4py.init(sys.argv)
from mpi4py import MPI  # noqa: E402

from lc_petsc.config import MaterialConfig, PhysicsConfig, SceneConfig, SimConfig, TimeConfig  # noqa: E402
from lc_petsc.simulator import build_simulator  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--wisps", type=int, default=2000)
    ap.add_argument("--frames", type=int, default=1)
    args, _ = ap.parse_known_args()
    comm = MPI.COMM_WORLD
    cfg = SimConfig(scene=SceneConfig(kind="hairball", n_wisps=args.wisps),
                    material=MaterialConfig(youngs_modulus=1.0e9),
                    physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity", "head_collision"),
                                          head_motion="shake"),
                    time=TimeConfig(dt=1.0 / 30.0, frames=args.frames, newton_iterations=3))
    t0 = time.perf_counter()
    sim = build_simulator(cfg)
    comm.Barrier()
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    sim.run()
    comm.Barrier()
    t_run = time.perf_counter() - t0
    s = sim.summary()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0   # MiB (Linux: KiB)
    rss_all = comm.gather(rss)
    if comm.rank == 0:
        print(f"hairball {s['wisps']} wisps, {s['dofs']} DoFs, {comm.size} rank(s), mat {s['mat_type']}")
        print(f"build (scene + rest state + pattern + KSP): {t_build:.3f} s")
        print(f"wall time per frame: {t_run / args.frames:.3f} s")
        print("per phase (max over ranks, all frames): " +
              ", ".join(f"{k} {v:.3f} s" for k, v in s["timings_s"].items()))
        print(f"Newton iterations per frame: {s['newton_iterations']}")
        print(f"KSP iterations per Newton solve: {s['ksp_iterations']}  reasons: {set(s['ksp_reasons'])}")
        print(f"peak RSS per rank (MiB): {[round(r) for r in rss_all]}; total {sum(rss_all):.0f} MiB")
    sim.close()


if __name__ == "__main__":
    main()
