"""Wisps -> MPI ranks: whole wisps per rank, contiguous numbering, balanced by vertices.

Rank r owns the wisps ``ranges[r] .. ranges[r+1] - 1`` and their vertices, which are
numbered contiguously wisp by wisp, so rank r's PETSc ownership range (in vertices) is
``vertex_offsets[ranges[r]] .. vertex_offsets[ranges[r+1]]``.  Because a wisp never
straddles two ranks, every element (stretch, bend, twist) is rank-local: no ghost
vertices are exchanged, only reductions.
"""

from __future__ import annotations

import numpy as np


def partition(sizes, n_ranks: int) -> np.ndarray:
    """Wisp ranges (n_ranks + 1,) balancing vertex counts with whole wisps per rank.

    Wisp w goes to the rank whose share [r T/P, (r+1) T/P) of the T vertices contains
    the wisp's midpoint; the result is contiguous and deterministic.  A rank may get no
    wisp when there are fewer wisps than ranks.
    """
    sizes = np.asarray(sizes, np.int64)
    n = len(sizes)
    if n == 0:
        return np.zeros(n_ranks + 1, np.int64)
    cum = np.concatenate([[0], np.cumsum(sizes)])
    total = cum[-1]
    mid = 0.5 * (cum[:-1] + cum[1:])
    owner = np.minimum((mid * n_ranks / total).astype(np.int64), n_ranks - 1)
    ranges = np.searchsorted(owner, np.arange(n_ranks + 1), side="left").astype(np.int64)
    ranges[-1] = n
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
