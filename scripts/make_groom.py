"""Write the example strands file configs/data/fringe.h5 (DESIGN section 3, "Strands
from a file") used by configs/from_file.toml.

A fringe of 24 curly wisps hanging from a patch 8 cm wide and 4.8 cm deep (4 rows of 6
roots, 1.6 cm apart both ways): lengths 40 to 101 vertices, coil radius 0.3 to 0.7 cm,
4 to 7 vertices per turn, left- and right-handed, each with its own tapering /radius
and the first 3 vertices /pinned.  The roots are far enough apart that no two wisps come
closer than 0.2 cm at rest, so the groom runs with strand contact (``ccd`` mode refuses a
rest pose whose wisps overlap; the first version of this file hung all 24 wisps from one
bar, 0.35 cm apart, their coils interleaved).  Deterministic
(seeded), so the committed file can be regenerated: bit for bit on the same CPU, to the
last ulp of NumPy's SIMD sin/cos (1e-15 cm) on another:

  .venv/bin/python scripts/make_groom.py [OUT.h5]
"""

import argparse
import sys
from pathlib import Path

import h5py
import numpy as np

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "configs" / "data" / "fringe.h5"


def wisp(n, coil_radius, per_turn, rise, handed, root):
    k = np.arange(n)
    stem = 3
    x = np.zeros((n, 3))
    x[:stem, 1] = -0.5 * k[:stem]
    th = handed * 2 * np.pi / per_turn * (k[stem:] - stem)
    x[stem:, 0] = coil_radius * (np.cos(th) - 1.0)
    x[stem:, 2] = coil_radius * np.sin(th)
    x[stem:, 1] = -0.5 * stem - rise * (k[stem:] - stem + 1)
    return x + root


def root(w, rng):
    """Wisp w's root: row w % 4, column w // 4 of the patch.  A coil of radius r spans
    [x - 2 r, x] and [z - r, z + r] about its root, so with r <= 0.7 the 1.6 cm spacing
    keeps neighbours at least 0.2 cm apart.  The normal draw is kept (unused) so the
    wisps' other random figures are those of the first version of the file."""
    rng.standard_normal()
    return np.array([-4.0 + 1.6 * (w // 4), 0.0, -2.4 + 1.6 * (w % 4)])


def main(out):
    rng = np.random.default_rng(2023)
    xs, radii, pins = [], [], []
    for w in range(24):
        n = int(rng.integers(40, 102))
        x = wisp(n, coil_radius=rng.uniform(0.3, 0.7), per_turn=int(rng.integers(4, 8)),
                 rise=rng.uniform(0.08, 0.2), handed=1 if w % 2 else -1,
                 root=root(w, rng))
        xs.append(x)
        radii.append(np.linspace(rng.uniform(0.06, 0.1), 0.03, n))
        p = np.zeros(n, bool)
        p[:3] = True
        pins.append(p)
    offsets = np.concatenate([[0], np.cumsum([len(x) for x in xs])]).astype(np.int64)
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(out, "w", track_order=False) as f:
        f.create_dataset("positions", data=np.concatenate(xs))
        f.create_dataset("wisp_offsets", data=offsets)
        f.create_dataset("radius", data=np.concatenate(radii))
        f.create_dataset("pinned", data=np.concatenate(pins))
        f.attrs["description"] = "lc_petsc example groom: a fringe of 24 curly wisps"
    print(f"wrote {out}: {len(xs)} wisps, {offsets[-1]} vertices")


def cli(argv=None):
    """The command line: an optional output path (``--help`` is help, not a file name)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", nargs="?", default=str(DEFAULT_OUT),
                    help=f"strands file to write (default {DEFAULT_OUT.relative_to(DEFAULT_OUT.parents[2])})")
    out = ap.parse_args(argv).out
    if Path(out).is_dir():
        ap.error(f"{out} is a folder: give the path of the .h5 file to write")
    try:
        main(out)
    except OSError as e:
        print(f"make_groom.py: error: {out}: cannot write it ({e})", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(cli())
