"""Element blocks -> one PETSc matrix of 3x3 blocks (+ the gradient), per Newton iteration.

Pattern.  All couplings lie inside a wisp and a wisp never straddles ranks, so every
rank's rows are block-banded with half bandwidth ``b`` = (largest enabled stencil) - 1
vertices (3 with twist, 2 with bend, 1 with stretch only, 0 for mass only) and have no
off-process columns.  The block-CSR pattern (every in-wisp pair |i - j| <= b, a *full*
band, explicit zeros kept) is built once per topology; for SBAIJ only j >= i is stored.

Values.  Each term's elements are padded to one element per local vertex: element v
starts at vertex v, and the last k - 1 vertices of every wisp get a copy of the wisp's
last element with zero stiffness (3% more elements, all-zero blocks).  Then one fused
``gradient_hessian`` call per term writes into a persistent buffer, and block (a, c) of
every element lands on band row v + a, diagonal c - a, so the whole term is added to the
band array B[i, d + b] = block (i, i + d) with k^2 contiguous slice-adds: no scatter, no
per-iteration allocation.  Mass / dt^2 and contact blocks go on the diagonal; rows and
columns of pinned vertices become identity.  A precomputed gather maps B to the CSR value
array: written in place into PETSc's value array of the rank's block (BAIJ and the
AIJ copy; see ``Assembler._probe_value_arrays``), else by ONE ``setValuesBlockedCSR``
call.  No per-element PETSc calls.

Compiled kernels (``kernels="compiled"``, the default; ``-lc_element_kernels``).  For
the filters :mod:`lc_petsc.elements.compiled` implements (analytic, none), one compiled
pass goes from the positions straight to the gradient and the column-major 3x3 blocks
in block-CSR order (:class:`~lc_petsc.elements.compiled.BlockLayout`): written into
PETSc's SeqBAIJ value array of the rank's block when the probe allows it
(``direct``), else into ``block_values`` for one ``setValuesBlockedCSR`` call.  Mass,
contact blocks and pinned rows then go to the same array (:meth:`Assembler._blocks`),
and the AIJ preconditioning copy is gathered from it; the band array is not used.  Its
time is reported under ``elements``.  Other filters, and ``kernels="numpy"``, run the
NumPy kernels into the band as above (their padded buffers are made on first use).
docs/performance.md has the figures.

Matrix type: the solver plan's (lc_petsc/solver_plan.py: ``baij`` (bs 3) unless
``-mat_type`` or the preconditioner asks for another); ``sbaij`` and ``aij`` (block size
3) get the same values.
"""

from __future__ import annotations

from contextlib import contextmanager, nullcontext

import numpy as np
from petsc4py import PETSc

from lc_petsc import curvature
from lc_petsc.elements import bend, compiled, stretch, twist
from lc_petsc.parallel import compile_in_turn
from lc_petsc.petsc_capi import has_value_array, value_array
from lc_petsc.solver_plan import ELEMENT_KERNELS, SUPPORTED_MAT_TYPES, base_type

KERNELS = {"stretch": stretch, "bend": bend, "twist": twist}


class Assembler:
    """Owns the band array, the CSR pattern and the PETSc matrix of one rank's wisps."""

    def __init__(self, scene, comm, timers, filter="analytic", mat_type="baij", pmat_type=None,
                 options_prefix="", kernels="compiled"):
        self.scene, self.comm, self.timers, self.filter = scene, comm, timers, filter
        self.options_prefix = options_prefix
        if kernels not in ELEMENT_KERNELS:
            raise ValueError(f"-lc_element_kernels {kernels!r}: use compiled (Numba, the "
                             f"default) or numpy (the reference kernels)")
        self.kernels = kernels
        #: seconds spent compiling (or loading from Numba's cache) the compiled kernels
        # (the curvature check at Newton's stops is compiled either way: lc_petsc/curvature.py)
        warm = (compiled.warm_up,) if kernels == "compiled" else ()
        self.compile_seconds = compile_in_turn(comm.tompi4py(), *warm, curvature.warm_up)
        nv, b = scene.nv, scene.bandwidth
        self.b = b
        # Band storage R[i, r, 3 (d + b) + c] = entry (3 i + r, 3 (i + d) + c): an element's
        # matrix row is then one contiguous run of 3k values here and in its Hessian.
        self.R = buffer((nv, 3, 3 * (2 * b + 1)))
        # The same storage seen as blocks: B[i, d + b] = 3x3 block (i, i + d) (a view).
        self.B = self.R.reshape(nv, 3, 2 * b + 1, 3).transpose(0, 2, 1, 3)
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
        self._padded = None
        # the compiled kernels' element arrays: (start, rest, stiffness) per term
        self.elements = {name: compiled.element_arrays(name, t.start, t.rest, t.stiffness)
                         for name, t in scene.terms.items()}
        self.mat = self._create_matrix(mat_type)
        # pinned rows and columns among the stored blocks (SBAIJ: upper only)
        self.pin_rows, self.pin_diags = np.nonzero(self.pin_mask & self.stored)
        self.pmat = self._create_pmat(pmat_type)
        self.mat_block = self.pmat_block = None     # see _probe_value_arrays
        self._probe_value_arrays()
        # The compiled kernels write column-major 3x3 blocks in block-CSR order
        # (``layout``): straight into the BAIJ block's value array (``direct``), else
        # into ``block_values``, copied to the matrix by the CSR call.
        self.layout = compiled.BlockLayout.block_csr(self.stored, b)
        self.block_index = np.where(self.layout.base >= 0, self.layout.base // 9, -1)
        self.direct = kernels == "compiled" and self.mat_block is not None
        #: (nv, 3) indices of the entries (r, r) of the diagonal blocks in block_array()
        self.diagonal_entries = self.layout.base[:, b, None] + 4 * np.arange(3)
        self.block_values = buffer(self.n_values) if kernels == "compiled" and not self.direct \
            else None
        if self.pmat is not None:
            self.p_from_values = self._band_to_values(self.p_from_band)
        if self.mat_block is None:
            self.values = buffer((len(self.csr_rows), 9))
        self._in_blocks = False     # this iteration's values are in block_array(), not in R
        self.commits = 0            #: matrices committed so far
        self.commit()   # first fill (PETSc's one-off row compression) at build, not frame 0

    # ------------------------------------------------------------------ pattern
    def _new_matrix(self, mat_type):
        sc, nv = self.scene, self.scene.nv
        A = PETSc.Mat().create(comm=self.comm)
        A.setSizes(((3 * nv, 3 * sc.n_vertices_global), (3 * nv, 3 * sc.n_vertices_global)))
        A.setBlockSize(3)
        if self.options_prefix:
            A.setOptionsPrefix(self.options_prefix)
        A.setType(mat_type)
        return A

    def _preallocate(self, A, kind):
        nnz = self.block_counts
        if kind == "aij":
            nnz = np.repeat(3 * nnz, 3).astype(PETSc.IntType)
        A.setPreallocationNNZ((nnz, np.zeros_like(nnz)))
        A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
        A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        A.setOption(PETSc.Mat.Option.SYMMETRY_ETERNAL, True)

    def _create_matrix(self, mat_type):
        sc, nv, b = self.scene, self.scene.nv, self.b
        A = self._new_matrix(mat_type)
        A.setFromOptions()                          # -mat_type wins
        self.mat_type = base_type(A.getType())
        if self.mat_type not in SUPPORTED_MAT_TYPES:
            raise ValueError(f"-mat_type {A.getType()} is not supported: use one of "
                             f"{', '.join(SUPPORTED_MAT_TYPES)}")
        keep = self.valid.copy()
        if self.mat_type == "sbaij":
            keep[:, :b] = False
        rows, diags = np.nonzero(keep)
        self.stored = keep
        self.csr_rows, self.csr_diags = rows.astype(np.int64), diags.astype(np.int64)
        self.csr_blocks = rows * (2 * b + 1) + diags     # into B as (nv * (2b+1), 9)
        # Persistent buffers: fresh 100 MB arrays every Newton iteration cost more in page
        # faults than the copies themselves.
        self.blocks = buffer((nv, 2 * b + 1, 3, 3)) if self.kernels == "numpy" else None
        self.n_values = 9 * len(rows)
        self.values = None      # the CSR call's value buffer (without in-place writes)
        self.block_counts = keep.sum(axis=1).astype(PETSc.IntType)
        self.rowptr = np.concatenate([[0], np.cumsum(self.block_counts)]).astype(PETSc.IntType)
        self.cols = (sc.first_vertex + rows + diags - b).astype(PETSc.IntType)
        self._preallocate(A, self.mat_type)
        return A

    def _create_pmat(self, pmat_type):
        """A second matrix with the same values for the preconditioner (or None).

        PETSc 3.18 extracts each block-Jacobi block from a SeqBAIJ matrix with a column
        map as wide as the whole matrix (MatCreateSubMatrix_SeqBAIJ_Private), so one
        block per wisp costs O(wisps x vertices) per setup: about 1 s per Newton
        iteration for 2,000 wisps on one rank. AIJ extracts contiguous blocks directly.
        """
        if pmat_type is None or pmat_type == self.mat_type:
            return None
        if self.mat_type != "baij" or pmat_type != "aij":
            raise ValueError(f"-lc_pmat_type {pmat_type} with -mat_type {self.mat_type}: a "
                             f"separate preconditioning matrix is only supported as aij next to "
                             f"a baij operator; use -lc_pmat_type same")
        P = self._new_matrix("aij")
        self._preallocate(P, "aij")
        # Point CSR of the same full band: row (i, r) of the matrix is row r of R[i],
        # restricted to in-wisp columns, so the values are one gather from R.
        nv, width = self.R.shape[0], self.R.shape[2]
        cols_valid = np.repeat(self.valid, 3, axis=1)                    # (nv, width)
        mask = np.broadcast_to(cols_valid[:, None, :], (nv, 3, width)).reshape(3 * nv, width)
        col = (3 * (self.scene.first_vertex + np.arange(nv) - self.b))[:, None] + np.arange(width)
        self.p_rowptr = np.concatenate([[0], np.cumsum(mask.sum(axis=1))]).astype(PETSc.IntType)
        self.p_cols = np.broadcast_to(col[:, None, :], (nv, 3, width)).reshape(3 * nv, width)[mask]
        self.p_cols = self.p_cols.astype(PETSc.IntType)
        self.p_from_band = np.flatnonzero(mask.ravel())
        self.p_values = buffer(len(self.p_from_band))
        return P

    # ------------------------------------------------------------------ values
    @property
    def padded(self):
        """The NumPy kernels' padded terms (see :class:`PaddedTerm`), made on first use."""
        if self._padded is None:
            self._padded = {name: PaddedTerm(t, self.scene.nv) for name, t in self.scene.terms.items()}
        return self._padded

    def energy(self, x):
        """Elastic energy of this rank's enabled terms at local positions x (nv, 3)."""
        e = 0.0
        with self.timers("elements"):
            if self.kernels == "compiled":
                return compiled.energy(self.elements, x)
            for name, t in self.padded.items():
                e += float(KERNELS[name].energy(x[t.index], t.rest, t.stiffness).sum())
        return e

    def vertex_energy(self, x):
        """Elastic energy (nv,) of this rank's enabled terms per vertex: vertex v's entry
        is that of the elements starting at v (so within v's wisp; the kernels of
        ``kernels``: the compiled one pass took hairball10's frame 0 on the converging path
        from 82 to 56 ms, docs/newton.md "Twenty-second round").
        Rank-local: a wisp's sum of it is its own energy."""
        with self.timers("elements"):
            if self.kernels == "compiled":
                return compiled.vertex_energy(self.elements, x)
            e = np.zeros(len(x))
            for name, t in self.scene.terms.items():
                if len(t.start):
                    e += np.bincount(t.start, KERNELS[name].energy(t.gather(x), t.rest, t.stiffness), minlength=len(x))
        return e

    def gradient(self, x):
        """Elastic gradient (nv, 3) of this rank's enabled terms."""
        g = np.zeros_like(x)
        with self.timers("elements"):
            if self.kernels == "compiled":
                compiled.add_gradient(self.elements, x, g)
                return g
            for name, t in self.padded.items():
                _add_gradient(g, KERNELS[name].gradient(x[t.index], t.rest, t.stiffness))
        return g

    def assemble(self, x, mass=None):
        """Fill the band array with the filtered element Hessians, plus ``mass`` (nv,)
        * I on the diagonal if given (M / dt^2: :meth:`add_mass`); return the gradient.

        One fused kernel call per term (gradient + filtered Hessian); the filter runs
        inside it, so its time is reported under ``elements``.  The compiled kernels add
        the mass in the same pass (each diagonal block once it is complete: the values
        of :meth:`add_mass` after, bit for bit, without a second pass over the matrix).
        """
        R, b = self.R, self.b
        g = np.zeros_like(x)
        sym = self.mat_type == "sbaij"
        self._in_blocks = False
        if self.kernels == "compiled" and self.filter in compiled.FILTERS:
            with self.timers("elements"), self.block_array() as v:   # rows zeroed on the way
                compiled.add_gradient_hessian_into(self.elements, x, g, v, self.layout, sym,
                                                   self.filter, mass)
            self._in_blocks = True
            return g
        with self.timers("assembly"):
            R[...] = 0.0
        for name, t in self.padded.items():
            with self.timers("elements"):
                ge, h = KERNELS[name].gradient_hessian(t.positions(x), t.rest, t.stiffness,
                                                       filter=self.filter, out=t.hessian)
            with self.timers("assembly"):
                _add_gradient(g, ge)
                k, nv = t.k, len(R)
                rows = h.reshape(nv, k, 3, 3 * k)
                # Rows of local vertex a of element v sit on band row v + a, from
                # diagonal -a on (SBAIJ: from diagonal 0, i.e. blocks c >= a).
                for a in range(k):
                    first = a if sym else 0
                    R[a:, :, 3 * (b - a + first):3 * (b - a + k)] += rows[:nv - a, a, :, 3 * first:]
        if mass is not None:
            with self.timers("assembly"):
                self.add_mass(mass)
        return g

    @contextmanager
    def block_array(self):
        """The compiled kernels' flat value array (:attr:`layout`): PETSc's, of the BAIJ
        block (``direct``), or :attr:`block_values`."""
        if self.direct:
            with value_array(self.mat_block, self.n_values) as v:
                yield v
        else:
            yield self.block_values

    @contextmanager
    def _blocks(self):
        """(view, at): this iteration's 3x3 blocks (row-major) are ``view[at(i, d + b)]``
        for local block rows i and band diagonals d (arrays or scalars, broadcast): the
        band B, or :meth:`block_array` when the compiled pass wrote there."""
        if not self._in_blocks:
            yield self.B, lambda rows, diags: (rows, diags)
            return
        with self.block_array() as v:
            yield (v.reshape(-1, 3, 3).transpose(0, 2, 1),
                   lambda rows, diags: (self.block_index[rows, diags],))

    def add_diagonal(self, idx, blocks):
        """Add 3x3 blocks (m, 3, 3) on the diagonal of local vertices idx (unique)."""
        with self._blocks() as (view, at):
            view[at(idx, self.b)] += blocks

    def add_band_blocks(self, idx, h00, h01, h11):
        """Add 2x2 blocks of segments (v, v+1) for the local first vertices v = idx
        (unique, never a wisp's last vertex): h00 to block (v, v), h01 to (v, v+1) and
        its transpose to (v+1, v), h11 to (v+1, v+1); all (m, 3, 3).  Used by strand
        contact (lc_petsc/contact.py); needs a half bandwidth >= 1."""
        b = self.b
        if self._in_blocks:
            with self.block_array() as v:
                compiled.add_segment_blocks(v, self.block_index, idx, b, h00, h01, h11)
            return
        self.B[idx, b] += h00
        self.B[idx + 1, b] += h11
        self.B[idx, b + 1] += h01
        self.B[idx + 1, b - 1] += h01.transpose(0, 2, 1)

    def diagonal_blocks(self):
        """A copy of this iteration's diagonal blocks (nv, 3, 3) before :meth:`commit` (after
        ``assemble(x)`` without a mass: the elements' own, which :meth:`set_diagonal_blocks`
        puts back to change the mass term without the elements' pass)."""
        with self._blocks() as (view, at):
            return view[at(np.arange(self.scene.nv), self.b)].copy()

    def set_diagonal_blocks(self, blocks):
        """Overwrite this iteration's diagonal blocks with ``blocks`` (nv, 3, 3) (from
        :meth:`diagonal_blocks`); the other blocks keep their values, then :meth:`commit`."""
        with self._blocks() as (view, at):
            view[at(np.arange(self.scene.nv), self.b)] = blocks

    def add_mass(self, diag):
        """Add diag (nv,) * I on the diagonal (M / dt^2)."""
        if not self._in_blocks:
            self.B[:, self.b, [0, 1, 2], [0, 1, 2]] += diag[:, None]
            return
        with self.block_array() as v:
            compiled.add_diagonal(v, self.diagonal_entries, diag)

    def _band_to_values(self, band_index):
        """Indices into the BAIJ value array (:attr:`layout`) of the entries at the flat
        indices ``band_index`` of the band R (all inside the stored blocks)."""
        width = self.R.shape[2]
        i, rest = np.divmod(band_index, 3 * width)
        r, col = np.divmod(rest, width)
        dd, c = np.divmod(col, 3)
        base = self.layout.base[i, dd]
        if np.any(base < 0):
            raise ValueError("band entries outside the stored blocks")    # pragma: no cover
        return base + r * self.layout.row_stride + c * self.layout.col_stride

    def _probe_value_arrays(self):
        """Let :meth:`commit` write the values straight into the rank-local blocks of the
        matrix and pmat (:func:`petsc_capi.value_array`: one gather, instead of
        ``MatSetValues*CSR`` searching every column again; measured 0.11 s per Newton
        iteration for the AIJ copy of the 2,000-wisp hairball on 2 ranks) where that is
        safe: a SeqBAIJ / SeqAIJ block holding exactly our values, whose storage order
        a probe fill through the CSR call reads back (the CSR call stays in use
        otherwise, e.g. for SBAIJ or an AIJ operator)."""
        if self.mat_type == "baij":
            probe = np.arange(1.0, self.n_values + 1.0)
            self.mat.setValuesBlockedCSR(self.rowptr, self.cols, probe)
            self.mat.assemble()
            stored = probe.reshape(-1, 3, 3).transpose(0, 2, 1).ravel()    # blocks column-major
            self.mat_block = _block_storing(self.mat, stored)
        if self.pmat is not None:
            probe = np.arange(1.0, len(self.p_values) + 1.0)
            self.pmat.setValuesCSR(self.p_rowptr, self.p_cols, probe)
            self.pmat.assemble()
            self.pmat_block = _block_storing(self.pmat, probe)

    def commit(self):
        """Pinned rows/cols -> identity; refill the matrix (and pmat): in place when
        possible (:meth:`_probe_value_arrays`), else with one CSR call each.  Counted in
        :attr:`commits` (what identifies the committed matrix)."""
        self.commits += 1
        with self.timers("assembly"):
            B, b = self.B, self.b
            with self._blocks() as (view, at):
                view[at(self.pin_rows, self.pin_diags)] = 0.0
                view[at(self.pinned_idx, b)] = np.eye(3)
            A = self.mat
            if self._in_blocks:
                if not self.direct:                     # else the compiled pass wrote them there
                    self.values.reshape(-1, 3, 3)[...] = \
                        self.block_values.reshape(-1, 3, 3).transpose(0, 2, 1)
                    A.setValuesBlockedCSR(self.rowptr, self.cols, self.values.ravel())
            elif self.kernels == "compiled":
                if self.mat_block is not None:
                    with value_array(self.mat_block, self.n_values) as v:
                        compiled.gather_blocks(self.R, self.csr_rows, self.csr_diags, v, True)
                else:
                    compiled.gather_blocks(self.R, self.csr_rows, self.csr_diags,
                                           self.values.reshape(-1), False)
                    A.setValuesBlockedCSR(self.rowptr, self.cols, self.values.ravel())
            elif self.mat_block is not None:
                np.copyto(self.blocks, B.transpose(0, 1, 3, 2))          # column-major blocks
                with value_array(self.mat_block, self.n_values) as v:
                    np.take(self.blocks.reshape(-1, 9), self.csr_blocks, axis=0, out=v.reshape(-1, 9))
            else:
                np.copyto(self.blocks, B)
                np.take(self.blocks.reshape(-1, 9), self.csr_blocks, axis=0, out=self.values)
                A.setValuesBlockedCSR(self.rowptr, self.cols, self.values.ravel())
            A.assemble()
            if self.pmat is not None:
                self._fill_pmat()
                self.pmat.assemble()
        return A


    def local_block_csr(self):
        """The committed matrix's rank-local block rows: (block row starts (nb + 1,),
        global block columns (k,), 3x3 blocks row-major (9 k,); the assembler's own
        arrays except for a BAIJ filled in place (do not modify); every column lies in
        this rank's range (a wisp lives on one rank).  For SBAIJ the upper blocks only,
        as stored.  What a matrix holding A plus other blocks is filled from
        (lc_petsc/contact.py, the coupled operator)."""
        if self.mat_block is None:          # commit's CSR call read them from here
            return self.rowptr, self.cols, self.values.reshape(-1)
        with value_array(self.mat_block, self.n_values) as v:      # column-major blocks
            values = v.reshape(-1, 3, 3).transpose(0, 2, 1).ravel()
        return self.rowptr, self.cols, values

    def _fill_pmat(self):
        """The AIJ copy's values from the band or (direct fill) from the BAIJ values."""
        p = self.p_values
        with value_array(self.pmat_block, len(p)) if self.pmat_block is not None \
                else nullcontext(p) as out:
            if self._in_blocks:
                with self.block_array() as v:
                    np.take(v, self.p_from_values, out=out)
            else:
                np.take(self.R.reshape(-1), self.p_from_band, out=out)
        if self.pmat_block is None:
            self.pmat.setValuesCSR(self.p_rowptr, self.p_cols, p)


def _block_storing(mat, stored):
    """The rank-local diagonal block of the assembled ``mat`` if its value array is
    exactly ``stored`` (same length and order), else None."""
    block = mat.getDiagonalBlock()
    if not has_value_array(block) or int(block.getInfo()["nz_used"]) != len(stored):
        return None
    with value_array(block, len(stored)) as v:
        same = np.array_equal(v, stored)
    return block if same else None


class PaddedTerm:
    """A term's elements padded to one per local vertex (see the module doc).

    ``index`` (nv, k) local vertices of element v (= v + 0..k-1 for real elements);
    ``rest``, ``stiffness`` (nv,) with zero stiffness on the padding; ``hessian`` the
    persistent (nv, 3k, 3k) output buffer of the kernel.
    """

    def __init__(self, term, nv):
        self.k = term.k
        v = np.arange(nv)
        # Element of each vertex: its own, or (padding) the last real one of its wisp.
        elem = np.searchsorted(term.start, v, side="right") - 1
        real = term.start[elem] == v
        self.index = term.start[elem][:, None] + np.arange(term.k)
        self.rest = term.rest[elem]
        self.stiffness = np.where(real, term.stiffness[elem], 0.0)
        self.hessian = buffer((nv, 3 * term.k, 3 * term.k))
        self._positions = buffer((nv, term.k, 3))

    def positions(self, x):
        """Element positions (nv, k, 3) gathered from x (nv, 3) into a reused buffer."""
        return np.take(x, self.index, axis=0, out=self._positions)


def buffer(shape):
    """A zeroed array whose pages are touched now, at build time.

    The operating system maps fresh pages lazily; on the machines measured here the
    first write to 2 GB of new buffers costs several seconds, which would otherwise land
    in the first frame.
    """
    a = np.empty(shape)
    a.fill(0.0)
    return a


def _add_gradient(g, ge):
    """Add padded element gradients ge (nv, k, 3) to vertex gradients g (nv, 3)."""
    nv, k = ge.shape[:2]
    for a in range(k):
        g[a:] += ge[:nv - a, a]
