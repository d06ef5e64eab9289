"""Self-contact (physics.strand_self_contact): segments of one wisp that are not
neighbours along it take part in the contact, the ccd limiter and the rest-pose check.
A curl smashed into itself never crosses itself (the control without self-contact
does), the pair selection matches brute force, the rest-pose check names a same-wisp
overlap, and 2 / 3 ranks follow 1 rank.  tests/test_mpi_launch.py runs the mpi tests
under mpiexec."""

import re

import numpy as np
import pytest
from mpi4py import MPI

import lc_petsc.simulator as simmod
from lc_petsc.config import (ConfigError, MaterialConfig, PhysicsConfig, SceneConfig, SimConfig,
                             SolverConfig, TimeConfig)
from lc_petsc.contact import NEIGHBOUR_GAP, StrandContact
from lc_petsc.contact_pc import ClusterPC, block_rows
from lc_petsc.crossings import count_crossings
from lc_petsc.elements.compiled_ccd import box_pairs
from lc_petsc.elements.segment_contact import distance
from lc_petsc.errors import RestPoseOverlapError
from lc_petsc.scene import geometry
from lc_petsc.scene.sources import ArraySource
from test_contact_pc import dense
from sim_helpers import frames_run

comm = MPI.COMM_WORLD
NV = 30             # vertices per smashed wisp: a 4C helix without its stem, 6 turns 0.5 cm apart
D0 = 0.1            # contact thickness (cm): the coil's closest non-neighbour pair is 0.49 cm
SQUEEZE = 30.0      # 1/s: the free vertices move towards the root's plane at SQUEEZE s cm/s


def smash_source(n_wisps=1, spacing=3.0):
    """``n_wisps`` 4C helices along -y, ``spacing`` cm apart (3: they never touch each
    other; 0.9: their coils of diameter 1 cm interleave, in phase), nothing
    pinned: a pinned stem is the limiter's known gap (docs/contact.md: a free vertex held
    back moves with the fitted field, into a pinned segment that does not)."""
    X = np.concatenate([geometry.wisp4c(NV + 3, root=(spacing * w, 16.0, 0.0))[3:]
                        for w in range(n_wisps)])
    return ArraySource(X, np.arange(n_wisps + 1) * NV, pinned=np.zeros(len(X), bool),
                       root_radius=0.08, tip_radius=0.05)


def smash_config(frames, self_contact, potential="penalty", options=""):
    return SimConfig(scene=SceneConfig(kind="straight"), material=MaterialConfig(youngs_modulus=2e6),
                     physics=PhysicsConfig(terms=("stretch", "bend", "twist", "strand_collision"),
                                           strand_thickness=D0, strand_stiffness=1e4,
                                           strand_contact_mode="ccd", strand_self_contact=self_contact,
                                           strand_contact_potential=potential),
                     time=TimeConfig(frames=frames),
                     solver=SolverConfig(options="-ksp_rtol 1e-12 -ksp_max_it 5000 " + options))


def smash_simulator(c, frames, self_contact, potential="penalty", options=""):
    """The simulator whose vertices start moving along the axis towards their wisp's
    middle at SQUEEZE times their distance from it: each coil is crushed within 1-2
    frames (``options``: more solver options)."""
    sim = simmod.build_simulator(smash_config(frames, self_contact, potential, options), comm=c)
    sc = sim.scene
    v = np.zeros_like(sim.x)
    for w in range(sc.n_wisps):
        a, b = sc.offsets[w], sc.offsets[w + 1]
        v[a:b, 1] = SQUEEZE * (sim.x[a:b, 1].mean() - sim.x[a:b, 1])
    sim.integrator.v = v
    return sim


def run_smash(c, frames, self_contact, n_wisps=1):
    """Positions at the start and after each frame (gathered on rank 0) and the summary
    of :func:`smash_simulator`."""
    return frames_run(smash_simulator(c, frames, self_contact), frames)


def self_crossings(X, n_wisps=1):
    off = np.arange(n_wisps + 1) * NV
    return [count_crossings(X[k], X[k + 1], off, self_contact=True)["crossings"] for k in range(len(X) - 1)]


@pytest.fixture
def smash(monkeypatch):
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: smash_source())


def test_smashed_curl_never_crosses_itself(smash):
    """One curl crushed along its axis in 1-2 frames, ccd mode: with self-contact no
    step crosses (counted between all segments of the wisp sharing no vertex); the
    control without self-contact passes its turns through each other."""
    X, summ = run_smash(MPI.COMM_SELF, 6, self_contact=True)
    c = summ["contact"]
    crossings = self_crossings(X)
    print(f"\nself-contact: crossings per step {crossings}, pairs per frame {c['pairs_per_frame']}, "
          f"min distance {c['min_distance']:.3g} cm, limited vertices {c['limited_vertices_per_frame']}, "
          f"held on the frame paths {c['frame_path_held_vertices_per_frame']}")
    assert sum(crossings) == 0, crossings
    assert max(c["pairs_per_frame"]) > 5                # the turns were pressed together
    assert max(c["limited_vertices_per_frame"] + c["frame_path_held_vertices_per_frame"]) > 0
    X0, summ0 = run_smash(MPI.COMM_SELF, 6, self_contact=False)
    control = self_crossings(X0)
    print(f"control (no self-contact): crossings per step {control}")
    assert sum(control) > 20, control
    assert sum(summ0["contact"]["pairs_per_frame"]) == 0


@pytest.mark.parametrize("potential", ["penalty", "barrier"])
def test_cluster_pc_holds_a_lone_wisps_self_contact(smash, potential):
    """A curl crushed into itself, touching no other wisp: the cluster preconditioner
    (the default) factors the wisp's band together with its own self-contact cross
    blocks (a one-wisp cluster), so it is the exact inverse of A + C and CG at rtol
    1e-12 takes 1-2 iterations.  Before, a wisp in no cluster kept only its band (the
    self-contact blocks dropped): 26-74 (penalty) and 37-133 (barrier) iterations per solve here, and a 60-wisp
    barrier scene with self-contact hit CG's 1,000-iteration cap (docs/contact.md,
    "Self-contact")."""
    sim = smash_simulator(MPI.COMM_SELF, 4, True, potential)
    try:
        pairs = []
        for _ in range(4):
            sim.step()
            pairs.append(sim.strand.last_pairs)
        its = sim.solver.iterations
        print(f"\n{potential}: CG iterations {its}, pairs per frame {pairs}")
        assert min(pairs[1:]) > 5                    # the turns are pressed together
        assert max(its) <= 2, its
        ctx = sim.solver.clusters
        assert ctx.stats["self_contact_wisps"] == 1 and ctx.stats["clusters"] == 1, ctx.stats
        # the last set-up's P^-1 against the dense solve of A + C
        op, _ = sim.solver.ksp.getOperators()
        K = dense(op.getPythonContext().A) + dense(op.getPythonContext().C)
        r = np.random.default_rng(1).standard_normal(len(K))
        x, y = op.createVecs()
        x.array[:] = r
        sim.solver.ksp.getPC().apply(x, y)
        sol = np.linalg.solve(K, r)
        assert np.abs(y.array - sol).max() <= 1e-8 * np.abs(sol).max()
        x.destroy()
        y.destroy()
    finally:
        sim.close()


def test_touching_curls_crushed_together(monkeypatch):
    """Two interleaved curls crushed at once: the contact clusters (the default
    preconditioner) hold self-contact cross blocks that fall on a wisp's band (segments
    two apart), summed into one block each (a repeated CSR column made the cluster
    factor indefinite: DIVERGED_INDEFINITE_PC in the first solve); no crossing of any
    kind."""
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: smash_source(2, 0.9))
    X, summ = run_smash(MPI.COMM_SELF, 5, True, n_wisps=2)
    off = [0, NV, 2 * NV]
    assert sum(self_crossings(X, 2)) == 0
    assert sum(count_crossings(X[k], X[k + 1], off)["crossings"] for k in range(5)) == 0
    assert max(summ["contact"]["pairs_per_frame"]) > 20
    assert summ["converged"]


def test_fallback_keeps_each_wisps_self_contact(monkeypatch):
    """Clusters refused (at most 1 wisp each, all of the coupling weight required): the
    set-up falls back to single wisps, but each of the two interleaved curls keeps its
    own self-contact blocks (a one-wisp cluster; before, the fallback dropped them)."""
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: smash_source(2, 0.9))
    sim = smash_simulator(MPI.COMM_SELF, 2, True,
                          options="-lc_cluster_max_wisps 1 -lc_cluster_min_captured 1")
    try:
        sim.run(2)
        fell = [h for h in sim.solver.clusters.history if h["fallback"]]
        assert fell and all(h["captured"] < 1.0 for h in fell)
        for h in fell:
            assert h["clusters"] == 2 and h["largest"] == 1, h         # main: 0 clusters
            assert h["self_contact_wisps"] == 2, h
    finally:
        sim.close()


def test_block_cap_counts_self_contact_blocks(monkeypatch):
    """-lc_cluster_max_blocks caps a cluster's cross blocks, self-contact blocks
    included: two interleaved curls crushed together, cap 200, are one cluster only
    while their pair blocks and both wisps' own blocks fit (then ``most_blocks`` is that
    sum), else two one-wisp clusters.  Before, the own blocks did not count: one
    cluster of 732 blocks (158 between the curls, 307 + 267 their own) at the first
    set-up here."""
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: smash_source(2, 0.9))
    cap = 200
    seen = []
    setup = ClusterPC._setup_clusters

    def counted(self, A, A_loc, C):         # the blocks of C, counted apart from the PC
        setup(self, A, A_loc, C)
        rows, cols, _ = block_rows(C)
        a, b = rows // NV, cols // NV              # wisps of NV vertices each
        seen.append((int((a < b).sum()), np.bincount(a[(a == b) & (rows < cols)], minlength=2),
                     dict(self.stats)))

    monkeypatch.setattr(ClusterPC, "_setup_clusters", counted)
    sim = smash_simulator(MPI.COMM_SELF, 3, True,
                          options=f"-lc_cluster_max_blocks {cap} -lc_cluster_min_captured 0")
    try:
        sim.run(3)
        assert sim.summary()["converged"]
    finally:
        sim.close()
    refused = 0
    for between, own, st in seen:
        joined = between > 0 and between + own.sum() <= cap
        refused += between > 0 and between <= cap < between + own.sum()
        assert st["largest"] == (2 if joined else 1), (between, own, st)
        assert st["most_blocks"] == (between + own.sum() if joined else own.max()), (between, own, st)
    assert refused >= 2, seen        # the case: the pair blocks alone fit, with the own ones not


def random_strands(rng, n_wisps=3, n_vertices=150, step=0.05):
    """Random walks folded into a 1 cm box: (P (m, 2, 3) segments, wisp (m,), arc (m, 2))."""
    P, wisp, arc = [], [], []
    for w in range(n_wisps):
        X = np.cumsum(rng.normal(size=(n_vertices, 3)) * step, axis=0)
        X = np.abs((X + 1.0) % 2.0 - 1.0)             # reflected into [0, 1]^3
        L = np.linalg.norm(np.diff(X, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(L)])
        P.append(np.stack([X[:-1], X[1:]], axis=1))
        wisp.append(np.full(n_vertices - 1, w))
        arc.append(np.stack([s[:-1], s[1:]], axis=1))
    return np.concatenate(P), np.concatenate(wisp), np.concatenate(arc)


def test_self_pairs_against_brute_force():
    """Candidates with self-contact hold every pair closer than d0 of different wisps or
    of one wisp at least NEIGHBOUR_GAP d0 of strand apart, and no neighbour pair."""
    rng = np.random.default_rng(5)
    P, wisp, arc = random_strands(rng)
    d0 = 0.1
    gap = NEIGHBOUR_GAP * d0
    ij = StrandContact.candidates(P, wisp, len(P), d0, arc=arc, min_gap=gap)
    i, j = np.triu_indices(len(P), 1)
    along = np.maximum(arc[j, 0] - arc[i, 1], arc[i, 0] - arc[j, 1])
    same = wisp[i] == wisp[j]
    neighbour = same & (along < gap)
    d = distance(np.concatenate([P[i], P[j]], axis=1))
    close = set(zip(i[(d < d0) & ~neighbour].tolist(), j[(d < d0) & ~neighbour].tolist()))
    found = set(map(tuple, ij.tolist()))
    assert sum(1 for p in close if wisp[p[0]] == wisp[p[1]]) > 50         # self pairs exist
    assert close <= found
    nb = set(zip(i[neighbour].tolist(), j[neighbour].tolist()))
    assert len(nb) > 300 and not (nb & found)
    # the segments sharing a vertex are among the neighbours, and some neighbours do not
    # share one (0.05 cm segments, gap pi / 2 d0 = 0.157 cm: 3 segments between)
    assert all((a, a + 1) in nb for a in range(len(P) - 1) if wisp[a] == wisp[a + 1])
    assert any(b - a > 1 for a, b in nb)
    # without self-contact: the pairs of different wisps, the old selection
    ij0 = StrandContact.candidates(P, wisp, len(P), d0)
    assert np.all(wisp[ij0[:, 0]] != wisp[ij0[:, 1]])
    assert {p for p in found if wisp[p[0]] != wisp[p[1]]} == set(map(tuple, ij0.tolist()))
    # box_pairs directly: all pairs of boxes against brute force, groups and arcs
    lo, hi = P.min(axis=1) - 0.5 * d0, P.max(axis=1) + 0.5 * d0
    touch = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
    want = set(zip(i[touch & ~neighbour].tolist(), j[touch & ~neighbour].tolist()))
    assert set(map(tuple, box_pairs(lo, hi, wisp, arc, gap).tolist())) == want
    with pytest.raises(ValueError, match="arc must be"):
        box_pairs(lo, hi, wisp, arc[:-1], gap)


def test_rest_arc_lengths_of_the_contact(smash):
    """StrandContact's rest arc lengths restart at 0 on every wisp and follow its edges."""
    sim = simmod.build_simulator(smash_config(1, True), comm=MPI.COMM_SELF)
    try:
        st = sim.strand
        X = sim.scene.x_rest
        L = np.linalg.norm(np.diff(X, axis=0), axis=1)[:NV - 1]
        np.testing.assert_allclose(st.seg_arc[:, 0], np.concatenate([[0.0], np.cumsum(L)[:-1]]), atol=1e-12)
        np.testing.assert_allclose(st.seg_arc[:, 1] - st.seg_arc[:, 0], L, rtol=1e-12)
        assert st.self_pairs(len(st.seg) + 2)["arc"][-2:].tolist() == [[0.0, 0.0]] * 2    # ghosts
        assert st.self_pairs(len(st.seg))["min_gap"] == pytest.approx(NEIGHBOUR_GAP * D0)
    finally:
        sim.close()


def folded_source():
    """Wisp 0 a plain helix; wisp 1 a helix squashed to 0.04 cm of rise per turn at rest
    (its turns within d0 = 0.1 cm of each other), 3 cm away."""
    A = geometry.wisp4c(NV + 3, root=(0.0, 16.0, 0.0))[3:]
    B = geometry.wisp4c(NV + 3, root=(3.0, 16.0, 0.0))[3:]
    B[:, 1] = B[0, 1] + (B[:, 1] - B[0, 1]) * 0.08
    return ArraySource(np.concatenate([A, B]), [0, NV, 2 * NV], pinned=np.zeros(2 * NV, bool),
                       root_radius=0.08, tip_radius=0.05)


def test_rest_pose_reports_a_same_wisp_overlap(monkeypatch):
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: folded_source())
    with pytest.raises(RestPoseOverlapError) as err:
        simmod.build_simulator(smash_config(1, True), comm=MPI.COMM_SELF)
    msg = str(err.value)
    # brute force over wisp 1's pairs sharing no vertex (edges 0.6 cm > pi / 2 d0)
    X = folded_source().positions
    a, b = np.triu_indices(NV - 1, 2)
    a, b = a + NV, b + NV
    d = distance(np.stack([X[a], X[a + 1], X[b], X[b + 1]], 1))
    assert d.min() < D0
    assert f"{int((d < D0).sum())} pair(s) of segments of different wisps or of one wisp" in msg
    m = re.search(r"wisp 1 segment \(vertices (\d+), \d+\) and wisp 1 segment \(vertices (\d+), "
                  r"\d+\), ([0-9.e-]+) cm apart", msg)
    assert m, msg
    va, vb = int(m.group(1)), int(m.group(2))
    assert distance(X[[va, va + 1, vb, vb + 1]][None])[0] == pytest.approx(d.min(), rel=1e-12)
    assert float(m.group(3)) == pytest.approx(d.min(), rel=1e-2)
    assert "strand_self_contact" in msg
    # control: without self-contact the same groom passes the check
    simmod.build_simulator(smash_config(1, False), comm=MPI.COMM_SELF).close()
    # the explicit exemption: the squashed turns never interact, the rest do
    cfg = smash_config(1, True)
    cfg.physics.strand_rest_overlap = "exempt"
    sim = simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
    try:
        sim.run(1)
        assert np.all(np.isfinite(sim.x))
        assert sim.summary()["contact"]["pairs_per_frame"] == [0]
    finally:
        sim.close()


def test_self_contact_config_is_checked():
    with pytest.raises(ConfigError, match="strand_self_contact must be true or false"):
        PhysicsConfig(strand_self_contact="yes").validate()
    from lc_petsc.config import config_from_dict
    from lc_petsc.config import keys_without_effect
    data = {"physics": {"terms": ["stretch"], "strand_self_contact": True}}
    warn = keys_without_effect(config_from_dict(data), data)
    assert any("strand_self_contact" in w for w in warn), warn


@pytest.mark.mpi
def test_self_contact_rank_invariance(monkeypatch):
    """Three curls crushed at once, ccd + self-contact: 2 / 3 ranks follow 1 rank (one
    wisp per rank on 3) to 1e-8, none crosses itself, and CG takes 1-2 iterations (each
    curl's self-contact in its own one-wisp cluster)."""
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: smash_source(3))
    X, summ = run_smash(comm, 6, True, n_wisps=3)
    ok, msg = True, ""
    if comm.rank == 0:
        ref, _ = run_smash(MPI.COMM_SELF, 6, True, n_wisps=3)
        err = float(np.abs(X[-1] - ref[-1]).max() / np.abs(ref[-1]).max())
        crossings = self_crossings(X, 3)
        c = summ["contact"]
        # each lone curl is a one-wisp cluster on any rank count: exact, 1-2 CG iterations
        its = summ["ksp_iterations"]
        ok = sum(crossings) == 0 and max(c["pairs_per_frame"]) > 10 and err <= 1e-8 and max(its) <= 2
        msg = (f"{comm.size} rank(s): crossings {crossings}, relative difference to 1 rank {err:.3e}, "
               f"pairs per frame {c['pairs_per_frame']}, CG iterations {its}")
        print("\n" + msg)
    ok, msg = comm.bcast((ok, msg))
    assert ok, msg
