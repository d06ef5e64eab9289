"""CPU per frame of Newton settings side by side: each setting's simulator runs FRAMES
frames from rest in turn, ROUNDS rounds, the order reversed every other round (a loaded
machine's drift falls on all alike); per setting the median over rounds of its CPU per
frame and of its frame 0, and its ratio to the first setting per round (median, range).
One rank; the scenes and settings of scripts/fixed_count_errors.py (docs/newton.md,
"Twenty-second round").

  .venv/bin/python scripts/setting_cost.py [--scene hairball10|demo10|smash]
      [--frames 30] [--rounds 5] NAME=SPEC ...
"""

import argparse
import importlib.util
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


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="hairball10")
    p.add_argument("--frames", type=integer_at_least(1), default=30)
    p.add_argument("--rounds", type=integer_at_least(1), default=5)
    p.add_argument("variants", nargs="+", metavar="NAME=SPEC")
    a = p.parse_args(argv)
    fce = _errors_script()
    try:
        cfg, variants = fce.scene_variants(a.scene, a.variants)
    except ValueError as e:                     # ConfigError is a ValueError
        return bad_input(MPI.COMM_WORLD, "setting_cost.py", e)
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
