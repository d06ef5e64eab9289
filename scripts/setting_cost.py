"""CPU per frame of Newton settings side by side: each setting's simulator runs FRAMES
frames from rest in turn, ROUNDS rounds, the order reversed every other round (a loaded
machine's drift falls on all alike); per setting the median over rounds of its CPU per
frame and of its frame 0, and its ratio to the first setting per round (median, range).
One rank; the scenes and settings of scripts/fixed_count_errors.py (docs/newton.md,
"Twenty-second round").  With ``--calls``, instead of timing: each setting's FRAMES
frames after two under cProfile, the Python and NumPy function calls per frame (a count
that does not depend on the machine's load) and the functions called most often per frame
beyond the first setting (docs/newton.md, "Twenty-fifth round").  With ``--turn-parts``:
the CPU of the root turn (``Integrator._last_turn``) per frame over FRAMES frames and its
share of the frames' CPU in the same run (a ratio that the machine's load moves far less
than separate runs' times: the turn costs 1 / (1 - share) a frame without it), then CPU per
call of the turn's parts at the turn of the last frame (the one setting given, with
``root_rotation=true``), ROUNDS rounds of 200 calls each, interleaved, medians.

  .venv/bin/python scripts/setting_cost.py [--scene hairball10|demo10|smash]
      [--frames 30] [--rounds 5] [--calls | --turn-parts] NAME=SPEC ...
"""

import argparse
import cProfile
import importlib.util
import pstats
import sys
import time
from pathlib import Path

import petsc4py

petsc4py.init(sys.argv[:1])
import numpy as np  # noqa: E402
from mpi4py import MPI  # noqa: E402

from lc_petsc.studies.command_line import bad_input, integer_at_least  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def _errors_script():
    spec = importlib.util.spec_from_file_location("fixed_count_errors", ROOT / "scripts" / "fixed_count_errors.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run_once(fce, cfg, s, frames):
    """(CPU seconds of frame 0, of all ``frames`` frames, Newton iterations) of one fresh run."""
    sim = fce.simulator(cfg, s, frames)
    c0 = time.process_time()
    sim.step()
    first = time.process_time() - c0
    for _ in range(frames - 1):
        sim.step()
    total = time.process_time() - c0
    its = sum(sim.integrator.newton_iterations)
    sim.close()
    return first, total, its


def call_counts(fce, cfg, s, frames):
    """(function calls per frame, {function: calls per frame}) of ``frames`` frames after
    two, under cProfile."""
    sim = fce.simulator(cfg, s, frames + 2)
    sim.step()
    sim.step()
    profile = cProfile.Profile(time.process_time)
    profile.enable()
    for _ in range(frames):
        sim.step()
    profile.disable()
    sim.close()
    stats = pstats.Stats(profile)
    per = {f"{Path(f).name}:{line}({name})" if line else name: v[1] / frames
           for (f, line, name), v in stats.stats.items()}     # type: ignore[attr-defined]
    return stats.total_calls / frames, per          # type: ignore[attr-defined]


def print_calls(fce, cfg, variants, frames, top=15):
    """:func:`call_counts` of each setting, and its most called functions beyond the first's."""
    counts = {label: call_counts(fce, cfg, s, frames) for label, s in variants.items()}
    first = next(iter(counts))
    for label, (total, per) in counts.items():
        print(f"{label}: {total:.1f} function calls per frame ({total - counts[first][0]:+.1f} on {first})")
        if label != first:
            extra = sorted(((n - counts[first][1].get(f, 0.0), f) for f, n in per.items()), reverse=True)
            print("   most extra calls per frame: " + ", ".join(f"{f} {n:.1f}" for n, f in extra[:top]))


def turn_parts(fce, cfg, s, frames, rounds):
    """{part: median CPU us per call} of the root turn at frame ``frames``'s turn, after
    the turn's CPU per frame and its share of the frames' CPU (printed)."""
    sim = fce.simulator(cfg, s, frames + 1)
    it, rt = sim.integrator, sim.integrator.root_turn
    kept, step, last_turn, turn_cpu = {}, rt.step, it._last_turn, [0.0]
    rt.step = lambda x, *args: kept.update(x=x.copy()) or step(x, *args)

    def timed(last, x):
        c0 = time.process_time()
        y = last_turn(last, x)
        turn_cpu[0] += time.process_time() - c0
        return y
    it._last_turn = timed
    c0 = time.process_time()
    for _ in range(frames):
        sim.step()
    total = time.process_time() - c0
    rt.step, it._last_turn = step, last_turn
    share = turn_cpu[0] / total
    print(f"the turn {1e6 * turn_cpu[0] / frames:.1f} us CPU per frame of {1e3 * total / frames:.2f} ms: "
          f"{100 * share:.1f}% of the frames, 1 / (1 - share) = {1 / (1 - share):.3f}")
    x, unit = kept["x"], it._mass_unit()
    outer, head, at_x = it._turn_terms(x)
    b, A, P = rt._model(x, outer, head, unit)
    theta = rt._pcg(A, P, b, rt.pivot >= 0)
    y = rt._turned(x, theta)
    parts = {"whole turn (Integrator._last_turn)": lambda: it._last_turn(True, x),
             "terms at x (Integrator._turn_terms)": lambda: it._turn_terms(x),
             "model (RootRotation._model)": lambda: rt._model(x, outer, head, unit),
             "conjugate gradients (turn_pcg)": lambda: rt._pcg(A, P, b, rt.pivot >= 0),
             "turn of the vertices (_turned)": lambda: rt._turned(x, theta),
             "guard: potentials at y": lambda: it._turn_potentials(y),
             "guard: share_change (with the above)": lambda: rt.share_change(
                 x, y, lambda _, z: it._turn_potentials(z) - at_x)}
    times = {k: [] for k in parts}
    for _ in range(rounds):
        for k, f in parts.items():
            c0 = time.process_time()
            for _ in range(200):
                f()
            times[k].append((time.process_time() - c0) / 200 * 1e6)
    sim.close()
    return {k: float(np.median(v)) for k, v in times.items()}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="hairball10")
    p.add_argument("--frames", type=integer_at_least(1), default=30)
    p.add_argument("--rounds", type=integer_at_least(1), default=5)
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--calls", action="store_true", help="count function calls per frame instead of timing")
    mode.add_argument("--turn-parts", action="store_true", help="CPU per call of the root turn's parts")
    p.add_argument("variants", nargs="+", metavar="NAME=SPEC")
    a = p.parse_args(argv)
    fce = _errors_script()
    try:
        cfg, variants = fce.scene_variants(a.scene, a.variants)
    except ValueError as e:                     # ConfigError is a ValueError
        return bad_input(MPI.COMM_WORLD, "setting_cost.py", e)
    if a.calls:
        print_calls(fce, cfg, variants, a.frames)
        return 0
    if a.turn_parts:
        if len(variants) != 1 or not next(iter(variants.values())).root_rotation:
            return bad_input(MPI.COMM_WORLD, "setting_cost.py",
                             ValueError("--turn-parts: give one setting with root_rotation=true"))
        for part, us in turn_parts(fce, cfg, next(iter(variants.values())), a.frames, a.rounds).items():
            print(f"{part:40s} {us:8.1f} us CPU per call")
        return 0
    for s in variants.values():                 # warm-up: compiled kernels, first allocations
        run_once(fce, cfg, s, 2)
    rows = {label: [] for label in variants}
    order = list(variants)
    for r in range(a.rounds):
        for label in (order if r % 2 == 0 else order[::-1]):
            rows[label].append(run_once(fce, cfg, variants[label], a.frames))
    first_label = order[0]
    for label in order:
        first, total, its = (np.array(c) for c in zip(*rows[label]))
        ratio = total / np.array([t for _, t, _ in rows[first_label]])
        print(f"{label}: {1e3 * np.median(total) / a.frames:.2f} ms per frame, frame 0 {1e3 * np.median(first):.1f} "
              f"ms, {int(its[0])} Newton its; / {first_label} {np.median(ratio):.2f} "
              f"({ratio.min():.2f}-{ratio.max():.2f}) per round")
    return 0


if __name__ == "__main__":
    sys.exit(main())
