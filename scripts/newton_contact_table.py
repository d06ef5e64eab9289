"""Per-frame Newton and contact figures of runs of drivers/simulate.py, side by side
(docs/newton.md "The tolerance default measured where contact is active"):

  .venv/bin/python scripts/newton_contact_table.py RUN_DIR [RUN_DIR ...]

For each run folder (its summary.json): per frame converged (y / n; ``capped``: a start/jolt
frame ended by ``time.start_iterations``, ``newton_capped``; ``-`` without a tolerance), Newton
iterations, substeps (1: no cutback), contact pairs at the frame's end and the closest pair
(``-`` without strand contact, or no segments near enough to measure); then the
totals, the frames converged, the crossings of the end-of-run check (between / within
wisps over the frame steps) and the keys the tolerance default resolved
(``solver_path_defaulted``).  A restart's summary lists its own frames only: they are
numbered from the checkpoint's frame on (frame k: the step from k to k + 1).
"""

import argparse
import json
import sys
from pathlib import Path


def rows(s):
    c = s.get("contact") or {}      # none without strand_collision
    n = len(s["newton_iterations"])
    pairs, closest = c.get("pairs_per_frame", [None] * n), c.get("min_distance_per_frame", [None] * n)
    capped = s.get("newton_capped") or [False] * n      # absent from summaries before 2026-12-07
    first = (s.get("restart") or {}).get("frame", 0)
    out = []
    for k in range(n):
        conv = s["newton_converged"][k]
        out.append((first + k, "-" if conv is None else "y" if conv else "capped" if capped[k] else "n",
                    s["newton_iterations"][k], s["newton_substeps"][k], pairs[k], closest[k]))
    return out


def _cell(value, fmt=""):
    return "-" if value is None else format(value, fmt)


def report(run: Path) -> str:
    s = json.loads((run / "summary.json").read_text())
    r = rows(s)
    lines = [f"## {run}  ({s['ranks']} rank(s), status {s.get('status')})",
             "| frame | converged | iterations | substeps | pairs | closest (cm) |", "|---|---|---|---|---|---|"]
    lines += [f"| {k} | {c} | {n} | {sub} | {_cell(p)} | {_cell(d, '.3g')} |" for k, c, n, sub, p, d in r]
    cr = s.get("crossings") or {}
    conv, capped = sum(x[1] == "y" for x in r), sum(x[1] == "capped" for x in r)
    lines.append(f"frames converged {conv}/{len(r)}" + (f" ({capped} capped)" if capped else "")
                 + f", iterations {sum(x[2] for x in r)}, frames cut back {sum(x[3] > 1 for x in r)}, "
                 f"crossings between wisps "
                 f"{cr.get('between_wisps')} within {cr.get('within_wisps')} over {cr.get('steps')} steps, "
                 f"defaulted {', '.join(s.get('solver_path_defaulted') or []) or '-'}")
    return "\n".join(lines)


def cli(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="output folders of drivers/simulate.py")
    a = ap.parse_args(argv)
    for run in a.runs:
        if not (run / "summary.json").is_file():
            ap.error(f"{run} has no summary.json: give the --out folder of a run of drivers/simulate.py")
        try:
            text = report(run)
        except (ValueError, KeyError) as e:     # json's errors are ValueErrors
            ap.error(f"{run / 'summary.json'} is not a readable summary of drivers/simulate.py "
                     f"({type(e).__name__}: {e})")
        print(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(cli())
