"""Step cutback against a larger Newton cap (docs/newton.md, fourth round): per setting,
frames converged to the tolerance, Newton iterations per frame (every attempt, the
cost) and per backward-Euler solve kept, frames cut back, CPU s per frame.

  .venv/bin/python scripts/bench_cutback.py [--scenes hairball10 smash] [--frames 30]
      [--tol 1e-6] [--wisps 10] [--out out/cutback]
      [--setting NAME=CAP,SUBSTEPS[,DT[,NEWTON[,UPDATE[,FALLBACK[,STOP[,STAY]]]]]]]

Every setting: ``solver.filter = "exact_or_analytic"``, the edge retraction (or
UPDATE: ``time.newton_update``, e.g. ``corotational``, docs/newton.md sixth round), the
tolerance ``time.newton_increment_tol``; CAP is ``time.newton_iterations``, SUBSTEPS
``time.max_substeps`` (1: no cutback), DT the step (default the scene's; empty: the
scene's), NEWTON ``time.newton`` (``trust_region``: with ``solver.filter = "analytic"``
as its preconditioner, docs/newton.md fifth round), FALLBACK ``solver.exact_fallback``
(``shifted``: docs/newton.md seventh round), STOP ``time.newton_stop`` and STAY
``solver.exact_stay`` (1: on; docs/newton.md eighth round).  The scenes
are those of scripts/newton_history.py (demo10: the demo with strand contact).  Prints a markdown table (also written to
--out/cutback.md, rows in cutback.json).  Runs with the lc_petsc it imports, so the
no-cutback settings also run on a checkout without ``time.max_substeps`` (then
ignored) for a side-by-side with main.
"""

import argparse
import copy
import json
import statistics
import sys
import time
from pathlib import Path

import petsc4py

petsc4py.init(sys.argv[:1])
from mpi4py import MPI  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from newton_history import scene  # noqa: E402

from lc_petsc.simulator import build_simulator  # noqa: E402
from lc_petsc.studies.command_line import bad_input, integer_at_least, positive_number  # noqa: E402

DEFAULT_SETTINGS = ["cap 30, no cutback=30,1", "cap 6, cutback=6,8", "cap 10, cutback=10,8",
                    "cap 15, cutback=15,8", "dt 1/120, cap 30, no cutback=30,1,0.008333333333333333"]


SETTING_FORM = "NAME=CAP,SUBSTEPS[,DT[,NEWTON[,UPDATE[,FALLBACK[,STOP[,STAY]]]]]]"


def parse_setting(spec):
    """``--setting`` text -> (label, keyword arguments of :func:`setting_config`); a
    ValueError names a malformed one."""
    label, _, vals = spec.rpartition("=")
    parts = vals.split(",")
    try:
        if not 2 <= len(parts) <= 8:
            raise ValueError(f"{len(parts)} values")
        kw = dict(cap=int(parts[0]), substeps=int(parts[1]),
                  dt=float(parts[2]) if len(parts) >= 3 and parts[2] else None,
                  newton=parts[3] if len(parts) >= 4 and parts[3] else None,
                  update=parts[4] if len(parts) >= 5 and parts[4] else "edge_retraction",
                  fallback=parts[5] if len(parts) >= 6 and parts[5] else None,
                  stop=parts[6] if len(parts) >= 7 and parts[6] else None,
                  stay=len(parts) == 8 and parts[7] == "1")
    except ValueError as e:
        raise ValueError(f"--setting {spec!r}: use {SETTING_FORM} ({e})") from None
    return label, kw


def setting_config(base, cap, substeps, dt, frames, tol, newton=None, update="edge_retraction",
                   fallback=None, stop=None, stay=False):
    """The validated config of one setting."""
    cfg = copy.deepcopy(base)
    cfg.solver.filter = "exact_or_analytic"
    cfg.time.newton_update = update
    if fallback is not None:
        cfg.solver.exact_fallback = fallback
    cfg.time.newton_increment_tol = tol
    if stop is not None:
        cfg.time.newton_stop = stop
    if stay:
        cfg.solver.exact_stay = True
    cfg.time.newton_tol = None
    cfg.time.newton_iterations = cap
    cfg.time.max_substeps = substeps
    if dt is not None:
        cfg.time.dt = dt
    if newton is not None:
        cfg.time.newton = newton
        if newton != "filtered":
            cfg.solver.filter = "analytic"
    # the same simulated time at every dt
    cfg.time.frames = int(round(frames * base.time.dt / cfg.time.dt))
    return cfg.validate()


def run(base, cap, substeps, dt, frames, tol, comm, newton=None, update="edge_retraction",
        fallback=None, stop=None, stay=False):
    """One setting: the summary figures (dict)."""
    cfg = setting_config(base, cap, substeps, dt, frames, tol, newton, update, fallback, stop, stay)
    n = cfg.time.frames
    sim = build_simulator(cfg, comm)
    try:
        c0 = time.process_time()
        for _ in range(n):
            sim.step()
        cpu = comm.allreduce(time.process_time() - c0, op=MPI.MAX)
        s = sim.summary()
    finally:
        sim.close()
    its = s["newton_iterations"]
    subs = s.get("newton_substeps") or [1] * n
    per_solve = [i for row in s.get("newton_substep_iterations") or [[i] for i in its] for i in row]
    # a frame at a smaller dt: the iterations of the dt of the scene's frame
    group = n // frames
    its_frame = [sum(its[k:k + group]) for k in range(0, n, group)]
    conv = s["newton_converged"]
    return {"frames": frames, "converged": sum(all(conv[k:k + group]) for k in range(0, n, group)),
            "median_its": statistics.median(its_frame), "worst_its": max(its_frame),
            "median_solve": statistics.median(per_solve), "worst_solve": max(per_solve),
            "cutback_frames": sum(k > 1 for k in subs), "max_substeps": max(subs),
            "total_its": sum(its), "cpu_per_frame": cpu / frames,
            "worst_increment": max(v for v in s["newton_increment"] if v is not None)}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", default=["hairball10", "smash"])
    p.add_argument("--frames", type=integer_at_least(1), default=30)
    p.add_argument("--tol", type=positive_number, default=1e-6)
    p.add_argument("--wisps", type=integer_at_least(1), default=10, help="wisps of hairball10 / demo10 (default 10)")
    p.add_argument("--setting", action="append", help=f"{SETTING_FORM} (repeatable)")
    p.add_argument("--out", default="out/cutback")
    a = p.parse_args(argv)
    comm = MPI.COMM_WORLD
    try:                                        # every scene and setting checked before any runs
        settings = [parse_setting(spec) for spec in a.setting or DEFAULT_SETTINGS]
        bases = [(name, scene(name, a.wisps)) for name in a.scenes]
        for name, base in bases:
            for label, kw in settings:
                try:
                    setting_config(base, frames=a.frames, tol=a.tol, **kw)
                except ValueError as e:
                    raise type(e)(f"--setting {label} on {name}: {e}") from None
    except (ValueError, OSError) as e:          # ConfigError is a ValueError
        return bad_input(comm, "bench_cutback.py", e)
    rows = []
    for name, base in bases:
        for label, kw in settings:
            r = run(base, frames=a.frames, tol=a.tol, comm=comm, **kw)
            rows.append({"scene": Path(name).stem, "setting": label, **r})
            if comm.rank == 0:
                print(f"  {rows[-1]}", flush=True)
    if comm.rank == 0:
        head = ("| scene | setting | frames converged | Newton its / frame median | worst | its / solve median "
                "| worst | frames cut back | most substeps | total its | CPU s / frame | worst final increment |")
        lines = [head, "|" + "---|" * 12]
        for r in rows:
            lines.append(f"| {r['scene']} | {r['setting']} | {r['converged']}/{r['frames']} | {r['median_its']:g} "
                         f"| {r['worst_its']} | {r['median_solve']:g} | {r['worst_solve']} | {r['cutback_frames']} "
                         f"| {r['max_substeps']} | {r['total_its']} | {r['cpu_per_frame']:.3f} "
                         f"| {r['worst_increment']:.1e} |")
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "cutback.md").write_text("\n".join(lines) + "\n")
        (out / "cutback.json").write_text(json.dumps(rows, indent=1))
        print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
