"""Solver comparison on the same Newton systems (SPEC 5; paper's Table 3).

  mpiexec -n P python drivers/compare_solvers.py [--wisps 250 500 1000 2000]
      [--sets default mumps_cholesky ...] [--sets-dir configs/solvers] [--budget 60]
      [--frames 1] [--skip-frames 0] [--systems N] [--repeats 1] [--config SCENE.toml]
      [--restart CHECKPOINT] [--no-head-contact]
      [--strand-contact] [--no-reference]
      [--skip-after-budget]
      [--out out/compare_solvers] [PETSc options ...]

For each hairball size (or the scene of ``--config``, once; ``--wisps`` then sets its
``scene.n_wisps``, a hairball's only), the simulator runs ``--frames`` frames with its own solver while every
Newton system (matrix + right-hand side) is recorded; every option set
(``configs/solvers/*.opts``: drop a file there to add one) then solves exactly those
systems (``--skip-frames K``: after K frames run unrecorded, e.g. to reach the
contact of a later frame; ``--restart CHECKPOINT``: from a checkpoint that
``drivers/simulate.py`` wrote with the same ``--config``, so that a late frame of a large
scene is recorded without running the frames before it again).  Reported per set: setup
and solve time, Krylov iterations, converged reason, true relative residual, error
against a MUMPS LU solve of the same system, RSS growth; with the contact preconditioner
(``-lc_contact_pc clusters``) per system whether its clusters fell back to per-wisp
blocks, the coupling weight they captured and their rows.
A set that exceeds ``--budget`` seconds (per size) is stopped and reported as such.
``--repeats N`` replays every set N times on the same systems (the sets interleaved, so
that a load change on a shared machine hits all of them) and reports median times; a
set stopped by the budget is not repeated.
PETSc options on the command line apply to EVERY set (they win over the sets' files).

Outputs in --out: rows.csv (one row per set and system), summary.csv, results.json,
table.md (paper's Table 3 layout, ratios against ``default``), time_vs_wisps.png.
"""

import argparse
import shlex
import sys
from pathlib import Path

import petsc4py

petsc4py.init(sys.argv)
from mpi4py import MPI  # noqa: E402

from lc_petsc.config import (MaterialConfig, PhysicsConfig, SceneConfig, SimConfig,  # noqa: E402
                             TimeConfig, load_config)
from lc_petsc.errors import CheckpointError  # noqa: E402
from lc_petsc.studies.command_line import (bad_input, check_wisps_flag, integer_at_least, parse_args,  # noqa: E402
                                           positive_number)
from lc_petsc.studies.compare import hairball_config, run_comparison  # noqa: E402
from lc_petsc.studies.systems import option_sets  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def base_config(head_contact=True, newton=3, strand_contact=False):
    terms = ("stretch", "bend", "twist", "gravity") + (("head_collision",) if head_contact else ()) \
        + (("strand_collision",) if strand_contact else ())
    return SimConfig(scene=SceneConfig(kind="hairball", n_wisps=250),
                     material=MaterialConfig(youngs_modulus=1.0e9),
                     physics=PhysicsConfig(terms=terms, head_motion="shake"),
                     time=TimeConfig(dt=1.0 / 30.0, frames=1, newton_iterations=newton))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--wisps", type=integer_at_least(1), nargs="+", default=None,
                    help="hairball sizes (default 250 500; with --config, its own scene once)")
    ap.add_argument("--sets", nargs="+", default=None, help="option set names (default: all)")
    ap.add_argument("--sets-dir", default=str(ROOT / "configs" / "solvers"))
    ap.add_argument("--budget", type=positive_number, default=60.0, help="seconds per set and size")
    ap.add_argument("--frames", type=integer_at_least(1), default=1, help="frames recorded (3 systems each)")
    ap.add_argument("--skip-frames", type=integer_at_least(0), default=0,
                    help="frames run before the recorded ones (not recorded)")
    ap.add_argument("--systems", type=integer_at_least(1), default=None,
                    help="record only the first N Newton systems (e.g. 1 to let a slow set "
                         "run to convergence on one system within the budget)")
    ap.add_argument("--repeats", type=integer_at_least(1), default=1,
                    help="replay each set this many times (sets interleaved); times are medians")
    ap.add_argument("--newton", type=integer_at_least(1), default=3)
    ap.add_argument("--config", default=None, help="scene TOML instead of the hairball")
    ap.add_argument("--restart", default=None, metavar="CHECKPOINT",
                    help="record from this checkpoint of drivers/simulate.py (written with the "
                         "same --config) instead of frame 0; --skip-frames counts from it")
    ap.add_argument("--no-head-contact", action="store_true")
    ap.add_argument("--strand-contact", action="store_true",
                    help="strand-strand contact on (the paper's hairball): the recorded "
                         "systems are the assembled strand + contact matrices")
    ap.add_argument("--skip-after-budget", action="store_true",
                    help="a set stopped by the budget at one size is not run at larger sizes "
                         "(reported as over budget)")
    ap.add_argument("--no-reference", action="store_true", help="skip the direct reference solves")
    ap.add_argument("--out", default="out/compare_solvers")
    args = parse_args(ap, argv)
    comm = MPI.COMM_WORLD
    try:
        sets = option_sets(args.sets_dir, args.sets)
        if args.restart is not None and (args.config is None or args.wisps is not None):
            raise ValueError("--restart needs --config (the config its checkpoint ran with) and no "
                             "--wisps (the checkpoint holds one scene)")
        if args.restart is not None and not Path(args.restart).is_file():
            raise ValueError(f"--restart {args.restart}: no such checkpoint file")
        if args.config:
            base = load_config(args.config)
            base.time.newton_iterations = args.newton
            if args.wisps is None:
                args.wisps = [base.scene.n_wisps]
            else:
                check_wisps_flag(base, args.config)
        else:
            args.wisps = args.wisps or [250, 500]
            base = base_config(not args.no_head_contact, args.newton, args.strand_contact)
    except (ValueError, OSError) as e:          # ConfigError is a ValueError
        return bad_input(comm, "compare_solvers.py", e)
    log = print if comm.rank == 0 else (lambda *a, **k: None)
    log(f"{comm.size} rank(s); sets: {', '.join(sets)}; budget {args.budget:g} s per set and size")
    cmd = f"mpiexec -n {comm.size} python " + " ".join(shlex.quote(a) for a in sys.argv)
    try:
        run_comparison(lambda n: hairball_config(base, n), args.wisps, sets, comm, args.out,
                       budget_s=args.budget, frames=args.frames, reference=not args.no_reference,
                       repeats=args.repeats, max_systems=args.systems, skip_frames=args.skip_frames,
                       skip_after_budget=args.skip_after_budget, restart=args.restart,
                       log=lambda *a: (log(*a), sys.stdout.flush()),
                       meta={"command": cmd, "sets": sets, "repeats": args.repeats,
                             "config": args.config, "restart": args.restart,
                             "head_contact": not args.no_head_contact, "strand_contact": args.strand_contact})
    except CheckpointError as e:       # refused on every rank, before any system is recorded
        return bad_input(comm, "compare_solvers.py", e)
    log(f"wrote {args.out}/table.md, summary.csv, rows.csv, results.json"
        + (", time_vs_wisps.png" if len(set(args.wisps)) > 1 else ""))
    if comm.rank == 0:
        print((Path(args.out) / "table.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
