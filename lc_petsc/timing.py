"""Phase timers: one PETSc log event per phase (``-log_view`` shows them) plus wall-clock
totals in a dict for summary.json."""

from __future__ import annotations

import time
from contextlib import contextmanager

from petsc4py import PETSc

PHASES = ("elements", "filter", "assembly", "solve", "collision", "io")
_EVENTS: dict[str, PETSc.Log.Event] = {}


def _event(name):
    if name not in _EVENTS:
        _EVENTS[name] = PETSc.Log.Event(f"LC_{name}")
    return _EVENTS[name]


class Timers:
    """Wall-clock totals per phase (``with timers("solve"): ...``), each phase also a
    PETSc log event."""

    def __init__(self):
        self.totals = {p: 0.0 for p in PHASES}

    @contextmanager
    def __call__(self, phase):
        """Time the block as ``phase`` (wall clock and PETSc log event)."""
        ev = _event(phase)
        ev.begin()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.totals[phase] = self.totals.get(phase, 0.0) + time.perf_counter() - t0
            ev.end()

    def as_dict(self):
        """{phase: seconds so far} (a copy)."""
        return dict(self.totals)


def timed_frame(sim):
    """Step the simulator ``sim`` by one frame between two barriers (the benchmarks' frame
    timer).  Returns (wall seconds, {phase: this frame's seconds, maximum over ranks},
    [KSP iterations of the frame's linear solves])."""
    from lc_petsc.parallel import global_max
    comm = sim.comm
    before = sim.timers.as_dict()
    n_ksp = len(sim.solver.iterations)
    comm.Barrier()
    t0 = time.perf_counter()
    sim.step()
    comm.Barrier()
    wall = time.perf_counter() - t0
    after = sim.timers.as_dict()
    phases = {k: global_max(comm, after[k] - before.get(k, 0.0)) for k in after}
    return wall, phases, sim.solver.iterations[n_ksp:]
