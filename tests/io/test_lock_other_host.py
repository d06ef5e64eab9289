"""A run into a folder whose lock a real run wrote on another host (the driver run in a
subprocess whose ``socket.gethostname`` says ``node-elsewhere``): while that run holds
the lock the folder is busy (this machine sees its flock); once the lock is free as seen
from here, its holder cannot be probed (a filesystem that does not pass flocks between
hosts shows a live foreign run's lock free too): a run here is refused, the folder left
as it was, until the lock file is removed by the user (lc_petsc/io/lock.py;
docs/design_notes.md, "A lock recorded on another host, met by a real run")."""

import json
import signal
import socket
import subprocess
import sys
import time

from lc_petsc.batch import main
from lc_petsc.io.lock import LOCK_NAME

from sim_helpers import MPI_ENV, hairball_toml  # noqa: E402
from test_progress_summary import DRIVER, _script

ELSEWHERE = "node-elsewhere"
#: the driver with the host name of another node
FOREIGN = (f"import runpy, socket, sys; socket.gethostname = lambda: {ELSEWHERE!r}; "
           f"sys.argv = [{DRIVER!r}] + sys.argv[1:]; runpy.run_path({DRIVER!r}, run_name='__main__')")


def _snapshot(out, writing=False):
    """Every file of the folder: name -> bytes (``writing``: but the checkpoint the live run
    is writing, which it may still be filling)."""
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file() and not (writing and p.name.endswith(".h5.tmp"))}


def test_a_lock_written_on_another_host(tmp_path, capsys):
    cfg = tmp_path / "s.toml"
    cfg.write_text(hairball_toml(n_wisps=2, frames=6, output="previews = false\nxdmf = false\nusd = false\n"
                                                             "checkpoint_every = 2"))
    out = tmp_path / "out"
    env = dict(MPI_ENV, LC_PETSC_TEST_CHECKPOINT_PAUSE="4:120")
    proc = subprocess.Popen([sys.executable, "-c", FOREIGN, str(cfg), "--out", str(out), "--quiet"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.time()
        while not (out / "checkpoints" / ".checkpoint_000004.h5.tmp").exists():
            assert proc.poll() is None, proc.communicate()[1][-3000:]
            assert time.time() - t0 < 120, "timed out"
            time.sleep(0.02)
        record = json.loads((out / LOCK_NAME).read_text())
        assert (record["pid"], record["host"]) == (proc.pid, ELSEWHERE)
        # alive, its flock seen from here: busy, named, the folder untouched
        before = _snapshot(out, writing=True)
        capsys.readouterr()
        assert main([str(cfg), "--out", str(out), "--quiet", "--restart", "latest"]) == 2
        err = capsys.readouterr().err
        assert f"is in use by another run: pid {proc.pid} on host {ELSEWHERE}" in err, err
        assert _snapshot(out, writing=True) == before
        assert _script("check_outputs").main([str(out)]) == 1
        assert f"running (pid {proc.pid} on host {ELSEWHERE}, alive: it holds the folder's lock" in \
            capsys.readouterr().out
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.communicate()
    # its lock free as seen from here: killed, or alive on a filesystem that does not pass
    # flocks between hosts; neither a restart nor a new run takes the folder
    left = _snapshot(out)
    assert left[LOCK_NAME] == (json.dumps(record) + "\n").encode()
    for extra in (["--restart", "latest"], [], ["--force"]):
        capsys.readouterr()
        assert main([str(cfg), "--out", str(out), "--quiet", *extra]) == 2, extra
        err = capsys.readouterr().err
        assert (f"the lock of a run on another host, pid {proc.pid} on host {ELSEWHERE}" in err
                and f"if it is not running there, remove {out / LOCK_NAME} and run again" in err), err
        assert _snapshot(out) == left, extra
    assert _script("check_outputs").main([str(out)]) == 1
    assert f"another host than {socket.gethostname()}" in capsys.readouterr().out
    # the user removes the lock file: the restart continues the run from checkpoint 2
    (out / LOCK_NAME).unlink()
    assert main([str(cfg), "--out", str(out), "--quiet", "--restart", "latest"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert (s["status"], s["frames"], s["restart"]["frame"]) == ("finished", 6, 2)
    assert not (out / LOCK_NAME).exists()
