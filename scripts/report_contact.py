"""Table and plot of strand-contact benchmark runs side by side.

  .venv/bin/python scripts/report_contact.py out/bench_contact_1r_100.json \
      out/bench_contact_2r_100.json --out out/bench_contact

Reads the ``--json`` files of scripts/bench_contact.py (one per rank count) and writes
``<out>.md`` (a markdown table, one column per run, and the benchmark's targets) and
``<out>.png`` (wall time and phases, CG iterations, contact pairs and minimum distance
per frame); the table is printed too.
"""

import argparse
import json
import sys
from pathlib import Path

from lc_petsc.studies.contact_report import plot_runs, summarize, summary_table


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="JSON files written by bench_contact.py --json")
    ap.add_argument("--out", default="out/bench_contact",
                    help="output path without extension (writes .md and .png)")
    args = ap.parse_args(argv)
    runs, summaries = [], []
    for path in args.runs:
        try:
            runs.append(json.loads(Path(path).read_text()))
        except (OSError, ValueError) as e:          # JSONDecodeError, UnicodeDecodeError are ValueErrors
            ap.exit(2, f"report_contact.py: error: cannot read {path}: {e}; give the files written by "
                       f"bench_contact.py --json\n")
        try:
            summaries.append(summarize(runs[-1]))
        except ValueError as e:
            ap.exit(2, f"report_contact.py: error: {path}: {e}\n")
    table = summary_table(summaries)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    md, png = out.parent / (out.name + ".md"), out.parent / (out.name + ".png")
    sources = ", ".join(f"`{p}`" for p in args.runs)
    md.write_text(f"Strand-contact benchmark ({sources})\n\n{table}")
    plot_runs(runs, png)
    print(table)
    print(f"wrote {md} and {png}")


if __name__ == "__main__":
    sys.exit(main())
