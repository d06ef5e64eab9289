"""Command lines of the study drivers (drivers/compare_solvers.py, drivers/tradeoff.py,
scripts/extremes.py): their own options with checked ranges, PETSc's options (one dash)
left for PETSc, and bad input reported as one line with exit status 2.

A double-dash option a driver does not know is an error: handed to PETSc it would be
ignored (PETSc options take one dash), and a typo such as ``--wisp 500`` would silently
run the default.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

#: exit status of a driver given bad input (as the main job's)
EXIT_BAD_INPUT = 2


def parse_args(parser: argparse.ArgumentParser, argv=None) -> argparse.Namespace:
    """The driver's options from ``argv``; the rest is left for PETSc, except unknown
    ``--`` options, which are an error (argparse's usage line and exit status 2).  Under
    mpiexec only rank 0 prints argparse's usage, errors and help; every rank exits."""
    from mpi4py import MPI
    if MPI.COMM_WORLD.rank != 0:
        parser._print_message = lambda message, file=None: None     # type: ignore[method-assign]
    args, extra = parser.parse_known_args(argv)
    unknown = [a for a in extra if a.startswith("--")]
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)} (see --help; PETSc options "
                     "take one dash)")
    return args


def integer_at_least(lo: int):
    """An argparse ``type``: an integer >= ``lo``."""
    def convert(text):
        value = int(text)
        if value < lo:
            raise argparse.ArgumentTypeError(f"must be an integer >= {lo}, got {value}")
        return value
    convert.__name__ = "integer"
    return convert


def positive_number(text) -> float:
    """An argparse ``type``: a finite number > 0."""
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


positive_number.__name__ = "number"


def output_file(text) -> str:
    """An argparse ``type``: the path of a file to write (``--json``, ``--plot``), whose
    folder exists, checked before a run rather than after it."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder: give a file name")
    if not path.resolve().parent.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: no such folder {path.parent}")
    return text


output_file.__name__ = "file"


def figure_file(text) -> str:
    """An argparse ``type``: :func:`output_file` whose suffix is a format matplotlib
    writes (png, pdf, svg, ...), checked before a run rather than at the end of it."""
    text = output_file(text)
    from matplotlib.backend_bases import FigureCanvasBase
    kinds = FigureCanvasBase.get_supported_filetypes()
    if Path(text).suffix.lstrip(".").lower() not in kinds:
        raise argparse.ArgumentTypeError(f"{text}: not a figure format matplotlib writes; end the name "
                                         f"in one of {', '.join('.' + k for k in sorted(kinds))}")
    return text


figure_file.__name__ = "figure"


def check_wisps_flag(cfg, path) -> None:
    """``--wisps`` sets ``scene.n_wisps``, which only a hairball scene has: a ValueError
    naming the config ``path`` otherwise (the flag was silently ignored)."""
    if cfg.scene.kind != "hairball":
        raise ValueError(f"--wisps sets scene.n_wisps, which only a hairball scene has; "
                         f"{path} is scene.kind = {cfg.scene.kind!r}: leave out --wisps")


def bad_input(comm, prog: str, error: Exception) -> int:
    """Report a bad input (a config, scene or option set the driver cannot use) once, by
    rank 0, as one line on stderr; returns :data:`EXIT_BAD_INPUT`."""
    if comm.rank == 0:
        print(f"{prog}: error: {error}", file=sys.stderr)
    return EXIT_BAD_INPUT
