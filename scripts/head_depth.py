"""How deep the hair sinks into the head sphere, per frame of a frames.h5 (lc_petsc.head_check).

    .venv/bin/python scripts/head_depth.py out/hairball_demo/frames.h5 [--json FILE]

Per row after the first: the deepest free vertex and the deepest point of an edge inside
the sphere of physics.head_radius (cm, and over the head radius), the largest depth
over the strand's radius (beyond 1 the strand is entirely inside the head: it vanishes
into the scalp), the strands that deep, and for the step from the row before: the
deepest point of a free vertex's straight path relative to the moving sphere and the
paths that pass through the head between the two frames.  Exits 0 whatever the depths,
2 for a file that is not a readable frames.h5 of a scene with a head sphere.
"""

import argparse
import json
import sys

from lc_petsc.crossings import frames_layout, step_rows, valid_steps
from lc_petsc.head_check import file_head, step_depths, summarize
from lc_petsc.studies.command_line import output_file


def head_rows(path, progress=None):
    """(head radius, [(step k, :func:`step_depths` dict of rows k -> k + 1)]) of the
    frames.h5 at ``path``; ValueError when its scene has no head sphere.  ``progress(k,
    dict, head radius)`` is called per step."""
    from lc_petsc.io.frames_read import FramesReader
    with FramesReader(path) as f:
        off = frames_layout(f)
        head = file_head(f)
        if head is None:
            raise ValueError("the run's scene has no head sphere (no head_collision, not a hairball)")
        steps = valid_steps(f.valid)     # the chunk index first: a damaged /time entry crashed libhdf5
        times = f.times
        out = []
        for k, prev, cur in step_rows(f, steps):
            out.append((k, step_depths(head[0], prev, cur, times[k], times[k + 1], off, head[1], head[2])))
            if progress is not None:
                progress(*out[-1], head[0].radius)
    return head[0].radius, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("frames", help="frames.h5 of a run")
    ap.add_argument("--json", type=output_file, help="write the per-row figures to this file")
    a = ap.parse_args(argv)
    print("row  vertex depth cm  edge depth cm  /head radius  /strand radius  strands sunk  "
          "path depth cm  paths through")

    def show(k, r, radius):
        print(f"{k + 1:4d}  {r['vertex']:14.4g}  {r['edge']:13.4g}  {max(r['vertex'], r['edge']) / radius:12.3g}  "
              f"{r['ratio']:14.3g}  {r['sunk']:12d}  {r['path_depth']:13.4g}  {r['path_through']:13d}", flush=True)

    try:
        R, rows = head_rows(a.frames, progress=show)
    except (OSError, KeyError, ValueError, TypeError) as e:
        print(f"head_depth.py: error: {a.frames}: not a readable frames.h5 of lc_petsc with a head "
              f"sphere ({e})", file=sys.stderr)
        return 2
    s = summarize(rows)
    if s is None:
        print(f"{a.frames}: fewer than two frames, nothing to measure")
    else:
        print(f"{a.frames}: deepest free vertex {s['vertex_depth']:.4g} cm (row {s['vertex_row']}), deepest "
              f"edge point {s['edge_depth']:.4g} cm (row {s['edge_row']}), {s['ratio']:.3g} strand radii at most; "
              f"rows with a strand entirely inside the head: {s['rows_sunk']} ({s['rows_sunk_by_chords']} only along "
              f"edges between vertices no deeper than their radius); paths through the head "
              f"between frames: {s['paths_through']} in {s['steps_through']} steps (deepest path point "
              f"{s['path_depth']:.4g} cm)")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"frames": a.frames, "head_radius": R, "summary": s,
                       "rows": [dict(r, row=k + 1) for k, r in rows]}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
