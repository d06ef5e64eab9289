"""Benchmark the hairball with strand-strand contact (issue 7): per-frame wall time and
phase breakdown, CG iterations per Newton solve, contact pairs per frame, minimum
segment distance over the run.

  mpiexec -n 1 .venv/bin/python scripts/bench_contact.py [--frames 100] [--config CONFIG] [PETSc options]
  mpiexec -n 2 .venv/bin/python scripts/bench_contact.py --frames 100

Scene: --config (default configs/hairball_2k.toml: the paper's 2,000-wisp hairball, head
turning about z, y, x, gravity, head and strand contact with d0 = twice the tip radius,
dt = 1/30, 3 Newton iterations), with strand_collision switched on if the config has it
off.  ``--wisps``, ``--stiffness``, ``--thickness`` override the config.  Phase times
are maxima over ranks.  ``--json FILE`` writes the per-frame figures.
"""

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import petsc4py

petsc4py.init(sys.argv)
from mpi4py import MPI  # noqa: E402

from lc_petsc.config import load_config  # noqa: E402
from lc_petsc.simulator import build_simulator  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def timed_frame(sim, comm):
    before = dict(sim.timers.as_dict())
    n_ksp = len(sim.solver.iterations)
    comm.Barrier()
    t0 = time.perf_counter()
    sim.step()
    comm.Barrier()
    wall = time.perf_counter() - t0
    after = sim.timers.as_dict()
    phases = {k: comm.allreduce(after[k] - before.get(k, 0.0), op=MPI.MAX) for k in after}
    return wall, phases, sim.solver.iterations[n_ksp:]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=str(ROOT / "configs" / "hairball_2k.toml"))
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--wisps", type=int, default=None)
    ap.add_argument("--thickness", type=float, default=None)
    ap.add_argument("--stiffness", type=float, default=None)
    ap.add_argument("--json", default=None)
    args, _ = ap.parse_known_args()
    comm = MPI.COMM_WORLD
    cfg = load_config(args.config)
    if "strand_collision" not in cfg.physics.terms:
        cfg.physics.terms = tuple(cfg.physics.terms) + ("strand_collision",)
    if args.wisps is not None:
        cfg.scene.n_wisps = args.wisps
    if args.thickness is not None:
        cfg.physics.strand_thickness = args.thickness
    if args.stiffness is not None:
        cfg.physics.strand_stiffness = args.stiffness
    cfg.time.frames = args.frames
    t0 = time.perf_counter()
    sim = build_simulator(cfg)
    comm.Barrier()
    t_build = time.perf_counter() - t0
    rows = []
    for f in range(args.frames):
        wall, ph, its = timed_frame(sim, comm)
        pairs = sim.integrator.contact_pairs[-1]
        dmin = sim.integrator.contact_min_distance[-1]
        deep = sim.integrator.contact_deep_pairs[-1]
        sep = sim.strand.last_separation          # (pairs < d0/2 found, Jacobi rounds, left)
        rows.append({"frame": f, "wall": wall, "phases": ph, "ksp": its, "pairs": pairs, "dmin": dmin,
                     "deep": deep, "separated": sep, "ghosts": sim.strand.ghosts_received[-1]})
        if comm.rank == 0:
            print(f"frame {f:3d}: {wall:6.2f} s  collision {ph['collision']:5.2f}  solve "
                  f"{ph['solve']:5.2f}  elements {ph['elements']:5.2f}  assembly {ph['assembly']:5.2f}"
                  f"  CG {its}  pairs {pairs} (< d0/2: {deep}; separated {sep[0]} in {sep[1]} rounds)"
                  f"  dmin {dmin:.4f}", flush=True)
    s = sim.summary()
    if comm.rank == 0:
        d0 = sim.strand.d0
        steady = rows[1:] or rows
        walls = [r["wall"] for r in steady]
        med = {k: statistics.median(r["phases"][k] for r in steady) for k in steady[0]["phases"]}
        tot = {k: sum(r["phases"][k] for r in rows) for k in rows[0]["phases"]}
        wall_tot = sum(r["wall"] for r in rows)
        its = [i for r in rows for i in r["ksp"]]
        dmin = min(r["dmin"] for r in rows)
        print(f"\nhairball {s['wisps']} wisps, {s['dofs']} DoFs, {comm.size} rank(s), "
              f"{len(rows)} frames; d0 = {d0:.4f} cm, k = {sim.strand.k:g} dyn/cm, "
              f"E = {cfg.material.youngs_modulus:g}; config {args.config}; solver {s['petsc_options']}")
        print(f"build: {t_build:.2f} s; first frame {rows[0]['wall']:.2f} s")
        print(f"wall per frame (frames after the first): median {statistics.median(walls):.2f} s, "
              f"mean {statistics.mean(walls):.2f} s, max {max(walls):.2f} s")
        print("median per frame by phase: " + ", ".join(f"{k} {v:.2f}" for k, v in med.items() if v > 0))
        print(f"collision share of the frame (whole run): {tot['collision'] / wall_tot:.1%}")
        print(f"CG iterations per Newton solve: first frame {rows[0]['ksp']}, median "
              f"{statistics.median(its):.0f}, max {max(its)}")
        print(f"contact pairs per frame: first {rows[0]['pairs']}, median "
              f"{statistics.median(r['pairs'] for r in rows):.0f}, max {max(r['pairs'] for r in rows)}")
        print(f"pairs closer than d0/2 per frame: {[r['deep'] for r in rows]}")
        print(f"minimum segment distance over the run: {dmin:.4f} cm = {dmin / d0:.3f} d0 "
              f"({'above' if dmin > 0.5 * d0 else 'BELOW'} half the thickness)")
        if args.json:
            with open(args.json, "w") as fh:
                json.dump({"ranks": comm.size, "d0": d0, "build": t_build, "frames": rows}, fh)
    sim.close()


if __name__ == "__main__":
    main()
