"""The main job never loses data and never ends in a traceback: one run per output
folder (lock, stale locks), inputs validated before anything is removed, frames.h5
grown as frames are written with a disk estimate, a full disk on a small tmpfs (exit 3,
frames and the previous checkpoint kept), Ctrl-C, unused PETSc options and unchecked
linear solves, physical ranges and config paths."""

import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from lc_petsc.batch import EXIT_PREEMPTED, main
from lc_petsc.integrator import Integrator
from lc_petsc.io.disk import RESERVE
from lc_petsc.io.frames import frame_bytes
from lc_petsc.errors import FolderBusy
from lc_petsc.io.lock import LOCK_NAME, OutputLock

ROOT = Path(__file__).resolve().parents[2]
DRIVER = str(ROOT / "drivers" / "simulate.py")

SMASH = """
[scene]
kind = "wisp4c"
n_vertices = 101
perturbation = "smash"
description = "{description}"
[material]
youngs_modulus = 3.9e9
[physics]
terms = ["stretch", "bend", "twist"]
[time]
dt = {dt}
frames = {frames}
[output]
previews = {previews}
checkpoint_every = {ce}
"""


def _smash(tmp_path, name="s.toml", frames=6, ce=2, previews="false", dt="0.03333333333333333",
           description="smash", extra=""):
    p = tmp_path / name
    p.write_text(SMASH.format(frames=frames, ce=ce, previews=previews, dt=dt,
                              description=description) + extra)
    return str(p)


def _snapshot(folder):
    """{relative path: (sha256, mtime_ns)} of every file under ``folder``."""
    out = {}
    for p in sorted(Path(folder).rglob("*")):
        if p.is_file():
            out[str(p.relative_to(folder))] = (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
    return out


def _wait(cond, proc, what, timeout=60):
    t0 = time.time()
    while not cond():
        assert proc.poll() is None, f"{what}: the run ended early: {proc.communicate()[1][-2000:]}"
        assert time.time() - t0 < timeout, f"{what} never happened"
        time.sleep(0.02)


def _lock_held(out):
    p = Path(out) / LOCK_NAME
    return lambda: p.exists() and p.stat().st_size > 0


# ----------------------------------------------------------------------------- lock
def test_second_run_into_a_busy_folder_is_refused_and_changes_nothing(tmp_path, capsys):
    cfg = _smash(tmp_path)
    out = tmp_path / "out"
    assert main([cfg, "--out", str(out), "--quiet", "--frames", "3"]) == 0
    before = _snapshot(out)
    lock = OutputLock(out).acquire()          # a run that holds the folder (this process)
    try:
        capsys.readouterr()
        assert main([cfg, "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert "is in use by another run" in err and f"pid {os.getpid()}" in err, err
        assert "Traceback" not in err and err.count("error:") == 1
        assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 2
        assert "in use by another run" in capsys.readouterr().err
    finally:
        lock.release()
    after = _snapshot(out)
    assert after == before, "the refused runs changed the folder"
    assert not (out / LOCK_NAME).exists()


def test_a_probe_of_the_lock_does_not_refuse_a_run_starting(tmp_path):
    """scripts/check_outputs.py and join_summaries.py look at the lock with a shared flock
    (lc_petsc.io.lock.probe); a run starting while one is held waits for it instead of
    taking the folder for busy (before: FolderBusy). Another process holds a shared flock
    for 0.3 s, as a probe would for two system calls; an exclusive one is still refused."""
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / LOCK_NAME).write_text("")
    hold = ("import fcntl, os, sys, time; fd = os.open(sys.argv[1], os.O_RDONLY); "
            "fcntl.flock(fd, fcntl.{} | fcntl.LOCK_NB); print('held', flush=True); time.sleep(float(sys.argv[2]))")
    prober = subprocess.Popen([sys.executable, "-c", hold.format("LOCK_SH"), str(folder / LOCK_NAME), "0.3"],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert prober.stdout.readline().strip() == "held"
        lock = OutputLock(folder).acquire()
        assert prober.poll() is not None, "the run took the lock while the probe's shared flock was held"
        lock.release()
    finally:
        prober.wait()
    (folder / LOCK_NAME).write_text("")
    holder = subprocess.Popen([sys.executable, "-c", hold.format("LOCK_EX"), str(folder / LOCK_NAME), "30"],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        start = time.monotonic()
        with pytest.raises(FolderBusy, match="in use by another run"):
            OutputLock(folder).acquire()
        assert time.monotonic() - start < 1.0      # a run's lock is refused at once, no probe wait
    finally:
        holder.kill()
        holder.wait()


def test_two_runs_started_one_after_the_other(tmp_path, capsys):
    """A runs (holding the lock), then B starts: B is refused naming A, A finishes its
    own frames.h5 (the race: B used to unlink A's file)."""
    cfg = _smash(tmp_path, frames=100000, ce=0)
    out = tmp_path / "out"
    a = subprocess.Popen([sys.executable, DRIVER, cfg, "--out", str(out), "--quiet"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait(_lock_held(out), a, "A taking the lock")
        _wait(lambda: (out / "frames.h5").exists(), a, "A writing frames.h5")
        capsys.readouterr()
        assert main([cfg, "--out", str(out), "--quiet", "--frames", "3"]) == 2
        err = capsys.readouterr().err
        assert f"pid {a.pid}" in err and "in use by another run" in err, err
    finally:
        a.send_signal(signal.SIGTERM)
        so, se = a.communicate(timeout=60)
    assert a.returncode == EXIT_PREEMPTED, se[-2000:]
    s = json.loads((out / "summary.json").read_text())
    with h5py.File(out / "frames.h5", "r") as f:
        assert f["positions"].shape[0] == s["output"]["frames_written"] == s["frames"] + 1
        assert np.isfinite(f["positions"][...]).all()
    assert f"{s['output']['frames_written']} frames in frames.h5" in so


def test_stale_lock_of_a_killed_run_is_reported_and_taken_over(tmp_path, capsys):
    cfg = _smash(tmp_path, frames=100000, ce=0)
    out = tmp_path / "out"
    a = subprocess.Popen([sys.executable, DRIVER, cfg, "--out", str(out), "--quiet"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait(_lock_held(out), a, "A taking the lock")
    a.send_signal(signal.SIGKILL)
    a.communicate()
    assert (out / LOCK_NAME).exists()
    capsys.readouterr()
    assert main([_smash(tmp_path, name="b.toml"), "--out", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "found the lock of a run that did not finish" in err and f"pid {a.pid}" in err, err
    s = json.loads((out / "summary.json").read_text())
    assert any(f"pid {a.pid}" in w for w in s["warnings"])
    assert not (out / LOCK_NAME).exists()


# ------------------------------------------------------- validation before any change
def test_exit_2_leaves_the_previous_run_untouched(tmp_path, capsys):
    cfg = _smash(tmp_path)
    out = tmp_path / "out"
    assert main([cfg, "--out", str(out), "--quiet", "--frames", "4"]) == 0
    before = _snapshot(out)

    def refused(args, *needles):
        capsys.readouterr()
        assert main(args + ["--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err
        for n in needles:
            assert n in err, err
        assert _snapshot(out) == before, f"{args} changed the folder"

    refused([_smash(tmp_path, name="nul.toml", description="a\\u0000b")], "scene.description", "NUL")
    refused([cfg, "--frames", str(2 ** 63 - 1)], "time.frames", "--frames")
    refused([cfg, "--frames", "1000000000000"], "time.frames")
    refused([_smash(tmp_path, name="dt.toml", dt="1e-300")], "time.dt")
    # a restart whose frames.h5 is missing
    (out / "frames.h5").rename(tmp_path / "frames.h5.away")
    before = _snapshot(out)
    refused([cfg, "--restart", "latest"], "frames.h5", "missing")
    (tmp_path / "frames.h5.away").rename(out / "frames.h5")
    # a folder refused before it existed is not left behind
    new = tmp_path / "new"
    capsys.readouterr()
    assert main([cfg, "--out", str(new), "--quiet", "--frames", str(2 ** 63 - 1)]) == 2
    assert main([_smash(tmp_path, name="dt.toml", dt="1e-300"), "--out", str(new), "--quiet"]) == 2
    assert not new.exists()


def test_frames_file_grows_with_the_frames_written(tmp_path):
    """A million planned frames: nothing is preallocated (main wrote 2.4 GB before frame
    0), the datasets are extendable and hold exactly the frames written."""
    cfg = _smash(tmp_path, frames=1000000, ce=0)
    out = tmp_path / "out"
    p = subprocess.Popen([sys.executable, DRIVER, cfg, "--out", str(out), "--quiet"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait(lambda: (out / "frames.h5").exists(), p, "frames.h5")
        time.sleep(0.5)
        size_running = (out / "frames.h5").stat().st_size
    finally:
        p.send_signal(signal.SIGTERM)
        so, se = p.communicate(timeout=60)
    assert p.returncode == EXIT_PREEMPTED, se[-2000:]
    with h5py.File(out / "frames.h5", "r") as f:
        n = f["positions"].shape[0]
        assert f["positions"].maxshape == (None, 101, 3) and f["time"].maxshape == (None,)
        assert f["positions"].chunks == (1, 101, 3)
        assert n == f["time"].shape[0] == json.loads((out / "summary.json").read_text())["frames"] + 1
        assert np.all(np.diff(f["time"][...]) > 0)
    size = (out / "frames.h5").stat().st_size
    assert size_running < 5e6 and size < 200_000 + 2 * n * frame_bytes(101), (size_running, size, n)


# ------------------------------------------------------------------- a full disk
@pytest.fixture
def small_volume(tmp_path):
    """A 4 MB tmpfs mounted for the test (CI runs as root: a failed mount fails)."""
    vol = tmp_path / "vol"
    vol.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(vol)],
                       capture_output=True, text=True)
    assert r.returncode == 0, f"cannot mount a tmpfs (the test needs root): {r.stderr}"
    try:
        yield vol
    finally:
        subprocess.run(["umount", "-l", str(vol)], check=True)


def _fill(vol, leave):
    """Fill the volume ``vol`` up to ``leave`` bytes free."""
    free = os.statvfs(vol).f_bavail * os.statvfs(vol).f_frsize
    with open(vol / "filler", "ab") as fh:
        fh.write(b"\0" * max(free - leave, 0))


def _fill_at(monkeypatch, vol, frame, leave):
    step = Integrator.step

    def step_and_fill(self):
        step(self)
        if self.frame == frame:
            _fill(vol, leave)
    monkeypatch.setattr(Integrator, "step", step_and_fill)


def test_a_full_volume_refuses_the_run_and_leaves_no_folder(tmp_path, small_volume, capsys):
    """On a volume with no block free the lock file is created (an inode) but its record
    cannot be written: the run was refused (exit 2) and left the folder it had created,
    with an empty lock file in it; and a refused run never removed the parents it had
    created (--out new/out left new)."""
    _fill(small_volume, 0)
    out = small_volume / "new" / "out"
    assert main([_smash(tmp_path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"output folder {str(out)!r}: No space left on device" in err, err
    assert sorted(p.name for p in small_volume.iterdir()) == ["filler"]


def test_a_lock_whose_record_cannot_be_written_leaves_the_folder_as_it_was(tmp_path, monkeypatch):
    """The same failure in a folder with a killed run's lock file: it is given back as
    it was (its record is what the next run's warning names), not removed or emptied."""
    import errno
    import lc_petsc.io.lock as lock

    def no_space(fd):
        raise OSError(errno.ENOSPC, "No space left on device")
    stale = json.dumps({"pid": 4242, "host": socket.gethostname(), "started": "2026-12-06 10:00:00 UTC"}) + "\n"
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / LOCK_NAME).write_text(stale)
    monkeypatch.setattr(lock.os, "fsync", no_space)
    for folder in (tmp_path / "old", tmp_path / "new"):
        with pytest.raises(OSError, match="No space left"):
            OutputLock(folder).acquire()
    monkeypatch.undo()
    assert (tmp_path / "old" / LOCK_NAME).read_text() == stale
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old"]
    assert OutputLock(tmp_path / "old").acquire().stale.startswith(f"pid 4242 on host {socket.gethostname()}")


def test_run_that_cannot_fit_is_refused_before_frame_0(tmp_path, small_volume, capsys):
    out = small_volume / "out"
    assert main([_smash(tmp_path, frames=5000), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "time.frames = 5000" in err and "free" in err and "frames.h5" in err, err
    assert not out.exists()


def test_a_refused_run_puts_back_a_killed_runs_lock(tmp_path, small_volume, capsys):
    """A run refused (here by the disk estimate, and by a missing checkpoint) in a folder
    with a killed run's lock file warned about it, then removed it: the folder was not
    as it was, and the next run no longer warned.  Now the file is put back, its bytes
    and times, so the next run still names the killed one."""
    out = small_volume / "out"
    assert main([_smash(tmp_path, frames=4), "--out", str(out), "--quiet"]) == 0
    # this host's: a lock recorded on another host is not taken over (test_lock_other_host.py)
    stale = (json.dumps({"pid": 4242, "host": socket.gethostname(), "started": "2026-12-06 10:00:00 UTC"})
             + "\n").encode()
    (out / LOCK_NAME).write_bytes(stale)
    os.utime(out / LOCK_NAME, ns=(1_000_000_000_123, 1_000_000_000_456))    # not the refused run's
    before = _snapshot(out)
    for args in (["--frames", "5000"], ["--restart", str(tmp_path / "none.h5")]):
        capsys.readouterr()
        assert main([_smash(tmp_path), "--out", str(out), "--quiet"] + args) == 2
        err = capsys.readouterr().err
        assert f"found the lock of a run that did not finish (pid 4242 on host {socket.gethostname()}" in err, err
        assert _snapshot(out) == before, args       # bytes and mtime
    assert main([_smash(tmp_path), "--out", str(out), "--quiet"]) == 0
    said = capsys.readouterr().err
    assert f"found the lock of a run that did not finish (pid 4242 on host {socket.gethostname()}" in said
    assert not (out / LOCK_NAME).exists()


def test_full_disk_while_writing_frames(tmp_path, small_volume, monkeypatch, capsys):
    cfg = _smash(tmp_path, frames=40, ce=2)
    out = small_volume / "out"
    _fill_at(monkeypatch, small_volume, 5, RESERVE // 2)
    capsys.readouterr()
    assert main([cfg, "--out", str(out), "--quiet"]) == 3
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err
    assert "frames.h5: disk full" in cap.err, cap.err
    s = json.loads((out / "summary.json").read_text())
    assert "frames.h5: disk full" in s["error"] and s["converged"] is False
    with h5py.File(out / "frames.h5", "r") as f:       # frames 0..4 readable
        assert f["positions"].shape[0] == 5 and np.isfinite(f["positions"][...]).all()
        assert np.allclose(f["time"][...], np.arange(5) / 30)
    names = sorted(p.name for p in (out / "checkpoints").iterdir())
    assert names == ["checkpoint_000002.h5", "checkpoint_000004.h5"]
    assert f"checkpoints are kept (newest {out / 'checkpoints' / 'checkpoint_000004.h5'}): once the " \
           "cause is fixed (e.g. space freed), continue with --restart latest; to continue on another disk, copy " \
           "the whole folder there" in cap.err, cap.err
    monkeypatch.undo()
    (small_volume / "filler").unlink()
    # the same command again, space freed: it used to start over, removing the checkpoints
    before = _snapshot(out)
    assert main([cfg, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "holds a run that did not finish (failed: output error: " in err, err
    assert _snapshot(out) == before
    # continued on another disk as the message says: the whole folder copied
    moved = tmp_path / "moved"
    shutil.copytree(out, moved)
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 0
    assert main([cfg, "--out", str(moved), "--quiet", "--restart", "latest"]) == 0
    assert main([cfg, "--out", str(tmp_path / "straight"), "--quiet"]) == 0
    with h5py.File(tmp_path / "straight" / "frames.h5", "r") as g:
        for folder in (out, moved):
            with h5py.File(folder / "frames.h5", "r") as f:
                assert f["positions"].shape[0] == 41
                assert np.allclose(f["time"][...], np.arange(41) / 30)
                assert np.array_equal(f["positions"][...], g["positions"][...])


def test_full_disk_while_writing_a_checkpoint(tmp_path, small_volume, monkeypatch, capsys):
    cfg = _smash(tmp_path, frames=40, ce=2, previews="true")
    out = small_volume / "out"
    # frame 4 still fits, its checkpoint (about 70 kB) does not
    _fill_at(monkeypatch, small_volume, 4, RESERVE + frame_bytes(101) + 20_000)
    capsys.readouterr()
    assert main([cfg, "--out", str(out), "--quiet"]) == 3
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err
    assert "checkpoint_000004.h5: disk full" in cap.err, cap.err
    s = json.loads((out / "summary.json").read_text())
    assert "checkpoint_000004.h5: disk full" in s["error"]
    # the previews and the USD export are not tried on the full disk, one warning says so
    # (before: pxr's failure as a warning, and the previews' as a second error)
    note = (f"previews and frames.usdc not written: the run stopped on an output error (above); --restart "
            f"latest writes them at the end of the continued run; drivers/to_usd.py {out / 'frames.h5'} writes "
            f"frames.usdc from the frames written")
    assert cap.err.count("not written: the run stopped") == 1 and note in cap.err, cap.err
    assert "USD export failed" not in cap.err and not (out / "frames.usdc").exists()
    assert not (out / "previews").exists() and not (out / "contact_sheet.png").exists()
    assert s["warnings"][-1] == note and s["output"]["not_written"] == []
    assert [c["frame"] for c in s["checkpoints"]] == [2]
    names = sorted(p.name for p in (out / "checkpoints").iterdir())
    assert names == ["checkpoint_000002.h5"]
    with h5py.File(out / "frames.h5", "r") as f:
        assert f["positions"].shape[0] == 5
    monkeypatch.undo()
    (small_volume / "filler").unlink()
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 0


HAIRBALL_2 = """
[scene]
kind = "hairball"
n_wisps = 8
[material]
youngs_modulus = 2.5e8
[physics]
terms = ["stretch", "bend", "gravity"]
[time]
frames = 8
[output]
previews = false
usd = false
checkpoint_every = 3
"""


def test_disk_filled_by_another_program_during_a_checkpoint(tmp_path, small_volume):
    """2 ranks; another program fills the volume while checkpoint 3 is being written (after
    its positions).  Before, both ranks hung in libhdf5's close of the failed file; now
    the checkpoint's bytes are reserved before its first write, so it completes and is
    valid, and the next frame is refused as a full disk: exit 3, frames 0-3 readable."""
    from sim_helpers import MPI_ENV
    from lc_petsc.io.checkpoint import PAUSE_ENV
    cfg, out = tmp_path / "h.toml", small_volume / "out"
    cfg.write_text(HAIRBALL_2)
    p = subprocess.Popen(["mpiexec", "-n", "2", sys.executable, DRIVER, str(cfg), "--out", str(out),
                          "--quiet"], env=dict(MPI_ENV, **{PAUSE_ENV: "3:6"}), stdin=subprocess.DEVNULL,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    tmp = out / "checkpoints" / ".checkpoint_000003.h5.tmp"
    t0 = time.time()
    while not tmp.exists():
        assert p.poll() is None and time.time() - t0 < 120, p.communicate()[1][-2000:]
        time.sleep(0.05)
    time.sleep(1.0)                               # inside the pause, after the positions
    _fill(small_volume, 0)
    try:
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 3, err[-3000:]
    assert "frames.h5: disk full" in err and "Traceback" not in err, err[-3000:]
    assert sorted(q.name for q in (out / "checkpoints").iterdir()) == ["checkpoint_000003.h5"]
    (small_volume / "filler").unlink()
    with h5py.File(out / "checkpoints" / "checkpoint_000003.h5", "r") as c, \
            h5py.File(out / "frames.h5", "r") as f:
        assert f["positions"].shape[0] == 4 and c.attrs["frame"] == 3
        assert np.array_equal(c["positions"][...], f["positions"][3])
    r = subprocess.run([sys.executable, DRIVER, str(cfg), "--out", str(out), "--quiet", "--restart",
                        "latest"], env=MPI_ENV, stdin=subprocess.DEVNULL, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]


ONE_RANK_FAILS = '''
import sys
import lc_petsc.io.frames as frames
from mpi4py import MPI
from lc_petsc.batch import exit_process, main

write = frames.write_rows


def velocities_fail_on_the_last_rank(dset, start, data, dxpl):
    write(dset, start, data, dxpl)              # the collective write itself completes
    if dset.name == "/velocities" and "checkpoint_000003" in dset.file.filename \\
            and MPI.COMM_WORLD.rank == MPI.COMM_WORLD.size - 1:
        raise OSError(28, "No space left on device")


frames.write_rows = velocities_fail_on_the_last_rank
exit_process(main())
'''


def test_checkpoint_write_failing_on_one_rank_is_every_ranks_error(tmp_path):
    """2 ranks; writing checkpoint 3's /velocities fails on the last rank only: every rank
    stops with the same error (exit 3, within the timeout: no rank left waiting in a
    collective), the partial file removed, frames 0-3 kept, and the folder takes a new run."""
    from sim_helpers import MPI_ENV
    cfg, out, driver = tmp_path / "h.toml", tmp_path / "out", tmp_path / "fails.py"
    cfg.write_text(HAIRBALL_2)
    driver.write_text(ONE_RANK_FAILS)
    r = subprocess.run(["mpiexec", "-n", "2", sys.executable, str(driver), str(cfg), "--out", str(out),
                        "--quiet"], env=MPI_ENV, stdin=subprocess.DEVNULL, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 3, r.stderr[-3000:]
    assert "checkpoint_000003.h5.tmp: writing /velocities: No space left on device" in r.stderr, r.stderr[-3000:]
    assert "Traceback" not in r.stderr
    assert not (out / "checkpoints" / ".checkpoint_000003.h5.tmp").exists()
    with h5py.File(out / "frames.h5", "r") as f:
        assert f["positions"].shape[0] == 4
    r = subprocess.run([sys.executable, DRIVER, str(cfg), "--out", str(out), "--quiet"], env=MPI_ENV,
                       stdin=subprocess.DEVNULL, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]


def test_checkpoint_that_cannot_reserve_its_bytes(tmp_path, monkeypatch, capsys):
    """The reservation fails (the volume filled after the free-space check): the run stops
    with exit 3 naming the step, the partial file is removed, the previous checkpoint
    and the frames are kept, and the run continues from it."""
    import errno
    from lc_petsc.io import checkpoint
    cfg = _smash(tmp_path, frames=40, ce=2)
    out = tmp_path / "out"
    reserve = checkpoint._reserve

    def reserve_fails_at_4(path, nbytes):
        if "000004" in str(path):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        reserve(path, nbytes)
    monkeypatch.setattr(checkpoint, "_reserve", reserve_fails_at_4)
    assert main([cfg, "--out", str(out), "--quiet"]) == 3
    err = capsys.readouterr().err
    assert "checkpoint_000004.h5.tmp: reserving its" in err and "No space left" in err, err
    assert sorted(q.name for q in (out / "checkpoints").iterdir()) == ["checkpoint_000002.h5"]
    with h5py.File(out / "frames.h5", "r") as f:
        assert f["positions"].shape[0] == 5
    monkeypatch.undo()
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 0


def test_usd_export_on_a_full_disk_leaves_no_temporary_file(tmp_path, small_volume, capsys):
    """On a full disk USD's CreateNew fails after creating frames.tmp.usdc (empty); it
    was created before the block that removes the temporary file on failure, so the
    file stayed.  The warning names the converter that writes the export later."""
    from lc_petsc.config import OutputConfig
    from lc_petsc.io.usd import export_run
    cfg = _smash(tmp_path, frames=2, ce=0)
    out = small_volume / "out"
    assert main([cfg, "--out", str(out), "--quiet"]) == 0
    (out / "frames.usdc").unlink()
    before = sorted(p.name for p in out.iterdir())
    _fill(small_volume, 0)
    capsys.readouterr()
    detail = []
    files, _ = export_run(OutputConfig(), out / "frames.h5", out, detail=detail.append)
    assert files == []
    err = capsys.readouterr().err
    assert "USD export failed, frames.h5 is intact" in err, err
    assert f"write it later with drivers/to_usd.py {out / 'frames.h5'}" in err, err
    assert sorted(p.name for p in out.iterdir()) == before
    # one line (pxr's text was 7, each with its C++ function and source file): what failed,
    # the file, the first reason; USD's own text goes to ``detail`` (the main job's summary.json)
    assert err.count("\n") == 1 and "Error in '" not in err and "pxrInternal" not in err, err
    assert f"{out / 'frames.usdc'}: " in err and "No space left on device" in err, err
    assert len(detail) == 1 and detail[0].count("Error in '") >= 2 and "No space left on device" in detail[0]
    more = detail[0].count("Error in '") - 1
    assert err.rstrip().endswith(f"({more} more from USD: summary.json's output.usd_error)"), err
    # to_usd.py the same, USD's text with --verbose
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "drivers"))
    import to_usd
    assert to_usd.main([str(out / "frames.h5"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"to_usd.py: error: USD could not write {out / 'frames.usdc'}: ") and \
        err.count("\n") == 1 and "No space left on device" in err and "to_usd.py --verbose" in err, err
    assert to_usd.main([str(out / "frames.h5"), "--quiet", "--verbose"]) == 2
    err = capsys.readouterr().err
    assert err.count("Error in '") >= 2 and err.splitlines()[1] == "to_usd.py: USD's text:", err
    assert sorted(p.name for p in out.iterdir()) == before


def test_a_failed_usd_export_is_a_warning_in_summary_json(tmp_path, monkeypatch, capsys):
    """A USD export that failed on a full disk (pxr's OSError) was a warning on stderr
    only: summary.json's ``warnings`` and the report said nothing of the missing
    frames.usdc, while an unexpected failure was recorded."""
    import errno
    import lc_petsc.io.usd as usd

    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(usd, "write_usd", full_disk)
    out = tmp_path / "out"
    assert main([_smash(tmp_path, frames=2, ce=0), "--out", str(out), "--quiet"]) == 0
    cap = capsys.readouterr()
    s = json.loads((out / "summary.json").read_text())
    said = [w for w in s["warnings"] if w.startswith("USD export failed, frames.h5 is intact")]
    assert len(said) == 1 and "No space left on device" in said[0], s["warnings"]
    assert f"drivers/to_usd.py {out / 'frames.h5'}" in said[0], said
    assert "frames.usdc" not in s["output"]["files"] and not (out / "frames.usdc").exists()
    assert s["output"]["usd_error"] == "[Errno 28] No space left on device"     # the error's own text
    assert cap.err.count("USD export failed") == 1, cap.err       # once on stderr
    assert "warning: USD export failed" in cap.out, cap.out       # and in the report


def test_outputs_that_cannot_be_written_are_reported(tmp_path, capsys):
    cfg = _smash(tmp_path, frames=3, ce=0, previews="true")
    out = tmp_path / "out"
    (out / "summary.json.tmp").mkdir(parents=True)     # the summary's temporary name is taken
    assert main([cfg, "--out", str(out), "--quiet"]) == 3
    cap = capsys.readouterr()
    assert "summary.json could not be written" in cap.err and "Traceback" not in cap.err
    assert "frames: 3" in cap.out                       # the report is still printed
    (out / "summary.json.tmp").rmdir()
    (out / "frames.xdmf.tmp").mkdir()                   # the XDMF cannot be written
    assert main([cfg, "--out", str(out), "--quiet"]) == 3
    cap = capsys.readouterr()
    assert "frames.xdmf" in cap.err and "Traceback" not in cap.err
    s = json.loads((out / "summary.json").read_text())
    assert "frames.xdmf" in s["error"] and s["output"]["not_written"]
    assert (out / "contact_sheet.png").exists()         # the other outputs are written


def test_output_folder_removed_during_the_run_skips_the_check_and_the_exports(tmp_path, monkeypatch, capsys):
    """The output folder removed after frame 4: exit 3, the run's output error, then
    one line saying frames.h5 is gone and that the crossing check and the exports are
    skipped.  There used to be a warning of the check that could not open the file
    (again in the report) and one of the USD export, and the report listed frames.h5."""
    cfg = _smash(tmp_path, frames=8, ce=0, previews="true")
    out = tmp_path / "out"
    step = Integrator.step

    def step_and_remove(self):
        step(self)
        if self.frame == 4:
            shutil.rmtree(out)
    monkeypatch.setattr(Integrator, "step", step_and_remove)
    capsys.readouterr()
    assert main([cfg, "--out", str(out), "--quiet"]) == 3
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err
    lines = [ln for ln in cap.err.splitlines() if ln.strip()]
    assert "summary.json could not be written (No such file or directory)" in lines[0], lines
    assert lines[-2] == f"simulate.py: error: output error: {out / 'frames.h5'}: cannot query the free space " \
                        f"of {out}: No such file or directory", lines
    assert lines[-1:] == [f"simulate.py: {out / 'frames.h5'} is gone (the output folder was removed or renamed during "
                    "the run?): no crossing check, frames.xdmf, previews or frames.usdc (nothing to make them "
                    "from)"], lines
    for said in ("crossing check could not", "USD export", "warning"):
        assert said not in cap.err + cap.out, said
    assert "frames: 4" in cap.out and "crossings between" not in cap.out
    # the report lists what is there (it listed frames.h5's 4 frames and summary.json)
    assert f"output: {out}  (4 frames (every 1) had been written to frames.h5, which is gone; no file)" \
        in cap.out, cap.out
    assert not out.exists()


# ------------------------------------------------------------------------ Ctrl-C
def test_ctrl_c_on_one_rank_checkpoints_and_exits_75(tmp_path):
    cfg = _smash(tmp_path, frames=100000, ce=0)
    out = tmp_path / "out"
    p = subprocess.Popen([sys.executable, DRIVER, cfg, "--out", str(out), "--quiet"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait(lambda: (out / "frames.h5").exists(), p, "frames.h5")
    time.sleep(0.3)
    p.send_signal(signal.SIGINT)
    so, se = p.communicate(timeout=60)
    assert p.returncode == EXIT_PREEMPTED, se[-2000:]
    assert "Traceback" not in se and "SIGINT received: stopped after frame" in se
    s = json.loads((out / "summary.json").read_text())
    assert s["preempted"] == "SIGINT" and s["error"] is None
    k = s["frames"]
    assert [c["frame"] for c in s["checkpoints"]] == [k] and k > 0
    assert (out / "checkpoints" / f"checkpoint_{k:06d}.h5").exists()


def test_second_ctrl_c_stops_at_once(tmp_path):
    cfg = _smash(tmp_path, frames=100000, ce=0, previews="true")
    out = tmp_path / "out"
    p = subprocess.Popen([sys.executable, DRIVER, cfg, "--out", str(out), "--quiet"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait(lambda: (out / "frames.h5").exists(), p, "frames.h5")
    time.sleep(0.3)
    p.send_signal(signal.SIGINT)
    line = p.stderr.readline()
    while "SIGINT: finishing this frame" not in line:
        assert line, "no SIGINT message"
        line = p.stderr.readline()
    p.send_signal(signal.SIGINT)
    p.communicate(timeout=60)
    assert p.returncode == -signal.SIGINT
    assert not (out / "summary.json").exists()


# ------------------------------------------------------------ PETSc options, solves
def test_unused_option_and_unchecked_solve_are_reported(tmp_path, capsys):
    cfg = _smash(tmp_path, frames=3, ce=0)
    out = tmp_path / "out"
    # a real option the chosen solver never reads (a misspelt one is refused up front:
    # tests/io/test_solver_check.py)
    assert main([cfg, "--out", str(out), "--quiet", "-pc_hypre_boomeramg_strong_threshold", "0.5"]) == 0
    cap = capsys.readouterr()
    assert "PETSc option -pc_hypre_boomeramg_strong_threshold was given but never used" in cap.err
    s = json.loads((out / "summary.json").read_text())
    assert s["petsc_options_unused"] == ["pc_hypre_boomeramg_strong_threshold"] and s["converged"] is True
    assert any("-pc_hypre_boomeramg_strong_threshold" in w for w in s["warnings"])
    # config options are tracked as well; used ones are not reported
    cfg2 = _smash(tmp_path, name="o.toml", frames=2, ce=0,
                  extra='[solver]\noptions = "-ksp_rtol 1e-8 -pc_hypre_boomeramg_max_iter 2"\n')
    assert main([cfg2, "--out", str(out), "--quiet"]) == 0
    assert json.loads((out / "summary.json").read_text())["petsc_options_unused"] == ["pc_hypre_boomeramg_max_iter"]
    capsys.readouterr()
    assert main([cfg, "--out", str(out), "--quiet", "-ksp_type", "preonly", "-pc_type", "jacobi"]) == 0
    cap = capsys.readouterr()
    assert "converged: NO" in cap.out and "without reaching -ksp_rtol" in cap.err
    s = json.loads((out / "summary.json").read_text())
    assert s["converged"] is False and len(s["linear_solves_not_converged"]) == 9
    assert all(c["relative_residual"] > 1e-3 for c in s["linear_solves_not_converged"])
    # an exact preonly solve is converged
    assert main([cfg, "--out", str(out), "--quiet", "-ksp_type", "preonly", "-pc_type", "lu",
                 "-mat_type", "aij"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["converged"] is True and s["linear_solves_not_converged"] == []


def test_options_file_that_does_not_exist(tmp_path, capsys):
    assert main([_smash(tmp_path), "--out", str(tmp_path / "o"), "--quiet",
                 "-options_file", "/nonexistent"]) == 2
    err = capsys.readouterr().err
    assert "-options_file /nonexistent: no such file" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------ physical ranges
def test_ranges_paths_and_keys_without_effect(tmp_path, capsys):
    out = str(tmp_path / "o")

    def err(args, code=2):
        capsys.readouterr()
        assert main(args + ["--quiet"]) == code
        e = capsys.readouterr().err
        assert "Traceback" not in e
        return e

    assert "time.dt = 1e-300" in err([_smash(tmp_path, dt="1e-300"), "--out", out])
    big = _smash(tmp_path, name="e.toml")
    Path(big).write_text(Path(big).read_text().replace("youngs_modulus = 3.9e9", "youngs_modulus = 1e300"))
    assert "material.youngs_modulus = 1e+300" in err([big, "--out", out])
    assert "--out ''" in err([_smash(tmp_path), "--out", ""])
    assert "/dev/zero: not a regular file" in err(["/dev/zero", "--out", out])
    # (the smashed curl does cross itself in its first step: test_crossing_check.py)
    assert "warning" not in err([_smash(tmp_path, name="k.toml", frames=1, ce=0,
                                        extra="check_crossings = false\n"), "--out", out], code=0)
    text = SMASH.format(frames=1, ce=0, previews="false", dt="0.03333333333333333", description="k")
    text = text.replace('kind = "wisp4c"', 'kind = "wisp4c"\nn_wisps = 3\njitter = 0.2')
    Path(tmp_path / "k2.toml").write_text(text)
    # another folder: o holds the finished run of k.toml, another config (n_wisps, jitter)
    e = err([str(tmp_path / "k2.toml"), "--out", str(tmp_path / "o2")], code=0)
    assert "scene.n_wisps is set but has no effect: it only acts with scene.kind = 'hairball'" in e
    assert "scene.jitter is set but has no effect" in e
    s = json.loads((tmp_path / "o2" / "summary.json").read_text())
    assert sum("has no effect" in w for w in s["warnings"]) == 2


def test_wisp_starting_inside_the_head_is_warned_about(tmp_path, capsys):
    text = SMASH.format(frames=1, ce=0, previews="false", dt="0.03333333333333333", description="h")
    text = text.replace('terms = ["stretch", "bend", "twist"]',
                        'terms = ["stretch", "bend", "twist", "head_collision"]\n'
                        'head_radius = 2.0\nhead_center = [0.0, -4.0, 0.0]')
    Path(tmp_path / "h.toml").write_text(text)
    assert main([str(tmp_path / "h.toml"), "--out", str(tmp_path / "o"), "--quiet"]) == 0
    e = capsys.readouterr().err
    assert "start inside the head sphere (physics.head_radius + physics.head_margin = 2 cm" in e, e


@pytest.mark.parametrize("flush_seconds, kept", [(0.0, 6), (None, 1)])
def test_a_run_killed_without_checkpoints_keeps_a_readable_frames_file(tmp_path, flush_seconds, kept):
    """checkpoint_every = 0 (the default) and SIGKILL: frames.h5 was never flushed and
    libhdf5 could not open it ("file signature not found"), losing every frame. It is
    now flushed after frame 0 and every FRAMES_FLUSH_SECONDS (0: every frame; the
    default 30 s: not again before the kill) and keeps the frames up to the last flush,
    each equal to an uninterrupted run's."""
    cfg = _smash(tmp_path, frames=100000, ce=0)
    out, ref = tmp_path / "out", tmp_path / "ref"
    script = tmp_path / "killed.py"
    script.write_text(f"""
import os, signal, sys
import lc_petsc.job as job
from lc_petsc.integrator import Integrator
if {flush_seconds!r} is not None:
    job.FRAMES_FLUSH_SECONDS = {flush_seconds!r}
step = Integrator.step
def step_then_die(self):
    step(self)
    if self.frame == 6:
        os.kill(os.getpid(), signal.SIGKILL)
Integrator.step = step_then_die
from lc_petsc.batch import main
sys.exit(main([{cfg!r}, "--out", {str(out)!r}, "--quiet"]))
""")
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    assert main([_smash(tmp_path, name="r.toml", frames=5, ce=0), "--out", str(ref), "--quiet"]) == 0
    with h5py.File(out / "frames.h5", "r") as f, h5py.File(ref / "frames.h5", "r") as g:
        assert f["positions"].shape[0] >= kept       # frames 0-5 (frame 6 was not written)
        n = kept
        assert np.array_equal(f["positions"][:n], g["positions"][:n])
        assert np.allclose(f["time"][:n], np.arange(n) / 30.0, rtol=0, atol=1e-15)


def test_a_new_run_does_not_remove_a_run_that_did_not_finish(tmp_path, capsys, monkeypatch):
    """A new run (no --restart) into the folder of a preempted or killed run used to remove
    its frames.h5 and checkpoints silently (forgetting --restart latest lost the run): it
    is refused, the folder unchanged, unless --force; a finished run's folder is reused."""
    cfg = _smash(tmp_path, frames=6, ce=2)
    out = tmp_path / "out"
    step = Integrator.step

    def step_and_signal(self):
        step(self)
        if self.frame == 3:
            signal.raise_signal(signal.SIGUSR1)
    monkeypatch.setattr(Integrator, "step", step_and_signal)
    assert main([cfg, "--out", str(out), "--quiet"]) == EXIT_PREEMPTED
    monkeypatch.setattr(Integrator, "step", step)
    capsys.readouterr()
    before = _snapshot(out)
    assert main([cfg, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "holds a run that did not finish (stopped by SIGUSR1 after frame 3; newest checkpoint " \
           "checkpoint_000003.h5): continue it with --restart latest, or start over with --force" in err, err
    assert _snapshot(out) == before
    # killed: no summary.json
    (out / "summary.json").unlink()
    assert main([cfg, "--out", str(out), "--quiet"]) == 2
    assert "(no summary.json: it was killed" in capsys.readouterr().err
    # --force starts over, saying so
    assert main([cfg, "--out", str(out), "--quiet", "--force"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert any(w.startswith("--force: starting over") for w in s["warnings"]), s["warnings"]
    assert s["frames"] == 6 and s["restart"] is None
    capsys.readouterr()
    # a finished run (with checkpoints) is replaced as before
    assert main([cfg, "--out", str(out), "--quiet"]) == 0
    assert "did not finish" not in capsys.readouterr().err


# ------------------------------------------------------- signals after the last frame
def _signal_inside(monkeypatch, target, name, signum=signal.SIGTERM):
    """``target.name`` sends ``signum`` to this process first (a signal that arrives
    while it runs), then does its work."""
    work = getattr(target, name)

    def signalled(*args, **kwargs):
        os.kill(os.getpid(), signum)
        return work(*args, **kwargs)
    monkeypatch.setattr(target, name, signalled)


def test_a_signal_during_the_end_of_run_outputs_stops_them_and_a_restart_writes_them(
        tmp_path, monkeypatch, capsys):
    """SIGTERM while the previews are drawn: they were finished, then the USD export
    and the rest were written and the run ended with exit 0 and summary.json's
    preempted null: the signal was ignored.  Now the previews stop before their next
    image, the outputs not begun are skipped, a checkpoint of the last frame is
    written, exit 75, and --restart latest writes them (frames.h5 unchanged; it runs
    no frame)."""
    import lc_petsc.job as job
    cfg = _smash(tmp_path, frames=5, ce=2, previews="true")
    out, ref = tmp_path / "out", tmp_path / "ref"
    assert main([cfg, "--out", str(ref), "--quiet"]) == 0
    with monkeypatch.context() as m:
        _signal_inside(m, job, "_previews")
        assert main([cfg, "--out", str(out), "--quiet"]) == EXIT_PREEMPTED
    err = capsys.readouterr().err
    assert (f"SIGTERM received during the end-of-run check and outputs: frames.h5 holds every frame (0-5); "
            f"skipped: previews, frames.usdc; continue with --restart latest (it does them, running no "
            f"frame) (exit status {EXIT_PREEMPTED})") in err, err
    s = json.loads((out / "summary.json").read_text())
    assert s["preempted"] == "SIGTERM" and s["output"]["skipped"] == ["previews", "frames.usdc"]
    assert s["error"] is None and [c["frame"] for c in s["checkpoints"]] == [2, 4, 5]
    assert not (out / "contact_sheet.png").exists() and not (out / "frames.usdc").exists()
    assert not (out / LOCK_NAME).exists()
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 0
    assert (out / "frames.usdc").exists()
    with h5py.File(out / "frames.h5", "r") as f, h5py.File(ref / "frames.h5", "r") as g:
        assert np.array_equal(f["positions"][...], g["positions"][...])
    s = json.loads((out / "summary.json").read_text())
    assert s["preempted"] is None and s["output"]["skipped"] == [] and s["frames_this_run"] == 0


def test_a_signal_during_the_last_frame_checkpoints_it(tmp_path, monkeypatch, capsys):
    """SIGTERM during the last frame (here: while frames.h5 is closed after it): the frame
    loop only looks before a frame, so the run went on with the crossing check and every
    output, exit 0.  Now it stops as during the loop: a checkpoint of the last frame,
    exit 75; --restart latest runs no frame and writes the outputs."""
    from lc_petsc.io.frames import FramesWriter
    cfg = _smash(tmp_path, frames=5, ce=4, previews="true")
    out = tmp_path / "out"
    with monkeypatch.context() as m:
        _signal_inside(m, FramesWriter, "close")
        assert main([cfg, "--out", str(out), "--quiet"]) == EXIT_PREEMPTED
    err = capsys.readouterr().err
    assert "SIGTERM received: stopped after frame 5, checkpoint" in err, err
    s = json.loads((out / "summary.json").read_text())
    assert s["preempted"] == "SIGTERM" and [c["frame"] for c in s["checkpoints"]] == [4, 5]
    assert s["crossings"] is None
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 0
    assert "frame 5 is the run's last: no frame to run" in capsys.readouterr().out
    assert (out / "frames.usdc").exists()


def test_a_signal_while_a_finished_run_ends_keeps_exit_0(tmp_path):
    """SIGTERM while the process ends after a finished run (here from an atexit hook: the
    interpreter's teardown, PETSc's and MPI's finalize, after the job restored its
    handlers) killed it, exit 143, although every output was written."""
    cfg = _smash(tmp_path, frames=2, ce=0)
    out = tmp_path / "out"
    code = ("import atexit, os, signal, sys, time\nsys.argv[0] = 'simulate.py'\n"
            "from lc_petsc.batch import exit_process, main\n"
            "atexit.register(lambda: (os.kill(os.getpid(), signal.SIGTERM), time.sleep(0.3)))\n"
            f"exit_process(main([{cfg!r}, '--out', {str(out)!r}, '--quiet']))\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, (p.returncode, p.stderr[-2000:])
    assert json.loads((out / "summary.json").read_text())["preempted"] is None
    assert not (out / LOCK_NAME).exists()


def test_a_signal_during_the_crossing_check_stops_it_and_a_restart_completes_it(
        tmp_path, monkeypatch, capsys):
    """SIGTERM during the end-of-run crossing check (at its step 2 of 6): the check ran
    every step to the end (minutes on the 8K, 221 s on a 200-wisp file) with the signal
    pending, then skipped the exports.  Now it stops at its next step, the exports are
    skipped, a checkpoint of the last frame is written (frame 6; the newest was frame 4),
    summary.json says what was skipped, exit 75; --restart latest runs no frame and does
    the whole check and the exports, frames.h5 unchanged."""
    import lc_petsc.crossings as crossings
    cfg = _smash(tmp_path, frames=6, ce=4, previews="true")
    out, ref = tmp_path / "out", tmp_path / "ref"
    assert main([cfg, "--out", str(ref), "--quiet"]) == 0
    count, steps = crossings.count_crossings, []

    def signalled(*args, **kwargs):
        steps.append(1)
        if len(steps) == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return count(*args, **kwargs)
    with monkeypatch.context() as m:
        m.setattr(crossings, "count_crossings", signalled)
        assert main([cfg, "--out", str(out), "--quiet"]) == EXIT_PREEMPTED
    assert len(steps) == 3                   # main: 6, every step after the signal too
    err = capsys.readouterr().err
    assert (f"SIGTERM received during the end-of-run check and outputs: frames.h5 holds every frame (0-6); "
            f"skipped: crossing check, previews, frames.usdc; continue with --restart latest (it does them, "
            f"running no frame) (exit status {EXIT_PREEMPTED})") in err, err
    s = json.loads((out / "summary.json").read_text())
    assert s["preempted"] == "SIGTERM" and s["crossings"] is None and s["error"] is None
    assert s["output"]["skipped"] == ["crossing check", "previews", "frames.usdc"]
    assert [c["frame"] for c in s["checkpoints"]] == [4, 6]
    assert not (out / "frames.usdc").exists() and not (out / "contact_sheet.png").exists()
    assert not (out / LOCK_NAME).exists()
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 0
    assert "frame 6 is the run's last: no frame to run" in capsys.readouterr().out
    s = json.loads((out / "summary.json").read_text())
    assert s["preempted"] is None and s["output"]["skipped"] == [] and s["frames_this_run"] == 0
    assert s["crossings"]["steps"] == 6 and s["crossings"]["between_wisps"] == 0
    assert (out / "frames.usdc").exists() and (out / "contact_sheet.png").exists()
    with h5py.File(out / "frames.h5", "r") as f, h5py.File(ref / "frames.h5", "r") as g:
        assert np.array_equal(f["positions"][...], g["positions"][...])


def test_a_signal_during_the_usd_export_stops_it_between_frames(tmp_path, monkeypatch, capsys):
    """SIGTERM while frames.usdc is written (after its frame 1 of 7): the export ran to the
    end and the run exited 0 with the signal ignored.  Now it stops after that frame, its
    temporary file removed, frames.usdc skipped, exit 75; a checkpoint of frame 6."""
    import lc_petsc.io.usd as usd
    cfg = _smash(tmp_path, frames=6, ce=4)
    out = tmp_path / "out"
    write, done = usd.write_usd, []

    def counted(*args, progress=None, **kwargs):
        def tick(k, n):
            done.append(k)
            if k == 2:
                os.kill(os.getpid(), signal.SIGTERM)
            if progress is not None:
                progress(k, n)
        return write(*args, progress=tick, **kwargs)
    monkeypatch.setattr(usd, "write_usd", counted)
    assert main([cfg, "--out", str(out), "--quiet"]) == EXIT_PREEMPTED
    assert done == [1, 2]                     # main: 1 .. 7
    s = json.loads((out / "summary.json").read_text())
    assert s["preempted"] == "SIGTERM" and s["output"]["skipped"] == ["frames.usdc"]
    assert s["crossings"]["steps"] == 6 and [c["frame"] for c in s["checkpoints"]] == [4, 6]
    assert sorted(p.name for p in out.iterdir() if "usd" in p.name) == []


def test_a_finished_run_of_another_config_is_not_replaced_without_force(tmp_path, capsys):
    """A new run into a folder holding a finished run of another physics (here Young's
    modulus) is refused, exit 2, the folder untouched, naming the key and both values (on
    main it replaced that run's outputs without a word); the same config with another
    frame count and another description reuses the folder, and --force replaces the other
    config's run with a warning."""
    out = tmp_path / "o"
    cfg = _smash(tmp_path, frames=2, ce=0)
    assert main([cfg, "--out", str(out), "--quiet"]) == 0
    stiffer = _smash(tmp_path, "t.toml", frames=2, ce=0)
    Path(stiffer).write_text(Path(stiffer).read_text().replace("youngs_modulus = 3.9e9", "youngs_modulus = 1e9"))
    capsys.readouterr()
    before = _snapshot(out)
    assert main([stiffer, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"{out} holds a finished run of another config, which differs in material.youngs_modulus " \
           "(finished run: 3900000000.0, config: 1000000000.0); this run would replace its outputs: give " \
           "another --out, or add --force to replace them" in err, err
    assert "Traceback" not in err and _snapshot(out) == before
    longer = _smash(tmp_path, "l.toml", frames=3, ce=0, description="the same smash, longer")
    assert main([longer, "--out", str(out), "--quiet"]) == 0
    assert json.loads((out / "summary.json").read_text())["frames"] == 3
    assert main([stiffer, "--out", str(out), "--quiet", "--force"]) == 0
    assert "--force: replacing the finished run in" in capsys.readouterr().err
    assert json.loads((out / "summary.json").read_text())["config"]["material"]["youngs_modulus"] == 1e9
