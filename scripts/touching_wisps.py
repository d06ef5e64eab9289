"""Write the six touching wisps of tests/contact/test_mpi_ccd.py (``six_wisps_ccd``: six
30-vertex 4C wisps in phase, roots 0.9 cm apart, 3 pinned vertices, radius 0.08 -> 0.05
cm, ccd strand contact, head shaking) as a strands file and a config file, so that the
scene runs through the job as a user runs it (docs/newton.md "The tolerance
default measured where contact is active"):

  .venv/bin/python scripts/touching_wisps.py OUT_DIR --frames 10 --tol 1e-4 --cap 30
  mpiexec -n 2 .venv/bin/python drivers/simulate.py OUT_DIR/touching_wisps.toml --out RUN

The config names the tolerance and the cap and no ``[solver]`` key, so the loader resolves
the tolerance default (``solver_path_defaulted`` in summary.json).  ``--set TABLE.KEY=VALUE``
(TOML values, repeatable) adds keys, e.g. ``--set time.max_substeps=1``.
"""

import argparse
import sys
import tomllib
from pathlib import Path

import h5py
import numpy as np

from lc_petsc.scene import geometry
from lc_petsc.studies.command_line import integer_at_least, positive_number

N_WISPS, N_VERTICES, N_PINNED, SPACING = 6, 30, 3, 0.9
#: the [time] keys the script writes from its flags
FLAG_KEYS = {"time.frames": "--frames", "time.newton_iterations": "--cap", "time.newton_increment_tol": "--tol"}

CONFIG = """\
# the six touching wisps of tests/contact/test_mpi_ccd.py, written by scripts/touching_wisps.py
[scene]
kind = "file"
path = "touching_wisps.h5"
n_pinned = {n_pinned}

[material]
youngs_modulus = 2.0e7

[physics]
terms = ["stretch", "bend", "twist", "gravity", "strand_collision"]
strand_contact_mode = "ccd"
head_motion = "shake"
head_amplitude = 0.3
head_period = 0.5
strand_thickness = 0.12
strand_stiffness = 1.0e4

[time]
frames = {frames}
newton_iterations = {cap}
newton_increment_tol = {tol!r}
{extra}
[output]
previews = false
xdmf = false
usd = false
contact_sheet = 0
"""


def write(out: Path, frames: int, tol: float, cap: int, extra: list[str]) -> Path:
    """The strands file and the config in ``out``; returns the config's path."""
    x = np.concatenate([geometry.wisp4c(N_VERTICES, root=(SPACING * w, 16.0, 0.0))
                        for w in range(N_WISPS)])
    rad = np.concatenate([geometry.tapered_radius(N_VERTICES, 0.08, 0.05)] * N_WISPS)
    pin = np.tile(np.arange(N_VERTICES) < N_PINNED, N_WISPS)
    tables: dict[str, list[str]] = {}
    for item in extra:
        key, _, value = item.partition("=")
        table, _, name = key.partition(".")
        if not value or not name:
            raise ValueError(f"--set wants TABLE.KEY=VALUE (e.g. time.max_substeps=1), got {item!r}")
        if table in ("scene", "material", "physics", "output"):
            raise ValueError(f"--set {key}: the script writes [{table}] itself; only [time] and other tables")
        if key in FLAG_KEYS:
            raise ValueError(f"--set {key}: the script writes it from {FLAG_KEYS[key]}; give that instead")
        tables.setdefault(table, []).append(f"{name} = {value}")
    time_keys = "".join(f"{line}\n" for line in tables.pop("time", []))
    other = "".join(f"\n[{t}]\n" + "".join(f"{line}\n" for line in lines) for t, lines in tables.items())
    text = CONFIG.format(n_pinned=N_PINNED, frames=frames, cap=cap, tol=tol, extra=time_keys) + other
    try:
        tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"--set {' '.join(extra)}: not TOML values or a key set twice ({e}); "
                         f"strings need quotes, e.g. solver.options='\"-ksp_rtol 1e-8\"'") from None
    out.mkdir(parents=True, exist_ok=True)
    with h5py.File(out / "touching_wisps.h5", "w") as f:
        f.create_dataset("positions", data=x)
        f.create_dataset("wisp_offsets", data=np.arange(N_WISPS + 1, dtype=np.int64) * N_VERTICES)
        f.create_dataset("radius", data=rad)
        f.create_dataset("pinned", data=pin)
    path = out / "touching_wisps.toml"
    path.write_text(text)
    return path


def cli(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", help="folder for touching_wisps.h5 and touching_wisps.toml")
    ap.add_argument("--frames", type=integer_at_least(1), default=10)
    ap.add_argument("--tol", type=positive_number, default=1e-4, help="time.newton_increment_tol")
    ap.add_argument("--cap", type=integer_at_least(1), default=30, help="time.newton_iterations")
    ap.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE")
    a = ap.parse_args(argv)
    try:
        print(write(Path(a.out), a.frames, a.tol, a.cap, a.set))
    except ValueError as e:
        ap.error(str(e))
    return 0


if __name__ == "__main__":
    sys.exit(cli())
