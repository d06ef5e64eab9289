"""Wisps -> MPI ranks: whole wisps per rank, contiguous numbering, balanced by vertices.

The simulator numbers the wisps along a Hilbert curve of their roots (:func:`order_wisps`,
``-lc_wisp_order spatial``), so a rank's contiguous share is compact in space whatever
order the scene lists them in; :class:`UserLayout` keeps outputs in the scene's order.
Rank r owns the (so numbered) wisps ``ranges[r] .. ranges[r+1] - 1`` and their vertices, which are
numbered contiguously wisp by wisp, so rank r's PETSc ownership range (in vertices) is
``vertex_offsets[ranges[r]] .. vertex_offsets[ranges[r+1]]``.  Because a wisp never
straddles two ranks, every element (stretch, bend, twist) is rank-local: no ghost
vertices are exchanged, only reductions.
"""

from __future__ import annotations

import os
import time
from contextlib import contextmanager

import numpy as np

from lc_petsc.errors import SimulationError

#: environment variables by which a user chooses the BLAS / OpenMP thread count
THREAD_COUNT_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                          "BLIS_NUM_THREADS")
_thread_limits: list = []


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


def global_reduce(comm, values, op):
    """Element-wise ``op`` (``"sum"``, ``"max"`` or ``"min"``) of the floats ``values``
    over the ranks of ``comm`` (on every rank), in one buffer ``Allreduce``."""
    from mpi4py import MPI
    buf = np.array(values, float)
    comm.Allreduce(MPI.IN_PLACE, buf, op={"sum": MPI.SUM, "max": MPI.MAX, "min": MPI.MIN}[op])
    return buf


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



def compile_in_turn(comm, *warm_ups):
    """Run the kernels' ``warm_ups`` (Numba compiles, or loads its cache) on rank 0 first,
    which writes the cache, then on the other ranks: ranks sharing a machine do not all
    compile at once.  ``comm``: an mpi4py communicator.  Returns this rank's seconds,
    waiting for rank 0 included (collective)."""
    t0 = time.perf_counter()
    for first in (True, False):
        if (comm.rank == 0) == first:
            for warm_up in warm_ups:
                warm_up()
        if first:
            comm.Barrier()
    return time.perf_counter() - t0

#: ``-lc_wisp_order``: wisps numbered along a space-filling curve of their roots, or in
#: the order of the scene (the groom file).
WISP_ORDERS = ("spatial", "input")
#: ``-lc_contact_work``: which rank computes a pair of segments (broad phase, limiter,
#: narrow phase, assembly rows; lc_petsc/contact.py): ``owner``, the lower of the ranks
#: owning its two wisps; ``balanced``, the lower of the two wisps' contact ranks, which
#: cut the wisps into contiguous runs of equal contact work (the last frame's candidate
#: pairs, :func:`partition`), apart from the solve's vertex-balanced ranges
CONTACT_WORK = ("owner", "balanced")


def hilbert_order(points, bits=10):
    """The permutation that sorts ``points`` (n, 3) along a 3D Hilbert curve.

    The points' bounding cube (the box's longest side on every axis, so the curve keeps
    the scene's proportions) is cut into 2^bits cells per axis; cells are ranked by
    Skilling's transpose form of the Hilbert index (J. Skilling, "Programming the
    Hilbert curve", AIP Conf. Proc. 707, 2004), ties kept in input order.  Consecutive
    cells along the curve are face neighbours, so contiguous runs of the result are
    compact in space.  Non-finite points are a ``ValueError``.
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if not np.isfinite(p).all():
        raise ValueError("hilbert_order: the points must be finite")
    if len(p) == 0:
        return np.zeros(0, np.int64)
    lo = p.min(axis=0)
    extent = float((p.max(axis=0) - lo).max()) or 1.0
    side = (1 << bits) - 1
    X = [np.minimum((side * (p[:, i] - lo[i]) / extent).astype(np.int64), side) for i in range(3)]
    top = 1 << (bits - 1)
    q = top
    while q > 1:                       # inverse undo of excess work
        mask = q - 1
        for i in range(3):
            on = (X[i] & q) != 0
            X[0] = np.where(on, X[0] ^ mask, X[0])
            t = np.where(on, 0, (X[0] ^ X[i]) & mask)
            X[0] = X[0] ^ t
            X[i] = X[i] ^ t
        q >>= 1
    for i in range(1, 3):             # Gray encode
        X[i] = X[i] ^ X[i - 1]
    t = np.zeros_like(X[0])
    q = top
    while q > 1:
        t = np.where((X[2] & q) != 0, t ^ (q - 1), t)
        q >>= 1
    X = [xi ^ t for xi in X]
    key = np.zeros_like(X[0])
    for bit in range(bits - 1, -1, -1):
        for i in range(3):
            key = (key << 1) | ((X[i] >> bit) & 1)
    return np.argsort(key, kind="stable").astype(np.int64)


def order_wisps(source, mode=None):
    """(source renumbered for the partition, order) for ``-lc_wisp_order`` ``mode``:
    ``spatial`` (the default) numbers the wisps along a Hilbert curve of their roots,
    so that each rank's contiguous share is compact in space whatever the scene's order
    (a groom file may interleave regions); ``input`` keeps the scene's order.
    ``order[i]`` is the scene's number of internal wisp i.  The order depends on the
    roots only, not on the rank count."""
    from lc_petsc.scene.sources import ReorderedSource, wisp_roots
    mode = mode or WISP_ORDERS[0]
    if mode not in WISP_ORDERS:
        raise ValueError(f"-lc_wisp_order {mode!r}: use spatial (wisps ordered along a "
                         f"space-filling curve of their roots, the default) or input (the "
                         f"scene's order)")
    identity = np.arange(source.n_wisps, dtype=np.int64)
    if mode == "input" or source.n_wisps < 2:
        return source, identity
    order = hilbert_order(wisp_roots(source))
    if np.array_equal(order, identity):
        return source, identity
    return ReorderedSource(source, order), order


class UserLayout:
    """The scene's own wisp order (the user's) next to the simulator's internal one.

    The simulator numbers wisps in ``order`` (internal wisp i is the scene's wisp
    ``order[i]``) and gives rank r the internal wisps ``ranges[r]:ranges[r+1]``; outputs
    (frames.h5, checkpoints, USD) keep the scene's order.  This is the rank's block of
    the *user* layout, the contiguous partition of the scene's wisps, with the same
    attributes the output code reads from a :class:`~lc_petsc.scene.state.LocalScene`:
    ``first_wisp``, ``first_vertex``, ``offsets``, ``x_rest``, ``pinned``, ``radius``.
    :meth:`to_user` moves per-vertex rows from the rank's internal rows to its user
    rows (one ``Alltoallv``), :meth:`from_user` back.  With ``order`` the identity both
    layouts are the same and nothing moves.
    """

    def __init__(self, comm, order, user_sizes, ranges, scene):
        order = np.asarray(order, np.int64)
        user_sizes = np.asarray(user_sizes, np.int64)
        n, P, r = len(order), comm.size, comm.rank
        self.comm, self.order = comm, order
        self.identity = bool(np.array_equal(order, np.arange(n)))
        user_ranges = np.asarray(ranges, np.int64) if self.identity else partition(user_sizes, P)
        user_off = np.concatenate([[0], np.cumsum(user_sizes)]).astype(np.int64)
        u0, u1 = int(user_ranges[r]), int(user_ranges[r + 1])
        self.first_wisp, self.first_vertex = u0, int(user_off[u0])
        self.offsets = user_off[u0:u1 + 1] - user_off[u0]
        self.nv = int(self.offsets[-1])
        internal_off = np.concatenate([[0], np.cumsum(user_sizes[order])]).astype(np.int64)
        self._internal_off, self._user_off = internal_off, user_off
        if not self.identity:
            dest = np.searchsorted(user_ranges, order, side="right") - 1      # per internal wisp
            self._send_rows, self._send_counts = self._rows(r, ranges, order, dest, internal_off,
                                                            internal_off[ranges[r]], P, by="dest")
            self._recv_rows, self._recv_counts = self._rows(r, ranges, order, dest, user_off,
                                                            self.first_vertex, P, by="source")
        self.x_rest = self.to_user(scene.x_rest)
        self.pinned = self.to_user(scene.pinned)
        self.radius = self.to_user(scene.radius)

    @staticmethod
    def _rows(r, ranges, order, dest, vertex_off, v0, P, by):
        """Local rows (and counts per peer) of the wisps this rank sends (``by="dest"``:
        its internal wisps grouped by destination) or receives (``by="source"``: its
        user wisps grouped by the rank that owns them internally), each group in
        increasing scene order; ``vertex_off`` numbers the rows of that layout."""
        if by == "dest":
            mine = np.arange(ranges[r], ranges[r + 1])
            peer = dest[mine]
        else:
            mine = np.flatnonzero(dest == r)
            peer = np.searchsorted(ranges, mine, side="right") - 1
        user = order[mine]
        sel = mine[np.lexsort((user, peer))]
        peer = np.searchsorted(ranges, sel, side="right") - 1 if by == "source" else dest[sel]
        wisp = sel if by == "dest" else order[sel]
        starts, sizes = vertex_off[wisp] - v0, vertex_off[wisp + 1] - vertex_off[wisp]
        rows = (np.concatenate([s + np.arange(n) for s, n in zip(starts, sizes)])
                if len(sel) else np.zeros(0, np.int64))
        counts = np.bincount(peer, weights=sizes, minlength=P).astype(np.int64)
        return rows.astype(np.int64), counts

    def _exchange(self, a, rows_out, counts_out, rows_in, counts_in, n_out):
        a = np.asarray(a)
        send = np.ascontiguousarray(a[rows_out])
        row_bytes = send.dtype.itemsize * int(np.prod(send.shape[1:], dtype=np.int64))
        recv = np.empty((len(rows_in),) + send.shape[1:], send.dtype)
        sc, rc = counts_out * row_bytes, counts_in * row_bytes
        sd = np.concatenate([[0], np.cumsum(sc)[:-1]])
        rd = np.concatenate([[0], np.cumsum(rc)[:-1]])
        from mpi4py import MPI
        self.comm.Alltoallv([send.view(np.uint8).reshape(-1), (sc, sd), MPI.BYTE],
                            [recv.view(np.uint8).reshape(-1), (rc, rd), MPI.BYTE])
        out = np.empty((n_out,) + send.shape[1:], send.dtype)
        out[rows_in] = recv
        return out

    def scene_numbers(self, wisp_vertex_pairs):
        """(wisp, global vertex, wisp, global vertex, ...) of the internal numbering ->
        the scene's numbers, for messages."""
        out = []
        for k, value in enumerate(wisp_vertex_pairs):
            if k % 2 == 0:
                out.append(int(self.order[value]))
            else:
                w = int(np.searchsorted(self._internal_off, value, side="right")) - 1
                out.append(int(self._user_off[self.order[w]] + value - self._internal_off[w]))
        return tuple(out)

    def to_user(self, a):
        """Per-vertex rows of this rank's internal wisps -> its rows of the user layout."""
        if self.identity:
            return a
        return self._exchange(a, self._send_rows, self._send_counts, self._recv_rows,
                              self._recv_counts, self.nv)

    def from_user(self, a):
        """Rows of this rank's block of the user layout -> its internal rows."""
        if self.identity:
            return a
        n_internal = int(self._send_counts.sum())
        return self._exchange(a, self._recv_rows, self._recv_counts, self._send_rows,
                              self._send_counts, n_internal)
