"""Reading a run's ``frames.h5`` (layout: :mod:`lc_petsc.io.frames`): :class:`FramesReader`,
the one reader object of every reader (:func:`read_frames`, the restart's read-back and
the recovery, the USD export, the previews, the end-of-run check, the scripts).

Opened once per file, it holds what every row's check needs: the rows that hold a frame
(after the chunk index check, before any read: a damaged chunk size crashed libhdf5),
``/time`` and ``/row_digest`` (read once, not once per row).  Rows are read in blocks of
consecutive rows, one HDF5 read per block (:data:`READ_BLOCK_BYTES` at most; a
``/positions`` chunk is one row, so every block is chunk-aligned), and each row of a
block is checked (finite, its digest).  A read that fails names the file's damage:
the dataset and the rows of the chunk (a block that fails is read again row by row to
find the row).
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from typing import NoReturn

import numpy as np

from lc_petsc.io.frames import (_FRAME_DATASETS, _why, index_problem, offsets_problem, row_digest, valid_rows,
                                vertex_digest)
from lc_petsc.io.hdf5 import h5py_module

#: the most bytes of ``/positions`` one read takes (a few rows of a 200K-vertex groom,
#: 4.8 MB each): the readers that stream (USD export, crossing check) stay at a few frames
READ_BLOCK_BYTES = 32 << 20


class FramesDamage(ValueError):
    """A value of ``frames.h5`` that cannot be read or is not what was written: ``what``
    names the dataset and the rows ("/time rows 5-8 (frames 5-8) cannot be read (...)");
    the message adds what to do (``rows_before``: the rows before it may still be read)."""

    def __init__(self, what, rows_before=False):
        more = "the rows before it may still be read, or rerun" if rows_before else "rerun"
        super().__init__(f"{what}: the file is damaged; {more} from a checkpoint")
        self.what = what


def _damaged(what, rows_before=False) -> NoReturn:
    raise FramesDamage(what, rows_before)


def layout_problem(f, rows=None, statics=True):
    """Why the datasets of the open ``frames.h5`` ``f`` do not have a frames file's shapes
    (a frame dataset shorter than ``/positions``: a row with no time or digest), else
    None; ``rows``: only the first ``rows`` rows must be in every frame dataset (a
    restart keeps those and cuts the others; 0: no length checked, the recovery takes
    the rows each holds); ``statics``: also the datasets of one entry
    per vertex (the recovery reads the rows only).  Shapes only, no frame dataset is
    read; the attributes ``every`` and ``dt`` first (:func:`attrs_problem`).  A missing
    ``/positions`` is a KeyError (``/time``: where a reader needs it); a
    dataset whose object header cannot be read is left to the reader that opens it
    (:meth:`FramesReader.dataset` names it)."""
    problem = attrs_problem(f)
    if problem:
        return problem
    pos, every = f["positions"], int(f.attrs.get("every", 1))
    if pos.ndim != 3 or pos.shape[2] != 3:
        off = f.get("wisp_offsets")
        nv = f"{int(off[-1])} vertices" if off is not None and off.ndim == 1 and len(off) else "n_vertices"
        return (f"/positions has shape {pos.shape}, a frames.h5 has (frames, {nv}, 3) (a strands file is a "
                "groom, not a run)")
    n, nv = pos.shape[:2]
    for name in _FRAME_DATASETS[1:]:
        d = f.get(name)
        if d is not None and (d.ndim != 1 or (len(d) != n if rows is None else len(d) < rows)):
            n = n if rows is None else rows
            lacking = f": {rows_text(len(d), n - 1, every)} no /{name} entry" if d.ndim == 1 and len(d) < n else ""
            return f"/{name} has shape {d.shape}, /positions {n} rows{lacking}: the file is damaged"
    for name, shape in (("rest_positions", (nv, 3)), ("pinned", (nv,)), ("radius", (nv,))) if statics else ():
        d = f.get(name)         # (None too where its header cannot be read)
        if d is not None and d.shape != shape:
            return f"/{name} has shape {d.shape}, a frames.h5 of {nv} vertices has {shape}: the file is damaged"
    return None


def attrs_problem(f):
    """Why the root attributes ``every`` and ``dt`` of the open ``frames.h5`` ``f`` are not
    a run's (an integer >= 1, a finite number > 0; a file may lack either), else None:
    every reader numbers its frames by ``every``, the USD export's frame rate is 1 / (dt
    every) (0 ended it in a ZeroDivisionError traceback)."""
    every, dt = f.attrs.get("every"), f.attrs.get("dt")
    if every is not None and not (np.ndim(every) == 0 and np.issubdtype(np.asarray(every).dtype, np.integer)
                                  and every >= 1):
        return f"the attribute every = {every!r} is not an integer >= 1 (row k is frame k * every): the file is damaged"
    if dt is not None and not (np.ndim(dt) == 0 and np.asarray(dt).dtype.kind in "iuf" and np.isfinite(dt)
                               and dt > 0):
        return f"the attribute dt = {dt!r} is not a finite number > 0 (the time step, s): the file is damaged"
    return None


def rows_text(a, b, every):
    """'row 5 (frame 10) has' or 'rows 5-8 (frames 10-16) have'."""
    if a == b:
        return f"row {a} (frame {a * every}) has"
    return f"rows {a}-{b} (frames {a * every}-{b * every}) have"


def order_problem(times, valid, every):
    """Why ``/time`` read as ``times`` is not increasing over the rows that hold a frame
    (``valid``), else None: the readers take a row's time for its frame's (the head's
    motion, the USD time samples)."""
    rows = np.flatnonzero(np.asarray(valid, bool)[:len(times)])
    t = np.asarray(times, float)[rows]
    bad = np.flatnonzero(~(np.diff(t) > 0))
    if not len(bad):
        return None
    a, b = rows[bad[0]], rows[bad[0] + 1]
    return (f"/time rows {a} and {b} (frames {a * every}, {b * every}) are not increasing ({t[bad[0]]:.9g} s, "
            f"then {t[bad[0] + 1]:.9g} s): not the times the run wrote, the file is damaged")


class FramesReader:
    """``frames.h5`` at ``path`` opened read-only, for reading (a context manager; ``f``:
    the h5py ``File``).  A folder (a run's output folder given for its ``frames.h5``) is a
    ValueError saying which file to give: libhdf5's own error was a multi-line dump ending
    in 'Is a directory'.  Errors of :meth:`dataset`, :meth:`rows` and :meth:`table` do not
    name the file (the caller does, :func:`naming`); :attr:`valid`'s does.  ``statics``:
    :attr:`valid` checks the shapes of ``/rest_positions``, ``/pinned`` and ``/radius``
    too (off for a reader of the rows alone); ``rows``: only the first ``rows`` rows
    must be in every frame dataset (:func:`layout_problem`)."""

    def __init__(self, path, statics=True, rows=None):
        path = str(path)
        if os.path.isdir(path):
            inside = os.path.join(path, "frames.h5")
            hint = f"; give {inside}" if os.path.isfile(inside) else ""
            raise ValueError(f"a folder, not a frames.h5 file{hint}")
        self.path = path
        self.f = h5py_module().File(path, "r")
        self._index: tuple | None = None      # (index_problem's answer,)
        self._valid = None
        self._table: tuple | str | None = None
        self._order = None          # order_problem of /time
        self._offsets = None
        # the static datasets' shapes checked too (the recovery salvages the rows of a
        # file whose /pinned or /radius is damaged: the new file takes them from the scene)
        self.statics = statics
        self.kept = rows            # layout_problem's rows: a restart's kept rows

    def close(self):
        """Close the file."""
        self.f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def every(self) -> int:
        """Row k is simulation frame k * every."""
        return int(self.f.attrs.get("every", 1))

    def index_problem(self):
        """:func:`lc_petsc.io.frames.index_problem` of the file, looked up once."""
        if self._index is None:
            self._index = (index_problem(self.f),)
        return self._index[0]

    @property
    def valid(self):
        """Which rows hold a frame (bool (n_frames,), :func:`lc_petsc.io.frames.valid_rows`);
        the first access checks the chunk index (a ValueError naming the file and the
        damage) and the datasets' shapes (:func:`layout_problem`, a ValueError naming the
        dataset), before any row is read."""
        if self._valid is None:
            problem = self.index_problem()
            if problem:
                raise ValueError(f"{self.f.filename}: {problem}; the rows before it may still be read, or rerun "
                                 "from a checkpoint")
            problem = layout_problem(self.f, self.kept, statics=self.statics)
            if problem:
                raise ValueError(problem)
            self._valid = valid_rows(self.f, check=False)
        return self._valid

    def dataset(self, name, rows=None):
        """Dataset ``name``, whole, or its first ``rows`` rows; one that cannot be read (a
        chunk failing its checksum) is a :class:`FramesDamage` naming the dataset and,
        for a frame dataset, the rows of the damaged chunk."""
        try:
            d = self.f[name]
        except KeyError as e:       # h5py's error for a damaged object header too
            if name not in self.f:
                raise
            _damaged(f"/{name} cannot be opened ({_why(e.args[0] if e.args else e)})")
        sel = np.s_[...] if rows is None else np.s_[:rows]
        try:
            return d[sel]
        except (OSError, ValueError) as e:
            why = _why(e)
        n = len(d) if rows is None else min(rows, len(d))
        if d.chunks and name in _FRAME_DATASETS:
            step = d.chunks[0]
            for a in range(0, n, step):            # which chunk: the rows it holds
                try:
                    d[a:a + step]
                except (OSError, ValueError):
                    b = min(a + step, len(d)) - 1
                    _damaged(f"/{name} rows {a}-{b} (frames {a * self.every}-{b * self.every}) "
                             f"cannot be read ({why})")
        _damaged(f"/{name} cannot be read ({why})")

    @property
    def offsets(self):
        """``/wisp_offsets`` (int64 (n_wisps + 1,)), read once and checked
        (:func:`lc_petsc.io.frames.offsets_problem`: integers, 0, increasing, ...,
        the vertex count of ``/positions``, and the wisps of ``/polylines`` where the
        file has it): a damaged one is a ValueError naming the dataset and its first bad
        entry or wisp (read as it was, one made the crossing check allocate wisps of
        2**60 vertices, one moved between its neighbours split the wisps elsewhere in
        every reader's strains, crossings and USD curves)."""
        if self._offsets is None:
            self.valid          # (the shapes first: their error names them)
            off = self.dataset("wisp_offsets")
            problem = offsets_problem(off, self.f["positions"].shape[1],
                                      self.dataset("polylines") if "polylines" in self.f else None)
            if problem:
                raise ValueError(problem)
            self._offsets = np.asarray(off, np.int64)
        return self._offsets

    def table(self):
        """(``/time`` float, ``/row_digest`` or None), read once (after the chunk index
        check).  A chunk failing its checksum is a :class:`FramesDamage` naming the
        dataset and its rows (kept, raised again: finding the chunk reads every chunk)."""
        if self._table is None:
            valid = self.valid
            try:
                self._table = (np.asarray(self.dataset("time"), float),
                               self.dataset("row_digest") if "row_digest" in self.f else None)
            except FramesDamage as e:
                self._table = e.what
            else:
                self._order = order_problem(self._table[0], valid, self.every)
        if isinstance(self._table, str):
            raise FramesDamage(self._table)
        return self._table

    @property
    def times(self):
        """``/time`` (s, one per row), :meth:`table`; a ValueError where it is not
        increasing over the rows that hold a frame (:func:`order_problem`)."""
        times = self.table()[0]
        if self._order:
            raise ValueError(f"{self._order}; rerun from a checkpoint")
        return times

    def entries(self, k):
        """(time, digest or None) of row ``k``: from :meth:`table`, or, where a chunk of it
        fails its checksum, the row's own (a restart keeps, a recovery salvages the rows
        of the intact chunks); a row whose own entries cannot be read is the table's
        :class:`FramesDamage`, naming the damaged chunk."""
        try:
            times, digests = self.table()
            return times[k], None if digests is None else digests[k]
        except FramesDamage as damaged:
            try:
                return self.f["time"][k], self.f["row_digest"][k] if "row_digest" in self.f else None
            except (OSError, ValueError):
                raise damaged from None

    def digest_problem(self, k, x):
        """Why row ``k``, read as ``x``, is not the row written (its ``/row_digest`` entry
        differs), else None; a file without ``/row_digest`` (written before it) is not
        checked."""
        if "row_digest" not in self.f:
            return None
        t, stored = self.entries(k)
        if int(stored) == row_digest([vertex_digest(x, 0)], k, float(t)):
            return None
        return (f"/positions row {k} (frame {k * self.every}) does not match its /row_digest: another row's "
                "values (a damaged chunk index), or its time in /time is another row's; the file is damaged")

    def check(self, k, x):
        """``x``, row ``k`` as read, when it is the row written: a row that holds a frame is
        finite as written (the integrator stops on a non-finite position), so a non-finite
        value is damage (a chunk missing from a damaged chunk index reads as the fill
        value NaN without any error from libhdf5); then its digest.  Else a
        :class:`FramesDamage` naming the row and the frame."""
        where = f"/positions row {k} (frame {k * self.every})"
        if not np.isfinite(x).all():
            _damaged(f"{where} reads as NaN or inf at {int((~np.isfinite(x).all(axis=1)).sum())} vertices "
                     "(a chunk missing from its index reads as NaN)", rows_before=True)
        problem = self.digest_problem(k, x)
        if problem:
            raise FramesDamage(problem.removesuffix("; the file is damaged"), rows_before=True)
        return x

    def row(self, k):
        """Row ``k`` of ``/positions`` (n_vertices, 3), checked (:meth:`check`)."""
        return next(self.rows([k]))[1]

    def rows(self, ks, check=True):
        """(k, positions of row k) for the rows ``ks`` in ascending order (each once), read
        in blocks of consecutive rows, one read per block; ``check``: each row that holds
        a frame (:attr:`valid`) is checked (:meth:`check`); a row that holds none is as
        stored (NaN)."""
        valid = self.valid
        if check and "time" in self.f:
            try:
                self.times      # (increasing)
            except FramesDamage:
                pass            # a chunk of /time: each row's own entries (entries)
        for a, b in self._blocks(ks):
            block = self._read(a, b)
            for k in range(a, b):
                x = block[k - a]
                yield k, self.check(k, x) if check and valid[k] else x

    def _blocks(self, ks):
        """[a, b) runs of consecutive rows of ``ks``, at most :data:`READ_BLOCK_BYTES` each."""
        pos = self.f["positions"]
        cap = max(1, READ_BLOCK_BYTES // max(1, int(np.prod(pos.shape[1:])) * pos.dtype.itemsize))
        out: list = []
        for k in sorted({int(k) for k in np.atleast_1d(ks)}):
            if not 0 <= k < len(pos):
                raise IndexError(f"row {k} of /positions: the file has rows 0-{len(pos) - 1}")
            if out and out[-1][1] == k and k - out[-1][0] < cap:
                out[-1][1] = k + 1
            else:
                out.append([k, k + 1])
        return out

    def _read(self, a, b):
        """Rows a .. b - 1 of ``/positions`` (float), one read; a failure is read again row
        by row, to name the row."""
        pos = self.f["positions"]
        try:
            return np.asarray(pos[a:b], float)
        except (OSError, ValueError) as e:
            why = _why(e)
        for k in range(a, b):
            try:
                pos[k]
            except (OSError, ValueError) as e:
                why = _why(e)
                _damaged(f"/positions row {k} (frame {k * self.every}) cannot be read ({why})", rows_before=True)
        _damaged(f"/positions rows {a}-{b - 1} cannot be read ({why})", rows_before=True)


@contextmanager
def naming(path):
    """Reads of the frames file at ``path`` inside: a damaged value's ValueError starts
    with the path (once)."""
    try:
        yield
    except ValueError as e:
        if str(e).startswith(f"{path}: "):
            raise
        raise ValueError(f"{path}: {e}") from None


def read_frames(path, frames=None):
    """Read ``frames.h5`` (serially) into a dict of arrays; ``frames`` selects rows of
    ``/positions``, ``/time`` and ``frame_valid`` (:func:`lc_petsc.io.frames.valid_rows`;
    default: all): row indices, or one row index (its positions (1, n, 3), its time and
    validity numbers).  The rows are read in blocks and each that holds a frame is checked
    against its digest (:meth:`FramesReader.rows`); a damaged one is a ValueError naming
    the file, the dataset and the row."""
    with FramesReader(path) as r, naming(r.f.filename):
        valid = r.valid
        out = {"wisp_offsets": r.offsets} | {k: r.dataset(k) for k in ("rest_positions", "pinned")}
        ks = np.arange(len(valid))[slice(None) if frames is None else np.asarray(frames)]
        out["time"], out["frame_valid"] = r.times[ks], valid[ks]     # (numbers for one row given as one)
        got = dict(r.rows(ks))
        shape = r.f["positions"].shape[1:]
        out["positions"] = np.stack([got[k] for k in np.atleast_1d(ks).tolist()]) if got \
            else np.zeros((0,) + shape)
        out["attrs"] = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in r.f.attrs.items()}
    return out
