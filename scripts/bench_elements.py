"""Element-kernel benchmark: gradient + filtered Hessian at hairball size, both filters.

Evaluates gradient + Hessian (one fused call per term, outputs reused across repeats as
the Newton loop does) of stretch, bend and twist at the element counts of the 2,000-wisp
hairball (101-vertex wisps: 200k edges, 198k bends, 196k twists), once with the analytic
filter and once with the numerical one, alternating in the same run, on one core. Prints
elements per second per term and filter (medians), the numerical/analytic time ratio and
the peak memory of the process.

    .venv/bin/python scripts/bench_elements.py [--wisps 2000] [--repeats 7]

Targets: ratio >= 8, analytic total <= 1.0 s, peak memory < 3 GB.
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
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--wisps", type=int, default=2000)
    parser.add_argument("--vertices", type=int, default=101)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--json", help="also write the figures to this JSON file")
    args = parser.parse_args()

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


if __name__ == "__main__":
    main()
