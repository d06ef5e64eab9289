"""A signal during the main job's end-of-run work (the crossing and head check, the
exports), told to every rank without waiting for a collective call.

The frame loop agrees on a signal with an allreduce at each frame end; after it the
ranks do long work of uneven length (each its share of the check's steps, rank 0 alone
the exports) and a signal may reach one rank only.  :class:`StopNotice` lets each rank
look, between two pieces of that work, whether it or any other rank got one: a rank
that sees its own flag sends a one-integer notice to every other rank (once), the
others find it with ``Iprobe``.  Waiting for the others polls too (:meth:`wait`), so a
rank that finished its share still hears and passes on a signal.  :meth:`close` is
collective: every notice sent is received before the communicator is freed.
"""

from __future__ import annotations

import time

import numpy as np

class Stopped(Exception):
    """Raised by the main job's ``stop`` callback inside a long end-of-run export (the
    previews, the USD export) on a signal: the export is skipped (control flow of the
    job, like the studies' private signals: not an error of lc_petsc.errors)."""


#: the message tag of a notice (on a communicator of its own)
TAG = 75
#: how often a waiting rank looks (seconds)
POLL = 0.005


class StopNotice:
    """Collective constructor over the mpi4py communicator ``comm``; ``flag()``: whether
    this rank received a signal (the job's :class:`~lc_petsc.job.Preemption`)."""

    def __init__(self, comm, flag):
        self.comm = comm.Dup() if comm.size > 1 else None
        self.flag = flag
        self.heard = False
        self._sent, self._buf = [], np.ones(1, np.intc)

    def requested(self):
        """Whether this rank or another received a signal (once True, stays True)."""
        if self.flag():
            self._tell_others()
            self.heard = True
        elif not self.heard and self.comm is not None:
            self.heard = bool(self.comm.Iprobe(tag=TAG))
        return self.heard

    def _tell_others(self):
        if self.comm is None or self._sent:
            return
        self._sent = [self.comm.Isend(self._buf, dest=r, tag=TAG)
                      for r in range(self.comm.size) if r != self.comm.rank]

    def wait(self, request):
        """Complete the nonblocking MPI ``request``, looking for signals meanwhile."""
        while not request.Test():
            self.requested()
            time.sleep(POLL)

    def barrier(self):
        """Collective: wait for every rank (a signal here is still passed on)."""
        if self.comm is not None:
            self.wait(self.comm.Ibarrier())

    def close(self):
        """Collective: receive the notices the other ranks sent, free the communicator."""
        if self.comm is None:
            return
        from mpi4py import MPI
        senders = self.comm.allgather(bool(self._sent))
        buf = np.empty(1, np.intc)
        for r, sent in enumerate(senders):
            if sent and r != self.comm.rank:
                self.comm.Recv(buf, source=r, tag=TAG)
        MPI.Request.Waitall(self._sent)
        self.comm.Free()
        self.comm, self._sent = None, []
