"""The main job's set-up (lock, build, validation, before the first frame): a signal
stops it at once with exit 75 and the folder as it was, also under mpiexec when only
one rank gets it while the other waits for it in a collective call; a generated scene
too large for the machine's memory is refused before it is built.

The long set-up of a huge scene is played by a driver whose build computes in Python
for two minutes (the signal lands there), on every rank or on one while the others
wait for it in a barrier."""

import hashlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lc_petsc.batch import EXIT_PREEMPTED, EXIT_USAGE, main
from lc_petsc.errors import ConfigError
from lc_petsc.io.lock import LOCK_NAME
from lc_petsc.scene import sources

from sim_helpers import MPI_ENV  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
DRIVER = str(ROOT / "drivers" / "simulate.py")

SLOW_DRIVER = '''
import os, sys, time
import lc_petsc.simulator as simulator
from lc_petsc.batch import exit_process, main

build = simulator.build_simulator


def slow_build(cfg, comm=None, **kw):
    with open(os.environ["SETUP_MARKER"] + f".{comm.rank}", "w") as f:
        f.write(str(os.getpid()))
    slow = os.environ.get("SLOW_RANK")
    if slow is None or int(slow) == comm.rank:
        t_end = time.monotonic() + 120
        while time.monotonic() < t_end:
            sum(range(1000))
    comm.Barrier()
    return build(cfg, comm, **kw)


simulator.build_simulator = slow_build
exit_process(main())
'''

HAIRBALL = """
[scene]
kind = "hairball"
n_wisps = {n_wisps}
[physics]
terms = ["stretch", "bend", "twist", "gravity"]
[time]
frames = 3
[output]
previews = false
usd = false
"""


def _config(tmp_path, n_wisps=4):
    p = tmp_path / "h.toml"
    p.write_text(HAIRBALL.format(n_wisps=n_wisps))
    return str(p)


def _snapshot(folder):
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(Path(folder).rglob("*")) if p.is_file()}


def _start_slow(tmp_path, out, ranks=None, slow_rank=None):
    """The job with the slow build, serial or under mpiexec; (process, marker prefix)."""
    driver = tmp_path / "slow_setup.py"
    driver.write_text(SLOW_DRIVER)
    marker = str(tmp_path / "building")
    env = dict(MPI_ENV if ranks else os.environ, SETUP_MARKER=marker)
    if slow_rank is not None:
        env["SLOW_RANK"] = str(slow_rank)
    cmd = [sys.executable, str(driver), _config(tmp_path), "--out", str(out), "--quiet"]
    if ranks:
        cmd = ["mpiexec", "--oversubscribe", "-n", str(ranks)] + cmd
    p = subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    return p, marker


def _pids_building(p, marker, ranks=1, timeout=60):
    """The pids of the ranks, once every rank is in the build."""
    t0 = time.time()
    paths = [Path(f"{marker}.{r}") for r in range(ranks)]
    while not all(q.exists() and q.stat().st_size for q in paths):
        assert p.poll() is None, f"the run ended early: {p.communicate()[1][-2000:]}"
        assert time.time() - t0 < timeout, "the build never started"
        time.sleep(0.02)
    time.sleep(0.3)
    return [int(q.read_text()) for q in paths]


def _stop(p, sig, pids, target=None, timeout=30):
    """Send ``sig`` to ``target`` (default the process ``p``), then (stdout, stderr,
    seconds to exit); kills ``p`` and the ranks ``pids`` if it does not end."""
    t0 = time.monotonic()
    os.kill(target or p.pid, sig)
    try:
        so, se = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        for pid in [p.pid] + pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        so, se = p.communicate()
        pytest.fail(f"still running {timeout} s after {sig.name}: {se[-2000:]}")
    return so, se, time.monotonic() - t0


# ------------------------------------------------------------------- one process
def test_sigterm_during_setup_stops_at_once(tmp_path):
    """SIGTERM used to be ignored until the build ended (minutes for a huge scene):
    it stops the set-up at once, exit 75, and the folder this run created is gone."""
    out = tmp_path / "out"
    p, marker = _start_slow(tmp_path, out)
    pids = _pids_building(p, marker)
    assert (out / LOCK_NAME).exists()
    so, se, seconds = _stop(p, signal.SIGTERM, pids)
    assert p.returncode == EXIT_PREEMPTED, se[-2000:]
    assert seconds < 5, seconds
    assert ("SIGTERM received during the set-up, before the first frame: stopped, nothing was "
            "written (the output folder is as it was); run the same command again") in se, se
    assert "Traceback" not in se and "finishing this frame" not in se
    assert not out.exists()


def test_ctrl_c_during_setup_leaves_the_previous_run(tmp_path, capsys):
    """The first Ctrl-C used to promise 'finishing this frame' with no frame running:
    it stops the set-up, and the previous run's outputs are untouched."""
    out = tmp_path / "out"
    assert main([_config(tmp_path), "--out", str(out), "--quiet"]) == 0
    before = _snapshot(out)
    p, marker = _start_slow(tmp_path, out)
    pids = _pids_building(p, marker)
    so, se, seconds = _stop(p, signal.SIGINT, pids)
    assert p.returncode == EXIT_PREEMPTED, se[-2000:]
    assert seconds < 5 and "SIGINT received during the set-up" in se, (seconds, se)
    assert "finishing this frame" not in se and "Traceback" not in se
    assert _snapshot(out) == before and not (out / LOCK_NAME).exists()


# ------------------------------------------------------------------- under mpiexec
def test_sigusr1_to_mpiexec_during_setup_stops_every_rank(tmp_path):
    """mpiexec forwards SIGUSR1 to every rank: they agree and exit 75, reported once."""
    out = tmp_path / "out"
    p, marker = _start_slow(tmp_path, out, ranks=2)
    pids = _pids_building(p, marker, ranks=2)
    so, se, seconds = _stop(p, signal.SIGUSR1, pids)
    assert p.returncode == EXIT_PREEMPTED, se[-2000:]
    assert seconds < 10, seconds
    assert se.count("SIGUSR1 received during the set-up, before the first frame") == 1, se
    assert "Traceback" not in se and "MPI_ABORT" not in se
    assert not out.exists()


def test_signal_to_one_rank_while_the_other_waits_for_it(tmp_path):
    """``kill`` of rank 1 alone, while rank 0 waits for it in a collective call: rank 1
    removes rank 0's lock and aborts the job after Preemption.SETUP_WAIT s, exit 75,
    no rank left waiting; the folder as it was."""
    out = tmp_path / "out"
    p, marker = _start_slow(tmp_path, out, ranks=2, slow_rank=1)
    pids = _pids_building(p, marker, ranks=2)
    so, se, seconds = _stop(p, signal.SIGTERM, pids, target=pids[1])
    assert p.returncode == EXIT_PREEMPTED, se[-2000:]
    assert seconds < 15, seconds
    assert "rank 1: SIGTERM received during the set-up; the other ranks did not stop within 5 s" in se, se
    assert "Traceback" not in se
    assert not out.exists()


# ------------------------------------------------------------------- size check
def test_absurd_n_wisps_is_refused_before_building(tmp_path):
    """n_wisps = 1e8 used to build for many minutes (1.8 GB and growing, no message):
    the memory estimate of strands files refuses it at once, naming the key."""
    out = tmp_path / "out"
    cmd = [sys.executable, DRIVER, _config(tmp_path, n_wisps=100_000_000), "--out", str(out), "--quiet"]
    t0 = time.monotonic()
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=30, stdin=subprocess.DEVNULL)
    assert r.returncode == EXIT_USAGE, r.stderr[-2000:]
    assert time.monotonic() - t0 < 15
    assert ("scene.n_wisps = 100000000: 100,000,000 wisps of 101 vertices (10,100,000,000 "
            "vertices); a run needs at least 4096 bytes per vertex, 4.14e+04 GB, and this machine "
            "has ") in r.stderr, r.stderr
    assert "GB of memory; use fewer wisps or run on more nodes" in r.stderr
    assert r.stderr.count("error:") == 1 and "Traceback" not in r.stderr
    assert not out.exists()


def test_an_unknown_solver_type_is_one_line_naming_it(tmp_path, capsys):
    """-ksp_type gmress: the refusal wrapped PETSc's whole traceback ("[0] KSPSetType()
    at ./src/...") in parentheses and said "see PETSc's message above", where there was
    none; now PETSc's messages, the code and the function, on one line."""
    out = tmp_path / "out"
    assert main([_config(tmp_path, n_wisps=2), "--out", str(out), "--quiet", "-ksp_type", "gmress"]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert err.startswith("simulate.py: error: PETSc rejected the solver set-up: Unable to find requested KSP "
                          "type gmress; Unknown type. Check for miss-spelling or missing package: "), err
    assert err.endswith(" (PETSc error code 86, in KSPSetType())\n") and err.count("\n") == 1, err
    assert not out.exists()


def test_generated_scene_memory_estimate(monkeypatch):
    """The strands files' estimate (4 kB per vertex against the memory of the job's
    nodes) on a machine of 1 GiB: 2,000 hairball wisps fit, 3,000 do not on one node but
    do on two; a straight strand names scene.n_vertices."""
    monkeypatch.setattr(sources, "machine_memory", lambda: 1 << 30)
    monkeypatch.setattr(sources, "job_nodes", lambda: 1)
    assert sources.GeneratedSource("hairball", n_wisps=2000).n_wisps == 2000
    with pytest.raises(ConfigError) as e:
        sources.GeneratedSource("hairball", n_wisps=3000)
    assert str(e.value) == ("scene.n_wisps = 3000: 3,000 wisps of 101 vertices (303,000 vertices); "
                            "a run needs at least 4096 bytes per vertex, 1.24 GB, and this machine has "
                            "1.07 GB of memory; use fewer wisps or run on more nodes")
    with pytest.raises(ConfigError, match=r"^scene.n_vertices = 300000: .* 1.07 GB of memory; use fewer"):
        sources.GeneratedSource("straight", n_vertices=300_000)
    monkeypatch.setattr(sources, "job_nodes", lambda: 2)
    assert sources.GeneratedSource("hairball", n_wisps=3000).n_wisps == 3000


# a ValueError on rank 1 alone before the set-up's first matrix (rank 0 waits for it in
# the collective creation): the model of any rank-local refusal inside a collective section
ONE_RANK_DRIVER = '''
import sys
from mpi4py import MPI
import lc_petsc.assembly as assembly
import lc_petsc.job as job
from lc_petsc.batch import exit_process, main

job.Preemption.REFUSED_WAIT = 3.0
init = assembly.Assembler.__init__


def refused_on_rank_1(self, *args, **kw):
    if MPI.COMM_WORLD.rank == 1:
        raise ValueError("rank 1's element check failed")
    init(self, *args, **kw)


assembly.Assembler.__init__ = refused_on_rank_1
exit_process(main())
'''


def test_a_refusal_on_one_rank_inside_a_collective_call_aborts_with_exit_2(tmp_path):
    """mpiexec hung for ever: rank 1 refused the run and waited at the set-up's end while
    rank 0 waited for rank 1 in the matrix creation.  Now rank 1 prints its refusal,
    drops the lock and aborts the job after Preemption.REFUSED_WAIT s: exit 2, the
    folder as it was."""
    driver = tmp_path / "one_rank.py"
    driver.write_text(ONE_RANK_DRIVER)
    out = tmp_path / "out"
    cmd = ["mpiexec", "--oversubscribe", "-n", "2", sys.executable, str(driver), _config(tmp_path),
           "--out", str(out), "--quiet"]
    try:
        p = subprocess.run(cmd, env=MPI_ENV, stdin=subprocess.DEVNULL, capture_output=True, text=True,
                           timeout=90)
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"mpiexec hung: {e.stderr[-2000:] if e.stderr else ''}")
    assert p.returncode == EXIT_USAGE, p.stderr[-2000:]
    assert p.stderr.count("simulate.py: error: rank 1's element check failed") == 1, p.stderr
    assert "rank 1 refused the run during the set-up (above) and the other ranks did not stop within 3 s" \
        in p.stderr, p.stderr
    assert "Traceback" not in p.stderr
    assert not out.exists()
