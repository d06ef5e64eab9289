"""Two checkouts of lc_petsc side by side on the same restart: did a code change make a
scene slower, or is the machine?  Each tree's ``drivers/simulate.py`` (with ``PYTHONPATH``
= the tree) continues the same checkpoint for the same frames, in a fresh folder holding
a copy of the checkpoint only, the trees interleaved A B, B A, A B, ... (a loaded
machine's drift falls on both alike); then per run the step time, CPU, the solve and
collision phases (wall and CPU, summary.json's ``timings_s`` / ``cpu_timings_s``), the
CG iterations, contact pairs and limiter candidates, and the largest position difference
of the last frame from the first tree's first run; per round B / A of the CPU figures,
and their medians.

  .venv/bin/python scripts/compare_trees.py --config CFG.toml --checkpoint CK.h5 \
      --frames 93 [--ranks 1] [--rounds 3] --out DIR TREE_A TREE_B

Every run uses ``--force`` (a checkpoint of another code version or rank count) and
writes frames.h5 from the checkpoint's frame on (the earlier rows NaN).  Each tree needs
its own compiled kernels: Numba's cache is per source path, so a tree's first run
compiles them (minutes; run a round more, or warm each tree first).  Bad input (a TREE
without drivers/simulate.py, a missing --config or --checkpoint, any other option: the runs
take their PETSc options from the config) is one error line, exit 2, before anything runs;
a run that fails stops the comparison, exit 3, with its last line and its log's path.
"""

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np

from lc_petsc.studies.command_line import integer_at_least

FIGURES = ("step", "cpu", "solve_cpu", "collision_cpu")


class RunFailed(RuntimeError):
    """A tree's run of drivers/simulate.py did not end with status 0."""


def check_inputs(ap: argparse.ArgumentParser, args: argparse.Namespace, extra: list[str]) -> None:
    """Bad input is argparse's error (one line, exit 2) before anything runs or is written."""
    if extra:
        ap.error(f"unrecognized arguments: {' '.join(extra)} (the runs get no PETSc options from this command "
                 "line: both trees run the config, so put them in its solver.options)")
    for tree in args.trees:
        if not (tree / "drivers" / "simulate.py").is_file():
            ap.error(f"TREE {tree}: not a checkout of lc_petsc (no drivers/simulate.py there)")
    for flag, path in (("--config", args.config), ("--checkpoint", args.checkpoint)):
        if not path.is_file():
            ap.error(f"{flag} {path}: no such file")


def run(tree: Path, config: Path, checkpoint: Path, frames: int, ranks: int, out: Path) -> dict:
    """One restarted run of ``tree`` into ``out`` (replaced); its figures."""
    shutil.rmtree(out, ignore_errors=True)
    (out / "checkpoints").mkdir(parents=True)
    ck = out / "checkpoints" / checkpoint.name
    shutil.copy(checkpoint, ck)
    cmd = ["mpiexec", "-n", str(ranks), sys.executable, str(tree / "drivers" / "simulate.py"), str(config),
           "--frames", str(frames), "--out", str(out), "--restart", str(ck), "--force", "--quiet"]
    env = dict(os.environ, PYTHONPATH=str(tree))
    with open(f"{out}.log", "w") as log:
        code = subprocess.run(cmd, env=env, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT).returncode
    if code:
        said = [line for line in Path(f"{out}.log").read_text(errors="replace").splitlines() if line.strip()]
        errors = [line for line in said if "error" in line.lower()] or said    # mpiexec's notes end the log
        raise RunFailed(f"the run of {tree} into {out} ended with exit status {code}: "
                        f"{errors[-1] if errors else 'no output'} (all of it: {out}.log)")
    s = json.loads((out / "summary.json").read_text())
    with h5py.File(out / "frames.h5", "r") as f:
        last = f["positions"][-1]
    c = s.get("contact", {})
    return {"step": s["step_time_s"], "cpu": s["cpu_time_s"], "solve": s["timings_s"]["solve"],
            "solve_cpu": s["cpu_timings_s"]["solve"], "collision": s["timings_s"]["collision"],
            "collision_cpu": s["cpu_timings_s"]["collision"], "ksp": int(sum(s["ksp_iterations"])),
            "pairs": int(sum(c.get("pairs_per_frame", []))),
            "limiter_candidates": int(sum(c.get("limiter_candidates_per_frame", []))), "last": last}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("trees", nargs=2, type=Path, metavar="TREE", help="two checkouts (A, B)")
    ap.add_argument("--config", type=Path, required=True)
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--frames", type=integer_at_least(1), required=True, help="the last frame")
    ap.add_argument("--ranks", type=integer_at_least(1), default=1)
    ap.add_argument("--rounds", type=integer_at_least(1), default=3)
    ap.add_argument("--out", type=Path, required=True)
    args, extra = ap.parse_known_args(argv)
    check_inputs(ap, args, extra)
    trees = [t.resolve() for t in args.trees]
    args.out.mkdir(parents=True, exist_ok=True)
    runs: list[list[dict]] = [[], []]
    ref = None
    for r in range(args.rounds):
        for k in ((0, 1) if r % 2 == 0 else (1, 0)):
            try:
                fig = run(trees[k], args.config.resolve(), args.checkpoint.resolve(), args.frames, args.ranks,
                          args.out / f"{'ab'[k]}{r}")
            except RunFailed as e:
                print(f"compare_trees.py: error: {e}", file=sys.stderr)
                return 3
            ref = fig["last"] if ref is None else ref
            fig["dx"] = float(np.abs(fig.pop("last") - ref).max())
            runs[k].append(fig)
            print(f"round {r} {'AB'[k]}: " + ", ".join(f"{n} {v:.4g}" for n, v in fig.items()), flush=True)
    ratios = {n: [b[n] / a[n] for a, b in zip(*runs)] for n in FIGURES}
    for n, v in ratios.items():
        print(f"B / A {n}: median {statistics.median(v):.3f} ({', '.join(f'{x:.3f}' for x in v)})")
    (args.out / "compare.json").write_text(json.dumps({"trees": [str(t) for t in trees], "runs": runs,
                                                       "ratios": ratios}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
