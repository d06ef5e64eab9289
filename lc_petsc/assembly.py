"""Element blocks -> one PETSc matrix of 3x3 blocks (+ the gradient), per Newton iteration.

Pattern.  All couplings lie inside a wisp and a wisp never straddles ranks, so every
rank's rows are block-banded with half bandwidth ``b`` = (largest enabled stencil) - 1
vertices (3 with twist, 2 with bend, 1 with stretch only, 0 for mass only) and have no
off-process columns.  The block-CSR pattern (every in-wisp pair |i - j| <= b, a *full*
band, explicit zeros kept) is built once per topology; for SBAIJ only j >= i is stored.

Values.  Element Hessians (n, 3k, 3k) are accumulated into a band array
B[i, d + b] = block (i, i + d): one fancy assignment puts each term's blocks at their
start vertex (starts are unique, so no ``np.add.at``), then k^2 contiguous slice-adds; mass / dt^2 and contact blocks go on the diagonal; rows and columns of
pinned vertices become identity.  A precomputed gather maps B to the CSR value array,
and ONE ``setValuesBlockedCSR`` call refills the matrix.  No per-element PETSc calls.

Matrix type: ``baij`` (bs 3) unless the options database says ``-mat_type``; ``sbaij``
and ``aij`` (block size 3) get the same values.
"""

from __future__ import annotations

import numpy as np
from petsc4py import PETSc

from lc_petsc.elements import bend, stretch, twist

KERNELS = {"stretch": stretch, "bend": bend, "twist": twist}
SUPPORTED_MAT_TYPES = ("baij", "sbaij", "aij")


def base_type(mat_type: str) -> str:
    t = mat_type.lower()
    for prefix in ("seq", "mpi"):
        if t.startswith(prefix):
            t = t[len(prefix):]
    return t


class Assembler:
    """Owns the band array, the CSR pattern and the PETSc matrix of one rank's wisps."""

    def __init__(self, scene, comm, timers, filter="analytic", mat_type="baij"):
        self.scene, self.comm, self.timers, self.filter = scene, comm, timers, filter
        nv, b = scene.nv, scene.bandwidth
        self.b = b
        self.B = np.zeros((nv, 2 * b + 1, 3, 3))
        # wisp bounds per vertex
        wid = np.repeat(np.arange(scene.n_wisps), np.diff(scene.offsets))
        lo = scene.offsets[:-1][wid] if nv else np.zeros(0, np.int64)
        hi = scene.offsets[1:][wid] if nv else np.zeros(0, np.int64)
        i = np.arange(nv)[:, None]
        d = np.arange(-b, b + 1)[None, :]
        j = i + d
        self.valid = (j >= lo[:, None]) & (j < hi[:, None])
        pin = scene.pinned
        jc = np.clip(j, 0, max(nv - 1, 0))
        self.pin_mask = self.valid & (pin[:, None] | (pin[jc] if nv else np.zeros_like(self.valid)))
        self.pinned_idx = np.flatnonzero(pin)
        self.mat = self._create_matrix(mat_type)

    # ------------------------------------------------------------------ pattern
    def _create_matrix(self, mat_type):
        sc, nv, b = self.scene, self.scene.nv, self.b
        A = PETSc.Mat().create(comm=self.comm)
        A.setSizes(((3 * nv, 3 * sc.n_vertices_global), (3 * nv, 3 * sc.n_vertices_global)))
        A.setBlockSize(3)
        A.setType(mat_type)
        A.setFromOptions()                          # -mat_type wins
        self.mat_type = base_type(A.getType())
        if self.mat_type not in SUPPORTED_MAT_TYPES:
            raise ValueError(f"-mat_type {A.getType()} is not supported: use one of "
                             f"{', '.join(SUPPORTED_MAT_TYPES)}")
        keep = self.valid.copy()
        if self.mat_type == "sbaij":
            keep[:, :b] = False
        self.csr_from_band = np.flatnonzero(keep.ravel())
        counts = keep.sum(axis=1)
        self.rowptr = np.concatenate([[0], np.cumsum(counts)]).astype(PETSc.IntType)
        ii, dd = np.nonzero(keep)
        self.cols = (sc.first_vertex + ii + dd - b).astype(PETSc.IntType)
        nnz = counts.astype(PETSc.IntType)
        if self.mat_type == "aij":
            nnz = np.repeat(3 * nnz, 3).astype(PETSc.IntType)
        A.setPreallocationNNZ((nnz, np.zeros_like(nnz)))
        A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
        A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        A.setOption(PETSc.Mat.Option.SYMMETRY_ETERNAL, True)
        return A

    # ------------------------------------------------------------------ values
    def energy(self, x):
        """Elastic energy of this rank's enabled terms at local positions x (nv, 3)."""
        e = 0.0
        with self.timers("elements"):
            for name, t in self.scene.terms.items():
                if len(t.start):
                    e += float(KERNELS[name].energy(t.gather(x), t.rest, t.stiffness).sum())
        return e

    def gradient(self, x):
        g = np.zeros_like(x)
        with self.timers("elements"):
            for name, t in self.scene.terms.items():
                if not len(t.start):
                    continue
                ge = KERNELS[name].gradient(t.gather(x), t.rest, t.stiffness)
                for a in range(t.k):
                    g[t.start + a] += ge[:, a]
        return g

    def hessian_band(self, x):
        """Zero the band array and add all enabled terms' filtered element Hessians."""
        B, b = self.B, self.b
        B[...] = 0.0
        sym = self.mat_type == "sbaij"
        for name, t in self.scene.terms.items():
            if not len(t.start):
                continue
            with self.timers("filter"):
                H = KERNELS[name].hessian(t.gather(x), t.rest, t.stiffness, filter=self.filter)
            with self.timers("assembly"):
                k, nv = t.k, len(B)
                # scatter element blocks to an array indexed by start vertex (one fancy
                # assignment), then add each (a, c) block with contiguous slices
                Hs = np.zeros((nv, k, k, 3, 3))
                Hs[t.start] = H.reshape(-1, k, 3, k, 3).transpose(0, 1, 3, 2, 4)
                for a in range(k):
                    for c in range(a if sym else 0, k):
                        B[a:, c - a + b] += Hs[:nv - a, a, c]

    def add_diagonal(self, idx, blocks):
        """Add 3x3 blocks (m, 3, 3) on the diagonal of local vertices idx (unique)."""
        self.B[idx, self.b] += blocks

    def add_mass(self, diag):
        """Add diag (nv,) * I on the diagonal (M / dt^2)."""
        self.B[:, self.b, [0, 1, 2], [0, 1, 2]] += diag[:, None]

    def commit(self):
        """Pinned rows/cols -> identity; refill the PETSc matrix with one CSR call."""
        with self.timers("assembly"):
            B, b = self.B, self.b
            B[self.pin_mask] = 0.0
            B[self.pinned_idx, b] = np.eye(3)
            vals = B.reshape(-1, 3, 3)[self.csr_from_band]
            A = self.mat
            A.setValuesBlockedCSR(self.rowptr, self.cols, vals.ravel())
            A.assemble()
        return A
