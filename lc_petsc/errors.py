"""The exception types of lc_petsc, all in one place.

Every error a caller may want to catch is defined here and importable from here; the
modules that raise them import them from here too.  Two families:

* **input errors** (``ValueError`` subclasses): something the user gave is wrong, the
  message names it, its value and what is allowed; the main job reports them once and
  exits with status 2 (nothing written).  :class:`ConfigError` (config keys and PETSc
  options), :class:`SceneError` (strands and USD files), :class:`ElementError` (bad
  element-kernel input), :class:`RestPoseOverlapError` (a groom whose wisps start in
  contact) and :class:`StartOverlapError` (a perturbed start tangled),
  :class:`CheckpointError` (a restart checkpoint that cannot be used); and, for the
  main job, :class:`UsageError` (a bad command line) and :class:`FolderBusy` (another
  run holds the output folder).
* **run failures** (``RuntimeError`` subclasses): the run went wrong part-way; the main
  job keeps what was written and exits with status 3.  :class:`SolverError` (a linear
  solve diverged; carries PETSc's converged reason), :class:`SimulationError` (a
  failure on some rank, raised on every rank), :class:`OutputError` (an output could
  not be written), :class:`PetscCallError` (a PETSc C function called through ctypes
  failed).

The studies' own control-flow signals (a time budget used up, a trajectory blowing up)
stay private to lc_petsc/studies.  This module imports nothing, so the element kernels
(no PETSc, no MPI) can use it.
"""

from __future__ import annotations

__all__ = ["ConfigError", "SceneError", "ElementError", "RestPoseOverlapError",
           "StartOverlapError", "CheckpointError", "UsageError", "FolderBusy", "SolverError", "SimulationError",
           "OutputError", "PetscCallError"]


class ConfigError(ValueError):
    """A configuration problem (a config key or a PETSc option); the message names the
    key or option, the value and what is allowed."""


class SceneError(ValueError):
    """A scene that cannot be built from its file (strands HDF5 or USD): the message
    names the file, the dataset or prim and what is wrong."""


class ElementError(ValueError):
    """Bad input to an element kernel (shape, non-finite value, zero-length edge...)."""


class RestPoseOverlapError(ValueError):
    """The groom has pairs of different wisps closer than the contact thickness."""


class StartOverlapError(RestPoseOverlapError):
    """The initial state made by ``scene.perturbation`` has pairs of segments closer than
    the contact thickness, or passed through each other on the way from the rest pose."""


class CheckpointError(ValueError):
    """A checkpoint that cannot be used; the message names the file (and dataset)."""


class UsageError(Exception):
    """A bad command line of the main job (exit 2, reported once by rank 0)."""


class FolderBusy(Exception):
    """Another live run holds the output folder; the message names it."""


class SolverError(RuntimeError):
    """A linear solve failed.  ``reason``: PETSc's converged reason (a negative
    ``KSPConvergedReason`` code), None when the failure has no reason code."""

    def __init__(self, message, reason=None):
        super().__init__(message)
        self.reason = reason


class SimulationError(RuntimeError):
    """A failure on some rank during a step, raised on every rank
    (:func:`lc_petsc.parallel.collectively`)."""


class OutputError(RuntimeError):
    """An output could not be written (disk full, permissions); names the file and why.

    ``hdf5_broken``: libhdf5 itself failed on an open file, which it can then neither
    flush nor close (:mod:`lc_petsc.io.disk`): the process must end without closing it."""

    def __init__(self, message, hdf5_broken=False):
        super().__init__(message)
        self.hdf5_broken = hdf5_broken


class PetscCallError(RuntimeError):
    """A PETSc C function called through ctypes returned an error code."""
