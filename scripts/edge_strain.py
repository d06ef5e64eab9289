"""Edge strain per frame of frames.h5 files (lc_petsc.crossings.edge_strain; issue 13).

    .venv/bin/python scripts/edge_strain.py A/frames.h5 [B/frames.h5 ...] [--labels a b] [--plot FILE.png]

Per frame: the largest and smallest edge strain against the file's rest positions, the
median and 99th percentile, the edges beyond +-10 %, and the median wisp root-to-tip
distance over its rest value.  --plot draws the largest strain and the edges beyond
+10 % per frame of every file.  Exits 2 for a file that is not a readable frames.h5.
"""

import argparse
import sys

import numpy as np

from lc_petsc.crossings import edge_strain, frames_layout
from lc_petsc.studies.command_line import figure_file


def frame_rows(path):
    """Per row of ``path`` that holds a frame (rows lost in a recovery are left out): (row,
    max, min, median, p99 strain, edges > +10 %, < -10 %, median root-to-tip distance /
    rest)."""
    from lc_petsc.io.frames_read import FramesReader
    rows = []
    with FramesReader(path) as f:
        off, rest = frames_layout(f, with_rest=True)
        reach0 = np.linalg.norm(rest[off[1:] - 1] - rest[off[:-1]], axis=1)
        for k, x in f.rows(np.flatnonzero(f.valid)):
            s = edge_strain(x, rest, off)
            reach = np.linalg.norm(x[off[1:] - 1] - x[off[:-1]], axis=1) / reach0
            rows.append((int(k), s.max(), s.min(), np.median(s), np.percentile(s, 99), int((s > 0.1).sum()),
                         int((s < -0.1).sum()), float(np.median(reach))))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("frames", nargs="+", help="frames.h5 of runs")
    ap.add_argument("--labels", nargs="+", help="one label per file (default: the paths)")
    ap.add_argument("--plot", type=figure_file, help="write a figure of the largest strain per frame here")
    a = ap.parse_args(argv)
    labels = a.labels or a.frames
    if len(labels) != len(a.frames):
        print("edge_strain.py: error: give one label per file", file=sys.stderr)
        return 2
    runs = []
    for path, label in zip(a.frames, labels):
        try:
            rows = frame_rows(path)
        except (OSError, KeyError, ValueError) as e:
            print(f"edge_strain.py: error: {path}: not a readable frames.h5 of lc_petsc ({e})",
                  file=sys.stderr)
            return 2
        print(f"{label}: frame  max strain  min strain  median  p99  edges>+10%  edges<-10%  root-tip/rest")
        for r in rows:
            print(f"{label}: {r[0]:5d}  {r[1]:+10.4f}  {r[2]:+10.4f}  {r[3]:+.4f}  {r[4]:+.4f}  {r[5]:10d}  "
                  f"{r[6]:10d}  {r[7]:.3f}")
        runs.append(rows)
    if a.plot:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 3.6))
        for rows, label in zip(runs, labels):
            r = np.array(rows)
            ax0.semilogy(r[:, 0], np.maximum(r[:, 1], 1e-4), label=label)
            ax1.plot(r[:, 0], r[:, 5], label=label)
        ax0.set(xlabel="frame", ylabel="largest edge strain")
        ax1.set(xlabel="frame", ylabel="edges stretched > 10 %")
        ax0.legend()
        fig.tight_layout()
        fig.savefig(a.plot, dpi=110)
    return 0


if __name__ == "__main__":
    sys.exit(main())
