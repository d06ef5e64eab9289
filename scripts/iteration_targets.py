"""Issue 14's iteration-target table on whole runs (docs/newton.md "Targets of the issue").

  .venv/bin/python scripts/iteration_targets.py [--scenes demo hairball10 smash]
      [--frames N] [--tol 1e-6] [--iterations 30] [--max-substeps 8]
      [--path NAME=SPEC ...] [--check-every 0] [--out out/iteration_targets.json]

Scenes: demo (configs/hairball_demo.toml without strand contact, 300 wisps, the inertial
first iterate), hairball10 (the same cut to 10 wisps), smash (configs/smash.toml), or a
config file; each runs its config's frames unless --frames.  Paths: SPEC as in
scripts/newton_history.py ("" keeps the config's own solver settings); by default main's
recommended path for a tolerance and the opt-ins solver.wisp_trust +
time.newton_stop = "chord_estimate", with the inertial and the follow-the-leader first
iterate, and with the inertial one and time.jolt_first_iterate (the start's first iterate
at each jump of the head's velocity).  Prints per scene and path the iterations per frame, the median over all frames
and over the first 30, the worst frame, the total, the frames converged and cut back,
the chord checks and the CPU seconds of the steps (summed over the ranks);
with --check-every K, every K-th frame (and the worst) is solved again from the run's own
start state to 1e-10 (the recommended path, inertial first iterate, cap 80, no cutback)
and the largest distance of the run's stop from it is printed relative to the wisp length
and to the tolerance (above 1: a stop not within the tolerance of the step's solution).
"""

import argparse
import json
import sys
from pathlib import Path

import petsc4py

petsc4py.init(sys.argv[:1])
from mpi4py import MPI  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from newton_history import named_variants, scene  # noqa: E402

from lc_petsc.studies.command_line import bad_input, integer_at_least, positive_number  # noqa: E402
from lc_petsc.studies.iteration_targets import (  # noqa: E402
    RECOMMENDED, REFERENCE, run_path, stop_distances, summarize, tolerance_config)

DEFAULT_PATHS = [
    f"recommended={RECOMMENDED}",
    f"trust+chord={RECOMMENDED},trust=1,stop=chord_estimate",
    f"trust+chord+ftl={RECOMMENDED},trust=1,stop=chord_estimate,guess=follow_the_leader",
    f"trust+chord+jolt={RECOMMENDED},trust=1,stop=chord_estimate,jolt=1",
]


def scene_config(name):
    """The base config of a scene name (``demo``: hairball10 with the demo's 300 wisps)."""
    return scene("hairball10", 300) if name == "demo" else scene(name)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["demo", "hairball10", "smash"])
    p.add_argument("--frames", type=integer_at_least(1), help="frames per scene (default: its config's)")
    p.add_argument("--tol", type=positive_number, default=1e-6)
    p.add_argument("--iterations", type=integer_at_least(1), default=30, help="the cap per step")
    p.add_argument("--max-substeps", type=integer_at_least(1), default=8)
    p.add_argument("--path", action="append", help="NAME=SPEC (repeatable)")
    p.add_argument("--check-every", type=integer_at_least(0), default=0,
                   help="check every K-th frame's stop against the step solved to 1e-10 (0: none)")
    p.add_argument("--out", default="out/iteration_targets.json")
    a = p.parse_args(argv)
    comm = MPI.COMM_WORLD
    log = print if comm.rank == 0 else (lambda *_: None)
    try:
        paths = named_variants(a.path or DEFAULT_PATHS)
        runs = []
        for s in a.scenes:
            base = scene_config(s)
            frames = a.frames or base.time.frames
            runs.append((s, base, [(n, tolerance_config(base, spec, a.tol, a.iterations, frames,
                                                        a.max_substeps)) for n, spec in paths]))
    except (ValueError, OSError) as e:          # ConfigError is a ValueError
        return bad_input(comm, "iteration_targets.py", e)
    out: dict = {"tol": a.tol, "cap": a.iterations, "scenes": {}}
    for s, base, configs in runs:
        out["scenes"][s] = res = {}
        for name, cfg in configs:
            frames = cfg.time.frames
            rows, states = run_path(cfg, comm)
            summary = summarize(rows)
            # every K-th frame and the worst, if solved in one step (a cut-back frame's
            # stop is a substep's)
            check = set(range(0, frames, a.check_every)) | {summary["worst_frame"]} if a.check_every else set()
            check = {f for f in check if rows[f]["substeps"] == 1}
            ref = tolerance_config(base, REFERENCE, a.tol, 80, frames, 1)
            dist = stop_distances(ref, comm, states, check) if check else {}
            res[name] = {"rows": rows, "summary": summary,
                         "distances": {str(f): d for f, d in dist.items()}}
            log(table_line(s, name, rows, summary, dist, a.tol))
    if comm.rank == 0:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(out))
    return 0


def table_line(scene_name, path, rows, s, dist, tol):
    """The printed block of one run."""
    lines = [f"{scene_name} / {path}: {s['frames']} frames, median {s['median']:g} (first 30: "
             f"{s['median_first30']:g}), worst {s['worst']} (frame {s['worst_frame']}), total {s['total']}, "
             f"converged {s['converged']}/{s['frames']}, cut back {s['cut_back']}, chord checks "
             f"{s['chord_checks']}, CPU {s['cpu_s']:.1f} s",
             "  iterations " + " ".join(str(r["iterations"]) + ("" if r["converged"] else "!") for r in rows)]
    if dist:
        worst = max(dist.values(), key=lambda d: d["distance"])
        lines.append(f"  stops checked {len(dist)}: largest distance {worst['distance']:.2e} wisp lengths = "
                     f"{worst['distance'] / tol:.3g} x tol; reference unconverged in "
                     f"{sum(not d['reference_converged'] for d in dist.values())}")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
