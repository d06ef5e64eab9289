r"""Cost of the USD export (lc_petsc.io.usd) of a run, with and without render hairs.

  .venv/bin/python scripts/bench_usd.py FRAMES.h5 [--hairs 100] [--repeats 3] [--out DIR]

FRAMES.h5: a run's frames file, e.g. a few frames of the 2,000-wisp hairball:
  mpiexec -n 2 .venv/bin/python drivers/simulate.py configs/hairball_2k.toml --frames 9 \\
      --out /tmp/h2k
Writes DIR/wisps.usdc and DIR/hairs.usdc (default DIR: a temporary folder, removed),
``--repeats`` times each, side by side, and prints the medians: total seconds, seconds
per frame, of which render-hair interpolation (RMFs and offsets, NumPy), file size, peak memory.
"""

import argparse
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

import h5py

from lc_petsc.studies.command_line import integer_at_least


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("frames")
    p.add_argument("--hairs", type=integer_at_least(0), default=100,
                   help="render hairs per wisp (default 100)")
    p.add_argument("--repeats", type=integer_at_least(1), default=3)
    p.add_argument("--out", help="folder for the USD files (default: a temporary one)")
    args = p.parse_args(argv)
    from lc_petsc.io.usd import write_usd

    try:
        with h5py.File(args.frames, "r") as f:
            n_frames, n_vertices = f["positions"].shape[:2]
            n_wisps = f["wisp_offsets"].shape[0] - 1
            if "dt" not in f.attrs:
                raise KeyError("no 'dt' attribute")
    except (OSError, KeyError, ValueError) as e:
        print(f"bench_usd.py: error: {args.frames}: not a readable frames.h5 of lc_petsc ({e})",
              file=sys.stderr)
        return 2
    print(f"{args.frames}: {n_frames} frames, {n_wisps:,} wisps, {n_vertices:,} vertices; "
          f"render hairs {args.hairs} per wisp = {args.hairs * n_wisps:,} hairs, "
          f"{args.hairs * n_vertices:,} points per frame", flush=True)
    tmp = None if args.out else tempfile.TemporaryDirectory()
    out = Path(args.out or tmp.name)
    out.mkdir(parents=True, exist_ok=True)
    rows = {"wisps only": [], f"+ {args.hairs * n_wisps:,} render hairs": []}
    info = {}
    for r in range(args.repeats):
        for (label, runs), hairs, name in zip(rows.items(), (0, args.hairs), ("wisps", "hairs")):
            t0 = time.perf_counter()
            i = write_usd(args.frames, out / f"{name}.usdc", render_hairs=hairs)
            runs.append((time.perf_counter() - t0, i["render_hair_seconds"]))
            info[label] = i
            print(f"  repeat {r + 1}/{args.repeats} {label}: {runs[-1][0]:.2f} s", flush=True)
    print()
    print("| export | frames | total s | s per frame | of which render-hair interpolation | file MB |")
    print("|---|---|---|---|---|---|")
    for label, runs in rows.items():
        tot = statistics.median(t for t, _ in runs)
        hair = statistics.median(h for _, h in runs)
        n = info[label]["frames"]
        print(f"| {label} | {n} | {tot:.2f} | {tot / n:.3f} | {hair / n:.3f} | "
              f"{info[label]['bytes'] / 1e6:.1f} |")
    print(f"\npeak memory of this process: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
