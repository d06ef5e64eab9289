"""Shared set-up of the test suite.

Markers (declared in pyproject.toml, ``--strict-markers``):

* ``mpi``: a collective test.  It runs in the serial suite on one rank, and again on
  2 and 3 ranks: tests/test_mpi_launch.py starts ``mpiexec -n N python -m pytest -m mpi
  tests/``, so every rank collects and runs the same ``mpi`` tests in the same order.
  Such a test must make the same collective calls (MPI, PETSc, parallel h5py) on every
  rank, also when it fails; use ``MPI.COMM_WORLD`` for the ranks and
  ``sim_helpers.shared_scene_dir`` for files every rank reads.
* ``slow``: takes more than a few seconds.

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
