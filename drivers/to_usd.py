"""Convert a run's frames.h5 into USD BasisCurves for DCC tools (lc_petsc.io.usd).

  python drivers/to_usd.py FRAMES.h5 [--out FILE.usdc] [--render-hairs N] [--seed S]
                           [--spread F] [--stride K] [--quiet] [--verbose]

--out: default frames.usdc beside FRAMES.h5 (.usd, .usda or .usdc; a missing folder is
created).  --render-hairs N: N interpolated hairs per wisp in a second prim (default:
the run's output.render_hairs); --seed / --spread: their offsets (default: the run's
output.render_hair_seed / render_hair_spread).  --stride K: every K-th frame of the file
only (time codes stay the file's frame rows; the stage ends at the last row written).
A USD failure is one line (what failed, the file, the first of USD's reasons);
--verbose adds USD's own text (a line per C++ error).
Exit status 0 done, 2 bad arguments or input (nothing written).
"""

import argparse
import sys
import time
from pathlib import Path


def main(argv=None):
    p = argparse.ArgumentParser(prog="to_usd.py", description=__doc__.split("\n\n")[0])
    p.add_argument("frames", metavar="FRAMES.h5", help="frames.h5 of a run (drivers/simulate.py)")
    p.add_argument("--out", metavar="FILE", help="USD file to write (default: frames.usdc beside FRAMES.h5; a missing "
                   "folder is created)")
    p.add_argument("--render-hairs", type=int, metavar="N", help="render hairs per wisp (0: none)")
    p.add_argument("--seed", type=int, metavar="S", help="seed of the render hairs' offsets")
    p.add_argument("--spread", type=float, metavar="F", help="render hairs' clump radius / wisp radius")
    p.add_argument("--stride", type=int, default=1, metavar="K", help="write every K-th frame")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--verbose", action="store_true", help="on a USD failure, print USD's own text too")
    args = p.parse_args(argv)
    for name in ("render_hairs", "seed"):
        v = getattr(args, name)
        if v is not None and v < 0:
            p.error(f"--{name.replace('_', '-')} must be >= 0, got {v}")
    if args.stride < 1:
        p.error(f"--stride must be >= 1, got {args.stride}")

    from lc_petsc.io.usd import USD_NAME, usd_failure, write_usd
    try:
        from pxr import Tf
    except ImportError as e:
        print(f"to_usd.py: error: USD is not installed ({e}); run scripts/setup.sh (usd-core)",
              file=sys.stderr)
        return 2
    bar = None
    if not args.quiet and sys.stderr.isatty():
        from tqdm import tqdm
        bar = tqdm(unit="frame", desc="to_usd", file=sys.stderr)

    def progress(done, total):
        if bar is not None:
            bar.total = total
            bar.update(done - bar.n)

    t0 = time.perf_counter()
    try:
        info = write_usd(args.frames, args.out, render_hairs=args.render_hairs,
                         render_hair_seed=args.seed, render_hair_spread=args.spread,
                         stride=args.stride, progress=progress)
    except (OSError, ValueError) as e:
        print(f"to_usd.py: error: {e}", file=sys.stderr)
        return 2
    except Tf.ErrorException as e:
        # pxr's text is a line per C++ error with its source file: the first reason here
        out = args.out or Path(args.frames).with_name(USD_NAME)
        print(f"to_usd.py: error: USD could not write {out}: {usd_failure(e, 'to_usd.py --verbose')}; "
              f"nothing was written; run it again once the cause is fixed (space, the folder)", file=sys.stderr)
        if args.verbose:
            print(f"to_usd.py: USD's text:\n{str(e).strip()}", file=sys.stderr)
        return 2
    finally:
        if bar is not None:
            bar.close()
    hairs = f", {info['render_hairs']:,} render hairs" if info["render_hairs"] else ""
    print(f"to_usd.py: wrote {info['path']}: {info['frames']} frames of {info['wisps']:,} wisps"
          f"{hairs}, {info['bytes'] / 1e6:.1f} MB in {time.perf_counter() - t0:.2f} s "
          f"({info['time_codes_per_second']:.6g} time codes per second)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
