"""Benchmark the hairball with strand-strand contact: per-frame wall time and
phase breakdown, CG iterations per Newton solve, contact pairs per frame, minimum
segment distance over the run.

  mpiexec -n 1 .venv/bin/python scripts/bench_contact.py [--frames 100] [--config CONFIG] [PETSc options]
  mpiexec -n 2 .venv/bin/python scripts/bench_contact.py --frames 100

Scene: --config (default configs/hairball_2k.toml: the paper's 2,000-wisp hairball, head
turning about z, y, x, gravity, head and strand contact with d0 = twice the tip radius,
dt = 1/30, 3 Newton iterations), with strand_collision switched on if the config has it
off.  ``--wisps``, ``--stiffness``, ``--thickness`` override the config; ``--mode
penalty|ccd`` sets ``physics.strand_contact_mode``.  The solver is the config's, PETSc
options on the command line win (e.g. ``-lc_contact_pc clusters``; with it, the
clusters per Newton iteration are printed).  Phase times
are maxima over ranks.  ``--json FILE`` writes the per-frame figures; give the files
of several runs (e.g. 1 and 2 ranks) to scripts/report_contact.py for a table side by
side and a plot.
"""

import argparse
import json
import math
import sys
import time
from pathlib import Path

import petsc4py

petsc4py.init(sys.argv)
from mpi4py import MPI  # noqa: E402

from lc_petsc.config import load_config  # noqa: E402
from lc_petsc.simulator import build_simulator  # noqa: E402
from lc_petsc.studies.command_line import (bad_input, check_wisps_flag, integer_at_least, output_file,  # noqa: E402
                                             parse_args, positive_number)
from lc_petsc.studies.contact_report import summarize, summary_table  # noqa: E402
from lc_petsc.timing import timed_frame  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=str(ROOT / "configs" / "hairball_2k.toml"))
    ap.add_argument("--frames", type=integer_at_least(1), default=100)
    ap.add_argument("--wisps", type=integer_at_least(1), default=None)
    ap.add_argument("--thickness", type=positive_number, default=None)
    ap.add_argument("--stiffness", type=positive_number, default=None)
    ap.add_argument("--mode", choices=("penalty", "ccd"), default=None,
                    help="strand contact mode (default: the config's)")
    ap.add_argument("--json", type=output_file, default=None)
    args = parse_args(ap)
    comm = MPI.COMM_WORLD
    try:
        cfg = load_config(args.config)
        if "strand_collision" not in cfg.physics.terms:
            cfg.physics.terms = tuple(cfg.physics.terms) + ("strand_collision",)
        if args.wisps is not None:
            check_wisps_flag(cfg, args.config)
            cfg.scene.n_wisps = args.wisps
        if args.thickness is not None:
            cfg.physics.strand_thickness = args.thickness
        if args.stiffness is not None:
            cfg.physics.strand_stiffness = args.stiffness
        if args.mode is not None:
            cfg.physics.strand_contact_mode = args.mode
        cfg.time.frames = args.frames
        cfg.validate()
    except (ValueError, OSError) as e:          # ConfigError is a ValueError
        return bad_input(comm, "bench_contact.py", e)
    t0 = time.perf_counter()
    sim = build_simulator(cfg)
    comm.Barrier()
    t_build = time.perf_counter() - t0
    rows = []
    for f in range(args.frames):
        wall, ph, its = timed_frame(sim)
        pairs = sim.integrator.contact_pairs[-1]
        dmin = sim.integrator.contact_min_distance[-1]
        deep = sim.integrator.contact_deep_pairs[-1]
        # (pairs < d0/2 found: the most over the frame's separation calls; Jacobi rounds and
        # pairs left of the last call)
        found = sim.integrator.contact_separated[-1] if sim.integrator.contact_separated else 0
        sep = (found,) + tuple(sim.strand.last_separation[1:])
        rows.append({"frame": f, "wall": wall, "phases": ph, "ksp": its, "pairs": pairs,
                     "dmin": dmin if math.isfinite(dmin) else None,     # None: no pair in range
                     "deep": deep, "separated": sep, "ghosts": sim.strand.ghosts_received.lasts[-1]})
        if comm.rank == 0:
            print(f"frame {f:3d}: {wall:6.2f} s  collision {ph['collision']:5.2f}  solve "
                  f"{ph['solve']:5.2f}  elements {ph['elements']:5.2f}  assembly {ph['assembly']:5.2f}"
                  f"  CG {its}  pairs {pairs} (< d0/2: {deep}; separated {sep[0]} in {sep[1]} rounds)"
                  f"  dmin {dmin:.4f}", flush=True)
            clusters = getattr(sim.solver, "clusters", None)
            if clusters is not None:
                print("           clusters (rank 0, per Newton iteration): "
                      + "; ".join(f"{h['clusters']} holding {h['wisps']} wisps (largest {h['largest']}, "
                                  f"captured {h['captured']:.2f}{', fallback' if h['fallback'] else ''})"
                                  for h in clusters.history[-len(its):]), flush=True)
    s = sim.summary()
    if comm.rank == 0:
        run = {"ranks": comm.size, "d0": sim.strand.d0, "build": t_build, "config": args.config,
               "wisps": s["wisps"], "dofs": s["dofs"],
               "petsc_options": s["petsc_options"], "frames": rows}
        print(f"\nhairball {s['wisps']} wisps, {s['dofs']} DoFs, {comm.size} rank(s), "
              f"{len(rows)} frames; d0 = {sim.strand.d0:.4f} cm, k = {sim.strand.k:g} dyn/cm, "
              f"E = {cfg.material.youngs_modulus:g}; config {args.config}; solver {s['petsc_options']}; "
              f"build {t_build:.2f} s\n")
        print(summary_table([summarize(run)]))
        print(f"pairs closer than d0/2 at the end of each frame: {[r['deep'] for r in rows]}")
        if args.json:
            with open(args.json, "w") as fh:
                json.dump(run, fh)
    sim.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
