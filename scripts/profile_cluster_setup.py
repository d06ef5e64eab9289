r"""Where the cluster preconditioner's set-up goes (``ClusterPC.setUp``, lc_petsc/contact_pc.py).

Runs a driver (normally drivers/simulate.py, any ranks) with the set-up's stages timed,
per set-up and rank: exclusive CPU (``time.process_time``) and wall of each stage
(``_setup_band`` and ``BandCholesky.factor``: the per-wisp band factor; ``_couplings``,
``local_blocks``, ``wisp_couplings``, ``self_coupled``, ``self_blocks``: C's blocks and the
coupled wisp pairs, their allgather inside ``_couplings``; ``cluster_labels`` (compiled)
and ``cluster_owners``; ``_cluster_blocks``, ``block_rows`` and ``_to_owners``: the blocks
of A + C sent to the ranks factoring their clusters; ``_factor_clusters`` (the cluster
matrix's CSR in NumPy, the scatter) and ``factor_cluster_matrix`` (the AIJ matrix and
PETSc's LU; with ``compiled_cluster.point_csr`` apart)), PETSc's event times around
each set-up (``MatGetOrdering``, ``MatLUFactorSym``, ``MatLUFactorNum``, ``MatConvert``;
wall) and the set-up's ``stats`` (clusters, cluster rows, fill).  Writes
``OUT.<rank>.json``; ``--report`` prints medians over the set-ups of each rank.

    mpiexec -n 2 python scripts/profile_cluster_setup.py --out /tmp/p/prof -- \
        drivers/simulate.py run.toml --frames 23 --out /tmp/r --restart /tmp/r/checkpoints/checkpoint_000020.h5
    python scripts/profile_cluster_setup.py --report /tmp/p/prof

docs/contact_solver.md, "Where the cluster set-up goes".
"""

from __future__ import annotations

import argparse
import atexit
import functools
import glob
import json
import runpy
import sys
import time

import numpy as np

EVENTS = ("MatGetOrdering", "MatLUFactorSym", "MatLUFactorNum", "MatConvert")
METHODS = ("_setup_band", "_couplings", "_to_owners", "_cluster_blocks", "_factor_clusters", "_setup_clusters")
FUNCTIONS = ("local_blocks", "block_rows", "wisp_couplings", "self_coupled", "self_blocks", "cluster_labels",
             "cluster_owners", "factor_cluster_matrix")
STATS = ("clusters", "wisps", "largest", "rows", "fill", "couplings", "couplings_left_out", "captured",
         "cross_rank_clusters", "moved_rows", "band_rows")


def instrument(out):
    """Wrap the set-up's stages; write ``out.<rank>.json`` at exit."""
    from mpi4py import MPI
    from petsc4py import PETSc

    from lc_petsc import contact_pc
    from lc_petsc.elements import compiled_band, compiled_cluster

    PETSc.Log.begin()
    calls: list[dict] = []
    stack: list[list] = []           # [child CPU, child wall] of the open stages
    current: dict = {}

    def timed(name, fn):
        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            if not stack:
                return fn(*args, **kwargs)
            stack.append([0.0, 0.0])
            c0, t0 = time.process_time(), time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                cpu, wall = time.process_time() - c0, time.perf_counter() - t0
                child_cpu, child_wall = stack.pop()
                own = current["stages"].setdefault(name, [0.0, 0.0, 0])
                own[0] += cpu - child_cpu
                own[1] += wall - child_wall
                own[2] += 1
                stack[-1][0] += cpu
                stack[-1][1] += wall
        return wrapper

    def events():
        return {e: PETSc.Log.Event(e).getPerfInfo() for e in EVENTS}

    set_up = contact_pc.ClusterPC.setUp

    def profiled_set_up(self, pc):
        current.clear()
        current["stages"] = {}
        before = events()
        stack.append([0.0, 0.0])
        c0, t0 = time.process_time(), time.perf_counter()
        try:
            return set_up(self, pc)
        finally:
            cpu, wall = time.process_time() - c0, time.perf_counter() - t0
            child_cpu, child_wall = stack.pop()
            current["stages"]["setUp (own)"] = [cpu - child_cpu, wall - child_wall, 1]
            after = events()
            current.update(cpu=cpu, wall=wall, stats={k: self.stats.get(k, 0) for k in STATS},
                           events={e: [after[e]["time"] - before[e]["time"], after[e]["count"] - before[e]["count"]]
                                   for e in EVENTS})
            calls.append(dict(current))

    contact_pc.ClusterPC.setUp = profiled_set_up
    for name in METHODS:
        setattr(contact_pc.ClusterPC, name, timed(name, getattr(contact_pc.ClusterPC, name)))
    for name in FUNCTIONS:
        setattr(contact_pc, name, timed(name, getattr(contact_pc, name)))
    compiled_band.BandCholesky.factor = timed("BandCholesky.factor", compiled_band.BandCholesky.factor)
    if hasattr(compiled_cluster, "point_csr"):
        compiled_cluster.point_csr = timed("point_csr", compiled_cluster.point_csr)

    def dump():
        with open(f"{out}.{MPI.COMM_WORLD.rank}.json", "w") as f:
            json.dump(calls, f)
    atexit.register(dump)


def report(prefix):
    """Medians over the set-ups of each rank's file (the first set-ups, with no contact, skipped)."""
    for path in sorted(glob.glob(f"{prefix}.*.json")):
        calls = [c for c in json.load(open(path)) if c["stats"]["couplings"] > 0]
        if not calls:
            print(f"{path}: no set-up with contact")
            continue
        cpu, wall = (1e3 * np.median([c[k] for c in calls]) for k in ("cpu", "wall"))
        print(f"{path}: {len(calls)} set-ups with contact; CPU per set-up median {cpu:.1f} ms, wall {wall:.1f} ms")
        names = {k for c in calls for k in c["stages"]}
        for name in sorted(names, key=lambda k: -np.median([c["stages"].get(k, [0.0])[0] for c in calls])):
            cpu = [1e3 * c["stages"].get(name, [0.0, 0.0])[0] for c in calls]
            wall = [1e3 * c["stages"].get(name, [0.0, 0.0])[1] for c in calls]
            print(f"  {name:24s} CPU {np.median(cpu):8.2f} ms ({min(cpu):.1f}-{max(cpu):.1f})  "
                  f"wall {np.median(wall):8.2f} ms")
        for e in EVENTS:
            print(f"  event {e:18s} wall {1e3 * np.median([c['events'][e][0] for c in calls]):8.2f} ms  "
                  f"count {np.median([c['events'][e][1] for c in calls]):.0f}")
        for s in STATS:
            v = [c["stats"][s] for c in calls]
            print(f"  {s:24s} median {np.median(v):12.3f} ({min(v):.3g}-{max(v):.3g})")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", help="write OUT.<rank>.json and run the driver after --")
    parser.add_argument("--report", metavar="OUT", help="print the medians of OUT.<rank>.json")
    parser.add_argument("driver", nargs=argparse.REMAINDER, help="-- driver.py and its arguments")
    args = parser.parse_args()
    if args.report:
        report(args.report)
        return
    driver = args.driver[1:] if args.driver[:1] == ["--"] else args.driver
    if not args.out or not driver:
        parser.error("give --out OUT -- DRIVER.py ARGS..., or --report OUT")
    instrument(args.out)
    sys.argv = driver
    runpy.run_path(driver[0], run_name="__main__")


if __name__ == "__main__":
    main()
