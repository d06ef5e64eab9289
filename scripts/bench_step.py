"""Benchmark frames of the 2,000-wisp hairball (head contact on, strand contact off,
dt = 1/30, 3 Newton iterations): wall time per frame and per phase, Newton and KSP
iterations, peak memory per rank.

  mpiexec -n 1 .venv/bin/python scripts/bench_step.py [--wisps 2000] [--frames 3] [PETSc options]
  mpiexec -n 2 .venv/bin/python scripts/bench_step.py

The first frame is reported on its own (it touches every buffer for the first time);
then ``--frames`` more frames are timed one by one and their medians reported: what a
long run pays per frame. Phase times are the maximum over ranks. The compiled element
kernels' JIT time (compile, or load from Numba's cache) is part of the build and printed
on its own; ``-lc_element_kernels numpy`` runs the NumPy kernels instead.
"""

import argparse
import resource
import statistics
import sys
import time

import petsc4py

petsc4py.init(sys.argv)
from mpi4py import MPI  # noqa: E402

from lc_petsc.config import MaterialConfig, PhysicsConfig, SceneConfig, SimConfig, TimeConfig  # noqa: E402
from lc_petsc.simulator import build_simulator  # noqa: E402
from lc_petsc.timing import timed_frame  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--wisps", type=int, default=2000)
    ap.add_argument("--frames", type=int, default=3, help="timed frames after the first")
    args, _ = ap.parse_known_args()
    comm = MPI.COMM_WORLD
    cfg = SimConfig(scene=SceneConfig(kind="hairball", n_wisps=args.wisps),
                    material=MaterialConfig(youngs_modulus=1.0e9),
                    physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity", "head_collision"),
                                          head_motion="shake"),
                    time=TimeConfig(dt=1.0 / 30.0, frames=args.frames + 1, newton_iterations=3))
    t0 = time.perf_counter()
    sim = build_simulator(cfg)
    comm.Barrier()
    t_build = time.perf_counter() - t0
    first_wall, first_phases, _ = timed_frame(sim)
    walls, phases = [], []
    for _ in range(args.frames):
        w, p, _ = timed_frame(sim)
        walls.append(w)
        phases.append(p)
    s = sim.summary()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0   # MiB (Linux: KiB)
    rss_all = comm.gather(rss)
    if comm.rank == 0:
        fmt = lambda d: ", ".join(f"{k} {v:.3f}" for k, v in d.items() if v > 0)  # noqa: E731
        print(f"hairball {s['wisps']} wisps, {s['dofs']} DoFs, {comm.size} rank(s), "
              f"solver {s['petsc_options']}")
        print(f"build (scene + rest state + pattern + KSP): {t_build:.3f} s, of which JIT of the "
              f"{s['element_kernels']} element kernels {s['jit_compile_s']:.3f} s")
        print(f"first frame: {first_wall:.3f} s ({fmt(first_phases)})")
        if walls:
            med = {k: statistics.median(p[k] for p in phases) for k in phases[0]}
            print(f"wall time per frame, median of {len(walls)} frames after the first: "
                  f"{statistics.median(walls):.3f} s (all: {', '.join(f'{w:.3f}' for w in walls)})")
            print(f"per phase, median s per frame: {fmt(med)}")
            its = statistics.median(s["newton_iterations"][1:])
            print(f"elements + assembly per Newton iteration: "
                  f"{1e3 * (med['elements'] + med['assembly']) / its:.1f} ms")
        print(f"Newton iterations per frame: {s['newton_iterations']}")
        print(f"KSP iterations per Newton solve: {s['ksp_iterations']}  reasons: {set(s['ksp_reasons'])}")
        print(f"peak RSS per rank (MiB): {[round(r) for r in rss_all]}; total {sum(rss_all):.0f} MiB")
    sim.close()


if __name__ == "__main__":
    main()
