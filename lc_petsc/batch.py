"""The main job (DESIGN section 3): one scene file in, frames + XDMF + previews + summary out.

``mpiexec -n P python drivers/simulate.py CONFIG.toml [--frames N] [--out DIR] [--quiet]
[PETSc options ...]``; ``drivers/simulate.py`` only calls :func:`main`.

Order of work, and what a failure at each step leaves behind:

1. command line and config file are checked on every rank (each rank reads the small
   TOML file; they all reach the same verdict).  Any problem is printed once, by rank 0,
   as ``simulate.py: error: <file>: <key> = <value>: <what is allowed>``; every rank
   exits with status 2; nothing is written.
2. PETSc is initialised with the remaining command-line options, which override the
   config's solver options; the simulator is built (scene, partition, matrix, KSP).
   Problems found here (a bad strands file, a matrix type a solver refuses, a PETSc
   option PETSc rejects) are collective: reported once, exit status 2, nothing written.
3. Only then is the output folder created and ``frames.h5`` opened; frame 0 (the
   initial state) is written, then every ``output.every``-th frame.  A run that fails
   part-way (a diverged linear solve, a non-finite position) keeps the frames written so
   far, writes ``frames.xdmf`` and ``summary.json`` with ``"error"`` set, and exits 3.
4. Rank 0 renders the previews from ``frames.h5``, writes ``summary.json`` and prints
   the report.

Checkpoints and restart (:mod:`lc_petsc.io.checkpoint`): every ``output.checkpoint_every``
frames, and when SIGTERM or SIGUSR1 arrives (at any rank: a flag is allreduced at every
frame end, the current frame is finished, a checkpoint written, exit status 75).
``--restart FILE|latest`` loads a checkpoint onto the current partition (any rank
count), checks the config (differences are an error unless ``--force``), reopens
``frames.h5`` keeping its rows up to the checkpoint's frame and continues to
``time.frames`` (or ``--frames``) in total.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from lc_petsc.options import option_pairs

EXIT_OK, EXIT_USAGE, EXIT_RUN_FAILED = 0, 2, 3
EXIT_PREEMPTED = 75         # EX_TEMPFAIL: stopped by SIGTERM/SIGUSR1 after a checkpoint; restart
# config keys a restart may change: they touch neither the trajectory nor frames.h5's rows
RESTART_FREE_KEYS = {"time.frames", "output.dir", "output.xdmf", "output.previews",
                     "output.preview_frames", "output.contact_sheet", "output.view",
                     "output.checkpoint_every", "output.checkpoints_kept",
                     "output.usd", "output.render_hairs", "output.render_hair_seed",
                     "output.render_hair_spread"}
PROG = "simulate.py"


class UsageError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    """argparse that raises instead of printing/exiting (so only rank 0 reports)."""

    def error(self, message):
        raise UsageError(message)


def make_parser():
    p = _Parser(
        prog=PROG, allow_abbrev=False, add_help=False,
        usage="mpiexec -n P python drivers/simulate.py CONFIG.toml [--frames N] [--out DIR] "
              "[--restart CHECKPOINT|latest [--force]] [--quiet] [PETSc options ...]",
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
                   help="with --restart: accept a config that differs from the checkpoint's")
    p.add_argument("-h", "--help", action="store_true", help="show this help and exit")
    return p


def _say(comm, text, stream=None):
    if comm.rank == 0:
        print(text, file=stream or sys.stdout, flush=True)


def _fail(comm, message, code=EXIT_USAGE):
    _say(comm, f"{PROG}: error: {message}", sys.stderr)
    return code


def parse_command_line(argv):
    """(args, petsc_argv) from ``argv``; raises UsageError."""
    if "-h" in argv or "--help" in argv:
        return argparse.Namespace(help=True), []
    args, extra = make_parser().parse_known_args(argv)
    if args.help:
        return args, []
    if args.frames is not None and args.frames < 0:
        raise UsageError(f"--frames must be an integer >= 0, got {args.frames}")
    if args.force and args.restart is None:
        raise UsageError("--force only applies with --restart")
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


def output_dir(args, cfg):
    if args.out:
        return Path(args.out)
    if cfg.output.dir:
        return Path(cfg.output.dir)
    return Path("out") / Path(args.config).stem


OUR_FILES = ("frames.h5", "frames.xdmf", "summary.json", "contact_sheet.png")


def _prepare_output(comm, out, restart=False):
    """Create the output folder (rank 0) and remove outputs of an earlier run there
    (on a restart ``frames.h5`` and the checkpoints stay; a new run removes the old
    checkpoints too, since they belong to the frames.h5 it replaces)."""
    from lc_petsc.io.checkpoint import checkpoint_folder
    problem = None
    if comm.rank == 0:
        try:
            out.mkdir(parents=True, exist_ok=True)
            for name in OUR_FILES:
                if not (restart and name == "frames.h5"):
                    (out / name).unlink(missing_ok=True)
            ck = checkpoint_folder(out)
            if ck.is_dir():
                for p in ck.iterdir():
                    if p.name.endswith(".h5.tmp") or (not restart and p.name.startswith("checkpoint_")):
                        p.unlink()
            if (out / "previews").is_dir():
                for p in (out / "previews").glob("frame_*.png"):
                    p.unlink()
        except OSError as e:
            problem = f"output folder {str(out)!r}: {e.strerror or e}"
    problem = comm.bcast(problem)
    return problem


def petsc_options_used(sim, command_line):
    """Options in effect: code defaults < sub-solver defaults < config < command line."""
    from lc_petsc.solver import DEFAULTS
    used = dict(DEFAULTS)
    used.update(sim.solver.extra)
    used.update(sim.scope.layers)
    used.update(command_line)
    used["mat_type"] = sim.assembler.mat_type
    return dict(sorted(used.items()))


def _options_string(d):
    return " ".join(f"-{k} {v}".rstrip() for k, v in d.items())


def main(argv=None, comm=None):
    """Run the main job on ``comm`` (default COMM_WORLD); returns the exit status (the
    same on every rank)."""
    from mpi4py import MPI
    comm = MPI.COMM_WORLD if comm is None else comm
    argv = sys.argv[1:] if argv is None else list(argv)

    # 1. command line and config: checked on every rank, reported once
    from lc_petsc.config import ConfigError, load_config
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
            cfg_text = Path(args.config).read_text()
        except (OSError, UnicodeDecodeError):
            cfg_text = ""
        command_line = dict(_petsc_options(petsc_argv))
    except (UsageError, ConfigError) as e:
        return _fail(comm, str(e))

    # 2. PETSc with the command-line options, then the simulator (collective checks)
    import petsc4py
    if "petsc4py.PETSc" not in sys.modules:
        # (a second init after PETSc is imported re-registers PETSc's exit handler, which
        # then hangs at exit when it ran on some ranks only; options are set below instead)
        petsc4py.init([sys.argv[0]] + petsc_argv, comm=comm)
    from petsc4py import PETSc
    from lc_petsc.simulator import build_simulator
    from lc_petsc.solver import SolverError
    opts = PETSc.Options()
    already = opts.getAll()          # PETSC_OPTIONS, or an earlier init in this process
    added = []
    for k, v in command_line.items():    # needed when PETSc was initialised before (tests)
        if not opts.hasName(k):
            opts.setValue(k, v)
            added.append(k)      # removed again on return: several runs in one process
        elif (already.get(k) or "") != v:
            opts.setValue(k, v)
    try:
        given = {k: (v or "") for k, v in already.items()}
        given.update(command_line)
        return _run(comm, args, cfg, given, build_simulator, SolverError, PETSc, cfg_text)
    except Exception:
        # a bug, not a user error: show it, and do not leave the other ranks waiting
        if comm.size > 1:
            import traceback
            traceback.print_exc()
            sys.stderr.flush()
            comm.Abort(1)
        raise
    finally:
        for k in added:
            opts.delValue(k)


def _petsc_options(tokens):
    """['-a', '1', '-flag', '-b', 'x'] -> [('a', '1'), ('flag', ''), ('b', 'x')]."""
    try:
        return option_pairs(tokens, what="command line")
    except ValueError as e:
        raise UsageError(f"{e} (PETSc options start with '-')") from None


def _run(comm, args, cfg, command_line, build_simulator, SolverError, PETSc, cfg_text=""):
    from lc_petsc import __version__
    from lc_petsc.diagnostics import shape_measures, term_warnings
    from lc_petsc.io.frames import FramesWriter
    from lc_petsc.io.summary import format_report, write_summary
    from lc_petsc.io.xdmf import write_xdmf

    import h5py  # noqa: F401  (imported before the clocks start)
    t_setup = time.perf_counter()
    try:
        sim = build_simulator(cfg, comm=comm)
    except (ValueError, SolverError) as e:
        return _fail(comm, str(e))
    except PETSc.Error as e:
        return _fail(comm, f"PETSc rejected the solver set-up ({e}); see PETSc's message above")
    try:
        warnings = term_warnings(sim)
        for w in warnings:
            _say(comm, f"{PROG}: warning: {w}", sys.stderr)
        out = output_dir(args, cfg)
        frames, every = cfg.time.frames, cfg.output.every
        sc = sim.scene
        r0 = int(sim.ranges[comm.rank])
        config_dict = cfg.to_dict()
        restart = None
        if args.restart is not None:
            restart, problem = _load_restart(comm, args, cfg, sim, out, config_dict)
            if problem:
                return _fail(comm, problem)
        problem = _prepare_output(comm, out, restart=restart is not None)
        if problem:
            return _fail(comm, problem)
        setup_time = comm.allreduce(time.perf_counter() - t_setup, op=_mpi_max())
        ckpt = _Checkpointer(comm, sim, cfg, out, config_dict, cfg_text,
                             petsc_options_used(sim, command_line), __version__)
        attrs = {"config": config_dict, "config_file": str(Path(args.config).resolve()),
                 "terms": sim.terms_run(), "dt": cfg.time.dt, "every": every, "frames": frames,
                 "description": cfg.scene.description, "lc_petsc_version": __version__}
        h5_path = out / "frames.h5"
        error = None
        start = 0 if restart is None else restart["frame"]
        try:
            with sim.timers("io"):
                writer = FramesWriter(h5_path, comm, n_wisps=sim.n_wisps, n_vertices=sim.n_vertices,
                                      first_wisp=r0, first_vertex=sc.first_vertex, local_offsets=sc.offsets,
                                      rest_positions=sc.x_rest, pinned=sc.pinned, n_out=1 + frames // every,
                                      attrs=attrs,
                                      resume_rows=None if restart is None else start // every + 1)
                if restart is None:
                    writer.write_frame(0.0, sim.x)
        except ValueError as e:
            return _fail(comm, str(e))
        times = [0.0] if restart is None else list(writer.times_kept)
        if restart is not None:
            _say(comm, f"{PROG}: restarting from {restart['path']} at frame {start} (t = {restart['time']:.6g} s"
                       f", written on {restart['attrs']['ranks']} rank(s), now {comm.size})")
        bar = _progress(comm, args, frames - start, Path(args.config).stem)
        preempt = _Preemption()
        t_loop = time.perf_counter()
        try:
            for _ in range(frames - start):
                sim.step()
                it = sim.integrator
                if it.frame % every == 0:
                    with sim.timers("io"):
                        writer.write_frame(it.t, sim.x)
                    times.append(it.t)
                stop = preempt.agreed(comm)
                if stop or (cfg.output.checkpoint_every and it.frame % cfg.output.checkpoint_every == 0):
                    with sim.timers("io"):
                        writer.flush()          # the frames a checkpoint vouches for are on disk
                        ckpt.write(it)
                if stop:
                    error = "preempted"
                    break
                if bar is not None:
                    bar.set_postfix_str(f"Newton {it.newton_iterations[-1]}, "
                                        f"KSP {sim.solver.iterations[-1] if sim.solver.iterations else 0}",
                                        refresh=False)
                    bar.update(1)
        except (SolverError, FloatingPointError) as e:
            error = str(e)
        finally:
            preempt.restore()
            if bar is not None:
                bar.close()
            with sim.timers("io"):
                writer.close()
        preempted = preempt.signal_name if error == "preempted" else None
        if preempted:
            error = None
        loop_time = comm.allreduce(time.perf_counter() - t_loop, op=_mpi_max())
        summary = sim.summary()
        summary["step_time_s"] = summary["wall_time_s"]
        summary["wall_time_s"] = loop_time
        shape = shape_measures(comm, sim.x, sc.x_rest, sc.offsets)
        used = petsc_options_used(sim, command_line)
        summary.update({
            "config_file": str(Path(args.config).resolve()),
            "description": cfg.scene.description,
            "lc_petsc_version": __version__,
            "setup_time_s": setup_time,
            "time_per_frame_s": summary["wall_time_s"] / max(summary["frames"] - start, 1),
            "frames_this_run": summary["frames"] - start,
            "restart": None if restart is None else {
                "checkpoint": str(restart["path"]), "frame": start,
                "ranks_before": restart["attrs"]["ranks"], "skipped": restart["skipped"]},
            "checkpoints": ckpt.written,
            "preempted": preempted,
            "solver": summary["petsc_options"],
            "petsc_options": _options_string(used),
            "petsc_options_used": used,
            "petsc_options_command_line": dict(command_line),
            "warnings": warnings,
            "shape": shape,
            "error": error,
        })
        if error:
            summary["converged"] = False
        if comm.rank == 0:
            files = ["frames.h5"]
            t0 = time.perf_counter()
            if cfg.output.xdmf:
                write_xdmf(out / "frames.xdmf", h5_path, times, sim.n_vertices, sim.n_wisps,
                           name=Path(args.config).stem)
                files.append("frames.xdmf")
            t_xdmf = time.perf_counter() - t0
            t0 = time.perf_counter()
            if cfg.output.previews and writer.written:
                files += [os.path.relpath(p, out) for p in _previews(cfg, out, h5_path, writer, frames,
                                                                     Path(args.config).stem)]
            t_prev = time.perf_counter() - t0
            # USD export for DCC tools (frames.usdc), from the closed frames.h5
            from lc_petsc.io.usd import export_run
            usd_files, t_usd = export_run(cfg.output, h5_path, out)
            files += usd_files
            files.append("summary.json")
            summary["output"] = {"dir": str(out), "every": every, "frames_written": writer.written,
                                 "files": files, "xdmf_s": t_xdmf, "previews_s": t_prev, "usd_s": t_usd}
            write_summary(out / "summary.json", summary)
            print(format_report(summary), flush=True)
            if error:
                print(f"{PROG}: error: {error}", file=sys.stderr, flush=True)
            if preempted:
                last = ckpt.written[-1]["path"] if ckpt.written else "?"
                print(f"{PROG}: {preempted} received: stopped after frame {sim.integrator.frame}, "
                      f"checkpoint {last} written; continue with --restart latest "
                      f"(exit status {EXIT_PREEMPTED})", file=sys.stderr, flush=True)
        comm.Barrier()
        if preempted:
            return EXIT_PREEMPTED
        return EXIT_RUN_FAILED if error else EXIT_OK
    finally:
        sim.close()


def _load_restart(comm, args, cfg, sim, out, config_dict):
    """(checkpoint dict, None) or (None, problem) for ``--restart``; collective."""
    from lc_petsc.io.checkpoint import (CheckpointError, checkpoint_folder, config_differences,
                                        find_latest, load_checkpoint)
    skipped = []
    try:
        if args.restart == "latest":
            ck, skipped = find_latest(checkpoint_folder(out), comm, sim.scene, sim.n_wisps,
                                      sim.n_vertices, sim.head)
            for m in skipped:
                _say(comm, f"{PROG}: warning: skipping an invalid checkpoint: {m}", sys.stderr)
            if skipped:
                _say(comm, f"{PROG}: warning: falling back to {ck['path']}, the newest valid checkpoint",
                     sys.stderr)
        else:
            ck = load_checkpoint(args.restart, comm, sim.scene, sim.n_wisps, sim.n_vertices, sim.head)
    except CheckpointError as e:
        return None, str(e)
    ck["skipped"] = skipped
    diff = config_differences(ck["attrs"]["config"], config_dict, ignore=RESTART_FREE_KEYS)
    if diff and not args.force:
        return None, (f"{ck['path']}: the config differs from the checkpoint's in "
                      f"{', '.join(diff)}; restart with the same config or add --force")
    if diff:
        _say(comm, f"{PROG}: warning: --force: config differs from the checkpoint's in {', '.join(diff)}",
             sys.stderr)
    if ck["attrs"]["every"] != cfg.output.every:
        return None, (f"{ck['path']}: output.every = {cfg.output.every} but the run's frames.h5 was "
                      f"written with {ck['attrs']['every']}; it cannot be appended to")
    if cfg.time.frames <= ck["frame"]:
        return None, (f"{ck['path']}: the checkpoint is at frame {ck['frame']}, the run ends at frame "
                      f"{cfg.time.frames} (time.frames / --frames is the total): nothing to do")
    from mpi4py import MPI
    same_rest = np.array_equal(ck["rest"], sim.scene.x_rest) and np.array_equal(ck["pinned"], sim.scene.pinned)
    if not comm.allreduce(int(not same_rest), op=MPI.MAX) == 0:
        if not args.force:
            return None, (f"{ck['path']}: the checkpoint's rest positions or pinned vertices differ "
                          "from the scene's; restart with the same scene or add --force")
        _say(comm, f"{PROG}: warning: --force: rest state differs from the checkpoint's; the scene's is used",
             sys.stderr)
    it = sim.integrator
    it.x, it.v = np.array(ck["x"]), np.array(ck["v"])
    it.t, it.frame = ck["time"], ck["frame"]
    return ck, None


class _Checkpointer:
    """Writes checkpoints of the running job (see lc_petsc.io.checkpoint)."""

    def __init__(self, comm, sim, cfg, out, config_dict, cfg_text, petsc_options, version):
        self.comm, self.sim, self.cfg, self.out = comm, sim, cfg, out
        self.config_dict, self.cfg_text = config_dict, cfg_text
        self.petsc_options, self.version = petsc_options, version
        self.written, self.last_frame = [], None

    def write(self, it):
        from lc_petsc.io.checkpoint import write_checkpoint
        if self.last_frame == it.frame:
            return
        sim, cfg = self.sim, self.cfg
        path, secs, size = write_checkpoint(
            self.out, self.comm, frame=it.frame, t=it.t, x=it.x, v=it.v, scene=sim.scene,
            n_wisps=sim.n_wisps, n_vertices=sim.n_vertices, head=sim.head, dt=cfg.time.dt,
            every=cfg.output.every, config_dict=self.config_dict, config_toml=self.cfg_text,
            petsc_options=self.petsc_options, keep=cfg.output.checkpoints_kept, version=self.version)
        self.written.append({"frame": it.frame, "path": str(path), "seconds": secs, "bytes": size})
        self.last_frame = it.frame


class _Preemption:
    """SIGTERM / SIGUSR1 set a flag (main thread only); :meth:`agreed` allreduces it at
    a frame end, so a signal that reached some ranks only stops all of them together."""

    SIGNALS = ("SIGTERM", "SIGUSR1")

    def __init__(self):
        import signal
        import threading
        self.flag, self.signal_name, self.previous = 0, None, {}
        if threading.current_thread() is threading.main_thread():
            for name in self.SIGNALS:
                sig = getattr(signal, name)
                self.previous[sig] = signal.signal(sig, self._handler)

    def _handler(self, signum, frame):
        import signal
        self.flag = 1
        self.signal_name = signal.Signals(signum).name

    def agreed(self, comm):
        from mpi4py import MPI
        stop = comm.allreduce(self.flag, op=MPI.MAX)
        if stop and self.signal_name is None:
            self.signal_name = "SIGTERM/SIGUSR1 (on another rank)"
        if stop:
            names = [n for n in comm.allgather(self.signal_name) if n and "another" not in n]
            self.signal_name = names[0] if names else self.signal_name
        return bool(stop)

    def restore(self):
        import signal
        for sig, h in self.previous.items():
            signal.signal(sig, h)
        self.previous = {}


def _previews(cfg, out, h5_path, writer, frames, title):
    from lc_petsc.io.previews import render_previews
    from lc_petsc.scene.kinematics import HeadMotion
    every, n = cfg.output.every, writer.written
    rows = []
    for f in cfg.output.preview_frames:
        fa = frames + 1 + f if f < 0 else f
        rows.append(min(max(fa, 0) // every, n - 1))
    head = None
    if "head_collision" in cfg.physics.terms or cfg.scene.kind == "hairball":
        hm = HeadMotion(cfg.physics)
        head = lambda t: (hm.sphere_center(t), hm.radius)   # noqa: E731
    return render_previews(h5_path, out, rows, contact_panels=cfg.output.contact_sheet,
                           view=cfg.output.view, title=title, head=head, every=every)


def _progress(comm, args, frames, name):
    if comm.rank != 0 or args.quiet or not sys.stderr.isatty() or frames == 0:
        return None
    from tqdm import tqdm
    return tqdm(total=frames, unit="frame", desc=name, dynamic_ncols=True, file=sys.stderr)


def _mpi_max():
    from mpi4py import MPI
    return MPI.MAX
