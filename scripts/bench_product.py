"""Benchmark the strand matrix's product y = A x: PETSc's ``MatMult`` against the compiled
loop that the contact operator uses (lc_petsc/elements/compiled_mult.py), side by side
on the same matrix, and a NumPy sum of the values (a read of the same bytes) for
scale.  One rank: A is the hairball's strand matrix after one frame.

  .venv/bin/python scripts/bench_product.py [--wisps 2000] [--repeats 50]

Prints the median and the minimum in ms of each, and checks that the compiled product
equals ``MatMult``'s bit for bit.
"""

import argparse
import statistics
import sys
import time

import numpy as np
import petsc4py

petsc4py.init(sys.argv)
from lc_petsc.config import MaterialConfig, PhysicsConfig, SceneConfig, SimConfig, TimeConfig  # noqa: E402
from lc_petsc.elements import compiled_mult  # noqa: E402
from lc_petsc.petsc_capi import value_array  # noqa: E402
from lc_petsc.simulator import build_simulator  # noqa: E402
from lc_petsc.studies.command_line import integer_at_least, parse_args  # noqa: E402


def timed(fn, repeats):
    """(median, minimum) milliseconds of ``repeats`` calls of ``fn``."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(1e3 * (time.perf_counter() - t0))
    return statistics.median(times), min(times)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--wisps", type=integer_at_least(1), default=2000)
    ap.add_argument("--repeats", type=integer_at_least(1), default=50)
    args = parse_args(ap)
    cfg = SimConfig(scene=SceneConfig(kind="hairball", n_wisps=args.wisps),
                    material=MaterialConfig(youngs_modulus=1.0e9),
                    physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity"), head_motion="shake"),
                    time=TimeConfig(dt=1.0 / 30.0, frames=1, newton_iterations=3))
    sim = build_simulator(cfg)
    try:
        sim.step()
        A = sim.assembler.mat
        if A.getComm().getSize() != 1 or A.getType() != "seqbaij":
            raise SystemExit("bench_product: run on one rank with the default BAIJ matrix")
        compiled_mult.warm_up()
        x, y = A.createVecs()
        x.setRandom()
        indptr, indices = A.getRowIJ(compressed=True)
        with value_array(A, 9 * len(indices)) as values:
            xa = x.getArray(readonly=True)
            ya = np.empty_like(xa)
            A.mult(x, y)
            compiled_mult.bsr3_mult(indptr, indices, values, xa, ya, False)
            same = np.array_equal(ya, y.getArray(readonly=True))
            rows = {
                "PETSc MatMult": timed(lambda: A.mult(x, y), args.repeats),
                "compiled (bsr3_mult)": timed(lambda: compiled_mult.bsr3_mult(indptr, indices, values, xa, ya, False),
                                              args.repeats),
                "NumPy sum of the values": timed(values.sum, args.repeats),
            }
            mb = values.nbytes / 1e6
        print(f"y = A x, hairball {args.wisps} wisps, {A.getSize()[0]} rows, {mb:.1f} MB of values, "
              f"one rank, {args.repeats} repeats")
        for name, (med, low) in rows.items():
            print(f"  {name:26s} median {med:7.2f} ms  min {low:7.2f} ms  ({mb / med:.1f} GB/s)")
        base = rows["PETSc MatMult"][0]
        print(f"compiled / MatMult: {rows['compiled (bsr3_mult)'][0] / base:.2f}x; "
              f"equal to MatMult bit for bit: {same}")
        x.destroy()
        y.destroy()
    finally:
        sim.close()


if __name__ == "__main__":
    main()
