"""Why the filtered Newton converges linearly: at converged frames of a small scene, the
linear rate of the filtered iteration (spectral radius of I - H_f^{-1} H) with every
term filtered and with one term filtered at a time, and the smallest eigenvalue of the
exact Newton matrix; and how close the Newton iterates come to the elements'
degenerate rules (docs/newton.md).  One rank, dense matrices: small scenes only.

  .venv/bin/python scripts/newton_rates.py [--scene hairball10|smash|CONFIG.toml]
      [--frames 3] [--margin-frames 10] [--out out/newton_rates]

Outputs in --out: rates.json, rates.md (table), rates.png (rate per frame and filter).
"""

import argparse
import sys
from pathlib import Path

import petsc4py

petsc4py.init(sys.argv[:1])
from mpi4py import MPI  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from newton_history import scene  # noqa: E402

from lc_petsc.studies import report  # noqa: E402
from lc_petsc.studies.command_line import bad_input, integer_at_least  # noqa: E402
from lc_petsc.studies.newton import degenerate_margins, filter_rates  # noqa: E402

TERMS = ("stretch", "bend", "twist")
COMBOS = ([("all analytic", {t: "analytic" for t in TERMS}), ("all abs", {t: "abs" for t in TERMS})]
          + [(f"{t} analytic", {t: "analytic"}) for t in TERMS])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="hairball10")
    p.add_argument("--frames", type=integer_at_least(1), default=3)
    p.add_argument("--margin-frames", type=integer_at_least(1), default=10)
    p.add_argument("--out", default="out/newton_rates")
    a = p.parse_args(argv)
    comm = MPI.COMM_WORLD
    try:
        cfg = scene(a.scene)
    except (ValueError, OSError) as e:          # ConfigError is a ValueError
        return bad_input(comm, "newton_rates.py", e)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"{a.scene}: filter rates at {a.frames} converged frames")
    rows = filter_rates(cfg, comm, COMBOS, a.frames)
    print(f"{a.scene}: degenerate-rule margins over {a.margin_frames} frames (exact_or_analytic)")
    mcfg = scene(a.scene)
    mcfg.solver.filter = "exact_or_analytic"
    mcfg.time.newton_iterations = 30
    mcfg.time.newton_increment_tol = 1e-6
    margins = degenerate_margins(mcfg, comm, a.margin_frames)
    print("  " + ", ".join(f"{k} {v:.3g}" for k, v in margins.items()))
    report.write_json({"scene": a.scene, "rates": rows, "margins": margins}, out / "rates.json")
    names = [n for n, _ in COMBOS]
    head = ["frame", "Newton its", "last increment", "exact min eig", "min M/dt^2"] + names
    body = [[str(r["frame"]), str(r["iterations"]), f"{r['increment']:.1e}",
             f"{r['exact_min_eigenvalue']:.3g}", f"{r['mass_dt2_min']:.3g}"]
            + [f"{r[n]:.4f}" for n in names] for r in rows]
    text = (f"# Linear rate of the filtered Newton at converged frames: {a.scene}\n\n"
            + report.markdown_table(head, body)
            + "\n\nDegenerate-rule margins over every Newton iterate of "
            f"{a.margin_frames} frames: " + ", ".join(f"{k} {v:.3g}" for k, v in margins.items()) + "\n")
    (out / "rates.md").write_text(text)
    plt = report._plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    for n in names:
        ax.plot([r["frame"] for r in rows], [r[n] for r in rows], marker="o", label=n)
    ax.set_xlabel("frame")
    ax.set_ylabel("rate (spectral radius of I - Hf^-1 H)")
    ax.set_title(f"{a.scene}: filtered Newton's linear rate at the solution")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "rates.png", dpi=110)
    plt.close(fig)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
