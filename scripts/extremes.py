"""Stability at the extremes: the catalogue's hard cases with their stated
expectations, PASS/FAIL and figures.

  python scripts/extremes.py [--quick] [--only NAME ...] [--start-increment-tol TOL]
      [--out out/extremes] [PETSc options]

Cases (lc_petsc/studies/extremes.py): Smash 60%; compression 30% and 40% with each
filter (analytic, numerical, none); filter none + CG/point-block Jacobi at dt 1 s;
Jitter; Straighten; curl radius 1 mm; dt 1/10 s; stretch/bend stiffness ratio 1e4, 1e6,
1e8; a 1,000-vertex wisp.  Single wisps: run on one rank.  Writes extremes.csv,
extremes.json and extremes.md to --out; exit status 1 if a case fails its expectation.
``--start-increment-tol``: every case (all run a fixed count) with its first frames to that
tolerance (``time.start_increment_tol``, docs/newton.md "Twenty-second round").
"""

import argparse
import sys
import tempfile
from dataclasses import replace

import petsc4py

petsc4py.init(sys.argv)
from mpi4py import MPI  # noqa: E402

from lc_petsc.studies.command_line import bad_input, parse_args, positive_number  # noqa: E402
from lc_petsc.studies.extremes import catalogue, run_cases  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="a tenth of the frames")
    ap.add_argument("--only", nargs="+", default=None, help="case names (prefixes)")
    ap.add_argument("--start-increment-tol", type=positive_number, default=None,
                    help="the cases' first frames to this tolerance (time.start_increment_tol)")
    ap.add_argument("--out", default="out/extremes")
    args = parse_args(ap, argv)
    comm = MPI.COMM_WORLD
    with tempfile.TemporaryDirectory(prefix="lc_extremes_") as folder:   # the cases' groom files
        cases = catalogue(quick=args.quick, tmpdir=folder)
        if args.start_increment_tol is not None:
            for c in cases:
                c.settings = replace(c.settings, start_increment_tol=args.start_increment_tol)
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
