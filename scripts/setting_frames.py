"""Frame by frame, one run per Newton setting from rest: the Newton iterations per frame,
which frames ran to ``time.start_increment_tol`` (start or jolt) and how each ended
(converged, capped by ``time.start_iterations`` with ``time.max_substeps = 1``, missed),
and the largest edge strain over frames 1..FRAMES; with ``--watch``, the calls of named
functions in one frame and the CPU inside them, and with ``--profile`` a cProfile of that
frame.  One rank; the scenes and settings of scripts/fixed_count_errors.py (docs/newton.md,
"Twenty-third round", "Twenty-fourth round").

  .venv/bin/python scripts/setting_frames.py [--scene hairball10|demo10|smash] [--frames 30]
      [--frame K] [--watch MODULE.FUNCTION] ... [--profile N] NAME=SPEC ...

e.g. ``--frames 1 --watch lc_petsc.curvature.least_definite_shifts --watch
lc_petsc.curvature._negative_pivots --profile 25 start=start_increment_tol=1e-3+root_rotation=true``:
frame 0's shift searches and inertia passes, their CPU, and its 25 largest cumulative
entries (a CPU-clock profile; with ``--profile`` the frame's CPU includes the
profiler's).  A watched function is replaced in its module for the run (callers that
imported it by name before are not seen: watch it where they look it up).
"""

import argparse
import cProfile
import importlib
import io
import pstats
import sys
import time
from contextlib import ExitStack
from pathlib import Path

import petsc4py

petsc4py.init(sys.argv[:1])
import numpy as np  # noqa: E402
from mpi4py import MPI  # noqa: E402

from lc_petsc.crossings import edge_strain  # noqa: E402
from lc_petsc.studies.command_line import bad_input, integer_at_least  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import setting_cost  # noqa: E402


class Watch:
    """Counts the calls of ``MODULE.FUNCTION`` (or ``MODULE.CLASS.METHOD``) and the CPU inside them while ``on``
    (a recursive call counts once, its CPU once)."""

    def __init__(self, name):
        parts = name.split(".")
        for cut in range(len(parts) - 1, 0, -1):     # the longest prefix that is a module
            try:
                owner = importlib.import_module(".".join(parts[:cut]))
                break
            except ImportError:
                continue
        else:
            raise ValueError(f"--watch {name!r}: give MODULE.FUNCTION or MODULE.CLASS.METHOD")
        try:
            for part in parts[cut:-1]:
                owner = getattr(owner, part)
            self.original = getattr(owner, parts[-1])
        except AttributeError:
            raise ValueError(f"--watch {name!r}: no {parts[-1]!r} in {'.'.join(parts[:-1])!r}") from None
        self.module, self.name, self.attr = owner, name, parts[-1]
        self.calls, self.cpu, self.on, self._depth = 0, 0.0, False, 0

    def __enter__(self):
        original = self.original

        def counted(*args, **kwargs):
            if not self.on or self._depth:
                return original(*args, **kwargs)
            self._depth += 1
            c0 = time.process_time()
            try:
                return original(*args, **kwargs)
            finally:
                self.cpu += time.process_time() - c0
                self.calls += 1
                self._depth -= 1
        setattr(self.module, self.attr, counted)
        return self

    def __exit__(self, *exc):
        setattr(self.module, self.attr, self.original)


def run(fce, cfg, s, frames, frame, watches, profile):
    """One run: (iterations, start, jolt, converged, capped per frame, largest |strain| over
    frames 1..frames, CPU of frame ``frame``, its cProfile text or None)."""
    sim = fce.simulator(cfg, s, frames)
    it = sim.integrator
    rest, off = sim.scene.x_rest, sim.scene.offsets
    strain, cpu, text = 0.0, None, None
    try:
        for k in range(frames):
            prof = cProfile.Profile(time.process_time) if profile and k == frame else None
            for w in watches:
                w.on = k == frame
            c0 = time.process_time()
            if prof is not None:
                prof.enable()
            sim.step()
            if prof is not None:
                prof.disable()
            if k == frame:
                cpu = time.process_time() - c0
            strain = max(strain, float(np.abs(edge_strain(it.x, rest, off)).max()))
            if prof is not None:
                out = io.StringIO()
                pstats.Stats(prof, stream=out).sort_stats("cumulative").print_stats(profile)
                text = out.getvalue()
    finally:
        sim.close()
    return (list(it.newton_iterations), list(it.newton_start), list(it.newton_jolt), list(it.newton_converged),
            list(it.newton_capped), strain, cpu, text)


def _ended(converged, capped):
    return "converged" if converged else "capped" if capped else "MISSED"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="hairball10")
    p.add_argument("--frames", type=integer_at_least(1), default=30)
    p.add_argument("--frame", type=integer_at_least(0), default=0, help="the frame --watch and --profile look at")
    p.add_argument("--watch", action="append", default=[], metavar="MODULE.FUNCTION",
                   help="count its calls and CPU in --frame (repeat for several)")
    p.add_argument("--profile", type=integer_at_least(1), metavar="N", help="cProfile's N largest cumulative entries")
    p.add_argument("variants", nargs="+", metavar="NAME=SPEC")
    a = p.parse_args(argv)
    fce = setting_cost._errors_script()
    try:
        if a.frame >= a.frames:
            raise ValueError(f"--frame {a.frame} is not among the {a.frames} frames run (--frames)")
        cfg, variants = fce.scene_variants(a.scene, a.variants)
        watches = [Watch(name) for name in a.watch]
    except ValueError as e:                     # ConfigError is a ValueError
        return bad_input(MPI.COMM_WORLD, "setting_frames.py", e)
    for label, s in variants.items():
        with ExitStack() as stack:
            for w in watches:
                w.calls, w.cpu = 0, 0.0
                stack.enter_context(w)
            its, start, jolt, conv, capped, strain, cpu, text = run(fce, cfg, s, a.frames, a.frame, watches,
                                                                     a.profile)
        tol = [k for k in range(len(its)) if start[k] or jolt[k]]
        print(f"{label}: {sum(its)} Newton iterations in {len(its)} frames; largest |edge strain| over frames "
              f"1-{len(its)} {100 * strain:.3g}%")
        print("  iterations per frame: " + " ".join(map(str, its)))
        if tol:
            print("  start/jolt frames: " + ", ".join(f"{k} ({'start' if start[k] else 'jolt'}, {its[k]} its, "
                                                      f"{_ended(conv[k], capped[k])})" for k in tol))
        print(f"  frame {a.frame}: {its[a.frame]} iterations, CPU {1e3 * cpu:.1f} ms")
        for w in watches:
            print(f"    {w.name}: {w.calls} calls, CPU {1e3 * w.cpu:.1f} ms")
        if text:
            print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
