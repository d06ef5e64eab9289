"""Repeat calls of the compiled gradient + Hessian pass, for instruction counts under valgrind.

On this machine ``perf stat -e instructions`` is not supported, and the shared cores
make CPU times noisy: the instruction count of the compiled pass is the firm measure.
The script builds ``--wisps`` helical 101-vertex wisps (0.01 cm noise, rest angle 0.3,
block-CSR layout of half bandwidth 3, no PETSc) and calls the fused pass of ``TERM``
(stretch, bend, twist or all) ``CALLS`` times; the counts of two runs with different
CALLS, subtracted, give the instructions of one call (imports, setup and the Numba
cache load cancel).  Valgrind has no AVX-512: compile for a CPU it runs (AVX2) with an
explicit feature list, so the run under valgrind loads the cache that a run without it
made (otherwise Numba recompiles inside valgrind, ~90G instructions, ~13 min)::

    export NUMBA_CPU_NAME=haswell NUMBA_CACHE_DIR=/tmp/numba_hsw
    F=+64bit,+avx,+avx2,+fma,+sse,+sse2,+sse3,+ssse3
    export NUMBA_CPU_FEATURES=$F,+sse4.1,+sse4.2,+popcnt,+cx16,+cmov,+mmx,+fxsr
    .venv/bin/python scripts/count_compiled.py twist 1          # fills the cache
    valgrind --tool=callgrind .venv/bin/python scripts/count_compiled.py twist 1
    valgrind --tool=callgrind .venv/bin/python scripts/count_compiled.py twist 6
    # per call: (I refs of the second - I refs of the first) / 5

``--filter none`` runs the exact Hessian.
"""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402

import numpy as np  # noqa: E402

from lc_petsc.elements import compiled  # noqa: E402
from lc_petsc.studies.command_line import integer_at_least  # noqa: E402

_K = {"stretch": 2, "bend": 3, "twist": 4}
_PER_WISP = 101


def synthetic(n_wisps, names, b=3):
    """(x, terms, layout) of n_wisps noisy helices, elements of ``names``."""
    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 20.0, _PER_WISP)
    helix = np.c_[np.cos(t), np.sin(t), 0.3 * t]
    x = np.concatenate([helix + rng.normal(size=3) * 10.0
                        + rng.normal(scale=0.01, size=helix.shape) for _ in range(n_wisps)])
    nv = len(x)
    wisp = np.arange(nv) // _PER_WISP
    terms = {}
    for name in names:
        start = np.flatnonzero((np.arange(nv) % _PER_WISP) <= _PER_WISP - _K[name])
        rest = np.full(len(start), 0.5 if name == "stretch" else 0.3)
        terms[name] = compiled.element_arrays(name, start, rest, np.ones(len(start)))
    j = np.arange(nv)[:, None] + np.arange(-b, b + 1)
    stored = (j >= 0) & (j < nv) & (wisp[np.clip(j, 0, nv - 1)] == wisp[:, None])
    return x, terms, compiled.BlockLayout.block_csr(stored, b)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("term", choices=(*compiled.TERMS, "all"))
    ap.add_argument("calls", type=integer_at_least(0))
    ap.add_argument("--wisps", type=integer_at_least(1), default=200)
    ap.add_argument("--filter", choices=compiled.FILTERS, default="analytic")
    args = ap.parse_args()
    x, terms, layout = synthetic(args.wisps, compiled.TERMS if args.term == "all" else (args.term,))
    values = np.zeros(layout.size())
    g = np.zeros_like(x)
    for _ in range(args.calls):
        compiled.add_gradient_hessian_into(terms, x, g, values, layout, False, args.filter)
    print(f"{args.calls} calls, {args.term}, {args.wisps} wisps, filter {args.filter}; "
          f"sum of values {values.sum():.6e}")


if __name__ == "__main__":
    main()
