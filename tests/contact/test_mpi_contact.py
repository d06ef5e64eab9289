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


def run(c, newton_iterations):
    cfg = touching_wisps_config(10)
    cfg.time.newton_iterations = newton_iterations
    sim = simmod.build_simulator(cfg, comm=c)
    try:
        sim.run()
        X = sim.gather_positions()
        summ = sim.summary()
        cross = sum(sim.strand.cross_pairs.sums)
    finally:
        sim.close()
    return X, summ, cross


# Why two settings.  A fixed, small number of Newton iterations per frame is not the
# converged backward-Euler step, and with contact (active pairs switching, the end-of-frame
# separation of pairs left deep) its frame-to-frame map amplifies round-off.  Measured on
# this scene, relative difference to 1 rank after 10 frames (the first frame: 2e-14 to
# 5e-14): 3 iterations (the paper's) 7.4e-11 on 2 ranks and 1.3e-10 on 3 ranks on an AMD
# EPYC (1e-12 to 2e-11 on the CPU of earlier sessions); 4 iterations 2.3e-12 and 5.6e-13;
# 12 iterations 1.2e-14 and 1.8e-14.  So the 1e-10 check runs with 4 iterations, and the
# paper's 3 are checked at the level their amplification allows (a partition bug, e.g. a
# lost or doubled pair, shows as 1e-6 or more, and in the pair counts).
@pytest.mark.parametrize("newton_iterations, tolerance", [(4, 1e-10), (3, 1e-9)])
def test_rank_invariance_with_contact_10_frames(monkeypatch, newton_iterations, tolerance):
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: touching_wisps_source())
    X, summ, cross = run(comm, newton_iterations)
    ok, msg = True, ""
    if comm.rank == 0:
        ref, ref_summ, _ = run(MPI.COMM_SELF, newton_iterations)
        err = float(np.abs(X - ref).max() / np.abs(ref).max())
        pairs = summ["contact"]["pairs_per_frame"]
        separated = summ["contact"]["pairs_separated_per_frame"]
        ok = bool(np.all(np.isfinite(X))) and err <= tolerance and sum(pairs) > 0 \
            and sum(separated) > 0 and pairs == ref_summ["contact"]["pairs_per_frame"] \
            and separated == ref_summ["contact"]["pairs_separated_per_frame"]
        msg = (f"{comm.size} ranks, {newton_iterations} Newton iterations: relative difference "
               f"{err:.3e} (tolerance {tolerance:g}), pairs per frame {pairs} (serial "
               f"{ref_summ['contact']['pairs_per_frame']}), separated per frame {separated} "
               f"(serial {ref_summ['contact']['pairs_separated_per_frame']}), cross-rank pairs {cross}")
        print("\n" + msg)
    ok, msg = comm.bcast((ok, msg))
    assert ok, msg
    if comm.size > 1:    # the comparison covers pairs straddling ranks
        assert cross > 0, f"no contact pair straddled ranks on {comm.size} ranks"
