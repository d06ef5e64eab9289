r"""Strand contact modes side by side: crossings per frame step, minimum distance,
per-frame wall time and phases, CPU time (the frame's over all ranks, and the collision
phase's, the largest rank's: on a shared machine the figures of the work), Newton and CG
iterations (prints figures, not a test).

    mpiexec -n 2 .venv/bin/python scripts/bench_ccd.py configs/hairball_demo.toml --frames 6 \\
        --modes penalty+inertial ccd [ccd+barrier] [ccd+self] [--json out/bench_ccd.json]

(``+self``: physics.strand_self_contact on; ``+inertial`` / ``+follow_the_leader``: that
time.initial_guess instead of the config's, e.g. ``penalty+inertial`` for the penalty
mode as it ran before the shipped hairballs chose ccd with follow the leader.)  Crossings are counted between different
wisps and, as ``self crossings``, between segments of one wisp sharing no vertex.

Runs each mode in turn in the same process (back to back, so the machine's load hits
both alike) and ends with a table of medians.  Two versions side by side (say main's
and a branch's ``--json`` of the same command):

    .venv/bin/python scripts/bench_ccd.py --compare out/main.json out/branch.json \\
        --labels main branch [--plot docs/figures/bench_ccd_demo.png]

Another version's library under this script: ``PYTHONPATH=/path/to/checkout`` (its
``lc_petsc`` is imported first).
"""

import argparse
import json
import sys

import numpy as np
from mpi4py import MPI

from lc_petsc.config import load_config
from lc_petsc.crossings import count_crossings
from lc_petsc.simulator import build_simulator
from lc_petsc.studies.command_line import bad_input, figure_file, integer_at_least, output_file
from lc_petsc.timing import frame_timing


def mode_config(path, mode):
    """The validated config of ``path`` in ``mode``: a strand_contact_mode, then optionally
    ``+barrier`` (the potential) and ``+self`` (self-contact), e.g. ``ccd+barrier+self``;
    a ConfigError names what is wrong."""
    cfg = load_config(path)
    cfg.physics.strand_contact_mode, *extras = mode.split("+")
    cfg.physics.strand_self_contact = "self" in extras
    for guess in {"inertial", "follow_the_leader"} & set(extras):
        cfg.time.initial_guess = guess
    for potential in set(extras) - {"self", "inertial", "follow_the_leader"}:
        cfg.physics.strand_contact_potential = potential
    try:
        return cfg.validate()
    except ValueError as e:
        raise type(e)(f"--modes {mode}: {e}") from None


def run(path, mode, frames):
    """Runs ``frames`` frames of ``path`` in ``mode`` (:func:`mode_config`)."""
    comm = MPI.COMM_WORLD
    sim = build_simulator(mode_config(path, mode), comm=comm)
    off = sim.wisp_offsets()
    rows = []
    try:
        prev = sim.gather_positions()
        for f in range(frames):
            ft = frame_timing(sim)
            wall, phases = ft.wall, ft.phases
            cur = sim.gather_positions()
            it = sim.integrator
            if comm.rank == 0:
                r = count_crossings(prev, cur, off)
                n_self = count_crossings(prev, cur, off, self_contact=True)["crossings"] - r["crossings"]
                row = {"frame": f, "mode": mode, "wall_s": wall, "phases_s": phases,
                       "crossings": r["crossings"], "self_crossings": n_self,
                       "min_distance": it.contact_min_distance[-1],
                       "newton": it.newton_iterations[-1], "cpu_s": ft.cpu_total,
                       "cpu_collision_s": ft.cpu.get("collision", 0.0),
                       "cg": int(sum(sim.solver.iterations[-it.newton_iterations[-1]:])),
                       "pairs": it.contact_pairs[-1]}
                rows.append(row)
                print(f"{mode:8s} frame {f:3d}: {wall:6.2f} s (collision {phases.get('collision', 0):.2f}, "
                      f"solve {phases.get('solve', 0):.2f}; CPU {ft.cpu_total:.2f}, collision CPU "
                      f"{row['cpu_collision_s']:.2f}), crossings {r['crossings']:4d} (self {n_self}), "
                      f"min distance "
                      f"{row['min_distance']:.4g} cm, pairs {row['pairs']}, CG {row['cg']}", flush=True)
            prev = cur
        s = sim.summary()["contact"]
    finally:
        sim.close()
    return rows, s


def _median(rows, key):
    """The median of ``key`` over ``rows`` as text ('-' where runs did not record it)."""
    v = [x[key] for x in rows if key in x]
    return f"{np.median(v):.2f}" if v else "-"


def compare(paths, labels, plot=None):
    """Table (and with ``plot`` a figure) of several ``--json`` results side by side."""
    runs = []
    for path in paths:
        try:
            with open(path) as f:
                runs.append(json.load(f))
            if not isinstance(runs[-1], dict) or not {"config", "ranks", "rows"} <= runs[-1].keys():
                raise ValueError("no 'config', 'ranks' and 'rows'")
        except (OSError, ValueError) as e:          # JSONDecodeError is a ValueError
            raise ValueError(f"{path}: not a --json file of bench_ccd.py ({e})") from None
    labels = labels or paths
    print(f"{runs[0]['config']}, {runs[0]['ranks']} rank(s), medians per frame:")
    print("| version | mode | wall / frame (s) | collision (s) | collision share | CPU / frame, all ranks (s) | "
          "collision CPU (s) | crossings | self crossings | min distance (cm) | "
          "limiter candidates per call, largest |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for label, run in zip(labels, runs):
        for mode in dict.fromkeys(r["mode"] for r in run["rows"]):
            r = [x for x in run["rows"] if x["mode"] == mode]
            w = np.median([x["wall_s"] for x in r])
            c = np.median([x["phases_s"].get("collision", 0.0) for x in r])
            dm = [x["min_distance"] for x in r if x["min_distance"] is not None and np.isfinite(x["min_distance"])]
            cand = (run.get("limiter", {}).get(mode) or {}).get("limiter_candidates_per_frame") or []
            cs = [x["self_crossings"] for x in r if "self_crossings" in x]     # not in older runs
            print(f"| {label} | {mode} | {w:.2f} | {c:.2f} | {100 * c / w:.0f}% | {_median(r, 'cpu_s')} | "
                  f"{_median(r, 'cpu_collision_s')} | {sum(x['crossings'] for x in r)} | "
                  f"{sum(cs) if cs else '-'} | {min(dm) if dm else float('nan'):.4g} | {max(cand) if cand else '-'} |")
    if plot:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(9, 4))
        for label, run in zip(labels, runs):
            for mode in dict.fromkeys(r["mode"] for r in run["rows"]):
                r = [x for x in run["rows"] if x["mode"] == mode]
                f = [x["frame"] for x in r]
                line, = ax.plot(f, [x["wall_s"] for x in r], "o-", label=f"{label} {mode}: wall")
                ax.plot(f, [x["phases_s"].get("collision", 0.0) for x in r], "x--", color=line.get_color(),
                        label=f"{label} {mode}: collision")
        ax.set_xlabel("frame")
        ax.set_ylabel("seconds per frame")
        ax.set_title(f"{runs[0]['config']}, {runs[0]['ranks']} rank(s)")
        ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        fig.tight_layout()
        fig.savefig(plot, dpi=110)
        print(f"wrote {plot}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?")
    ap.add_argument("--frames", type=integer_at_least(1), default=6)
    ap.add_argument("--modes", nargs="+", default=["penalty", "ccd"])
    ap.add_argument("--json", type=output_file)
    ap.add_argument("--compare", nargs="+", metavar="JSON", help="print --json results side by side")
    ap.add_argument("--labels", nargs="+")
    ap.add_argument("--plot", type=figure_file, help="with --compare: a figure of wall and collision time per frame")
    a = ap.parse_args()
    comm = MPI.COMM_WORLD
    if a.compare:
        if a.labels and len(a.labels) != len(a.compare):
            ap.error(f"--labels: {len(a.labels)} labels for {len(a.compare)} --compare files")
        if comm.rank == 0:
            try:
                compare(a.compare, a.labels, a.plot)
            except ValueError as e:
                return bad_input(comm, "bench_ccd.py", e)
        return 0
    if not a.config:
        ap.error("a config (or --compare)")
    try:
        for mode in dict.fromkeys(a.modes):
            mode_config(a.config, mode)
    except (ValueError, OSError) as e:          # ConfigError is a ValueError
        return bad_input(comm, "bench_ccd.py", e)
    allrows, extra = [], {}
    for mode in a.modes:
        rows, s = run(a.config, mode, a.frames)
        allrows += rows
        extra[mode] = {k: s.get(k) for k in ("ccd_unresolved_pairs_per_frame", "frame_path_held_vertices_per_frame",
                                               "limited_vertices_per_frame", "limiter_rounds_per_frame",
                                               "limiter_candidates_per_frame")}
    if MPI.COMM_WORLD.rank:
        return 0
    print(f"\n{a.config}, {MPI.COMM_WORLD.size} rank(s), {a.frames} frames per mode and run (medians "
          f"over a mode's runs; crossings: total per run):")
    print("| mode | wall / frame (s) | collision (s) | collision share | CPU / frame, all ranks (s) | "
          "collision CPU (s) | crossings (total, max/step) | self crossings (total, max/step) | "
          "min distance (cm) | CG / frame |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for mode in dict.fromkeys(a.modes):      # a mode given twice (A B A B): one row, over its runs
        r = [x for x in allrows if x["mode"] == mode]
        runs = a.modes.count(mode)
        w = np.median([x["wall_s"] for x in r])
        c = np.median([x["phases_s"].get("collision", 0.0) for x in r])
        cr = [x["crossings"] for x in r]
        cs = [x["self_crossings"] for x in r]
        dm = [x["min_distance"] for x in r if x["min_distance"] is not None and np.isfinite(x["min_distance"])]
        print(f"| {mode} | {w:.2f} | {c:.2f} | {100 * c / w:.0f}% | {_median(r, 'cpu_s')} | "
              f"{_median(r, 'cpu_collision_s')} | {sum(cr) / runs:g}, {max(cr)} | {sum(cs) / runs:g}, {max(cs)} | "
              f"{min(dm) if dm else float('nan'):.4g} | {np.median([x['cg'] for x in r]):.0f} |")
    for mode in dict.fromkeys(a.modes):
        if extra[mode].get("limiter_candidates_per_frame"):
            e = extra[mode]
            print(f"{mode} limiter per frame: candidate pairs (largest call) {e['limiter_candidates_per_frame']}, "
                  f"vertices limited {e['limited_vertices_per_frame']}, rounds (most) "
                  f"{e['limiter_rounds_per_frame']}, held on the frame paths "
                  f"{e['frame_path_held_vertices_per_frame']}, unresolved pairs {e['ccd_unresolved_pairs_per_frame']}")
    modes = list(dict.fromkeys(a.modes))
    if len(modes) == 2:
        w = [np.median([x["wall_s"] for x in allrows if x["mode"] == m]) for m in modes]
        cpu = [np.median([x["cpu_s"] for x in allrows if x["mode"] == m]) for m in modes]
        print(f"per frame {modes[1]} / {modes[0]}: wall {w[1] / w[0]:.2f}, CPU {cpu[1] / cpu[0]:.2f}")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"config": a.config, "ranks": MPI.COMM_WORLD.size, "rows": allrows,
                       "limiter": extra}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
