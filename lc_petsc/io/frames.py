"""``frames.h5`` (DESIGN section 3), written collectively: every rank writes the rows of
the vertices it owns, nothing is gathered.

Layout (plain h5py reads it):

* ``/positions`` float64 (n_frames, n_vertices, 3), global vertex order, cm;
* ``/time`` float64 (n_frames,), s;
* ``/wisp_offsets`` int64 (n_wisps + 1,);
* ``/rest_positions`` float64 (n_vertices, 3); ``/pinned`` bool (n_vertices,);
* extension: ``/polylines`` int64 (2 n_wisps + n_vertices,), the XDMF "Mixed" topology
  of the wisps (for every wisp: 2 = polyline, its vertex count, its vertex indices),
  which ``frames.xdmf`` points at;
* ``/row_digest`` uint64 (n_frames,): each row's digest (:func:`row_digest`, over its
  positions' bits, its row number and its time), written with the row and checked by
  every read of a row (:meth:`lc_petsc.io.frames_read.FramesReader.rows`) and by a
  restart; files written before it (2026-12-07) have none and are read unchecked;
* ``/frame_valid`` bool (n_frames,), only in a file that continued a run whose own
  ``frames.h5`` was lost (``--restart ... --force``, :mod:`lc_petsc.io.recovery`):
  False marks a row that could not be recovered, its ``/positions`` and ``/time`` are
  NaN; a file without it has every row valid (:func:`valid_rows`);
* root attributes: ``config`` (the resolved config as JSON), ``terms``, ``dt``,
  ``every`` (frame ``k`` of the file is simulation frame ``k * every``), ``frames``
  (simulation frames planned), ``ranks``, ``format``.

Every dataset is chunked with a Fletcher-32 checksum per chunk, and the file is in the
HDF5 1.8 format (``libver`` v108: checksums on the superblock and object headers), so
a damaged value is a read error ("data error detected by Fletcher32 checksum") for
every reader, never a wrong number; a restart reads back every value it keeps
(:func:`resumable_problem`).  Files written before that have no checksums
(:func:`has_checksums`) and still restart, unverified.

Frame 0 of the file is the initial state (t = 0, after the scene's perturbation).
With an MPI-enabled h5py (Debian's, under mpiexec) the file is opened with the ``mpio``
driver on the simulator's communicator and every write is collective (ranks without
vertices take part with an empty selection).  The frame datasets are chunked one frame
per chunk and extendable (``maxshape`` None along frames): they start empty and grow
by one row per frame written (the chunks of the new row are allocated then), so the
file's size follows what the run has written, not the planned frame count.  A restart
cuts the file to the rows it keeps when it reopens it.  (Growing ahead and shrinking
on close was tried: shrinking a grown dataset hangs H5Fclose under the mpio driver of
Debian's HDF5 1.10 on 2 ranks.)  The metadata is flushed at every checkpoint, so a run
killed later leaves a file that is readable up to that point at least.  Before every
frame the free space is checked (:mod:`lc_petsc.io.disk`: libhdf5 does not survive a
full disk), collectively.
"""

from __future__ import annotations

import json
import os
import re

import numpy as np

from lc_petsc.io.hdf5 import collective_file_options, collective_transfer, h5py_module, is_parallel

FORMAT = "lc_petsc frames 1"
#: the datasets with a row per frame
_FRAME_DATASETS = ("positions", "time", "frame_valid", "row_digest")

_MUL1, _MUL2, _GOLDEN = (np.array([c], np.uint64) for c in
                         (0xBF58476D1CE4E5B9, 0x94D049BB133111EB, 0x9E3779B97F4A7C15))


def _mix(z):
    """splitmix64's finaliser on a uint64 array (wrapping): every input bit flips about
    half the output bits, so a sum of mixed values is a digest."""
    z = (z ^ (z >> np.uint64(30))) * _MUL1
    z = (z ^ (z >> np.uint64(27))) * _MUL2
    return z ^ (z >> np.uint64(31))


def vertex_digest(x, first_vertex) -> int:
    """This rank's part of a row's digest: the wrapping uint64 sum over its vertices
    (``x`` (n, 3), the first of global index ``first_vertex``) of a hash of the bits of
    the vertex's coordinates and its global index.  A sum, so the row's digest is the
    same whatever the ranks' shares (and a restart on another rank count goes on with
    the same digests)."""
    bits = np.ascontiguousarray(x, np.float64).reshape(-1, 3).view(np.uint64)
    h = _mix((np.arange(len(bits), dtype=np.uint64) + np.uint64(first_vertex)) * _GOLDEN)
    for c in range(3):
        h = _mix(h ^ bits[:, c])
    return int(h.sum(dtype=np.uint64))


def row_digest(parts, row, t) -> int:
    """The digest of frame row ``row``, at time ``t``, from every rank's
    :func:`vertex_digest` (``parts``): the row number and the time are in it, so a row
    read in another row's place (two chunk index entries exchanged: libhdf5 reads each
    row's chunk for the other, their Fletcher-32 checksums pass) fails it, and so does
    /time's chunk in another's place."""
    total = np.array([sum(parts) % (1 << 64)], np.uint64)
    tb = np.array([t], np.float64).view(np.uint64)
    return int(_mix(total ^ _mix(tb ^ _mix(np.array([row], np.uint64) * _GOLDEN)))[0])


def write_rows(dset, start, data, dxpl):
    """Write ``data`` at ``start`` (a corner) of ``dset`` through the low-level API;
    collective when ``dxpl`` says so, an empty ``data`` takes part with an empty
    selection (h5py's high-level API would skip the call and deadlock the others)."""
    h5py = h5py_module()
    data = np.ascontiguousarray(data, dtype=dset.dtype)
    fs = dset.id.get_space()
    if data.size:
        count = data.shape + tuple(dset.shape[len(data.shape):])
        fs.select_hyperslab(tuple(start) + (0,) * (len(dset.shape) - len(start)), count)
        ms = h5py.h5s.create_simple(data.shape)
    else:
        fs.select_none()
        ms = h5py.h5s.create_simple((1,))
        ms.select_none()
        data = np.zeros(1, dtype=dset.dtype)
    dset.id.write(ms, fs, data, dxpl=dxpl)


def frame_bytes(n_vertices) -> int:
    """Bytes one frame adds to ``frames.h5`` (positions, time and digest)."""
    return 24 * int(n_vertices) + 16


def static_bytes(n_wisps, n_vertices) -> int:
    """Bytes of ``frames.h5``'s datasets written once (offsets, rest state, radii,
    topology)."""
    nv, nw = int(n_vertices), int(n_wisps)
    return 8 * (nw + 1) + 33 * nv + 8 * (2 * nw + nv) + 64 * 1024


def _h5_error(path, e):
    """OutputError naming the file and libhdf5's reason (errno text when it has one)."""
    from lc_petsc.io.disk import OutputError
    text = str(e)
    m = re.search(r"error message = '([^']*)'", text)
    why = m.group(1) if m else text.split(" (", 1)[0] if text else type(e).__name__
    return OutputError(f"{path}: {why}", hdf5_broken=True)


def resumable_problem(path, n_wisps, n_vertices, rows, dt=None, every=None, checkpoint_row=None,
                      offsets=None):
    """Why ``path`` cannot be appended to by a restart needing its first ``rows`` frame
    rows, or None; ``dt`` and ``every`` (the run's time.dt and output.every) must be the
    file's attributes, where it has them (a file of another run with the same counts
    was taken over); ``checkpoint_row`` (row, positions (n_vertices, 3)): the row the
    checkpoint vouches for must hold its positions bit for bit; ``offsets``: the scene's
    global wisp offsets, which ``/wisp_offsets`` must equal.  Every value the restart
    keeps is read back (:func:`_kept_problem`), so a file with checksums whose kept rows
    are damaged is refused here, before anything is changed.  Serial and read-only
    (rank 0, before anything is changed)."""
    h5py = h5py_module()
    path = str(path)
    if not os.path.isfile(path):
        return f"{path}: the run's frames file is missing, --restart appends to it"
    if not h5py.is_hdf5(path):
        return f"{path}: not an HDF5 file, cannot append the restarted frames to it"
    from lc_petsc.io.frames_read import FramesReader
    try:
        with FramesReader(path, rows=rows) as r:     # (the rows after the kept ones are rewritten)
            return _layout_problem(r.f, path, n_wisps, n_vertices, rows, dt, every) or \
                _kept_problem(r, path, rows, offsets) or _row_problem(r.f, path, checkpoint_row)
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
        # whatever h5py raises on a damaged file (a damaged datatype: ValueError)
        return f"{path}: unreadable, truncated or damaged HDF5 file ({_why(e)})"


def _layout_problem(f, path, n_wisps, n_vertices, rows, dt, every):
    """:func:`resumable_problem`'s datasets, shapes, rows and attributes."""
    h5py = h5py_module()
    for k in ("positions", "time", "wisp_offsets"):
        if not isinstance(f.get(k), h5py.Dataset):
            return f"{path}: no dataset /{k}, not an lc_petsc frames file"
    pos = f["positions"]
    if pos.ndim != 3 or pos.shape[1:] != (n_vertices, 3) or f["wisp_offsets"].shape != (n_wisps + 1,):
        return (f"{path}: has {f['wisp_offsets'].shape[0] - 1} wisps and /positions "
                f"{pos.shape}, the scene {n_wisps} wisps and {n_vertices} vertices")
    if pos.maxshape[0] is not None or f["time"].maxshape[0] is not None:
        return f"{path}: /positions or /time is not extendable, cannot append to it"
    if pos.shape[0] < rows:
        return (f"{path}: holds {pos.shape[0]} frame row(s), the checkpoint needs the first "
                f"{rows}; it does not belong to this checkpoint's run")
    from lc_petsc.io.frames_read import layout_problem
    problem = layout_problem(f, rows)       # the kept rows' time and digest, the rest positions
    if problem:
        return f"{path}: {problem}"
    for key, want in (("dt", dt), ("every", every)):
        have = f.attrs.get(key)
        if want is not None and have is not None and float(have) != float(want):
            return (f"{path}: written with {key} = {float(have):g}, this run has {float(want):g}; "
                    f"it does not belong to this checkpoint's run")
    return None


def has_checksums(path) -> bool:
    """Whether ``frames.h5`` at ``path`` (readable) was written with Fletcher-32 checksums
    (files written before them have none: a damaged value there reads as a wrong number)."""
    with h5py_module().File(str(path), "r") as f:
        return bool(f["positions"].fletcher32)


def offsets_problem(off, n_vertices, polylines=None):
    """Why ``off`` is not a valid ``/wisp_offsets`` for ``n_vertices`` vertices (integers,
    0 first, increasing, ``n_vertices`` last; the first entry that is not named), or None.
    ``polylines``: the file's ``/polylines`` as read (written with the offsets: per wisp
    2, its vertex count, its vertex indices), whose wisps the offsets must give (an offset
    moved within its neighbours is still increasing)."""
    off = np.asarray(off)
    want = f"0, increasing, ..., {n_vertices} (the vertex count of /positions)"
    if off.ndim != 1 or len(off) < 2 or off.dtype.kind not in "iu":
        return f"/wisp_offsets has shape {off.shape} and type {off.dtype}, a frames.h5 has {want}: the file is damaged"
    bad = np.flatnonzero(np.diff(off) <= 0)
    for wrong, what in ((off[0] != 0, f"entry 0 is {off[0]}"),
                        (len(bad), lambda: f"entry {bad[0] + 1} is {off[bad[0] + 1]} after {off[bad[0]]}"),
                        (off[-1] != n_vertices, f"the last entry is {off[-1]}")):
        if wrong:
            return f"/wisp_offsets is not {want}: {what if isinstance(what, str) else what()}; the file is damaged"
    if polylines is None:
        return None
    poly, sizes = np.asarray(polylines), np.diff(off)
    heads = off[:-1] + 2 * np.arange(len(sizes))        # each wisp's entry 2 in /polylines
    if poly.shape != (2 * len(sizes) + n_vertices,):
        return (f"/polylines has shape {poly.shape}, the {len(sizes)} wisps of /wisp_offsets and {n_vertices} "
                f"vertices have ({2 * len(sizes) + n_vertices},): the file is damaged")
    vertex = np.ones(len(poly), bool)
    vertex[heads] = vertex[heads + 1] = False
    differ = (poly[heads] != 2) | (poly[heads + 1] != sizes)
    if differ.any() or not np.array_equal(poly[vertex], np.arange(n_vertices)):
        w = int(np.flatnonzero(differ)[0]) if differ.any() else \
            int(np.searchsorted(off, np.flatnonzero(poly[vertex] != np.arange(n_vertices))[0], side="right") - 1)
        return (f"/wisp_offsets gives wisp {w} vertices {off[w]}-{off[w + 1] - 1}, /polylines (the wisps written "
                f"with it) does not: the file is damaged")
    return None


def _why(e):
    """libhdf5's reason in an h5py error: 'data error detected by Fletcher32 checksum'."""
    text = str(e)
    inner = re.search(r"\(([^()]*)\)\s*$", text)
    return inner.group(1) if inner else text or type(e).__name__


def _fill(dtype):
    """The fill value of a dataset of ``dtype``: what a read of a chunk missing from the
    index returns (NaN, -1; a bool has none), never a value the writer writes."""
    dtype = np.dtype(dtype)
    return np.array(np.nan if dtype.kind == "f" else -1 if dtype.kind == "i" else False, dtype)


def _holds_fill(a, valid=None):
    """Whether ``a`` (a read of a frames.h5 dataset; ``valid``: of its rows, or of its one
    row, those that hold a frame, default all) holds its fill value (a file written
    before the fill values: zeros, not found)."""
    a = np.asarray(a)
    if valid is not None:
        a = a[np.asarray(valid, bool)] if np.ndim(valid) else a if valid else a[:0]
    return bool(np.isnan(a).any()) if a.dtype.kind == "f" else bool((a < 0).any()) if a.dtype.kind == "i" \
        else False


def _kept_problem(r, path, rows, offsets):
    """:func:`resumable_problem`'s read-back (``r``: the file's
    :class:`lc_petsc.io.frames_read.FramesReader`) of every value the restart keeps: the
    static datasets and the first ``rows`` rows of the frame datasets.  A read error (a
    value failing its checksum, a damaged chunk index) names the dataset and the rows of
    the chunk, before the restart changes anything (it failed in the frame loop, after the
    outputs were removed, on every try; or it kept a damaged row and appended to it)."""
    from lc_petsc.io.frames_read import FramesDamage, order_problem
    f = r.f
    try:        # the restart rewrites the attributes: damaged storage failed it there (exit 3)
        for obj in [f] + [f[k] for k in f]:
            dict(obj.attrs)
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
        return f"{path}: its attributes cannot be read ({_why(e)}): the file is damaged"
    problem = r.index_problem()      # before a read: a damaged chunk size crashed libhdf5
    if problem:
        return f"{path}: {problem}"
    frame_dsets = [k for k in _FRAME_DATASETS if k in f]
    static = [k for k in ("wisp_offsets", "rest_positions", "pinned", "polylines", "radius") if k in f]
    valid = r.valid
    fill = ("{}: read as the fill value (NaN or -1), its chunk missing from the chunk index (which has "
            "no checksum): the file is damaged")
    try:
        for name in static + frame_dsets[1:]:
            a = r.dataset(name, None if name in static else rows)
            if _holds_fill(a, valid[:rows] if name in frame_dsets else None):
                return f"{path}: " + fill.format(f"/{name}" + (f" rows 0-{rows - 1}" if name in frame_dsets else ""))
            problem = name == "time" and order_problem(a, valid, r.every)
            if problem:
                return f"{path}: {problem}"
            problem = name == "wisp_offsets" and _offsets_differ(
                a, f["positions"].shape[1], offsets, r.dataset("polylines") if "polylines" in f else None)
            if problem:
                return f"{path}: {problem}"
        for k, x in r.rows(range(rows), check=False):      # in blocks, each row checked here
            if _holds_fill(x, valid[k]):
                return f"{path}: " + fill.format(f"/positions row {k} (frame {k * r.every})")
            problem = valid[k] and r.digest_problem(k, x)
            if problem:
                return f"{path}: {problem}"
    except FramesDamage as e:
        return f"{path}: {e.what}: the file is damaged"
    return None


def _offsets_differ(a, n_vertices, offsets, polylines=None):
    """Why ``/wisp_offsets`` read as ``a`` is damaged (``polylines``: the file's
    ``/polylines``, :func:`offsets_problem`) or not the scene's ``offsets`` (None: not
    checked), else None."""
    problem = offsets_problem(a, n_vertices, polylines)
    if problem is None and offsets is not None and not np.array_equal(a, offsets):
        problem = ("/wisp_offsets differs from the scene's wisp sizes: the file is damaged, "
                   "or another scene's with the same counts")
    return problem


def _row_problem(f, path, checkpoint_row):
    """:func:`resumable_problem`'s check of the row the checkpoint vouches for."""
    if checkpoint_row is None:
        return None
    row, x = checkpoint_row
    if valid_rows(f, check=False)[row] and not np.array_equal(f["positions"][row], x):
        return (f"{path}: row {row} differs from the checkpoint's positions at that frame: "
                f"corrupt, or it does not belong to this checkpoint's run")
    return None


def index_problem(f):
    """Why the chunk index of a frame dataset (``/positions``, ``/time``,
    ``/frame_valid``, ``/row_digest``) of the open ``frames.h5`` ``f`` cannot be trusted, else None.

    The HDF5 1.8 format has no checksum on a chunk index (a v1 B-tree), and the
    Fletcher-32 checksum of a chunk covers its bytes, not which row it is: a damaged key
    (a chunk's row offset) makes libhdf5 read another row's chunk for a row, whose
    checksum passes, and the row it belonged to reads as the fill value (NaN); a damaged
    chunk size made libhdf5 crash (a segfault) reading it.  So every chunk is looked up
    in the index (``H5Dget_chunk_info_by_coord``) before any is read: each must be found,
    of its stored size (the chunk's bytes + 4 for the checksum), not filtered out,
    inside the file and used by no other chunk.  One changed key is always found: only
    its own chunk had the row it named, so that row is then missing.  A key byte
    libhdf5 does not use (a row offset is divided by the chunk's extent, so the low bits
    of the offset along the vertex axis, below one chunk, are dropped) changes nothing
    and is not seen (docs/design_notes.md, "Checksums").  Two entries exchanged (each
    row then has one chunk, another row's) pass here: the rows' ``/row_digest`` finds
    them when a row is read (:meth:`lc_petsc.io.frames_read.FramesReader.check`)."""
    import itertools
    size = f.id.get_filesize()
    every = int(f.attrs.get("every", 1))
    for name in _FRAME_DATASETS:
        d = f.get(name)
        if d is None or d.chunks is None or 0 in d.shape:
            continue
        want = int(np.prod(d.chunks)) * d.dtype.itemsize + (4 if d.fletcher32 else 0)
        seen = {}
        for at in itertools.product(*(range(0, n, c) for n, c in zip(d.shape, d.chunks))):
            info = d.id.get_chunk_info_by_coord(at)
            where = f"/{name} row {at[0]} (frame {at[0] * every})" if d.chunks[0] == 1 \
                else f"/{name} chunk at {at}"
            if info.byte_offset is None:
                why = "its chunk is missing from the chunk index (a read returns the fill value, NaN)"
            elif info.size != want or info.filter_mask != 0 or info.byte_offset + info.size > size:
                why = (f"its chunk index entry is damaged (stored size {info.size} bytes, not {want}; filter "
                       f"mask {info.filter_mask}; at byte {info.byte_offset} of {size})")
            elif info.byte_offset in seen:
                why = (f"its chunk index entry points at the chunk of {seen[info.byte_offset]} (a read "
                       "returns that row's values)")
            else:
                seen[info.byte_offset] = where
                continue
            return (f"{where}: {why}: the file's chunk index (which has no checksum in the HDF5 1.8 "
                    "format) is damaged")
    return None


def valid_rows(f, check=True):
    """Which rows of the open ``frames.h5`` ``f`` hold a frame (bool (n_frames,)):
    ``/frame_valid`` where the file has it, else every row.  Every reader asks first:
    ``check`` (not the writer's resume, whose file the restart checked) raises a
    ValueError naming the damage when the chunk index cannot be trusted
    (:func:`index_problem`)."""
    problem = index_problem(f) if check else None
    if problem:
        raise ValueError(f"{f.filename}: {problem}; the rows before it may still be read, or rerun "
                         "from a checkpoint")
    n = f["positions"].shape[0]
    if "frame_valid" in f:
        return np.asarray(f["frame_valid"][:n], bool)
    return np.ones(n, bool)


class FramesWriter:
    """Collective writer of one run's ``frames.h5``.

    ``comm``: the simulator's mpi4py communicator; ``first_vertex``/``positions`` of
    this rank's vertices; ``first_wisp``/``local_offsets`` of this rank's wisps;
    ``n_out``: the planned number of frame rows (sizes the chunks; the datasets grow by one
    row per frame written, nothing is preallocated); ``track_valid``: a new file gets
    ``/frame_valid`` (a recovery writes rows that were lost, :meth:`write_row`).
    Every h5py failure is an :class:`lc_petsc.io.disk.OutputError` naming the file;
    after one, :attr:`broken` is set and the file must not be closed (libhdf5 would
    crash): the caller stops the run.
    """

    def __init__(self, path, comm, *, n_wisps, n_vertices, first_wisp, first_vertex,
                 local_offsets, rest_positions, pinned, n_out, attrs, resume_rows=None,
                 radius=None, track_valid=False):
        self.comm, self.path = comm, str(path)
        self.folder = os.path.dirname(os.path.abspath(self.path))
        self.parallel = is_parallel()
        if comm.size > 1 and not self.parallel:
            raise RuntimeError("frames.h5 with several ranks needs an MPI-enabled h5py "
                               "(Debian's python3-h5py-mpi, run under mpiexec)")
        self.nv, self.v0 = int(n_vertices), int(first_vertex)
        self.nv_local = len(rest_positions)
        self.n_out, self.written, self.capacity = int(n_out), 0, 0
        self.f, self.broken = None, False
        self.times_kept = []           # times of the frames kept from before a restart
        self.valid = None              # /frame_valid, where the file has one
        self.digest = None             # /row_digest, where the file has one (not before 2026-12-07)
        self.rows_valid = []           # whether each row kept or written holds a frame (rank 0)
        # no chunk cache: a frame goes to the file when written, so the space checked
        # before the write is the space it takes
        kw = collective_file_options(comm)
        if not self.parallel:          # (mpio writes go to the file, no cache)
            kw["rdcc_nbytes"] = 0
        self._dxpl = collective_transfer()
        try:
            if resume_rows is not None:
                self._resume(kw, n_wisps, int(resume_rows), attrs)
            else:
                self._create(kw, n_wisps, first_wisp, local_offsets, rest_positions, pinned, attrs,
                             radius, track_valid)
        except (OSError, RuntimeError, KeyError) as e:
            self.broken = self.f is not None
            err = _h5_error(self.path, e)
            err.hdf5_broken = self.broken
            raise err from None

    def _create(self, kw, n_wisps, first_wisp, local_offsets, rest_positions, pinned, attrs,
                radius=None, track_valid=False):
        h5py = h5py_module()
        comm = self.comm
        # the HDF5 1.8 format: checksums on the superblock and object headers (1.10's, v3
        # superblock, also on the chunk indexes, but a killed writer leaves its file
        # unopenable without h5clear: "file is already open for write")
        self.f = f = h5py.File(self.path, "w", libver=("v108", "latest"), **kw)
        nv = self.nv
        # frame datasets: one frame per chunk (at most 2**16 vertices), empty, extendable
        self.positions = self._dataset("positions", (0, nv, 3), np.float64,
                                       maxshape=(None, nv, 3), chunks=(1, max(1, min(nv, 1 << 16)), 3))
        self.time = self._dataset("time", (0,), np.float64, maxshape=(None,),
                                  chunks=(max(1, min(self.n_out, 4096)),))
        self.digest = self._dataset("row_digest", (0,), np.uint64, maxshape=(None,),
                                    chunks=(max(1, min(self.n_out, 4096)),))
        if track_valid:
            self.valid = self._dataset("frame_valid", (0,), np.bool_, maxshape=(None,),
                                       chunks=(max(1, min(self.n_out, 4096)),))
        offs = self._dataset("wisp_offsets", (n_wisps + 1,), np.int64)
        rest = self._dataset("rest_positions", (nv, 3), np.float64)
        pin = self._dataset("pinned", (nv,), np.bool_)
        poly = self._dataset("polylines", (2 * n_wisps + nv,), np.int64)
        # static data: each rank its own rows
        lo = np.asarray(local_offsets, np.int64)
        nw_local = len(lo) - 1
        self._write(offs, (first_wisp,), self.v0 + lo[:-1])
        self._write(offs, (n_wisps,), np.array([nv], np.int64) if comm.rank == 0 else np.zeros(0, np.int64))
        self._write(rest, (self.v0, 0), np.asarray(rest_positions, np.float64))
        self._write(pin, (self.v0,), np.asarray(pinned, np.bool_))
        if radius is not None:         # the strands' radii, for exports (USD widths)
            rad = self._dataset("radius", (nv,), np.float64)
            self._write(rad, (self.v0,), np.asarray(radius, np.float64))
        parts = []
        for w in range(nw_local):
            n = int(lo[w + 1] - lo[w])
            parts.append(np.concatenate([[2, n], self.v0 + lo[w] + np.arange(n)]))
        self._write(poly, (2 * first_wisp + self.v0,),
                    np.concatenate(parts).astype(np.int64) if parts else np.zeros(0, np.int64))
        for k, v in attrs.items():             # collective: the same values on every rank
            f.attrs[k] = json.dumps(v) if isinstance(v, (dict, list, tuple)) else v
        f.attrs["format"] = FORMAT
        f.attrs["ranks"] = comm.size
        self.positions.attrs["units"] = "cm"
        self.time.attrs["units"] = "s"

    def _resume(self, kw, n_wisps, rows, attrs):
        """Reopen an existing ``frames.h5`` (restart): keep its first ``rows`` frames,
        write the next frame at row ``rows`` (later rows are overwritten).  A file that
        does not fit is a ValueError (:func:`resumable_problem` checks it beforehand)."""
        h5py = h5py_module()
        try:
            self.f = f = h5py.File(self.path, "r+", **kw)
        except (OSError, FileNotFoundError) as e:
            raise ValueError(f"{self.path}: cannot reopen the run's frames file to append to it "
                             f"({e}); restart with --out naming the folder of the checkpointed run") from None
        try:
            self.positions, self.time = f["positions"], f["time"]
            have = self.positions.shape[0]
            if self.positions.shape[1] != self.nv or f["wisp_offsets"].shape[0] != n_wisps + 1:
                raise ValueError(f"{self.path}: has {f['wisp_offsets'].shape[0] - 1} wisps and "
                                 f"{self.positions.shape[1]} vertices, the scene {n_wisps} and {self.nv}")
            if have < rows:
                raise ValueError(f"{self.path}: holds {have} frame row(s), the checkpoint needs the "
                                 f"first {rows}; it does not belong to this checkpoint's run")
            self.times_kept = [float(t) for t in f["time"][:rows]]
            self.valid = f.get("frame_valid")
            # a file written before the digests goes on without: its kept rows have none
            self.digest = f.get("row_digest")
            self.rows_valid = valid_rows(f, check=False)[:rows].tolist()
        except Exception:
            f.close()
            self.f = None
            raise
        if have != rows:            # later rows are rewritten by this run
            for d in self._frame_datasets():
                d.resize(rows, axis=0)
            # flushed now: libhdf5 1.10's mpio driver otherwise loses the next writes into
            # the chunk the cut shortened (/time's rows came back 0.0; one frame per chunk
            # keeps /positions safe); tests/io/test_mpi_checkpoint.py
            f.flush()
        self.capacity = rows
        self.n_out = max(self.n_out, rows)
        self.written = rows
        for k, v in attrs.items():
            f.attrs[k] = json.dumps(v) if isinstance(v, (dict, list, tuple)) else v
        f.attrs["ranks"] = self.comm.size

    def _dataset(self, name, shape, dtype, maxshape=None, chunks=None):
        """A chunked dataset with a Fletcher-32 checksum per chunk (libhdf5 checks it on
        every read: a damaged value is a read error, never a wrong number); ``chunks``
        default: the whole dataset, at most 2**16 rows a chunk."""
        h5py = h5py_module()
        dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        dcpl.set_fill_time(h5py.h5d.FILL_TIME_NEVER)
        # never written, but what a read of a chunk the (unchecksummed) index lost
        # returns: NaN, not the zeros a damaged index gave as a row of positions
        dcpl.set_fill_value(_fill(dtype))
        # chunks allocated when the dataset grows, not at the first write
        dcpl.set_alloc_time(h5py.h5d.ALLOC_TIME_EARLY)
        if chunks is None:
            chunks = (max(1, min(shape[0], 1 << 16)),) + tuple(shape[1:])
        return self.f.create_dataset(name, shape=shape, dtype=dtype, maxshape=maxshape,
                                     chunks=chunks, dcpl=dcpl, fletcher32=True)

    def _write(self, dset, start, data):
        write_rows(dset, start, data, self._dxpl)

    def _frame_datasets(self):
        """The datasets with a row per frame."""
        return [d for d in (self.positions, self.time, self.valid, self.digest) if d is not None]

    def _grow(self):
        """One more row in the frame datasets."""
        self.capacity = self.written + 1
        for d in self._frame_datasets():
            d.resize(self.capacity, axis=0)

    def flush(self):
        """Collective: push everything written so far to the file (H5Fflush, which with
        the mpio driver ends in MPI_File_sync)."""
        self._guarded(self.f.flush)

    def _guarded(self, action):
        try:
            action()
        except (OSError, RuntimeError) as e:
            self.broken = True
            raise _h5_error(self.path, e) from None

    def write_frame(self, t, x_local):
        """Append one frame: this rank's positions (nv_local, 3) at time ``t``.  The
        free space is checked first (collective); an OutputError if it does not fit."""
        self._append(t, x_local, self.v0, True)

    def write_row(self, t, x, valid):
        """Append one row written by rank 0 alone (collective; a recovery): ``x`` the whole
        row (n_vertices, 3) on rank 0, ignored elsewhere; ``valid`` (rank 0's) goes to
        ``/frame_valid``."""
        self._append(t, x if self.comm.rank == 0 else np.zeros((0, 3)), 0, valid)

    def _append(self, t, x, first_vertex, valid):
        from lc_petsc.io.disk import check_space
        k = self.written
        grow = k >= self.capacity
        check_space(self.comm, self.folder, frame_bytes(self.nv), self.path)
        root = self.comm.rank == 0
        digest = None
        if self.digest is not None:     # collective, before the writes
            parts = self.comm.gather(vertex_digest(x, first_vertex), root=0)
            digest = np.array([row_digest(parts, k, t)] if root else [], np.uint64)

        def write():
            if grow:
                self._grow()
            self._write(self.positions, (k, first_vertex, 0), np.asarray(x)[None])
            self._write(self.time, (k,), np.array([t]) if root else np.zeros(0))
            if self.valid is not None:
                self._write(self.valid, (k,), np.array([valid], bool) if root else np.zeros(0, bool))
            if digest is not None:
                self._write(self.digest, (k,), digest)
        self._guarded(write)
        self.written += 1
        self.rows_valid.append(bool(valid))

    def close(self):
        """Shrink the frame datasets to the frames written; close the file.  A broken
        file (an h5py failure before) is left alone: libhdf5 cannot close it."""
        if self.f is None or self.broken:
            return

        def close():
            if self.written < self.positions.shape[0]:
                for d in self._frame_datasets():
                    d.resize(self.written, axis=0)
            self.f.close()
        try:
            self._guarded(close)
        finally:
            if not self.broken:
                self.f = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
