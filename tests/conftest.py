"""Shared set-up of the test suite.

Markers (declared in pyproject.toml, ``--strict-markers``):

* ``mpi``: a collective test.  It runs in the serial suite on one rank, and again on
  2 and 3 ranks: tests/test_mpi_launch.py starts ``mpiexec -n N python -m pytest -m mpi
  tests/``, so every rank collects and runs the same ``mpi`` tests in the same order.
  Such a test must make the same collective calls (MPI, PETSc, parallel h5py) on every
  rank, also when it fails; use ``MPI.COMM_WORLD`` for the ranks and
  ``sim_helpers.shared_scene_dir`` for files every rank reads.
* ``slow``: takes more than a few seconds.

Under ``mpiexec -n N`` (N > 1) only the ``mpi`` tests are collected, whatever ``-m`` says:
the others are serial by design (per-rank temporary directories, their own ``mpiexec``
launches, one-wisp scenes) and some would wait forever in a collective file open;
they run in the serial suite.  The report's last lines say how many were left out.

After every test, :func:`collective_teardown` frees what the test left behind on every
rank at the same point: Python garbage (PETSc objects without ``destroy``), then PETSc's
deferred destruction of parallel objects (``PETSc.garbage_cleanup``, collective), then a
barrier, so no rank starts the next test while another is still inside the last one's
collectives.

The helper modules next to the tests (``sim_helpers``, ``element_helpers``,
``ccd_reference``) are importable from every test folder.
"""

import gc
import sys
from pathlib import Path

import pytest

_HELPERS = str(Path(__file__).resolve().parent)
if _HELPERS not in sys.path:
    sys.path.insert(0, _HELPERS)


_SERIAL_LEFT_OUT = pytest.StashKey[int]()


def _world_size():
    from mpi4py import MPI
    return MPI.COMM_WORLD.size


def pytest_collection_modifyitems(config, items):
    """Under mpiexec, keep only the collective (``mpi``) tests (see the module's note)."""
    if _world_size() == 1:
        return
    serial = [item for item in items if item.get_closest_marker("mpi") is None]
    if serial:
        config.hook.pytest_deselected(items=serial)
        items[:] = [item for item in items if item.get_closest_marker("mpi") is not None]
        config.stash[_SERIAL_LEFT_OUT] = len(serial)


def pytest_report_header(config):
    if _world_size() > 1:
        return (f"{_world_size()} MPI ranks: only the collective (mpi) tests run here; "
                "the serial ones run in the serial suite")
    return None


def pytest_terminal_summary(terminalreporter, config):
    left_out = config.stash.get(_SERIAL_LEFT_OUT, 0)
    if left_out:
        terminalreporter.write_line(
            f"{left_out} serial tests not run under {_world_size()} MPI ranks "
            "(run them with `.venv/bin/python -m pytest -q`, without mpiexec)")


@pytest.fixture(scope="session", autouse=True)
def compiled_kernels():
    """Compile (or load from Numba's cache) the kernels once, then freeze what the
    compiler left: a process that compiled them holds ~570k objects that every
    ``gc.collect()`` below would scan again (0.45 s per test, against 0.05 s when they
    were loaded from the cache)."""
    from lc_petsc.elements import compiled, compiled_ccd
    compiled.warm_up()
    compiled_ccd.warm_up()
    gc.collect()
    gc.freeze()
    yield
    gc.unfreeze()


@pytest.fixture(autouse=True)
def collective_teardown():
    """Garbage collection, ``PETSc.garbage_cleanup()`` and a barrier after each test."""
    yield
    gc.collect()
    from mpi4py import MPI
    from petsc4py import PETSc
    PETSc.garbage_cleanup()
    MPI.COMM_WORLD.Barrier()


@pytest.fixture(autouse=True)
def fresh_hdf5_state(monkeypatch):
    """Each test starts with libhdf5 unmarked: a test that made it fail on an open file
    (a full disk) marks the process (``lc_petsc.io.hdf5.mark_unclosable``), which would
    make the later tests of the process skip their XDMF, previews and USD."""
    from lc_petsc.io import hdf5
    monkeypatch.setattr(hdf5, "_unclosable", False)
