"""Rank invariance with strand-strand contact; run serially and by tests/test_mpi_launch.py
under mpiexec -n 2 and -n 3.  The COMM_WORLD run is compared with the same run on
COMM_SELF on rank 0."""

import numpy as np
import pytest
from mpi4py import MPI

import lc_petsc.simulator as simmod
from sim_helpers import touching_wisps_config, touching_wisps_source

pytestmark = pytest.mark.mpi
comm = MPI.COMM_WORLD


def run(c):
    sim = simmod.build_simulator(touching_wisps_config(10), comm=c)
    try:
        sim.run()
        X = sim.gather_positions()
        summ = sim.summary()
        cross = sum(sim.strand.cross_pairs)
    finally:
        sim.close()
    return X, summ, cross


def test_rank_invariance_with_contact_10_frames(monkeypatch):
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: touching_wisps_source())
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
