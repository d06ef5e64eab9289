"""Phase timers: one PETSc log event per phase (``-log_view`` shows them) plus wall-clock
totals in a dict for summary.json."""

from __future__ import annotations

import time
from contextlib import contextmanager

from petsc4py import PETSc

PHASES = ("elements", "filter", "assembly", "solve", "collision", "io")
_EVENTS = {}


def _event(name):
    if name not in _EVENTS:
        _EVENTS[name] = PETSc.Log.Event(f"LC_{name}")
    return _EVENTS[name]


class Timers:
    def __init__(self):
        self.totals = {p: 0.0 for p in PHASES}

    @contextmanager
    def __call__(self, phase):
        ev = _event(phase)
        ev.begin()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.totals[phase] = self.totals.get(phase, 0.0) + time.perf_counter() - t0
            ev.end()

    def as_dict(self):
        return dict(self.totals)
