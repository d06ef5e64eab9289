"""ccd strand contact with step cutback (time.max_substeps): the frame's straight path
x_n -> x_{n+1}, the one between two rows of frames.h5 that the end-of-run check and a
viewer interpolate, must not cross, not only each substep's path.  The substeps' chain
is a curve; its chord can cut through a wisp the curve went around (60 soft wisps with
self-contact, 8 substeps a frame: 180 crossings between wisps and 51 within over 30
frames before the frame's own path was checked)."""

import numpy as np
from mpi4py import MPI

import lc_petsc.simulator as simmod
from lc_petsc.config import MaterialConfig, PhysicsConfig, SceneConfig, SimConfig, SolverConfig, TimeConfig
from lc_petsc.crossings import count_crossings
from lc_petsc.integrator import Integrator
from lc_petsc.scene.sources import ArraySource

N = 21                  # vertices per wisp, 0.5 cm apart
D0 = 0.2
DT = 0.1
G = 4000.0              # along -z


def orbit_source():
    """Wisp A along z with its tip at the origin, every vertex pinned; wisp B along x,
    1 cm above A and 1 cm back from A's tip, free."""
    s = np.arange(N) * 0.5
    A = np.stack([np.zeros(N), np.zeros(N), s - 10.0], 1)
    B = np.stack([s - 5.0, np.full(N, 1.0), np.full(N, -1.0)], 1)
    return ArraySource(np.concatenate([A, B]), [0, N, 2 * N], pinned=np.r_[np.ones(N, bool), np.zeros(N, bool)],
                       root_radius=0.05, tip_radius=0.05)


def run_orbit(monkeypatch, substeps):
    """B thrown down past A's height and out beyond A's tip, gravity along -z bringing it
    back within the frame: its path (the substeps') goes round A's tip, the straight
    path between the frame's ends goes through A.  One Newton iteration against a
    tolerance it cannot meet: every frame is cut into ``substeps``.  Returns (the frame's
    crossings, substeps, B's mean height at the end)."""
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: orbit_source())
    cfg = SimConfig(scene=SceneConfig(kind="straight"), material=MaterialConfig(youngs_modulus=1e9),
                    physics=PhysicsConfig(terms=("stretch", "bend", "gravity", "strand_collision"),
                                          gravity=(0.0, 0.0, -G), strand_thickness=D0,
                                          strand_contact_mode="ccd"),
                    time=TimeConfig(dt=DT, frames=1, newton_iterations=1, newton_increment_tol=1e-9,
                                    max_substeps=substeps),
                    solver=SolverConfig(options="-ksp_rtol 1e-12 -ksp_max_it 5000"))
    sim = simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
    try:
        b = sim.x[:, 1] > 0.5           # B's vertices (the partition may reorder the wisps)
        v = np.zeros_like(sim.x)
        v[b, 1] = -2.0 / DT             # from 1 cm above A to 1 cm below it over the frame
        v[b, 2] = G * DT / 2            # out to 4 cm beyond A's tip at mid-frame and back
        sim.integrator.v = v
        X0 = sim.gather_positions()
        sim.step()
        X1 = sim.gather_positions()
        return (count_crossings(X0, X1, [0, N, 2 * N])["crossings"], sim.integrator.newton_substeps[-1],
                float(X1[N:, 1].mean()))
    finally:
        sim.close()


def test_cut_back_frame_path_does_not_cross(monkeypatch):
    crossings, substeps, _ = run_orbit(monkeypatch, 8)
    assert substeps == 8
    assert crossings == 0


def test_without_the_frame_path_check_the_chord_crosses(monkeypatch):
    """The control: each substep's path is collision-free, their chord is not."""
    monkeypatch.setattr(Integrator, "_collision_free_frame_path", lambda self, x, t, last: last)
    crossings, substeps, y = run_orbit(monkeypatch, 8)
    assert substeps == 8
    assert y < -0.5                     # B went round A's tip to below it
    assert crossings > 0
