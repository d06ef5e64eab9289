"""scripts/dump_system.py (a run's Newton systems as .npz without PETSc) and
scripts/pc_prototype.py (SciPy PCG and preconditioner prototypes) on the touching wisps:
the dump equals PETSc's matrices, the prototype's per-wisp blocks are the cluster
preconditioner's fallback, and its PCG takes the run's CG iterations
(docs/contact_solver.md, "Preconditioner prototypes on a dumped system")."""

import importlib.util
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from mpi4py import MPI

import lc_petsc.simulator as simmod
from sim_helpers import touching_wisps_config, touching_wisps_source
from test_contact_pc import dense
from test_self_contact import smash_simulator, smash_source

ROOT = Path(__file__).resolve().parents[2]
#: the cluster preconditioner with one wisp per cluster and all the coupling
#: weight asked for: it falls back to the per-wisp blocks at every set-up with contact
FALLBACK = "-ksp_rtol 1e-4 -lc_contact_pc clusters -lc_cluster_max_wisps 1 -lc_cluster_min_captured 1"


def script(name):
    spec = importlib.util.spec_from_file_location(f"script_{name}", ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def config():
    cfg = touching_wisps_config(1, options=FALLBACK)
    cfg.time.carry_with_head = False        # test_contact_pc.py: the first frame's pairs fall back
    return cfg


def simulator(monkeypatch, scene):
    """After its run: the touching wisps (1 frame), or two interleaved curls crushed
    with self-contact (test_self_contact.py; 2 frames), with :data:`FALLBACK`."""
    if scene == "touching":
        monkeypatch.setattr(simmod, "source_from_config", lambda *a: touching_wisps_source())
        sim = simmod.build_simulator(config(), comm=MPI.COMM_SELF)
        sim.run()
    else:
        monkeypatch.setattr(simmod, "source_from_config", lambda *a: smash_source(2, 0.9))
        sim = smash_simulator(MPI.COMM_SELF, 2, True, options=FALLBACK)
        sim.run(2)
    return sim


@pytest.mark.parametrize("scene", ["touching", "curls_self_contact"])
def test_dump_equals_petsc_and_prototype_blocks_equal_the_fallback(monkeypatch, tmp_path, scene):
    dump, proto = script("dump_system"), script("pc_prototype")
    self_contact = scene != "touching"
    sim = simulator(monkeypatch, scene)
    try:
        st = sim.solver.clusters.stats
        assert st["fallback"] and st["largest"] <= 1 and (st["self_contact_wisps"] > 0) == self_contact, st
        op, _ = sim.solver.ksp.getOperators()
        A, C = op.getPythonContext().A, op.getPythonContext().C
        rng = np.random.default_rng(1)
        b = rng.standard_normal(A.getSize()[0])
        x = rng.standard_normal((A.getSize()[0] // 3, 3))
        rows = 3 * np.diff(sim.scene.offsets)
        dump.save_system(tmp_path / "s.npz", dump.to_bsr(A), dump.to_bsr(C), b, x, rows, 7, 90, 2)
        got = dump.load_system(tmp_path / "s.npz")
        # the .npz matrices are PETSc's, entry for entry
        np.testing.assert_array_equal(got["A"].toarray(), dense(A))
        np.testing.assert_array_equal(got["C"].toarray(), dense(C))
        np.testing.assert_array_equal(got["b"], b)
        np.testing.assert_array_equal(got["x"], x)
        np.testing.assert_array_equal(got["wisp_rows"], rows)
        assert (got["iterations"], got["frame"], got["newton_it"]) == (7, 90, 2)
        inside = np.repeat(np.arange(len(rows)), rows)
        Cd = dense(C)
        same = inside[:, None] == inside[None, :]
        # self-contact puts blocks of C inside a wisp (the fallback factors them with its
        # band); without it C only couples wisps
        assert (np.abs(Cd[same]).max() > 0) == self_contact
        assert np.abs(Cd[~same]).max() > 0
        # the prototype's per-wisp blocks applied = the cluster PC's fallback applied
        _, lu = proto.block_jacobi(got["A"], got["C"], rows)
        pc = sim.solver.ksp.getPC()
        u, v = op.createVecs()
        for _ in range(2):
            r = rng.standard_normal(len(b))
            u.array[:] = r
            pc.apply(u, v)
            np.testing.assert_allclose(lu.solve(r), v.array, rtol=0, atol=1e-9 * np.abs(v.array).max())
        # and it is not A's blocks alone when self-contact puts blocks inside a wisp
        Ad = dense(A)
        alone = np.linalg.solve(Ad, r)
        assert (np.abs(alone - v.array).max() > 1e-6 * np.abs(v.array).max()) == self_contact
        u.destroy()
        v.destroy()
    finally:
        sim.close()


def test_dump_records_the_runs_systems_and_pcg_takes_the_runs_iterations(monkeypatch, tmp_path):
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: touching_wisps_source())
    dump, proto = script("dump_system"), script("pc_prototype")
    paths = dump.dump(config(), tmp_path, comm=MPI.COMM_SELF)
    assert [p.name for p in paths] == [f"system_00000_{i}.npz" for i in range(3)]
    runs = []
    for p in paths:
        s = dump.load_system(p)
        runs.append(s["iterations"])
        K = (s["A"] + s["C"]).tocsr()
        _, lu = proto.block_jacobi(s["A"], s["C"], s["wisp_rows"])
        coeffs = []
        x, its, red = proto.pcg(K, s["b"], lu.solve, rtol=1e-4, coeffs=coeffs)
        # PETSc's CG and the prototype's: the same iterations but for round-off near the
        # stopping test
        assert abs(its - s["iterations"]) <= 1, (its, s["iterations"])
        assert red <= 1e-4
        assert np.linalg.norm(s["b"] - K @ x) <= 1e-2 * np.linalg.norm(s["b"])
        # the Ritz values from CG's coefficients lie in the spectrum of B^-1 K, and the
        # largest is its largest (CG finds the extremes first)
        eig = np.sort(np.linalg.eigvals(lu.solve(K.toarray())).real)
        ritz = proto.ritz_values(coeffs)
        assert len(ritz) == its and eig[0] * (1 - 1e-8) <= ritz[0] and ritz[-1] <= eig[-1] * (1 + 1e-8)
        assert abs(ritz[-1] - eig[-1]) <= 1e-3 * eig[-1] or its < 5, (ritz[-1], eig[-1])
    assert sum(runs) > 30, runs        # measured: 3, 23, 20 (CG has work to do)
    with pytest.raises(ValueError, match="one rank"):
        dump.dump(config(), tmp_path, comm=SimpleNamespace(size=2))


def test_prototype_refuses_unknown_variants():
    with pytest.raises(ValueError, match="unknown variant"):
        script("pc_prototype").main(["x.npz", "--variants", "gauss-seidel"])
    for bad in ("add", "add:aggx", "blocks:agg", "ilu:agg", "add:agg@8", "add:agg@0x2", "ilu@8x2"):
        with pytest.raises(ValueError, match="unknown variant"):
            script("pc_prototype").parse_variant(bad)
    assert script("pc_prototype").parse_variant("bnn:aggrots") == ("bnn", "aggrot", True, None, None)
    assert script("pc_prototype").parse_variant("add:chunk@16x1") == ("add", "chunk", False, 16, 1)
