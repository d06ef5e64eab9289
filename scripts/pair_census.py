"""Census of strand-contact pairs per frame of a frames.h5 (lc_petsc.pair_census).

    .venv/bin/python scripts/pair_census.py out/hairball_demo/frames.h5 [--thickness D0]
        [--stiffness K] [--every N] [--json FILE]

Per frame: pairs of segments of different wisps closer than d0 (rest-exempt apart),
their d/d0 histogram, how many are held far inside (< 0.05 d0, < 0.25 d0), nearly
parallel, kept from the previous frame and for how long, the segments and wisps
involved.  d0 defaults to the run's strand_thickness, else twice the smallest vertex
radius (the simulator's default).  Exits 2 for a file that is not a readable frames.h5.
"""

import argparse
import json
import sys

from lc_petsc.pair_census import census_frames
from lc_petsc.studies.command_line import integer_at_least, output_file, positive_number


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("frames", help="frames.h5 of a run")
    ap.add_argument("--thickness", type=positive_number, help="d0 (cm); default the run's")
    ap.add_argument("--stiffness", type=positive_number, help="k (dyn/cm); default the run's strand_stiffness")
    ap.add_argument("--every", type=integer_at_least(1), default=1, help="every n-th frame (ages need 1)")
    ap.add_argument("--json", type=output_file, help="write the per-frame figures to this file")
    a = ap.parse_args(argv)

    def show(r):
        print(f"frame {r['frame']:3d}: {r['pairs']:6d} pairs (exempt {r['exempt']}), d/d0 hist "
              f"{r['hist']} (<0.05: {r['below_0.05']}, <0.25: {r['below_0.25']}), "
              f"median d/d0 {r['median_d_over_d0'] or 0:.3f}, parallel {r['parallel']}, "
              f"kept {r['kept_from_previous']}, age>=10 {r['age_ge_10']}, "
              f"segments {r['segments']}, wisps {r['wisps']}", flush=True)

    try:
        rows, d0, k = census_frames(a.frames, a.thickness, a.stiffness, a.every, progress=show)
    except (OSError, KeyError, ValueError) as e:
        print(f"pair_census.py: error: {a.frames}: not a readable frames.h5 of lc_petsc ({e})",
              file=sys.stderr)
        return 2
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"frames": a.frames, "d0": d0, "k": k, "rows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
