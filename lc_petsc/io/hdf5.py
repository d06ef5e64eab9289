"""Collective HDF5 files (frames.h5, checkpoints) and libhdf5's unrecoverable state.

h5py is imported lazily: importing it under mpiexec picks Debian's MPI build, which
only the writers need.

:func:`collective_file_options` and :func:`collective_transfer` are the one way the
writers open a file on every rank (the ``mpio`` driver when h5py is MPI-enabled, a
plain serial file otherwise) and write rows collectively.

libhdf5 1.10 cannot recover from a failed write on an open file: the file can then be
neither flushed nor closed, and closing it at interpreter exit crashes
(lc_petsc/io/disk.py).  :func:`mark_unclosable` records that this happened;
:func:`unclosable` tells the job to write nothing more from frames.h5 and the process
to end without closing it (``lc_petsc.batch.exit_process``).
"""

from __future__ import annotations

_unclosable = False


def h5py_module():
    """``h5py``, imported on first use."""
    import h5py
    return h5py


def is_parallel() -> bool:
    """Whether this h5py is Debian's MPI build (true under mpiexec)."""
    return bool(h5py_module().get_config().mpi)


def collective_file_options(comm) -> dict:
    """Keyword arguments of ``h5py.File`` for a file every rank of ``comm`` opens
    together: the ``mpio`` driver with MPI-enabled h5py, none otherwise."""
    return {"driver": "mpio", "comm": comm} if is_parallel() else {}


def collective_transfer():
    """A dataset-transfer property list for collective writes (MPI-IO collective with
    MPI-enabled h5py, the default transfer otherwise)."""
    h5py = h5py_module()
    dxpl = h5py.h5p.create(h5py.h5p.DATASET_XFER)
    if is_parallel():
        dxpl.set_dxpl_mpio(h5py.h5fd.MPIO_COLLECTIVE)
    return dxpl


def mark_unclosable():
    """Record that libhdf5 failed on an open file (see the module doc)."""
    global _unclosable
    _unclosable = True


def unclosable() -> bool:
    """Whether libhdf5 failed on an open file in this process."""
    return _unclosable
