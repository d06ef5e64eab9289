"""Checkpoint and restart of the main job: equivalence with a straight run
(serial: bitwise; 2 -> 3 and 3 -> 1 ranks through mpiexec: 3e-11 relative; measured 1.4e-11 with the edge
retraction update, 5e-12 with the linear one), frames.h5
holding every frame once and in order, SIGKILL while a checkpoint is written, SIGTERM,
corruption and truncation, fallback of ``--restart latest``, keeping the last K, and
the errors a user can meet."""

import json
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from lc_petsc.batch import EXIT_PREEMPTED, main
from lc_petsc.config import ConfigError, config_from_dict
from lc_petsc.io.checkpoint import GLOBAL_DATASETS, VERTEX_DATASETS
from lc_petsc.io.checkpoint_seal import seal

ROOT = Path(__file__).resolve().parents[2]
DRIVER = str(ROOT / "drivers" / "simulate.py")
from sim_helpers import MPI_ENV, hairball_toml, undocumented_outputs, undocumented_summary_keys  # noqa: E402

SCENE = hairball_toml(frames="{frames}",
                      output="every = {every}\npreviews = false\nxdmf = false\n"
                             "checkpoint_every = {ce}\ncheckpoints_kept = {kept}")


def _config(tmp_path, name="s.toml", frames=6, every=1, ce=2, kept=2, **subs):
    text = SCENE.format(frames=frames, every=every, ce=ce, kept=kept)
    for k, v in subs.items():
        text = text.replace(k, v)
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def _frames(out):
    with h5py.File(Path(out) / "frames.h5", "r") as f:
        return f["positions"][...], f["time"][...]


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """The reference: 6 frames straight, serial (frames.h5 positions and times)."""
    d = tmp_path_factory.mktemp("straight")
    cfg = _config(d, ce=0)
    assert main([cfg, "--out", str(d / "out"), "--quiet"]) == 0
    return _frames(d / "out")


def _mpiexec(n, args, cwd, env=MPI_ENV):
    cmd = ["mpiexec", "--oversubscribe", "-n", str(n), sys.executable, DRIVER] + args
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120, cwd=cwd)
    return p


def _check_each_frame_once(out, ref_pos, ref_time, rtol=0.0):
    pos, t = _frames(out)
    assert pos.shape == ref_pos.shape and t.shape == ref_time.shape
    assert np.all(np.diff(t) > 0), f"times not increasing: {t}"
    np.testing.assert_allclose(t, ref_time, rtol=1e-15, atol=0)
    if rtol == 0.0:
        assert np.array_equal(pos, ref_pos), "positions differ from the straight run"
    else:
        err = np.abs(pos - ref_pos).max() / np.abs(ref_pos).max()
        assert err <= rtol, f"relative difference {err:.2e} > {rtol:g}"


def test_serial_restart_is_bitwise_equal(tmp_path, straight, capsys):
    cfg = _config(tmp_path)
    out = str(tmp_path / "out")
    assert main([cfg, "--out", out, "--quiet", "--frames", "3"]) == 0     # checkpoint at 2
    assert main([cfg, "--out", out, "--quiet", "--restart", "latest"]) == 0
    assert "restarting from" in capsys.readouterr().out
    _check_each_frame_once(out, *straight)
    # explicit file, from frame 2: frames 3.. are overwritten, not duplicated
    ck = Path(out) / "checkpoints" / "checkpoint_000002.h5"
    assert not ck.exists()          # kept 2: 4 and 6 remain
    names = sorted(p.name for p in (Path(out) / "checkpoints").iterdir())
    assert names == ["checkpoint_000004.h5", "checkpoint_000006.h5"]
    assert main([cfg, "--out", out, "--quiet", "--restart", str(Path(out) / "checkpoints" /
                                                               "checkpoint_000004.h5")]) == 0
    _check_each_frame_once(out, *straight)


def test_every_two_restart_from_odd_frame(tmp_path):
    """output.every = 2 and a checkpoint at frame 3 (between written frames)."""
    ref = tmp_path / "ref"
    cfg = _config(tmp_path, every=2, ce=3, frames=8)
    assert main([cfg, "--out", str(ref), "--quiet"]) == 0
    out = str(tmp_path / "out")
    assert main([cfg, "--out", out, "--quiet", "--frames", "5"]) == 0     # checkpoint at 3
    ck = Path(out) / "checkpoints" / "checkpoint_000003.h5"
    assert main([cfg, "--out", out, "--quiet", "--restart", str(ck)]) == 0
    _check_each_frame_once(out, *_frames(ref))


def test_two_to_three_and_three_to_one_ranks(tmp_path, straight):
    cfg = _config(tmp_path)
    a = tmp_path / "a"
    p = _mpiexec(2, [cfg, "--out", str(a), "--quiet", "--frames", "4"], tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    p = _mpiexec(3, [cfg, "--out", str(a), "--quiet", "--restart", "latest"], tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "written on 2 rank(s), now 3" in p.stdout
    # rank 0 set the 2-rank run's summary aside, whole
    kept = json.loads((a / "summaries" / "summary_frames_000000-000004.json").read_text())
    assert (kept["ranks"], len(kept["newton_iterations"])) == (2, 4)
    assert [e["file"] for e in json.loads((a / "summary.json").read_text())["restart"]["earlier_summaries"]] \
        == ["summaries/summary_frames_000000-000004.json"]
    # a different rank count changes only the order of CG's global sums; the dynamics
    # amplify that round-off to 2-5e-12 over 6 frames with the default fused BAIJ
    # ILU(0) (2-4e-13 with an AIJ copy, -lc_pmat_type aij: its LU has 10x smaller
    # residuals, 4e-19 vs 4e-18; the preconditioner itself is partition independent)
    _check_each_frame_once(a, *straight, rtol=3e-11)
    b = tmp_path / "b"
    p = _mpiexec(3, [cfg, "--out", str(b), "--quiet", "--frames", "2"], tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert main([cfg, "--out", str(b), "--quiet", "--restart", "latest"]) == 0
    _check_each_frame_once(b, *straight, rtol=3e-11)


def _listed(out):
    """summary.json's (checkpoints, checkpoints_removed) frames, after checking that the
    checkpoints it lists are the folder's files with their sizes."""
    s = json.loads((Path(out) / "summary.json").read_text())
    folder = sorted((Path(out) / "checkpoints").glob("checkpoint_*.h5"))
    assert [c["path"] for c in s["checkpoints"]] == [str(p) for p in folder], s["checkpoints"]
    assert [c["bytes"] for c in s["checkpoints"]] == [p.stat().st_size for p in folder]
    assert not any(Path(c["path"]).exists() for c in s["checkpoints_removed"])
    return ([(c["frame"], c["seconds"] is not None) for c in s["checkpoints"]],
            [c["frame"] for c in s["checkpoints_removed"]])


def test_summary_lists_the_checkpoints_in_the_folder(tmp_path):
    """summary.json's ``checkpoints`` are the files in the folder at the end (main listed
    every one written, those the rotation had deleted too), with ``seconds`` for this
    run's; ``checkpoints_removed`` the ones gone: 1 rank, a restart on 3 ranks (the
    earlier run's checkpoint kept and those removed named), a run on 2 ranks."""
    cfg = _config(tmp_path, ce=1, kept=3)
    a = tmp_path / "a"
    assert main([cfg, "--out", str(a), "--quiet", "--frames", "4"]) == 0
    assert _listed(a) == ([(2, True), (3, True), (4, True)], [1])
    p = _mpiexec(3, [cfg, "--out", str(a), "--quiet", "--restart", "latest"], tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert _listed(a) == ([(4, False), (5, True), (6, True)], [2, 3])
    b = tmp_path / "b"
    p = _mpiexec(2, [cfg, "--out", str(b), "--quiet"], tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert _listed(b) == ([(4, True), (5, True), (6, True)], [1, 2, 3])


def _wait_for(path, proc, timeout=60):
    t0 = time.time()
    while not Path(path).exists():
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        assert time.time() - t0 < timeout, f"{path} never appeared"
        time.sleep(0.02)


def test_sigkill_while_writing_keeps_previous_checkpoint(tmp_path, straight):
    cfg = _config(tmp_path, kept=1)
    out = tmp_path / "out"
    env = dict(os.environ, LC_PETSC_TEST_CHECKPOINT_PAUSE="4:60")
    proc = subprocess.Popen([sys.executable, DRIVER, cfg, "--out", str(out), "--quiet"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(out / "checkpoints" / ".checkpoint_000004.h5.tmp", proc)
        time.sleep(0.3)                       # inside the write: positions written, paused
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.communicate()
    assert proc.returncode == -signal.SIGKILL
    names = sorted(p.name for p in (out / "checkpoints").iterdir())
    assert names == [".checkpoint_000004.h5.tmp", "checkpoint_000002.h5"]
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 0
    _check_each_frame_once(out, *straight)
    assert not (out / "checkpoints" / ".checkpoint_000004.h5.tmp").exists()


def test_sigterm_writes_final_checkpoint_that_restarts(tmp_path):
    frames = 150
    cfg = _config(tmp_path, frames=frames, every=3, ce=0)
    ref = tmp_path / "ref"
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, DRIVER, cfg, "--out", str(out), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait_for(out / "frames.h5", proc)
    time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    so, se = proc.communicate(timeout=60)
    assert proc.returncode == EXIT_PREEMPTED, se[-2000:]
    assert "SIGTERM received: stopped after frame" in se and "--restart latest" in se
    cks = list((out / "checkpoints").glob("checkpoint_*.h5"))
    assert len(cks) == 1
    k = int(cks[0].stem.split("_")[1])
    assert 0 < k < frames
    assert main([cfg, "--out", str(ref), "--quiet"]) == 0
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 0
    _check_each_frame_once(out, *_frames(ref))
    # the stopped run's summary is kept with its per-frame records (it was replaced)
    name = f"summaries/summary_frames_000000-{k:06d}.json"
    assert json.loads((out / "summary.json").read_text())["restart"]["earlier_summaries"] == [
        {"file": name, "frames": [0, k], "frames_kept": [0, k]}]
    stopped = json.loads((out / name).read_text())
    assert (stopped["preempted"], len(stopped["newton_iterations"])) == ("SIGTERM", k)


def _flip(path, dataset, at=100):
    with h5py.File(path, "r") as f:
        off = f[dataset].id.get_offset()
    with open(path, "r+b") as fh:
        fh.seek(off + at)
        b = fh.read(1)
        fh.seek(off + at)
        fh.write(bytes([b[0] ^ 0x5A]))


def _damage_header(path, dataset):
    """Break the object header of ``dataset``: its version byte (h5py then raises
    KeyError "bad object header version number" on opening it, not OSError)."""
    with h5py.File(path, "r") as f:
        addr = f.userblock_size + h5py.h5o.get_info(f[dataset].id).addr
    with open(path, "r+b") as fh:
        fh.seek(addr)
        fh.write(b"\x07")


def _unseal(path):
    """Zero the seal in the user block: a checkpoint written before it (opened as before)."""
    with open(path, "r+b") as fh:
        fh.write(bytes(512))


@pytest.mark.parametrize("damage, message", [
    (lambda p: _flip(p, "velocities"), "corrupt checkpoint: dataset /velocities fails its checksum"),
    (lambda p: _damage_header(p, "wisp_offsets"), "corrupt checkpoint: its HDF5 metadata (all but the "
     "datasets' values) fails its checksum (sha256 in the user block); not opened"),
    # without the seal libhdf5 meets the damage: h5py's KeyError was a traceback (exit 1)
    # from --restart FILE and from --restart latest, which never got to the older one
    (lambda p: (_unseal(p), _damage_header(p, "wisp_offsets")), "corrupt checkpoint: its HDF5 structure "
     "is damaged (Unable to open object (bad object header version number))"),
])
def test_corruption_detected_and_latest_falls_back(tmp_path, straight, capsys, damage, message):
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    assert main([cfg, "--out", str(out), "--quiet", "--frames", "4"]) == 0
    ck4 = out / "checkpoints" / "checkpoint_000004.h5"
    damage(ck4)
    capsys.readouterr()
    assert main([cfg, "--out", str(out), "--quiet", "--restart", str(ck4)]) == 2
    err = capsys.readouterr().err
    assert f"{ck4}: {message}" in err, err
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 0
    err = capsys.readouterr().err
    assert "skipping an invalid checkpoint" in err and message in err
    assert "falling back to" in err and "checkpoint_000002.h5" in err
    _check_each_frame_once(out, *straight)


def _damage_format_heap_index(path):
    """The top byte of the global-heap index of the ``format`` attribute's string
    (length 19, heap address, index): libhdf5 1.10 segfaults opening the file."""
    data = bytearray(Path(path).read_bytes())
    at = data.index(struct.pack("<I", len("lc_petsc checkpoint")), data.index(b"format\x00\x00"))
    data[at + 15] = 100
    Path(path).write_bytes(bytes(data))


def test_damaged_metadata_is_refused_before_libhdf5_opens_it(tmp_path, straight):
    """A checkpoint whose metadata libhdf5 cannot survive (a segfault, exit 59 through
    PETSc's handler, in a subprocess here) is refused by its seal, and --restart
    latest falls back to the older checkpoint."""
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    assert main([cfg, "--out", str(out), "--quiet", "--frames", "4"]) == 0
    ck4 = out / "checkpoints" / "checkpoint_000004.h5"
    _damage_format_heap_index(ck4)
    p = subprocess.run([sys.executable, DRIVER, cfg, "--out", str(out), "--quiet", "--restart", "latest"],
                       capture_output=True, text=True, timeout=300, env=MPI_ENV)
    assert p.returncode == 0, p.stderr[-3000:]
    assert f"skipping an invalid checkpoint: {ck4}: corrupt checkpoint: its HDF5 metadata" in p.stderr, p.stderr
    assert "falling back to" in p.stderr and "checkpoint_000002.h5" in p.stderr
    _check_each_frame_once(out, *straight)


def test_truncated_and_flipped_positions_rejected(tmp_path, capsys):
    cfg = _config(tmp_path, ce=1, kept=3, frames=3)
    out = tmp_path / "out"
    assert main([cfg, "--out", str(out), "--quiet"]) == 0
    c3, c2 = out / "checkpoints" / "checkpoint_000003.h5", out / "checkpoints" / "checkpoint_000002.h5"
    size = c3.stat().st_size
    with open(c3, "r+b") as fh:
        fh.truncate(size - 1000)
    _flip(c2, "positions", at=8 * 3 * 17)
    capsys.readouterr()
    assert main([cfg, "--out", str(out), "--quiet", "--restart", str(c3), "--frames", "4"]) == 2
    err = capsys.readouterr().err
    assert str(c3) in err and ("truncated" in err or "unreadable" in err or "corrupt" in err), err
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest", "--frames", "4"]) == 0
    err = capsys.readouterr().err
    assert "/positions fails its checksum" in err and "checkpoint_000001.h5" in err


def test_a_run_killed_in_its_end_of_run_outputs_restarts_from_its_last_frame(tmp_path, straight, capsys):
    """Killed (SIGKILL; or mpiexec's SIGKILL a second after its SIGTERM) while writing the
    exports after its last frame's checkpoint, a run leaves frames.h5 whole, that
    checkpoint and no summary.json: a new run is refused ("continue it with --restart
    latest"), and --restart latest was refused too ("nothing to do"), so only --force
    (start over) was left.  Now the restart writes the outputs, running no frame."""
    cfg = _config(tmp_path, frames=4)
    out = tmp_path / "out"
    assert main([cfg, "--out", str(out), "--quiet"]) == 0
    (out / "summary.json").unlink()          # what the kill during the exports leaves
    capsys.readouterr()
    assert main([cfg, "--out", str(out), "--quiet"]) == 2
    assert "continue it with --restart latest" in capsys.readouterr().err
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 0
    text = capsys.readouterr().out
    assert "frame 4 is the run's last: no frame to run; writing the end-of-run outputs" in text
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["frames"], summary["frames_this_run"], summary["error"]) == (4, 0, None)
    assert summary["restart"]["frame"] == 4
    pos, t = _frames(out)
    ref_pos, ref_t = straight
    assert np.array_equal(pos, ref_pos[:5]) and np.array_equal(t, ref_t[:5])
    # the outputs are done: the same restart again has nothing to do
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 2
    assert "nothing to do" in capsys.readouterr().err


def test_restart_latest_of_a_finished_run_is_refused(tmp_path, straight, capsys):
    """A finished run whose last checkpoint is before its end (5 frames, checkpoints at
    2 and 4): --restart latest ran frame 5 again (on another rank count to round-off) and
    replaced the outputs and summary.json with this run's, where a run checkpointed at
    its end was refused ("nothing to do").  Now it is refused too, the folder unchanged;
    a larger --frames continues it as before."""
    import hashlib
    cfg = _config(tmp_path, frames=5)
    out = tmp_path / "out"
    assert main([cfg, "--out", str(out), "--quiet"]) == 0

    def files():
        return {str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(out.rglob("*")) if p.is_file()}
    before = files()
    capsys.readouterr()
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 2
    ck = out / "checkpoints" / "checkpoint_000004.h5"
    assert (f"{out} holds a run that finished its 5 frames (its summary.json): nothing to do; to continue "
            f"it from {ck} give a larger --frames (time.frames, the total), or add --force to run frame 5 "
            "again from it") in capsys.readouterr().err
    assert files() == before
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest", "--frames", "6"]) == 0
    pos, t = _frames(out)
    assert np.array_equal(pos, straight[0]) and np.array_equal(t, straight[1])


def test_clear_errors(tmp_path, capsys):
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    assert main([cfg, "--out", str(out), "--quiet", "--frames", "2"]) == 0
    ck = out / "checkpoints" / "checkpoint_000002.h5"
    capsys.readouterr()

    def err(args):
        assert main([cfg, "--out", str(out), "--quiet"] + args) == 2
        return capsys.readouterr().err

    assert "no such checkpoint file" in err(["--restart", str(tmp_path / "nope.h5")])
    # a run killed before its first checkpoint: say so, and how to go on (main: "there are none")
    assert main([cfg, "--out", str(tmp_path / "early"), "--quiet", "--restart", "latest"]) == 2
    assert ("no valid checkpoint in '" + str(tmp_path / "early" / "checkpoints") + "' (there are none: the run "
            "there stopped before its first checkpoint (output.checkpoint_every); run the same command without "
            "--restart to start it over)") in capsys.readouterr().err
    assert "not an lc_petsc checkpoint" in err(["--restart", cfg])
    assert "not an lc_petsc checkpoint" in err(["--restart", str(out / "frames.h5")])
    assert "nothing to do" in err(["--restart", str(ck), "--frames", "2"])
    newer = tmp_path / "newer.h5"
    newer.write_bytes(ck.read_bytes())
    with h5py.File(newer, "r+") as f:
        f.attrs["format_version"] = 99
    seal(newer, h5py, VERTEX_DATASETS + GLOBAL_DATASETS)        # as a newer lc_petsc would
    assert "format version 99 is newer" in err(["--restart", str(newer)])
    # a different scene: wisp / vertex counts
    other = _config(tmp_path, name="other.toml", **{"n_wisps = 5": "n_wisps = 6"})
    assert main([other, "--out", str(out), "--quiet", "--restart", str(ck)]) == 2
    e = capsys.readouterr().err
    assert "5 wisps and 505 vertices, the scene 6 wisps and 606 vertices" in e
    # ... and which setting made it another scene, with what to do (main: the counts only)
    assert (f"; {ck} was written with another config, which differs in scene.n_wisps (checkpoint: 5, "
            f"config: 6): restart with that config (its attribute config_toml)") in e, e
    # a different config: named keys with both values; --force accepts it
    diff = _config(tmp_path, name="diff.toml", **{"youngs_modulus = 2.5e8": "youngs_modulus = 3e8",
                                                  "head_period = 0.4": "head_period = 0.4\nhead_stiffness = 2e5"})
    assert main([diff, "--out", str(out), "--quiet", "--restart", str(ck)]) == 2
    e = capsys.readouterr().err
    assert ("the config differs from the checkpoint's in material.youngs_modulus (checkpoint: 250000000.0, "
            "config: 300000000.0), physics.head_stiffness (checkpoint: 100000.0, config: 200000.0); restart "
            "with the config the checkpoint ran with (its attribute config_toml) or add --force (continues "
            "with this config)") in e, e
    assert main([diff, "--out", str(out), "--quiet", "--restart", str(ck), "--force", "--frames", "3"]) == 0
    # a different groom (pinned vertices): refused even with --force, frames.h5 holds one groom
    pins = _config(tmp_path, name="pins.toml", **{"seed = 3": "seed = 3\nn_pinned = 5"})
    assert main([pins, "--out", str(out), "--quiet", "--restart", str(ck), "--force", "--frames", "3"]) == 2
    e = capsys.readouterr().err
    assert "scene.n_pinned" in e and "the groom cannot change in a restart, not even with --force" in e, e
    # a frames.h5 of another run with the same counts (another dt) is not appended to
    own = (out / "frames.h5").read_bytes()
    with h5py.File(out / "frames.h5", "r+") as f:
        f.attrs["dt"] = 0.02
    assert "written with dt = 0.02, this run has 0.0333333" in err(["--restart", str(ck)])
    (out / "frames.h5").write_bytes(own)
    # output-only keys may change
    more = _config(tmp_path, name="more.toml", ce=1, kept=5)
    assert main([more, "--out", str(out), "--quiet", "--restart", "latest", "--frames", "4"]) == 0
    assert "PETSc options differ" not in capsys.readouterr().err
    # solver options may change, with a warning naming them (summary.json too)
    assert main([more, "--out", str(out), "--quiet", "--restart", "latest", "--frames", "5",
                 "-ksp_rtol", "1e-3", "-ksp_monitor_cancel"]) == 0
    e = capsys.readouterr().err
    assert "PETSc options differ from the checkpoint's: -ksp_rtol 1e-3 (was 1e-4); the run" in e, e
    assert any("-ksp_rtol 1e-3" in w for w in json.loads((out / "summary.json").read_text())["warnings"])
    # options that only report (monitors, views, logs) change nothing: no warning
    assert main([more, "--out", str(out), "--quiet", "--restart", "latest", "--frames", "6",
                 "-ksp_rtol", "1e-3", "-lc_newton_monitor", "-ksp_converged_reason"]) == 0
    assert "PETSc options differ" not in capsys.readouterr().err


def test_checkpoint_contents_and_config_keys(tmp_path):
    cfg = _config(tmp_path, frames=2, ce=2)
    out = tmp_path / "out"
    assert main([cfg, "--out", str(out), "--quiet", "-ksp_rtol", "1e-9"]) == 0
    with h5py.File(out / "checkpoints" / "checkpoint_000002.h5", "r") as f:
        a = dict(f.attrs)
        assert a["format"] == "lc_petsc checkpoint" and a["format_version"] == 1
        assert a["frame"] == 2 and a["n_wisps"] == 5 and a["n_vertices"] == 505
        assert "ksp_rtol" in a["petsc_options"] and "[scene]" in a["config_toml"]
        assert len(a["config_sha256"]) == 64 and a["lc_petsc_version"]
        for k in ("positions", "velocities", "rest_positions", "pinned", "wisp_offsets", "head_state"):
            assert len(f[k].attrs["sha256"]) == 64
        assert f["head_state"][0] == a["time"]
    base = {"output": {"checkpoint_every": -1}}
    with pytest.raises(ConfigError, match="output.checkpoint_every must be an integer >= 0"):
        config_from_dict(base)
    with pytest.raises(ConfigError, match="output.checkpoints_kept must be an integer >= 1"):
        config_from_dict({"output": {"checkpoints_kept": 0}})


def test_a_key_newer_than_the_checkpoint_is_no_difference_at_its_default():
    """A checkpoint written before a key existed (time.newton_stop, solver.exact_stay came
    on 2026-12-04) restarts with that key at its default, and not with another value; a
    key of the checkpoint that changed is still a difference."""
    from lc_petsc.config import SimConfig
    from lc_petsc.io.checkpoint import config_differences
    defaults = SimConfig().to_dict()
    current = SimConfig().to_dict()
    saved = SimConfig().to_dict()
    del saved["time"]["newton_stop"], saved["solver"]["exact_stay"]
    assert config_differences(saved, current, defaults=defaults) == []
    assert config_differences(saved, current) == ["solver.exact_stay", "time.newton_stop"]
    current["solver"]["exact_stay"] = True
    current["time"]["dt"] = 0.01
    assert config_differences(saved, current, defaults=defaults) == ["solver.exact_stay", "time.dt"]


@pytest.mark.parametrize("key, legacy", [("time.carry_with_head", False),
                                         ("material.twist_rest_sine", 0.0)])
def test_a_checkpoint_from_before_a_key_is_a_difference_with_its_new_default(key, legacy):
    """time.carry_with_head (2026-12-05) defaults to true, but the code before it did not
    carry; material.twist_rest_sine (2026-12-06) defaults to 0.05, the code before it did
    not fade: a checkpoint without the key ran as the legacy value, so restarting it with
    the new default is a config difference (refused without --force), and with the key
    set to the legacy value none."""
    from lc_petsc.config import SimConfig
    from lc_petsc.io.checkpoint import config_differences
    table, name = key.split(".")
    defaults = SimConfig().to_dict()
    saved = SimConfig().to_dict()
    del saved[table][name]
    current = SimConfig().to_dict()
    assert current[table][name] != legacy
    assert config_differences(saved, current, defaults=defaults) == [key]
    current[table][name] = legacy
    assert config_differences(saved, current, defaults=defaults) == []


def test_restarting_a_checkpoint_from_before_the_carry_is_refused_with_the_fix(tmp_path, capsys):
    """A checkpoint whose config lacks time.carry_with_head (written before it existed, by
    code that did not carry): the restart is refused, naming the key and the value that
    continues the run as it ran; with that value it restarts."""
    import json
    from lc_petsc.io.checkpoint import _meta_digest, config_sha256
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    assert main([cfg, "--out", str(out), "--quiet", "--frames", "2"]) == 0
    ck = out / "checkpoints" / "checkpoint_000002.h5"
    with h5py.File(ck, "r+") as f:
        config = json.loads(f.attrs["config"])
        del config["time"]["carry_with_head"]
        f.attrs["config"] = json.dumps(config, sort_keys=True)
        f.attrs["config_sha256"] = config_sha256(config)
        f.attrs["meta_sha256"] = _meta_digest(dict(f.attrs))      # as its writer had
    _unseal(ck)                       # that code wrote no seal either
    assert main([cfg, "--out", str(out), "--quiet", "--restart", str(ck), "--frames", "3"]) == 2
    e = capsys.readouterr().err
    assert "time.carry_with_head" in e and "time.carry_with_head = false" in e, e
    old = _config(tmp_path, name="old.toml", **{"[time]": "[time]\ncarry_with_head = false"})
    assert main([old, "--out", str(out), "--quiet", "--restart", str(ck), "--frames", "3"]) == 0


def test_restart_with_a_nonzero_initial_guess_is_bitwise_equal(tmp_path):
    """-ksp_initial_guess_nonzero: CG starts from the solver's solution vector, which
    holds the last Newton step of the frame before; a restart has no such step (it is not
    in the checkpoint), so every frame's first solve starts from zero, in a straight run
    too (before, the restart's first frame differed by 2e-7 cm on the touching wisps)."""
    solver = '\n[solver]\noptions = "-ksp_initial_guess_nonzero"\n'
    cfg = _config(tmp_path, frames=5, ce=2, kept=5)
    Path(cfg).write_text(Path(cfg).read_text() + solver)
    ref = tmp_path / "ref"
    assert main([cfg, "--out", str(ref), "--quiet"]) == 0
    out = tmp_path / "out"
    assert main([cfg, "--out", str(out), "--quiet", "--frames", "3"]) == 0    # checkpoint at 2
    ck = out / "checkpoints" / "checkpoint_000002.h5"
    assert main([cfg, "--out", str(out), "--quiet", "--frames", "5", "--restart", str(ck)]) == 0
    _check_each_frame_once(out, *_frames(ref))


def test_a_restart_sets_the_later_checkpoints_aside(tmp_path, straight, capsys):
    """A restart from frame 2 of a run that had checkpoints up to frame 6 replaces that
    run from frame 3 on: its checkpoints 4 and 6 are renamed aside (kept), so a later
    --restart latest continues the new run (before, it picked the old checkpoint 6,
    whose frames the new frames.h5 no longer holds, and was refused; and the rotation
    kept the old ones in place of the new run's)."""
    cfg = _config(tmp_path, kept=10)
    out = tmp_path / "out"
    assert main([cfg, "--out", str(out), "--quiet"]) == 0
    folder = out / "checkpoints"
    assert sorted(p.name for p in folder.iterdir()) == [f"checkpoint_00000{k}.h5" for k in (2, 4, 6)]
    capsys.readouterr()
    assert main([cfg, "--out", str(out), "--quiet", "--frames", "3",
                 "--restart", str(folder / "checkpoint_000002.h5")]) == 0
    err = capsys.readouterr().err
    assert "checkpoint_000004.h5 -> checkpoint_000004.superseded-1.h5" in err
    assert sorted(p.name for p in folder.iterdir()) == [
        "checkpoint_000002.h5", "checkpoint_000004.superseded-1.h5", "checkpoint_000006.superseded-1.h5"]
    summary = json.loads((out / "summary.json").read_text())
    assert any("renamed aside" in w for w in summary["warnings"])
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 0
    assert "restarting from" in capsys.readouterr().out
    _check_each_frame_once(out, *straight)
    # the set-aside files stay, and a second set-aside of the same frame gets the next number
    assert main([cfg, "--out", str(out), "--quiet", "--frames", "3",
                 "--restart", str(folder / "checkpoint_000002.h5")]) == 0
    assert (folder / "checkpoint_000004.superseded-2.h5").exists()
    assert (folder / "checkpoint_000006.superseded-1.h5").exists()


def test_a_restart_keeps_the_earlier_summaries(tmp_path, capsys):
    """A restart used to replace summary.json with one describing its own frames only:
    the earlier run's per-frame records (Newton, KSP, warnings) were gone.  Now the
    earlier summary.json is renamed into summaries/ under the frames it covers, byte for
    byte, and listed in restart.earlier_summaries with the frames no later run re-ran
    (``frames_kept``); a second restart keeps both; a damaged one is kept under a name
    saying so, with a warning; a new run removes them with the run they belong to."""
    cfg = _config(tmp_path, kept=10)
    out = tmp_path / "out"
    folder = out / "summaries"
    assert main([cfg, "--out", str(out), "--quiet", "--frames", "3"]) == 0     # checkpoint at 2
    first = (out / "summary.json").read_bytes()
    assert len(json.loads(first)["newton_iterations"]) == 3
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 0    # frames 3-6
    a = folder / "summary_frames_000000-000003.json"
    assert a.read_bytes() == first
    s = json.loads((out / "summary.json").read_text())
    assert (s["restart"]["frame"], len(s["newton_iterations"])) == (2, 4)
    assert s["restart"]["earlier_summaries"] == [
        {"file": "summaries/summary_frames_000000-000003.json", "frames": [0, 3], "frames_kept": [0, 2]}]
    # the restart's keys and its folder's checkpoints/ and summaries/ are in the README's outputs table
    assert undocumented_summary_keys(s) == [] and undocumented_outputs(out) == []
    assert {"checkpoints", "summaries"} <= {q.name for q in out.iterdir()}
    second = (out / "summary.json").read_bytes()
    # a second restart, from frame 4: frames 5-6 again; both earlier summaries kept
    ck4 = str(out / "checkpoints" / "checkpoint_000004.h5")
    assert main([cfg, "--out", str(out), "--quiet", "--restart", ck4]) == 0
    b = folder / "summary_frames_000002-000006.json"
    assert a.read_bytes() == first and b.read_bytes() == second
    s = json.loads((out / "summary.json").read_text())
    assert s["restart"]["earlier_summaries"] == [
        {"file": "summaries/summary_frames_000000-000003.json", "frames": [0, 3], "frames_kept": [0, 2]},
        {"file": "summaries/summary_frames_000002-000006.json", "frames": [2, 6], "frames_kept": [2, 4]}]
    capsys.readouterr()
    assert main([cfg, "--out", str(out), "--restart", ck4]) == 0
    assert "the earlier runs' summaries (set aside by the restarts): summaries/summary_frames_000000-000003.json " \
           "(frames 1-3)" in capsys.readouterr().out
    assert (folder / "summary_frames_000004-000006.json").is_file()
    # a damaged summary.json does not stop the restart
    (out / "summary.json").write_text('{"frames": 6, "newton_iter')
    assert main([cfg, "--out", str(out), "--quiet", "--restart", ck4]) == 0
    err = capsys.readouterr().err
    assert f"the earlier run's {out / 'summary.json'} is damaged (not JSON: " in err
    assert f"kept as {folder / 'summary_damaged.json'}" in err
    assert (folder / "summary_damaged.json").read_text() == '{"frames": 6, "newton_iter'
    s = json.loads((out / "summary.json").read_text())
    assert [e["file"] for e in s["restart"]["earlier_summaries"]] == [
        f"summaries/{n}.json" for n in ("summary_frames_000000-000003", "summary_frames_000002-000006",
                                        "summary_frames_000004-000006", "summary_damaged")]
    assert s["restart"]["earlier_summaries"][-1]["frames"] is None
    assert any("is damaged" in w for w in s["warnings"])
    # the same frames set aside again get the next number
    assert main([cfg, "--out", str(out), "--quiet", "--restart", ck4]) == 0
    assert (folder / "summary_frames_000004-000006.2.json").is_file()
    # a new run replaces the run they belong to
    assert main([cfg, "--out", str(out), "--quiet", "--force"]) == 0
    assert not folder.exists()
    assert json.loads((out / "summary.json").read_text())["restart"] is None
