"""Stability at the extremes: the catalogue's hard cases with their stated
expectations, PASS/FAIL and figures.

  python scripts/extremes.py [--quick] [--only NAME ...] [--start-increment-tol TOL]
      [--tolerance TOL [--cap N]] [--out out/extremes] [PETSc options]

Cases (lc_petsc/studies/extremes.py): Smash 60%; compression 30% and 40% with each
filter (analytic, numerical, none); filter none + CG/point-block Jacobi at dt 1 s;
Jitter; Straighten; curl radius 1 mm; dt 1/10 s; stretch/bend stiffness ratio 1e4, 1e6,
1e8; a 1,000-vertex wisp.  Single wisps: run on one rank.  Writes extremes.csv,
extremes.json and extremes.md to --out; exit status 1 if a case fails its expectation.
``--start-increment-tol``: every case (all run a fixed count) with its first frames to that
tolerance (``time.start_increment_tol``, docs/newton.md "Twenty-second round").
``--tolerance``: every case to that relative increment tolerance (``time.newton_increment_tol``)
with at most ``--cap`` iterations per step (default 30), on the path a config file of the case
naming the tolerance (and the case's filter, where it is about one) gets from the loader
(``lc_petsc.config.tolerance_defaults``, listed as solver_path_defaulted), judged by the same
expectations and reported with frames converged, iterations per frame and frames cut back.
"""

import argparse
import sys
import tempfile
from dataclasses import replace

import petsc4py

petsc4py.init(sys.argv)
from mpi4py import MPI  # noqa: E402

from lc_petsc.studies.command_line import bad_input, integer_at_least, parse_args, positive_number  # noqa: E402
from lc_petsc.studies.extremes import at_tolerance, catalogue, run_cases  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="a tenth of the frames")
    ap.add_argument("--only", nargs="+", default=None, help="case names (prefixes)")
    ap.add_argument("--start-increment-tol", type=positive_number, default=None,
                    help="the cases' first frames to this tolerance (time.start_increment_tol)")
    ap.add_argument("--tolerance", type=positive_number, default=None,
                    help="every case to this relative increment tolerance (time.newton_increment_tol) "
                         "on the path a config file naming it gets")
    ap.add_argument("--cap", type=integer_at_least(1), default=None,
                    help="with --tolerance: iterations per step at most (default 30)")
    ap.add_argument("--out", default="out/extremes")
    args = parse_args(ap, argv)
    comm = MPI.COMM_WORLD
    if args.tolerance is not None and args.start_increment_tol is not None:
        return bad_input(comm, "extremes.py", ValueError(
            "--start-increment-tol converges the first frames of a fixed count; with --tolerance every "
            "frame runs to the tolerance: give one of the two"))
    if args.cap is not None and args.tolerance is None:
        return bad_input(comm, "extremes.py", ValueError(
            f"--cap {args.cap} caps the iterations of a run to --tolerance; add --tolerance TOL "
            "(the cases run fixed counts otherwise)"))
    with tempfile.TemporaryDirectory(prefix="lc_extremes_") as folder:   # the cases' groom files
        cases = catalogue(quick=args.quick, tmpdir=folder)
        if args.start_increment_tol is not None:
            for c in cases:
                c.settings = replace(c.settings, start_increment_tol=args.start_increment_tol)
        if args.tolerance is not None:
            cases = [at_tolerance(c, args.tolerance, 30 if args.cap is None else args.cap) for c in cases]
        return _run(args, comm, cases)


def _run(args, comm, cases):
    if args.only:
        names = [c.name for c in cases]
        cases = [c for c in cases if any(c.name.startswith(p) for p in args.only)]
        if not cases:
            return bad_input(comm, "extremes.py", ValueError(
                f"--only {' '.join(args.only)}: no case name starts with that; the cases: "
                f"{', '.join(names)}"))
    rows = run_cases(cases, comm, args.out,
                     log=(lambda *a: (print(*a), sys.stdout.flush())) if comm.rank == 0 else (lambda *a: None))
    if comm.rank == 0:
        n_fail = sum(r["passed"] is False for r in rows)
        judged = sum(r["passed"] is not None for r in rows)
        print(f"{judged - n_fail}/{judged} judged cases pass, {len(rows) - judged} reported without an "
              f"expectation (INFO); wrote {args.out}/extremes.md")
    return int(comm.bcast(n_fail if comm.rank == 0 else None) > 0)


if __name__ == "__main__":
    sys.exit(main())
