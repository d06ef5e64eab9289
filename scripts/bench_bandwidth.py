"""The machine's own bound on parallel efficiency: memory bandwidth per rank when every
rank streams at once, against one rank alone.

  mpiexec -n 1 .venv/bin/python scripts/bench_bandwidth.py
  mpiexec -n 2 .venv/bin/python scripts/bench_bandwidth.py   # same node, then compare

Each rank repeats ``a = b + c`` (NumPy, one thread) over arrays of ``--doubles`` float64
values, all ranks starting together (a barrier before each pass), and reports the median
bandwidth of its passes (3 arrays x 8 bytes per value moved; the first two passes are
warm-up).  The default 4e7 values (320 MB per array) are far beyond any cache, so the
figure is what the solve's products and triangular solves see when they stream their
matrices; a few 1e5 values fit the caches.  A phase that streams memory on N ranks can
run at most (per-rank bandwidth on N ranks) / (bandwidth on 1 rank) as efficiently as
its one-rank run; docs/performance.md "The machine's bound" has this machine's figures.
"""

import argparse
import statistics
import sys
import time

import numpy as np
from mpi4py import MPI

from lc_petsc.studies.command_line import integer_at_least, parse_args

WARM_UP = 2


def stream_rate(comm, doubles: int, passes: int) -> float:
    """Median GB/s of ``passes`` timed ``a = b + c`` passes over ``doubles`` values,
    started together on every rank of ``comm``."""
    rng = np.random.default_rng(comm.rank)
    b, c = rng.random(doubles), rng.random(doubles)
    a = np.empty(doubles)
    rates = []
    for k in range(WARM_UP + passes):
        comm.Barrier()
        start = time.perf_counter()
        np.add(b, c, out=a)
        elapsed = time.perf_counter() - start
        if k >= WARM_UP:
            rates.append(3 * a.itemsize * doubles / elapsed / 1e9)
    return statistics.median(rates)


def main(argv=None) -> int:
    """Print every rank's bandwidth, their sum and the per-rank mean."""
    parser = argparse.ArgumentParser(prog="bench_bandwidth.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--doubles", type=integer_at_least(1000), default=40_000_000,
                        help="values per array (default 4e7: 320 MB, beyond the caches)")
    parser.add_argument("--passes", type=integer_at_least(1), default=10, help="timed passes (default 10)")
    args = parse_args(parser, argv)
    comm = MPI.COMM_WORLD
    rates = comm.gather(stream_rate(comm, args.doubles, args.passes))
    if comm.rank == 0:
        print(f"{comm.size} rank(s), {args.doubles:.3g} values per array, median of {args.passes} passes")
        print("GB/s per rank: " + " ".join(f"{r:.1f}" for r in rates))
        print(f"total {sum(rates):.1f} GB/s, per-rank mean {sum(rates) / len(rates):.1f} GB/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
