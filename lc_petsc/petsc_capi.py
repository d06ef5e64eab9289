"""The few PETSc C functions petsc4py 3.18 does not bind, called through ctypes.

* ``PCBJacobiSetLocalBlocks`` (the per-wisp block Jacobi, lc_petsc/solver.py);
* ``PetscOptionsUsed`` (options given but never used are reported, lc_petsc/solver_plan.py);
* ``MatSeqAIJGetArray`` / ``MatSeqBAIJGetArray`` and their ``Restore``: the value array
  of a rank's diagonal block, written in place by lc_petsc/assembly.py (one NumPy
  gather into PETSc's memory instead of ``MatSetValues*CSR``, which searches every
  column index again);
* ``MatMPIBAIJGetSeqBAIJ`` and ``MatGetRowIJ``: the diagonal and off-diagonal blocks of
  an MPI BAIJ matrix, their block patterns and the off-diagonal block's global columns,
  for the compiled product of the contact operator (lc_petsc/contact.py).

Every call checks PETSc's error code and raises :class:`PetscCallError` naming the
function.
"""

from __future__ import annotations

import ctypes
from contextlib import contextmanager
from functools import lru_cache

import numpy as np
from petsc4py import PETSc

from lc_petsc.errors import PetscCallError

#: C function returning the value array of each supported sequential matrix type
_GET_ARRAY = {"seqaij": "MatSeqAIJGetArray", "seqbaij": "MatSeqBAIJGetArray"}


@lru_cache(maxsize=1)
def libpetsc():
    """Debian's PETSc 3.18 shared library (ctypes), loaded once."""
    for name in ("libpetsc_real.so.3.18", "libpetsc.so.3.18"):
        try:
            return ctypes.CDLL(name, mode=ctypes.RTLD_GLOBAL)
        except OSError:
            continue
    raise OSError("cannot load libpetsc_real.so.3.18 (Debian's PETSc 3.18, installed by "
                  "scripts/setup.sh)")


def _call(name, argtypes, *args):
    fn = getattr(libpetsc(), name)
    fn.restype = ctypes.c_int
    fn.argtypes = argtypes
    ierr = fn(*args)
    if ierr != 0:
        raise PetscCallError(f"{name} failed with PETSc error {ierr}")


def bjacobi_set_local_blocks(pc, lens):
    """PCBJacobiSetLocalBlocks(pc, len(lens), lens) (lens in matrix rows)."""
    arr = np.ascontiguousarray(lens, dtype=PETSc.IntType)
    ctype = ctypes.c_int32 if PETSc.IntType == np.int32 else ctypes.c_int64
    _call("PCBJacobiSetLocalBlocks", [ctypes.c_void_p, ctype, ctypes.c_void_p],
          ctypes.c_void_p(pc.handle), ctype(len(arr)),
          arr.ctypes.data_as(ctypes.c_void_p) if len(arr) else None)


def option_used(name) -> bool:
    """Whether the option ``name`` (without the dash) of the global options database
    has been queried by anything since it was set (``PetscOptionsUsed``)."""
    flag = ctypes.c_int(0)
    _call("PetscOptionsUsed", [ctypes.c_void_p, ctypes.c_char_p, ctypes.POINTER(ctypes.c_int)],
          None, str(name).encode(), ctypes.byref(flag))
    return bool(flag.value)


def has_value_array(mat) -> bool:
    """Whether :func:`value_array` supports ``mat`` (a SeqAIJ or SeqBAIJ matrix)."""
    return mat.getType() in _GET_ARRAY


@contextmanager
def value_array(mat, n):
    """The value array (n,) of the sequential matrix ``mat`` (SeqAIJ: row-major CSR
    order; SeqBAIJ: block CSR order, each block column-major), writable in place; the
    caller checks that ``n`` is the matrix's number of stored values.  Restoring it (on
    exit) advances a SeqAIJ matrix's state, not a SeqBAIJ one's (PETSc 3.18): after
    writing, assemble the matrix (``MatAssemblyEnd`` advances it), so that whatever
    caches its values (:class:`lc_petsc.contact.SumOperator`) sees the change."""
    get = _GET_ARRAY.get(mat.getType())
    if get is None:
        raise TypeError(f"value_array: unsupported matrix type {mat.getType()} "
                        f"(expected one of {', '.join(_GET_ARRAY)})")
    ptr = ctypes.POINTER(ctypes.c_double)()
    args = ([ctypes.c_void_p, ctypes.POINTER(ctypes.POINTER(ctypes.c_double))],
            ctypes.c_void_p(mat.handle), ctypes.byref(ptr))
    _call(get, *args)
    try:
        yield np.ctypeslib.as_array(ptr, shape=(n,)) if n else np.zeros(0)
    finally:
        _call(get.replace("Get", "Restore"), *args)


def cg_set_radius(ksp, radius):
    """KSPCGSetRadius(ksp, radius): the trust region of KSPSTCG / KSPNASH / KSPGLTR."""
    _call("KSPCGSetRadius", [ctypes.c_void_p, ctypes.c_double],
          ctypes.c_void_p(ksp.handle), ctypes.c_double(radius))


def _cg_get_real(name, ksp):
    out = ctypes.c_double(0.0)
    _call(name, [ctypes.c_void_p, ctypes.POINTER(ctypes.c_double)],
          ctypes.c_void_p(ksp.handle), ctypes.byref(out))
    return float(out.value)


def cg_get_norm_d(ksp):
    """KSPCGGetNormD: the last trust-region solve's step length (with PETSc 3.18 the
    Euclidean norm of the step, not its preconditioner norm: tests/sim/test_trust_region.py)."""
    return _cg_get_real("KSPCGGetNormD", ksp)


def cg_get_obj_fcn(ksp):
    """KSPCGGetObjFcn: the last trust-region solve's model value 1/2 d^T A d - b . d."""
    return _cg_get_real("KSPCGGetObjFcn", ksp)


class SeqBAIJHandle:
    """A sequential BAIJ matrix known by its C handle alone (a block of an MPI BAIJ
    matrix from :func:`mpibaij_blocks`), usable with :func:`value_array` and
    :func:`block_pattern`.  Borrowed: valid while its MPI matrix lives."""

    def __init__(self, handle):
        self.handle = handle

    def getType(self):
        """PETSc's type name, as petsc4py's ``Mat.getType``."""
        return "seqbaij"

    def getSize(self):
        """(rows, columns), as petsc4py's ``Mat.getSize``."""
        index = ctypes.c_int32 if PETSc.IntType == np.int32 else ctypes.c_int64
        rows, cols = index(), index()
        _call("MatGetSize", [ctypes.c_void_p, ctypes.POINTER(index), ctypes.POINTER(index)],
              ctypes.c_void_p(self.handle), ctypes.byref(rows), ctypes.byref(cols))
        return rows.value, cols.value

    def stateGet(self):
        """The object's state (``PetscObjectStateGet``), as petsc4py's ``Mat.stateGet``."""
        state = ctypes.c_int64()
        _call("PetscObjectStateGet", [ctypes.c_void_p, ctypes.POINTER(ctypes.c_int64)],
              ctypes.c_void_p(self.handle), ctypes.byref(state))
        return state.value


def _int_pointer():
    return ctypes.POINTER(ctypes.c_int32 if PETSc.IntType == np.int32 else ctypes.c_int64)


def mpibaij_blocks(mat):
    """(diagonal block, off-diagonal block, global block column of each column of the
    off-diagonal block (copied)) of the MPI BAIJ ``mat`` (``MatMPIBAIJGetSeqBAIJ``); the
    blocks are :class:`SeqBAIJHandle`."""
    diag, off = ctypes.c_void_p(), ctypes.c_void_p()
    colmap = _int_pointer()()
    _call("MatMPIBAIJGetSeqBAIJ", [ctypes.c_void_p, ctypes.POINTER(ctypes.c_void_p),
                                   ctypes.POINTER(ctypes.c_void_p), ctypes.POINTER(_int_pointer())],
          ctypes.c_void_p(mat.handle), ctypes.byref(diag), ctypes.byref(off), ctypes.byref(colmap))
    index = ctypes.c_int32 if PETSc.IntType == np.int32 else ctypes.c_int64
    rows, cols = index(), index()
    _call("MatGetSize", [ctypes.c_void_p, ctypes.POINTER(index), ctypes.POINTER(index)],
          off, ctypes.byref(rows), ctypes.byref(cols))
    k = cols.value // mat.getBlockSize()      # the off-diagonal block's block columns
    columns = np.ctypeslib.as_array(colmap, shape=(k,)).copy() if k else np.zeros(0, PETSc.IntType)
    return SeqBAIJHandle(diag.value), SeqBAIJHandle(off.value), columns


def block_pattern(mat):
    """(block row starts (nb + 1,), block columns (k,)), copied, of the sequential BAIJ
    ``mat`` (a petsc4py Mat or a :class:`SeqBAIJHandle`; ``MatGetRowIJ`` with block
    compression)."""
    n = (ctypes.c_int32 if PETSc.IntType == np.int32 else ctypes.c_int64)()
    ia, ja = _int_pointer()(), _int_pointer()()
    done = ctypes.c_int(0)           # PetscBool
    args = ([ctypes.c_void_p, n.__class__, ctypes.c_int, ctypes.c_int, ctypes.POINTER(n.__class__),
             ctypes.POINTER(_int_pointer()), ctypes.POINTER(_int_pointer()), ctypes.POINTER(ctypes.c_int)],
            ctypes.c_void_p(mat.handle), n.__class__(0), 0, 1, ctypes.byref(n), ctypes.byref(ia),
            ctypes.byref(ja), ctypes.byref(done))
    _call("MatGetRowIJ", *args)
    try:
        if not done.value:
            raise PetscCallError("MatGetRowIJ: the matrix gave no row structure")
        indptr = np.ctypeslib.as_array(ia, shape=(n.value + 1,)).copy()
        k = int(indptr[-1])
        indices = np.ctypeslib.as_array(ja, shape=(k,)).copy() if k else np.zeros(0, PETSc.IntType)
    finally:
        _call("MatRestoreRowIJ", *args)
    return indptr, indices
