"""Phase timers: one PETSc log event per phase (``-log_view`` shows them) plus wall-clock
and CPU-time totals in dicts (wall for summary.json, both for the benchmarks).

CPU time is the process's (``time.process_time``: user + system of all its threads).
On a machine shared with other jobs it is the figure that measures the work: wall time
also holds the time the process waited for a core.
"""

from __future__ import annotations

import resource
import time
from contextlib import contextmanager
from dataclasses import dataclass

from petsc4py import PETSc

#: ``filter`` is never entered: the eigen-filters run inside the fused element kernels
#: (timed as ``elements``); it stays for DESIGN's phase list of summary.json (always 0).
#: ``update``: the Newton update after the solve (``Integrator.update``: the edge
#: retraction), the root turn (``time.root_rotation``, its head passes included) and the
#: final rest-length projection.
PHASES = ("elements", "filter", "assembly", "solve", "collision", "update", "io")
_EVENTS: dict[str, PETSc.Log.Event] = {}


def _event(name):
    if name not in _EVENTS:
        _EVENTS[name] = PETSc.Log.Event(f"LC_{name}")
    return _EVENTS[name]


class Timers:
    """Wall-clock and CPU-time totals per phase (``with timers("solve"): ...``), each
    phase also a PETSc log event.  A phase entered inside another (same or other name)
    is counted in both."""

    def __init__(self):
        self.totals = {p: 0.0 for p in PHASES}
        self.cpu = {p: 0.0 for p in PHASES}

    @contextmanager
    def __call__(self, phase):
        """Time the block as ``phase`` (wall clock, CPU time and PETSc log event)."""
        ev = _event(phase)
        ev.begin()
        c0 = time.process_time()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.totals[phase] = self.totals.get(phase, 0.0) + time.perf_counter() - t0
            self.cpu[phase] = self.cpu.get(phase, 0.0) + time.process_time() - c0
            ev.end()

    def reset(self):
        """Every total back to zero (the main job's frame loop starts: its phases span
        its wall time, without the set-up's)."""
        self.totals = dict.fromkeys(PHASES, 0.0)
        self.cpu = dict.fromkeys(PHASES, 0.0)

    def as_dict(self):
        """{phase: wall seconds so far} (a copy)."""
        return dict(self.totals)

    def cpu_dict(self):
        """{phase: CPU seconds so far} (a copy)."""
        return dict(self.cpu)


@dataclass
class FrameTiming:
    """One frame's figures (:func:`frame_timing`): ``wall`` seconds; ``phases`` {phase:
    wall seconds, maximum over ranks}; ``ksp`` the KSP iterations of the frame's linear
    solves; ``cpu`` {phase: CPU seconds, maximum over ranks}; ``cpu_total`` the frame's
    CPU seconds summed over the ranks (the job's work)."""

    wall: float
    phases: dict
    ksp: list
    cpu: dict
    cpu_total: float


def frame_timing(sim):
    """Step the simulator ``sim`` by one frame between two barriers (the benchmarks' frame
    timer); returns its :class:`FrameTiming`.  Collective."""
    from lc_petsc.parallel import global_max
    comm = sim.comm
    before, cpu_before = sim.timers.as_dict(), sim.timers.cpu_dict()
    n_ksp = len(sim.solver.iterations)
    comm.Barrier()
    t0 = time.perf_counter()
    c0 = time.process_time()
    sim.step()
    c1 = time.process_time()
    comm.Barrier()
    wall = time.perf_counter() - t0
    after, cpu_after = sim.timers.as_dict(), sim.timers.cpu_dict()
    phases = {k: global_max(comm, after[k] - before.get(k, 0.0)) for k in after}
    cpu = {k: global_max(comm, cpu_after[k] - cpu_before.get(k, 0.0)) for k in cpu_after}
    return FrameTiming(wall, phases, sim.solver.iterations[n_ksp:], cpu, comm.allreduce(c1 - c0))


def timed_frame(sim):
    """:func:`frame_timing` as (wall seconds, {phase: wall seconds, maximum over ranks},
    [KSP iterations of the frame's linear solves])."""
    f = frame_timing(sim)
    return f.wall, f.phases, f.ksp


def peak_rss_mib() -> float:
    """Peak resident set size of this process over its whole life (MiB; Linux reports
    ``ru_maxrss`` in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
