"""Checkpoints on every rank of COMM_WORLD (run by tests/test_mpi_launch.py under
mpiexec -n 2 and -n 3): a SIGUSR1 that reaches one rank only stops every rank after
the same frame with a checkpoint and exit status 75; the restart on the same ranks
continues to the serial result with each frame once; a corrupt dataset is rejected
on every rank with the same status, and so is a damaged HDF5 structure."""

import os
import signal

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.batch import EXIT_PREEMPTED, main
from lc_petsc.integrator import Integrator

from sim_helpers import hairball_toml, shared_scene_dir  # noqa: E402

pytestmark = pytest.mark.mpi
comm = MPI.COMM_WORLD

SCENE = hairball_toml(n_wisps=4, seed=7,
                      output="previews = false\nxdmf = false\ncheckpoint_every = 0")


@pytest.fixture
def shared_dir():
    with shared_scene_dir(comm, "lc_mpi_ckpt_", SCENE) as folder:
        yield folder


def _agree(ok, msg):
    ok, msg = comm.bcast((ok, msg))
    assert ok, msg


def test_signal_on_one_rank_stops_all(shared_dir, monkeypatch):
    d, cfg = shared_dir
    out = os.path.join(d, "out")
    step = Integrator.step

    def step_and_signal(self):
        step(self)
        if self.frame == 2 and comm.rank == comm.size - 1:
            signal.raise_signal(signal.SIGUSR1)

    monkeypatch.setattr(Integrator, "step", step_and_signal)
    code = main([cfg, "--out", out, "--quiet"], comm=comm)
    monkeypatch.setattr(Integrator, "step", step)
    assert comm.allgather(code) == [EXIT_PREEMPTED] * comm.size
    names = comm.bcast(sorted(os.listdir(os.path.join(out, "checkpoints"))) if comm.rank == 0 else None)
    assert names == ["checkpoint_000002.h5"]
    code = main([cfg, "--out", out, "--quiet", "--restart", "latest"], comm=comm)
    assert comm.allgather(code) == [0] * comm.size
    ok, msg = True, ""
    if comm.rank == 0:
        ref = os.path.join(d, "ref")
        assert main([cfg, "--out", ref, "--quiet"], comm=MPI.COMM_SELF) == 0
        with h5py.File(os.path.join(out, "frames.h5"), "r") as a, \
                h5py.File(os.path.join(ref, "frames.h5"), "r") as b:
            if a["positions"].shape != b["positions"].shape or not np.array_equal(a["time"][...], b["time"][...]):
                ok, msg = False, f"frames: {a['positions'].shape} {a['time'][...]} vs {b['time'][...]}"
            else:
                err = np.abs(a["positions"][...] - b["positions"][...]).max() / np.abs(b["positions"][...]).max()
                ok, msg = err <= 1e-10, f"positions differ by {err:.2e} on {comm.size} ranks"
    _agree(ok, msg)


def _byte_in_the_last_ranks_rows(ck):
    with h5py.File(ck, "r") as f:
        off = f["positions"].id.get_offset()
    with open(ck, "r+b") as fh:
        fh.seek(off + 350 * 24 + 8)
        fh.write(b"\xff")


def _object_header(ck, seal=True):
    """Its version byte; without the seal (a checkpoint written before it) h5py's
    KeyError on it was raised on rank 0 alone, in the serial check the other ranks wait
    for (a traceback, or a hang in the broadcast)."""
    with h5py.File(ck, "r") as f:
        addr = f.userblock_size + h5py.h5o.get_info(f["head_state"].id).addr
    with open(ck, "r+b") as fh:
        if not seal:
            fh.write(bytes(512))
        fh.seek(addr)
        fh.write(b"\x07")


@pytest.mark.parametrize("damage, message", [
    (_byte_in_the_last_ranks_rows, "/positions fails its checksum"),
    (_object_header, "corrupt checkpoint: its HDF5 metadata (all but the datasets' values) fails its checksum"),
    (lambda ck: _object_header(ck, seal=False), "corrupt checkpoint: its HDF5 structure is damaged"),
])
def test_corrupt_checkpoint_rejected_on_every_rank(shared_dir, capsys, damage, message):
    d, cfg = shared_dir
    out = os.path.join(d, "out")
    ck = os.path.join(out, "checkpoints", "checkpoint_000002.h5")
    over = os.path.join(d, "c.toml")
    if comm.rank == 0:
        with open(over, "w") as f:
            f.write(SCENE.replace("checkpoint_every = 0", "checkpoint_every = 2"))
    comm.Barrier()
    assert comm.allgather(main([over, "--out", out, "--quiet", "--frames", "2"], comm=comm)) == [0] * comm.size
    if comm.rank == 0:
        damage(ck)
    comm.Barrier()
    capsys.readouterr()
    code = main([over, "--out", out, "--quiet", "--restart", ck, "--frames", "3"], comm=comm)
    assert comm.allgather(code) == [2] * comm.size
    err = capsys.readouterr().err
    if comm.rank == 0:
        assert message in err and ck in err, err


def test_restart_from_an_earlier_checkpoint_rewrites_every_time_row(shared_dir):
    """A restart from a checkpoint before frames.h5's last row cuts /time back and
    writes it again: every row must hold its frame's time (libhdf5's mpio driver lost
    the writes into the chunk the cut had just shortened: rows of 0.0, which the USD
    export and the previews read as the head at t = 0)."""
    d, _ = shared_dir
    out = os.path.join(d, "out")
    over = os.path.join(d, "c.toml")
    if comm.rank == 0:
        with open(over, "w") as f:
            f.write(SCENE.replace("checkpoint_every = 0", "checkpoint_every = 2"))
    comm.Barrier()
    path = os.path.join(out, "frames.h5")
    assert comm.allgather(main([over, "--out", out, "--quiet", "--frames", "5"], comm=comm)) == [0] * comm.size
    before = _read_on_root(path)
    ck = os.path.join(out, "checkpoints", "checkpoint_000002.h5")
    code = main([over, "--out", out, "--quiet", "--restart", ck, "--frames", "6"], comm=comm)
    assert comm.allgather(code) == [0] * comm.size
    after = _read_on_root(path)
    ok, msg = True, ""
    if comm.rank == 0:
        (_, x0), (t, x) = before, after
        ok, msg = np.allclose(t, np.arange(7) / 30.0, rtol=0, atol=1e-15), f"/time after the restart: {t}"
        if ok:
            ok, msg = np.array_equal(x[:6], x0), "the rewritten frames 3-5 differ from the first run's"
    _agree(ok, msg)


def _read_on_root(path):
    """(time, positions) of a frames.h5 on rank 0 (None elsewhere), after every rank closed it."""
    comm.Barrier()
    if comm.rank != 0:
        return None
    with h5py.File(path, "r") as f:
        return f["time"][...], f["positions"][...]
