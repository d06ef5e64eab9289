"""Scene builders, partition, rest state, assembly pattern and bad input."""

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc import parallel
from lc_petsc.config import MaterialConfig, PhysicsConfig, SceneConfig, SimConfig, SolverConfig, TimeConfig
from lc_petsc.elements import bend, stretch, twist
from lc_petsc.scene import geometry
from lc_petsc.scene.sources import ArraySource, GeneratedSource
from lc_petsc.scene.state import LocalScene
from lc_petsc.simulator import build_simulator


def test_wisp4c_checked_numbers():
    x = geometry.wisp4c(101)
    assert x.shape == (101, 3)
    L = np.linalg.norm(np.diff(x, axis=0), axis=1)
    assert np.allclose(L[3:], 0.5962, atol=1e-4)          # helix edge ~0.596 cm
    assert 58 < L.sum() < 61                              # about 60 cm
    i = np.arange(5, 99)
    th = bend.angle(np.stack([x[i - 1], x[i], x[i + 1]], 1))
    assert np.allclose(th, 1.906, atol=1e-3)
    i = np.arange(4, 97)
    phi = twist.angle(np.stack([x[i], x[i + 1], x[i + 2], x[i + 3]], 1))
    assert np.allclose(np.abs(phi), 0.2425, atol=1e-4)


def test_partition_whole_wisps_balanced():
    sizes = np.array([101] * 7 + [20, 300, 5, 5, 101])
    for P in (1, 2, 3, 5, 12):
        r = parallel.partition(sizes, P)
        assert r[0] == 0 and r[-1] == len(sizes) and np.all(np.diff(r) >= 1)
        loads = [sizes[r[p]:r[p + 1]].sum() for p in range(P)]
        assert sum(loads) == sizes.sum()
        if P <= 3:
            assert max(loads) - sizes.sum() / P <= sizes.max()


def test_partition_gives_every_rank_a_wisp_or_says_how_many_ranks():
    # One huge wisp would take every rank's share by vertex count alone.
    assert list(parallel.partition(np.array([1000, 4, 4, 4]), 4)) == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match=r"2 wisp\(s\) but the run uses 3 MPI ranks.*mpiexec -n 2"):
        parallel.partition(np.array([50, 50]), 3)


def test_hairball_wisps_independent_of_range():
    src = GeneratedSource("hairball", n_wisps=50, seed=3)
    whole = src.load(0, 50)
    part = src.load(17, 23)
    a, b = whole.offsets[17], whole.offsets[23]
    assert np.array_equal(part.positions, whole.positions[a:b])
    roots = whole.positions[whole.offsets[:-1]]
    assert np.allclose(np.linalg.norm(roots, axis=1), 15.0)
    assert np.all(roots[:, 1] >= 0)
    d = np.linalg.norm(roots[:, None] - roots[None], axis=2) + 100 * np.eye(50)
    assert d.min() > 0.25 * 15 * np.sqrt(2 * np.pi / 50)   # blue-noise-like spacing
    # free vertices start outside the head sphere (radius 15.25)
    free = ~whole.pinned
    assert np.linalg.norm(whole.positions[free], axis=1).min() > 15.25


def test_lumped_mass_and_stiffness():
    mat = MaterialConfig(youngs_modulus=2e9, density=1.3, root_radius=0.2, tip_radius=0.1)
    src = GeneratedSource("wisp4c", root_radius=0.2, tip_radius=0.1)
    b = src.load(0, 1)
    sc, probs = LocalScene.build(b, mat, ["stretch", "bend", "twist"], 1, 0, 101)
    assert not probs
    L = np.linalg.norm(np.diff(b.positions, axis=0), axis=1)
    re = 0.5 * (b.radius[1:] + b.radius[:-1])
    assert np.isclose(sc.mass.sum(), np.sum(1.3 * np.pi * re ** 2 * L))
    assert np.allclose(sc.terms["stretch"].stiffness, 2e9 * np.pi * re ** 2 / L)
    assert sc.bandwidth == 3
    # rest state is the rest pose: every element force vanishes there
    for name, mod in (("stretch", stretch), ("bend", bend), ("twist", twist)):
        t = sc.terms[name]
        g = mod.gradient(t.gather(b.positions), t.rest, t.stiffness)
        assert np.abs(g).max() < 1e-6 * t.stiffness.max()


def _array_cfg():
    return SimConfig(scene=SceneConfig(kind="straight"), physics=PhysicsConfig(terms=("stretch", "bend", "twist")))


def _build_arrays(positions, offsets, **kw):
    """Run LocalScene validation through the simulator's collective path."""
    cfg = _array_cfg()
    src = ArraySource(positions, offsets, **kw)
    b = src.load(0, src.n_wisps)
    _, probs = LocalScene.build(b, cfg.material, ["stretch", "bend", "twist"], src.n_wisps, 0,
                                len(positions))
    parallel.collective_raise(MPI.COMM_SELF, probs)


def _two_wisps():
    x = np.concatenate([geometry.straight(6, direction=(1, 0, 0)),
                        geometry.wisp4c(10, root=(0, 0, 5))])
    return x, np.array([0, 6, 16])


def test_bad_input_short_wisp():
    x, _ = _two_wisps()
    with pytest.raises(ValueError, match=r"wisp 1 has 3 vertices"):
        _build_arrays(x[:9], np.array([0, 6, 9]))


def test_bad_input_zero_length_edge_names_the_edge_even_beside_a_far_wisp():
    x, off = _two_wisps()
    dup = x.copy()
    dup[9] = dup[8]                                  # wisp 1, edge 2: coincident vertices
    with pytest.raises(ValueError, match=r"wisp 1, edge 2: rest length 0.0 is zero \(coincident vertices\)"):
        _build_arrays(dup, off)
    far = x.copy()
    far[6:] += 1e12                  # wisp 1 far away: its edges are below round-off (wisp 0 was blamed)
    with pytest.raises(ValueError, match=r"wisp 1, edge 0: .*below round-off at coordinates of 1e\+12"):
        _build_arrays(far, off)


def test_bad_input_non_finite_position():
    x, off = _two_wisps()
    x[12, 1] = np.nan
    with pytest.raises(ValueError, match=r"wisp 1, vertex 6 \(global vertex 12\).*nan.*not finite"):
        _build_arrays(x, off)


def test_bad_input_negative_stiffness_and_density():
    x, off = _two_wisps()
    with pytest.raises(ValueError, match=r"wisp 1: Young's modulus \(stiffness\) -5.0"):
        _build_arrays(x, off, youngs_modulus=[1e9, -5.0])
    with pytest.raises(ValueError, match=r"wisp 0: density -1.3"):
        _build_arrays(x, off, density=[-1.3, 1.3])
    with pytest.raises(ValueError, match=r"material.density must be a finite positive number, got -1"):
        SimConfig(material=MaterialConfig(density=-1)).validate()
    with pytest.raises(ValueError, match=r"material.youngs_modulus must be a number, got '-1e9'"):
        SimConfig(material=MaterialConfig(youngs_modulus="-1e9")).validate()


def test_bad_config_values():
    with pytest.raises(ValueError, match="physics.terms: unknown term 'bending'"):
        SimConfig(physics=PhysicsConfig(terms=("bending",))).validate()
    with pytest.raises(ValueError, match="time.newton_iterations"):
        SimConfig(time=TimeConfig(newton_iterations=0)).validate()
    with pytest.raises(ValueError, match="solver.filter"):
        SimConfig(solver=SolverConfig(filter="exact")).validate()


def test_strands_file(tmp_path):
    x, off = _two_wisps()
    path = tmp_path / "strands.h5"
    with h5py.File(path, "w") as f:
        f["positions"] = x
        f["wisp_offsets"] = off
        f["radius"] = np.full(len(x), 0.05)
        pinned = np.zeros(len(x), bool)
        pinned[[0, 1, 6, 7]] = True
        f["pinned"] = pinned
    cfg = SimConfig(scene=SceneConfig(kind="file", path=str(path)),
                    physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity")),
                    time=TimeConfig(frames=3))
    sim = build_simulator(cfg, comm=MPI.COMM_SELF)
    try:
        assert sim.n_wisps == 2 and sim.n_vertices == 16
        assert np.array_equal(sim.scene.pinned, pinned)
        sim.run()
        X = sim.gather_positions()
        assert np.all(np.isfinite(X))
        assert np.array_equal(X[pinned], x[pinned])
        assert X[5, 1] < x[5, 1]            # the free tip fell
    finally:
        sim.close()
    with h5py.File(tmp_path / "bad.h5", "w") as f:
        f["positions"] = x
    with pytest.raises(ValueError, match="missing dataset /wisp_offsets"):
        build_simulator(SimConfig(scene=SceneConfig(kind="file", path=str(tmp_path / "bad.h5"))),
                        comm=MPI.COMM_SELF)
