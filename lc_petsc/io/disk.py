"""Disk space: the estimate of a run's outputs before frame 0, and the check before
every HDF5 write.

Why check before writing instead of handling the error: libhdf5 1.10 (Debian's) does
not survive a full disk.  Measured on a 2 MB tmpfs: the failed write raises in h5py,
but the file's cached metadata can then be neither flushed nor closed, and the
interpreter segfaults in ``H5D_close`` at exit (exit 139); with the ``mpio`` driver
on 2 ranks, one rank fails in ``H5Dset_extent`` and the other in ``H5Dwrite``, and the
next collective call hangs.  So rank 0 looks at the free space (``shutil.disk_usage``)
before each frame and checkpoint write, broadcasts the verdict, and every rank stops
before libhdf5 sees the error; :data:`RESERVE` bytes are kept free for the metadata
HDF5 writes when the files are closed and for ``summary.json``.
"""

from __future__ import annotations

import os
import shutil
from contextlib import contextmanager
from pathlib import Path

from lc_petsc.errors import OutputError

#: bytes kept free for HDF5's metadata flush on close, frames.xdmf and summary.json
RESERVE = 256 * 1024


def free_bytes(path) -> int:
    """Free bytes of the volume holding ``path``."""
    return shutil.disk_usage(path).free


def human(n) -> str:
    """``n`` bytes for a person (``2.4 kB``)."""
    n = float(n)
    for unit in ("B", "kB", "MB", "GB", "TB", "PB", "EB"):
        if abs(n) < 1000 or unit == "EB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} EB"  # pragma: no cover


def space_problem(folder, needed, what):
    """None if ``needed`` bytes (+ :data:`RESERVE`) fit on the volume of ``folder``,
    else the message naming ``what`` (the file about to be written)."""
    try:
        free = free_bytes(folder)
    except OSError as e:
        return f"{what}: cannot query the free space of {folder}: {e.strerror or e}"
    if free < needed + RESERVE:
        return (f"{what}: disk full: writing it needs {human(needed)} (+ {human(RESERVE)} kept free "
                f"for closing the files), the volume of {folder} has {human(free)} free")
    return None


def check_space(comm, folder, needed, what):
    """Collective: raise :class:`OutputError` on every rank if rank 0 finds that
    ``needed`` bytes do not fit (the verdict of rank 0 is broadcast)."""
    problem = space_problem(folder, needed, what) if comm.rank == 0 else None
    problem = comm.bcast(problem)
    if problem:
        raise OutputError(problem)


def replace_atomically(tmp, path, fsync=False):
    """Rename the complete file ``tmp`` over ``path``.  Atomic on POSIX: a reader sees
    the old file or the new one, never half of one.  ``fsync``: ``tmp``'s data reach the
    disk before the rename and the folder's entry after it, so a crash leaves one of the
    two files whole (checkpoints)."""
    if fsync:
        _fsync_path(tmp)
    os.replace(tmp, path)
    if fsync:
        _fsync_path(Path(path).parent, directory=True)


@contextmanager
def written_aside(path, tmp=None, fsync=False):
    """Write ``path`` through a temporary file next to it (default ``<path>.tmp``): yields
    the temporary path; when the block completes the file replaces ``path``
    (:func:`replace_atomically`, with ``fsync``), when it raises the file is removed."""
    tmp = Path(f"{path}.tmp") if tmp is None else Path(tmp)
    try:
        yield tmp
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    replace_atomically(tmp, path, fsync=fsync)


def _fsync_path(path, directory=False):
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if directory else 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
