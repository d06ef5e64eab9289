"""Phase timers (lc_petsc/timing.py): wall and CPU time per phase, and the frame
timer of the benchmarks."""

import time

from mpi4py import MPI

from lc_petsc.config import PhysicsConfig, SceneConfig, SimConfig, TimeConfig
from lc_petsc.simulator import build_simulator
from lc_petsc.timing import PHASES, Timers, frame_timing, timed_frame


def _spin(seconds):
    t0 = time.process_time()
    while time.process_time() - t0 < seconds:
        pass


def test_cpu_time_counts_work_not_waiting():
    t = Timers()
    with t("solve"):
        _spin(0.05)
    with t("io"):
        time.sleep(0.1)
    cpu, wall = t.cpu_dict(), t.as_dict()
    assert cpu["solve"] >= 0.05 and wall["solve"] >= cpu["solve"] - 1e-3
    assert wall["io"] >= 0.1 and cpu["io"] < 0.05          # sleeping costs no CPU
    assert set(cpu) == set(wall) == set(PHASES)
    cpu["solve"] = -1.0                                     # a copy
    assert t.cpu_dict()["solve"] >= 0.05


def test_frame_timing_reports_cpu_per_phase_and_the_update():
    cfg = SimConfig(scene=SceneConfig(kind="hairball", n_wisps=6),
                    physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity")),
                    time=TimeConfig(frames=2, newton_iterations=2))
    sim = build_simulator(cfg, MPI.COMM_WORLD)
    try:
        f = frame_timing(sim)
        assert f.wall > 0 and f.cpu_total > 0 and len(f.ksp) == 2
        assert f.cpu["elements"] > 0 and f.cpu["solve"] > 0
        assert f.phases["update"] > 0 and f.cpu["update"] > 0    # the edge retraction
        assert f.cpu["io"] == 0.0
        wall, phases, ksp = timed_frame(sim)
        assert wall > 0 and phases["elements"] > 0 and len(ksp) == 2
    finally:
        sim.close()
