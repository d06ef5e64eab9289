"""The coupled operator A + C filled directly (``StrandContact._summed_matrix``, the
operator of ``-lc_contact_pc coupled``: MUMPS, AMG) equals ``MatAXPY``'s sum, for each
matrix type, on any rank count (mpi)."""

import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc

import lc_petsc.simulator as simmod
from sim_helpers import touching_wisps_config, touching_wisps_source

pytestmark = pytest.mark.mpi


@pytest.mark.parametrize("mat_type", ["baij", "sbaij", "aij"])
def test_direct_fill_of_the_coupled_operator_equals_mataxpy(monkeypatch, mat_type):
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: touching_wisps_source())
    # an exact solve of the sum on each type: MUMPS Cholesky (SBAIJ), MUMPS LU (AIJ), and
    # for BAIJ (which MUMPS refuses) PETSc's LU, sequential only, under a redundant PC
    solver = {"sbaij": "-ksp_type preonly -pc_type cholesky -pc_factor_mat_solver_type mumps",
              "aij": "-ksp_type preonly -pc_type lu -pc_factor_mat_solver_type mumps",
              "baij": "-ksp_type preonly -pc_type redundant -redundant_pc_type lu"}[mat_type]
    cfg = touching_wisps_config(2, options=f"{solver} -mat_type {mat_type} -lc_contact_pc coupled")
    sim = simmod.build_simulator(cfg, comm=MPI.COMM_WORLD)
    try:
        sim.run()
        st = sim.strand
        assert st.C is not None and st.op is not None, "no contact pair: the test needs some"
        A = sim.assembler.mat
        assert st.op.getType() == A.getType()
        pairs = MPI.COMM_WORLD.allreduce(len(st._c_fill[2]))
        assert pairs > 0
        ref = A.duplicate(copy=True)
        ref.axpy(1.0, st.C, structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
        diff = st.op.duplicate(copy=True)
        diff.axpy(-1.0, ref, structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
        scale = ref.norm(PETSc.NormType.FROBENIUS)
        assert diff.norm(PETSc.NormType.FROBENIUS) <= 1e-14 * scale
        # C's couplings are in it: the sum differs from A by C
        gap = st.op.duplicate(copy=True)
        gap.axpy(-1.0, A, structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
        assert gap.norm(PETSc.NormType.FROBENIUS) == pytest.approx(st.C.norm(PETSc.NormType.FROBENIUS), rel=1e-12)
        # and the symmetric flag a Cholesky needs
        assert st.op.isSymmetricKnown()[1]
        for m in (ref, diff, gap):
            m.destroy()
        # the run solved with it: one exact application per Newton solve
        assert set(sim.solver.reasons) <= {"CONVERGED_ITS"}
        X = sim.gather_positions()
        if MPI.COMM_WORLD.rank == 0:
            assert np.all(np.isfinite(X))
    finally:
        sim.close()
