"""Count edge-edge crossings between wisps in a frames.h5 (lc_petsc.crossings).

    .venv/bin/python scripts/count_crossings.py out/hairball_demo/frames.h5 [--self] [--json FILE]

A crossing is a pair of segments whose linear path between two consecutive frames
passes through each other (different wisps; with --self also non-adjacent segments of
one wisp).  Prints one line per frame step (its crossings, and the smallest distance between
two segments of different wisps at the step's later frame, exact) and a summary; exits 0
whatever the count, 2 for a file that is not a readable frames.h5.
"""

import argparse
import json
import sys

import numpy as np

from lc_petsc.crossings import count_frames
from lc_petsc.studies.command_line import output_file


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("frames", help="frames.h5 of a run")
    ap.add_argument("--self", action="store_true", help="count crossings of a wisp with itself too")
    ap.add_argument("--json", type=output_file, help="write the per-step figures to this file")
    a = ap.parse_args(argv)

    def show(r):
        d = "-" if r["min_distance"] is None else f"{r['min_distance']:.4g} cm"
        print(f"step {r['step']:4d} (frame {r['frames'][0]} -> {r['frames'][1]}): {r['crossings']:6d} crossings, "
              f"min distance {d}", flush=True)

    try:
        steps, d0 = count_frames(a.frames, self_contact=a.self, progress=show)
    except (OSError, KeyError, ValueError) as e:
        print(f"count_crossings.py: error: {a.frames}: not a readable frames.h5 of lc_petsc ({e})",
              file=sys.stderr)
        return 2
    c = np.array([r["crossings"] for r in steps], np.int64)
    if len(c):
        print(f"{a.frames}: {int(c.sum())} crossings over {len(c)} frame steps; per step median "
              f"{float(np.median(c)):g}, max {int(c.max())}; steps with crossings: {int((c > 0).sum())}")
    else:
        print(f"{a.frames}: fewer than two frames, nothing to count")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"frames": a.frames, "self_contact": a.self, "steps": steps,
                       "total": int(c.sum())}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
