"""A restart with --force into a new frames.h5 (the run's was deleted), on every rank
of COMM_WORLD (run by tests/test_mpi_launch.py under mpiexec -n 2 and -n 3 too): the
rows come from the checkpoints (rank 0 reads them, every rank writes collectively),
the lost ones are NaN and marked, and the continuation is bit for bit the straight run
on the same ranks."""

import os

import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.batch import main
from lc_petsc.io import read_frames

from sim_helpers import hairball_toml, shared_scene_dir  # noqa: E402

pytestmark = pytest.mark.mpi
comm = MPI.COMM_WORLD

SCENE = hairball_toml(n_wisps=4, seed=7, frames=6,
                      output="previews = false\ncheckpoint_every = 2\ncheckpoints_kept = 3")


def _all(code):
    return comm.allgather(code)


def test_deleted_frames_file_continues_on_every_rank():
    with shared_scene_dir(comm, "lc_mpi_recover_", SCENE) as (d, cfg):
        out, ref = os.path.join(d, "out"), os.path.join(d, "ref")
        assert _all(main([cfg, "--out", ref, "--quiet"], comm=comm)) == [0] * comm.size
        assert _all(main([cfg, "--out", out, "--quiet", "--frames", "4"], comm=comm)) == [0] * comm.size
        if comm.rank == 0:
            os.unlink(os.path.join(out, "frames.h5"))
        comm.Barrier()
        code = main([cfg, "--out", out, "--quiet", "--restart", "latest"], comm=comm)
        assert _all(code) == [2] * comm.size
        code = main([cfg, "--out", out, "--quiet", "--restart", "latest", "--force"], comm=comm)
        assert _all(code) == [0] * comm.size
        ok, msg = True, ""
        if comm.rank == 0:
            a, b = read_frames(os.path.join(out, "frames.h5")), read_frames(os.path.join(ref, "frames.h5"))
            kept, lost = [2, 4, 5, 6], [0, 1, 3]
            if a["frame_valid"].tolist() != [k not in lost for k in range(7)]:
                ok, msg = False, f"/frame_valid {a['frame_valid']}"
            elif not (np.array_equal(a["positions"][kept], b["positions"][kept])
                      and np.array_equal(a["time"][kept], b["time"][kept])):
                ok, msg = False, f"recovered or continued rows differ from the straight run on {comm.size} ranks"
            elif not np.isnan(a["positions"][lost]).all():
                ok, msg = False, "a lost row holds numbers"
        ok, msg = comm.bcast((ok, msg))
        assert ok, msg
