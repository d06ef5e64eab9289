"""Benchmark frames of the 2,000-wisp hairball (head contact on, strand contact off,
dt = 1/30, 3 Newton iterations): wall time per frame and per phase, Newton and KSP
iterations, peak memory per rank.

  mpiexec -n 1 .venv/bin/python scripts/bench_step.py [--wisps 2000] [--frames 3] [--json F] [PETSc options]
  mpiexec -n 2 .venv/bin/python scripts/bench_step.py

The first frame is reported on its own (it touches every buffer for the first time);
then ``--frames`` more frames are timed one by one and their medians reported: what a
long run pays per frame. Phase times are the maximum over ranks. The compiled element
kernels' JIT time (compile, or load from Numba's cache) is part of the build and printed
on its own; ``-lc_element_kernels numpy`` runs the NumPy kernels instead.

CPU time per phase (maximum over ranks) is printed beside the wall time: on a machine
shared with other jobs it measures the work, wall time also the waiting for a core.
``update`` is the Newton update (edge retraction) and the final length projection.
``--contact off`` drops the head contact (the issue's figures are without contact);
``--json F`` writes every figure to F.
"""

import argparse
import json
import resource
import statistics
import sys
import time

import petsc4py

petsc4py.init(sys.argv)
from mpi4py import MPI  # noqa: E402

from lc_petsc.config import MaterialConfig, PhysicsConfig, SceneConfig, SimConfig, TimeConfig  # noqa: E402
from lc_petsc.simulator import build_simulator  # noqa: E402
from lc_petsc.studies.command_line import integer_at_least, output_file, parse_args  # noqa: E402
from lc_petsc.timing import frame_timing  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--wisps", type=integer_at_least(1), default=2000)
    ap.add_argument("--frames", type=integer_at_least(0), default=3, help="timed frames after the first")
    ap.add_argument("--contact", choices=("head", "off"), default="head",
                    help="head contact on (default) or off")
    ap.add_argument("--json", type=output_file, help="write the figures to this JSON file")
    args = parse_args(ap)
    comm = MPI.COMM_WORLD
    terms = ("stretch", "bend", "twist", "gravity") + (("head_collision",) if args.contact == "head" else ())
    cfg = SimConfig(scene=SceneConfig(kind="hairball", n_wisps=args.wisps),
                    material=MaterialConfig(youngs_modulus=1.0e9),
                    physics=PhysicsConfig(terms=terms, head_motion="shake"),
                    time=TimeConfig(dt=1.0 / 30.0, frames=args.frames + 1, newton_iterations=3))
    t0 = time.perf_counter()
    sim = build_simulator(cfg)
    comm.Barrier()
    t_build = time.perf_counter() - t0
    first = frame_timing(sim)
    frames = [frame_timing(sim) for _ in range(args.frames)]
    s = sim.summary()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0   # MiB (Linux: KiB)
    rss_all = comm.gather(rss)
    if comm.rank == 0:
        fmt = lambda d: ", ".join(f"{k} {v:.3f}" for k, v in d.items() if v > 0)  # noqa: E731
        med = lambda key: {k: statistics.median(getattr(f, key)[k] for f in frames)  # noqa: E731
                           for k in getattr(frames[0], key)} if frames else {}
        wall, cpu = med("phases"), med("cpu")
        its = statistics.median(s["newton_iterations"][1:]) if frames else 1
        per_it = lambda d: 1e3 * (d["elements"] + d["assembly"]) / its  # noqa: E731
        out = dict(wisps=s["wisps"], dofs=s["dofs"], ranks=comm.size, petsc_options=s["petsc_options"],
                   build_s=t_build, jit_s=s["jit_compile_s"], first_frame_s=first.wall,
                   frame_walls_s=[f.wall for f in frames], frame_cpu_total_s=[f.cpu_total for f in frames],
                   phase_wall_s=wall, phase_cpu_s=cpu, newton_iterations=s["newton_iterations"],
                   ksp_iterations=s["ksp_iterations"], peak_rss_mib=rss_all)
        print(f"hairball {s['wisps']} wisps, {s['dofs']} DoFs, {comm.size} rank(s), "
              f"solver {s['petsc_options']}, contact {args.contact}")
        print(f"build (scene + rest state + pattern + KSP): {t_build:.3f} s, of which JIT of the "
              f"{s['element_kernels']} element kernels {s['jit_compile_s']:.3f} s")
        print(f"first frame: {first.wall:.3f} s ({fmt(first.phases)})")
        if frames:
            walls = [f.wall for f in frames]
            print(f"wall time per frame, median of {len(walls)} frames after the first: "
                  f"{statistics.median(walls):.3f} s (all: {', '.join(f'{w:.3f}' for w in walls)})")
            print(f"CPU time per frame, all ranks: {statistics.median(f.cpu_total for f in frames):.3f} s")
            print(f"per phase, median wall s per frame: {fmt(wall)}")
            print(f"per phase, median CPU s per frame:  {fmt(cpu)}")
            print(f"elements + assembly per Newton iteration: wall {per_it(wall):.1f} ms, "
                  f"CPU {per_it(cpu):.1f} ms; update (retraction) CPU "
                  f"{1e3 * cpu.get('update', 0.0) / its:.1f} ms")
            out.update(elements_assembly_ms_per_iteration=dict(wall=per_it(wall), cpu=per_it(cpu)))
        print(f"Newton iterations per frame: {s['newton_iterations']}")
        print(f"KSP iterations per Newton solve: {s['ksp_iterations']}  reasons: {set(s['ksp_reasons'])}")
        print(f"peak RSS per rank (MiB): {[round(r) for r in rss_all]}; total {sum(rss_all):.0f} MiB")
        if args.json:
            with open(args.json, "w") as fh:
                json.dump(out, fh, indent=1)
    sim.close()


if __name__ == "__main__":
    main()
