"""Continuing a run whose ``frames.h5`` cannot be appended to (missing, truncated,
corrupt, another run's: :func:`lc_petsc.io.frames.resumable_problem`) from its
checkpoint, with ``--restart ... --force``, into a new ``frames.h5``.

Nothing is deleted: the old file is renamed aside (:func:`aside_path`,
``frames.unusable-N.h5``) and no later run removes it.  The new file has every row from
frame 0, as any ``frames.h5`` (row k is simulation frame k * every, so restarts, the
exports and plain h5py readers keep their meaning of a row); the rows up to the
checkpoint's are recovered where they can be, and the others are marked lost:

* from the checkpoints of the run (the restart checkpoint and those in the output
  folder at frames up to it that are rows, with the same config and valid checksums):
  their positions and time;
* from the old file, the other rows that are readable and finite, when the file has
  the scene's wisps and the checkpoint's ``dt`` and ``every``, and, where it shares
  rows with those checkpoints, at least one of them holds the checkpoint's positions
  bit for bit (none does: another run's file, none of its rows is used).  A shared row
  that differs is corrupt and the checkpoint's replaces it; frames.h5 has no checksums,
  so its other rows are trusted as a plain restart trusts the rows it keeps;
* every other row is lost: NaN in ``/positions`` and ``/time``, False in
  ``/frame_valid``.  Nothing is interpolated or recomputed.

The plan is made by rank 0 (serial reads, nothing changed), before anything in the
folder is touched; :func:`write_recovered` then writes the rows collectively (rank 0
writes each whole row, the other ranks take part with empty selections).
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lc_petsc.errors import CheckpointError
from lc_petsc.io.hdf5 import h5py_module

ASIDE = "frames.unusable-{}.h5"


@dataclass
class RecoveryPlan:
    """What a recovery keeps of the rows 0 .. ``rows`` - 1 (up to the checkpoint's frame)."""

    problem: str                 # why the old frames.h5 cannot be appended to
    rows: int
    every: int
    from_file: list = field(default_factory=list)          # rows read from the old file
    from_checkpoints: dict = field(default_factory=dict)   # row -> checkpoint path
    file_note: str = ""          # why no row comes from the old file

    def recovered(self):
        """The rows recovered, in order."""
        return sorted(set(self.from_file) | set(self.from_checkpoints))

    def lost(self):
        """The rows lost, in order."""
        kept = set(self.recovered())
        return [k for k in range(self.rows) if k not in kept]

    def describe(self, recovered=None):
        """'frames 0-4 recovered (...); frames 5-9 lost' for ``recovered`` rows (default:
        the plan's)."""
        rows = self.recovered() if recovered is None else list(recovered)
        lost = [k for k in range(self.rows) if k not in set(rows)]
        ck = sorted(k for k in self.from_checkpoints if k in rows)
        src = [f"{frames_text(self.from_file, self.every)} from the old frames.h5"] if self.from_file else []
        src += [f"{frames_text(ck, self.every)} from checkpoints"] if ck else []
        note = f"; nothing from the old frames.h5: {self.file_note}" if self.file_note else ""
        every = f" (output.every = {self.every})" if self.every > 1 else ""
        return (f"of the {self.rows} frame row(s) up to the checkpoint{every}, "
                f"{frames_text(rows, self.every)} recovered ({', '.join(src) or 'none'}), "
                f"{frames_text(lost, self.every)} lost{note}")


def frame_ranges(rows, every):
    """Consecutive runs of ``rows`` as [first, last] simulation frames."""
    out = []
    for k in sorted(rows):
        if out and k * every == out[-1][1] + every:
            out[-1][1] = k * every
        else:
            out.append([k * every, k * every])
    return out


def frames_text(rows, every):
    """'frames 0-4, 8' for ``rows``, 'no frame' for none."""
    ranges = frame_ranges(rows, every)
    if not ranges:
        return "no frame"
    return "frame(s) " + ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in ranges)


def aside_path(path) -> Path:
    """The first free ``frames.unusable-N.h5`` beside ``path``."""
    folder, n = Path(path).parent, 1
    while (folder / ASIDE.format(n)).exists():
        n += 1
    return folder / ASIDE.format(n)


def plan_recovery(path, problem, checkpoint, checkpoints, offsets, rows):
    """Rank 0, serial, read-only: the :class:`RecoveryPlan` for ``frames.h5`` at ``path``
    (``problem``: why it cannot be appended to) and the loaded restart ``checkpoint``;
    ``checkpoints``: the output folder's checkpoint files; ``offsets``: the global wisp
    offsets; ``rows``: the rows up to the checkpoint's frame."""
    attrs = checkpoint["attrs"]
    every = int(attrs["every"])
    positions = _checkpoint_rows(checkpoint, checkpoints, offsets, rows, every)
    plan = RecoveryPlan(problem, rows, every, from_checkpoints={k: p for k, (p, _) in positions.items()})
    plan.from_file, plan.file_note = _file_rows(path, offsets, rows, float(attrs["dt"]), every,
                                                {k: x for k, (_, x) in positions.items()})
    return plan


def _checkpoint_rows(checkpoint, checkpoints, offsets, rows, every):
    """{row: (path, positions)} of the checkpoints at frames that are rows up to the
    restart checkpoint's, with its config and valid checksums."""
    from lc_petsc.io.checkpoint import read_positions
    sha = checkpoint["attrs"]["config_sha256"]
    out = {}
    for p in {Path(checkpoint["path"]), *map(Path, checkpoints)}:
        try:
            c = read_positions(p, offsets)
        except CheckpointError:
            continue
        if c["frame"] % every == 0 and c["frame"] // every < rows and c["config_sha256"] == sha:
            out[c["frame"] // every] = (str(p), c["positions"])
    return out


def _file_rows(path, offsets, rows, dt, every, vouched):
    """(rows of the old file that can be recovered, why none can or ""); ``vouched``:
    {row: a checkpoint's positions} the file's rows must equal."""
    from lc_petsc.io.frames_read import FramesReader
    if not os.path.isfile(path):
        return [], ""
    if not h5py_module().is_hdf5(str(path)):
        return [], "not an HDF5 file"
    try:
        # (its /pinned, /radius, /rest_positions not needed: the new file has the scene's;
        # a frame dataset shorter than /positions: the rows all of them hold)
        with FramesReader(path, statics=False, rows=0) as r:
            return _readable_rows(r, offsets, rows, dt, every, vouched)
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:   # whatever a damaged file raises
        return [], f"unreadable ({str(e).split(' (')[0]})"


def _readable_rows(r, offsets, rows, dt, every, vouched):
    """:func:`_file_rows` of the open :class:`lc_petsc.io.frames_read.FramesReader` ``r``."""
    from lc_petsc.io.frames import offsets_problem
    f = r.f
    if not np.array_equal(f["wisp_offsets"][...], offsets) or f["positions"].shape[1:] != (offsets[-1], 3):
        # a damaged /wisp_offsets is not another scene's: say which it is
        return [], (offsets_problem(f["wisp_offsets"][...], f["positions"].shape[1])
                    or "it has other wisps than the scene")
    for key, want in (("dt", dt), ("every", every)):
        have = f.attrs.get(key)
        if have is None or float(have) != want:
            return [], f"it was written with {key} = {have}, the checkpoint with {want:g}"
    valid = r.valid
    found, agree = [], {}
    for k in range(min(rows, len(valid), f["time"].shape[0])):
        try:        # (row by row: a row that cannot be read is lost, the others are kept)
            x, t = f["positions"][k], r.entries(k)[0]
            if k in vouched:
                agree[k] = np.array_equal(x, vouched[k])
            elif valid[k] and np.isfinite(t) and np.isfinite(x).all() and not r.digest_problem(k, x):
                found.append(k)     # (a row failing its digest: another row's values, lost)
        except (OSError, ValueError, IndexError):   # its positions, time or digest damaged or missing: lost
            continue
    if agree and not any(agree.values()):
        return [], (f"its rows at the checkpoints' frames ({frames_text(agree, every)}) differ from "
                    f"the checkpoints: another run's file, or corrupt there")
    return found, ""


def write_recovered(writer, plan, old_path, offsets, comm):
    """Collective: write the plan's rows 0 .. rows - 1 into the new ``writer`` (rank 0
    reads them from ``old_path`` and the checkpoints, ``offsets`` the global wisp
    offsets; a row that fails to read now is lost).  Returns (rows recovered, every
    row's time, NaN for the lost) on every rank."""
    from lc_petsc.io.checkpoint import read_positions
    nan = np.full((writer.nv, 3), np.nan)
    recovered, times = [], []
    with contextlib.ExitStack() as stack:
        old = None
        if comm.rank == 0 and plan.from_file:
            try:        # gone since the plan: its rows are lost, the collective writes go on
                old = stack.enter_context(h5py_module().File(str(old_path), "r"))
            except OSError:
                old = None
        for k in range(plan.rows):
            t, x = np.nan, nan
            if comm.rank == 0:
                try:
                    if k in plan.from_checkpoints:
                        c = read_positions(plan.from_checkpoints[k], offsets)
                        t, x = c["time"], c["positions"]
                    elif k in plan.from_file and old is not None:
                        t, x = float(old["time"][k]), old["positions"][k]
                except (OSError, KeyError, CheckpointError):
                    t, x = np.nan, nan
            ok = bool(np.isfinite(t))
            writer.write_row(t, x, ok)
            if ok:
                recovered.append(k)
            times.append(t)
    return comm.bcast((recovered, times))

