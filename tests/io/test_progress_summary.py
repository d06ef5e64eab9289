"""The summary a run keeps on disk while it goes (status ``running``) and the joined
per-frame history of a restarted run (``scripts/join_summaries.py``).

A run killed by SIGKILL (the OOM killer, a batch system's hard limit) used to leave no
summary.json: its per-frame records were lost and a restart had nothing to set aside.
Now rank 0 replaces summary.json (atomically, synced) before each checkpoint and after
each flush of frames.h5; the killed run's records are set aside by the restart like any
other, and join_summaries.py joins the segments into one record per frame."""

import errno
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lc_petsc.batch import main
from lc_petsc.io.history import history_table
from lc_petsc.io.summary import write_summary

from sim_helpers import MPI_ENV, hairball_toml  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
DRIVER = str(ROOT / "drivers" / "simulate.py")
FRAMES = 10
#: strand contact on, so the records hold contact pairs per frame
SCENE = hairball_toml(n_wisps=5, seed=3, frames=FRAMES,
                      output="previews = false\nxdmf = false\nusd = false\ncheckpoint_every = {ce}\n"
                             "checkpoints_kept = 2").replace(
    '"head_collision"]', '"head_collision", "strand_collision"]')
#: the keys of a frame's record that do not depend on the clock
DETERMINISTIC = ("newton_iterations", "ksp_solves", "ksp_iterations", "newton_substeps",
                 "contact.pairs_per_frame")


def _config(d, ce=2):
    p = Path(d) / "s.toml"
    p.write_text(SCENE.format(ce=ce))
    return str(p)


def _script(name):
    import importlib.util
    spec = importlib.util.spec_from_file_location(f"script_{name}", ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _records(summary, start=0):
    """{key: per-frame list} of a single summary (frames start + 1 ..), ksp split per frame."""
    out = {k: summary[k] for k in ("newton_iterations", "ksp_solves", "newton_substeps")}
    out["contact.pairs_per_frame"] = summary["contact"]["pairs_per_frame"]
    at = [sum(summary["ksp_solves"][:j]) for j in range(len(summary["ksp_solves"]) + 1)]
    out["ksp_iterations"] = [summary["ksp_iterations"][a:b] for a, b in zip(at, at[1:])]
    return out


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """The uninterrupted run's summary (serial, no checkpoints)."""
    d = tmp_path_factory.mktemp("straight")
    assert main([_config(d, ce=0), "--out", str(d / "out"), "--quiet"]) == 0
    return json.loads((d / "out" / "summary.json").read_text())


def _wait(proc, what, timeout=120):
    t0 = time.time()
    while not what():
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        assert time.time() - t0 < timeout, "timed out"
        time.sleep(0.02)


def test_a_killed_run_keeps_its_records_and_a_restart_sets_them_aside(tmp_path, straight, capsys):
    """SIGKILL while checkpoint 6 is written (paused there by the test hook; checkpoint 4
    is the newest whole one): summary.json is on disk, status running, with the records
    of frames 1-6; a second run into the busy folder is refused by the lock and leaves it
    alone; check_outputs.py and join_summaries.py say it is running, its pid alive (it
    holds the lock), and after the kill that it was killed (its lock stale); a new run is
    refused (a killed run),
    ``--restart latest`` sets the killed run's summary aside with frames_kept [0, 4];
    the joined history has every frame once, equal to the uninterrupted run's records."""
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    env = dict(MPI_ENV, LC_PETSC_TEST_CHECKPOINT_PAUSE="6:120")
    proc = subprocess.Popen([sys.executable, DRIVER, cfg, "--out", str(out), "--quiet"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait(proc, lambda: (out / "checkpoints" / ".checkpoint_000006.h5.tmp").exists())
        running = (out / "summary.json").read_bytes()
        capsys.readouterr()
        assert main([cfg, "--out", str(out), "--quiet"]) == 2     # the lock: the run is going
        assert f"pid {proc.pid}" in capsys.readouterr().err
        assert (out / "summary.json").read_bytes() == running
        alive = (f"running (pid {proc.pid} on host {socket.gethostname()}, alive: it holds the folder's lock "
                 ".lc_petsc.lock), 6 frames recorded so far")
        assert _script("check_outputs").main([str(out)]) == 1
        assert capsys.readouterr().out == \
            f"{out}: not finished: summary.json says running, 6 frames recorded: {alive}\n"
        assert _script("join_summaries").main([str(out), "--quiet", "--json", str(tmp_path / "h.json")]) == 0
        said = capsys.readouterr().out
        assert f"(the last says running: {alive})" in said and "segment 0: summary.json, running, 1 rank(s)" in said
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.communicate()
    assert proc.returncode == -signal.SIGKILL
    assert sorted(p.name for p in (out / "checkpoints").glob("checkpoint_*.h5")) == \
        ["checkpoint_000002.h5", "checkpoint_000004.h5"]
    killed = json.loads(running)
    assert straight["status"] == "finished"
    straight = _records(straight)
    assert (killed["status"], killed["frames"], killed["preempted"], killed["error"]) == ("running", 6, None, None)
    assert _records(killed) == {k: v[:6] for k, v in straight.items()}
    assert killed["output"]["frames_written"] == 7 and killed["restart"] is None
    # killed in the middle of writing the next one: its temporary file never replaces it
    (out / "summary.json.tmp").write_text('{"status": "running", "frames": 8, "newton_iter')
    assert (out / "summary.json").read_bytes() == running
    capsys.readouterr()
    assert _script("check_outputs").main([str(out)]) == 1
    said = capsys.readouterr().out
    assert said.startswith(f"{out}: not finished: summary.json says running, 6 frames recorded: killed after frame "
                           f"6 (its lock .lc_petsc.lock is stale: pid {proc.pid} on host {socket.gethostname()}, "
                           "started ")
    assert said.endswith("; no process holds it); --restart latest continues it\n")
    assert _script("join_summaries").main([str(out), "--quiet", "--json", str(tmp_path / "h.json")]) == 0
    said = capsys.readouterr().out
    assert f"(the last says running: killed after frame 6 (its lock .lc_petsc.lock is stale: pid {proc.pid}" in said
    assert "segment 0: summary.json, killed (running), 1 rank(s)" in said
    assert main([cfg, "--out", str(out), "--quiet"]) == 2
    assert "killed after frame 6 (its summary.json, kept while it ran, says running)" in capsys.readouterr().err
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 0
    aside = out / "summaries" / "summary_frames_000000-000006.json"
    # set aside as it was, with what the restart found of its run (its lock stale: killed)
    assert json.loads(aside.read_text()) == {**json.loads(running), "ended": "killed"}
    assert not (out / "summary.json.tmp").exists() and not list((out / "summaries").glob("*.tmp"))
    s = json.loads((out / "summary.json").read_text())
    assert s["status"] == "finished" and s["restart"]["frame"] == 4
    assert s["restart"]["earlier_summaries"] == [
        {"file": "summaries/summary_frames_000000-000006.json", "frames": [0, 6], "frames_kept": [0, 4]}]
    # before checkpoints 6, 8 and 10 (and after a frames.h5 flush, every 30 s)
    assert s["output"]["progress_summaries"]["written"] >= 3
    capsys.readouterr()
    assert _script("join_summaries").main([str(out)]) == 0
    said = capsys.readouterr().out
    assert "segment 0: summaries/summary_frames_000000-000006.json, killed (running), 1 rank(s)" in said
    h = json.loads((out / "history.json").read_text())
    pf = h["per_frame"]
    assert pf["frame"] == list(range(1, FRAMES + 1)) and pf["segment"] == [0] * 4 + [1] * 6
    assert {k: pf[k] for k in DETERMINISTIC} == straight
    assert pf["config_sha256"] == [h["segments"][0]["config_sha256"]] * FRAMES
    assert [seg["ended"] for seg in h["segments"]] == ["killed", None]
    # the next run into the folder removes the history, which would be stale
    assert main([cfg, "--out", str(out), "--quiet", "--force"]) == 0
    assert not (out / "history.json").exists()


def _summary(frames, first=0, status="finished", earlier=None, ranks=1):
    n = frames - first
    return {"frames": frames, "ranks": ranks, "status": status, "config": {"time": {"dt": 0.1, "frames": frames}},
            "restart": None if not first else {"frame": first, "earlier_summaries": earlier or []},
            "newton_iterations": [first * 10 + j for j in range(n)], "ksp_solves": [1] * n,
            "ksp_iterations": list(range(n)), "per_frame_keys": ["newton_iterations", "ksp_solves"]}


def _folder(tmp_path):
    """A run of 6 frames killed after frame 4 (checkpoint 2), restarted from 2 on 2 ranks."""
    out = tmp_path / "o"
    (out / "summaries").mkdir(parents=True)
    write_summary(out / "summaries" / "summary_frames_000000-000004.json", _summary(4, status="running"))
    entry = {"file": "summaries/summary_frames_000000-000004.json", "frames": [0, 4], "frames_kept": [0, 2]}
    write_summary(out / "summary.json", _summary(6, first=2, earlier=[entry], ranks=2))
    return out, entry


def test_join_takes_each_frame_from_the_last_segment_that_ran_it(tmp_path):
    from lc_petsc.io.history import join_history
    out, _ = _folder(tmp_path)
    h = join_history(out)
    pf = h["per_frame"]
    assert pf["frame"] == [1, 2, 3, 4, 5, 6] and pf["segment"] == [0, 0, 1, 1, 1, 1]
    assert pf["ranks"] == [1, 1, 2, 2, 2, 2]
    assert pf["newton_iterations"] == [0, 1, 20, 21, 22, 23]
    assert pf["ksp_iterations"] == [[0], [1], [0], [1], [2], [3]]
    # time.frames is a key a restart may change: the same digest
    assert h["segments"][0]["config_sha256"] == h["segments"][1]["config_sha256"]
    assert [s["status"] for s in h["segments"]] == ["running", "finished"]


def test_join_read_through_a_closed_pipe_writes_the_history_without_petsc(tmp_path):
    """`join_summaries.py OUT | head -1`: the table's reader leaves early; the script
    still writes history.json and exits 0 (it had loaded PETSc through lc_petsc.job, whose
    SIGPIPE handler aborted MPI: exit 59, nothing written)."""
    out, entry = _folder(tmp_path)
    # a table of 3,000 rows: longer than the pipe's buffer
    write_summary(out / "summary.json", _summary(3000, first=2, earlier=[entry], ranks=2))
    script = Path(__file__).resolve().parents[2] / "scripts" / "join_summaries.py"
    proc = subprocess.Popen([sys.executable, str(script), str(out)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    assert proc.stdout.readline().startswith(str(out))
    proc.stdout.close()
    err = proc.stderr.read()
    assert proc.wait(timeout=60) == 0, err
    assert "Traceback" not in err and "MPI_ABORT" not in err, err
    assert json.loads((out / "history.json").read_text())["per_frame"]["frame"][-1] == 3000


def test_join_refuses_a_damaged_or_inconsistent_set(tmp_path, capsys):
    from lc_petsc.io.history import join_history
    out, entry = _folder(tmp_path)
    aside = out / "summaries" / "summary_frames_000000-000004.json"
    good = aside.read_text()
    aside.write_text(good[:40])
    with pytest.raises(ValueError, match="summaries/summary_frames_000000-000004.json: damaged"):
        join_history(out)
    aside.unlink()
    capsys.readouterr()
    assert _script("join_summaries").main([str(out)]) == 2
    assert "summaries/summary_frames_000000-000004.json: missing; nothing written" in capsys.readouterr().err
    assert not (out / "history.json").exists()
    aside.write_text(good)
    # listed as kept up to frame 1 only: frame 2 has no record
    write_summary(out / "summary.json", _summary(6, first=2, earlier=[dict(entry, frames_kept=[0, 1])]))
    with pytest.raises(ValueError, match="summary.json: its kept frames start at 3; frames 2-2 have no record"):
        join_history(out)
    # kept up to frame 3 while the restart re-ran it: recorded twice
    write_summary(out / "summary.json", _summary(6, first=2, earlier=[dict(entry, frames_kept=[0, 3])]))
    with pytest.raises(ValueError, match="frames 3-3 are recorded twice"):
        join_history(out)
    s = _summary(6, first=2, earlier=[entry])
    s["newton_iterations"].pop()
    write_summary(out / "summary.json", s)
    with pytest.raises(ValueError, match="summary.json: newton_iterations has 3 entries for its 4 frames"):
        join_history(out)


def test_the_running_summary_on_every_rank_count_restarts(tmp_path, straight):
    """On 2 ranks (mpiexec): the summary kept while the run goes is written collectively
    (rank 0 writes, every rank reduces); its ranks SIGKILLed while checkpoint 4 is
    written (the folder's lock says running, then killed), a restart on 1 rank sets it
    aside and the history names both rank counts."""
    from lc_petsc.io.history import join_history, running_state
    cfg = _config(tmp_path, ce=2)
    out = tmp_path / "out"
    env = dict(MPI_ENV, LC_PETSC_TEST_CHECKPOINT_PAUSE="4:120")
    proc = subprocess.Popen(["mpiexec", "--oversubscribe", "-n", "2", sys.executable, DRIVER, cfg, "--out",
                             str(out), "--quiet"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=tmp_path, stdin=subprocess.DEVNULL)
    try:
        _wait(proc, lambda: (out / "checkpoints" / ".checkpoint_000004.h5.tmp").exists())
        running = json.loads((out / "summary.json").read_text())
        ranks = _descendants(proc.pid)
        state, said = running_state(out, running)       # rank 0 holds the lock
        assert state == "running" and int(said.split()[2]) in ranks and "alive" in said
    finally:
        for pid in _descendants(proc.pid):      # the ranks, as the OOM killer or a lost node does
            os.kill(pid, signal.SIGKILL)
        proc.communicate(timeout=60)
    assert running_state(out, running)[0] == "killed"
    assert (running["status"], running["frames"], running["ranks"]) == ("running", 4, 2)
    assert len(running["newton_iterations"]) == len(running["contact"]["pairs_per_frame"]) == 4
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"]) == 0
    h = join_history(out)
    assert h["segments"][0]["frames_kept"] == [0, 2] and h["per_frame"]["ranks"] == [2] * 2 + [1] * 8
    assert h["per_frame"]["frame"] == list(range(1, FRAMES + 1))
    # the counts a rank count does not change (the positions differ by round-off)
    ref = _records(straight)
    assert [h["per_frame"][k] for k in ("newton_iterations", "ksp_solves")] == \
        [ref["newton_iterations"], ref["ksp_solves"]]


def _descendants(pid):
    """The processes started by ``pid`` (mpiexec's ranks), from /proc."""
    children = {}
    for p in Path("/proc").iterdir():
        if not p.name.isdigit():
            continue
        try:
            ppid = int((p / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        children.setdefault(ppid, []).append(int(p.name))
    found, todo = [], [pid]
    while todo:
        kids = children.get(todo.pop(), [])
        found += kids
        todo += kids
    return found


def test_a_rank_abort_keeps_the_running_records(tmp_path, capsys):
    """An internal error on one rank of several aborts the job after writing summary.json
    with the error: it used to replace the summary kept while the run went (its records)
    by the error alone."""
    from lc_petsc.config import SimConfig
    from lc_petsc.job import Job

    class Aborted(Exception):
        pass

    class TwoRanks:
        size, rank = 2, 1

        def Abort(self, code):
            raise Aborted(code)
    job = Job.__new__(Job)
    job.comm, job.out, job.cfg = TwoRanks(), tmp_path, SimConfig()
    write_summary(tmp_path / "summary.json", _summary(4, status="running"))
    with pytest.raises(Aborted):
        job._uncollective_failure(KeyError("x"))
    s = json.loads((tmp_path / "summary.json").read_text())
    assert (s["status"], s["frames"], s["newton_iterations"]) == ("error", 4, [0, 1, 2, 3])
    assert s["aborted"] and s["error"].startswith("rank 1: KeyError: 'x' (an internal error")


def test_a_run_without_checkpoints_keeps_its_records_at_each_flush(tmp_path, monkeypatch, straight):
    """checkpoint_every = 0: the summary is kept at each flush of frames.h5 (every
    FRAMES_FLUSH_SECONDS; 0 here, so at every frame), each one the records so far."""
    import lc_petsc.job as job
    seen = []
    record = job.Job._record_progress

    def record_and_read(self):
        record(self)
        seen.append(json.loads((self.out / "summary.json").read_text()))
    monkeypatch.setattr(job, "FRAMES_FLUSH_SECONDS", 0.0)
    monkeypatch.setattr(job.Job, "_record_progress", record_and_read)
    out = tmp_path / "out"
    assert main([_config(tmp_path, ce=0), "--out", str(out), "--quiet", "--frames", "4"]) == 0
    assert [(s["status"], s["frames"], s["output"]["frames_written"]) for s in seen] == \
        [("running", k, k + 1) for k in range(1, 5)]
    ref = _records(straight)
    assert _records(seen[2]) == {k: v[:3] for k, v in ref.items()}
    s = json.loads((out / "summary.json").read_text())
    assert (s["status"], s["output"]["progress_summaries"]["written"]) == ("finished", 4)


@pytest.mark.parametrize("when", ["frame 3", "last frame", "crossing check"])
def test_a_signals_checkpoint_has_its_frames_records_on_disk(tmp_path, monkeypatch, when):
    """SIGTERM during frame 3 (the loop's checkpoint of frame 3 before it stops) or while
    frames.h5 is closed after the last frame 5 (the checkpoint of frame 5): when each
    checkpoint is written, summary.json on disk already holds its frames' records, so a
    SIGKILL in the grace period after it (a second Ctrl-C, the batch system's kill) leaves
    no frame without a record.  main wrote these two checkpoints with summary.json at the
    frames of the checkpoint before (2 and 4): a restart from them had frames 3 (5) with
    no record in any summary and join_summaries.py refused the folder.  The same for a
    signal during the end-of-run crossing check (the checkpoint of frame 5 that
    ``_stopped_late`` writes before the final summary: a SIGKILL between the two)."""
    import lc_petsc.job as job
    from lc_petsc.io.frames import FramesWriter
    from lc_petsc.simulator import Simulator
    on_disk = []
    write = job.Checkpointer.write

    def write_and_look(self, integrator):
        s = json.loads((tmp_path / "out" / "summary.json").read_text())
        on_disk.append((integrator.frame, s["status"], s["frames"], len(s["newton_iterations"])))
        return write(self, integrator)
    monkeypatch.setattr(job.Checkpointer, "write", write_and_look)
    if when == "frame 3":
        step = Simulator.step

        def signalled(self):
            if self.integrator.frame == 2:
                os.kill(os.getpid(), signal.SIGTERM)
            return step(self)
        monkeypatch.setattr(Simulator, "step", signalled)
    elif when == "last frame":
        close = FramesWriter.close

        def signalled(self):
            os.kill(os.getpid(), signal.SIGTERM)
            return close(self)
        monkeypatch.setattr(FramesWriter, "close", signalled)
    else:
        import lc_petsc.crossings as crossings
        count = crossings.count_crossings

        def counted(*args, **kwargs):
            os.kill(os.getpid(), signal.SIGTERM)
            return count(*args, **kwargs)
        monkeypatch.setattr(crossings, "count_crossings", counted)
    out = tmp_path / "out"
    assert main([_config(tmp_path, ce=2 if when == "frame 3" else 4), "--out", str(out), "--quiet",
                 "--frames", "5"]) == 75
    last = 3 if when == "frame 3" else 5
    assert on_disk[-1] == (last, "running", last, last)
    assert all(k == frames == n for k, _, frames, n in on_disk)
    s = json.loads((out / "summary.json").read_text())
    assert (s["status"], s["frames"], [c["frame"] for c in s["checkpoints"]][-1]) == ("preempted", last, last)


def test_the_folders_lock_tells_what_a_running_summary_means(tmp_path, monkeypatch, capsys):
    """A summary.json that says running, read by check_outputs.py and join_summaries.py:
    the folder's lock says whether its run is going (a process holds it: here this one),
    was killed (no lock file, or one no process holds), could not write its final
    summary (the lock file left saying so) or ran on another host, which cannot be
    probed from here; a run ending while it is read is read again."""
    import lc_petsc.io.lock as lock
    from lc_petsc.io.history import join_history, running_state
    out = tmp_path / "o"
    out.mkdir()
    write_summary(out / "summary.json", _summary(4, status="running"))
    host = socket.gethostname()
    assert running_state(out, _summary(4)) == \
        ("killed", "killed after frame 4 (no lock file .lc_petsc.lock: no run holds the folder)")
    held = lock.OutputLock(out).acquire()
    assert running_state(out, _summary(4)) == \
        ("running", f"running (pid {os.getpid()} on host {host}, alive: it holds the folder's lock .lc_petsc.lock), "
                    "4 frames recorded so far")
    held.leave("its final summary.json (finished) could not be written: No space left on device")
    record = json.loads((out / lock.LOCK_NAME).read_text())
    assert (record["pid"], record["host"]) == (os.getpid(), host)
    failed = ("failed after frame 4: its final summary.json (finished) could not be written: No space left on device "
              "(its lock file .lc_petsc.lock says so; summary.json is the one kept while it ran)")
    assert running_state(out, _summary(4)) == ("failed", failed)
    capsys.readouterr()
    assert _script("check_outputs").main([str(out)]) == 1
    assert capsys.readouterr().out == \
        f"{out}: not finished: summary.json says running, 4 frames recorded: {failed}; --restart latest continues it\n"
    (out / lock.LOCK_NAME).write_text(json.dumps({"pid": 4242, "host": "node-elsewhere", "started": "x"}))
    assert running_state(out, _summary(4)) == (
        "unknown", f"not known after frame 4: pid 4242 on host node-elsewhere, another host than {host}: no process "
                   "holds its lock .lc_petsc.lock as seen from here, but this filesystem may not share locks between "
                   "hosts; it cannot be probed from here (killed, or still running: look on node-elsewhere)")
    h = join_history(out)
    assert h["running"] and h["running_state"]["state"] == "unknown"
    assert "segment 0: summary.json, unknown (running), 1 rank(s)" in "\n".join(history_table(h))
    # the run writes its final summary while the folder is looked at: read again
    probe = lock.probe

    def then_finished(folder):
        write_summary(out / "summary.json", _summary(5))
        return probe(folder)
    monkeypatch.setattr(lock, "probe", then_finished)
    h = join_history(out)
    assert (h["running"], h["frames"], h["segments"][0]["status"]) == (False, 5, "finished")


def test_a_final_summary_that_cannot_be_written_is_not_taken_for_a_kill(tmp_path, monkeypatch, capsys):
    """The final summary.json fails (ENOSPC) after the frames ran: the job says so on
    stderr and exits 3, and the summary left (the one kept while it ran, which says
    running) is not read as a killed run's: the lock file is left saying why the run
    ended, which check_outputs.py, join_summaries.py and the next run report; --restart
    latest (checkpoint at the last frame) writes the outputs and the summary."""
    import lc_petsc.io.summary as summary_io
    write = summary_io.write_summary

    def full_disk(path, summary):
        if summary.get("status") != "running":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path) + ".tmp")
        write(path, summary)
    monkeypatch.setattr(summary_io, "write_summary", full_disk)
    cfg, out = _config(tmp_path, ce=2), tmp_path / "out"
    assert main([cfg, "--out", str(out), "--quiet", "--frames", "4"]) == 3
    err = capsys.readouterr().err
    assert (f"error: {out / 'summary.json'} could not be written (No space left on device); the summary.json left "
            "is the one kept while the run went (status running, up to frame 4); the run's figures are in the "
            "report below") in err
    assert f"error: output error: {out / 'summary.json'}: No space left on device" in err
    assert (f"{out / '.lc_petsc.lock'} is left in the folder, saying why the run ended, so scripts/check_outputs.py, "
            "scripts/join_summaries.py and the next run do not take it for a killed run") in err
    monkeypatch.undo()
    s = json.loads((out / "summary.json").read_text())
    assert (s["status"], s["frames"], len(s["newton_iterations"])) == ("running", 4, 4)
    ended = "its final summary.json (finished) could not be written: No space left on device"
    assert json.loads((out / ".lc_petsc.lock").read_text())["ended"] == ended
    assert _script("check_outputs").main([str(out)]) == 1
    assert f"4 frames recorded: failed after frame 4: {ended} (its lock file" in capsys.readouterr().out
    assert _script("join_summaries").main([str(out), "--quiet"]) == 0
    assert "segment 0: summary.json, failed (running), 1 rank(s)" in capsys.readouterr().out
    assert main([cfg, "--out", str(out), "--quiet", "--frames", "4"]) == 2
    assert f"holds a run that did not finish (failed after frame 4: {ended} (its lock file says so;" in \
        capsys.readouterr().err
    assert main([cfg, "--out", str(out), "--quiet", "--frames", "4", "--restart", "latest"]) == 0
    assert f"; it ended: {ended}); it failed (its lock file says why): its outputs are" in capsys.readouterr().err
    assert json.loads((out / "summary.json").read_text())["status"] == "finished"
    assert not (out / ".lc_petsc.lock").exists()
    # the summary the restart set aside keeps why its run ended: the joined history says
    # failed, not killed (before, the lock's note was gone with the restart)
    aside = json.loads((out / "summaries" / "summary_frames_000000-000004.json").read_text())
    assert (aside["status"], aside["ended"]) == ("running", f"failed: {ended}")
    assert _script("join_summaries").main([str(out), "--quiet"]) == 0
    assert "segment 0: summaries/summary_frames_000000-000004.json, failed (running), 1 rank(s)" in \
        capsys.readouterr().out


def test_a_stale_lock_file_without_a_record_is_not_called_empty(tmp_path):
    """A killed run's lock file whose text is no record (cut short: '{"pid":') was
    reported as "an empty lock file" by check_outputs.py and join_summaries.py; it says
    the file holds no record, empty or damaged, for either."""
    from lc_petsc.io.history import running_state
    out = tmp_path / "o"
    out.mkdir()
    write_summary(out / "summary.json", _summary(4, status="running"))
    for text in ('{"pid":', ""):
        (out / ".lc_petsc.lock").write_text(text)
        assert running_state(out, _summary(4)) == (
            "killed", "killed after frame 4 (its lock .lc_petsc.lock is stale: a lock file without a run's record "
                      "(empty or damaged); no process holds it)")


#: join_summaries.py's main() with its stdout a pipe whose reader leaves after the table,
#: while the history is written (before the last line); in a process of its own (PETSc, loaded
#: by this module, would take the SIGPIPE)
LEAVES_AFTER_TABLE = """
import importlib.util, os, sys
spec = importlib.util.spec_from_file_location("join", sys.argv[1])
script = importlib.util.module_from_spec(spec)
spec.loader.exec_module(script)
read, write = os.pipe()
sys.stdout = os.fdopen(write, "w")
written = script.write_summary
def reader_leaves(path, history):
    os.close(read)
    written(path, history)
script.write_summary = reader_leaves
sys.exit(script.main(sys.argv[2:]))
"""


def test_join_read_by_a_reader_that_leaves_after_the_table(tmp_path):
    """`join_summaries.py OUT | head -8` where the whole table fits the pipe's buffer: the
    reader leaves after the table, before the last line ("written: ..."), which met the
    closed pipe (a BrokenPipeError traceback, exit 1, in 1 of 3 tries on a loaded machine;
    here made certain by closing the reader while the history is written)."""
    out, entry = _folder(tmp_path)
    write_summary(out / "summary.json", _summary(6, first=2, earlier=[entry]))
    proc = subprocess.run([sys.executable, "-c", LEAVES_AFTER_TABLE, str(ROOT / "scripts" / "join_summaries.py"),
                           str(out)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    assert json.loads((out / "history.json").read_text())["per_frame"]["frame"][-1] == 6


def test_join_names_a_segment_that_ran_no_frame(tmp_path):
    """A restart at the last frame's checkpoint (its run killed while writing the end-of-run
    outputs) runs no frame: its segment is "no frame run (the end-of-run outputs after frame
    6)", where main printed "frames 7-6 kept of 7-6"."""
    out = tmp_path / "o"
    (out / "summaries").mkdir(parents=True)
    write_summary(out / "summaries" / "summary_frames_000000-000006.json", _summary(6, status="running"))
    entry = {"file": "summaries/summary_frames_000000-000006.json", "frames": [0, 6], "frames_kept": [0, 6]}
    write_summary(out / "summary.json", _summary(6, first=6, earlier=[entry]))
    lines = history_table(_script("join_summaries").join_history(out))
    assert lines[1].endswith("killed (running), 1 rank(s), config " + lines[1].split("config ")[1][:12]
                             + ", frames 1-6 kept of 1-6")
    assert lines[2].startswith("  segment 1: summary.json, finished, 1 rank(s)")
    assert lines[2].endswith(", no frame run (the end-of-run outputs after frame 6)")
    assert lines[4].split() == ["1", "0", "1", "0", "0"] and len(lines) == 4 + 6
