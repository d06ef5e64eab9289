"""Intersection-free strand contact (physics.strand_contact_mode = "ccd") in the
simulator: wisps driven into each other never pass through (1, 2, 3 ranks, the pair
straddling ranks), the penalty mode as control does, and runs on 2 and 3 ranks follow
the serial one.  Serial here; tests/test_mpi_launch.py runs it under mpiexec."""

from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI

import lc_petsc.simulator as simmod
from lc_petsc.config import load_config
from lc_petsc.crossings import count_crossings
from lc_petsc.elements.segment_contact import distance
from lc_petsc.scene import geometry
from lc_petsc.scene.sources import ArraySource
from sim_helpers import frames_run, touching_wisps_config, touching_wisps_source
from test_contact_sim import D0, N, crossing_config, crossing_source

pytestmark = pytest.mark.mpi
comm = MPI.COMM_WORLD
ROOT = Path(__file__).resolve().parents[2]
FRAMES = 12
SPEED = 10 * D0 * 30.0          # 10x the contact thickness per frame (dt = 1/30 s)


def drive_together(c, mode):
    """A up, B down at SPEED; returns (crossings per frame step, summary) on rank 0."""
    cfg = crossing_config(FRAMES, gravity=False, strand_contact_mode=mode,
                          strand_separation=mode == "penalty")
    sim = simmod.build_simulator(cfg, comm=c)
    v = np.zeros_like(sim.x)
    up = sim.scene.first_wisp + np.repeat(np.arange(sim.scene.n_wisps),
                                          np.diff(sim.scene.offsets)) == 0
    v[:, 1] = np.where(up, SPEED, -SPEED)
    sim.integrator.v = v
    X, summ = frames_run(sim, FRAMES)
    if c.rank != 0:
        return None, summ
    off = [0, N, 2 * N]
    return [count_crossings(X[k], X[k + 1], off)["crossings"] for k in range(FRAMES)], summ


def test_wisps_driven_together_never_cross(monkeypatch):
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: crossing_source())
    sub = comm.Split(0 if comm.rank < 2 else MPI.UNDEFINED)   # two wisps: at most 2 ranks
    if sub == MPI.COMM_NULL:
        comm.Barrier()
        return
    try:
        crossings, summ = drive_together(sub, "ccd")
        c = summ["contact"]
        if sub.rank == 0:
            print(f"\nccd on {sub.size} rank(s): crossings per step {crossings}, min distance "
                  f"{c['min_distance']:.4g} cm (d0 = {D0}), limited vertices per frame "
                  f"{c['limited_vertices_per_frame']}, held on the frame paths "
                  f"{c['frame_path_held_vertices_per_frame']}")
            assert sum(crossings) == 0, crossings
            assert sum(c["pairs_per_frame"]) > 0
            # the limiter did the work (on a Newton step or on a frame's path)
            assert max(c["limited_vertices_per_frame"] + c["frame_path_held_vertices_per_frame"]) > 0
            assert c["min_distance"] > 0.0
    finally:
        sub.Free()
        comm.Barrier()


def run_touching(c, frames=10, carry=False):
    cfg = touching_wisps_config(frames)
    cfg.physics.strand_contact_mode = "ccd"
    cfg.time.newton_iterations = 4
    # the trajectory measured uncarried (time.carry_with_head): carried, the same limiter
    # decisions amplify the partition's round-off more on this scene (2 ranks: 3.9e-15
    # after frame 1, 2.6e-12 after 4, 3.6e-7 after 10; 3 ranks 2.6e-8), checked below
    cfg.time.carry_with_head = carry
    return frames_run(simmod.build_simulator(cfg, comm=c), frames)


def test_ccd_rank_invariance_and_no_crossing(monkeypatch):
    """Six in-phase wisps, head shaking: 0 crossings, and 2 / 3 ranks follow 1 rank.
    Only the straight stems are pinned: a pinned helix vertex turning with the head
    into a held-back neighbour is the limiter's known gap (ccd_unresolved_pairs_per_frame).
    Bound 1e-7, the contact tolerance of docs/contact.md ("Rank invariance with the rigid
    frame-path field"): the limiter's decisions are the same on every rank count, but its
    fractions amplify round-off (measured 1.8e-8 on 2 ranks, 5.4e-8 on 3; main 1.5e-11)."""
    monkeypatch.setattr(simmod, "source_from_config",
                        lambda *a: touching_wisps_source(spin_step=0.0, n_pinned=3))
    X, summ = run_touching(comm)
    ok, msg = True, ""
    if comm.rank == 0:
        ref, ref_summ = run_touching(MPI.COMM_SELF)
        off = np.arange(7) * 30
        crossings = [count_crossings(X[k], X[k + 1], off)["crossings"] for k in range(len(X) - 1)]
        err = float(np.abs(X[-1] - ref[-1]).max() / np.abs(ref[-1]).max())
        c = summ["contact"]
        ok = sum(crossings) == 0 and sum(c["pairs_per_frame"]) > 0 and err <= 1e-7 \
            and max(c["limited_vertices_per_frame"]) > 0 and sum(c["ccd_unresolved_pairs_per_frame"]) == 0
        msg = (f"{comm.size} ranks: crossings {crossings}, relative difference to 1 rank {err:.3e}, "
               f"pairs per frame {c['pairs_per_frame']}, limited vertices per frame "
               f"{c['limited_vertices_per_frame']}, held on the frame paths "
               f"{c['frame_path_held_vertices_per_frame']}")
        print("\n" + msg)
    ok, msg = comm.bcast((ok, msg))
    assert ok, msg



def test_ccd_rank_invariance_with_the_carried_first_iterate(monkeypatch):
    """The same scene with the carried first iterate (the default): the carry is computed
    row by row (the same bits on any partition), so after 4 frames 2 / 3 ranks are within
    round-off of 1 rank (measured 2.6e-12 / 2.9e-13; later frames' contact decisions
    amplify it, above), with no crossing."""
    monkeypatch.setattr(simmod, "source_from_config",
                        lambda *a: touching_wisps_source(spin_step=0.0, n_pinned=3))
    X, summ = run_touching(comm, frames=4, carry=True)
    ok, msg = True, ""
    if comm.rank == 0:
        ref, _ = run_touching(MPI.COMM_SELF, frames=4, carry=True)
        off = np.arange(7) * 30
        crossings = [count_crossings(X[k], X[k + 1], off)["crossings"] for k in range(len(X) - 1)]
        err = float(np.abs(X[-1] - ref[-1]).max() / np.abs(ref[-1]).max())
        ok = sum(crossings) == 0 and err <= 1e-10 and sum(summ["contact"]["pairs_per_frame"]) > 0
        msg = f"{comm.size} ranks: crossings {crossings}, relative difference to 1 rank {err:.3e}"
    ok, msg = comm.bcast((ok, msg))
    assert ok, msg

def six_wisps_ccd(monkeypatch, frames=1, solver=(), **time):
    """A simulator of the six in-phase touching wisps (3 pinned vertices each) in ccd
    mode; ``solver``: SolverConfig fields to set, as (key, value) pairs; ``time``:
    TimeConfig fields to set."""
    monkeypatch.setattr(simmod, "source_from_config",
                        lambda *a: touching_wisps_source(spin_step=0.0, n_pinned=3))
    cfg = touching_wisps_config(frames)
    cfg.physics.strand_contact_mode = "ccd"
    for section, fields in ((cfg.solver, dict(solver)), (cfg.time, time)):
        for key, value in fields.items():
            setattr(section, key, value)
    return simmod.build_simulator(cfg.validate(), comm=comm)


def test_limiter_candidates_serve_the_next_pair_search(monkeypatch):
    """The contact pairs at positions that a limiter call produced come from that call's
    candidates (StrandContact._reached), not from a new ghost exchange and broad phase.
    Random steps of the six wisps, each wisp also pushed sideways against its neighbours,
    so that pairs far beyond the search radius at the step's start end in contact: at the
    limited positions the reused pairs are every pair closer than d0 (brute force over all
    pairs of segments of different wisps) and equal, array for array, to those of a fresh
    exchange and broad phase."""
    sim = six_wisps_ccd(monkeypatch)
    try:
        st, sc = sim.integrator.strand, sim.scene
        d0, n = st.d0, sc.nv
        rng = np.random.default_rng(5)
        x = sim.integrator.x.copy()
        wisp_of = np.repeat(np.arange(6), 30)
        newly_close = 0
        for trial in range(5):
            push = np.where(wisp_of % 2 == 0, 1.0, -1.0)[:, None] * np.array([0.25, 0.0, 0.0])
            D = rng.normal(scale=0.08, size=(6 * 30, 3)) + push * (1 + trial % 2)
            target = x + D[sc.first_vertex:sc.first_vertex + n]
            x_new = st.limit_step(x, target)
            assert st._reached(x_new) is not None
            st._pairs_cache = None
            got = st._pairs(x_new)
            limited, st._limited, st._pairs_cache = st._limited, None, None
            ref = st._pairs(x_new)                      # fresh exchange and broad phase
            assert len(got[0]) == len(ref[0])
            for a, b in zip(got, ref):
                np.testing.assert_array_equal(a, b)
            st._limited = limited
            # brute force on rank 0 over the gathered positions
            pairs = comm.gather(np.stack([got[1], got[2]], axis=1))
            Xs, X0s = comm.gather(x_new), comm.gather(x)
            if comm.rank == 0:
                X1, X0 = np.concatenate(Xs), np.concatenate(X0s)
                seg = np.array([v for v in range(6 * 30) if v % 30 != 29])
                i, j = np.triu_indices(len(seg), 1)
                i, j = i[wisp_of[seg[i]] != wisp_of[seg[j]]], j[wisp_of[seg[i]] != wisp_of[seg[j]]]
                close = distance(np.stack([X1[seg[i]], X1[seg[i] + 1], X1[seg[j]], X1[seg[j] + 1]], axis=1)) < d0
                want = {(seg[a], seg[b]) for a, b in zip(i[close], j[close])}
                found = {tuple(p) for p in np.concatenate(pairs).tolist()}
                assert found == want, (trial, len(found), len(want))
                # pairs that a broad phase at the step's start would not have listed
                A = np.stack([X0[seg[i]], X0[seg[i] + 1]], axis=1)
                B = np.stack([X0[seg[j]], X0[seg[j] + 1]], axis=1)
                apart = ((A.min(1) - 0.5 * d0 > B.max(1) + 0.5 * d0) |
                         (B.min(1) - 0.5 * d0 > A.max(1) + 0.5 * d0)).any(axis=1)
                newly_close += int(np.sum(close & apart))
            x = x_new
        print(f"\npairs newly in contact over the steps: {comm.bcast(newly_close)}")
        assert comm.bcast(newly_close) > 0
    finally:
        sim.close()


def test_frame_path_checks_reuse_candidates_inside_their_skin(monkeypatch):
    """A frame path check (collision_free_frame) whose segment boxes all stay inside
    the boxes of the check that exchanged the ghosts and found the box pairs, grown by
    LIMITER_SKIN d0, reuses them; its result equals, bit for bit, that of a fresh
    exchange and broad phase.  A box leaving its skin makes the next check start anew
    (on every rank, the pair straddling ranks on 2 and 3)."""
    sim = six_wisps_ccd(monkeypatch)
    try:
        st, sc = sim.integrator.strand, sim.scene
        d0, lo, hi = st.d0, sc.first_vertex, sc.first_vertex + sc.nv
        x_old = sim.integrator.x.copy()
        c, s_ = np.cos(0.02), np.sin(0.02)      # the head turning a little, and moving
        motion = (np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]]), np.array([0.05, 0.0, 0.0]))
        carried = x_old @ motion[0].T + motion[1]
        rng = np.random.default_rng(11)
        wisp_of = np.repeat(np.arange(6), 30)
        push = np.where(wisp_of % 2 == 0, 1.0, -1.0)[:, None] * np.array([0.4, 0.0, 0.0])
        D = (rng.normal(scale=0.05, size=(6 * 30, 3)) + push)[lo:hi]
        small = 0.05 * d0 * rng.uniform(-1.0, 1.0, size=(6 * 30, 3))[lo:hi]

        def check(target, reuse):
            target = np.where(sc.pinned[:, None], carried, target)
            before = st.path_checks_reused
            got = st.collision_free_frame(x_old, target, motion)
            assert st.path_checks_reused - before == reuse
            st._path_cache = st._path_ends = None
            ref = st.collision_free_frame(x_old, target, motion)      # a fresh exchange, every pair tested
            np.testing.assert_array_equal(got[0], ref[0])
            assert got[1] == ref[1]
            return got[1]

        st._path_cache = None
        held = [check(carried + D, 0),
                check(carried + D + small, 1),                  # inside the skin: reused
                check(carried + 1.5 * D, 0)]                    # far outside: anew
        print(f"\nvertices held back per check: {held}")
        assert min(held) > 0
    finally:
        sim.close()


def test_frame_end_path_check_tests_first_only_the_pairs_that_moved(monkeypatch):
    """The frame end's path checks after its first start from the same positions and
    fallbacks: their first round tests only the pairs with a vertex whose path end
    differs from the last check's final one, or that the last check left held
    (StrandContact._first_round).  The result equals a check whose first round tests
    every pair, bit for bit; a check from other start positions tests every pair."""
    from lc_petsc.elements import compiled_ccd
    sim = six_wisps_ccd(monkeypatch)
    try:
        st, sc = sim.integrator.strand, sim.scene
        d0, lo, hi = st.d0, sc.first_vertex, sc.first_vertex + sc.nv
        x_old = sim.integrator.x.copy()
        motion = (np.eye(3), np.array([0.05, 0.0, 0.0]))
        carried = x_old + motion[1]
        rng = np.random.default_rng(3)
        wisp_of = np.repeat(np.arange(6), 30)
        push = np.where(wisp_of % 2 == 0, 1.0, -1.0)[:, None] * np.array([0.4, 0.0, 0.0])
        D = (rng.normal(scale=0.05, size=(6 * 30, 3)) + push)[lo:hi]
        first_round = []
        limit_pairs = compiled_ccd.limit_pairs

        def spy(S, E, inv, redo, *a, **k):
            if not first_round or first_round[-1] is None:
                first_round[-1:] = [(len(redo), len(inv))]
            return limit_pairs(S, E, inv, redo, *a, **k)

        monkeypatch.setattr(compiled_ccd, "limit_pairs", spy)

        def check(x_start, target):
            first_round.append(None)
            return st.collision_free_frame(x_start, np.where(sc.pinned[:, None], carried, target), motion)

        x1, held = check(x_old, carried + D)
        assert comm.allreduce(held) > 0
        # a separation's few nudges, then the next check from the same start
        nudged = x1.copy()
        nudged[rng.random(len(x1)) < 0.05] += 0.05 * d0
        got = check(x_old, nudged)
        tested, kept = first_round[-1]
        st._path_ends = None
        ref = check(x_old, nudged)
        np.testing.assert_array_equal(got[0], ref[0])
        assert got[1] == ref[1] and first_round[-1] == (kept, kept)
        assert comm.allreduce(kept) > 0 and comm.allreduce(tested) < comm.allreduce(kept) // 2
        # other start positions: every pair
        check(x_old + 1e-3 * d0, nudged)
        assert first_round[-1][0] == first_round[-1][1]
    finally:
        sim.close()


def test_frame_end_distance_does_not_decay_over_a_run(monkeypatch):
    """Six in-phase wisps, 3 pinned stem vertices, head shaking, 24 frames, 3 Newton
    iterations (main: 5 crossings, 19 unresolved pairs, frame-end minimum 0.019 d0): 0
    crossings, 0 unresolved pairs and every frame-end minimum distance >= 0.25 d0 (the
    separation and the frame-path check alternate at the frame's end; the head's rigid
    motion is the frame paths' field, the zero field the Newton steps')."""
    monkeypatch.setattr(simmod, "source_from_config",
                        lambda *a: touching_wisps_source(spin_step=0.0, n_pinned=3))
    cfg = touching_wisps_config(24)
    cfg.physics.strand_contact_mode = "ccd"
    cfg.time.newton_iterations = 3
    X, summ = frames_run(simmod.build_simulator(cfg, comm=comm), 24)
    ok, msg = True, ""
    if comm.rank == 0:
        c, d0 = summ["contact"], cfg.physics.strand_thickness
        off = np.arange(7) * 30
        crossings = [count_crossings(X[k], X[k + 1], off)["crossings"] for k in range(24)]
        dmin = min(c["min_distance_per_frame"]) / d0
        ok = sum(crossings) == 0 and dmin >= 0.25 and sum(c["ccd_unresolved_pairs_per_frame"]) == 0 \
            and max(c["frame_path_checks_per_frame"]) >= 2
        msg = (f"crossings {crossings}, frame-end min distance {dmin:.3g} d0, unresolved "
               f"{c['ccd_unresolved_pairs_per_frame']}, path checks {c['frame_path_checks_per_frame']}")
    ok, msg = comm.bcast((ok, msg))
    assert ok, msg


def six_wisps_parts(sim):
    """(strand contact, scene, gathered rest positions, wisp of each local vertex) of a
    :func:`six_wisps_ccd` simulator."""
    sc = sim.scene
    return (sim.integrator.strand, sc, np.concatenate(comm.allgather(sc.x_rest)),
            np.repeat(np.arange(6), 30)[sc.first_vertex:sc.first_vertex + sc.nv])


def brute_force_measure(X, X_rest, d0):
    """measure()'s figures by brute force over all pairs of segments of different wisps
    of the six wisps (gathered positions X, rest X_rest (180, 3)): (pairs closer than d0
    that were not closer at rest, those closer than d0 / 2, the smallest distance over
    those pairs and the farther pairs whose boxes grown by d0 / 2 overlap)."""
    seg = np.array([v for v in range(6 * 30) if v % 30 != 29])
    i, j = np.triu_indices(len(seg), 1)
    other = seg[i] // 30 != seg[j] // 30
    i, j = seg[i[other]], seg[j[other]]

    def dist(Y):
        return distance(np.stack([Y[i], Y[i + 1], Y[j], Y[j + 1]], axis=1))

    d, d_rest = dist(X), dist(X_rest)
    active = (d < d0) & (d_rest >= d0)
    A, B = np.stack([X[i], X[i + 1]], axis=1), np.stack([X[j], X[j + 1]], axis=1)
    overlap = ~((A.min(1) - 0.5 * d0 > B.max(1) + 0.5 * d0) | (B.min(1) - 0.5 * d0 > A.max(1) + 0.5 * d0)).any(axis=1)
    considered = active | ((d >= d0) & overlap)
    return int(active.sum()), int(np.sum(active & (d < 0.5 * d0))), float(d[considered].min(initial=np.inf))


def test_measure_equals_brute_force(monkeypatch):
    """StrandContact.measure (close pairs, deep pairs, minimum distance over the candidates)
    against brute force over all segment pairs: at the start (no close pair; a fresh broad
    phase), after a
    limited Newton step (the limiter's candidates reused), after a frame path check with a
    turning head (a field's boxes), and after a path check with no pair close (the minimum
    then comes from a fresh broad phase, not from the path check's candidates), on 1-3
    ranks."""
    sim = six_wisps_ccd(monkeypatch)
    try:
        st, sc, X_rest, wisp_of = six_wisps_parts(sim)
        d0 = st.d0
        rng = np.random.default_rng(3)
        x0 = sim.integrator.x.copy()
        push = np.where(wisp_of % 2 == 0, 1.0, -1.0)[:, None] * np.array([0.3, 0.0, 0.0])
        x1 = st.limit_step(x0, x0 + push + rng.normal(scale=0.05, size=x0.shape))
        c, s_ = np.cos(0.3), np.sin(0.3)
        motion = (np.array([[c, 0.0, s_], [0.0, 1.0, 0.0], [-s_, 0.0, c]]), np.array([0.0, 0.2, 0.0]))
        x2 = st.collision_free_frame(x1, x1 @ motion[0].T + motion[1] - 0.5 * push, motion)[0]
        # no close pair: the start turned rigidly, through a path check (the field's boxes
        # turn with it, so far pairs whose boxes overlap at the end can be missing from its
        # candidates: the minimum must come from a fresh broad phase)
        x3 = st.collision_free_frame(x0, x0 @ motion[0].T + motion[1], motion)[0]
        # no close pair, the closest at 1.2 d0: the even wisps' free vertices pushed towards the odd ones
        # (bisection on the brute-force distance, the same on every rank), limited
        X0, w_all = np.concatenate(comm.allgather(x0)), np.repeat(np.arange(6), 30)
        free_all = ~np.concatenate(comm.allgather(sc.pinned))      # the roots stay (prescribed)
        sign = (np.where(w_all % 2 == 0, 1.0, -1.0) * free_all)[:, None] * np.array([1.0, 0.0, 0.0])
        lo_s, hi_s = 0.0, 0.5
        for _ in range(40):
            X_s = X0 + 0.5 * (lo_s + hi_s) * sign
            closest = brute_force_measure(X_s, X_s + 1e10 * w_all[:, None], 1e9)[2]
            lo_s, hi_s = (0.5 * (lo_s + hi_s), hi_s) if closest > 1.2 * d0 else (lo_s, 0.5 * (lo_s + hi_s))
        x4 = st.limit_step(x0, x0 + lo_s * sign[sc.first_vertex:sc.first_vertex + sc.nv])
        got_close = []
        for x in (x0, x1, x2, x3, x4):
            got = st.measure(x)
            want = brute_force_measure(np.concatenate(comm.allgather(x)), X_rest, d0)
            assert got[:2] == want[:2] and got[2] == pytest.approx(want[2], rel=1e-12, abs=1e-12), (got, want)
            got_close.append(got[0])
        assert got_close[1] > 0 and got_close[2] > 0 and got_close[3] == got_close[4] == 0, got_close
        assert 1.0 * d0 < st.measure(x4)[2] < 1.21 * d0
        # the limiter's candidates hold every pair closer than d0, not every farther one: with
        # none close the minimum comes from a fresh broad phase (here: none reused at all)
        x_end, *rest, ci, cj = st._limited
        st._limited, st._pairs_cache = (x_end, *rest, ci[:0], cj[:0]), None
        assert st.measure(x_end)[2] == pytest.approx(want[2], rel=1e-12, abs=0.0)
    finally:
        sim.close()


def brute_force_min(X, X_rest, d0):
    """The smallest distance between segments of different wisps of the six wisps at X,
    pairs closer than d0 at rest and now (exempt) left out: what summary.json's
    contact.min_distance_per_frame means."""
    seg = np.array([v for v in range(6 * 30) if v % 30 != 29])
    i, j = np.triu_indices(len(seg), 1)
    other = seg[i] // 30 != seg[j] // 30
    i, j = seg[i[other]], seg[j[other]]
    d = distance(np.stack([X[i], X[i + 1], X[j], X[j + 1]], axis=1))
    d_rest = distance(np.stack([X_rest[i], X_rest[i + 1], X_rest[j], X_rest[j + 1]], axis=1))
    return float(d[(d >= d0) | (d_rest >= d0)].min())


def test_min_distance_is_the_true_minimum(monkeypatch):
    """StrandContact.min_distance against brute force over all pairs of segments of
    different wisps, on 1-3 ranks: with pairs closer than d0 (measure's minimum), at rest
    and with the wisps spread 1.2x and 3x apart, every other one turned (measure's
    minimum is then the closest candidate of its d0 broad phase, or inf: main reported
    those, 0.2527 cm for a true 0.1379 in from_file), from no hint and from hints too
    small and too large."""
    sim = six_wisps_ccd(monkeypatch)
    try:
        st, sc, X_rest, wisp_of = six_wisps_parts(sim)
        d0 = st.d0
        free = ~sc.pinned[:, None]
        x0 = sim.integrator.x.copy()
        push = np.where(wisp_of % 2 == 0, 1.0, -1.0)[:, None] * np.array([0.3, 0.0, 0.0]) * free
        states = {"pushed together": st.limit_step(x0, x0 + push), "rest": x0}
        c, s_ = np.cos(0.9), np.sin(0.9)
        for k in (1.2, 3.0):          # each wisp moved along the row of roots
            x = x0 + (k - 1.0) * 0.9 * wisp_of[:, None] * np.array([1.0, 0.0, 0.0])
            for w in range(1, 6, 2):  # the odd wisps turned 0.9 rad about their vertical axis
                m = wisp_of == w      # (whole wisps per rank)
                if m.any():
                    x[m] = (x[m] - x[m].mean(axis=0)) @ np.array([[c, 0.0, -s_], [0.0, 1.0, 0.0], [s_, 0.0, c]]) \
                        + x[m].mean(axis=0)
            states[f"spread {k}x, turned"] = x
        seen = []
        for name, x in states.items():
            want = brute_force_min(np.concatenate(comm.allgather(x)), X_rest, d0)
            dmin = st.measure(x)[2]
            for hint in (np.inf, 0.5 * want, 3.0 * want):
                got = st.min_distance(x, dmin, hint=hint)
                assert got == pytest.approx(want, rel=1e-12), (name, hint, got, want, dmin)
            seen.append((name, dmin, want))
        # the cases: measure exact, measure a wrong candidate, measure inf
        assert seen[0][1] == pytest.approx(seen[0][2]) and seen[0][2] < d0, seen
        assert any(np.isfinite(d) and d > 1.01 * w for _, d, w in seen[1:]), seen
        assert seen[-1][1] == np.inf and seen[-1][2] > d0, seen
    finally:
        sim.close()


def turned_wisps_source():
    """The six wisps 1.2 cm apart, every other one turned 0.9 rad about its axis: out of
    contact at first, the closest pair's boxes grown by d0 / 2 apart while farther pairs'
    overlap (the d0 broad phase's closest candidate is not the closest pair)."""
    pos = np.concatenate([geometry.wisp4c(30, root=(1.2 * w, 16.0, 0.0), spin=0.9 * (w % 2))
                          for w in range(6)])
    pin = (np.arange(len(pos)) % 30) < 3
    return ArraySource(pos, np.arange(7) * 30, pinned=pin, root_radius=0.08, tip_radius=0.05)


def test_summary_min_distance_per_frame_is_each_frames_minimum(monkeypatch):
    """summary.json's contact.min_distance_per_frame and min_distance against brute force
    over each frame's positions (12 frames of the shaken ``turned_wisps_source``, out of
    contact for 4 frames, then in it), on 1-3 ranks.  Main reported the closest candidate
    of the contact's broad phase: frames 1-3 wrong (or null)."""
    frames = 12
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: turned_wisps_source())
    cfg = touching_wisps_config(frames)
    cfg.physics.strand_contact_mode = "ccd"
    sim = simmod.build_simulator(cfg.validate(), comm=comm)
    X_rest = np.concatenate(comm.allgather(sim.scene.x_rest))
    d0 = sim.integrator.strand.d0
    X, summ = frames_run(sim, frames)
    ok, msg = True, ""
    if comm.rank == 0:
        want = [brute_force_min(x, X_rest, d0) for x in X[1:]]
        got = summ["contact"]["min_distance_per_frame"]
        ok = all(g is not None and abs(g - w) <= 1e-12 * w for g, w in zip(got, want)) \
            and summ["contact"]["min_distance"] == pytest.approx(min(want), rel=1e-12) \
            and min(want[:3]) > d0 > min(want)        # out of contact, then in it
        msg = f"reported {got}, brute force {want}"
    ok, msg = comm.bcast((ok, msg))
    assert ok, msg


def test_limiter_takes_a_nonlinear_update_whole_or_the_linear_one(monkeypatch):
    """limit_step(x, target, linear): a target whose path no pair would cut comes back
    unchanged; one whose path is cut anywhere is replaced by the limited linear update
    (its per-vertex fractions of a retracted step would stretch the edges), the same
    positions as limit_step(x, linear); the decision is the same on every rank."""
    sim = six_wisps_ccd(monkeypatch)
    try:
        st, sc = sim.integrator.strand, sim.scene
        x = sim.integrator.x.copy()
        wisp_of = np.repeat(np.arange(6), 30)[sc.first_vertex:sc.first_vertex + sc.nv]
        free = ~sc.pinned[:, None]
        rng = np.random.default_rng(11)
        # a small step: no pair comes near (the wisps are 0.9 cm apart, d0 0.12 cm)
        small = x + free * rng.normal(scale=1e-3, size=x.shape)
        nonlinear = small + free * 1e-4          # stands for a retraction of the step
        assert np.array_equal(st.limit_step(x, nonlinear, small), nonlinear)
        assert not st.replaced and not st.last_cut
        # wisps pushed into each other: the path is cut
        push = np.where(wisp_of % 2 == 0, 1.0, -1.0)[:, None] * np.array([0.6, 0.0, 0.0]) * free
        linear = x + push
        nonlinear = linear + free * rng.normal(scale=1e-3, size=x.shape)
        replaced_before = sum(st.updates_replaced.sums)
        got = st.limit_step(x, nonlinear, linear)
        assert st.replaced and st.last_cut and sum(st.updates_replaced.sums) == replaced_before + 1
        want = st.limit_step(x, linear)
        assert not st.replaced and st.last_cut
        assert comm.allreduce(int(np.sum(got != nonlinear))) > 0
        np.testing.assert_array_equal(got, want)
    finally:
        sim.close()


def test_newton_to_a_tolerance_in_ccd_mode_takes_the_configured_update():
    """The demo hairball cut to 10 wisps in ccd mode (its first iterate and projection
    off, as the studies measure it), Newton to 1e-6 wisp lengths (exact_or_analytic,
    shifted fallback, exact steps kept, cap 30, no cutback), 6 frames: with the
    corotational update every frame reaches the tolerance (measured 26 11 10 9 9 8
    iterations on 1-3 ranks; frame 0, from rest, at the step's minimum: its indefinite
    wisps are shifted, docs/newton.md "Avoiding the saddle"; 23 while the ladder's shifts
    left some wisp blocks indefinite, "Frame 0 wisp by wisp"; before the shifts, 21
    iterations stopped on a saddle of G, refused, and frames 1-5 took 16 10 9 8 7; ccd
    forced the linear update before, which converged in none of them, 30 each), with no
    crossing, on 1-3 ranks within 1e-7 of 1 rank (converged frames: measured 4e-9 on
    10 frames); at a fixed count ccd keeps the linear update (the same positions as
    newton_update = "linear")."""
    def config(update, tol=1e-6, iterations=30):
        cfg = load_config(ROOT / "configs" / "hairball_demo.toml")
        cfg.scene.n_wisps = 10
        cfg.time.frames = 6
        cfg.time.length_projection = False
        cfg.solver.filter = "exact_or_analytic"
        cfg.solver.exact_fallback = "shifted"
        cfg.solver.exact_stay = True
        cfg.time.newton_update = update
        cfg.time.newton_iterations = iterations
        cfg.time.newton_increment_tol = tol
        cfg.time.max_substeps = 1
        return cfg.validate()

    X, summ = frames_run(simmod.build_simulator(config("corotational"), comm=comm), 6)
    serial = frames_run(simmod.build_simulator(config("corotational"), comm=MPI.COMM_SELF), 6)[0] \
        if comm.rank == 0 else None
    lin = frames_run(simmod.build_simulator(config("linear"), comm=comm), 6)[1]
    fixed = [frames_run(simmod.build_simulator(config(u, None, 3), comm=comm), 2)[0]
             for u in ("corotational", "linear")]
    ok, msg = True, ""
    if comm.rank == 0:
        off = np.arange(11) * (len(X[0]) // 10)
        crossings = [count_crossings(X[k], X[k + 1], off)["crossings"] for k in range(len(X) - 1)]
        err = float(np.abs(X[-1] - serial[-1]).max() / np.abs(serial[-1]).max())
        ok = summ["newton_converged"] == [True] * 6 and summ["newton_saddle"] == [0] * 6 \
            and max(summ["newton_iterations"]) <= 26 \
            and not any(lin["newton_converged"]) and sum(crossings) == 0 \
            and np.array_equal(fixed[0][-1], fixed[1][-1]) and err < 1e-7 \
            and len(summ["contact"]["limiter_replaced_updates_per_frame"]) == 6
        msg = (f"{comm.size} ranks: corotational {summ['newton_iterations']} {summ['newton_converged']}, "
               f"linear {lin['newton_iterations']} {lin['newton_converged']}, crossings {crossings}, "
               f"relative difference to 1 rank {err:.1e}")
        print("\n" + msg)
    ok, msg = comm.bcast((ok, msg))
    assert ok, msg


def test_cut_nonlinear_updates_are_replaced_in_the_run(monkeypatch):
    """The six touching wisps in ccd mode with a Newton tolerance and the edge retraction
    (contact active from frame 3 on, the limiter cutting): every Newton update reaches the
    limiter with its linear step, and the limiter replaced some (a cut retracted step is
    never kept; measured 0 0 0 1 2 4 per frame)."""
    sim = six_wisps_ccd(monkeypatch, 6, newton_update="edge_retraction", newton_iterations=6,
                        newton_increment_tol=1e-6, max_substeps=1)
    st = sim.integrator.strand
    linear_given = []
    limit = st.limit_step

    def spy(x, target, linear=None):
        linear_given.append(linear is not None)
        return limit(x, target, linear)

    monkeypatch.setattr(st, "limit_step", spy)
    summ = frames_run(sim, 6)[1]
    replaced = summ["contact"]["limiter_replaced_updates_per_frame"] if comm.rank == 0 else None
    replaced = comm.bcast(replaced)
    assert linear_given and all(linear_given), linear_given
    assert sum(replaced) > 0, replaced


def test_a_cut_step_is_measured_by_its_full_step(monkeypatch):
    """ccd mode with a tolerance: a limiter that cuts the k-th update of a frame to 10^-k
    of its length makes the steps shrink 10x per iteration without the iterate moving.
    The stop measures the full Newton step, so no frame is called converged, and
    newton_increment reports a step above the tolerance (measured by the cut step, both
    said converged after a few iterations)."""
    sim = six_wisps_ccd(monkeypatch, 2, newton_update="linear", newton_iterations=8,
                        newton_increment_tol=1e-6, max_substeps=1)
    st = sim.integrator.strand
    calls = []

    def shrinking(x, target, linear=None):
        calls.append(1)
        st.replaced, st.last_cut = False, True
        return x + 10.0 ** -(1 + (len(calls) - 1) % 8) * (target - x)

    monkeypatch.setattr(st, "limit_step", shrinking)
    summ = frames_run(sim, 2)[1]
    converged, increments = comm.bcast((summ["newton_converged"], summ["newton_increment"])
                                       if comm.rank == 0 else None)
    assert converged == [False, False], (converged, increments)
    assert all(d > 1e-6 for d in increments), increments


def test_contact_frames_converge_within_a_cap_of_100(monkeypatch):
    """The six touching wisps (3 pinned vertices), ccd, Newton to 1e-6 with the
    recommended settings and no cutback: frames 3-5 have active contact pairs and need
    29-71 iterations (measured 12 15 10 64 29 30 on 1 rank, frame 3 taking 62 on 2 and 71 on
    3 since the clusters' LU is of the point matrix, scenes56; 64 / 64 / 62 with the BAIJ LU:
    the contact frames amplify the partition's round-off; before the ladder shifts were
    added to each wisp's least shift (docs/newton.md "Frame 0 wisp by wisp"): 57 41 36 /
    80 45 33, then 61 29 30), so a cap of 100 reaches the tolerance in every frame; at the cap of 30
    they did not (docs/newton.md "Thirteenth round"), and before the straight stem's
    twist was faded no frame did.  Frame 0 reaches it on a saddle of A + C spread over
    three contact-coupled wisps (-0.517 M/dt^2, every wisp block definite): refused
    (docs/newton.md "A saddle over contact-coupled wisps"; main had called it converged);
    frame 3 had once stopped on a wisp's saddle (refused too)."""
    sim = six_wisps_ccd(monkeypatch, 6, solver=(("filter", "exact_or_analytic"), ("exact_fallback", "shifted"),
                                                 ("exact_stay", True)),
                        newton_iterations=100, newton_increment_tol=1e-6, max_substeps=1,
                        newton_update="corotational")
    summary = frames_run(sim, 6)[1]
    s = comm.bcast(summary if comm.rank == 0 else None)         # rank 0's: every rank asserts
    its = s["newton_iterations"]
    # frame 0 stops on the coupled saddle (refused); a frame may stop on a saddle of G
    # (frame 3 had, wisp 5, -0.43): refused; every other frame converges
    assert all(c or n == 1 for c, n in zip(s["newton_converged"], s["newton_saddle"])), (its, s["newton_saddle"])
    assert s["newton_converged"][:3] == [False, True, True] and s["newton_saddle"][0] == 1, its
    assert sum(s["newton_saddle"]) <= 2 and max(its[3:]) <= 72, its
    assert max(its[3:]) > 30                        # contact frames: beyond the old cap
    assert sum(s["contact"]["pairs_per_frame"][3:]) > 0


def test_limiter_drops_the_pairs_its_hulls_keep_apart(monkeypatch):
    """The limiter's pair test runs only on the pairs whose hulls (each segment's ends at
    the step's start and at start + residual) a separating axis does not prove md apart
    (compiled_ccd.order_candidates with ``hulls``): on random pushes of the six wisps the
    positions, limited vertices and rounds equal those of the boxes alone bit for bit,
    under 90% of the pairs are tested (83% here, 37% on the 2K hairball), every pair
    whose path comes within md (sampled, at beta = 1 and at the limited fractions) is
    among them, and on 2 and 3 ranks the tested pairs are those of the whole scene on
    one rank."""
    from lc_petsc.elements import compiled_ccd
    sim = six_wisps_ccd(monkeypatch)
    try:
        st, sc = sim.integrator.strand, sim.scene
        assert not st.self_contact
        md, n = st.min_separation * st.d0, sc.nv
        order = compiled_ccd.order_candidates
        kept, hulls_on = [], [True]

        def recorded(ij, n_local, gv, lo, hi, shrink, free, hulls=None):
            out = order(ij, n_local, gv, lo, hi, shrink, free,
                        **({"hulls": hulls} if hulls_on[0] and hulls is not None else {}))
            kept.append(np.stack([gv[out[0][out[2]]], gv[out[1][out[2]]]], axis=1))
            return out
        monkeypatch.setattr(compiled_ccd, "order_candidates", recorded)
        rng = np.random.default_rng(8)
        x = sim.integrator.x.copy()
        wisp_of = np.repeat(np.arange(6), 30)
        seg = np.array([v for v in range(6 * 30) if v % 30 != 29], np.int64)
        pinned = np.concatenate(comm.allgather(sc.pinned))
        counts, limited = np.zeros(2, int), 0
        for trial in range(4):
            push = np.where(wisp_of % 2 == 0, 1.0, -1.0)[:, None] * np.array([0.25, 0.0, 0.0])
            D = rng.normal(scale=0.08, size=(6 * 30, 3)) + push * (1 + trial % 2)
            target = x + D[sc.first_vertex:sc.first_vertex + n]
            got = []
            for on in (False, True):
                hulls_on[0] = on
                before = (st.limited_vertices.sums[-1], st.limit_rounds.sums[-1])
                got.append((st.limit_step(x, target), st.limited_vertices.sums[-1] - before[0],
                            st.limit_rounds.sums[-1] - before[1]))
            np.testing.assert_array_equal(got[0][0], got[1][0])
            assert got[0][1:] == got[1][1:]
            limited += got[1][1]
            boxes, hull = kept[-2], kept[-1]
            counts += comm.allreduce(np.array([len(boxes), len(hull)]))
            assert set(map(tuple, hull.tolist())) <= set(map(tuple, boxes.tolist()))
            pairs, Xs, Es, Ts = comm.gather(hull), comm.gather(x), comm.gather(got[1][0]), comm.gather(target)
            if comm.rank == 0:
                S, E, T = np.concatenate(Xs), np.concatenate(Es), np.concatenate(Ts)
                tested = {tuple(p) for p in np.concatenate(pairs).tolist()}
                # every pair that comes within md on either path is tested
                i, j = np.triu_indices(len(seg), 1)
                moving = ~(pinned[seg] & pinned[seg + 1])       # pinned pairs move rigidly
                other = (wisp_of[seg[i]] != wisp_of[seg[j]]) & (moving[i] | moving[j])
                i, j = i[other], j[other]
                for end in (T, E):
                    dmin = np.full(len(i), np.inf)
                    for t in np.linspace(0.0, 1.0, 41):
                        X = S + t * (end - S)
                        dmin = np.minimum(dmin, distance(np.stack([X[seg[i]], X[seg[i] + 1], X[seg[j]],
                                                                   X[seg[j] + 1]], axis=1)))
                    need = {(seg[a], seg[b]) for a, b in zip(i[dmin < md], j[dmin < md])}
                    assert need <= tested, (trial, len(need - tested))
                # the whole scene on one rank tests the same pairs
                lo, hi = compiled_ccd.field_boxes(S, T - S, seg, 0.0, md)
                ij = compiled_ccd.box_pairs(lo, hi, group=wisp_of[seg], n_local=len(seg))
                P = [np.stack([a[seg], a[seg + 1]], axis=1) for a in (S, T, S)]
                free = np.stack([~pinned[seg], ~pinned[seg + 1]], axis=1)
                ci, cj, near, _ = order(ij, len(seg), seg, lo, hi, 0.0, free, hulls=(*P, 0.0, md))
                assert {(a, b) for a, b in zip(seg[ci[near]], seg[cj[near]])} == tested, trial
            x = got[1][0]
        print(f"\npairs tested: boxes alone {counts[0]}, with the hulls {counts[1]}; limited vertices {limited}")
        assert counts[1] < 0.9 * counts[0] and comm.bcast(limited) > 0
    finally:
        sim.close()
