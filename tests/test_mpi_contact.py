"""Rank invariance with strand-strand contact; run serially and by tests/test_mpi_launch.py
under mpiexec -n 2 and -n 3.  The COMM_WORLD run is compared with the same run on
COMM_SELF on rank 0."""

import numpy as np
import pytest
from mpi4py import MPI

import lc_petsc.simulator as simmod
from lc_petsc.config import (MaterialConfig, PhysicsConfig, SceneConfig, SimConfig, SolverConfig,
                             TimeConfig)
from lc_petsc.scene import geometry
from lc_petsc.scene.sources import ArraySource

pytestmark = pytest.mark.mpi
comm = MPI.COMM_WORLD
N_WISPS, N_VERT = 6, 30


def hairball_source():
    """Six short 4C wisps hanging from a row of roots 0.9 cm apart (coil diameter 1 cm):
    neighbours touch and interleave, so contact pairs form between wisps 1-2 and 3-4,
    which sit on different ranks with 3 ranks (and 2-3 with 2 ranks)."""
    wisps = [geometry.wisp4c(N_VERT, root=(0.9 * w, 16.0, 0.0), spin=1.3 * w) for w in range(N_WISPS)]
    pos = np.concatenate(wisps)
    off = np.arange(N_WISPS + 1) * N_VERT
    pin = np.zeros(len(pos), bool)
    for w in range(N_WISPS):
        pin[w * N_VERT: w * N_VERT + 4] = True
    return ArraySource(pos, off, pinned=pin, root_radius=0.08, tip_radius=0.05)


def contact_config(frames):
    return SimConfig(
        scene=SceneConfig(kind="straight"),
        material=MaterialConfig(youngs_modulus=2.0e7),
        physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity", "strand_collision"),
                              head_motion="shake", head_amplitude=0.3, head_period=0.5,
                              strand_thickness=0.12, strand_stiffness=1.0e4),
        time=TimeConfig(frames=frames),
        # a tight tolerance: with contact CG takes several iterations, and the 1e-10
        # comparison must not depend on where round-off stops it
        solver=SolverConfig(options="-ksp_rtol 1e-14 -ksp_max_it 5000"))


def run(c):
    sim = simmod.build_simulator(contact_config(10), comm=c)
    try:
        sim.run()
        X = sim.gather_positions()
        summ = sim.summary()
        cross = sum(sim.strand.cross_pairs)
    finally:
        sim.close()
    return X, summ, cross


def test_rank_invariance_with_contact_10_frames(monkeypatch):
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: hairball_source())
    X, summ, cross = run(comm)
    ok, msg = True, ""
    if comm.rank == 0:
        ref, ref_summ, _ = run(MPI.COMM_SELF)
        err = float(np.abs(X - ref).max() / np.abs(ref).max())
        pairs = summ["contact"]["pairs_per_frame"]
        ok = bool(np.all(np.isfinite(X))) and err <= 1e-10 and sum(pairs) > 0 \
            and pairs == ref_summ["contact"]["pairs_per_frame"]
        msg = (f"{comm.size} ranks: relative difference {err:.3e}, pairs per frame {pairs} "
               f"(serial {ref_summ['contact']['pairs_per_frame']}), cross-rank pairs {cross}")
        print("\n" + msg)
    ok, msg = comm.bcast((ok, msg))
    assert ok, msg
    if comm.size > 1:    # the comparison covers pairs straddling ranks
        assert cross > 0, f"no contact pair straddled ranks on {comm.size} ranks"
