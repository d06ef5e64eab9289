"""Restart checkpoints: ``<out>/checkpoints/checkpoint_FFFFFF.h5`` (FFFFFF = frame).

Layout (format ``lc_petsc checkpoint``, ``format_version`` 1; plain h5py reads it):

* ``/positions``, ``/velocities`` float64 (n_vertices, 3), global vertex order;
* ``/rest_positions`` float64 (n_vertices, 3), ``/pinned`` bool (n_vertices,);
* ``/wisp_offsets`` int64 (n_wisps + 1,);
* ``/head_state`` float64 (16,): t, the head's rotation R (row-major 3x3), translation
  T and centre c at t (the head kinematics are a function of t, so this is a record and
  a consistency check, not extra state);
* a 512-byte HDF5 user block before the HDF5 file: the *seal*, a SHA-256 of the
  metadata checked with plain reads before libhdf5 opens the file
  (:mod:`lc_petsc.io.checkpoint_seal`; files without it load as before);
* root attributes: ``format``, ``format_version``, ``frame``, ``time``, ``dt``,
  ``every`` (output.every), ``frames_rows`` (rows of ``frames.h5`` that belong to frames
  <= ``frame``), ``n_wisps``, ``n_vertices``, ``ranks``, ``config`` (resolved config,
  JSON), ``config_toml`` (the config file's text), ``config_sha256``,
  ``petsc_options`` (JSON), ``lc_petsc_version``, ``contact_state``, ``radius_sha256``
  (the strands' radii, hashed as a vertex dataset: with ``/rest_positions`` and
  ``/pinned`` the groom's content, which a restart compares instead of its path;
  checkpoints before 2026-12-07 lack it), ``meta_sha256`` (over the attributes above).
  Every dataset has a ``sha256`` attribute.

Contact state: none is carried between frames (strand contact rebuilds its broad phase
from the positions at every call, head contact is a function of positions and t), so
x, v, t and frame are the whole dynamic state; ``contact_state`` says so.

**Written collectively** with the ``mpio`` driver: every rank writes the rows of its
own vertices (contiguous datasets, no fill writes); rank 0 writes the small global
datasets; nothing is gathered.

**Checksums, on any rank count.** A vertex dataset's ``sha256`` is the SHA-256 of the
concatenated SHA-256 digests of its wisps' rows (C order, native little-endian bytes),
in global wisp order.  Wisps are never split across ranks in any partition, so each
rank hashes its own wisps, the 32-byte digests (64 kB for 2,000 wisps) are gathered to
rank 0, which combines them: the same value whatever the rank count of the writer or
the reader.  Small global datasets are hashed whole.

**Atomic and durable.** The file is written to ``.checkpoint_FFFFFF.h5.tmp`` in the same
folder (its bytes reserved on disk after its datasets are created and before any is
written, so that another program filling the volume cannot make a write fail; the
ranks agree after every step of the write, and a failure is one OutputError on all),
flushed (``H5Fflush``: ``MPI_File_sync`` under mpio), closed, ``fsync``-ed by
rank 0, renamed over the final name (``os.replace``, atomic on POSIX) and the folder is
``fsync``-ed.  A kill at any moment leaves either no new checkpoint (a stray ``.tmp``,
ignored and removed by the next run) or a complete one; older checkpoints are
untouched until the new one is in place, then all but the newest ``keep`` are removed.

**Loading** (:func:`load_checkpoint`, collective): rank 0 opens the file serially and
checks the format, version, counts against the scene, the attribute checksum and the
small datasets; then every rank reads its rows for the *current* partition and the
vertex datasets' digests are combined and compared.  Any failure is a
:class:`CheckpointError` on every rank naming the file (and the dataset).
:func:`find_latest` walks the checkpoints newest first and returns the first valid one
with the messages of those it skipped.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import time
from pathlib import Path

import numpy as np

from lc_petsc.errors import CheckpointError
from lc_petsc.io.checkpoint_seal import USERBLOCK, check_seal, seal
from lc_petsc.io.disk import replace_atomically
from lc_petsc.io.hdf5 import collective_file_options, collective_transfer, h5py_module
from lc_petsc.parallel import global_wisp_offsets, on_root

FORMAT = "lc_petsc checkpoint"
FORMAT_VERSION = 1
FOLDER = "checkpoints"
PAUSE_ENV = "LC_PETSC_TEST_CHECKPOINT_PAUSE"   # test hook, "FRAME:SECONDS": sleep inside the write
VERTEX_DATASETS = ("positions", "velocities", "rest_positions", "pinned")
GLOBAL_DATASETS = ("wisp_offsets", "head_state")
META_KEYS = ("format", "format_version", "frame", "time", "dt", "every", "frames_rows",
             "n_wisps", "n_vertices", "config", "config_sha256", "lc_petsc_version", "radius_sha256")
CONTACT_STATE = "none: contact is recomputed from positions and time at every call"
_NAME = re.compile(r"^checkpoint_(\d+)\.h5$")




def checkpoint_folder(out) -> Path:
    """The checkpoint folder of the output folder ``out``."""
    return Path(out) / FOLDER


def checkpoint_path(out, frame) -> Path:
    """The checkpoint file of ``frame`` in the output folder ``out``."""
    return checkpoint_folder(out) / f"checkpoint_{int(frame):06d}.h5"


def _numbered(folder):
    """(frame, path) of the checkpoint files in ``folder``, newest (highest frame) first."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(((int(m.group(1)), folder / p) for p in os.listdir(folder) if (m := _NAME.match(p))),
                  reverse=True)


def list_checkpoints(folder):
    """Checkpoint files in ``folder``, newest (highest frame) first."""
    return [p for _, p in _numbered(folder)]


def checkpoint_files(folder):
    """[(frame, path as str, bytes)] of the checkpoint files in ``folder``, oldest first
    (a file removed while listed is left out)."""
    out = []
    for frame, p in reversed(_numbered(folder)):
        try:
            out.append((frame, str(p), p.stat().st_size))
        except FileNotFoundError:
            continue
    return out


def set_aside_later(folder, frame):
    """Rank 0: rename the checkpoints in ``folder`` of frames after ``frame`` (a restart
    from ``frame`` replaces the run they continued) to ``checkpoint_FFFFFF.superseded-N.h5``
    (never removed; ``--restart`` can still name them).  Left as they were, the newest of
    them was ``--restart latest``'s pick although frames.h5 no longer holds its frames,
    and the rotation kept them in place of the new run's checkpoints.  Returns the
    [(old, new)] paths."""
    moved = []
    for at, p in _numbered(folder):
        if at <= int(frame):
            break
        n = 1
        while (target := p.with_name(f"{p.stem}.superseded-{n}.h5")).exists():
            n += 1
        os.rename(p, target)
        moved.append((p, target))
    return moved


def config_sha256(config_dict) -> str:
    """SHA-256 of the resolved config (canonical JSON): a restart compares it with the checkpoint's."""
    return hashlib.sha256(json.dumps(config_dict, sort_keys=True).encode()).hexdigest()


def _normal(d):
    return json.loads(json.dumps(d))


#: Keys whose default is not what the versions before them did: a checkpoint without
#: the key ran as this value (time.carry_with_head came on 2026-12-05, default true; the
#: code before it did not carry; material.twist_rest_sine on 2026-12-06, default 0.05;
#: the code before it kept every twist element at full stiffness).
LEGACY_VALUES = {"time.carry_with_head": False, "material.twist_rest_sine": 0.0}


def config_differences(saved, current, ignore=(), defaults=None):
    """Dotted keys whose values differ between two config dicts (``ignore``: keys that
    do not change the trajectory or the frames file's layout).  With ``defaults`` (a
    config dict of every key's default), a key the saved config lacks is no difference
    while the current one holds its default: the checkpoint was written by a version
    without that key, which ran as its default does, unless :data:`LEGACY_VALUES` says
    what it ran as instead."""
    def flat(d, pre=""):
        out = {}
        for k, v in d.items():
            key = f"{pre}{k}"
            if isinstance(v, dict):
                out.update(flat(v, key + "."))
            else:
                out[key] = v
        return out
    a, b = flat(_normal(saved)), flat(_normal(current))
    if defaults is not None:
        d = flat(_normal(defaults))
        a.update({k: LEGACY_VALUES.get(k, d[k]) for k in b if k not in a and k in d})
    return [k for k in sorted(set(a) | set(b)) if k not in ignore and a.get(k, "<absent>") != b.get(k, "<absent>")]


def head_state(head, t) -> np.ndarray:
    """The head's state at ``t``, flattened: t, rotation (9), translation (3), sphere centre (3)."""
    R, T = head.transform(t)
    return np.concatenate([[t], np.asarray(R, float).ravel(), np.asarray(T, float),
                           np.asarray(head.center, float)])


def _wisp_digests(data, local_offsets) -> np.ndarray:
    data = np.ascontiguousarray(data)
    rows = data.reshape(len(data), -1)
    out = np.empty((len(local_offsets) - 1, 32), np.uint8)
    for w in range(len(local_offsets) - 1):
        out[w] = np.frombuffer(hashlib.sha256(rows[local_offsets[w]:local_offsets[w + 1]].tobytes()).digest(),
                               np.uint8)
    return out


def radius_digest(comm, scene) -> str:
    """The SHA-256 of the scene's per-vertex radii (``scene``: this rank's LocalScene),
    the same on any rank count; on every rank."""
    return comm.bcast(_combine(comm, _wisp_digests(np.asarray(scene.radius, np.float64),
                                                   np.asarray(scene.offsets, np.int64))))


def _combine(comm, digests):
    """SHA-256 over all ranks' per-wisp digests in rank (= global wisp) order; on rank 0
    (None elsewhere)."""
    parts = comm.gather(digests, root=0)
    if comm.rank != 0:
        return None
    return hashlib.sha256(np.concatenate(parts).tobytes()).hexdigest()


def _whole(data) -> str:
    return hashlib.sha256(np.ascontiguousarray(data).tobytes()).hexdigest()


def _meta_digest(attrs) -> str:
    meta = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in attrs.items() if k in META_KEYS}
    return hashlib.sha256(json.dumps(meta, sort_keys=True).encode()).hexdigest()


def _pause(frame):
    spec = os.environ.get(PAUSE_ENV)
    if spec:
        f, s = spec.split(":")
        if int(f) == int(frame):
            time.sleep(float(s))


def _on_root(comm, action, what):
    """Run a file-system ``action`` on rank 0; an OSError there is raised on every rank
    as an OSError naming ``what``."""
    _, problem = on_root(comm, action)
    if isinstance(problem, OSError):
        raise OSError(f"{what}: {problem.strerror or problem}")
    if problem is not None:
        raise problem


def write_checkpoint(out, comm, *, frame, t, x, v, scene, n_wisps, n_vertices, head, dt, every,
                     config_dict, config_toml, petsc_options, keep, version):
    """Collectively write the checkpoint of ``frame`` into ``<out>/checkpoints``; keep the
    newest ``keep``.  ``x``/``v``: this rank's rows; ``scene``: the rank's LocalScene.
    Returns (path, seconds, bytes) on every rank."""
    h5py = h5py_module()
    t0 = time.perf_counter()
    folder = checkpoint_folder(out)
    final = checkpoint_path(out, frame)
    tmp = folder / f".{final.name}.tmp"
    def prepare():
        folder.mkdir(parents=True, exist_ok=True)
        tmp.unlink(missing_ok=True)
    _on_root(comm, prepare, f"checkpoint folder {str(folder)!r}")
    from lc_petsc.io.disk import check_space
    check_space(comm, folder, checkpoint_bytes(n_wisps, n_vertices), str(final))
    lo = np.asarray(scene.offsets, np.int64)
    local = {"positions": np.asarray(x, np.float64), "velocities": np.asarray(v, np.float64),
             "rest_positions": np.asarray(scene.x_rest, np.float64), "pinned": np.asarray(scene.pinned, np.bool_)}
    digests = {k: _combine(comm, _wisp_digests(a, lo)) for k, a in local.items()}
    offsets = global_wisp_offsets(comm, lo)
    hs = head_state(head, t)
    digests.update({"wisp_offsets": _whole(offsets), "head_state": _whole(hs)})
    radius = radius_digest(comm, scene)
    digests = comm.bcast(digests)          # attributes are written collectively: same values
    attrs = {"format": FORMAT, "format_version": FORMAT_VERSION, "frame": int(frame), "time": float(t),
             "dt": float(dt), "every": int(every), "frames_rows": int(frame) // int(every) + 1,
             "n_wisps": int(n_wisps), "n_vertices": int(n_vertices), "ranks": comm.size,
             "config": json.dumps(config_dict, sort_keys=True), "config_toml": config_toml,
             "config_sha256": config_sha256(config_dict), "petsc_options": json.dumps(petsc_options),
             "lc_petsc_version": version, "contact_state": CONTACT_STATE, "radius_sha256": radius}
    attrs["meta_sha256"] = _meta_digest(attrs)

    kw = collective_file_options(comm)
    dxpl = collective_transfer()
    v0 = int(scene.first_vertex)
    try:
        _write_file(h5py, tmp, kw, local, digests, n_vertices, v0, offsets, hs, attrs, dxpl, comm, frame)
    except (OSError, RuntimeError) as e:
        from lc_petsc.io.frames import _h5_error
        raise _h5_error(tmp, e) from None
    def publish():
        # the reservation may have left the file longer than its data: a serial reopen
        # cuts it to HDF5's end of allocation (the mpio close already does)
        with h5py.File(str(tmp), "r+"):
            pass
        seal(tmp, h5py, VERTEX_DATASETS + GLOBAL_DATASETS)
        replace_atomically(tmp, final, fsync=True)
        for old in list_checkpoints(folder)[max(int(keep), 1):]:
            old.unlink(missing_ok=True)
    _on_root(comm, publish, f"checkpoint {str(final)!r}")
    size = comm.bcast(final.stat().st_size if comm.rank == 0 else None)
    return final, time.perf_counter() - t0, size


def checkpoint_bytes(n_wisps, n_vertices) -> int:
    """Upper estimate of a checkpoint's size (measured: 73 bytes per vertex + 30 kB)."""
    return 73 * int(n_vertices) + 8 * (int(n_wisps) + 1) + 64 * 1024


def _write_file(h5py, tmp, kw, local, digests, n_vertices, v0, offsets, hs, attrs, dxpl, comm, frame):
    """Create ``tmp`` on every rank, reserve its bytes, write it, close it.  A failure on
    any rank is an OutputError on every rank (:func:`_together`), and the file is then
    left open (``_ABANDONED``): closing it after a failed write hung both ranks in
    libhdf5's close (a disk filled by another program during the write)."""
    from lc_petsc.io.frames import write_rows
    f = h5py.File(str(tmp), "w", userblock_size=USERBLOCK, **kw)
    try:
        def dataset(name, shape, dtype):
            dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
            dcpl.set_fill_time(h5py.h5d.FILL_TIME_NEVER)
            dcpl.set_alloc_time(h5py.h5d.ALLOC_TIME_EARLY)
            d = f.create_dataset(name, shape=shape, dtype=dtype, dcpl=dcpl)
            d.attrs["sha256"] = digests[name]
            return d
        # name: (this rank's rows, where they start, the dataset's shape)
        rows = {name: (local[name], (v0,), (n_vertices,) + local[name].shape[1:])
                for name in VERTEX_DATASETS}
        rows.update({name: (a if comm.rank == 0 else a[:0], (0,), a.shape)
                     for name, a in (("wisp_offsets", offsets), ("head_state", hs))})
        dsets = _together(comm, "creating the datasets", lambda: {
            name: dataset(name, shape, a.dtype) for name, (a, _, shape) in rows.items()})
        nbytes = checkpoint_bytes(len(offsets) - 1, n_vertices)
        _together(comm, f"reserving its {nbytes:,} bytes on disk",
                  lambda: _reserve(tmp, nbytes) if comm.rank == 0 else None)
        for name, (a, start, _) in rows.items():
            _together(comm, f"writing /{name}", lambda: write_rows(dsets[name], start, a, dxpl))
            if name == "positions":
                _pause(frame)

        def finish():
            for k, val in attrs.items():
                f.attrs[k] = val
            f.flush()
        _together(comm, "writing its attributes", finish)
    except _Failed as e:
        _ABANDONED.append(f)
        from lc_petsc.io.disk import OutputError
        _on_root(comm, lambda: tmp.unlink(missing_ok=True), f"checkpoint {str(tmp)!r}")
        raise OutputError(f"{tmp}: {e} (the partial checkpoint is removed, the previous "
                          "ones are intact)", hdf5_broken=True) from None
    f.close()


#: checkpoint files libhdf5 failed on: never closed (lc_petsc.io.hdf5), kept referenced
#: so that the garbage collector does not close them either
_ABANDONED: list = []


class _Failed(Exception):
    """A step of the checkpoint's write failed on some rank (the message names it)."""


def _together(comm, what, action):
    """``action()`` on every rank, then one verdict for all: its result, or _Failed on
    every rank if it raised OSError / RuntimeError on any (the first rank's reason).
    A collective write that fails on one rank (ENOSPC on an aggregator) returns on the
    others, so the ranks agree before the next collective call instead of parting."""
    result, problem = None, None
    try:
        result = action()
    except (OSError, RuntimeError) as e:
        problem = f"{what}: {e.strerror if isinstance(e, OSError) and e.strerror else e}"
    problems = [p for p in comm.allgather(problem) if p]
    if problems:
        raise _Failed(problems[0])
    return result


def _reserve(path, nbytes):
    """Allocate the file's first ``nbytes`` on disk (rank 0, before any data is written):
    the writes that follow then cannot run out of space, whatever else fills the volume.
    A file system that cannot preallocate is written without it."""
    import errno
    fd = os.open(str(path), os.O_RDWR)
    try:
        os.posix_fallocate(fd, 0, int(nbytes))
    except OSError as e:
        if e.errno not in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
            raise
    finally:
        os.close(fd)


#: what h5py raises on a damaged file: OSError (unreadable bytes), KeyError (an object
#: header it cannot open: "bad object header version number"), RuntimeError, and
#: ValueError / TypeError (a dataset of another shape or type)
_H5_DAMAGE = (OSError, KeyError, RuntimeError, ValueError, TypeError)


def _h5_reason(e):
    """h5py's message without the quotes a KeyError adds."""
    return e.args[0] if isinstance(e, KeyError) and e.args else str(e)


def _attr(v):
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.generic):
        return v.item()
    return v


def _precheck(path, n_wisps, n_vertices, offsets, head):
    """Rank 0, serial: format, version, counts, attribute and small-dataset checksums.
    Returns the attributes; raises CheckpointError."""
    h5py = h5py_module()
    name = str(path)
    if not os.path.exists(name):
        raise CheckpointError(f"{name}: no such checkpoint file")
    if not os.path.isfile(name):
        raise CheckpointError(f"{name}: not an lc_petsc checkpoint (not a regular file)")
    check_seal(name)                # before libhdf5 parses a byte of it
    if not h5py.is_hdf5(name):
        raise CheckpointError(f"{name}: not an lc_petsc checkpoint (not an HDF5 file)")
    try:
        f = h5py.File(name, "r")
    except OSError as e:
        raise CheckpointError(f"{name}: unreadable or truncated HDF5 file ({e})") from None
    with f:
        try:
            attrs = {k: _attr(v) for k, v in f.attrs.items()}
        except OSError as e:
            raise CheckpointError(f"{name}: unreadable attributes ({e})") from None
        if attrs.get("format") != FORMAT:
            raise CheckpointError(f"{name}: not an lc_petsc checkpoint (format attribute "
                                  f"{attrs.get('format')!r}, expected {FORMAT!r})")
        ver = attrs.get("format_version")
        if not isinstance(ver, int) or ver > FORMAT_VERSION:
            raise CheckpointError(f"{name}: checkpoint format version {ver} is newer than this "
                                  f"lc_petsc reads (version {FORMAT_VERSION}); use a newer lc_petsc")
        if attrs.get("meta_sha256") != _meta_digest(attrs):
            raise CheckpointError(f"{name}: corrupt checkpoint: the attributes (frame, time, config) "
                                  "do not match their checksum meta_sha256")
        if attrs["n_wisps"] != n_wisps or attrs["n_vertices"] != n_vertices:
            raise CheckpointError(f"{name}: the checkpoint has {attrs['n_wisps']} wisps and "
                                  f"{attrs['n_vertices']} vertices, the scene {n_wisps} wisps and "
                                  f"{n_vertices} vertices")
        for k in VERTEX_DATASETS + GLOBAL_DATASETS:
            if k not in f:
                raise CheckpointError(f"{name}: corrupt checkpoint: dataset /{k} is missing")
        for k in GLOBAL_DATASETS:
            try:
                a = f[k][...]
                ok = _attr(f[k].attrs.get("sha256")) == _whole(a)
            except OSError as e:
                raise CheckpointError(f"{name}: corrupt checkpoint: dataset /{k} unreadable ({e})") from None
            if not ok:
                raise CheckpointError(f"{name}: corrupt checkpoint: dataset /{k} fails its checksum")
            if k == "wisp_offsets" and not np.array_equal(a, offsets):
                raise CheckpointError(f"{name}: the checkpoint's wisp sizes (/wisp_offsets) differ "
                                      "from the scene's")
            if k == "head_state" and not np.allclose(a, head_state(head, attrs["time"]), rtol=1e-12, atol=1e-12):
                raise CheckpointError(f"{name}: the head state stored at t = {attrs['time']} differs "
                                      "from the configured head motion's")
        attrs["digests"] = {k: _attr(f[k].attrs.get("sha256")) for k in VERTEX_DATASETS}
        return attrs


def load_checkpoint(path, comm, scene, n_wisps, n_vertices, head):
    """Collectively load ``path`` for the current partition (``scene``: this rank's
    LocalScene).  Returns a dict: ``x``, ``v`` (this rank's rows), ``frame``, ``time``,
    ``attrs`` (root attributes, ``config`` parsed), ``path``.  Raises
    :class:`CheckpointError` on every rank."""
    h5py = h5py_module()
    lo = np.asarray(scene.offsets, np.int64)
    offsets = global_wisp_offsets(comm, lo)
    res = None
    if comm.rank == 0:
        try:
            res = _precheck(path, n_wisps, n_vertices, offsets, head)
        except CheckpointError as e:
            res = e
        except _H5_DAMAGE as e:     # raised on rank 0 alone, the others would wait in bcast
            res = CheckpointError(f"{path}: corrupt checkpoint: its HDF5 structure is damaged "
                                  f"({_h5_reason(e)})")
    res = comm.bcast(res)
    if isinstance(res, CheckpointError):
        raise CheckpointError(str(res))
    attrs = res
    name = str(path)
    kw = collective_file_options(comm)
    v0, nv = int(scene.first_vertex), len(scene.x_rest)
    data, err = {}, None
    try:
        with h5py.File(name, "r", **kw) as f:
            for k in VERTEX_DATASETS:
                data[k] = f[k][v0:v0 + nv]
    except Exception as e:  # noqa: BLE001 - reported collectively below
        err = f"{name}: corrupt checkpoint: cannot read its datasets ({e})"
    errs = [m for m in comm.allgather(err) if m]
    if errs:
        raise CheckpointError(errs[0])
    bad = None
    for k in VERTEX_DATASETS:
        h = _combine(comm, _wisp_digests(data[k], lo))
        if comm.rank == 0 and bad is None and h != attrs["digests"][k]:
            bad = k
    bad = comm.bcast(bad)
    if bad:
        raise CheckpointError(f"{name}: corrupt checkpoint: dataset /{bad} fails its checksum (sha256)")
    attrs["config"] = json.loads(attrs["config"])
    attrs["petsc_options"] = json.loads(attrs["petsc_options"])
    return {"x": data["positions"], "v": data["velocities"], "rest": data["rest_positions"],
            "pinned": data["pinned"],
            "frame": int(attrs["frame"]), "time": float(attrs["time"]), "attrs": attrs, "path": Path(name)}


def read_positions(path, offsets):
    """Rank 0, serial: a checkpoint's ``frame``, ``time``, ``config_sha256`` and
    ``positions`` (n_vertices, 3) in global order, checked against their checksums
    (``offsets``: the global wisp offsets); a CheckpointError naming the file otherwise."""
    h5py = h5py_module()
    name = str(path)
    try:
        check_seal(name)
        with h5py.File(name, "r") as f:
            attrs = {k: _attr(v) for k, v in f.attrs.items()}
            x = f["positions"][...]
            digest = _attr(f["positions"].attrs.get("sha256"))
    except _H5_DAMAGE as e:
        raise CheckpointError(f"{name}: unreadable checkpoint ({_h5_reason(e)})") from None
    if attrs.get("format") != FORMAT or attrs.get("meta_sha256") != _meta_digest(attrs):
        raise CheckpointError(f"{name}: not an lc_petsc checkpoint, or its attributes fail their checksum")
    if x.shape != (int(offsets[-1]), 3) or \
            hashlib.sha256(_wisp_digests(x, offsets).tobytes()).hexdigest() != digest:
        raise CheckpointError(f"{name}: corrupt checkpoint: dataset /positions fails its checksum (sha256)")
    return {"frame": int(attrs["frame"]), "time": float(attrs["time"]),
            "config_sha256": attrs.get("config_sha256"), "positions": x}


def find_latest(folder, comm, scene, n_wisps, n_vertices, head):
    """The newest valid checkpoint in ``folder``: (loaded dict, [messages of the newer
    ones rejected]).  None valid: CheckpointError listing why."""
    rejected = []
    for p in comm.bcast(list_checkpoints(folder) if comm.rank == 0 else None):
        try:
            return load_checkpoint(p, comm, scene, n_wisps, n_vertices, head), rejected
        except CheckpointError as e:
            rejected.append(str(e))
    # none at all: the run stopped (killed) before its first checkpoint; nothing to continue
    why = ("; ".join(rejected)) if rejected else ("there are none: the run there stopped before its first "
                                                  "checkpoint (output.checkpoint_every); run the same command "
                                                  "without --restart to start it over")
    raise CheckpointError(f"--restart latest: no valid checkpoint in {str(folder)!r} ({why})")


def groom_differences(comm, checkpoint, scene) -> list:
    """What differs between the loaded ``checkpoint``'s groom and the scene's (``scene``:
    this rank's LocalScene): phrases naming the first differing vertex of the rest
    positions and the pinned vertices, and whether the radii differ (checkpoints that
    hold their digest); [] when the content is the same.  Collective."""
    lo = np.asarray(scene.offsets, np.int64)
    found = []
    for name, saved, now in (("rest positions", checkpoint["rest"], scene.x_rest),
                             ("pinned vertices", checkpoint["pinned"], scene.pinned)):
        saved, now = np.asarray(saved), np.asarray(now)
        bad = np.flatnonzero((saved != now).reshape(len(now), -1).any(axis=1))
        first = None
        if len(bad):
            i = int(bad[0])
            w = int(np.searchsorted(lo, i, side="right")) - 1
            first = (int(scene.first_vertex) + i, int(scene.first_wisp) + w, i - int(lo[w]),
                     saved[i].tolist(), now[i].tolist())
        per_rank = comm.allgather((len(bad), first))
        count = sum(n for n, _ in per_rank)
        if count:
            v, w, j, a, b = next(f for _, f in per_rank if f is not None)
            found.append(f"its {name} at {count} {'vertex' if count == 1 else 'vertices'} (first: vertex {v}, "
                         f"wisp {w}'s vertex {j}: checkpoint {a}, scene {b})")
    saved_radius = checkpoint["attrs"].get("radius_sha256")
    if saved_radius is not None and radius_digest(comm, scene) != saved_radius:
        found.append("its radii")
    return found
