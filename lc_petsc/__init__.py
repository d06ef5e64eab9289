"""lc_petsc: a PETSc-backed, MPI-parallel simulator of tightly coiled hair.

Implements the "Lifted Curls" model (Shi, Wu, Parr, Darke, Kim, SCA 2023). See
``../shared/SPEC.md`` for the model and ``docs/architecture.md`` for the code layout.
"""

__version__ = "0.1.0"
