"""Rest-pose check of the intersection-free contact: generated hairballs are in phase
and clear of the contact thickness; an interlocked groom is reported with its worst
pair, and runs only with the explicit exemption."""

import numpy as np
import pytest
from mpi4py import MPI

import lc_petsc.simulator as simmod
from lc_petsc.config import (MaterialConfig, PhysicsConfig, SceneConfig, SimConfig, TimeConfig)
from lc_petsc.contact import StrandContact
from lc_petsc.elements.segment_contact import distance
from lc_petsc.errors import RestPoseOverlapError, StartOverlapError
from lc_petsc.scene import geometry
from lc_petsc.scene.sources import ArraySource, GeneratedSource


@pytest.mark.parametrize("n_wisps, d0, search", [(300, 0.14, 1.5), (2000, 0.14, 0.5)])
def test_generated_hairball_is_clear_of_the_thickness(n_wisps, d0, search):
    """The demo's and the 2K hairball's rest pose (d0 = twice their tip radius), pairs
    searched within ``search`` cm (> d0, so every pair closer than d0 is found; at 2K
    1.5 cm found 25.6M pairs and took 8.2 GB on every rank: 3 ranks ran out of memory
    on a 24 GB machine; 0.5 cm finds 1.4M in 0.7 GB, the same closest pair)."""
    src = GeneratedSource("hairball", n_wisps=n_wisps, seed=1, head_radius=15.0)
    b = src.load(0, n_wisps)
    seg = np.concatenate([np.arange(b.offsets[w], b.offsets[w + 1] - 1) for w in range(n_wisps)])
    wisp = np.repeat(np.arange(n_wisps), 100)
    P = np.stack([b.positions[seg], b.positions[seg + 1]], axis=1)
    ij = StrandContact.candidates(P, wisp, len(P), search)
    d = distance(np.concatenate([P[ij[:, 0]], P[ij[:, 1]]], axis=1))
    assert len(d) > 100                       # neighbours are searched
    assert d.min() >= d0, d.min()


def interlocked_config(overlap="error"):
    return SimConfig(scene=SceneConfig(kind="straight"), material=MaterialConfig(youngs_modulus=1e8),
                     physics=PhysicsConfig(terms=("stretch", "bend", "strand_collision"),
                                           strand_thickness=0.1, strand_contact_mode="ccd",
                                           strand_rest_overlap=overlap),
                     time=TimeConfig(frames=1))


def interlocked_source():
    """Two 4C wisps 0.5 cm apart, phases 0 and 2.5 rad: their coils interlock."""
    X = np.concatenate([geometry.wisp4c(40, root=(0.0, 16.0, 0.0)),
                        geometry.wisp4c(40, root=(0.5, 16.0, 0.0), spin=2.5)])
    return ArraySource(X, [0, 40, 80], n_pinned=3)


def test_interlocked_groom_is_reported_with_its_worst_pair(monkeypatch):
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: interlocked_source())
    with pytest.raises(RestPoseOverlapError) as err:
        simmod.build_simulator(interlocked_config(), comm=MPI.COMM_SELF)
    msg = str(err.value)
    # the worst pair, by brute force over all segment pairs of the two wisps
    X = interlocked_source().positions
    a, b = np.meshgrid(np.arange(39), np.arange(40, 79), indexing="ij")
    d = distance(np.stack([X[a.ravel()], X[a.ravel() + 1], X[b.ravel()], X[b.ravel() + 1]], 1))
    k = int(np.argmin(d))
    n_close = int((d < 0.1).sum())
    assert n_close > 0
    assert f"{n_close} pair(s)" in msg
    import re
    m = re.search(r"wisp 0 segment \(vertices (\d+), \d+\) and wisp 1 segment \(vertices (\d+), "
                  r"\d+\), ([0-9.e-]+) cm apart", msg)
    assert m, msg
    va, vb = int(m.group(1)), int(m.group(2))
    # the reported pair is a closest one (the helices repeat, so several tie)
    assert distance(X[[va, va + 1, vb, vb + 1]][None])[0] == pytest.approx(d[k], rel=1e-12)
    assert float(m.group(3)) == pytest.approx(d[k], rel=1e-2)
    assert "strand_rest_overlap" in msg
    # the explicit exemption builds and runs
    sim = simmod.build_simulator(interlocked_config("exempt"), comm=MPI.COMM_SELF)
    try:
        sim.run(1)
        assert np.all(np.isfinite(sim.x))
    finally:
        sim.close()


def test_rest_overlap_config_is_checked():
    from lc_petsc.config import ConfigError
    with pytest.raises(ConfigError, match="strand_rest_overlap"):
        PhysicsConfig(strand_rest_overlap="ignore").validate()
    with pytest.raises(ConfigError, match="strand_contact_mode"):
        PhysicsConfig(strand_contact_mode="ipc").validate()
    with pytest.raises(ConfigError, match="strand_min_separation"):
        PhysicsConfig(strand_min_separation=1.5).validate()


# ---------------------------------------------------------------- the initial state
#: a row of 6 coils 3 cm apart; wisps 4 and 5 only 0.8 cm apart, in phase (0.171 cm apart at rest)
ROW = [0.0, 3.0, 6.0, 9.0, 12.0, 12.8]


def row_source(n_pinned=3):
    return ArraySource(np.concatenate([geometry.wisp4c(40, root=(x, 16.0, 0.0)) for x in ROW]),
                       np.arange(0, 40 * len(ROW) + 1, 40), n_pinned=n_pinned)


def spun_last_wisp(batch, scene_cfg):
    """A perturbation that turns the last wisp's coil by 2.5 rad about its axis (its
    stem, the pinned vertices, stays): interlocked with wisp 4 (test_interlocked_...)."""
    x = batch.positions.copy()
    for w, sid in enumerate(batch.ids()):
        if sid == len(ROW) - 1:
            a, b = int(batch.offsets[w]), int(batch.offsets[w + 1])
            x[a:b] = geometry.wisp4c(40, root=(ROW[-1], 16.0, 0.0), spin=2.5)
    return x


def start_config(perturbation="jitter", jitter=0.5, self_contact=False):
    cfg = interlocked_config()
    cfg.scene.perturbation, cfg.scene.jitter = perturbation, jitter
    cfg.physics.strand_self_contact = self_contact
    return cfg


@pytest.mark.mpi
def test_a_tangled_initial_state_is_refused_on_every_rank(monkeypatch):
    """Rest pose clear (the rest check passes), the initial state tangled by a
    perturbation: refused on every rank with the same message naming the pair, also
    when the tangled wisps are one rank's only (no hang); the same pose as a groom
    (rest = start) is refused by the rest check.  A restart (check_start=False) is not
    judged on the initial state."""
    comm = MPI.COMM_WORLD
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: row_source())
    monkeypatch.setattr(simmod, "apply_perturbation", spun_last_wisp)
    with pytest.raises(StartOverlapError) as err:
        simmod.build_simulator(start_config(), comm=comm)
    msg = str(err.value)
    assert "initial state (scene.perturbation = \"jitter\", scene.jitter = 0.5 cm) is tangled" in msg
    assert "lower scene.jitter" in msg and "strand_collision" in msg
    import re
    m = re.search(r"(\d+) pair\(s\).*wisp 4 segment \(vertices (\d+), \d+\) and wisp 5 segment \(vertices "
                  r"(\d+), \d+\), ([0-9.e-]+) cm apart", msg)
    assert m, msg
    assert 160 <= int(m.group(2)) < 199 and 200 <= int(m.group(3)) < 239
    # the same verdict on every rank
    assert comm.allgather(msg) == [msg] * comm.size
    # the count against a brute force over the pairs of wisps 4 and 5 (the only ones
    # that come near): Tight-Inclusion on every pair of their segments, rest -> start
    from lc_petsc.crossings import crossing_pairs
    R = row_source().positions
    S = R.copy()
    S[200:240] = geometry.wisp4c(40, root=(ROW[-1], 16.0, 0.0), spin=2.5)
    a, b = (g.ravel() for g in np.meshgrid(np.arange(160, 199), np.arange(200, 239), indexing="ij"))
    quad = lambda X: np.stack([X[a], X[a + 1], X[b], X[b + 1]], 1)      # noqa: E731
    assert distance(quad(R)).min() >= 0.1
    crossed = crossing_pairs(quad(R), quad(S))
    assert int(m.group(1)) == int(crossed.sum()) > 0
    d = distance(quad(S))[crossed].min()
    assert float(m.group(4)) == pytest.approx(d, rel=1e-2)
    # a restart continues from its checkpoint's state: the initial one is not judged
    sim = simmod.build_simulator(start_config(), comm=comm, check_start=False)
    assert sim.strand.start_warning is None
    sim.close()
    # strand_rest_overlap = "exempt": the user runs it anyway, warned with the same finding
    from lc_petsc.diagnostics import term_warnings
    cfg = start_config()
    cfg.physics.strand_rest_overlap = "exempt"
    sim = simmod.build_simulator(cfg, comm=comm)
    try:
        (w,) = [m for m in term_warnings(sim) if "initial state" in m]
        assert w.startswith(msg.split(".  ")[0]) and "run anyway" in w
    finally:
        sim.close()
    # the same pose as a groom's rest is that groom's own shape (0.133 cm apart): it builds
    monkeypatch.setattr(simmod, "source_from_config",
                        lambda *a: ArraySource(S, np.arange(0, 40 * len(ROW) + 1, 40), n_pinned=3))
    assert distance(quad(S)).min() > 0.1
    simmod.build_simulator(start_config(perturbation="none"), comm=comm).close()


def test_real_perturbations_of_an_untangled_start_run(monkeypatch):
    """A jitter that tangles nothing (0.05 cm) and a smash by 0.9 build and run a frame
    with 0 crossings.  Refused: a jitter of 0.5 cm, which tangles the coils with
    themselves (self-contact), and a smash by 0.4, which squeezes the coils' free turns
    through each other (built without the check: 60 crossings in the first step, then 5
    in every step to frame 10, the tangle held)."""
    from lc_petsc.crossings import count_crossings
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: row_source(4))
    smash = start_config("smash", self_contact=True)
    smash.scene.smash_factor = 0.9
    for cfg in (start_config(jitter=0.05, self_contact=True), smash):
        sim = simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
        try:
            x0 = sim.x.copy()
            assert np.abs(x0 - sim.scene.x_rest).max() > 0.04
            sim.run(1)
            assert count_crossings(x0, sim.x, sim.scene.offsets, self_contact=True)["crossings"] == 0
        finally:
            sim.close()
    with pytest.raises(StartOverlapError, match=r"of different wisps or of one wisp.*wisp (\d) segment .* "
                                                r"and wisp \1 segment.*lower scene.jitter below") as e:
        simmod.build_simulator(start_config(jitter=0.5, self_contact=True), comm=MPI.COMM_SELF)
    with pytest.raises(StartOverlapError, match=r"smash_factor = 0.4\) is tangled: .*raise "
                                                r"scene.smash_factor above") as f:
        simmod.build_simulator(start_config("smash", self_contact=True), comm=MPI.COMM_SELF)
    # the values the messages give start untangled (the same seed), and a little beyond them not:
    # each start lies on the straight way to the refused one, which meets its first pair there
    import re
    jitter = float(re.search(r"lower scene.jitter below ([0-9.e-]+) cm \(the same seed: ", str(e.value)).group(1))
    factor = float(re.search(r"raise scene.smash_factor above ([0-9.e-]+) \(towards 1: ", str(f.value)).group(1))
    assert 0.05 < jitter < 0.5 and 0.4 < factor < 0.9, (jitter, factor)
    smash = start_config("smash", self_contact=True)
    for cfg, key, ok, bad in ((start_config(self_contact=True), "jitter", jitter, 1.02 * jitter),
                              (smash, "smash_factor", factor, factor - 0.02 * (1.0 - factor))):
        setattr(cfg.scene, key, ok)
        simmod.build_simulator(cfg, comm=MPI.COMM_SELF).close()
        setattr(cfg.scene, key, bad)
        with pytest.raises(StartOverlapError):
            simmod.build_simulator(cfg, comm=MPI.COMM_SELF)



def test_a_tangling_stretch_is_told_to_come_down_towards_1(monkeypatch):
    """A smash_factor above 1 stretches the wisps: a coil hanging above another lying
    across, stretched by 2, is pushed through it.  The message said "raise
    scene.smash_factor above" a value above 1 (a larger stretch: refused again); the way
    to a smaller perturbation is down towards 1, and the value given (the way's first
    meeting) builds, 2% of its distance from 1 beyond it not.  A squeeze close to 1 was
    told "raise above 1" (the bound rounded up onto a stretch); its bound stays below 1."""
    X = np.concatenate([geometry.wisp4c(40, root=(0.0, 16.0, 0.0)),
                        geometry.wisp4c(40, root=(-2.5, 9.0, 0.0), axis=(1.0, 0.0, 0.0))])
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: ArraySource(X, [0, 40, 80], n_pinned=3))
    cfg = start_config("smash")
    cfg.scene.smash_factor = 2.0
    with pytest.raises(StartOverlapError, match=r"smash_factor = 2\) is tangled: ") as e:
        simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
    import re
    m = re.search(r"lower scene.smash_factor below ([0-9.e-]+) \(towards 1: ", str(e.value))
    assert m, str(e.value)
    factor = float(m.group(1))
    assert 1.0 < factor < 2.0, factor
    for value, tangled in ((factor, False), (factor + 0.02 * (factor - 1.0), True)):
        cfg.scene.smash_factor = value
        if tangled:
            with pytest.raises(StartOverlapError):
                simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
        else:
            simmod.build_simulator(cfg, comm=MPI.COMM_SELF).close()
    squeeze = SceneConfig(perturbation="smash", smash_factor=0.999)
    assert simmod.perturbation_text(squeeze)[1](0.5) == ("raise scene.smash_factor above 0.9995 (towards 1: 50% of "
                                                         "the way from the rest pose to this start is tangle-free)")


def test_a_straightened_start_is_not_judged_on_the_straight_way():
    """``straighten`` unwinds each coil onto a line: the straight way from the coiled rest
    pose passes a hairball wisp's turns through each other (19 pairs for one wisp, which
    the start check counted and refused) where the straight start itself has no tangle.
    Such a start is built and runs a frame in ccd mode with self-contact, with 0 crossings;
    the same wisp jittered by 0.5 cm is still judged (the straight way is the jitter's path)."""
    from lc_petsc.crossings import count_crossings
    cfg = SimConfig(scene=SceneConfig(kind="hairball", n_wisps=1, seed=1, n_pinned=4, perturbation="straighten"),
                    material=MaterialConfig(youngs_modulus=2.5e8),
                    physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity", "strand_collision"),
                                          strand_contact_mode="ccd", strand_self_contact=True),
                    time=TimeConfig(frames=1))
    sim = simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
    try:
        x0 = sim.x.copy()
        assert np.abs(x0 - sim.scene.x_rest).max() > 1.0        # the coil really was unwound
        sim.run(1)
        assert count_crossings(x0, sim.x, sim.scene.offsets, self_contact=True)["crossings"] == 0
    finally:
        sim.close()
    cfg.scene.perturbation, cfg.scene.jitter = "jitter", 0.5
    with pytest.raises(StartOverlapError, match="scene.jitter = 0.5 cm"):
        simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
