"""Newton variants frame by frame from the same start states (docs/newton.md, seventh
round; logic in lc_petsc/studies/newton_frames.py).  One rank.

  .venv/bin/python scripts/newton_frames.py [--scene hairball10] [--frames 30] [--tol 1e-6]
      [--iterations 30] [--variant NAME=SPEC ...] [--wisps 10] [--out out/newton_frames.json]
      [--plot FIGURE.png]

SPEC as in scripts/newton_history.py (e.g. filter=exact_or_analytic,update=corotational,
fallback=shifted).  The start states are those of a run converged to 1e-9 (cap 60) with
exact_or_analytic, corotational, shifted fallback.  Prints per variant the iterations
per frame to the tolerance ("-": not within the cap), median / worst (a miss counts as
cap + 1) / total, the first iteration within the tolerance of the reference solution
("true error"), the exact steps per frame, and the median first-iterate error; --plot
draws the iterations per frame (increment test and true error) and the median error
per iteration over the frames from 3 on.
"""

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np
import petsc4py

petsc4py.init(sys.argv[:1])
from mpi4py import MPI  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from newton_history import check_variants, named_variants, scene  # noqa: E402

from lc_petsc.studies import report  # noqa: E402
from lc_petsc.studies.command_line import bad_input, figure_file, integer_at_least, positive_number  # noqa: E402
from lc_petsc.studies.newton_frames import compare  # noqa: E402

DEFAULT_VARIANTS = [
    "corotational (sixth round)=filter=exact_or_analytic,update=corotational",
    "corotational, shifted fallback=filter=exact_or_analytic,update=corotational,fallback=shifted",
]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="hairball10")
    p.add_argument("--frames", type=integer_at_least(1), default=30)
    p.add_argument("--tol", type=positive_number, default=1e-6)
    p.add_argument("--iterations", type=integer_at_least(1), default=30)
    p.add_argument("--variant", action="append", help="NAME=SPEC (repeatable)")
    p.add_argument("--wisps", type=integer_at_least(1), default=10)
    p.add_argument("--out", default="out/newton_frames.json")
    p.add_argument("--plot", type=figure_file, help="figure path (png)")
    a = p.parse_args(argv)
    try:
        variants = named_variants(a.variant or DEFAULT_VARIANTS)
        base = scene(a.scene, a.wisps)
        check_variants([(a.scene, base)], variants, a.iterations, a.frames)
    except (ValueError, OSError) as e:          # ConfigError is a ValueError
        return bad_input(MPI.COMM_WORLD, "newton_frames.py", e)
    res = compare(base, variants, MPI.COMM_WORLD, a.frames, a.tol, a.iterations)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res))
    print(f"reference converged in every frame: {res['reference_converged']} (stops refused on a saddle "
          f"of G in frames {[f for f, s in enumerate(res['reference_saddle']) if s]})")
    miss = a.iterations + 1
    for name, _ in variants:
        rows = res[name]
        its = [r["iterations"] if r["converged"] else miss for r in rows]
        true = [r["true"] or miss for r in rows]
        print(f"{name}: median {statistics.median(its):g}, worst {max(its)}, total "
              f"{sum(r['iterations'] for r in rows)}, frames missed {its.count(miss)}")
        print("  iterations  " + " ".join(str(i) if i < miss else "-" for i in its))
        print(f"  true error < {a.tol:g} at (median {statistics.median(true):g})  "
              + " ".join(str(i) if i < miss else "-" for i in true))
        print(f"  exact steps (median {statistics.median(r['exact_steps'] for r in rows):g})  "
              + " ".join(str(r["exact_steps"]) for r in rows)
              + f"; shifted {sum(r['shifted_steps'] for r in rows)}")
        print(f"  first iterate's error: median {statistics.median(r['first_error'] for r in rows):.2e}")
    if a.plot:
        plot(res, [n for n, _ in variants], a.tol, a.iterations, a.plot, a.scene)
    return 0


def plot(res, names, tol, cap, path, title):
    """Left: iterations per frame (solid: the increment test, dotted: the true error below
    ``tol``; a miss at cap + 1); right: the median over frames 3.. of the error after each
    iteration (the first iterate at 0)."""
    plt = report._plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for k, name in enumerate(names):
        rows, c = res[name], f"C{k}"
        axes[0].plot([r["iterations"] if r["converged"] else cap + 1 for r in rows], c, marker=".", label=name)
        axes[0].plot([r["true"] or cap + 1 for r in rows], c, ls=":", lw=1)
        errs = [[r["first_error"]] + r["errors"] for r in rows[3:]]
        if errs:                                # none with fewer than 4 frames: the panel stays empty
            n = min(len(e) for e in errs)
            axes[1].semilogy(range(n), np.maximum(np.median([e[:n] for e in errs], axis=0), 1e-17),
                             c, marker=".", label=name)
    axes[0].set_xlabel("frame")
    axes[0].set_ylabel(f"iterations to {tol:g} (dotted: true error)")
    axes[1].axhline(tol, color="k", lw=0.8, ls="--")
    axes[1].set_xlabel("Newton iteration (0: first iterate)")
    axes[1].set_ylabel("error / wisp length (median, frames 3..)")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{title}: each frame from the reference's start state")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
