"""Wisps -> MPI ranks: whole wisps per rank, contiguous numbering, balanced by vertices.

Rank r owns the wisps ``ranges[r] .. ranges[r+1] - 1`` and their vertices, which are
numbered contiguously wisp by wisp, so rank r's PETSc ownership range (in vertices) is
``vertex_offsets[ranges[r]] .. vertex_offsets[ranges[r+1]]``.  Because a wisp never
straddles two ranks, every element (stretch, bend, twist) is rank-local: no ghost
vertices are exchanged, only reductions.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np


class SimulationError(RuntimeError):
    """A failure on some rank during a step, raised on every rank (see :func:`collectively`)."""


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
