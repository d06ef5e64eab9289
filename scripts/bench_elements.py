"""Element-kernel benchmark: gradient + filtered Hessian at hairball size, both filters;
with ``--assembly``, one Newton iteration's elements + band assembly, NumPy vs compiled.

Evaluates gradient + Hessian (one fused call per term, outputs reused across repeats as
the Newton loop does) of stretch, bend and twist at the element counts of the 2,000-wisp
hairball (101-vertex wisps: 200k edges, 198k bends, 196k twists), once with the analytic
filter and once with the numerical one, alternating in the same run, on one core. Prints
elements per second per term and filter (medians), the numerical/analytic time ratio and
the peak memory of the process.

    .venv/bin/python scripts/bench_elements.py [--wisps 2000] [--vertices 101] [--repeats 7] [--json F]

Targets: ratio >= 8, analytic total <= 1.0 s, peak memory < 3 GB.

    .venv/bin/python scripts/bench_elements.py --assembly [--wisps 2000] [--repeats 7] [--json F]

builds the hairball's Assembler twice on one rank (``-lc_element_kernels numpy`` and
``compiled``, analytic filter, BAIJ) and times, alternating in the same run, what one
Newton iteration spends in the assembler: ``assemble`` (elements, gradient, band and
the mass term) and ``commit`` (pinned rows, CSR values into the matrix), wall and CPU time
(medians; CPU time is less disturbed by other processes on the machine).  Also the
compiled kernels' JIT time (compile, or load from Numba's cache), reported apart.
Target: compiled elements + assembly <= 60 ms per Newton iteration.
"""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")   # one core, before NumPy loads BLAS
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from lc_petsc.elements import bend, stretch, twist  # noqa: E402
from lc_petsc.studies.command_line import integer_at_least, output_file  # noqa: E402

TERMS = (("stretch", stretch, 2), ("bend", bend, 3), ("twist", twist, 4))
FILTERS = ("analytic", "numerical")


def curly_wisps(n_wisps, n_vertices, seed=0):
    """Helical wisps (0.5 cm radius, 72 degrees and 0.1 cm per vertex), randomly oriented.

    Returns (rest, deformed) positions (n_wisps, n_vertices, 3); the deformed state is the
    rest state with 0.05 cm noise, so every filter has negative eigenvalues to clamp.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n_vertices) * (2.0 * np.pi / 5.0)
    helix = np.stack([0.5 * np.cos(t), 0.5 * np.sin(t), 0.1 * np.arange(n_vertices)], axis=1)
    q, _ = np.linalg.qr(rng.normal(size=(n_wisps, 3, 3)))
    rest = np.einsum("wij,vj->wvi", q, helix) + rng.normal(scale=15.0, size=(n_wisps, 1, 3))
    return rest, rest + rng.normal(scale=0.05, size=rest.shape)


def element_arrays(wisps, k):
    """Stencils of k consecutive vertices of every wisp: (n_wisps * (n_v - k + 1), k, 3)."""
    n_v = wisps.shape[1]
    idx = np.arange(n_v - k + 1)[:, None] + np.arange(k)
    return wisps[:, idx].reshape(-1, k, 3)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--wisps", type=integer_at_least(1), default=2000)
    parser.add_argument("--vertices", type=integer_at_least(4), default=101)
    parser.add_argument("--repeats", type=integer_at_least(1), default=7)
    parser.add_argument("--json", type=output_file, help="also write the figures to this JSON file")
    parser.add_argument("--assembly", action="store_true",
                        help="elements + assembly of one Newton iteration, NumPy vs compiled")
    args = parser.parse_args()
    if args.assembly:
        return assembly_benchmark(args)

    rest, x = curly_wisps(args.wisps, args.vertices)
    cases = []
    for name, mod, k in TERMS:
        xr, xe = element_arrays(rest, k), element_arrays(x, k)
        rest_value = stretch.length(xr) if mod is stretch else mod.angle(xr)
        cases.append((name, mod, xe, rest_value, np.ones(len(xe))))
    print("elements: " + ", ".join(f"{len(c[2])} {c[0]}" for c in cases)
          + f"; {args.repeats} alternating rounds, one core")

    times = {(f, c[0]): [] for f in FILTERS for c in cases}
    buffers = {}
    for round_ in range(args.repeats + 1):          # round 0 warms up and is dropped
        for f in FILTERS:
            for name, mod, xe, rv, ks in cases:
                t0 = time.perf_counter()
                _, h = mod.gradient_hessian(xe, rv, ks, filter=f, out=buffers.get((f, name)))
                dt = time.perf_counter() - t0
                buffers[(f, name)] = h
                if round_ > 0:
                    times[(f, name)].append(dt)

    med = {key: statistics.median(v) for key, v in times.items()}
    print(f"\n{'term':8} {'filter':10} {'median s':>9} {'elements/s':>12}")
    for f in FILTERS:
        for name, _, xe, _, _ in cases:
            print(f"{name:8} {f:10} {med[(f, name)]:9.3f} {len(xe) / med[(f, name)]:12.3e}")
    totals = {f: statistics.median([sum(times[(f, c[0])][r] for c in cases)
                                    for r in range(args.repeats)]) for f in FILTERS}
    ratio = totals["numerical"] / totals["analytic"]
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"\nall three terms: analytic {totals['analytic']:.3f} s, numerical "
          f"{totals['numerical']:.3f} s (medians)")
    print(f"numerical/analytic time ratio: {ratio:.2f}x (target >= 8; paper 3.6x)")
    print(f"analytic total {'meets' if totals['analytic'] <= 1.0 else 'MISSES'} the 1.0 s target")
    print(f"peak memory (process max RSS, both filters' buffers): {peak_gb:.2f} GB (target < 3)")
    for name, _, _, _, _ in cases:
        print(f"  {name}: numerical/analytic {med[('numerical', name)] / med[('analytic', name)]:.2f}x")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"median_s": {f"{f}/{n}": v for (f, n), v in med.items()},
                       "total_s": totals, "ratio": ratio, "peak_rss_gb": peak_gb}, fh, indent=2)


def assembly_benchmark(args):
    """``--assembly``: see the module doc."""
    import petsc4py
    petsc4py.init([])
    from mpi4py import MPI
    from lc_petsc.config import (MaterialConfig, PhysicsConfig, SceneConfig, SimConfig,
                                 SolverConfig)
    from lc_petsc.simulator import build_simulator

    modes = ("numpy", "compiled")
    sims, build = {}, {}
    for mode in modes:
        cfg = SimConfig(scene=SceneConfig(kind="hairball", n_wisps=args.wisps, perturbation="jitter",
                                          jitter=0.05),
                        material=MaterialConfig(youngs_modulus=1.0e9),
                        physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity")),
                        solver=SolverConfig(options=f"-lc_element_kernels {mode}"))
        t0 = time.perf_counter()
        sims[mode] = build_simulator(cfg, comm=MPI.COMM_SELF)
        build[mode] = time.perf_counter() - t0
    sim0 = sims["numpy"]
    x = sim0.x.copy()
    mass = sim0.scene.mass * 900.0
    print(f"hairball {args.wisps} wisps, {3 * sim0.scene.nv} DoFs, one rank, analytic filter, "
          f"{sim0.assembler.mat.getType()}; {args.repeats} alternating rounds")
    print(f"compiled kernels' JIT (compile or load from cache): "
          f"{sims['compiled'].assembler.compile_seconds:.2f} s (in the build, not a frame)")
    wall = {m: {"assemble": [], "commit": []} for m in modes}
    cpu = {m: {"assemble": [], "commit": []} for m in modes}
    for round_ in range(args.repeats + 1):          # round 0 warms up and is dropped
        for mode in modes:
            asm = sims[mode].assembler
            for phase in ("assemble", "commit"):
                w0, c0 = time.perf_counter(), time.process_time()
                if phase == "assemble":
                    asm.assemble(x, mass)
                else:
                    asm.commit()
                if round_ > 0:
                    wall[mode][phase].append(time.perf_counter() - w0)
                    cpu[mode][phase].append(time.process_time() - c0)
    # the same matrix from both (round-off)
    va = sims["numpy"].assembler.mat.getValuesCSR()[2]
    vb = sims["compiled"].assembler.mat.getValuesCSR()[2]
    diff = float(np.abs(va - vb).max() / np.abs(va).max())
    med = lambda v: 1e3 * statistics.median(v)  # noqa: E731
    print(f"\n{'kernels':9} {'assemble ms':>12} {'commit ms':>10} {'total ms':>9} {'total CPU ms':>13}")
    res = {}
    for mode in modes:
        tot = med([a + c for a, c in zip(wall[mode]["assemble"], wall[mode]["commit"])])
        tot_cpu = med([a + c for a, c in zip(cpu[mode]["assemble"], cpu[mode]["commit"])])
        res[mode] = dict(assemble_ms=med(wall[mode]["assemble"]), commit_ms=med(wall[mode]["commit"]),
                         total_ms=tot, total_cpu_ms=tot_cpu)
        print(f"{mode:9} {res[mode]['assemble_ms']:12.1f} {res[mode]['commit_ms']:10.1f} {tot:9.1f} "
              f"{tot_cpu:13.1f}")
    speedup = res["numpy"]["total_ms"] / res["compiled"]["total_ms"]
    target = res["compiled"]["total_ms"] <= 60.0
    print(f"compiled / numpy: {speedup:.1f}x faster; largest matrix difference {diff:.1e} (relative)")
    print(f"compiled elements + assembly {'meets' if target else 'MISSES'} the 60 ms target")
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"peak memory (both assemblers): {peak_gb:.2f} GB")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"per_newton_iteration": res, "speedup": speedup, "matrix_rel_diff": diff,
                       "jit_s": sims["compiled"].assembler.compile_seconds, "build_s": build,
                       "peak_rss_gb": peak_gb}, fh, indent=2)
    for s_ in sims.values():
        s_.close()


if __name__ == "__main__":
    main()
