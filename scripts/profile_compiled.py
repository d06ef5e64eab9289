"""CPU time of the compiled element pass per term and mode, at hairball size, one core.

Builds the 2,000-wisp hairball (stretch + bend + twist, analytic filter, BAIJ, one
rank) and times, on one Newton iterate (rest state + 0.01 cm noise), each term alone
and all together in the three modes of ``lc_petsc.elements.compiled`` (energy,
gradient, gradient + Hessian into PETSc's value array), the row zeroing alone, a plain
``fill(0)`` of the value array, and the assembler's ``assemble``, ``add_mass`` and
``commit``, and a Newton iteration's elements + assembly (``assemble`` with the mass
term, then ``commit``): minimum and median CPU ms over ``--repeats`` calls.

    .venv/bin/python scripts/profile_compiled.py [--wisps 2000] [--repeats 9] [--only TERM]

``--only TERM`` times that term's gradient + Hessian alone (a short run for
interleaved A/B comparisons of one kernel).
"""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")   # one core, before NumPy loads BLAS

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import petsc4py  # noqa: E402

petsc4py.init([])
from mpi4py import MPI  # noqa: E402

from lc_petsc.config import MaterialConfig, PhysicsConfig, SceneConfig, SimConfig  # noqa: E402
from lc_petsc.elements import compiled  # noqa: E402
from lc_petsc.simulator import build_simulator  # noqa: E402
from lc_petsc.studies.command_line import integer_at_least  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--wisps", type=integer_at_least(1), default=2000)
    ap.add_argument("--repeats", type=integer_at_least(1), default=9)
    ap.add_argument("--only", choices=compiled.TERMS, default=None,
                    help="time only this term's gradient + Hessian")
    args = ap.parse_args()
    cfg = SimConfig(scene=SceneConfig(kind="hairball", n_wisps=args.wisps),
                    material=MaterialConfig(youngs_modulus=1.0e9),
                    physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity")))
    sim = build_simulator(cfg, comm=MPI.COMM_SELF)
    asm = sim.assembler
    x = sim.x + np.random.default_rng(0).normal(scale=0.01, size=sim.x.shape)
    g = np.zeros_like(x)

    def cpu_ms(f):
        ts = []
        for _ in range(args.repeats):
            c0 = time.process_time()
            f()
            ts.append(time.process_time() - c0)
        return 1e3 * min(ts), 1e3 * statistics.median(ts)

    res = {}
    with asm.block_array() as v:
        for name in (args.only,) if args.only else compiled.TERMS:
            one = {name: asm.elements[name]}
            res[f"{name} gradient+Hessian"] = cpu_ms(
                lambda: compiled.add_gradient_hessian_into(one, x, g, v, asm.layout, False))
            if not args.only:
                res[f"{name} gradient"] = cpu_ms(lambda: compiled.add_gradient(one, x, g))
        if not args.only:
            res["all gradient+Hessian"] = cpu_ms(
                lambda: compiled.add_gradient_hessian_into(asm.elements, x, g, v, asm.layout,
                                                           False))
            res["all gradient"] = cpu_ms(lambda: compiled.add_gradient(asm.elements, x, g))
            res["all energy"] = cpu_ms(lambda: compiled.energy(asm.elements, x))
            res["row zeroing only"] = cpu_ms(
                lambda: compiled.add_gradient_hessian_into({}, x, g, v, asm.layout, False))
            res["values.fill(0)"] = cpu_ms(lambda: v.fill(0.0))
    if not args.only:
        res["Assembler.assemble"] = cpu_ms(lambda: asm.assemble(x))
        mass = sim.scene.mass * 900.0
        res["Assembler.add_mass"] = cpu_ms(lambda: asm.add_mass(mass))
        res["Assembler.commit"] = cpu_ms(asm.commit)
        # what a Newton iteration runs: the mass added in the element pass, then commit
        res["assemble(x, mass)+commit"] = cpu_ms(lambda: (asm.assemble(x, mass), asm.commit()))
    counts = {k: len(e[0]) for k, e in asm.elements.items()}
    print(f"hairball {args.wisps} wisps, {sim.scene.nv} vertices, elements {counts}, "
          f"{asm.n_values} stored values; CPU ms over {args.repeats} calls")
    for k, (lo, med) in res.items():
        print(f"{k:24s} min {lo:7.1f}  median {med:7.1f}")
    sim.close()


if __name__ == "__main__":
    main()
