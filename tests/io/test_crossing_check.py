"""The main job's end-of-run crossing check (``output.check_crossings``): the crossings
along the straight paths between the frames written, counted between wisps and within
each wisp into summary.json,
with a warning naming the key that prevents them.  ``check_run`` splits the steps over
the ranks and gives every rank the same answer (mpi marker: tests/test_mpi_launch.py)."""

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.batch import main
from lc_petsc.crossings import check_run, edge_strain

comm = MPI.COMM_WORLD
N = 10                  # vertices per wisp (even: crossings fall inside segments)


def write_frames(path, frames, offsets):
    """A minimal frames.h5 (the datasets the check reads, the first frame as the rest
    positions) on rank 0."""
    if comm.rank == 0:
        with h5py.File(path, "w") as f:
            f["positions"] = np.asarray(frames, float)
            f["wisp_offsets"] = np.asarray(offsets, np.int64)
            f["rest_positions"] = np.asarray(frames[0], float)
    comm.Barrier()


def bar(y, along, n=N, z=0.0):
    """A straight wisp of n vertices from -1 to 1 cm along axis ``along`` at height y."""
    x = np.zeros((n, 3))
    x[:, along] = np.linspace(-1.0, 1.0, n)
    x[:, 1] += y
    x[:, 2] += z if along != 2 else 0.0
    return x


@pytest.mark.mpi
def test_check_counts_each_step_once_on_any_rank_count(tmp_path):
    """Wisp B (along z) falls through wisp A (along x) in step 2 only, and back up in
    step 4; a folded wisp C crosses itself in step 1.  The same figures on 1-3 ranks."""
    path = Path(comm.bcast(str(tmp_path) if comm.rank == 0 else None)) / "f.h5"
    ys = [1.0, 0.9, -0.5, -0.6, 0.5, 0.4]                   # B's height per frame
    c_open = np.column_stack([np.linspace(0, 1, 6), 5.0 + np.zeros(6), np.zeros(6)])
    c_open[3:, 0] = c_open[2::-1, 0]
    c_open[3:, 2] = 0.3                                       # folded back 0.3 cm apart in z
    c_through = c_open.copy()
    c_through[3:, 2] = -0.3                                   # the fold passed through itself
    frames = []
    for k, y in enumerate(ys):
        c = c_through if k >= 2 else c_open
        a = bar(0.0, 0)
        if k == 4:
            a[0, 0] -= 0.25 * (a[1, 0] - a[0, 0])        # its first edge 25% longer
        frames.append(np.concatenate([a, bar(y, 2), c]))
    offsets = [0, N, 2 * N, 2 * N + 6]
    write_frames(path, frames, offsets)
    r = check_run(path, comm, self_contact=False)
    strain = {k: r.pop(k) for k in ("largest_strain", "largest_strain_row", "rows_over_strain", "initial_strain")}
    assert r.pop("head") is None            # no config: no head sphere (tests/io/test_head_check.py)
    assert r == {"steps": 5, "between_wisps": 2, "steps_between": 2, "first_between": 1,
                 "within_wisps": None, "steps_within": None, "first_within": None,
                 "between_exempt": None, "within_exempt": None}
    # C's fold edge (vertices 2-3) has rest length 0.3; through the fold it is 0.3 as well,
    # but row 4 stretches A's first edge by 25%
    assert strain == {"largest_strain": pytest.approx(0.25), "largest_strain_row": 4,
                      "rows_over_strain": 1, "initial_strain": 0.0}, strain
    r = check_run(path, comm, self_contact=True)
    assert (r["between_wisps"], r["first_between"]) == (2, 1)
    assert r["within_wisps"] >= 1 and r["steps_within"] == 1 and r["first_within"] == 1, r
    # an unreadable file is an answer on every rank, not an exception on some
    missing = check_run(path.with_name("none.h5"), comm)
    assert set(missing) == {"error"} and "none.h5" in missing["error"], missing


def folded_wisp(through):
    """Wisp C: 6 vertices along x, folded back 0.3 cm apart in z (``through``: the fold
    passed through itself, -0.3 cm)."""
    c = np.column_stack([np.linspace(0, 1, 6), 5.0 + np.zeros(6), np.zeros(6)])
    c[3:, 0] = c[2::-1, 0]
    c[3:, 2] = -0.3 if through else 0.3
    return c


@pytest.mark.mpi
def test_crossings_of_rest_exempt_pairs_are_counted_apart(tmp_path):
    """With ``rest_exempt`` (the contact thickness d0) the crossings of pairs closer than
    d0 at rest, which the contact exempts and lets pass through each other, are counted
    apart: B falls through A (1 cm apart at rest), C's fold (0.3 cm apart at rest)
    passes through itself.  The same figures on 1-3 ranks."""
    path = Path(comm.bcast(str(tmp_path) if comm.rank == 0 else None)) / "f.h5"
    frames = [np.concatenate([bar(0.0, 0), bar(y, 2), folded_wisp(k > 0)])
              for k, y in enumerate((1.0, -0.5, -0.6))]
    write_frames(path, frames, [0, N, 2 * N, 2 * N + 6])
    plain = check_run(path, comm, self_contact=True)
    assert plain["between_wisps"] == 1 and plain["within_wisps"] >= 1, plain
    assert (plain["between_exempt"], plain["within_exempt"]) == (None, None)
    r = check_run(path, comm, self_contact=True, rest_exempt=0.5)       # C's fold only
    assert r == dict(plain, between_exempt=0, within_exempt=plain["within_wisps"]), r
    r = check_run(path, comm, self_contact=True, rest_exempt=1.5)       # and A-B
    assert (r["between_exempt"], r["within_exempt"]) == (1, plain["within_wisps"]), r
    r = check_run(path, comm, self_contact=False, rest_exempt=1.5)
    assert (r["between_exempt"], r["within_exempt"]) == (1, None), r
    r = check_run(path, comm, self_contact=True, rest_exempt=0.1)
    assert (r["between_exempt"], r["within_exempt"]) == (0, 0), r
    assert comm.allgather(r) == [r] * comm.size


GROOM_TOML = """
[scene]
kind = "file"
path = "{groom}"
[material]
youngs_modulus = 1.0e9
[physics]
terms = {terms}
{contact}
[time]
dt = 0.03333333333333333
frames = 8
initial_guess = "{guess}"
[output]
previews = false
usd = false
xdmf = false
"""


def write_groom(path, height=0.5):
    """Wisp A along x at y = 0, every vertex pinned; wisp B along z ``height`` cm above
    it, free: it falls onto (or through) A under gravity."""
    with h5py.File(path, "w") as f:
        f["positions"] = np.concatenate([bar(0.0, 0), bar(height, 2)])
        f["wisp_offsets"] = np.array([0, N, 2 * N], np.int64)
        f["pinned"] = np.concatenate([np.ones(N, bool), np.zeros(N, bool)])
        f["radius"] = np.full(2 * N, 0.02)


def run(tmp_path, name, contact, height=0.5, exempt=False):
    groom = tmp_path / "groom.h5"
    write_groom(groom, height)
    terms = ["stretch", "bend", "gravity"] + (["strand_collision"] if contact else [])
    cfg = tmp_path / f"{name}.toml"
    cfg.write_text(GROOM_TOML.format(
        groom=groom, terms=json.dumps(terms),
        contact='strand_contact_mode = "ccd"\nstrand_thickness = 0.04' + (
            '\nstrand_rest_overlap = "exempt"' if exempt else "") if contact else "",
        guess="follow_the_leader" if contact else "inertial"))
    out = tmp_path / name
    assert main([str(cfg), "--out", str(out), "--quiet"]) == 0
    return json.loads((out / "summary.json").read_text()), out / "frames.h5"


def test_run_without_contact_reports_and_warns(tmp_path):
    """The wisp falls through the other: the summary counts it, the warning names the
    key; with ccd contact it lands on it: 0 and no warning."""
    s, frames = run(tmp_path, "free", contact=False)
    c = s["crossings"]
    with h5py.File(frames) as f:
        y_mid = f["positions"][:, N + N // 2, 1]
    passed = int(np.argmax(y_mid < 0.0)) - 1                 # the step in which B passed y = 0
    assert passed >= 0 and c["between_wisps"] >= 1 and c["first_between"] == passed, (c, y_mid)
    assert c["steps"] == 8 and c["within_wisps"] == 0 and c["seconds"] > 0
    w = [m for m in s["warnings"] if "crossing(s) between wisps" in m]
    assert len(w) == 1 and 'add "strand_collision" to physics.terms' in w[0], s["warnings"]
    assert f"frame {passed} -> {passed + 1}" in w[0]
    s, frames = run(tmp_path, "ccd", contact=True)
    with h5py.File(frames) as f:
        assert f["positions"][-1, N + N // 2, 1] > 0.0       # it rests on A
    assert s["crossings"]["between_wisps"] == 0 and s["crossings"]["steps"] == 8
    assert not [m for m in s["warnings"] if "crossing" in m], s["warnings"]


def test_rest_exempt_crossings_are_not_blamed_on_the_limiter(tmp_path):
    """B hangs 0.03 cm above A, inside the 0.04 cm thickness: with
    ``strand_rest_overlap = "exempt"`` their middle segments are exempt and B falls
    through A.  The summary counts that crossing as the exemption's, and the warning
    names the exemption, not a ccd limiter failure to report (it did: a dense groom run
    with the exemption, 63 crossings in 60 frames, all of exempt pairs, each reported
    as "the ccd limiter should have prevented them ... please report it")."""
    s, frames = run(tmp_path, "exempt", contact=True, height=0.03, exempt=True)
    with h5py.File(frames) as f:
        assert f["positions"][-1, N + N // 2, 1] < 0.0          # it fell through A
    w = [m for m in s["warnings"] if "crossing(s) between wisps" in m]
    assert len(w) == 1 and "report" not in w[0] and "should have" not in w[0], w
    assert "all by pairs of segments closer than the contact thickness" in w[0] and "strand_rest_overlap" in w[0]
    c = s["crossings"]
    # (no self-contact: a wisp's crossings of itself, if any, would be no exemption's)
    assert c["between_wisps"] == 1 and c["between_exempt"] == 1 and c["within_exempt"] is None, c


#: one smashed 4C curl, 2 frames (``terms``: the physics.terms list's items; ``contact``:
#: more [physics] lines)
SMASHED_CURL = """
[scene]
kind = "wisp4c"
n_vertices = 101
perturbation = "smash"
[material]
youngs_modulus = 3.9e9
[physics]
terms = [{terms}]
{contact}
[time]
frames = 2
[output]
previews = false
usd = false
"""


def test_single_wisp_checked_within_and_switch_off(tmp_path):
    """A smashed curl (one wisp, no contact) crosses itself when it springs back: counted
    within the wisp, with self-contact as the fix; ``check_crossings = false`` skips it."""
    toml = SMASHED_CURL.format(terms='"stretch", "bend", "twist"', contact="")
    p = tmp_path / "s.toml"
    p.write_text(toml)
    assert main([str(p), "--out", str(tmp_path / "a"), "--quiet"]) == 0
    s = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert s["crossings"]["between_wisps"] == 0 and s["crossings"]["within_wisps"] > 0
    assert s["crossings"]["first_within"] == 0
    assert any("within a wisp" in w and "strand_self_contact = true" in w for w in s["warnings"])
    p.write_text(toml + "check_crossings = false\n")
    assert main([str(p), "--out", str(tmp_path / "b"), "--quiet"]) == 0
    s = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert s["crossings"] is None and not [w for w in s["warnings"] if "crossing" in w]


def test_warning_names_the_cause_for_the_run_setup():
    """The key that prevents crossings, per contact set-up; in ccd mode with output.every
    > 1 the cause is the interpolation across the simulated steps, not the limiter."""
    from lc_petsc.config import load_config
    from lc_petsc.job import crossing_warnings
    root = Path(__file__).resolve().parents[2]
    check = {"steps": 15, "between_wisps": 7, "steps_between": 2, "first_between": 6,
             "within_wisps": 3, "steps_within": 1, "first_within": 2}
    cfg = load_config(root / "configs" / "hairball_2k.toml")          # ccd + self-contact, every 3
    between, within = crossing_warnings(check, cfg)
    assert between.startswith("7 crossing(s) between wisps in 2 of the 15 steps") and "frame 18 -> 21" in between
    assert "this check cannot see those steps" in between and "report" not in between
    assert "this check cannot see those steps" in within and "frame 6 -> 9" in within
    cfg.physics.strand_self_contact = False
    within = crossing_warnings(check, cfg)[1]
    assert "strand_self_contact = true" in within and "frame 6 -> 9" in within
    cfg.output.every = 1
    between = crossing_warnings(check, cfg)[0]
    assert "should have prevented them" in between and "frame 6 -> 7" in between
    cfg.physics.strand_contact_mode = "penalty"
    assert 'strand_contact_mode = "ccd" prevents them' in crossing_warnings(check, cfg)[0]
    cfg.physics.terms = tuple(t for t in cfg.physics.terms if t != "strand_collision")
    assert 'add "strand_collision" to physics.terms' in crossing_warnings(check, cfg)[0]
    assert crossing_warnings(dict(check, between_wisps=0, within_wisps=None), cfg) == []
    # crossings of rest-exempt pairs are the exemption's, the others the limiter's
    cfg = load_config(root / "configs" / "hairball_demo.toml")         # ccd, every 1
    cfg.physics.strand_self_contact = True      # (without it check_run counts no exemption within)
    between, within = crossing_warnings(dict(check, between_exempt=7, within_exempt=1), cfg)
    assert "all by pairs of segments closer than the contact thickness in the rest pose" in between
    assert "should have prevented" not in between and "report" not in between
    assert "1 of them by pairs of segments closer" in within and "the other 2: the ccd limiter should" in within


def test_a_fold_without_self_contact_is_not_called_exempt(tmp_path):
    """A smashed curl springing back through itself, in ccd mode without self-contact and
    a contact thickness (2 cm) its neighbouring turns are closer than at rest: its
    crossings of itself were reported as "of pairs exempt at rest" and the warning put them
    down to strand_rest_overlap = "exempt", advising to untangle the groom or lower
    strand_thickness, neither of which changes anything: the contact does not act within
    a wisp at all.  Now they are counted as within-wisp crossings only, and the warning
    names self-contact."""
    p = tmp_path / "s.toml"
    p.write_text(SMASHED_CURL.format(terms='"stretch", "bend", "twist", "strand_collision"',
                                     contact='strand_contact_mode = "ccd"\nstrand_thickness = 2.0'))
    assert main([str(p), "--out", str(tmp_path / "a"), "--quiet"]) == 0
    s = json.loads((tmp_path / "a" / "summary.json").read_text())
    c = s["crossings"]
    assert c["within_wisps"] > 0 and c["between_wisps"] == 0 and c["within_exempt"] is None, c
    (w,) = [m for m in s["warnings"] if "within a wisp" in m]
    assert "strand_self_contact = true" in w and "exempt" not in w, w
    # (its crossing pairs are closer than the thickness at rest: what was called exempt)
    assert check_run(tmp_path / "a" / "frames.h5", MPI.COMM_SELF, self_contact=True,
                     rest_exempt=2.0)["within_exempt"] == c["within_wisps"]


def test_strained_edges_are_reported(tmp_path):
    """The jitter scene's scramble leaves edges 19% off their rest length after its first
    frame: the summary gives the largest strain and its frame, a warning names
    time.length_projection; the demo-like runs above stay under 10% (no warning)."""
    p = tmp_path / "j.toml"
    p.write_text(open(Path(__file__).resolve().parents[2] / "configs" / "jitter.toml").read()
                 .replace("frames = 200", "frames = 2").replace("[output]", "[output]\nusd = false"))
    assert main([str(p), "--out", str(tmp_path / "j"), "--quiet"]) == 0
    s = json.loads((tmp_path / "j" / "summary.json").read_text())
    c = s["crossings"]
    assert c["largest_strain"] > 0.15 and c["largest_strain_row"] == 1 and c["rows_over_strain"] >= 1, c
    w = [m for m in s["warnings"] if m.startswith("edges stretch or compress by up to")]
    assert len(w) == 1 and "(frame 1;" in w[0] and "time.length_projection = true" in w[0], s["warnings"]
    # the scramble is the initial state's: measured apart, and the warning says so (it
    # blamed Newton and dt alone, start57)
    with h5py.File(tmp_path / "j" / "frames.h5", "r") as f:
        x0, rest, off = f["positions"][0], f["rest_positions"][...], f["wisp_offsets"][...]
    start = float(np.abs(edge_strain(x0, rest, off)).max())
    assert c["initial_strain"] == pytest.approx(start, rel=1e-12) and start > c["largest_strain"] > 0.1
    assert f"the initial state (frame 0, scene.perturbation = \"jitter\") already has edges {100 * start:.1f}%" \
        in w[0]


def _two_bar_file(tmp_path, name="g.h5"):
    """Wisp B (along z) falls through wisp A (along x) in step 1 of 3."""
    path = Path(comm.bcast(str(tmp_path) if comm.rank == 0 else None)) / name
    write_frames(path, [np.concatenate([bar(0.0, 0), bar(y, 2)]) for y in (1.0, 0.5, -0.5, -0.6)],
                 [0, N, 2 * N])
    return path


@pytest.mark.mpi
def test_a_failure_on_one_rank_is_every_ranks_answer(tmp_path, monkeypatch):
    """Any exception of the last rank's share (not only a file error) is the check's
    error on every rank: raised there, the other ranks would wait in its allgather."""
    from lc_petsc import crossings
    path = _two_bar_file(tmp_path)
    if comm.rank == comm.size - 1:
        def fails(*a, **k):
            raise RuntimeError("numba kernel failed")
        monkeypatch.setattr(crossings, "count_crossings", fails)
    r = check_run(path, comm)
    assert set(r) == {"error"} and "RuntimeError: numba kernel failed" in r["error"], r
    assert comm.allgather(r) == [r] * comm.size


def _job_stub(path, unclosable_rank=None):
    """What Job._check_crossings reads of a job whose frames.h5 is ``path``."""
    from types import SimpleNamespace
    from lc_petsc.config import SimConfig
    cfg = SimConfig()
    return SimpleNamespace(
        cfg=cfg, comm=comm, out=path.parent, sim=SimpleNamespace(n_wisps=2, strand=None),
        writer=SimpleNamespace(broken=comm.rank == unclosable_rank), stop=None)


@pytest.mark.mpi
def test_whether_to_check_is_one_verdict_for_all_ranks(tmp_path):
    """libhdf5 failed on frames.h5 on the last rank only (``writer.broken``): no rank
    checks (a rank that skipped the collective check left the others waiting in it);
    a preempted run is not checked (its restart checks the whole file)."""
    from lc_petsc.job import Job
    path = _two_bar_file(tmp_path, name="frames.h5")
    r = Job._check_crossings(_job_stub(path, unclosable_rank=comm.size - 1))
    assert comm.allgather(r) == [None] * comm.size
    assert Job._check_crossings(_job_stub(path), preempted="SIGTERM") is None
    r = Job._check_crossings(_job_stub(path))
    assert (r["steps"], r["between_wisps"], r["first_between"]) == (3, 1, 1), r


def test_count_frames_names_the_simulation_frames(tmp_path):
    """scripts/count_crossings.py's steps carry the simulation frames of their rows
    (output.every = 3: step 1 is frames 3 -> 6), as the job's warning names them."""
    from lc_petsc.crossings import count_frames
    path = tmp_path / "f.h5"
    frames = [np.concatenate([bar(0.0, 0), bar(y, 2)]) for y in (1.0, 0.5, -0.5)]
    with h5py.File(path, "w") as f:
        f["positions"] = np.asarray(frames)
        f["wisp_offsets"] = np.array([0, N, 2 * N], np.int64)
        f.attrs["every"] = 3
    steps, _ = count_frames(path)
    assert [(s["step"], s["frames"], s["crossings"]) for s in steps] == [(0, (0, 3), 0), (1, (3, 6), 1)]


def test_check_is_not_counted_in_the_frame_loops_wall_time(tmp_path, monkeypatch):
    """summary.json's wall_time_s (and time_per_frame_s) is the frame loop's; the check
    reports its own seconds (it was counted in the loop's time: 1.3 s of the demo's)."""
    import time
    from lc_petsc import crossings
    check = crossings.check_run

    def slow_check(*a, **k):
        time.sleep(3.0)
        return check(*a, **k)
    monkeypatch.setattr(crossings, "check_run", slow_check)
    s, _ = run(tmp_path, "free", contact=False)
    assert s["crossings"]["seconds"] >= 3.0
    assert s["wall_time_s"] < 3.0, (s["wall_time_s"], s["crossings"]["seconds"])


def test_count_crossings_screens_in_chunks_and_stops_between_them(monkeypatch):
    """The screen of the candidate pairs (43 s for the 68M of a scrambled 200-wisp step)
    was one compiled call a signal could not stop: it now goes SCREEN_CHUNK pairs at a
    time, looking at ``stop`` before each (and the Tight-Inclusion pairs CROSSING_CHUNK at
    a time); the counts are the same in any chunking."""
    import lc_petsc.crossings as crossings
    rng = np.random.default_rng(3)
    X0 = np.concatenate([bar(0.1 * k, k % 3) for k in range(8)]) + 0.05 * rng.standard_normal((8 * N, 3))
    X1 = X0 + 0.3 * rng.standard_normal(X0.shape)
    off = np.arange(9) * N
    whole = crossings.count_crossings(X0, X1, off, self_contact=True)
    n_pairs = len(crossings.candidate_pairs(X0, X1, off, True))
    assert whole["crossings"] > 0 and n_pairs > 40
    monkeypatch.setattr(crossings, "SCREEN_CHUNK", 7)
    looks = []
    crossings.candidate_pairs(X0, X1, off, True, stop=lambda: looks.append(1) and False)
    broad = len(looks)                  # the broad phase's parts (box_pairs)
    looks.clear()
    chunked = crossings.count_crossings(X0, X1, off, self_contact=True, stop=lambda: looks.append(1) and False)
    # and every CROSSING_CHUNK of the pairs the screen leaves to Tight-Inclusion
    n_near = int(crossings.screen_paths(X0, X1, crossings.candidate_pairs(X0, X1, off, True))[0].sum())
    assert n_near > 0
    assert len(looks) == broad + -(-n_pairs // 7) + -(-n_near // crossings.CROSSING_CHUNK)
    assert chunked["crossings"] == whole["crossings"] and np.array_equal(chunked["pairs"], whole["pairs"])
    looks.clear()
    stop_at = broad + 2
    assert crossings.count_crossings(X0, X1, off, True, stop=lambda: len(looks) >= stop_at or looks.append(1)) \
        is None
    assert len(looks) == stop_at


def test_count_crossings_stops_inside_the_broad_phase(monkeypatch):
    """A shuffled 200-wisp file's worst step spent 83 s in the broad phase, one compiled
    call: a signal now stops it between two parts of BOX_TESTS box tests, before any
    pair is screened."""
    import lc_petsc.crossings as crossings
    from lc_petsc.elements import compiled_ccd
    rng = np.random.default_rng(4)
    X0 = np.concatenate([bar(0.1 * k, k % 3) for k in range(8)]) + 0.05 * rng.standard_normal((8 * N, 3))
    X1 = X0[rng.permutation(len(X0))]   # a wild step: every vertex jumps
    off = np.arange(9) * N
    screened = []
    screen = crossings.screen_paths
    monkeypatch.setattr(crossings, "screen_paths", lambda *a: screened.append(1) or screen(*a))
    whole = crossings.count_crossings(X0, X1, off, self_contact=True)
    assert whole["crossings"] > 100 and screened
    monkeypatch.setattr(compiled_ccd, "BOX_TESTS", 50)
    looks, screened[:] = [], []
    assert crossings.count_crossings(X0, X1, off, True, stop=lambda: len(looks) >= 5 or looks.append(1)) is None
    assert len(looks) == 5 and not screened
    looks.clear()
    parts = crossings.count_crossings(X0, X1, off, True, stop=lambda: looks.append(1) and False)
    assert parts["crossings"] == whole["crossings"] and np.array_equal(parts["pairs"], whole["pairs"])
    assert len(looks) > 20, len(looks)


def test_count_frames_min_distance_is_each_frames_minimum(tmp_path):
    """scripts/count_crossings.py's per-step min_distance was the closest of the
    candidate pairs within the run's strand_thickness (touching boxes without one): inf
    (and "Infinity" in --json) for a step whose closest pair is farther, every step of
    the 20-wisp demo.  It is now the frame's minimum between wisps, against brute force;
    None with one wisp."""
    import json as json_module
    from lc_petsc.crossings import count_frames, min_distance, pair_positions, segments
    from lc_petsc.elements.segment_contact import distance
    from scripts.count_crossings import main as count_main
    path = tmp_path / "f.h5"
    rng = np.random.default_rng(5)
    frames = [np.concatenate([bar(0.0, 0), bar(y, 2)]) for y in (1.0, 0.5, -0.5)]
    curls = rng.uniform(-3, 3, (6, 1, 3)) + 0.4 * np.cumsum(rng.standard_normal((6, N, 3)), axis=1)
    frames.append(np.concatenate([bar(3.0, 0), bar(3.0, 2, z=0.2)]))
    with h5py.File(path, "w") as f:
        f["positions"] = np.asarray(frames)
        f["wisp_offsets"] = np.array([0, N, 2 * N], np.int64)
        f.attrs["config"] = json_module.dumps({"physics": {"strand_thickness": 0.1}})
    steps, d0 = count_frames(path)
    assert d0 == 0.1
    assert [s["min_distance"] for s in steps] == pytest.approx([0.5, 0.5, 0.0], abs=1e-12)
    assert count_main([str(path), "--json", str(tmp_path / "c.json")]) == 0
    saved = json_module.loads((tmp_path / "c.json").read_text(),
                              parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))
    assert [s["min_distance"] for s in saved["steps"]] == pytest.approx([0.5, 0.5, 0.0], abs=1e-12)
    off = np.arange(7) * N
    seg, wisp = segments(off)
    i, j = np.triu_indices(len(seg), 1)
    other = wisp[i] != wisp[j]
    X = curls.reshape(-1, 3)
    brute = distance(pair_positions(X, np.stack([seg[i[other]], seg[j[other]]], axis=1))).min()
    for reach in (0.0, 1e-6, 0.3, 100.0):
        assert min_distance(X, off, reach) == pytest.approx(brute, rel=1e-12), reach
    assert 0.05 < brute < 1.0, brute
    assert min_distance(X[:N], off[:2]) is None
