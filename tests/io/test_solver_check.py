"""PETSc options that PETSc accepts but that fail the run at its first solve are refused
before frame 0 (exit 2, nothing written), from the command line and from
solver.options_file alike: the tolerances the KSP read, and a trial solve of the run's
own solver on a small symmetric positive definite system (lc_petsc/solver_check.py).
Before, ``-- -ksp_max_it -5`` wrote frame 0 and failed there with exit 3, and
``-ksp_rtol 1`` ran every frame with zero Newton steps, without an error."""

import pytest
from mpi4py import MPI

from lc_petsc.batch import main

from sim_helpers import shared_scene_dir  # noqa: E402

GOOD = """
[scene]
kind = "hairball"
n_wisps = 3
seed = 5
[physics]
terms = ["stretch", "bend", "twist", "gravity"]
[time]
frames = 2
[output]
previews = false
usd = false
"""

#: (options, what the one error line must hold)
REFUSED = [
    # typos, which PETSc ignores (its -options_left lists them at the end)
    ("-ksp_rtoll 1e-6", "-ksp_rtoll ({where}) is not an option of this PETSc or of lc_petsc (a typo, or an "
                        "option of a package this PETSc was built without): did you mean -ksp_rtol?"),
    ("-sub_pc_tipe lu", "-sub_pc_tipe ({where}) is not an option"),
    ("-lc_wisp_blockz separate", "-lc_wisp_blockz ({where}) is not an option of this PETSc or of lc_petsc "
                                 "(a typo, or an option of a package this PETSc was built without): did you "
                                 "mean -lc_wisp_blocks?"),
    ("-ksp_max_it -5", "-ksp_max_it -5 ({where}): the cap of Krylov iterations per linear solve must be "
                       "a whole number >= 1"),
    ("-ksp_max_it 0", "-ksp_max_it 0 ({where}): the cap of Krylov iterations"),
    ("-ksp_rtol 1", "-ksp_rtol 1 ({where}): a solve stops once its residual is below rtol times"),
    ("-ksp_rtol 0", "-ksp_rtol 0 ({where}): a solve stops once"),
    ("-ksp_rtol -1e-6", "-ksp_rtol -1e-06 ({where})"),
    ("-ksp_atol -1", "-ksp_atol -1 ({where}): an absolute residual tolerance must be >= 0"),
    ("-ksp_divtol 0.5", "-ksp_divtol 0.5 ({where}): a solve is called diverged"),
    # PETSc has no LU of its own for SBAIJ: found at the first factorisation
    ("-ksp_type preonly -pc_type lu -mat_type sbaij",
     "the linear solver fails to set up or solve a small symmetric positive definite test system: "),
    # MUMPS checks its orderings only when it factors
    ("-ksp_type preonly -pc_type cholesky -pc_factor_mat_solver_type mumps -mat_mumps_icntl_7 9",
     "the linear solver fails to set up or solve a small symmetric positive definite test system: "),
]


def _run(capsys, argv, comm):
    code = main(argv, comm=comm)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("where", ["on the command line", "in the config's [solver] options"])
@pytest.mark.parametrize("options, part", REFUSED, ids=[r[0] for r in REFUSED])
def test_options_that_fail_the_first_solve_are_refused_up_front(tmp_path, capsys, options, part, where):
    cfg = tmp_path / "c.toml"
    argv = [str(cfg), "--out", str(tmp_path / "o"), "--quiet"]
    if where == "on the command line":
        cfg.write_text(GOOD)
        argv += options.split()
    else:
        (tmp_path / "x.opts").write_text(options + "\n")
        cfg.write_text(GOOD + '[solver]\noptions_file = "x.opts"\n')
    code, out, err = _run(capsys, argv, MPI.COMM_SELF)
    assert code == 2, (code, err)
    assert err.count("simulate.py: error:") == 1 and "Traceback" not in err + out, err
    assert part.format(where=where) in err, err
    assert not (tmp_path / "o").exists(), "nothing written"


def test_a_solver_that_works_is_not_refused(tmp_path, capsys):
    """The trial solve neither refuses a slow solver (its iteration cap says nothing on a
    system of another size) nor prints the run's monitors."""
    cfg = tmp_path / "c.toml"
    cfg.write_text(GOOD)
    code, out, err = _run(capsys, [str(cfg), "--out", str(tmp_path / "o"), "--quiet", "--frames", "1",
                                   "-pc_type", "jacobi", "-ksp_max_it", "2", "-ksp_monitor"], MPI.COMM_SELF)
    # the run fails at its first solve, as asked (exit 3), after frame 0
    assert code == 3 and "DIVERGED_MAX_IT" in err, err
    # the monitor printed the real solve's residuals only: its first line is of a 3-wisp system
    assert out.count("KSP Residual norm") == 3, out


@pytest.mark.mpi
@pytest.mark.parametrize("options, part", [REFUSED[3], REFUSED[10]], ids=["max_it", "lu_sbaij"])
def test_refused_on_every_rank_count(capsys, options, part):
    comm = MPI.COMM_WORLD
    with shared_scene_dir(comm, "lc_solver_check_", GOOD) as (d, cfg):
        code, out, err = _run(capsys, [cfg, "--out", f"{d}/o", "--quiet"] + options.split(), comm)
        assert code == 2
        if comm.rank == 0:
            assert err.count("simulate.py: error:") == 1 and part.format(where="on the command line") in err, err
        else:
            assert "error" not in err, err
        comm.Barrier()
        import os
        assert not os.path.exists(f"{d}/o")
