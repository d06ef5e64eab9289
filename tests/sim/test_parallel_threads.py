"""BLAS / OpenMP thread pools: one thread per process unless the user chose a count
(lc_petsc.parallel.limit_blas_threads; why: docs/design_notes.md)."""

import os

import numpy as np  # noqa: F401  (loads OpenBLAS, as every lc_petsc process does)
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from lc_petsc import parallel


@pytest.fixture
def fresh_limits(monkeypatch):
    """No thread-count variable set, no limit applied yet; restores the pools after."""
    for v in parallel.THREAD_COUNT_VARIABLES:
        monkeypatch.delenv(v, raising=False)
    monkeypatch.setattr(parallel, "_thread_limits", [])
    with threadpool_limits(limits=2):           # a known multi-threaded starting point
        yield


def test_blas_pools_limited_to_one_thread(fresh_limits):
    if (os.cpu_count() or 1) >= 2:      # OpenBLAS caps its pool at the core count
        assert all(p["num_threads"] == 2 for p in threadpool_info())
    assert parallel.limit_blas_threads() >= 1               # NumPy's BLAS was found
    assert all(p["num_threads"] == 1 for p in threadpool_info())
    assert parallel.limit_blas_threads() == 0               # once per process


def test_user_thread_count_is_respected(fresh_limits, monkeypatch):
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")
    assert parallel.limit_blas_threads() == 0
    assert all(p["num_threads"] == 2 for p in threadpool_info())
