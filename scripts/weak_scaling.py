"""Weak scaling: the hairball with a fixed number of wisps per rank (default 500), no
contact, on 1, 2, ... ranks: wall and CPU time per frame, elements + assembly and solve
CPU per Newton iteration, Newton and KSP iterations (which must not change with the
rank count: the per-wisp block Jacobi is exact without contact).

  .venv/bin/python scripts/weak_scaling.py [--per-rank 500] [--ranks 1 2 3 4] [--frames 2]
      [--measured 2] [--out out/weak_scaling] [--figure docs/figures/weak_scaling_500.png]

Each rank count runs ``mpiexec -n P scripts/bench_step.py --wisps (per-rank x P)
--contact off --json ...`` (medians of ``--frames`` frames after the first).  Rank
counts above ``--measured`` (default 2: this machine's cores) are oversubscribed and
reported for correctness only (iteration counts), not for time.  Prints a table, writes
it as JSON to ``--out`` and plots wall and CPU per frame against ranks to ``--figure``.
"""

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from lc_petsc.studies.command_line import integer_at_least

ROOT = Path(__file__).resolve().parent.parent


def run(ranks, wisps, frames, out):
    """One bench_step run; returns its JSON figures."""
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1")
    cmd = ["mpiexec", "--oversubscribe", "-n", str(ranks), sys.executable,
           str(ROOT / "scripts" / "bench_step.py"), "--wisps", str(wisps), "--frames", str(frames),
           "--contact", "off", "--json", str(out)]
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stdout}\n{proc.stderr}")
    return json.loads(Path(out).read_text())


def median(values):
    v = sorted(values)
    n = len(v)
    return v[n // 2] if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--per-rank", type=integer_at_least(1), default=500)
    ap.add_argument("--ranks", type=integer_at_least(1), nargs="+", default=[1, 2, 3, 4])
    ap.add_argument("--frames", type=integer_at_least(1), default=2)
    ap.add_argument("--measured", type=integer_at_least(0), default=2,
                    help="rank counts up to this are timed; above, correctness only")
    ap.add_argument("--out", default="out/weak_scaling")
    ap.add_argument("--figure", default="docs/figures/weak_scaling_500.png")
    args = ap.parse_args()
    out = ROOT / args.out
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for p in args.ranks:
        r = run(p, args.per_rank * p, args.frames, out / f"ranks_{p}.json")
        its = median(r["newton_iterations"][1:])
        rows.append(dict(ranks=p, wisps=r["wisps"], dofs=r["dofs"], timed=p <= args.measured,
                         wall_s=median(r["frame_walls_s"]),
                         cpu_per_rank_s=median(r["frame_cpu_total_s"]) / p,
                         elements_assembly_cpu_ms=r["elements_assembly_ms_per_iteration"]["cpu"],
                         solve_cpu_ms=1e3 * r["phase_cpu_s"]["solve"] / its,
                         newton=r["newton_iterations"], ksp=r["ksp_iterations"]))
    base = rows[0]
    print(f"weak scaling, {args.per_rank} wisps per rank, no contact, medians of {args.frames} "
          f"frames after the first")
    print("ranks | wisps | DoFs | wall s/frame | CPU s/frame/rank | elem+asm CPU ms/it | "
          "solve CPU ms/it | wall eff. | CPU eff. | Newton its | KSP its/solve")
    for r in rows:
        note = "" if r["timed"] else " (oversubscribed: correctness only)"
        print(f"{r['ranks']} | {r['wisps']} | {r['dofs']} | {r['wall_s']:.3f} | "
              f"{r['cpu_per_rank_s']:.3f} | {r['elements_assembly_cpu_ms']:.1f} | "
              f"{r['solve_cpu_ms']:.1f} | {base['wall_s'] / r['wall_s']:.2f} | "
              f"{base['cpu_per_rank_s'] / r['cpu_per_rank_s']:.2f} | {sorted(set(r['newton']))} | "
              f"{sorted(set(r['ksp']))}{note}")
    same = all(r["newton"] == base["newton"] and r["ksp"] == base["ksp"] for r in rows)
    print(f"iteration counts identical on every rank count: {same}")
    (out / "weak_scaling.json").write_text(json.dumps(dict(per_rank=args.per_rank, rows=rows), indent=1))
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    for key, label in (("wall_s", "wall per frame"), ("cpu_per_rank_s", "CPU per frame per rank")):
        for timed, style in ((True, "o-"), (False, "x:")):
            pts = [(r["ranks"], r[key]) for r in rows if r["timed"] == timed]
            if pts:
                ax.plot(*zip(*pts), style, label=f"{label}{'' if timed else ' (oversubscribed)'}")
    ax.axhline(base["cpu_per_rank_s"], color="grey", lw=0.5)
    ax.set_xlabel("ranks")
    ax.set_ylabel("s")
    ax.set_xticks([r["ranks"] for r in rows])
    ax.set_title(f"weak scaling, {args.per_rank} wisps per rank, no contact")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(ROOT / args.figure, dpi=120)
    print(f"wrote {out / 'weak_scaling.json'} and {args.figure}")


if __name__ == "__main__":
    main()
