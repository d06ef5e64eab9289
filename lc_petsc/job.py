"""One run of the main job (``drivers/simulate.py``, parsed by :mod:`lc_petsc.batch`):
the output folder and its lock, the frames writer, the checkpointer, preemption and
the summary, as the steps of :meth:`Job.run`.

What each step leaves behind when it fails:

1. **lock** (rank 0): the folder is created if needed and ``.lc_petsc.lock`` locked
   (:mod:`lc_petsc.io.lock`).  Held by another run: exit 2 naming it; a lock left by a
   killed run is reported and taken over.
2. **build** the simulator and **validate** the run: the scene (strands file), the
   restart checkpoint and the ``frames.h5`` it appends to, the output estimate against
   the free disk space.  Any problem: exit 2, reported once, and the folder is as it
   was (a folder this run created is removed again).  A signal (SIGTERM, SIGUSR1,
   SIGINT) stops the set-up at once (nothing to checkpoint yet): exit 75, the folder as
   it was (:class:`Preemption`).
3. **prepare** the folder (the previous run's outputs are removed only now; a
   ``frames.h5`` a restart cannot append to is renamed aside, never removed, with
   ``--force``: :mod:`lc_petsc.io.recovery`) and write frame 0 (a recovery: the rows up
   to the checkpoint's).
4. the **frame loop**: each frame is stepped, written, then every rank agrees on
   whether to stop (a signal) or to checkpoint.  Every failure on any rank that the
   simulator raises collectively (a diverged solve, a non-finite position, an element
   error on one rank, which :func:`lc_petsc.parallel.collectively` turns into an error
   on every rank) and every output error (a full disk, checked before each write; a
   permission error) ends the loop on every rank with exit status 3.
5. **finish**: ``frames.h5`` closed (the frames so far stay readable), ``frames.xdmf``,
   previews, ``summary.json`` (with ``error``) and the report; an output that cannot be
   written is reported (exit 3) and the others are still tried (a summary.json that
   cannot be written: the lock file is left saying so, :meth:`OutputLock.leave`, so the
   running summary on disk is not taken for a killed run's).  A signal (any rank)
   during the end-of-run check or exports stops them between two pieces, writes a
   checkpoint of the last frame and summary.json (``output.skipped``).  Exit 0, 3
   (failed), 75 (stopped by a signal after a checkpoint, or during the set-up).
"""

from __future__ import annotations

import json
import os
import re
import sys
import time
import traceback
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from lc_petsc.config import RESTART_FREE_KEYS, TOLERANCE_PATH, TOLERANCE_PATH_WITHOUT_STRAND_CONTACT, SimConfig
from lc_petsc.io import hdf5
from lc_petsc.io.summary import missed_frames, run_status
from lc_petsc.errors import CheckpointError, OutputError, SimulationError, SolverError
from lc_petsc.parallel import global_max, global_wisp_offsets, on_root
from lc_petsc.newton_stop import unconfirmed_note
from lc_petsc.options import diagnostic_option

EXIT_OK, EXIT_USAGE, EXIT_RUN_FAILED = 0, 2, 3
EXIT_PREEMPTED = 75         # EX_TEMPFAIL: stopped by a signal after a checkpoint; restart
# how the set-up ended on a rank; the job takes the largest over the ranks
SETUP_DONE, SETUP_REFUSED, SETUP_INTERRUPTED = 0, 1, 2
#: keys every row of frames.h5 and frames.usdc shares (its dt and every attributes, the
#: USD's timeCodesPerSecond): refused in a restart even with --force
RESTART_FIXED_KEYS = ("time.dt", "output.every")
#: a config's PETSc options: a new run may change them in a finished run's folder, as it
#: may change the command line's (:meth:`Job._check_finished_run`)
PETSC_OPTION_KEYS = {"solver.options", "solver.options_file"}
#: scene kinds read from a file, whose path a restart does not compare (the content is)
GROOM_FILE_KINDS = ("file", "usd")
PROG = "simulate.py"
#: frames.h5 is flushed at least this often (seconds; a checkpoint flushes it too)
FRAMES_FLUSH_SECONDS = 30.0
#: the frames a warning names before it says how many more
MISSED_FRAMES_SHOWN = 8
OUR_FILES = ("frames.h5", "frames.xdmf", "frames.usdc", "frames.tmp.usdc", "summary.json",
             "history.json", "contact_sheet.png", "contact_sheet.png.tmp")


class Refused(Exception):
    """The run cannot start (exit 2); the message says why, nothing was changed."""


class SetupInterrupted(BaseException):
    """A signal during the set-up, raised where the rank was (a BaseException, like
    KeyboardInterrupt, so that no ``except Exception`` on the way swallows it)."""


def say(comm, text, stream=None):
    """Print ``text`` on rank 0 only."""
    if comm.rank == 0:
        print(text, file=stream or sys.stdout, flush=True)


def warn(comm, text):
    """Print a warning on rank 0 only (stderr)."""
    say(comm, f"{PROG}: warning: {text}", sys.stderr)


def output_dir(args, cfg):
    """The output folder: ``--out``, else ``output.dir``, else ``out/<config name>``."""
    if args.out:
        return Path(args.out)
    if cfg.output.dir:
        return Path(cfg.output.dir)
    return Path("out") / Path(args.config).stem


def petsc_options_used(sim, command_line):
    """Options in effect: code defaults < sub-solver defaults < config < command line."""
    return sim.plan.options_used(command_line, sim.assembler.mat_type)


def _options_string(d):
    return " ".join(f"-{k} {v}".rstrip() for k, v in d.items())


def unfinished_run(out, ended=None):
    """Why the output folder ``out`` holds a run that did not finish and can be
    continued (its checkpoints, and a summary.json that says it was stopped by a signal
    or failed (a full disk), or that it was running (the one a run keeps up to date: it
    was killed, or it failed to write its final summary, which its lock file's record
    says: ``ended``, :attr:`OutputLock.ended`; a run still going holds the folder's
    lock), or none: killed), else None.  A new run there would remove them (serial,
    read-only)."""
    from lc_petsc.io.checkpoint import checkpoint_folder, list_checkpoints
    from lc_petsc.io.summary import RUNNING
    found = list_checkpoints(checkpoint_folder(out))
    if not found:
        return None
    newest = f"newest checkpoint {found[0].name}"
    try:
        summary = json.loads((Path(out) / "summary.json").read_text())
    except FileNotFoundError:
        return f"no summary.json: it was killed or is still being written; {newest}"
    except (OSError, ValueError):
        return f"summary.json unreadable; {newest}"
    if not isinstance(summary, dict):
        return f"summary.json is not a JSON object; {newest}"
    if summary.get("status") == RUNNING and ended:
        return (f"failed after frame {summary.get('frames')}: {ended} (its lock file says so; its "
                f"summary.json is the one kept while it ran, which says {RUNNING}); {newest}")
    if summary.get("status") == RUNNING:
        return (f"killed after frame {summary.get('frames')} (its summary.json, kept while it ran, says "
                f"{RUNNING}); {newest}")
    if summary.get("preempted"):
        return f"stopped by {summary['preempted']} after frame {summary.get('frames')}; {newest}"
    if summary.get("error"):      # a full disk: free space and continue, not start over
        return f"failed: {summary['error']}; {newest}"
    return None


def petsc_error_text(e):
    """A PETSc.Error in one line: its messages, the last (the most specific) first, then
    the code and the function that raised it.  str() of the error is PETSc's traceback,
    one "[rank] ..." line per call and message, which the refusal used to wrap whole."""
    lines = [re.sub(r"^\[\d+\]\s*", "", line).strip() for line in str(e).splitlines()]
    calls = [line.split("(")[0] for line in lines[1:] if re.match(r"^\w+\(\) at ", line)]
    said = [line for line in lines[1:] if line and not re.match(r"^\w+\(\) at ", line)]
    code = lines[0] if lines else f"error code {getattr(e, 'ierr', '?')}"
    where = f", in {calls[-1]}()" if calls else ""
    return f"{'; '.join(reversed(said)) or 'no message'} (PETSc {code}{where})"


def finished_summary(out):
    """The summary.json (a dict) of the run in the output folder ``out`` when it says the
    run finished (no signal, no error, not running: a killed run's), else None (serial,
    read-only)."""
    try:
        summary = json.loads((Path(out) / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    return summary if isinstance(summary, dict) and run_status(summary) == "finished" else None


def finished_frames(out):
    """The frame count (``frames``) of the finished run in ``out``
    (:func:`finished_summary`), else None (serial, read-only)."""
    frames = (finished_summary(out) or {}).get("frames")
    return frames if isinstance(frames, int) else None


def _frame_list(indices, start):
    """'3, 7, ... 2 more': the frames of the per-frame list ``indices`` (the list's entry
    0 is frame ``start``), the first MISSED_FRAMES_SHOWN of them."""
    shown = [str(start + i) for i in indices[:MISSED_FRAMES_SHOWN]]
    if len(indices) > MISSED_FRAMES_SHOWN:
        shown.append(f"... {len(indices) - MISSED_FRAMES_SHOWN} more")
    return ", ".join(shown)


def outcome_warnings(summary, start, time_config):
    """Warnings about what the run's frames are (``summary``: the simulator's, this run's
    frames from ``start``): frames where the ccd limiter left pairs unresolved, a length
    projection that left the tolerance, frames whose Newton missed it."""
    out = []
    unresolved = (summary.get("contact") or {}).get("ccd_unresolved_pairs_per_frame") or []
    hit = [i for i, n in enumerate(unresolved) if n]
    if hit:
        out.append(f"the ccd limiter could not resolve every pair in {len(hit)} frame(s) (first: "
                   f"{_frame_list(hit, start)}; {sum(unresolved)} over its calls, "
                   f"ccd_unresolved_pairs_per_frame in summary.json): wisps may pass through each "
                   f"other there (count them with scripts/count_crossings.py); a smaller time.dt "
                   f"helps (docs/contact.md, \"The head's turn per step\")")
    moves = [m for m in summary["length_projection_move"] if m is not None]
    tol = time_config.newton_increment_tol
    if tol is not None and moves and max(moves) > tol:
        out.append(f"time.length_projection moved the converged positions by up to {max(moves):.3g} "
                   f"wisp lengths, {max(moves) / tol:.0f}x time.newton_increment_tol = {tol:g}: the "
                   f"frames written are the projection's, not the Newton solution the tolerance "
                   f"certifies (length_projection_move in summary.json); set "
                   f"time.length_projection = false for frames within the tolerance")
    capped = [i for i, n in enumerate(summary.get("newton_extend_capped") or []) if n]
    if capped:
        out.append(f"the extended Newton count reached time.newton_extend_cap = {time_config.newton_extend_cap} "
                   f"with the increment still above time.newton_extend_above = "
                   f"{time_config.newton_extend_above:g} in {len(capped)} frame(s) ({_frame_list(capped, start)}; "
                   f"newton_extend_capped and newton_increment in summary.json): those frames are as far from "
                   f"their solution as the bound was meant to prevent; raise time.newton_extend_cap, or lower "
                   f"time.dt (with strand contact in ccd mode the bound measures the step before the limiter's "
                   f"cut, which can stay large: docs/newton.md \"Eighteenth round\")")
    missed = missed_frames(summary)        # not the start/jolt frames ended by their cap
    if missed:
        worst = max(summary["newton_increment"][i] or 0.0 for i in missed)
        # with time.start_increment_tol only the start/jolt frames have a tolerance (a fixed count elsewhere)
        cap = (f"time.start_iterations (now {time_config.start_iterations})"
               if time_config.start_increment_tol is not None
               else f"time.newton_iterations (now {time_config.newton_iterations})")
        unconfirmed, refused, saddles = (sum(summary.get(key, [0] * (max(missed) + 1))[i] for i in missed)
                                         for key in ("newton_unconfirmed", "newton_refused", "newton_saddle"))
        out.append(f"Newton missed the tolerance in {len(missed)} of {len(summary['newton_converged'])} "
                   f"frame(s) ({_frame_list(missed, start)}; largest final measure {worst:.3g}, see "
                   f"newton_converged and newton_increment in summary.json"
                   f"{unconfirmed_note(unconfirmed, refused, saddles)}); they were kept "
                   f"(time.unconverged = \"accept\"). Raise {cap} or time.max_substeps (now "
                   f"{time_config.max_substeps}), or watch those frames with -lc_newton_monitor "
                   f"(docs/newton.md)")
    return out


def crossing_warnings(check, cfg):
    """Warnings for the end-of-run crossing check ``check``
    (:func:`lc_petsc.crossings.check_run`): how many, where first, and the key that
    prevents them in this run's contact set-up; edges strained beyond STRAIN_WARN.  In
    ``ccd`` mode with ``output.every`` > 1 the limiter limits the simulated steps, which
    this check cannot see; the straight paths across several of them, which a viewer
    interpolating the frames written draws, need not be collision-free.  Crossings of
    pairs the contact exempts (closer than its thickness at rest: ``between_exempt`` /
    ``within_exempt``) are put down to the exemption, not to the limiter."""
    from lc_petsc.crossings import STRAIN_WARN
    out = []
    every, phys = cfg.output.every, cfg.physics
    contact = "strand_collision" in phys.terms
    ccd = contact and phys.strand_contact_mode == "ccd"
    apart = (f"; the frames written are output.every = {every} simulation frames apart, so a viewer's "
             f"straight path between them is not the simulated one (output.every = 1 checks the "
             f"simulated paths)") if every > 1 else ""
    if every > 1:       # in ccd mode: the cause is the interpolation, not the limiter
        limited = (f"the frames written are output.every = {every} steps apart and the straight paths "
                   f"across them are not the simulated ones, which the ccd limiter limits (this check "
                   f"cannot see those steps): a viewer or renderer interpolating between the frames "
                   f"(motion blur, USD time samples) shows these crossings; output.every = 1 writes "
                   f"and checks the simulated paths")
    else:
        limited = ("the ccd limiter should have prevented them (see any unresolved-pairs warning); "
                   "please report it with the config")
    if ccd:
        between = limited
    elif contact:
        between = ("physics.strand_contact_mode = \"ccd\" prevents them (penalty mode lets wisps pass "
                   "through each other)" + apart)
    else:
        between = ("model strand contact: add \"strand_collision\" to physics.terms with "
                   "physics.strand_contact_mode = \"ccd\"" + apart)
    within = limited if ccd and phys.strand_self_contact else (
        "model self-contact: physics.strand_self_contact = true with \"strand_collision\" in "
        "physics.terms and physics.strand_contact_mode = \"ccd\"" + apart)
    exempt = ("by pairs of segments closer than the contact thickness in the rest pose, which strand "
              "contact exempts (physics.strand_rest_overlap = \"exempt\" in ccd mode) and so lets pass "
              "through each other: untangle the groom or lower physics.strand_thickness below its closest "
              "rest pair (physics.strand_rest_overlap = \"error\" in ccd mode names it)")
    for kind, n, steps, first, fix, n_ex in (
            ("between wisps", check["between_wisps"], check["steps_between"], check["first_between"], between,
             check.get("between_exempt")),
            ("within a wisp", check["within_wisps"], check["steps_within"], check["first_within"], within,
             check.get("within_exempt"))):
        if n and n_ex:
            fix = f"all {exempt}" if n_ex == n else f"{n_ex} of them {exempt}; the other {n - n_ex}: {fix}"
        if n:
            out.append(f"{n} crossing(s) {kind} in {steps} of the {check['steps']} steps between the "
                       f"frames written (first: frame {first * every} -> {(first + 1) * every}; "
                       f"scripts/count_crossings.py lists them per step): strands pass through each "
                       f"other; {fix}")
    if check.get("rows_over_strain"):
        fix = ("raise time.newton_iterations or lower time.dt" if cfg.time.length_projection else
               "set time.length_projection = true (each frame projected onto the rest lengths), or "
               "raise time.newton_iterations or lower time.dt")
        start = check.get("initial_strain")
        if start is not None and start > STRAIN_WARN:
            # the run did not tear them: the initial state came so (a perturbation)
            fix = (f"the initial state (frame 0, scene.perturbation = \"{cfg.scene.perturbation}\") already has "
                   f"edges {100 * start:.1f}% off their rest length, and the first frames carry what is left of "
                   f"it; if it stays, {fix}")
        out.append(f"edges stretch or compress by up to {100 * check['largest_strain']:.1f}% of their rest "
                   f"length (frame {check['largest_strain_row'] * every}; beyond "
                   f"{100 * STRAIN_WARN:.0f}% in {check['rows_over_strain']} of the frames written; "
                   f"scripts/edge_strain.py lists them per frame): strands look torn or crushed; {fix}")
    return out + head_warnings(check.get("head"), cfg)


def head_warnings(head, cfg):
    """Warnings for the end-of-run check's ``head`` figures
    (:func:`lc_petsc.head_check.summarize`): strands entirely inside the head sphere in a
    frame written, and vertex paths through it between frames, with the knobs that keep
    hair out."""
    if not head or not (head["rows_sunk"] or head["paths_through"]):
        return []
    every, phys = cfg.output.every, cfg.physics
    if "head_collision" not in phys.terms:
        fix = "add \"head_collision\" to physics.terms (the head sphere is drawn, not modelled)"
    else:
        fix = ("the push-out (physics.head_push_out) is on, so this is what it leaves: vertex paths a "
               "lift of their end by 4 strand radii cannot keep out (slides of several cm a frame) and "
               "vertices the strand contact's frame end moves after it; to lessen it, "
               if phys.head_push_out else "set physics.head_push_out = true (vertices deeper than their "
               "radius put back on the sphere after each step), or ")
        fix += (f"raise time.newton_iterations or lower time.dt (the last Newton step of a frame can carry "
                f"hair into the head before the penalty acts), or raise physics.head_stiffness (now "
                f"{phys.head_stiffness:g} dyn/cm: a resting vertex sinks by its load over it); "
                f"physics.head_margin keeps hair that far outside the sphere drawn")
    out = []
    by_chords = head.get("rows_sunk_by_chords") or 0
    if by_chords:
        out.append(chord_warning(head, phys.head_radius))
    if head["rows_sunk"] > by_chords:
        more = f" ({head['rows_sunk'] - by_chords} with a vertex that deep)" if by_chords else ""
        out.append(f"hair sinks into the head{more}: strands lie entirely inside the head sphere (deeper than their "
                   f"radius) in {head['rows_sunk']} of the frames written (first: frame "
                   f"{head['first_sunk_row'] * every}; deepest free vertex {head['vertex_depth']:.3g} cm, edge "
                   f"point {head['edge_depth']:.3g} cm, {head['ratio']:.3g} strand radii; scripts/head_depth.py "
                   f"lists them per frame); {fix}")
    if head["paths_through"]:
        out.append(f"{head['paths_through']} hair vertex path(s) between frames written pass deeper into the head "
                   f"than their strand radius while neither frame shows them that deep, in {head['steps_through']} "
                   f"steps (first: frame {head['first_through'] * every} -> {(head['first_through'] + 1) * every}; "
                   f"up to {head['path_depth']:.3g} cm deep): a viewer interpolating the frames (motion blur, USD "
                   f"time samples) draws that hair under the scalp, the straight path cutting under the curved "
                   f"head or through the moving one; frames written closer together (time.dt, output.every) "
                   f"shorten those paths")
    return out


def chord_warning(head, radius):
    """The warning for frames in which strands lie inside the head sphere only along
    straight edges between vertices that rest on it (``head["rows_sunk_by_chords"]``): the
    chord of an edge of length L between two points of a sphere of ``radius`` R dips
    R - sqrt(R^2 - L^2 / 4) (about L^2 / 8R) under it, deeper than a thin strand's radius r
    unless L < 2 sqrt(2 R r - r^2); only finer edges change that."""
    from math import sqrt
    L, r = head["chord_length"], head["chord_radius"]
    sag = radius - sqrt(max(radius ** 2 - 0.25 * L ** 2, 0.0))
    fit = 2.0 * sqrt(max(2.0 * radius * r - r * r, 0.0))
    return (f"strands lie inside the head sphere along straight edges between vertices resting on it, in "
            f"{head['rows_sunk_by_chords']} of the frames written (no vertex deeper than its strand radius "
            f"there; deepest edge point {head['edge_depth']:.3g} cm, {head['ratio']:.3g} strand radii; "
            f"scripts/head_depth.py lists them per frame): an edge of {L:.3g} cm between two points of the "
            f"{radius:g} cm head sphere dips {sag:.3g} cm under it, {sag / r:.3g} times the strand radius "
            f"{r:.3g} cm, and the head contact holds vertices, not the edges between them; only edges shorter "
            f"than {fit:.3g} cm keep such a strand out along its length (a groom resampled finer, or "
            f"scene.n_vertices with shorter segments); Newton iterations, dt and physics.head_stiffness "
            f"cannot change it")


def output_estimate(cfg, n_wisps, n_vertices, rows_kept=0):
    """Bytes the run will add to its output folder, by file ({name: bytes})."""
    from lc_petsc.io.checkpoint import checkpoint_bytes
    from lc_petsc.io.frames import frame_bytes, static_bytes
    rows = 1 + cfg.time.frames // cfg.output.every
    parts = {"frames.h5": max(rows - rows_kept, 0) * frame_bytes(n_vertices)
             + (static_bytes(n_wisps, n_vertices) if rows_kept == 0 else 0)}
    # a new checkpoint is complete before the oldest is removed
    n_ck = cfg.output.checkpoints_kept + 1 if cfg.output.checkpoint_every else 1
    parts["checkpoints"] = n_ck * checkpoint_bytes(n_wisps, n_vertices)
    if cfg.output.xdmf:
        parts["frames.xdmf"] = 1000 * rows
    if cfg.output.usd:    # float32 points per row (measured 15 B per vertex), render hairs too
        parts["frames.usdc"] = 16 * n_vertices * rows * (1 + cfg.output.render_hairs)
    if cfg.output.previews:
        parts["previews"] = 300_000 * (len(cfg.output.preview_frames) + (cfg.output.contact_sheet > 0))
    parts["summary.json"] = 64 * 1024 + 400 * cfg.time.frames
    return parts


class Job:
    """The main job on ``comm`` for the parsed command line ``args`` and config ``cfg``.

    ``command_line``: the PETSc options given (command line and PETSC_OPTIONS);
    ``config_warnings``: warnings found while reading the config (keys without effect).
    """

    def __init__(self, comm, args, cfg, cfg_text, command_line, config_warnings=()):
        self.comm, self.args, self.cfg, self.cfg_text = comm, args, cfg, cfg_text
        self.command_line = dict(command_line)
        self.out = output_dir(args, cfg)
        self.name = Path(args.config).stem
        self.config_warnings = list(config_warnings)
        self.warnings = []
        self.lock = None
        self.lock_taken = None      # rank 0's lock, on every rank (OutputLock.taken)
        self.sim = None
        self.writer = None
        self.flushed = 0.0               # when frames.h5 was last flushed (perf_counter)
        self.restart = None
        self.outputs_only = False   # a restart at the last frame: the end-of-run outputs only
        self.recovery = None        # the RecoveryPlan of a frames.h5 that cannot be appended to
        self.aside = None           # where that frames.h5 was renamed to
        self.recovery_report = None     # summary.json's frames_recovery
        self.earlier_summaries = []     # a restart's: the earlier runs' summaries set aside
        self.times = []
        self.error = None
        self.preemption = None
        self.skipped_outputs = []   # the end-of-run check and outputs a signal skipped
        self.stop = None            # the StopNotice of the end-of-run work
        self.stopped_in_loop = False    # a signal stopped the frame loop (or its last frame)
        self.frames_lost = False        # frames.h5 gone after the frame loop (folder removed)
        self.progress_seconds = []      # each _record_progress's (rank 0's clock)
        self.progress_frame = None      # the last frame in the summary _record_progress wrote
        self.ended = None           # rank 0: why the final summary.json is not on disk (the lock keeps it)

    # ------------------------------------------------------------------ the steps
    def run(self):
        """Run the job's steps (module doc); returns the exit status, the same on every rank."""
        self.preemption = Preemption(self.comm)
        try:
            status = self._setup()
            if status is not None:
                return status
            try:
                self.checkpointer = Checkpointer(self)
                self._loop()
                return self._finish()
            finally:
                self.sim.close()
                self._unlock()
        finally:
            self.preemption.restore()

    def _setup(self):
        """Steps 1 and 2.  None when the run goes on, else the exit status, the folder as
        it was: 2 refused, 75 stopped by a signal (which stops the build at once)."""
        from lc_petsc.simulator import build_simulator
        from lc_petsc.solver_check import check_solver
        from petsc4py import PETSc
        comm, outcome, t_setup = self.comm, SETUP_DONE, time.perf_counter()
        refusal = None
        try:
            self._lock()
            with self.preemption.setup():
                try:
                    self.sim = build_simulator(self.cfg, comm=comm, check_start=self.args.restart is None)
                    check_solver(self.sim, self.command_line)
                except (ValueError, SolverError) as e:
                    raise Refused(str(e)) from None
                except PETSc.Error as e:
                    raise Refused(f"PETSc rejected the solver set-up: {petsc_error_text(e)}") from None
                self._validate()
        except Refused as e:
            say(comm, f"{PROG}: error: {e}", sys.stderr)
            outcome, refusal = SETUP_REFUSED, str(e)
        except SetupInterrupted:
            outcome = SETUP_INTERRUPTED
        if outcome == SETUP_INTERRUPTED or self.preemption.flag:
            self._drop_lock()       # now: mpiexec kills the ranks a second after a SIGTERM
        ends = self.preemption.end_setup(outcome, built=self.sim is not None, refusal=refusal)
        if ends is None:
            if outcome == SETUP_REFUSED:
                self._abort_refused(refusal)    # does not return
            self._abort_setup()         # does not return
        verdict = max(e[0] for e in ends)
        if verdict == SETUP_REFUSED:
            # a refusal of some ranks only (an element error in rank 1's wisps) was
            # printed by no one: rank 0 prints the first refused rank's
            first = self.preemption.refusals[0] if self.preemption.refusals else None
            if outcome != SETUP_REFUSED and first is not None:
                say(comm, f"{PROG}: error: {first}", sys.stderr)
        if verdict == SETUP_DONE:
            self.setup_time = global_max(comm, time.perf_counter() - t_setup)
            return None
        if verdict == SETUP_INTERRUPTED:
            got = [(r, e[1]) for r, e in enumerate(ends) if e[0] == SETUP_INTERRUPTED]
            where = "" if len(got) == comm.size else f" on rank {', '.join(str(r) for r, _ in got)}"
            say(comm, f"{PROG}: {_signal_name(got[0][1])} received{where} during the set-up, before "
                      f"the first frame: stopped, nothing was written (the output folder is as it "
                      f"was); run the same command again (exit status {EXIT_PREEMPTED})", sys.stderr)
        if all(e[2] for e in ends):     # closing is collective
            self.sim.close()
        self._unlock(refused=True)
        return EXIT_USAGE if verdict == SETUP_REFUSED else EXIT_PREEMPTED

    def _drop_lock(self):
        """Remove the lock and a folder this run created, from any rank (rank 0 may be
        the one waiting for this rank in a collective call, until it is killed)."""
        from lc_petsc.io.lock import remove_for_holder
        if self.lock is not None:
            self._unlock(refused=True)
        elif self.lock_taken is not None:
            remove_for_holder(self.out, self.lock_taken)
        self.lock_taken = None

    def _abort_setup(self):
        """This rank was stopped by a signal during the set-up and the others did not
        answer (not signalled, or waiting for this one in a collective call): abort the
        job, exit status 75, the lock dropped (already, unless the signal came just after
        the set-up)."""
        p = self.preemption
        self._drop_lock()
        print(f"{PROG}: rank {self.comm.rank}: {p.signal_name} received during the set-up; the other "
              f"ranks did not stop within {p.SETUP_WAIT:g} s (not signalled, or waiting for this one): "
              f"aborting the job (exit status {EXIT_PREEMPTED}); nothing was written, run the same "
              "command again", file=sys.stderr, flush=True)
        self.comm.Abort(EXIT_PREEMPTED)

    def _abort_refused(self, refusal):
        """This rank refused the run during the set-up and the others did not reach its
        end within :attr:`Preemption.REFUSED_WAIT` s: they wait in a collective call the
        refusal made this rank skip (before, mpiexec hung for ever).  The refusal is
        printed here (rank 0, if it is waiting, never heard it), the lock dropped and
        the job aborted with exit status 2; nothing was written."""
        self._drop_lock()
        if self.comm.rank != 0:
            print(f"{PROG}: error: {refusal}", file=sys.stderr, flush=True)
        print(f"{PROG}: rank {self.comm.rank} refused the run during the set-up (above) and the other ranks "
              f"did not stop within {self.preemption.REFUSED_WAIT:g} s (waiting in a collective call it "
              f"skipped): aborting the job (exit status {EXIT_USAGE}); nothing was written",
              file=sys.stderr, flush=True)
        self.comm.Abort(EXIT_USAGE)

    def _lock(self):
        """Step 1: rank 0 locks the output folder (collective verdict)."""
        from lc_petsc.io.lock import FolderBusy, OutputLock
        comm = self.comm
        if str(self.out) == "":
            raise Refused("the output folder is empty ('')")
        self.lock = OutputLock(self.out) if comm.rank == 0 else None
        taken, problem = on_root(comm, lambda: self.lock.acquire().taken())
        if isinstance(problem, FolderBusy):
            self.lock = None
            raise Refused(str(problem))
        if problem is not None:
            self.lock = None
            why = problem.strerror if isinstance(problem, OSError) and problem.strerror else problem
            raise Refused(f"output folder {str(self.out)!r}: {why}")
        self.lock_taken = taken
        if taken["stale"]:
            how = "it failed (its lock file says why)" if taken["ended"] else "it was killed or crashed"
            self._warn(f"{self.out}: found the lock of a run that did not finish ({taken['stale']}); {how}: "
                       "its outputs are as it left them, this run takes the folder over")

    def _unlock(self, refused=False):
        if self.lock is None:
            return
        if self.ended and not refused:
            try:
                if self.lock.leave(self.ended):
                    print(f"{PROG}: {self.lock.path} is left in the folder, saying why the run ended, so "
                          "scripts/check_outputs.py, scripts/join_summaries.py and the next run do not take "
                          "it for a killed run", file=sys.stderr, flush=True)
            except OSError as e:
                print(f"{PROG}: error: {self.lock.path} could not record why the run ended "
                      f"({e.strerror or e}): the folder looks like a killed run's", file=sys.stderr, flush=True)
        else:
            self.lock.release(remove_created_folder=refused)
        self.lock = None

    def _warn(self, text):
        self.warnings.append(text)
        warn(self.comm, text)

    def _validate(self):
        """Step 2 (after the build): warnings, restart, frames.h5, disk space; raises Refused."""
        from lc_petsc.diagnostics import (newton_warnings, preview_warnings, term_warnings,
                                          unwritten_frames_warnings)
        for w in (self.config_warnings + newton_warnings(self.sim.config) + term_warnings(self.sim)
                  + unwritten_frames_warnings(self.cfg) + preview_warnings(self.cfg)):
            self._warn(w)
        rows_kept = 0
        if self.args.restart is not None:
            self.restart = self._load_restart()
            if self.recovery is None:
                rows_kept = self.restart["frame"] // self.cfg.output.every + 1
        else:
            unfinished = self.comm.bcast(unfinished_run(self.out, self.lock_taken["ended"])
                                         if self.comm.rank == 0 else None)
            if unfinished and not self.args.force:
                raise Refused(f"{self.out} holds a run that did not finish ({unfinished}): continue it "
                              f"with --restart latest, or start over with --force (removes its "
                              f"frames.h5 and checkpoints)")
            if unfinished:
                self._warn(f"--force: starting over in {self.out}, whose run did not finish "
                           f"({unfinished}); its frames.h5 and checkpoints are removed")
            else:
                self._check_finished_run()
        self._check_disk(rows_kept)

    def _check_finished_run(self):
        """A new run into a folder that holds a finished run of *another* scene or
        physics (its summary.json's config differs in a key that changes the trajectory;
        the frame count, the output keys and the PETSc options, which the command line
        changes freely too, do not count) is refused without --force:
        it would replace that run's outputs, a run lost by a mistyped --out.  The same
        config (a rerun, longer or shorter) reuses the folder.  Raises Refused."""
        from lc_petsc.io.checkpoint import config_differences

        def read():
            saved = (finished_summary(self.out) or {}).get("config")
            if not isinstance(saved, dict):
                return None
            now = self.cfg.to_dict()
            diff = config_differences(saved, now, ignore=RESTART_FREE_KEYS | PETSC_OPTION_KEYS,
                                      defaults=SimConfig().to_dict())
            return _differences_text(diff, saved, now, ("finished run", "config")) if diff else None
        differs, problem = on_root(self.comm, read)
        if problem is not None or differs is None:
            return
        if not self.args.force:
            raise Refused(f"{self.out} holds a finished run of another config, which differs in {differs}; "
                          f"this run would replace its outputs: give another --out, or add --force to "
                          f"replace them")
        self._warn(f"--force: replacing the finished run in {self.out}, whose config differs in {differs}")

    def _load_restart(self):
        """The checkpoint to continue from, checked against the config, the scene and
        the folder's frames.h5; restored into the simulator.  Raises Refused."""
        from lc_petsc.io.checkpoint import (LEGACY_VALUES, checkpoint_folder, config_differences,
                                            find_latest, groom_differences, load_checkpoint)
        comm, args, cfg, sim = self.comm, self.args, self.cfg, self.sim
        skipped = []
        try:
            if args.restart == "latest":
                ck, skipped = find_latest(checkpoint_folder(self.out), comm, sim.user, sim.n_wisps,
                                          sim.n_vertices, sim.head)
                for m in skipped:
                    warn(comm, f"skipping an invalid checkpoint: {m}")
                if skipped:
                    warn(comm, f"falling back to {ck['path']}, the newest valid checkpoint")
            else:
                ck = load_checkpoint(args.restart, comm, sim.user, sim.n_wisps, sim.n_vertices, sim.head)
        except CheckpointError as e:
            raise Refused(str(e) + self._scene_hint()) from None
        ck["skipped"] = skipped
        diff = config_differences(ck["attrs"]["config"], cfg.to_dict(), ignore=RESTART_FREE_KEYS,
                                  defaults=SimConfig().to_dict())
        saved = ck["attrs"]["config"]
        # a groom file's path is no difference where the checkpoint holds the groom's
        # content (rest positions, pinned vertices, radius digest): compared below, so a
        # moved copy restarts and a changed file is refused naming what differs
        by_content = cfg.scene.kind in GROOM_FILE_KINDS and "radius_sha256" in ck["attrs"]
        hint = ""
        if by_content:
            diff = [k for k in diff if k != "scene.path"]
        elif "scene.path" in diff and cfg.scene.kind in GROOM_FILE_KINDS:
            hint += ("; the checkpoint predates radius_sha256 (2026-12-07), so its groom is compared by path "
                     "(a link at the checkpoint's path to a moved file will do)")
        legacy = [k for k in diff if k in LEGACY_VALUES
                  and k.split(".")[1] not in saved.get(k.split(".")[0], {})]
        hint += "".join(f"; the checkpoint predates {k} and ran as {k} = {str(LEGACY_VALUES[k]).lower()}, "
                        f"set that to continue it as it ran" for k in legacy)
        defaulted = [k for k in cfg.solver_path_defaulted if k in diff]
        if defaulted:
            # a key the checkpoint lacks ran as its default then (config_differences)
            old = SimConfig().to_dict()
            ran = ", ".join(f"{k} = {json.dumps(saved.get(table, {}).get(key, old[table][key]))}"
                            for k in defaulted for table, key in [k.split(".")])
            hint += (f"; this config leaves {', '.join(defaulted)} unset, which with a tolerance now selects "
                     f"the converging path (docs/newton.md \"The default for tolerance runs\"), and the "
                     f"checkpoint ran with {ran}: set that in the config to continue it as it ran")
        hint += _named_filter_hint(cfg, diff, saved)
        fixed = [k for k in diff if k in RESTART_FIXED_KEYS]
        if fixed:
            raise Refused(f"{ck['path']}: the config differs from the checkpoint's in "
                          f"{_differences_text(diff, saved, cfg.to_dict())}; {' and '.join(fixed)} cannot "
                          f"change in a restart, not even with --force: the run's frames.h5 (its dt and every "
                          f"attributes) and frames.usdc (timeCodesPerSecond = 1 / (dt * every)) give all its "
                          f"rows one time step; restart with the checkpoint's value (its attribute "
                          f"config_toml), or start a new run (without --restart) for another")
        if diff and not args.force:
            raise Refused(f"{ck['path']}: the config differs from the checkpoint's in "
                          f"{_differences_text(diff, saved, cfg.to_dict())}{hint}; restart with the config "
                          f"the checkpoint ran with (its attribute config_toml) or add --force (continues "
                          f"with this config)")
        if diff:
            warn(comm, f"--force: config differs from the checkpoint's in "
                       f"{_differences_text(diff, saved, cfg.to_dict())}")
        before, now = ck["attrs"].get("petsc_options") or {}, petsc_options_used(sim, self.command_line)
        changed = [k for k in sorted(set(before) | set(now))
                   if str(before.get(k)) != str(now.get(k)) and not diagnostic_option(k)]
        if changed:
            def shown(d, k):
                return "unset" if k not in d else (str(d[k]) or "set")
            self._warn("PETSc options differ from the checkpoint's: " + ", ".join(
                f"-{k} {shown(now, k)} (was {shown(before, k)})" for k in changed)
                + "; the run continues with them, so it is not bit for bit the run it continues")
        # a finished run whose last checkpoint is before its end: "latest" used to run
        # the frames after it again (on another rank count to round-off) and replace its
        # outputs and summary.json, where one checkpointed at its end was refused
        done = self.comm.bcast(finished_frames(self.out) if self.comm.rank == 0 else None)
        if args.restart == "latest" and not args.force and done is not None and cfg.time.frames <= done:
            a, b = ck["frame"] + 1, cfg.time.frames
            again = "" if a > b else f", or add --force to run frame{f' {a}' if a == b else f's {a}-{b}'} again from it"
            raise Refused(f"{self.out} holds a run that finished its {done} frames (its summary.json): "
                          f"nothing to do; to continue it from {ck['path']} give a larger --frames "
                          f"(time.frames, the total){again}")
        # a checkpoint at the last frame continues a run killed during its end-of-run
        # outputs (no summary.json): they are written again, no frame is run
        self.outputs_only = cfg.time.frames == ck["frame"] and self.comm.bcast(
            unfinished_run(self.out, self.lock_taken["ended"]) is not None if self.comm.rank == 0 else None)
        if cfg.time.frames <= ck["frame"] and not self.outputs_only:
            raise Refused(f"{ck['path']}: the checkpoint is at frame {ck['frame']}, the run ends at frame "
                          f"{cfg.time.frames} (time.frames / --frames is the total): nothing to do")
        groom = groom_differences(comm, ck, sim.user)
        if groom:
            was = saved.get("scene", {}).get("path")
            where = f" ({cfg.scene.path}; the checkpoint's run read {was})" if by_content and \
                was != cfg.scene.path else ""
            # refused like time.dt: frames.h5 holds one groom (/rest_positions, /pinned,
            # /radius) for all its rows, which the USD export's widths, pinned primvar and
            # rest pose, the crossing check and the head check read; --force used to keep
            # the old groom there under the rows simulated with the new one
            raise Refused(f"{ck['path']}: the scene's groom{where} differs from the checkpoint's in "
                          f"{'; '.join(groom)}; the groom cannot change in a restart, not even with --force: "
                          f"the run's frames.h5 (/rest_positions, /pinned, /radius) and frames.usdc (widths, "
                          f"pinned, the rest pose) hold one groom for all its rows; restart with the groom the "
                          f"checkpoint ran with, or start a new run (without --restart) with this one")
        self.recovery = self._frames_recovery(ck, ck["frame"] // cfg.output.every + 1)
        sim.restore(dict(ck, x=sim.user.from_user(ck["x"]), v=sim.user.from_user(ck["v"])))
        return ck

    def _scene_hint(self):
        """For a refused restart: the config keys in which the newest checkpoint in the
        folder (or --restart's file) was written with another value (a checkpoint of
        another scene fails its wisp counts before the configs are compared), else ''."""
        from lc_petsc.io.checkpoint import checkpoint_folder, config_differences, list_checkpoints

        def read():
            import h5py
            found = list_checkpoints(checkpoint_folder(self.out)) if self.args.restart == "latest" \
                else [Path(self.args.restart)]
            with h5py.File(found[0], "r") as f:
                saved = json.loads(f.attrs["config"])
            now = self.cfg.to_dict()
            diff = config_differences(saved, now, ignore=RESTART_FREE_KEYS, defaults=SimConfig().to_dict())
            return f"; {found[0]} was written with another config, which differs in " \
                   f"{_differences_text(diff, saved, now)}: restart with that config (its attribute " \
                   f"config_toml)" if diff else ""
        hint, problem = on_root(self.comm, read)
        return "" if problem is not None else hint

    def _frames_recovery(self, ck, rows):
        """None when the folder's frames.h5 can be appended to from the checkpoint ``ck``
        (its first ``rows`` rows kept), else the RecoveryPlan that --force continues
        with into a new frames.h5; without --force Refused, saying what --force keeps
        and loses (rank 0 inspects, read-only; one verdict for all)."""
        from lc_petsc.io.checkpoint import checkpoint_folder, list_checkpoints, read_positions
        from lc_petsc.io.frames import has_checksums, resumable_problem
        from lc_petsc.io.recovery import aside_path, plan_recovery
        args, cfg, sim = self.args, self.cfg, self.sim
        path = self.out / "frames.h5"
        offsets = global_wisp_offsets(self.comm, sim.user.offsets)

        def inspect():
            vouched = None
            if ck["frame"] % cfg.output.every == 0:
                vouched = (rows - 1, read_positions(ck["path"], offsets)["positions"])
            problem = resumable_problem(path, sim.n_wisps, sim.n_vertices, rows, checkpoint_row=vouched,
                                        offsets=offsets,
                                        dt=cfg.time.dt, every=cfg.output.every)
            if problem is None:
                return None, None, not has_checksums(path)
            plan = plan_recovery(path, problem, ck, list_checkpoints(checkpoint_folder(self.out)), offsets, rows)
            return plan, aside_path(path).name if os.path.lexists(path) else None, False
        verdict, error = on_root(self.comm, inspect)
        if error is not None:
            raise Refused(f"{path}: cannot inspect it before appending to it ({error})")
        plan, aside, unchecked = verdict
        if unchecked:
            self._warn(f"{path} was written before frames.h5 had checksums: its kept rows could be read but "
                       "not verified (a damaged value reads as a wrong number); the rows this run appends "
                       "have none either (a new run, without --restart, writes them)")
        if plan is not None and not args.force:
            kept = f", renaming this one to {aside} (kept, never removed)" if aside else ""
            raise Refused(f"{plan.problem}. With --force the run continues from {ck['path']} into a new "
                          f"frames.h5{kept}: {plan.describe()}; or restart with --out naming the folder "
                          f"of the checkpointed run")
        return plan

    def _check_disk(self, rows_kept):
        """Refuse a run whose outputs cannot fit on the output folder's volume."""
        from lc_petsc.io.checkpoint import checkpoint_folder, list_checkpoints
        from lc_petsc.io.disk import RESERVE, free_bytes, human
        cfg, sim = self.cfg, self.sim
        parts = output_estimate(cfg, sim.n_wisps, sim.n_vertices, rows_kept)
        need = sum(parts.values())

        def free():
            reclaim = 0
            if self.restart is None:      # a new run replaces the old frames and checkpoints
                for p in [self.out / "frames.h5", *list_checkpoints(checkpoint_folder(self.out))]:
                    if p.is_file():
                        reclaim += p.stat().st_size
            return free_bytes(self.out) + reclaim
        avail, problem = on_root(self.comm, free)
        if problem is not None:
            raise Refused(f"output folder {str(self.out)!r}: cannot query its free space ({problem})")
        if need + RESERVE > avail:
            rows = 1 + cfg.time.frames // cfg.output.every - rows_kept
            raise Refused(
                f"time.frames = {cfg.time.frames} (--frames): the outputs would need about {human(need)} "
                f"(frames.h5 {human(parts['frames.h5'])} for {rows} frame(s) of {sim.n_vertices} vertices, "
                f"output.every = {cfg.output.every}; "
                + ", ".join(f"{k} {human(v)}" for k, v in parts.items() if k != "frames.h5")
                + f"), the volume of {self.out} has {human(avail)} free; run fewer frames, raise "
                  "output.every or choose another --out")

    def _prepare_output(self):
        """Step 3: remove the previous run's outputs (on a restart frames.h5 and the
        checkpoints stay; a new run removes the old checkpoints with the frames.h5 they
        belong to).  OutputError on every rank."""
        from lc_petsc.io.checkpoint import checkpoint_folder, set_aside_later
        from lc_petsc.io.summary import remove_summaries
        out, restart = self.out, self.restart is not None
        if self.recovery is not None:
            self.aside = self._set_aside()
        if restart:
            self._set_summary_aside()

        def clean():
            if not restart:
                remove_summaries(out)
            for name in OUR_FILES:
                if not (restart and name == "frames.h5"):
                    (out / name).unlink(missing_ok=True)
            ck = checkpoint_folder(out)
            moved = []
            if ck.is_dir():
                for p in ck.iterdir():
                    if p.name.endswith(".h5.tmp") or (not restart and p.name.startswith("checkpoint_")):
                        p.unlink()
                if restart:
                    moved = set_aside_later(ck, self.restart["frame"])
            if (out / "previews").is_dir():     # with a killed run's image written aside
                for p in [*(out / "previews").glob("frame_*.png"), *(out / "previews").glob("frame_*.png.tmp")]:
                    p.unlink()
            return moved
        moved, problem = on_root(self.comm, clean)
        if problem is not None:
            raise OutputError(f"output folder {str(out)!r}: cannot remove the previous run's outputs "
                              f"({problem.strerror if isinstance(problem, OSError) else problem})")
        if moved:
            self._warn(f"restarting from frame {self.restart['frame']}: the checkpoints of later frames "
                       f"belong to the run this one replaces; renamed aside (kept, not used by --restart "
                       f"latest): " + ", ".join(f"{a.name} -> {b.name}" for a, b in moved))

    def _set_summary_aside(self):
        """Rank 0 renames the earlier run's summary.json into summaries/ (kept: this run's
        summary describes its own frames) and lists the summaries there in
        ``self.earlier_summaries``; a damaged one is kept under a name saying so, with a
        warning.  OutputError on every rank when it cannot be renamed."""
        from lc_petsc.io.summary import earlier_summaries, set_summary_aside
        out, frame = self.out, self.restart["frame"]

        failed = (self.lock_taken or {}).get("ended")     # the lock file said why its run ended

        def keep():
            target, damaged = set_summary_aside(out, failed)
            return target, damaged, earlier_summaries(out, frame)
        kept, problem = on_root(self.comm, keep)
        if problem is not None:
            raise OutputError(f"{out / 'summary.json'}: cannot set the earlier run's summary aside "
                              f"({problem.strerror if isinstance(problem, OSError) else problem})")
        target, damaged, self.earlier_summaries = kept
        if damaged:
            self._warn(f"the earlier run's {out / 'summary.json'} is damaged ({damaged}): kept as {target}; "
                       f"its per-frame records are lost, this run's summary.json has frames {frame + 1} on")

    def _set_aside(self):
        """Rank 0 renames the frames.h5 that cannot be appended to aside (no run removes
        it); its new path, None when there was none.  OutputError on every rank."""
        from lc_petsc.io.recovery import aside_path
        path = self.out / "frames.h5"

        def rename():
            if not os.path.lexists(path):
                return None
            target = aside_path(path)
            os.rename(path, target)
            return target
        target, problem = on_root(self.comm, rename)
        if problem is not None:
            raise OutputError(f"{path}: cannot rename it aside "
                              f"({problem.strerror if isinstance(problem, OSError) else problem})")
        return target

    def _write_recovered(self):
        """Rows 0 .. the checkpoint's into the new frames.h5 (the recovered ones, the
        lost ones marked); a warning and summary.json's frames_recovery say which.
        Returns every row's time (NaN for the lost)."""
        from lc_petsc.io.recovery import frame_ranges, frames_text, write_recovered
        plan, every = self.recovery, self.cfg.output.every
        offsets = global_wisp_offsets(self.comm, self.sim.user.offsets)
        recovered, times = write_recovered(self.writer, plan, self.aside, offsets, self.comm)
        self.writer.flush()
        lost = [k for k in range(plan.rows) if k not in set(recovered)]
        where = f"it was renamed to {self.aside} (kept)" if self.aside else "there was none to keep"
        self._warn(f"--force: {plan.problem}; {where}, and the run continues into a new frames.h5: "
                   f"{plan.describe(recovered)}"
                   + (f"; {frames_text(lost, every)} hold NaN in /positions and /time and False in "
                      f"/frame_valid" if lost else ""))
        self.recovery_report = {
            "problem": plan.problem, "renamed_to": None if self.aside is None else str(self.aside),
            "recovered_frames": frame_ranges(recovered, every), "missing_frames": frame_ranges(lost, every),
            "from_frames_file": frame_ranges([k for k in plan.from_file if k in recovered], every),
            "from_checkpoints": [k * every for k in sorted(plan.from_checkpoints) if k in recovered]}
        return times

    def _open_frames(self):
        from lc_petsc import __version__
        from lc_petsc.io.frames import FramesWriter
        sim, cfg = self.sim, self.cfg
        attrs = {"config": cfg.to_dict(), "config_file": str(Path(self.args.config).resolve()),
                 "terms": sim.terms_run(), "dt": cfg.time.dt, "every": cfg.output.every,
                 "frames": cfg.time.frames, "description": cfg.scene.description,
                 "lc_petsc_version": __version__}
        start = 0 if self.restart is None else self.restart["frame"]
        resume = self.restart is not None and self.recovery is None
        with sim.timers("io"):
            self.writer = FramesWriter(
                self.out / "frames.h5", self.comm, n_wisps=sim.n_wisps, n_vertices=sim.n_vertices,
                first_wisp=sim.user.first_wisp, first_vertex=sim.user.first_vertex,
                local_offsets=sim.user.offsets, rest_positions=sim.user.x_rest,
                pinned=sim.user.pinned, radius=sim.user.radius,
                n_out=1 + cfg.time.frames // cfg.output.every, attrs=attrs,
                resume_rows=start // cfg.output.every + 1 if resume else None,
                track_valid=self.recovery is not None)
            if self.restart is None:
                self.writer.write_frame(0.0, sim.user.to_user(sim.x))
                self.writer.flush()      # readable from the start, not only after FRAMES_FLUSH_SECONDS
                self.times = [0.0]
            elif self.recovery is not None:
                self.times = self._write_recovered()
            else:
                self.times = list(self.writer.times_kept)

    def _loop(self):
        """Steps 3 and 4: prepare, frame 0, the frames; failures end in self.error."""
        comm, cfg, sim = self.comm, self.cfg, self.sim
        start = 0 if self.restart is None else self.restart["frame"]
        self.t_loop, self.c_loop = time.perf_counter(), time.process_time()
        bar = None
        try:
            self._prepare_output()
            # the frame loop's span (wall_time_s, cpu_time_s and the phases of summary.json)
            # starts here: frames.h5's creation and frame 0 are its output (timed as io), the
            # set-up's phase times are not its frames' (main: io 1421% of a frame's wall time)
            self.t_loop, self.c_loop = time.perf_counter(), time.process_time()
            sim.timers.reset()
            self._open_frames()
            if self.restart is not None:
                say(comm, f"{PROG}: restarting from {self.restart['path']} at frame {start} "
                          f"(t = {self.restart['time']:.6g} s, written on "
                          f"{self.restart['attrs']['ranks']} rank(s), now {comm.size})")
            if self.outputs_only:
                say(comm, f"{PROG}: frame {start} is the run's last: no frame to run; writing the "
                          "end-of-run outputs the interrupted run did not finish (summary.json and "
                          "the exports from frames.h5)")
            bar = _progress(comm, self.args, cfg.time.frames - start, self.name)
            self.flushed = time.perf_counter()
            every, ck_every = cfg.output.every, cfg.output.checkpoint_every
            for _ in range(cfg.time.frames - start):
                if self.preemption.agreed():      # a signal since the set-up or in the frame before
                    self._record_progress()     # first, as below: a SIGKILL in the grace period
                    self._checkpoint()
                    break
                sim.step()
                it = sim.integrator
                if it.frame % every == 0:
                    with sim.timers("io"):
                        self.writer.write_frame(it.t, sim.user.to_user(sim.x))
                    self.times.append(it.t)
                if ck_every and it.frame % ck_every == 0:
                    self._record_progress()     # first: a checkpoint on disk has its frames' records
                    self._checkpoint()
                elif it.frame % every == 0 and self._flush_due():
                    with sim.timers("io"):
                        self.writer.flush()
                    self._record_progress()
                if bar is not None:
                    bar.set_postfix_str(f"Newton {it.newton_iterations[-1]}, "
                                        f"KSP {sim.solver.iterations[-1] if sim.solver.iterations else 0}",
                                        refresh=False)
                    bar.update(1)
        except (SolverError, FloatingPointError, SimulationError) as e:
            self.error = str(e)
        except OutputError as e:
            if e.hdf5_broken:
                hdf5.mark_unclosable()
            self.error = f"output error: {e}"
        except Exception as e:  # noqa: BLE001 - a failure that is not collective
            self._uncollective_failure(e)
        finally:
            if bar is not None:
                bar.close()

    def _record_progress(self):
        """Collective, in the frame loop (before each checkpoint, a signal's too, and after
        each flush of frames.h5): rank 0 replaces summary.json by the run's summary so
        far, ``status`` ``running`` (atomically, synced), so a run killed at any moment
        (SIGKILL, the OOM killer, a lost node) keeps the per-frame records of its frames up to its last
        checkpoint, and a restart sets them aside like any summary.  Its seconds are in
        ``output.progress_summaries``; a failed write is an output error (exit 3)."""
        from lc_petsc.io.summary import RUNNING, write_summary
        with self.sim.timers("io"):
            t0 = time.perf_counter()
            summary = self._summary(None, running=True)
            summary.update({"status": RUNNING, "crossings": None,
                            "output": {"dir": str(self.out), "every": self.cfg.output.every,
                                       "frames_written": self.writer.written}})
            path = self.out / "summary.json"
            _, problem = on_root(self.comm, lambda: write_summary(path, summary))
            if problem is not None:
                raise OutputError(f"{path} (the summary of the run so far): "
                                  f"{problem.strerror if isinstance(problem, OSError) else problem}")
            self.progress_seconds.append(time.perf_counter() - t0)
            self.progress_frame = summary["frames"]

    def _checkpoint(self):
        with self.sim.timers("io"):
            self.writer.flush()          # the frames a checkpoint vouches for are on disk
            self.flushed = time.perf_counter()
            self.checkpointer.write(self.sim.integrator)

    def _flush_due(self):
        """Whether frames.h5 is flushed now (rank 0's clock, one verdict for all): a run
        killed between flushes keeps a readable file with the frames up to the last one
        (never flushed, libhdf5 left it unreadable: "file signature not found")."""
        now = time.perf_counter()
        due = self.comm.bcast(now - self.flushed >= FRAMES_FLUSH_SECONDS if self.comm.rank == 0 else None)
        if due:
            self.flushed = now
        return due

    def _uncollective_failure(self, e):
        """An exception the simulator does not raise collectively (a bug).  Alone: an
        ordinary failed run.  With several ranks the others may be waiting in a
        collective call that will never complete: this rank records the error in
        summary.json (and the traceback on stderr) and aborts the job, exit status 3."""
        if self.comm.size == 1:
            traceback.print_exc()
            self.error = f"{type(e).__name__}: {e} (an internal error; traceback on stderr)"
            return
        msg = f"rank {self.comm.rank}: {type(e).__name__}: {e} (an internal error; traceback on stderr)"
        print(f"{PROG}: error: {msg}; aborting all ranks", file=sys.stderr, flush=True)
        traceback.print_exc()
        sys.stderr.flush()
        try:
            from lc_petsc.io.summary import RUNNING, write_summary
            path = self.out / "summary.json"
            try:        # the summary kept while the run went: its records stay
                kept = json.loads(path.read_text())
            except (OSError, ValueError):
                kept = None
            kept = kept if isinstance(kept, dict) and kept.get("status") == RUNNING else {}
            write_summary(path, {**kept, "error": msg, "aborted": True, "status": "error", "converged": False,
                                 "config": self.cfg.to_dict()})
        except OSError:
            pass
        self.comm.Abort(EXIT_RUN_FAILED)

    def _finish(self):
        """Step 5: close frames.h5, the end-of-run check, XDMF, previews, USD, summary,
        report; exit status.  A signal on any rank during the check or the exports stops
        them (:class:`~lc_petsc.stop_notice.StopNotice`): :meth:`_stopped_late`."""
        from lc_petsc.stop_notice import StopNotice
        comm, sim = self.comm, self.sim
        out_errors = []
        if self.writer is not None:
            try:
                with sim.timers("io"):
                    self.writer.close()
            except OutputError as e:
                hdf5.mark_unclosable()
                out_errors.append(str(e))
        self._stop_after_last_frame()
        self.frames_lost = self._frames_lost()
        self.stopped_in_loop = self.preemption.stopped
        self.stop = StopNotice(comm, lambda: bool(self.preemption.flag))
        try:
            preempted = self.preemption.signal_name if self.preemption.stopped else None
            summary = self._summary(preempted)       # first: its wall time is the frame loop's alone
            crossings = summary["crossings"] = None if self.frames_lost else self._check_crossings(preempted)
            if crossings and "interrupted" in crossings:
                self.skipped_outputs.append("crossing check")
                crossings = summary["crossings"] = None
            if crossings and "error" in crossings:
                self._warn(f"the crossing check could not read the frames ({crossings['error']}); "
                           "count them with scripts/count_crossings.py")
            for w in crossing_warnings(crossings, self.cfg) if crossings and "error" not in crossings else []:
                self._warn(w)
            if out_errors and not self.error:
                self.error = f"output error: {out_errors[0]}"
                summary["error"] = self.error
                summary["converged"] = False
            exports = self._write_exports(summary) if comm.rank == 0 else None
            self.stop.barrier()         # the others wait for rank 0's exports, passing on signals
            self.skipped_outputs = comm.bcast(self.skipped_outputs)
            if self.skipped_outputs:
                self._stopped_late(summary)
            if comm.rank == 0:
                self._write_summary(summary, exports)
        finally:
            self.stop.close()
        self.error = comm.bcast(self.error)
        if self.error:
            return EXIT_RUN_FAILED
        return EXIT_PREEMPTED if summary["preempted"] else EXIT_OK

    def _stopped_late(self, summary):
        """Collective, after a signal stopped the end-of-run check or exports: the signal's
        name in ``summary["preempted"]`` and a checkpoint of the last frame, unless there is
        one (a --restart latest then runs no frame and writes what was skipped)."""
        p = self.preemption
        p.agreed()
        summary["preempted"] = p.signal_name
        if self.error or self.writer is None or self.outputs_only:
            return
        try:
            self._record_progress()         # first: a checkpoint on disk has its frames' records
            with self.sim.timers("io"):
                self.checkpointer.write(self.sim.integrator)
        except OutputError as e:
            self.error = summary["error"] = f"output error: {e}"
            summary["converged"] = False
        summary["checkpoints"] = self.checkpointer.written

    def _stop_after_last_frame(self):
        """Collective, after the frame loop: a signal during the last frame or the close of
        frames.h5 (the loop only looks before a frame) stops the run as one during the
        loop does: a checkpoint of the last frame (a --restart latest then only writes the
        outputs), no crossing check, exit 75.  One later, during the check or the
        exports, is :meth:`_stopped_late`'s."""
        p, it = self.preemption, self.sim.integrator
        p.in_outputs = True
        if p.stopped or not p.agreed() or self.error or self.writer is None:
            return
        try:
            self._record_progress()         # first: a checkpoint on disk has its frames' records
            with self.sim.timers("io"):
                self.checkpointer.write(it)
        except OutputError as e:
            self.error = f"output error: {e}"

    def _frames_lost(self):
        """Collective: whether frames.h5 is gone after the frame loop (the output folder
        removed or renamed during the run; the run's output error says so first).  Then
        there is nothing to check or export from: the crossing check and the exports are
        skipped, and said so once after the error (each used to add a warning that it
        could not open the file)."""
        if self.writer is None:
            return False
        return self.comm.bcast(not (self.out / "frames.h5").is_file() if self.comm.rank == 0 else None)

    def _check_crossings(self, preempted=None):
        """The end-of-run crossing check of frames.h5 (``output.check_crossings``), between
        wisps and within each wisp, with its seconds; None when off or there is nothing to
        check, and on a preempted run (its time is the grace period's: the restart checks
        the whole file).  Whether to check is one verdict for all ranks: libhdf5's failure
        on the file (unclosable, broken) can be one rank's, and a rank that skipped the
        collective check would leave the others waiting in it."""
        from lc_petsc.crossings import check_run
        cfg, writer = self.cfg, self.writer
        if not cfg.output.check_crossings or writer is None or preempted:
            return None
        if global_max(self.comm, int(hdf5.unclosable() or writer.broken)):
            return None
        t0 = time.perf_counter()
        say(self.comm, f"{PROG}: checking the steps between the frames written for crossings", sys.stdout)
        # crossings of rest-exempt pairs are the exemption's, not a limiter failure; within a
        # wisp only where the contact acts there (self-contact): else a fold passes through
        # itself because nothing models it, whatever its rest distance
        d0 = self.sim.strand.d0 if self.sim.strand is not None else None
        check = check_run(self.out / "frames.h5", self.comm, self_contact=True, rest_exempt=d0, stop=self.stop,
                          contact_within=cfg.physics.strand_self_contact)
        check["seconds"] = global_max(self.comm, time.perf_counter() - t0)
        return check

    def _summary(self, preempted, running=False):
        """The run's summary (collective).  ``running``: the one kept on disk while the
        run goes (:meth:`_record_progress`): the warnings about the frames so far are in
        it but not printed (the end of the run prints them once)."""
        from lc_petsc import __version__
        from lc_petsc.diagnostics import shape_measures
        # here, not at the module's top: lc_petsc.timing imports PETSc, and lc_petsc.batch
        # imports this module before petsc4py.init, which then never ran (the command
        # line's -log_view was dropped)
        from lc_petsc.timing import peak_rss_mib
        comm, cfg, sim = self.comm, self.cfg, self.sim
        start = 0 if self.restart is None else self.restart["frame"]
        loop_time = global_max(comm, time.perf_counter() - self.t_loop)
        summary = sim.summary()
        summary["step_time_s"] = summary["wall_time_s"]
        summary["wall_time_s"] = loop_time
        # CPU time measures the work on a shared machine, where wall time also holds waits
        summary["cpu_time_s"] = comm.allreduce(time.process_time() - self.c_loop)
        # the job's memory as a batch system sees it: each rank's peak resident set
        peak = peak_rss_mib()
        summary["peak_memory_mib"] = {"max_rank": global_max(comm, peak), "sum_ranks": comm.allreduce(peak)}
        used = petsc_options_used(sim, self.command_line)
        unused = sim.plan.unused_options(self.command_line)
        notes = [f"PETSc option -{k} was given but never used by the solver (a typo, or an "
                 "option of a solver that is not selected?)" for k in unused]
        not_reduced = sim.solver.not_reduced
        if not_reduced:
            worst = max(r for _, r in not_reduced)
            notes.append(f"{len(not_reduced)} of {len(sim.solver.reasons)} linear solve(s) reported "
                         f"{sim.solver.reasons[not_reduced[0][0]]} without reaching -ksp_rtol "
                         f"{sim.solver.rtol:g} (true relative residual up to {worst:.3g}, first at solve "
                         f"{not_reduced[0][0]}): not converged; use a KSP that tests the residual "
                         "(e.g. -ksp_type cg) or an exact preconditioner with -ksp_type preonly")
        notes += outcome_warnings(summary, start, cfg.time)
        if not running:
            for w in notes:
                self._warn(w)
        summary.update({
            "config_file": str(Path(self.args.config).resolve()),
            "description": cfg.scene.description,
            "solver_path_defaulted": list(cfg.solver_path_defaulted),
            "lc_petsc_version": __version__,
            "setup_time_s": self.setup_time,
            "time_per_frame_s": summary["wall_time_s"] / max(summary["frames"] - start, 1),
            "frames_this_run": summary["frames"] - start,
            "restart": None if self.restart is None else {
                "checkpoint": str(self.restart["path"]), "frame": start,
                "ranks_before": self.restart["attrs"]["ranks"], "skipped": self.restart["skipped"],
                "earlier_summaries": self.earlier_summaries},
            **dict(zip(("checkpoints", "checkpoints_removed"), self.checkpointer.report())),
            "frames_recovery": self.recovery_report,
            "preempted": preempted,
            "solver": summary["petsc_options"],
            "petsc_options": _options_string(used),
            "petsc_options_used": used,
            "petsc_options_unused": unused,
            "petsc_options_command_line": dict(self.command_line),
            "linear_solves_not_converged": [{"solve": i, "relative_residual": r} for i, r in not_reduced],
            "warnings": self.warnings + notes if running else self.warnings,
            # the end's shape; not in a running summary (11.7 ms of its 17.5 on a 5-wisp scene)
            "shape": None if running else shape_measures(comm, sim.x, sim.scene.x_rest, sim.scene.offsets),
            "error": self.error,
        })
        # a frame whose Newton missed time.newton_increment_tol / newton_tol is not converged
        # either (main said "converged: yes" beside the warning naming the frames it missed);
        # a start/jolt frame ended by the cap asked for there (newton_capped) is no miss
        if self.error or not_reduced or missed_frames(summary):
            summary["converged"] = False
        return summary

    def _write_exports(self, summary):
        """Rank 0: frames.xdmf, previews, frames.usdc; each that fails is named in the
        returned dict's ``not_written``, the others are still written.  A signal (on any
        rank) skips those not begun and stops the previews and the export between two
        frames (``output.skipped``)."""
        from lc_petsc.stop_notice import Stopped
        from lc_petsc.io.xdmf import write_xdmf
        cfg, sim, out, writer = self.cfg, self.sim, self.out, self.writer
        h5_path = out / "frames.h5"
        problems = []
        if self.frames_lost:            # said once by _frames_lost
            return {"files": [], "not_written": problems, "xdmf_s": 0.0, "previews_s": 0.0, "usd_s": 0.0}
        files = ["frames.h5"] if writer is not None else []
        # after an output error the previews and the export would meet the same full disk
        # or unwritable folder: skipped, and one warning says so (below)
        stopped = bool(self.error and self.error.startswith("output error")) and writer is not None
        t0 = time.perf_counter()
        if cfg.output.xdmf and writer is not None and not hdf5.unclosable():
            try:
                write_xdmf(out / "frames.xdmf", h5_path, self.times, sim.n_vertices, sim.n_wisps,
                           name=self.name, valid=writer.rows_valid)
                files.append("frames.xdmf")
            except OSError as e:
                problems.append(f"{out / 'frames.xdmf'}: {e.strerror or e}")
        t_xdmf = time.perf_counter() - t0
        t0 = time.perf_counter()
        if cfg.output.previews and not stopped and self._late_signal("previews") and writer is not None \
                and writer.written and not hdf5.unclosable():
            try:
                files += [os.path.relpath(p, out) for p in _previews(cfg, out, h5_path, writer,
                                                                     cfg.time.frames, self.name, self._stop)]
            except Stopped:
                self.skipped_outputs.append("previews")
            except Exception as e:  # noqa: BLE001 - a preview is never worth the run's summary
                problems.append(f"previews in {out}: {getattr(e, 'strerror', None) or e}")
        t_prev = time.perf_counter() - t0
        t_usd = 0.0
        usd_error: list = []        # USD's own text of a failed export (a line per C++ error)

        def usd_warning(text):
            # on stderr and in summary.json: a pipeline reading the summary must learn
            # that frames.usdc is missing (a full disk's failure was on stderr only)
            print(f"{PROG}: warning: {text}", file=sys.stderr, flush=True)
            summary["warnings"] = list(summary.get("warnings") or []) + [text]
        skipped = [name for on, name in ((cfg.output.previews and writer is not None and writer.written, "previews"),
                                         (cfg.output.usd, "frames.usdc")) if on and stopped]
        if skipped:
            # pxr's 6-line failure used to follow the error as a warning, and a preview's
            # failure made a second error (output.not_written)
            to_usd = "" if "frames.usdc" not in skipped else \
                f", or drivers/to_usd.py {h5_path} from the frames written" if len(skipped) == 1 else \
                f"; drivers/to_usd.py {h5_path} writes frames.usdc from the frames written"
            usd_warning(f"{' and '.join(skipped)} not written: the run stopped on an output error (above); "
                        f"--restart latest writes {'it' if len(skipped) == 1 else 'them'} at the end of the "
                        f"continued run{to_usd}")
        if "frames.usdc" not in skipped and (not cfg.output.usd or self._late_signal("frames.usdc")) \
                and writer is not None and writer.written and not hdf5.unclosable():
            # USD export for DCC tools (frames.usdc), from the closed frames.h5
            from lc_petsc.io.usd import export_failed, export_run
            try:
                usd_files, t_usd = export_run(cfg.output, h5_path, out, stop=self._stop, warn=usd_warning,
                                              detail=usd_error.append)
                files += usd_files
            except Stopped:
                self.skipped_outputs.append("frames.usdc")
            except Exception as e:  # noqa: BLE001 - like a preview, never worth the summary
                usd_warning(export_failed(h5_path, f"{type(e).__name__}: {e}"))
        return {"files": files, "not_written": problems, "xdmf_s": t_xdmf, "previews_s": t_prev,
                "usd_s": t_usd, "usd_error": usd_error[0] if usd_error else None}

    def _write_summary(self, summary, exports):
        """Rank 0: summary.json (with the exports' ``output`` figures) and the report."""
        from lc_petsc.io.summary import format_report, write_summary
        cfg, sim, out, writer = self.cfg, self.sim, self.out, self.writer
        problems = exports["not_written"]
        if problems and not self.error:
            self.error = summary["error"] = f"output error: {problems[0]}"
            summary["converged"] = False
        summary["output"] = {"dir": str(out), "every": cfg.output.every,
                             "frames_written": writer.written if writer is not None else 0,
                             "files": exports["files"] + ["summary.json"], "xdmf_s": exports["xdmf_s"],
                             "previews_s": exports["previews_s"], "usd_s": exports["usd_s"],
                             "not_written": problems, "skipped": self.skipped_outputs,
                             "usd_error": exports.get("usd_error"),
                             "progress_summaries": {"written": len(self.progress_seconds),
                                                    "seconds": sum(self.progress_seconds),
                                                    "max_seconds": max(self.progress_seconds, default=0.0)}}
        summary["status"] = "error" if self.error else "preempted" if summary["preempted"] else "finished"
        try:
            write_summary(out / "summary.json", summary)
        except OSError as e:
            left = (f"the summary.json left is the one kept while the run went (status running, up to frame "
                    f"{self.progress_frame})" if self.progress_seconds else "no summary.json of this run is left")
            print(f"{PROG}: error: {out / 'summary.json'} could not be written ({e.strerror or e}); {left}; "
                  "the run's figures are in the report below", file=sys.stderr, flush=True)
            was = summary["status"] + (f": {self.error}" if self.error else "")
            self.ended = f"its final summary.json ({was}) could not be written: {e.strerror or e}"
            self.error = self.error or f"output error: {out / 'summary.json'}: {e.strerror or e}"
            summary["output"]["files"].remove("summary.json")      # the report says what is there
            try:
                os.unlink(f"{out / 'summary.json'}.tmp")
            except OSError:
                pass
        print(format_report(summary), flush=True)
        if self.error:
            print(f"{PROG}: error: {self.error}", file=sys.stderr, flush=True)
            self._say_how_to_continue()
        if self.frames_lost:
            print(f"{PROG}: {out / 'frames.h5'} is gone (the output folder was removed or renamed during the "
                  "run?): no crossing check, frames.xdmf, previews or frames.usdc (nothing to make them from)",
                  file=sys.stderr, flush=True)
        if self.skipped_outputs and not self.stopped_in_loop:
            self._say_outputs_skipped()
        elif summary["preempted"]:
            last = self.checkpointer.written[-1]["path"] if self.checkpointer.written else "?"
            print(f"{PROG}: {summary['preempted']} received: stopped after frame {sim.integrator.frame}, "
                  f"checkpoint {last} written; continue with --restart latest "
                  f"(exit status {EXIT_PREEMPTED})", file=sys.stderr, flush=True)

    def _late_signal(self, output):
        """Rank 0, before a slow end-of-run output: False (and ``output`` recorded as skipped)
        once a signal came on any rank, also one that stopped the frame loop; else True.
        The run stops promptly (a scheduler's grace period is running), a --restart latest
        writes what was skipped."""
        if self.preemption.stopped or self.stop.requested():
            self.skipped_outputs.append(output)
            return False
        return True

    def _stop(self):
        """Rank 0, between two frames of a slow export: raise Stopped on a signal."""
        from lc_petsc.stop_notice import Stopped
        if self.stop.requested():
            raise Stopped("a signal during the end-of-run outputs")

    def _say_outputs_skipped(self):
        """Rank 0: what a signal during the end-of-run check and outputs left undone, how to finish."""
        written = self.checkpointer.written
        last = written[-1]["frame"] if written else self.restart["frame"] if self.restart else None
        frame = self.sim.integrator.frame
        how = "continue with --restart latest (it does them"
        if last is not None and last < frame:
            again = f"frame {frame}" if last + 1 == frame else f"frames {last + 1}-{frame}"
            how += f", after running {again} again from the checkpoint of frame {last})"
        elif last is not None:
            how += ", running no frame)"
        else:
            how = (f"no checkpoint to restart from (output.checkpoint_every = 0): drivers/to_usd.py "
                   f"{self.out / 'frames.h5'} writes frames.usdc")
        print(f"{PROG}: {self.preemption.signal_name} received during the end-of-run check and outputs: "
              f"frames.h5 holds every frame (0-{frame}); skipped: {', '.join(self.skipped_outputs)}; {how} "
              f"(exit status {EXIT_PREEMPTED})", file=sys.stderr, flush=True)

    def _say_how_to_continue(self):
        """Rank 0, after a failure: the folder's newest checkpoint and --restart latest
        (a new run into the folder is refused while they are there, unfinished_run)."""
        from lc_petsc.io.checkpoint import checkpoint_folder, list_checkpoints
        found = list_checkpoints(checkpoint_folder(self.out))
        if found:
            print(f"{PROG}: the checkpoints are kept (newest {found[0]}): once the cause is fixed "
                  "(e.g. space freed), continue with --restart latest; to continue on another disk, "
                  "copy the whole folder there (cp -a: frames.h5 with its checkpoints) and run "
                  "--restart latest in the copy; or start over with --force",
                  file=sys.stderr, flush=True)


class Checkpointer:
    """Writes checkpoints of the running job (see lc_petsc.io.checkpoint)."""

    def __init__(self, job):
        from lc_petsc import __version__
        self.job = job
        self.petsc_options = petsc_options_used(job.sim, job.command_line)
        self.version = __version__
        self.config_dict = job.cfg.to_dict()
        self.written, self.last_frame = [], None
        self.before = self._in_folder()           # an earlier run's, after a restart

    def _in_folder(self):
        """{path: (frame, bytes)} of the checkpoint files in the folder now, rank 0's view
        on every rank (collective)."""
        from lc_petsc.io.checkpoint import checkpoint_files, checkpoint_folder
        found, problem = on_root(self.job.comm, lambda: checkpoint_files(checkpoint_folder(self.job.out)))
        return {} if problem is not None else {p: (f, size) for f, p, size in found}

    def report(self):
        """(kept, removed) for summary.json (collective): the checkpoint files in the folder
        now, oldest first (frame, path, this run's seconds to write it, None for an
        earlier run's, bytes), and those this run saw that are gone, oldest first (frame,
        path: the rotation keeps the newest ``output.checkpoints_kept``).  Listing what
        was written named files the rotation had deleted."""
        now = self._in_folder()
        secs = {c["path"]: c["seconds"] for c in self.written}
        kept = [{"frame": f, "path": p, "seconds": secs.get(p), "bytes": size}
                for p, (f, size) in sorted(now.items(), key=lambda i: i[1][0])]
        seen = {**{p: f for p, (f, _) in self.before.items()}, **{c["path"]: c["frame"] for c in self.written}}
        removed = [{"frame": f, "path": p} for p, f in sorted(seen.items(), key=lambda i: i[1]) if p not in now]
        return kept, removed

    def write(self, it):
        """Write the checkpoint of the integrator ``it``'s frame (once per frame), timed under ``io``."""
        from lc_petsc.io.checkpoint import write_checkpoint
        if self.last_frame == it.frame:
            return
        job = self.job
        sim, cfg = job.sim, job.cfg
        try:
            path, secs, size = write_checkpoint(
                job.out, job.comm, frame=it.frame, t=it.t, x=sim.user.to_user(it.x),
                v=sim.user.to_user(it.v), scene=sim.user,
                n_wisps=sim.n_wisps, n_vertices=sim.n_vertices, head=sim.head, dt=cfg.time.dt,
                every=cfg.output.every, config_dict=self.config_dict, config_toml=job.cfg_text,
                petsc_options=self.petsc_options, keep=cfg.output.checkpoints_kept, version=self.version)
        except OSError as e:          # the folder or the rename (collective, from rank 0)
            raise OutputError(f"checkpoint of frame {it.frame}: {e}") from None
        self.written.append({"frame": it.frame, "path": str(path), "seconds": secs, "bytes": size})
        self.last_frame = it.frame


class Preemption:
    """SIGTERM, SIGUSR1 and SIGINT (Ctrl-C) set a flag (main thread only); :meth:`agreed`
    allreduces it at a frame end, so a signal that reached some ranks only stops all of
    them together after the same frame, with a checkpoint.  After a first SIGINT the
    default action is back: a second Ctrl-C ends the process at once (no checkpoint;
    the previous checkpoints and the frames written so far are kept).

    During the set-up (:meth:`setup`; minutes for a big scene) there is nothing to
    checkpoint: a signal raises :class:`SetupInterrupted` where the rank is.  Then
    :meth:`end_setup` tells every rank how the set-up ended on every rank, on a
    communicator of its own (the interrupted rank may have left the others inside a
    collective call on the job's).  A rank that got no signal (``kill`` of one rank),
    or that waits for the interrupted one in a collective call, cannot answer: the
    interrupted rank gives up after :attr:`SETUP_WAIT` seconds and the job is aborted."""

    SIGNALS = ("SIGTERM", "SIGUSR1", "SIGINT")
    SETUP_WAIT = 5.0
    #: how long a rank that refused the run waits for the others at the set-up's end
    #: (a refusal on every rank meets there at once; on some ranks only, the others may
    #: wait in a collective call it skipped)
    REFUSED_WAIT = 20.0

    def __init__(self, comm):
        import signal
        import threading
        self.comm = comm
        self.flag, self.signal_name, self.previous, self.stopped = 0, None, {}, False
        self.signum, self.raising, self.setup_over = 0, False, False
        self.in_outputs = False     # after the frame loop (the handler's SIGINT note)
        self.setup_comm = comm.Dup() if comm.size > 1 else None
        self.refusals = []      # end_setup: the refused ranks' messages, by rank
        if threading.current_thread() is threading.main_thread():
            for name in self.SIGNALS:
                sig = getattr(signal, name)
                self.previous[sig] = signal.signal(sig, self._handler)

    def _handler(self, signum, frame):
        import signal
        self.flag = 1
        self.signum = self.signum or signum
        self.signal_name = self.signal_name or signal.Signals(signum).name
        if signum == signal.SIGINT:
            signal.signal(signal.SIGINT, signal.SIG_DFL)
        if self.raising:
            self.raising = False
            raise SetupInterrupted(self.signal_name)
        if signum == signal.SIGINT and self.setup_over:
            now = "stopping the end-of-run check and outputs, a checkpoint of the last frame" \
                if self.in_outputs else "finishing this frame, then a checkpoint"
            print(f"\n{PROG}: SIGINT: {now} and exit {EXIT_PREEMPTED}; press Ctrl-C again "
                  "to stop at once (no checkpoint)", file=sys.stderr, flush=True)

    @contextmanager
    def setup(self):
        """The set-up: a signal (also one before it) raises SetupInterrupted."""
        self.raising = True
        try:
            if self.flag:
                self.raising = False
                raise SetupInterrupted(self.signal_name)
            yield
        finally:
            self.raising = False

    def end_setup(self, outcome, built, refusal=None):
        """Collective: ``(outcome, signal number, built)`` of every rank, by rank (a signal
        after the set-up counts as one during it: nothing has changed yet); None on a rank
        stopped by a signal, or that refused the run, whose ranks did not all answer
        within SETUP_WAIT (REFUSED_WAIT) s.  When some rank refused, :attr:`refusals`
        holds the refused ranks' messages (``refusal``), by rank."""
        self.raising, self.setup_over = False, True
        if self.flag:
            outcome = SETUP_INTERRUPTED
        mine = np.array([outcome, self.signum, built], np.intc)
        if self.setup_comm is None:
            self.refusals = [refusal] if outcome == SETUP_REFUSED else []
            return [tuple(int(v) for v in mine)]
        every = np.empty((self.comm.size, 3), np.intc)
        req = self.setup_comm.Iallgather(mine, every)
        if outcome in (SETUP_INTERRUPTED, SETUP_REFUSED):
            wait = self.SETUP_WAIT if outcome == SETUP_INTERRUPTED else self.REFUSED_WAIT
            deadline = time.monotonic() + wait
            while not req.Test():
                if time.monotonic() > deadline:
                    return None
                time.sleep(0.01)
        else:
            req.Wait()
        if any(row[0] == SETUP_REFUSED for row in every):     # every rank is here: no one waits
            self.refusals = [m for m in self.setup_comm.allgather(
                refusal if outcome == SETUP_REFUSED else None) if m is not None]
        self.setup_comm.Free()
        self.setup_comm = None
        return [tuple(int(v) for v in row) for row in every]

    def agreed(self):
        """Collective: whether any rank received a signal (then ``stopped`` is set)."""
        comm = self.comm
        if not global_max(comm, self.flag):
            return False
        names = [n for n in comm.allgather(self.signal_name) if n]
        self.signal_name = names[0] if names else "a signal (on another rank)"
        self.stopped = True
        return True

    def restore(self):
        """Put back the signal handlers that were there before."""
        import signal
        for sig, h in self.previous.items():
            signal.signal(sig, h)
        self.previous = {}


def _named_filter_hint(cfg, diff, saved):
    """The refusal's hint for a checkpoint that ran the converging path a tolerance takes
    where the config file leaves ``solver.filter`` unset (:func:`lc_petsc.config.tolerance_defaults`),
    restarted with a file that names ``solver.filter``: that keeps the keys it leaves
    unset at their defaults, so the keys of ``diff`` the checkpoint (``saved``) ran at
    the path's values and ``cfg`` has at its defaults are named, with those values; or ''.
    Without it the refusal listed them (six where the file named the very filter the
    checkpoint ran) and did not say why they changed."""
    # (a tolerance on the filtered path resolves nothing only where the file names solver.filter)
    if cfg.solver_path_defaulted or not cfg.time.newton_converges or cfg.time.newton != "filtered":
        return ""
    ran = [(f"{table}.{key}", value) for (table, key), value in
           {**TOLERANCE_PATH, **TOLERANCE_PATH_WITHOUT_STRAND_CONTACT}.items()
           if f"{table}.{key}" in diff and saved.get(table, {}).get(key) == value
           and getattr(getattr(cfg, table), key) == getattr(type(getattr(cfg, table))(), key)]
    if not ran:
        return ""
    return (f"; the checkpoint ran the converging path a tolerance takes where the config file leaves "
            f"solver.filter unset, and this config names solver.filter, which keeps the keys it leaves unset "
            f"at their defaults (docs/newton.md \"The default for tolerance runs\"): set "
            f"{', '.join(f'{k} = {json.dumps(v)}' for k, v in ran)} in the config to continue it as it ran")


def _differences_text(keys, saved, now, names=("checkpoint", "config")):
    """'time.dt (checkpoint: 0.0333, config: 0.02), ...' for the dotted config ``keys``
    of the checkpoint's config dict ``saved`` and the run's ``now`` (``names``: what the
    two are called)."""
    def value(d, key):
        for part in key.split("."):
            if not isinstance(d, dict) or part not in d:
                return "unset"
            d = d[part]
        return repr(d)
    return ", ".join(f"{k} ({names[0]}: {value(saved, k)}, {names[1]}: {value(now, k)})" for k in keys)


def _signal_name(signum):
    import signal
    return signal.Signals(signum).name


def _previews(cfg, out, h5_path, writer, frames, title, stop=None):
    from lc_petsc.io.previews import render_previews
    from lc_petsc.scene.kinematics import HeadMotion
    every, n = cfg.output.every, writer.written
    rows = []
    for f in cfg.output.preview_frames:
        fa = frames + 1 + f if f < 0 else f
        rows.append(min(max(fa, 0) // every, n - 1))
    from lc_petsc.io.usd import has_head_sphere
    head = None
    if has_head_sphere(cfg.physics, cfg.scene):
        hm = HeadMotion(cfg.physics)
        head = lambda t: (hm.sphere_center(t), hm.radius)   # noqa: E731
    return render_previews(h5_path, out, rows, contact_panels=cfg.output.contact_sheet,
                           view=cfg.output.view, title=title, head=head, every=every, stop=stop)


def _progress(comm, args, frames, name):
    """Rank 0's progress on stderr: a bar on a terminal, plain lines in a batch log."""
    if comm.rank != 0 or args.quiet or frames == 0:
        return None
    if not sys.stderr.isatty():
        return LogProgress(frames, name)
    from tqdm import tqdm
    return tqdm(total=frames, unit="frame", desc=name, dynamic_ncols=True, file=sys.stderr)


class LogProgress:
    """Progress for a batch job whose stderr is a file: one line after the first frame,
    then at most one every ``interval`` seconds of wall time, and one after the last
    (frames done, seconds per frame so far, the time left at that rate, and the last
    frame's postfix).  The two calls of tqdm that the frame loop makes, and ``close``."""

    def __init__(self, total, name, interval=30.0, stream=None, clock=time.perf_counter):
        self.total, self.name, self.interval = int(total), name, float(interval)
        self.stream, self.clock = stream, clock
        self.done, self.postfix = 0, ""
        self.t0 = self.last = clock()

    def set_postfix_str(self, text, refresh=False):
        """The text that ends the next line (tqdm's call; ``refresh`` is ignored)."""
        self.postfix = text

    def update(self, n=1):
        """n more frames done: print a line if one is due."""
        self.done += n
        now = self.clock()
        if self.done == 1 or self.done >= self.total or now - self.last >= self.interval:
            self.last = now
            per = (now - self.t0) / self.done
            left = per * (self.total - self.done)
            tail = f", {self.postfix}" if self.postfix else ""
            print(f"{self.name}: frame {self.done}/{self.total} ({100 * self.done // self.total}%), "
                  f"{_per_frame_text(per)} per frame, {_clock_text(left)} left{tail}",
                  file=self.stream or sys.stderr, flush=True)

    def close(self):
        """Nothing to close (tqdm's call)."""


def _per_frame_text(seconds):
    return f"{seconds:.3g} s" if seconds < 60 else _clock_text(seconds)


def _clock_text(seconds):
    """``1 h 02 min``, ``3 min 05 s`` or ``42 s``."""
    s = int(round(seconds))
    if s >= 3600:
        return f"{s // 3600} h {s % 3600 // 60:02d} min"
    return f"{s // 60} min {s % 60:02d} s" if s >= 60 else f"{s} s"
