"""Per-rank work counts and CPU of the strand-contact kernels of a main-job run.

Wraps ``drivers/simulate.py`` (or any script) under mpiexec: counts the calls, sizes and
CPU time (``time.process_time``) of the broad phase (``box_pairs``), the limiter's
candidate filter and pair tests, the narrow phase and the contact assembly on every
rank, and the CPU / wall time of each timer phase, and writes ``PREFIX.RANK.json``::

    mpiexec -n 2 python scripts/contact_work_stats.py PREFIX drivers/simulate.py CONFIG ...
    python scripts/contact_work_stats.py --show PREFIX RANKS     # the table, max/mean

The counts do not depend on the machine's load (the CPU times do: MPI's busy waits
inside the collectives are CPU time too, so only the kernels' own CPU is work).
docs/performance.md, "Contact work balanced by contact", used it.
"""

import atexit
import json
import runpy
import sys
import time
from collections import defaultdict
from contextlib import contextmanager

STATS: dict = defaultdict(float)
PHASES: dict = defaultdict(float)
#: the kernels' summed CPU (the work the ranks share; the rest of a phase includes waits)
KERNELS = ("box_pairs", "order_candidates", "limit_pairs", "near_pair_distances", "pair_distances",
           "penalty_rows", "_close_pairs", "_rebuild_matrix")


def wrap(owner, name, count=None):
    """Replace ``owner.name`` by a wrapper adding its calls, CPU and ``count``'s sizes."""
    f = getattr(owner, name)

    def counted(*a, **k):
        c0 = time.process_time()
        r = f(*a, **k)
        STATS[name + ".cpu"] += time.process_time() - c0
        STATS[name + ".calls"] += 1
        for n, v in (count(a, r) if count else {}).items():
            STATS[name + "." + n] += v
        return r
    setattr(owner, name, counted)


def instrument():
    """Wrap the contact kernels and the phase timers."""
    import lc_petsc.contact as contact
    import lc_petsc.timing as timing
    from lc_petsc.elements import compiled_ccd, compiled_contact
    wrap(contact, "box_pairs", lambda a, r: {"pairs": len(r), "segments": len(a[0])})
    wrap(compiled_ccd, "order_candidates", lambda a, r: {"candidates": len(r[0]), "kept": int(r[2].sum())})
    wrap(compiled_ccd, "limit_pairs", lambda a, r: {"tests": len(a[3])})
    wrap(compiled_ccd, "near_pair_distances", lambda a, r: {"near": len(r[0])})
    wrap(compiled_ccd, "pair_distances", lambda a, r: {"pairs": len(a[1])})
    wrap(compiled_contact, "penalty_rows", lambda a, r: {"pairs": len(a[0])})
    sc = contact.StrandContact
    wrap(sc, "_close_pairs", lambda a, r: {"pairs": len(r[0][0]), "cross_rank": int((r[0][5] != r[0][6]).sum())})
    wrap(sc, "_gather_segments", lambda a, r: {"local": r[-1], "ghosts": len(r[1]) - r[-1]})
    for name in ("_safe_fractions", "assemble", "separate", "_rebuild_matrix"):
        wrap(sc, name)
    timer = timing.Timers.__call__

    @contextmanager
    def timed(self, phase):
        c0, t0 = time.process_time(), time.perf_counter()
        with timer(self, phase):
            yield
        PHASES[phase + ".cpu"] += time.process_time() - c0
        PHASES[phase + ".wall"] += time.perf_counter() - t0
    timing.Timers.__call__ = timed


def show(prefix, ranks):
    """Print every count per rank with its max / mean, and the kernels' summed CPU."""
    runs = [json.load(open(f"{prefix}.{r}.json")) for r in range(ranks)]
    for key in sorted(set().union(*(r["stats"] for r in runs))):
        v = [r["stats"].get(key, 0.0) for r in runs]
        mean = sum(v) / len(v)
        ratio = f"   max/mean {max(v) / mean:.3f}" if mean else ""
        print(f"{key:32s} " + " / ".join(f"{x:12.3f}" if x < 1000 else f"{x:12.0f}" for x in v) + ratio)
    print("kernels cpu".ljust(32), " / ".join(f"{sum(r['stats'].get(k + '.cpu', 0.0) for k in KERNELS):12.3f}"
                                             for r in runs))
    for key in sorted(runs[0]["phases"]):
        print(f"{key:32s} " + " / ".join(f"{r['phases'].get(key, 0.0):12.3f}" for r in runs))


def main():
    """Show a run's table, or run a script instrumented."""
    args = sys.argv[1:]
    if not args or args[0] in ("-h", "--help"):
        print(__doc__)
        return 0 if args else 2
    if args[0] == "--show":
        if len(args) != 3 or not args[2].isdigit():
            print("contact_work_stats.py: error: --show PREFIX RANKS (the ranks as a number)", file=sys.stderr)
            return 2
        show(args[1], int(args[2]))
        return 0
    if len(args) < 2 or args[0].startswith("-") or not args[1].endswith(".py"):
        print(f"contact_work_stats.py: error: give PREFIX SCRIPT.py [its arguments], got {' '.join(args)} "
              "(--help)", file=sys.stderr)
        return 2
    from mpi4py import MPI
    prefix = sys.argv[1]
    instrument()
    atexit.register(lambda: json.dump({"stats": dict(STATS), "phases": dict(PHASES)},
                                      open(f"{prefix}.{MPI.COMM_WORLD.rank}.json", "w"), indent=1))
    sys.argv = sys.argv[2:]
    runpy.run_path(sys.argv[0], run_name="__main__")
    return 0


if __name__ == "__main__":
    sys.exit(main())
