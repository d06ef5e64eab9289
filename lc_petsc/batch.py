"""The main job's command line (DESIGN section 3): one scene file in, frames + XDMF +
previews + summary out.

``mpiexec -n P python drivers/simulate.py CONFIG.toml [--frames N] [--out DIR]
[--restart CHECKPOINT|latest] [--force] [--quiet] [PETSc options ...]``;
``drivers/simulate.py`` only calls :func:`main` and :func:`exit_process`.

Here: the command line and the config are checked on every rank (each rank reads the
small TOML file; they all reach the same verdict).  Any problem is printed once, by
rank 0, as ``simulate.py: error: <file>: <key> = <value>: <what is allowed>``; every
rank exits with status 2; nothing is written.  Then PETSc is initialised with the
remaining command-line options (they override the config's solver options) and the run
itself is a :class:`lc_petsc.job.Job` (lock, build, validation, frame loop, outputs;
its module doc says what each step leaves behind when it fails).
"""

from __future__ import annotations

import argparse
import difflib
import os
import shlex
import sys
from pathlib import Path

from lc_petsc.errors import ConfigError, UsageError
from lc_petsc.options import option_pairs

from lc_petsc.job import (EXIT_OK, EXIT_PREEMPTED, EXIT_RUN_FAILED, EXIT_USAGE,  # noqa: F401
                          PROG, RESTART_FREE_KEYS, output_dir, say)


class _Parser(argparse.ArgumentParser):
    """argparse that raises instead of printing/exiting (so only rank 0 reports)."""

    def error(self, message):
        raise UsageError(message)


def make_parser():
    """The main job's argument parser (PETSc options are left over for PETSc)."""
    p = _Parser(
        prog=PROG, allow_abbrev=False, add_help=False,
        usage="mpiexec -n P python drivers/simulate.py CONFIG.toml [--frames N] [--out DIR] "
              "[--restart CHECKPOINT|latest] [--force] [--quiet] [PETSc options ...]",
        description="Run the scene CONFIG.toml and write frames.h5, frames.xdmf, previews and "
                    "summary.json to the output folder.",
        epilog="Every other option (single dash, e.g. -ksp_type cg -pc_type hypre -log_view) "
               "goes to PETSc and overrides the config's [solver] options.")
    p.add_argument("config", metavar="CONFIG.toml", help="scene file (see configs/)")
    p.add_argument("--frames", type=int, metavar="N", help="run N frames instead of time.frames")
    p.add_argument("--out", metavar="DIR", help="output folder (default: output.dir, "
                                                 "else out/<config name>)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--restart", metavar="CHECKPOINT|latest",
                   help="continue from a checkpoint file, or from the newest valid one in "
                        "<output folder>/checkpoints ('latest'); --frames / time.frames is the "
                        "total frame count")
    p.add_argument("--force", action="store_true",
                   help="with --restart: accept a config that differs from the checkpoint's, "
                        "and continue into a new frames.h5 when the run's cannot be appended "
                        "to (it is renamed aside, lost frames are NaN); without: start over in "
                        "a folder whose run did not finish, or replace a finished run of another "
                        "config")
    p.add_argument("-h", "--help", action="store_true", help="show this help and exit")
    return p


def _fail(comm, message, code=EXIT_USAGE):
    say(comm, f"{PROG}: error: {message}", sys.stderr)
    return code


def parse_command_line(argv):
    """(args, petsc_argv) from ``argv``; raises UsageError."""
    if "-h" in argv or "--help" in argv:
        return argparse.Namespace(help=True), []
    args, extra = make_parser().parse_known_args(argv)
    # `--` (end of our options) is no PETSc option: passed on, PETSc warned that an
    # option "-" was never used and summary.json recorded an empty option name
    extra = [t for t in extra if t != "--"]
    if args.help:
        return args, []
    if args.frames is not None and args.frames < 0:
        raise UsageError(f"--frames must be an integer >= 0, got {args.frames}")
    if args.out is not None and not args.out.strip():
        raise UsageError(f"--out {args.out!r}: give the output folder (a path), or leave --out "
                         "out to use output.dir / out/<config name>")
    # PETSc's options take one dash: `--bogus` was passed on and reported as the PETSc
    # option -bogus, never as a mistyped flag of this program
    flag = next((t for t in extra if t.startswith("--")), None)
    if flag is not None:
        parser = make_parser()
        ours = [o for a in parser._actions for o in a.option_strings if o.startswith("--")]
        close = difflib.get_close_matches(flag.split("=")[0], ours, n=1, cutoff=0.75)
        hint = f"did you mean {close[0]}? " if close else ""
        usage = parser.format_usage().replace("usage: ", "", 1).strip()
        raise UsageError(f"{flag} is not a flag of {PROG} ({hint}usage: {usage}); a PETSc option "
                         f"takes one dash: -{flag.lstrip('-')}")
    if extra and not extra[0].startswith("-"):
        hint = ""
        if str(args.config).startswith("-") or not str(args.config).endswith(".toml"):
            hint = " (give CONFIG.toml before the PETSc options)"
        raise UsageError(f"unexpected argument {extra[0]!r}{hint}")
    if any(t.endswith(".toml") for t in extra):
        raise UsageError(f"give CONFIG.toml before the PETSc options (got {args.config!r} "
                         f"as the config and {[t for t in extra if t.endswith('.toml')][0]!r} "
                         "among the PETSc options)")
    return args, extra


def main(argv=None, comm=None):
    """Run the main job on ``comm`` (default COMM_WORLD); returns the exit status (the
    same on every rank)."""
    from mpi4py import MPI
    comm = MPI.COMM_WORLD if comm is None else comm
    argv = sys.argv[1:] if argv is None else list(argv)

    # 1. command line and config: checked on every rank, reported once
    from lc_petsc.config import load_config
    from lc_petsc.errors import ConfigError
    try:
        args, petsc_argv = parse_command_line(argv)
        if args.help:
            if comm.rank == 0:
                make_parser().print_help()
            return EXIT_OK
        cfg = load_config(args.config)
        if args.frames is not None:
            cfg.time.frames = args.frames
            try:
                cfg.time.validate()
            except ConfigError as e:
                raise UsageError(f"--frames: {e}") from None
        try:
            cfg_text = Path(args.config).read_text()
        except (OSError, UnicodeDecodeError):
            cfg_text = ""
        petsc_argv = expand_options_files(petsc_argv)
        command_line = dict(_petsc_options(petsc_argv))
    except (UsageError, ConfigError) as e:
        return _fail(comm, str(e))

    # 2. PETSc with the command-line options, then the simulator (collective checks)
    import petsc4py
    if "petsc4py.PETSc" not in sys.modules:
        # (a second init after PETSc is imported re-registers PETSc's exit handler, which
        # then hangs at exit when it ran on some ranks only; options are set below instead)
        petsc4py.init([sys.argv[0]] + petsc_argv, comm=comm)
    from lc_petsc.job import Job
    from lc_petsc.solver_plan import command_line_options
    try:
        with command_line_options(command_line) as given:
            return Job(comm, args, cfg, cfg_text, given, config_warnings=cfg.key_warnings).run()
    except Exception:
        # a bug, not a user error (the job reports its own): show it, and do not leave
        # the other ranks waiting
        if comm.size > 1:
            import traceback
            traceback.print_exc()
            sys.stderr.flush()
            comm.Abort(1)
        raise


def _petsc_options(tokens):
    """['-a', '1', '-flag', '-b', 'x'] -> [('a', '1'), ('flag', ''), ('b', 'x')]."""
    try:
        return option_pairs(tokens, what="command line")
    except ValueError as e:
        raise UsageError(f"{e} (PETSc options start with '-')") from None




def check_options_file(key, path):
    """UsageError unless ``path`` is a readable regular file (PETSc would print its whole
    error stack and abort on it)."""
    if not path:
        raise UsageError(f"{key} needs a file name")
    if not os.path.isfile(path):
        raise UsageError(f"{key} {path}: no such file (a file of PETSc options is expected)")
    if not os.access(path, os.R_OK):
        raise UsageError(f"{key} {path}: the file is not readable")


def expand_options_files(tokens):
    """``tokens`` with each ``-options_file FILE`` replaced in place by the file's options,
    read as ``solver.options_file`` reads it (several options per line, ``#`` comments).
    PETSc 3.18's own reader takes one option per line: it refused the shipped
    configs/solvers/*.opts ("extra token") on one rank, and mpiexec hung with the other
    ranks waiting in PetscInitialize."""
    from lc_petsc.config import read_options_file
    out, i = [], 0
    while i < len(tokens):
        if tokens[i] != "-options_file":
            out.append(tokens[i])
            i += 1
            continue
        path = tokens[i + 1] if i + 1 < len(tokens) and not tokens[i + 1].startswith("-") else ""
        check_options_file("-options_file", path)
        try:
            text = read_options_file(path, where="-options_file ")
        except ConfigError as e:
            raise UsageError(str(e)) from None
        try:
            out += shlex.split(text)
        except ValueError as e:
            raise UsageError(f"-options_file {path}: cannot parse its options: {e}") from None
        i += 2
    return out


def exit_process(code):
    """End the process with ``code`` (drivers/simulate.py), ignoring SIGTERM, SIGUSR1 and
    SIGINT from now on.  When libhdf5 failed on an
    open file (:func:`lc_petsc.io.hdf5.unclosable`) the interpreter's normal exit would
    crash in libhdf5 closing it: MPI is finalised and the process ends without that."""
    import signal
    from lc_petsc.io import hdf5
    # the job is over (outputs written, lock removed, its handlers restored): a signal
    # while the process ends (PETSc's and MPI's finalize) made a finished run exit 143,
    # which a scheduler reads as killed
    for name in ("SIGTERM", "SIGUSR1", "SIGINT"):
        signal.signal(getattr(signal, name), signal.SIG_IGN)
    if hdf5.unclosable():
        sys.stdout.flush()
        sys.stderr.flush()
        from mpi4py import MPI
        if MPI.Is_initialized() and not MPI.Is_finalized():
            MPI.Finalize()
        os._exit(code)
    sys.exit(code)
