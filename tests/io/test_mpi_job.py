"""The main job on every rank of COMM_WORLD (run by tests/test_mpi_launch.py under
mpiexec -n 2 and -n 3): an element error on one rank ends the run on every rank with
exit status 3, summary.json and the frames so far; SIGINT on one rank checkpoints and
exits 75; a full disk (a tmpfs mounted by rank 0) stops every rank with exit 3; a bad
strands file is reported once, by rank 0."""

import json
import os
import signal
import subprocess

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.assembly import Assembler
from lc_petsc.batch import EXIT_PREEMPTED, main
from lc_petsc.integrator import Integrator
from lc_petsc.io.disk import RESERVE

from sim_helpers import hairball_toml, shared_scene_dir  # noqa: E402

pytestmark = pytest.mark.mpi
comm = MPI.COMM_WORLD
LAST = comm.size - 1

SCENE = hairball_toml(n_wisps=4, seed=7, frames=8,
                      output="previews = false\nxdmf = false\ncheckpoint_every = 2")


@pytest.fixture
def shared_dir():
    with shared_scene_dir(comm, "lc_mpi_job_", SCENE) as folder:
        yield folder


def _on_root(fn):
    """fn() on rank 0, its result (or the assertion error) on every rank."""
    res = None
    if comm.rank == 0:
        try:
            res = ("ok", fn())
        except AssertionError as e:
            res = ("fail", str(e))
    res = comm.bcast(res)
    assert res[0] == "ok", res[1]
    return res[1]


def test_element_error_on_one_rank_ends_as_exit_3(shared_dir, monkeypatch, capsys):
    d, cfg = shared_dir
    out = os.path.join(d, "out")
    assemble = Assembler.assemble
    calls = []

    def failing(self, x, mass=None):
        calls.append(1)
        if comm.rank == LAST and len(calls) == 10:     # frame 3 -> 4, first Newton iteration
            raise ValueError("injected element failure")
        return assemble(self, x, mass)

    monkeypatch.setattr(Assembler, "assemble", failing)
    code = main([cfg, "--out", out, "--quiet"], comm=comm)
    assert comm.allgather(code) == [3] * comm.size
    err = capsys.readouterr().err
    assert "Traceback" not in err

    def check():
        s = json.load(open(os.path.join(out, "summary.json")))
        assert f"rank {LAST}: ValueError: injected element failure" in s["error"], s["error"]
        assert s["converged"] is False and s["frames"] == 3
        with h5py.File(os.path.join(out, "frames.h5"), "r") as f:
            assert f["positions"].shape[0] == 4 and np.isfinite(f["positions"][...]).all()
        assert sorted(os.listdir(os.path.join(out, "checkpoints"))) == ["checkpoint_000002.h5"]
        assert "injected element failure" in err
    _on_root(check)


def test_sigint_on_one_rank_checkpoints_and_exits_75(shared_dir, monkeypatch):
    d, cfg = shared_dir
    out = os.path.join(d, "out")
    step = Integrator.step

    def step_and_interrupt(self):
        step(self)
        if self.frame == 3 and comm.rank == LAST:
            signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(Integrator, "step", step_and_interrupt)
    code = main([cfg, "--out", out, "--quiet"], comm=comm)
    assert comm.allgather(code) == [EXIT_PREEMPTED] * comm.size

    def check():
        s = json.load(open(os.path.join(out, "summary.json")))
        assert s["preempted"] == "SIGINT" and s["frames"] == 3
        assert sorted(os.listdir(os.path.join(out, "checkpoints"))) == ["checkpoint_000002.h5",
                                                                         "checkpoint_000003.h5"]
    _on_root(check)


def test_full_disk_stops_every_rank(shared_dir, monkeypatch):
    d, cfg = shared_dir
    vol = os.path.join(d, "vol")

    def mount():
        os.mkdir(vol)
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", vol],
                           capture_output=True, text=True)
        assert r.returncode == 0, f"cannot mount a tmpfs (the test needs root): {r.stderr}"
    _on_root(mount)
    out = os.path.join(vol, "out")
    step = Integrator.step

    def step_and_fill(self):
        step(self)
        if self.frame == 5 and comm.rank == 0:
            st = os.statvfs(vol)
            with open(os.path.join(vol, "filler"), "wb") as fh:
                fh.write(b"\0" * max(st.f_bavail * st.f_frsize - RESERVE // 2, 0))
    monkeypatch.setattr(Integrator, "step", step_and_fill)
    try:
        code = main([cfg, "--out", out, "--quiet"], comm=comm)
        assert comm.allgather(code) == [3] * comm.size

        def check():
            s = json.load(open(os.path.join(out, "summary.json")))
            assert "frames.h5: disk full" in s["error"], s["error"]
            with h5py.File(os.path.join(out, "frames.h5"), "r") as f:
                assert f["positions"].shape[0] == 5
            assert sorted(os.listdir(os.path.join(out, "checkpoints"))) == ["checkpoint_000002.h5",
                                                                             "checkpoint_000004.h5"]
        _on_root(check)
    finally:
        comm.Barrier()
        if comm.rank == 0:
            subprocess.run(["umount", "-l", vol], check=True)


def _refused(cfg, d, capsys, said):
    """Run the job of ``cfg`` into ``d``/o on every rank: exit 2 on every rank, ``said``
    printed once, by rank 0, no traceback, nothing written; returns the stderr."""
    code = main([cfg, "--out", os.path.join(d, "o"), "--quiet"], comm=comm)
    assert comm.allgather(code) == [2] * comm.size
    err = capsys.readouterr().err
    assert comm.allgather(err.count(said)) == [1] + [0] * LAST, err
    assert "Traceback" not in err
    assert not os.path.exists(os.path.join(d, "o"))
    return err


def test_bad_strands_file_reported_once(shared_dir, capsys):
    d, _ = shared_dir
    g = os.path.join(d, "g.h5")
    cfg = os.path.join(d, "f.toml")
    if comm.rank == 0:
        with open(g, "wb") as fh:
            fh.write(b"")
        with open(cfg, "w") as fh:
            fh.write(f'[scene]\nkind = "file"\npath = "{g}"\n')
    comm.Barrier()
    code = main([cfg, "--out", os.path.join(d, "o"), "--quiet"], comm=comm)
    assert comm.allgather(code) == [2] * comm.size
    err = capsys.readouterr().err
    n_reports = comm.allgather(err.count("is empty (0 bytes)"))
    assert n_reports == [1] + [0] * (comm.size - 1), n_reports
    assert "Traceback" not in err


def test_a_signal_on_one_rank_during_the_crossing_check_stops_every_rank(shared_dir, monkeypatch):
    """SIGTERM to the last rank alone at its first step of the end-of-run crossing check
    (8 steps, shared by the ranks): every rank checked its whole share, the others
    never learnt of the signal.  Now each rank stops at its next step (the others hear
    of it between two steps, or while they wait), every rank exits 75, the check and
    the exports are skipped, a checkpoint of frame 8 is written (the newest was frame
    6), and --restart latest completes the check over all 8 steps without running a
    frame."""
    import time
    import lc_petsc.crossings as crossings
    d, cfg = shared_dir
    out = os.path.join(d, "out")
    count, calls = crossings.count_crossings, []

    def signalled(*args, **kwargs):
        calls.append(1)
        if comm.rank == LAST and len(calls) == 1:
            os.kill(os.getpid(), signal.SIGTERM)
        elif comm.rank != LAST:
            time.sleep(0.5)             # so that the notice arrives before the share is done
        return count(*args, **kwargs)
    with monkeypatch.context() as m:
        m.setattr(crossings, "count_crossings", signalled)
        code = main([cfg, "--out", out, "--quiet"], comm=comm)
    assert comm.allgather(code) == [EXIT_PREEMPTED] * comm.size
    done = comm.allgather(len(calls))
    assert done[LAST] == 1 and max(done) <= 2, done          # main: 8 // size each

    def check():
        s = json.load(open(os.path.join(out, "summary.json")))
        assert s["preempted"] == "SIGTERM" and s["crossings"] is None
        assert s["output"]["skipped"] == ["crossing check", "frames.usdc"]
        assert [c["frame"] for c in s["checkpoints"]] == [2, 4, 6, 8]
    _on_root(check)
    code = main([cfg, "--out", out, "--quiet", "--restart", "latest"], comm=comm)
    assert comm.allgather(code) == [0] * comm.size

    def complete():
        s = json.load(open(os.path.join(out, "summary.json")))
        assert s["frames_this_run"] == 0 and s["crossings"]["steps"] == 8 and s["output"]["skipped"] == []
        assert os.path.exists(os.path.join(out, "frames.usdc"))
    _on_root(complete)


def test_a_wisp_too_large_for_floats_on_one_rank_is_refused_on_every_rank(shared_dir, capsys):
    """A groom whose last wisp is scaled by 1e160 (its rest lengths overflow): the
    assembler's element check raised on the rank owning it alone, and the others waited
    for it in the matrix creation: mpiexec hung (2 and 3 ranks).  Now the rest state
    refuses it on every rank, once, naming the wisp."""
    d, _ = shared_dir
    g, cfg = _four_wisp_groom(d, lambda pos: pos * 1e160)
    _refused(cfg, d, capsys, "error: strands file " + g + ": wisp 3, edge 0: rest length overflows to inf")


def _four_wisp_groom(d, last_wisp=None, **datasets):
    """(groom, config) in ``d``: four 30-vertex 4C wisps 2 cm apart, the last one's
    positions passed through ``last_wisp``, the ``datasets`` added (rank 0 writes)."""
    from lc_petsc.scene import geometry
    g, cfg = os.path.join(d, "g.h5"), os.path.join(d, "g.toml")
    if comm.rank == 0:
        n = 30
        pos = [geometry.wisp4c(n, root=(2.0 * w, 0.0, 0.0)) for w in range(4)]
        if last_wisp is not None:
            pos[3] = last_wisp(pos[3])
        with h5py.File(g, "w") as f:
            f["positions"] = np.concatenate(pos)
            f["wisp_offsets"] = np.arange(5, dtype=np.int64) * n
            for k, v in datasets.items():
                f[k] = v
        with open(cfg, "w") as fh:
            fh.write(f'[scene]\nkind = "file"\npath = "{g}"\n[physics]\nterms = ["stretch", "bend", "twist"]\n')
    comm.Barrier()
    return g, cfg


@pytest.mark.parametrize("damage, said", [
    ("radius", "wisp 3, vertex 0: radius 1e-300 cm is below 1e-08 cm"),
    ("youngs_modulus", "wisp 3: Young's modulus 1e+300 dyn/cm^2 is beyond 1e+15"),
    ("shrunk", "wisp 3, edge 0: rest length 6e-11 cm is below 1e-08 cm"),
    ("density", "wisp 3: /density 1300 g/cm^3 is outside 0.1 to 10 g/cm^3: it looks like kg/m^3 (hair: "
                "1300 kg/m^3 = 1.3 g/cm^3); a density 1000 times off runs the scene as if 1000 times softer"),
])
def test_a_wisp_beyond_double_precision_on_one_rank_is_refused_before_frame_0(shared_dir, capsys, damage,
                                                                             said):
    """A groom whose last wisp has radius 1e-300 (masses 0), Young's modulus 1e300 or
    is shrunk by 1e-10 (stiffnesses 1e27 times its mass term) passed the groom's checks
    and failed the solve in frame 0, exit 3, after writing it; one whose density is in
    kg/m^3 (1300) ran as if 1000 times softer, with a warning.  Now refused on every rank,
    exit 2, once, naming file, wisp, dataset and value; nothing written."""
    d, _ = shared_dir
    radius, youngs, density = np.full(4 * 30, 0.05), np.full(4, 1e10), np.full(4, 1.3)
    shrink = None
    if damage == "shrunk":      # about the root: its first edge is 0.6 cm
        shrink = lambda pos: pos[0] + (pos - pos[0]) * 1e-10    # noqa: E731
    elif damage == "radius":
        radius[3 * 30:] = 1e-300
    elif damage == "density":
        density[3] = 1300.0
    else:
        youngs[3] = 1e300
    g, cfg = _four_wisp_groom(d, shrink, radius=radius, youngs_modulus=youngs, density=density)
    _refused(cfg, d, capsys, "error: strands file " + g + ": " + said)


def test_a_mass_term_that_overflows_is_refused_before_frame_0(shared_dir, capsys):
    """material.density = 1e308 overflowed M/dt^2 and the solve failed in frame 0, exit 3,
    after writing it; such a density is now refused by its range (config.DENSITY_RANGE),
    and a radius of 1e153 cm (stretch alone, soft enough for finite stiffnesses) still
    overflows the mass term: refused on every rank, naming the density, wisp and radius."""
    d, _ = shared_dir
    cfg = os.path.join(d, "heavy.toml")
    if comm.rank == 0:
        with open(cfg, "w") as fh:
            fh.write(SCENE.replace("youngs_modulus = 2.5e8\n", "youngs_modulus = 1e-3\nroot_radius = 1e153\n"
                                   "tip_radius = 1e153\n").replace('"bend", "twist", ', ""))
    comm.Barrier()
    err = _refused(cfg, d, capsys, "error: material.density = 1.3 g/cm^3 gives wisp ")
    assert comm.rank != 0 or "(radius 1e+153 cm) a mass of 1.2" in err and "a mass term M/dt^2 of inf" in err, err


def test_a_refusal_on_one_rank_only_is_reported_by_rank_0(shared_dir, capsys, monkeypatch):
    """A refusal on the last rank alone after the set-up's collective calls (here injected
    after the disk check, the set-up's last step): every rank exits 2, and rank 0 prints
    that rank's message once (it printed only its own, so nobody printed it)."""
    from lc_petsc.job import Job, Refused
    d, cfg = shared_dir
    check = Job._check_disk

    def refused_on_the_last_rank(self, rows_kept):
        check(self, rows_kept)
        if comm.rank == LAST:
            raise Refused(f"rank {LAST}'s own refusal")
    monkeypatch.setattr(Job, "_check_disk", refused_on_the_last_rank)
    _refused(cfg, d, capsys, f"error: rank {LAST}'s own refusal")
