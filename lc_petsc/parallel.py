"""Wisps -> MPI ranks: whole wisps per rank, contiguous numbering, balanced by vertices.

Rank r owns the wisps ``ranges[r] .. ranges[r+1] - 1`` and their vertices, which are
numbered contiguously wisp by wisp, so rank r's PETSc ownership range (in vertices) is
``vertex_offsets[ranges[r]] .. vertex_offsets[ranges[r+1]]``.  Because a wisp never
straddles two ranks, every element (stretch, bend, twist) is rank-local: no ghost
vertices are exchanged, only reductions.
"""

from __future__ import annotations

import os
from contextlib import contextmanager

import numpy as np

from lc_petsc.errors import SimulationError

#: environment variables by which a user chooses the BLAS / OpenMP thread count
THREAD_COUNT_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                          "BLIS_NUM_THREADS")
_thread_limits = []


def limit_blas_threads():
    """One BLAS / OpenMP thread per process, unless the user set a thread count (any of
    :data:`THREAD_COUNT_VARIABLES`); returns the number of thread pools limited.

    Why: Debian's NumPy and SciPy use OpenBLAS (pthreads), which starts a thread per core
    in every process; under mpiexec with one rank per core, a rank's idle BLAS threads
    spin on the cores where the other ranks compute (PETSc itself is single-threaded).
    Measured on the 2,000-wisp hairball with strand contact, 2 ranks on 2 cores: 10.4 s
    per frame with OpenBLAS's default, 8.9 s with one thread (1 rank: no change).
    Applied once per process, through threadpoolctl (Debian's python3-threadpoolctl),
    which also works after NumPy has loaded OpenBLAS."""
    if _thread_limits or any(os.environ.get(v) for v in THREAD_COUNT_VARIABLES):
        return 0
    from threadpoolctl import threadpool_info, threadpool_limits
    _thread_limits.append(threadpool_limits(limits=1))
    return len(threadpool_info())


def partition(sizes, n_ranks: int) -> np.ndarray:
    """Wisp ranges (n_ranks + 1,) balancing vertex counts with whole wisps per rank.

    Wisp w goes to the rank whose share [r T/P, (r+1) T/P) of the T vertices contains
    the wisp's midpoint; ranges are then nudged so that every rank owns at least one
    wisp (PETSc's block Jacobi needs a block on every rank). The result is contiguous and
    deterministic. Fewer wisps than ranks is a ``ValueError``.
    """
    sizes = np.asarray(sizes, np.int64)
    n = len(sizes)
    if n < n_ranks:
        raise ValueError(f"the scene has {n} wisp(s) but the run uses {n_ranks} MPI ranks; "
                         f"whole wisps are distributed, so every rank needs at least one: "
                         f"run with mpiexec -n {max(n, 1)} or fewer ranks")
    cum = np.concatenate([[0], np.cumsum(sizes)])
    total = cum[-1]
    mid = 0.5 * (cum[:-1] + cum[1:])
    owner = np.minimum((mid * n_ranks / total).astype(np.int64), n_ranks - 1)
    ranges = np.searchsorted(owner, np.arange(n_ranks + 1), side="left").astype(np.int64)
    ranges[0], ranges[-1] = 0, n
    # At least one wisp per rank: ranges strictly increasing, leaving room for the rest.
    for r in range(1, n_ranks):
        ranges[r] = min(max(ranges[r], ranges[r - 1] + 1), n - (n_ranks - r))
    return ranges


def collective_raise(comm, messages) -> None:
    """Raise ValueError on every rank if any rank found a problem (no rank left waiting).

    ``messages``: list of strings found on this rank.  The message of the lowest rank
    with problems is raised (with a count of further problems).
    """
    all_msgs = comm.allgather(list(messages))
    flat = [m for ms in all_msgs for m in ms]
    if flat:
        more = f" (and {len(flat) - 1} more problem(s))" if len(flat) > 1 else ""
        raise ValueError(flat[0] + more)


def on_root(comm, action):
    """Run ``action()`` on rank 0 only; every rank gets ``(result, None)``, or ``(None,
    the exception)`` when it raised there (the caller decides how to report it)."""
    result, problem = None, None
    if comm.rank == 0:
        try:
            result = action()
        except Exception as e:  # noqa: BLE001 - handed to every rank
            problem = e
    return comm.bcast((result, problem))


def global_max(comm, value):
    """The largest ``value`` over the ranks of ``comm`` (on every rank)."""
    from mpi4py import MPI
    return comm.allreduce(value, op=MPI.MAX)


def global_min(comm, value):
    """The smallest ``value`` over the ranks of ``comm`` (on every rank)."""
    from mpi4py import MPI
    return comm.allreduce(value, op=MPI.MIN)


def global_wisp_offsets(comm, local_offsets) -> np.ndarray:
    """Global wisp offsets (n_wisps + 1,) int64 from every rank's local ones (its wisps'
    vertex offsets, starting at 0): wisp w owns vertices ``offsets[w]:offsets[w + 1]``
    in the global numbering (ranks own consecutive wisps in rank order)."""
    sizes = np.concatenate(comm.allgather(np.diff(np.asarray(local_offsets, np.int64))))
    return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)


@contextmanager
def collectively(comm, what):
    """Run a rank-local block; if it raises on any rank, raise on every rank.

    Without this, an error on one rank (a bad element, a NaN) leaves the others waiting
    in the next collective call forever. Costs one small allgather. The error raised is
    :class:`SimulationError` naming ``what`` and the first failing rank's message.
    """
    error = None
    try:
        yield
    except Exception as exc:  # noqa: BLE001 - every rank re-raises below
        error = exc
    reports = comm.allgather(None if error is None else f"{type(error).__name__}: {error}")
    failed = [(rank, msg) for rank, msg in enumerate(reports) if msg is not None]
    if failed:
        rank, msg = failed[0]
        more = f" ({len(failed) - 1} more rank(s) failed)" if len(failed) > 1 else ""
        raise SimulationError(f"{what}: rank {rank}: {msg}{more}") from error
