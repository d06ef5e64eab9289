"""lc_petsc/errors.py: every public error type defined once, in the right family, and
raised where the modules raise it."""

import pytest

import lc_petsc.errors as E


def test_every_public_error_type_is_the_one_in_errors():
    from lc_petsc import batch, config, parallel, petsc_capi, rest_pose, solver
    from lc_petsc.elements import common
    from lc_petsc.io import checkpoint, disk, lock
    assert config.ConfigError is E.ConfigError
    assert common.ElementError is E.ElementError
    assert rest_pose.RestPoseOverlapError is E.RestPoseOverlapError
    assert checkpoint.CheckpointError is E.CheckpointError
    assert batch.UsageError is E.UsageError and lock.FolderBusy is E.FolderBusy
    assert solver.SolverError is E.SolverError and parallel.SimulationError is E.SimulationError
    assert disk.OutputError is E.OutputError and petsc_capi.PetscCallError is E.PetscCallError
    assert set(E.__all__) == {n for n in dir(E) if n.endswith(("Error", "Busy"))}


@pytest.mark.parametrize("name", ["ConfigError", "SceneError", "ElementError", "RestPoseOverlapError",
                                  "CheckpointError"])
def test_input_errors_are_value_errors(name):
    assert issubclass(getattr(E, name), ValueError)


@pytest.mark.parametrize("name", ["SolverError", "SimulationError", "OutputError", "PetscCallError"])
def test_run_failures_are_runtime_errors(name):
    assert issubclass(getattr(E, name), RuntimeError)


def test_solver_error_keeps_the_reason_and_output_error_the_hdf5_state():
    e = E.SolverError("diverged", reason=-3)
    assert e.reason == -3 and str(e) == "diverged" and E.SolverError("x").reason is None
    assert E.OutputError("full", hdf5_broken=True).hdf5_broken


def test_a_bad_strands_file_is_a_scene_error(tmp_path):
    from lc_petsc.scene.sources import check_strands_file
    p = tmp_path / "empty.h5"
    p.write_bytes(b"")
    with pytest.raises(E.SceneError, match=r"empty.h5: the file is empty \(0 bytes\)"):
        check_strands_file(str(p))
