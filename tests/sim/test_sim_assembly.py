"""The assembled PETSc matrix and gradient against a brute-force dense reference."""

import dataclasses

import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.assembly import KERNELS
from lc_petsc.config import PhysicsConfig, SceneConfig, SimConfig, SolverConfig, TimeConfig
from lc_petsc.simulator import build_simulator


def _dense_reference(sim, x, dt):
    sc = sim.scene
    n = 3 * sc.nv
    K = np.zeros((n, n))
    for name, t in sc.terms.items():
        H = KERNELS[name].hessian(t.gather(x), t.rest, t.stiffness, filter=sim.assembler.filter)
        idx = (3 * (t.start[:, None] + np.arange(t.k))[:, :, None] + np.arange(3)).reshape(len(t.start), -1)
        for e in range(len(t.start)):
            K[np.ix_(idx[e], idx[e])] += H[e]
    K += np.diag(np.repeat(sc.mass / dt ** 2, 3))
    pin = np.repeat(sc.pinned, 3)
    K[pin, :] = 0
    K[:, pin] = 0
    K[pin, pin] = 1.0
    return K


@pytest.mark.parametrize("kernels", ["compiled", "numpy"])
@pytest.mark.parametrize("mat_type", ["baij", "sbaij", "aij"])
@pytest.mark.parametrize("terms", [("stretch",), ("stretch", "bend"), ("stretch", "bend", "twist")])
def test_matrix_matches_dense_reference(mat_type, terms, kernels):
    cfg = SimConfig(scene=SceneConfig(kind="hairball", n_wisps=2, perturbation="jitter", jitter=0.2),
                    physics=PhysicsConfig(terms=terms + ("gravity",)),
                    solver=SolverConfig(options=f"-mat_type {mat_type} -lc_element_kernels {kernels}"))
    sim = build_simulator(cfg, comm=MPI.COMM_SELF)
    try:
        x = sim.x
        dt = cfg.time.dt
        asm = sim.assembler
        assert asm.b == max(len(t) for t in [terms]) and asm.mat_type == mat_type
        assert asm.kernels == kernels
        # BAIJ values are written in place (probed storage order); SBAIJ / AIJ by CSR call
        assert (asm.mat_block is not None) == (mat_type == "baij")
        g_fused = asm.assemble(x)
        assert np.abs(g_fused - asm.gradient(x)).max() <= 1e-12 * np.abs(g_fused).max()
        asm.add_mass(sim.scene.mass / dt ** 2)
        A = asm.commit()
        v = np.sin(np.arange(3 * sim.scene.nv))
        xv, yv = A.createVecs()
        xv.array[:] = v
        A.mult(xv, yv)
        K = _dense_reference(sim, x, dt)
        ref = K @ v
        assert np.abs(yv.array - ref).max() < 1e-12 * np.abs(ref).max()
        # gradient of G against central differences of G
        it = sim.integrator
        it.xhat = sim.scene.x_rest.copy()
        it.t_next = 0.0
        g = it.gradient(x)
        d = np.random.default_rng(1).normal(size=x.shape)
        d[sim.scene.pinned] = 0
        h = 1e-6
        fd = (it.incremental_potential(x + h * d) - it.incremental_potential(x - h * d)) / (2 * h)
        assert abs(fd - np.sum(g * d)) < 1e-5 * abs(fd)
    finally:
        sim.close()


def test_preconditioning_matrix_is_an_exact_aij_copy():
    """BAIJ operator + separate per-wisp blocks: the PC is built from an AIJ copy (same
    values).  And -lc_pmat_type same (the BAIJ operator itself) reaches the same Newton
    iterate.  (The default, fused blocks, factors the operator itself:
    tests/sim/test_sim_wisp_blocks.py.)
    """
    cfg = SimConfig(scene=SceneConfig(kind="hairball", n_wisps=3, perturbation="jitter", jitter=0.2),
                    physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity")),
                    time=TimeConfig(frames=2))
    separate = "-lc_wisp_blocks separate"
    sims = [build_simulator(dataclasses.replace(cfg, solver=SolverConfig(options=separate)),
                            comm=MPI.COMM_SELF),
            build_simulator(dataclasses.replace(
                cfg, solver=SolverConfig(options=separate + " -lc_pmat_type same")), comm=MPI.COMM_SELF)]
    try:
        A, P = sims[0].solver.ksp.getOperators()
        assert A.getType() == "seqbaij" and P.getType() == "seqaij"
        A2, P2 = sims[1].solver.ksp.getOperators()
        assert P2.getType() == "seqbaij"
        assert sims[0].assembler.pmat_block is not None     # the copy is filled in place
        for sim in sims:
            sim.run()
        v = np.cos(np.arange(A.getSize()[0]))
        xa, ya = A.createVecs()
        xp, yp = P.createVecs()
        xa.array[:] = v
        xp.array[:] = v
        A.mult(xa, ya)
        P.mult(xp, yp)
        assert np.abs(ya.array - yp.array).max() <= 1e-13 * np.abs(ya.array).max()
        assert np.abs(sims[0].x - sims[1].x).max() <= 1e-9 * np.abs(sims[0].x).max()
    finally:
        for sim in sims:
            sim.close()


@pytest.mark.mpi
@pytest.mark.parametrize("blocks", ["fused", "separate"])
def test_in_place_values_refresh_the_preconditioner(blocks):
    """Values written in place into PETSc's arrays (Assembler._probe_value_arrays) must
    reach the factorisation of every later Newton iteration: the per-wisp block Jacobi
    is exact without contact, so after two frames P^-1 (A v) = v holds only if the PC
    was refactored from the current matrix (a stale factor from the build misses it by
    far: the check is made against the frame-0 matrix too)."""
    cfg = SimConfig(scene=SceneConfig(kind="hairball", n_wisps=3, perturbation="jitter", jitter=0.2),
                    physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity")),
                    time=TimeConfig(frames=2),
                    solver=SolverConfig(options=f"-lc_wisp_blocks {blocks}"))
    sim = build_simulator(cfg, comm=MPI.COMM_WORLD)     # also run on 2 and 3 ranks
    try:
        A, P = sim.solver.ksp.getOperators()
        first = A.duplicate(copy=True)
        sim.run()
        A, P = sim.solver.ksp.getOperators()
        xv, yv = A.createVecs()
        zv = yv.duplicate()
        v = np.cos(np.arange(*A.getOwnershipRange()))       # the same vector on any rank count
        xv.array[:] = v
        assert sim.assembler.mat_block is not None
        assert (sim.assembler.pmat_block is not None) == (blocks == "separate")
        pc = sim.solver.ksp.getPC()
        A.mult(xv, yv)
        pc.apply(yv, zv)
        err_now = MPI.COMM_WORLD.allreduce(float(np.abs(zv.array - v).max(initial=0.0)), op=MPI.MAX)
        first.mult(xv, yv)
        pc.apply(yv, zv)
        err_first = MPI.COMM_WORLD.allreduce(float(np.abs(zv.array - v).max(initial=0.0)), op=MPI.MAX)
        assert err_now <= 1e-9 * np.abs(v).max() < 1e-6 * np.abs(v).max() < err_first
        first.destroy()
    finally:
        sim.close()
