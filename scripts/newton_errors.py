"""Distance of every Newton iterate to the frame's converged solution, and where the
largest one sits (wisp, vertex along the wisp, distance to the head), on the scenes of
scripts/newton_history.py (docs/newton.md, sixth round).  One rank.

  .venv/bin/python scripts/newton_errors.py [--scene hairball10] [--frames 10]
      [--iterations 40] [--variant SPEC] [--wisps 10] [--profile WISP] [--out out/newton_errors.json]

SPEC as in newton_history.py (e.g. filter=exact_or_analytic,update=corotational).  Prints
per frame the errors (relative to the wisp length) of the first iterate and iterations
1.., and the wisp:vertex of the largest; --profile WISP also writes that wisp's per-vertex
distances (cm) to the JSON.
"""

import argparse
import json
import sys
from pathlib import Path

import petsc4py

petsc4py.init(sys.argv[:1])
from mpi4py import MPI  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from newton_history import scene  # noqa: E402

from lc_petsc.studies.command_line import bad_input, integer_at_least  # noqa: E402
from lc_petsc.studies.newton import configure, error_history, parse_variant  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="hairball10")
    p.add_argument("--frames", type=integer_at_least(1), default=10)
    p.add_argument("--iterations", type=integer_at_least(1), default=40)
    p.add_argument("--variant", default="filter=exact_or_analytic,update=edge_retraction")
    p.add_argument("--wisps", type=integer_at_least(1), default=10)
    p.add_argument("--profile", type=integer_at_least(0), help="a wisp whose per-vertex distances are kept")
    p.add_argument("--out", default="out/newton_errors.json")
    a = p.parse_args(argv)
    try:
        base = scene(a.scene, a.wisps)
        try:
            cfg = configure(base, parse_variant(a.variant), a.iterations, a.frames)
        except ValueError as e:
            raise type(e)(f"--variant {a.variant}: {e}") from None
    except (ValueError, OSError) as e:          # ConfigError is a ValueError
        return bad_input(MPI.COMM_WORLD, "newton_errors.py", e)
    rows = error_history(cfg, MPI.COMM_WORLD, a.frames, a.iterations, a.profile)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(rows))
    for f in range(a.frames):
        fr = [r for r in rows if r["frame"] == f][:20]
        print(f"frame {f}: " + " ".join(f"{r['error']:.1e}" for r in fr))
        print("   at " + " ".join(f"w{r['wisp']}:{r['vertex']}" for r in fr))
    return 0


if __name__ == "__main__":
    sys.exit(main())
