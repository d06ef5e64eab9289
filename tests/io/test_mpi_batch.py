"""The main job on every rank of COMM_WORLD (run by tests/test_mpi_launch.py under
mpiexec -n 2 and -n 3): frames.h5 written collectively equals the serial file up to
round-off (3 wisps on 3 ranks: one each); a bad config is reported
by rank 0 only and every rank returns the same status."""

import os
import shutil
import tempfile

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.batch import main
from lc_petsc.io.frames import row_digest, vertex_digest

from sim_helpers import hairball_toml  # noqa: E402

pytestmark = pytest.mark.mpi
comm = MPI.COMM_WORLD

SCENE = hairball_toml(n_wisps="{n}", seed=5, output="every = 2\npreviews = false")


@pytest.fixture
def shared_dir():
    d = comm.bcast(tempfile.mkdtemp(prefix="lc_mpi_batch_") if comm.rank == 0 else None)
    yield d
    comm.Barrier()
    if comm.rank == 0:
        shutil.rmtree(d, ignore_errors=True)


@pytest.mark.parametrize("n_wisps", [3, 7])
def test_collective_frames_equal_serial(shared_dir, n_wisps):
    cfg = os.path.join(shared_dir, f"s{n_wisps}.toml")
    if comm.rank == 0:
        with open(cfg, "w") as f:
            f.write(SCENE.format(n=n_wisps))
    comm.Barrier()
    par, ser = os.path.join(shared_dir, f"par{n_wisps}"), os.path.join(shared_dir, f"ser{n_wisps}")
    code = main([cfg, "--out", par, "--quiet"], comm=comm)
    assert comm.allgather(code) == [0] * comm.size
    ok, msg = True, ""
    if comm.rank == 0:
        assert main([cfg, "--out", ser, "--quiet"], comm=MPI.COMM_SELF) == 0
        with h5py.File(os.path.join(par, "frames.h5"), "r") as a, \
                h5py.File(os.path.join(ser, "frames.h5"), "r") as b:
            for k in b:
                if a[k].shape != b[k].shape or a[k].dtype != b[k].dtype:
                    ok, msg = False, f"{k}: {a[k].shape} {a[k].dtype} vs {b[k].shape} {b[k].dtype}"
                elif k == "row_digest":     # written in parts by the ranks: the whole row's
                    want = [row_digest([vertex_digest(a["positions"][r], 0)], r, a["time"][r])
                            for r in range(a[k].shape[0])]
                    if a[k][...].tolist() != want:
                        ok, msg = False, f"row_digest is not the rows' digest on {comm.size} ranks"
                elif k == "positions":
                    err = np.abs(a[k][...] - b[k][...]).max() / np.abs(b[k][...]).max()
                    if not err <= 1e-10:
                        ok, msg = False, f"positions differ by {err:.2e} on {comm.size} ranks"
                elif not np.array_equal(a[k][...], b[k][...]):
                    ok, msg = False, f"{k} differs on {comm.size} ranks"
            if a.attrs["ranks"] != comm.size or a["positions"].shape[0] != 3:
                ok, msg = False, "attributes / frame count"
    ok, msg = comm.bcast((ok, msg))
    assert ok, msg


def test_bad_config_reported_by_rank_0_only(shared_dir, capsys):
    cfg = os.path.join(shared_dir, "bad.toml")
    if comm.rank == 0:
        with open(cfg, "w") as f:
            f.write(SCENE.format(n=3).replace("frames = 5", "frames = -5"))
    comm.Barrier()
    code = main([cfg, "--out", os.path.join(shared_dir, "o")], comm=comm)
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("time.frames must be an integer >= 0, got -5") == (1 if comm.rank == 0 else 0)
    assert not os.path.exists(os.path.join(shared_dir, "o"))
