"""How deep hair sinks into the head sphere (lc_petsc.head_check): the deepest free
vertex and edge point of a frame against brute force, vertex paths through a moving
head, and the end-of-run check's ``head`` figures on 1-3 ranks (mpi marker)."""

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.crossings import check_run
from lc_petsc.head_check import SUNK, frame_depths, path_depths, segment_depth, summarize

comm = MPI.COMM_WORLD
R = 15.25


def brute_force(x, c, offsets, pinned, rad, n=20001):
    """(deepest free vertex, deepest edge point less its pinned end's depth, largest
    depth / radius, edges with a point deeper than SUNK radii) by sampling every edge
    with a free vertex at n points."""
    depth = R - np.linalg.norm(x - c, axis=1)
    free = ~pinned
    vertex = max(depth[free].max(initial=0.0), 0.0)
    edge, ratio, sunk = 0.0, max((depth[free] / rad[free]).max(initial=0.0), 0.0), 0
    s = np.linspace(0.0, 1.0, n)[:, None]
    for w in range(len(offsets) - 1):
        for a in range(offsets[w], offsets[w + 1] - 1):
            if pinned[a] and pinned[a + 1]:
                continue
            pts = (1 - s) * x[a] + s * x[a + 1]
            d = R - np.linalg.norm(pts - c, axis=1)
            held = max(depth[a] if pinned[a] else 0.0, depth[a + 1] if pinned[a + 1] else 0.0, 0.0)
            edge = max(edge, d.max() - held)
            r = ((d - held) / ((1 - s[:, 0]) * rad[a] + s[:, 0] * rad[a + 1])).max()
            ratio, sunk = max(ratio, r), sunk + int(r > SUNK)
    return vertex, edge, ratio, sunk


def test_deepest_vertex_and_edge_point_match_brute_force():
    """Random wisps around the head: zigzag strands whose edges (0.3-3 cm) cut the
    sphere; the first vertex of some wisps pinned under the scalp.  The deepest figures
    equal dense sampling's within its resolution."""
    rng = np.random.default_rng(7)
    c = np.array([0.5, 6.0, -1.0])
    x, offsets, pinned = [], [0], []
    for w in range(12):
        n = int(rng.integers(3, 12))
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        r = R + rng.uniform(-0.4, 0.6, n)                  # around the surface
        wiggle = rng.normal(scale=0.08 * (1 + w % 4), size=(n, 3))
        dirs = d + wiggle + np.linspace(0, 0.2, n)[:, None] * rng.normal(size=3)
        dirs /= np.linalg.norm(dirs, axis=1)[:, None]
        x.append(c + r[:, None] * dirs)
        offsets.append(offsets[-1] + n)
        pinned.append(np.arange(n) < (w % 3 == 0))
    x, offsets, pinned = np.concatenate(x), np.array(offsets), np.concatenate(pinned)
    rad = rng.uniform(0.05, 0.35, len(x))
    got = frame_depths(x, c, R, offsets, pinned, rad)
    vertex, edge, ratio, sunk = brute_force(x, c, offsets, pinned, rad)
    assert vertex > 0.1 and edge > vertex + 0.01            # chords go deeper than vertices
    assert got["vertex"] == pytest.approx(vertex, abs=1e-12)
    assert got["edge"] == pytest.approx(edge, abs=1e-6) and got["edge"] >= edge
    assert ratio > 2 and sunk > 3
    assert got["ratio"] == pytest.approx(ratio, abs=1e-6) and got["ratio"] >= ratio - 1e-12
    assert got["sunk"] == sunk
    i = got["vertex_at"]
    assert not pinned[i] and R - np.linalg.norm(x[i] - c) == pytest.approx(vertex)
    a = got["edge_at"]
    assert offsets[np.searchsorted(offsets, a, side="right")] - 1 > a    # an edge of one wisp


def test_a_chord_through_the_head_with_both_ends_outside():
    """An edge of 4 cm with both ends 0.01 cm outside the sphere: no vertex inside, the
    edge's middle sqrt(R^2 - ...) deep: the sagitta of the chord."""
    half = 2.0
    y = np.sqrt((R + 0.01) ** 2 - half ** 2)
    x = np.array([[-half, y, 0.0], [half, y, 0.0]])
    got = frame_depths(x, np.zeros(3), R, np.array([0, 2]), np.zeros(2, bool), np.full(2, 0.05))
    assert got["vertex"] == 0.0 and got["vertex_at"] == -1
    assert got["edge"] == pytest.approx(R - y) and got["edge_at"] == 0
    assert R - y == pytest.approx(0.1216, abs=1e-4)         # 2.4 strand radii
    assert got["ratio"] == pytest.approx((R - y) / 0.05) and got["sunk"] == 1
    # the same edge from a pinned root 0.3 cm under the scalp: only what it sinks below it
    x[0] = [-half, np.sqrt((R - 0.3) ** 2 - half ** 2), 0.0]
    got = frame_depths(x, np.zeros(3), R, np.array([0, 2]), np.array([True, False]), np.full(2, 0.05))
    s = np.linspace(0.0, 1.0, 100001)[:, None]
    below = R - np.linalg.norm((1 - s) * x[0] + s * x[1], axis=1).min() - 0.3
    assert got["vertex"] == 0.0 and got["edge"] == pytest.approx(below, abs=1e-8)
    assert got["edge"] == pytest.approx(0.0236, abs=1e-4)      # not the 0.3 of the root


def test_thin_strand_resting_on_the_scalp_warns_of_its_chords_not_newton():
    """A strand of radius 1e-3 cm lying on the scalp, its 0.596 cm edges' vertices on the
    sphere: every edge's chord dips L^2 / 8R = 0.00291 cm (2.91 radii) under it, no vertex
    does.  Counted as sunk by chords; the warning names the chord, the radius and the
    edge length that fits (2 sqrt(2 R r - r^2) = 0.349 cm), not Newton iterations or dt
    (scenes56's thin run: 19 of 20 frames advised them).  A vertex sunk 2 radii deep is
    still the Newton/dt warning."""
    from lc_petsc.config import PhysicsConfig, SimConfig
    from lc_petsc.job import head_warnings
    L, r, n = 0.596, 1e-3, 12
    ang = L / R * np.arange(n)            # vertices on the sphere, chords about L long
    x = R * np.stack([np.sin(ang), np.cos(ang), np.zeros(n)], axis=1)
    pinned = np.zeros(n, bool)
    pinned[0] = True
    got = frame_depths(x, np.zeros(3), R, np.array([0, n]), pinned, np.full(n, r))
    chord = 2 * R * np.sin(L / (2 * R))
    sag = R - np.sqrt(R ** 2 - chord ** 2 / 4)
    assert sag == pytest.approx(0.00291, abs=1e-5)
    assert got["vertex"] == pytest.approx(0.0, abs=1e-12) and got["edge"] == pytest.approx(sag, rel=1e-9)
    assert got["sunk"] == got["sunk_chords"] == n - 1
    assert got["chord_length"] == pytest.approx(chord) and got["chord_radius"] == r
    head = summarize([(0, dict(got, path_depth=0.0, path_beyond=0.0, path_through=0))])
    assert head["rows_sunk"] == head["rows_sunk_by_chords"] == 1
    cfg = SimConfig(physics=PhysicsConfig(terms=("stretch", "bend", "gravity", "head_collision")))
    (m,) = head_warnings(head, cfg)
    assert "dips 0.00291 cm under it, 2.91 times the strand radius 0.001 cm" in m, m
    assert "edges shorter than 0.349 cm" in m and "cannot change it" in m
    assert "raise time.newton_iterations" not in m
    # one vertex 2 radii under the sphere: a sink, not a chord
    x[5] *= (R - 2 * r) / R
    got = frame_depths(x, np.zeros(3), R, np.array([0, n]), pinned, np.full(n, r))
    assert got["sunk"] > got["sunk_chords"] == n - 3
    head = summarize([(0, dict(got, path_depth=0.0, path_beyond=0.0, path_through=0))])
    assert head["rows_sunk"] == 1 and head["rows_sunk_by_chords"] == 0
    (m,) = head_warnings(head, cfg)
    assert m.startswith("hair sinks into the head") and "raise time.newton_iterations" in m


def test_a_vertex_passing_through_a_moving_head_between_frames():
    """The head moves 40 cm along x in a step; a vertex at rest 2 cm above its centre's
    path is outside at both frames, yet the head passes through it: relative to the
    centre its path dips 13.25 cm deep (the viewer sees the head sweep through the hair)."""
    x0 = x1 = np.array([[0.0, 2.0, 0.0], [0.0, 40.0, 0.0]])
    pinned = np.array([False, True])
    got = path_depths(x0, x1, [-20.0, 0.0, 0.0], [20.0, 0.0, 0.0], R, pinned, np.full(2, 0.1))
    assert got == {"depth": pytest.approx(R - 2.0), "beyond": pytest.approx(R - 2.0), "through": 1}
    # a still head: nothing moves, nothing passes
    got = path_depths(x0, x1, [-20.0, 0.0, 0.0], [-20.0, 0.0, 0.0], R, pinned, np.full(2, 0.1))
    assert got == {"depth": 0.0, "beyond": 0.0, "through": 0}
    # a vertex that ends 0.5 cm deep: no pass-through, the path no deeper than its end
    got = path_depths([[0.0, 16.0, 0.0]], [[0.0, R - 0.5, 0.0]], np.zeros(3), np.zeros(3), R,
                      [False], [0.1])
    assert got == {"depth": pytest.approx(0.5), "beyond": pytest.approx(0.0, abs=1e-12), "through": 0}
    d, t = segment_depth(np.array([[0.0, 16.0, 0.0]]), np.array([[0.0, 16.0, 0.0]]), R)
    assert d[0] == pytest.approx(R - 16.0) and t[0] == 0.0      # a still point: its own depth


def test_summarize_names_rows_and_steps():
    """Rows are steps + 1; a row not checked is None in ``depth_per_row``."""
    def step(v, e, ratio, sunk, pd, through):
        return {"vertex": v, "edge": e, "ratio": ratio, "sunk": sunk, "path_depth": pd,
                "path_beyond": pd / 2, "path_through": through}
    s = summarize([(2, step(0.2, 0.3, 2.0, 3, 0.4, 0)), (0, step(0.0, 0.0, 0.0, 0, 0.0, 0)),
                   (3, step(0.1, 0.1, 0.5, 0, 1.0, 2))])
    assert s == {"vertex_depth": 0.2, "vertex_row": 3, "edge_depth": 0.3, "edge_row": 3, "ratio": 2.0,
                 "ratio_row": 3, "rows_sunk": 1, "rows_sunk_by_chords": 0, "chord_length": None,
                 "chord_radius": None, "first_sunk_row": 3, "path_depth": 1.0, "path_beyond": 0.5,
                 "paths_through": 2, "steps_through": 1, "first_through": 3,
                 "depth_per_row": [0.0, None, 0.3, 0.1]}
    assert summarize([]) is None


def write_frames(path, frames, times, offsets, pinned, radius, physics, kind="file"):
    """A frames.h5 with what the check reads, the run's config holding ``physics``."""
    if comm.rank == 0:
        with h5py.File(path, "w") as f:
            f["positions"] = np.asarray(frames, float)
            f["time"] = np.asarray(times, float)
            f["wisp_offsets"] = np.asarray(offsets, np.int64)
            f["rest_positions"] = np.asarray(frames[0], float)
            f["pinned"] = np.asarray(pinned, bool)
            f["radius"] = np.asarray(radius, float)
            f.attrs["config"] = json.dumps({"scene": {"kind": kind}, "physics": physics})
    comm.Barrier()


@pytest.mark.mpi
def test_end_of_run_check_measures_the_head_on_any_rank_count(tmp_path):
    """A head translating at 30 cm/s along x and a free wisp hanging still 14.75 cm
    above its start: row k's vertex depth is R - |x - c(t_k)|, the wisp's edges the same
    at their deepest point; the same figures on 1-3 ranks, none without a head sphere."""
    path = Path(comm.bcast(str(tmp_path) if comm.rank == 0 else None)) / "f.h5"
    wisp = np.column_stack([np.linspace(-3, 3, 7), np.full(7, 14.75), np.zeros(7)])
    root = np.array([[0.0, R + 1.0, 0.0], [0.0, R + 1.6, 0.0]])    # a pinned wisp, carried
    times = np.arange(6) / 30.0
    frames = [np.concatenate([wisp, root + [30.0 * t, 0, 0]]) for t in times]
    phys = {"terms": ["head_collision"], "head_motion": "translate", "head_velocity": [30.0, 0.0, 0.0]}
    pinned = np.r_[np.zeros(7, bool), True, True]
    write_frames(path, frames, times, [0, 7, 9], pinned, np.full(9, 0.2), phys)
    h = check_run(path, comm)["head"]
    want = [R - np.min(np.linalg.norm(wisp - [30.0 * t, 0, 0], axis=1)) for t in times[1:]]
    assert h["vertex_depth"] == pytest.approx(0.5) and h["vertex_row"] == 1
    assert h["depth_per_row"] == pytest.approx(want)
    assert h["edge_depth"] == pytest.approx(max(want)) and h["ratio"] == pytest.approx(2.5)
    assert h["rows_sunk"] == 5 and h["first_sunk_row"] == 1 and h["paths_through"] == 0
    assert comm.allgather(h) == [h] * comm.size
    # no head_collision and not a hairball: no head sphere, no figures
    write_frames(path, frames, times, [0, 7, 9], pinned, np.full(9, 0.2), {"terms": ["gravity"]})
    assert check_run(path, comm)["head"] is None


STRAND_TOML = """
[scene]
kind = "straight"
n_vertices = 30
n_pinned = 2
direction = [1.0, 0.0, 0.0]
segment_length = 0.5
[material]
youngs_modulus = 1.0e7
root_radius = 0.05
tip_radius = 0.05
[physics]
terms = ["stretch", "bend", "gravity", "head_collision"]
head_radius = 5.0
head_center = [8.0, -5.05, 0.0]
head_push_out = {push_out}
[time]
frames = 10
newton_iterations = 3
[output]
previews = false
usd = false
xdmf = false
"""


def test_run_reports_and_warns_hair_inside_the_head(tmp_path):
    """A strand falls onto the head at 3 Newton iterations: without the push-out it ends
    frames 0.59 cm deep (12 radii); the summary's ``head`` figures say so and a warning
    names head_push_out and newton_iterations.  With it no vertex ends deeper than its
    0.05 cm radius less its edges' sagitta on the head (0.5 cm edges on a 5 cm head:
    0.006 cm), so no edge's chord goes past the radius either: 0.039 cm, 0.82 radii, no
    warning (1.08 radii in 2 frames, and a warning, when vertices could rest a whole
    radius deep)."""
    from lc_petsc.batch import main
    got = {}
    for push_out in ("false", "true"):
        cfg = tmp_path / f"{push_out}.toml"
        cfg.write_text(STRAND_TOML.format(push_out=push_out))
        out = tmp_path / push_out
        assert main([str(cfg), "--out", str(out), "--quiet"]) == 0
        s = json.loads((out / "summary.json").read_text())
        h = s["crossings"]["head"]
        with h5py.File(out / "frames.h5") as f:
            X = f["positions"][1:][:, 2:]                    # the free vertices, rows after the first
        deepest = float(np.max(5.0 - np.linalg.norm(X - [8.0, -5.05, 0.0], axis=2)))
        assert h["vertex_depth"] == pytest.approx(deepest, abs=1e-12)
        assert len(h["depth_per_row"]) == 10 and h["edge_depth"] >= deepest
        got[push_out] = h, [m for m in s["warnings"] if m.startswith("hair sinks into the head")]
    (h, sunk), (h_on, sunk_on) = got["false"], got["true"]
    assert h["vertex_depth"] > 0.5 and h["ratio"] > 10 and h["rows_sunk"] >= 3, h
    assert len(sunk) == 1 and "physics.head_push_out = true" in sunk[0] and "newton_iterations" in sunk[0]
    assert 0.01 < h_on["vertex_depth"] <= 0.05 and 0.5 < h_on["ratio"] < 1.0 and h_on["rows_sunk"] == 0, h_on
    assert h_on["paths_through"] == 0 and sunk_on == []


def test_warning_with_the_push_out_on_says_what_it_leaves():
    """With physics.head_push_out on, the sunk warning names what the push-out leaves
    (paths a lift by the strand radius cannot mend, the strand contact's moves, wisps
    without a pinned vertex) instead of asking for it."""
    from lc_petsc.config import PhysicsConfig, SimConfig
    from lc_petsc.job import head_warnings
    head = {"rows_sunk": 1, "first_sunk_row": 3, "vertex_depth": 0.08, "edge_depth": 0.08, "ratio": 1.1,
            "paths_through": 0}
    cfg = SimConfig(physics=PhysicsConfig(terms=("stretch", "bend", "gravity", "head_collision")))
    (m,) = head_warnings(head, cfg)
    assert "what it leaves" in m and "cannot keep out" in m and "physics.head_push_out = true" not in m, m
    assert "frame 3" in m and "1.1 strand radii" in m
