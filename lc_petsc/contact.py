"""Strand-strand contact across MPI ranks: broad phase, ghost exchange, assembly.

See docs/contact.md for the design and its cost.  In short, per Newton iteration
(:meth:`StrandContact.assemble`) and for every energy evaluation of the line search
(:meth:`StrandContact.energy`):

1. **Occupancy.** Each rank lists the cells of a uniform grid over the scene (cell
   size = the largest segment box extent + 2 d0 over all ranks, one allreduce, and
   at least 1/128 of the scene's extent) touched by its segments' boxes inflated by
   d0, found through a boolean array over the cells, and the lists are allgathered
   (about 28k cells per rank of the 2K hairball on 2 ranks, vs 100k segments).  One box per
   rank, the first plan, selects
   3x more ghosts here: a rank's wisps span a spherical cap whose box covers much of
   the other ranks' hair (measured at rest on 2 ranks: 30% of rank 1's segments vs 9%).
2. **Ghosts.** A pair of segments on ranks q < r is computed by rank q (the owner of the
   segment with the smaller global index: ranks own increasing vertex ranges), so rank
   r sends to every lower rank q, with one ``alltoall``, the segments whose box touches
   a cell occupied by q: only segments that can be within d0 of one of q's.
   ``-lc_contact_work balanced`` replaces a segment's rank here by its wisp's contact
   rank (:meth:`StrandContact.start_frame`): a rank also gets the segments of the wisps
   whose pairs it computes for their owner, in the same ``alltoall``.
3. **Broad phase.** :func:`compiled_ccd.box_pairs` over the local + ghost segments'
   boxes grown by d0 / 2 (:meth:`StrandContact.candidates`), which contains every pair
   closer than d0.  Rebuilt from the current positions
   (reused only for bit-identical positions), so no margin for motion is needed: the
   search is exact, not predictive.  In ccd mode every position the contact sees comes
   out of a limiter call, whose candidates (reach d0) and path end cover it: the pairs
   are taken from there instead (:meth:`StrandContact._reached`, the same pairs).
   The frame end's path checks after the first reuse the first one's ghosts and box
   pairs while their boxes stay within a skin (:data:`LIMITER_SKIN`).
   Pairs of the same wisp are excluded, unless ``self_contact``: then only neighbours
   along the strand are (:data:`NEIGHBOUR_GAP`; docs/contact.md, "Self-contact").
4. **Narrow phase.** :mod:`lc_petsc.elements.segment_contact` (the penalty; or the
   barrier of :mod:`lc_petsc.elements.segment_barrier`, ccd mode) on the candidates, the
   smaller global segment first (so the arithmetic of a pair does not depend on the
   partition); active pairs have d < d0.
5. **Assembly.** Per active pair, each segment gets its gradient (2 x 3), its own 2x2
   blocks of the 12x12 Hessian (these lie in the strand band: same wisp, adjacent
   vertices) and two preallocation counts: 35 numbers added (ADD_VALUES) into a PETSc
   Vec of block size 35 indexed by the segment's first global vertex.  One Vec assembly
   brings off-process contributions to their owners, which add them to the gradient and
   to the band (:meth:`Assembler.add_band_blocks`), so the operator *and* the per-wisp
   preconditioner see them.  The cross blocks (segment A x segment B) go into a
   separate contact matrix C (the strand matrix's type), created per Newton iteration
   with exact per-row preallocation from those counts and filled with
   ``setValuesBlockedRCV(ADD_VALUES)``; PETSc ships off-process rows at assembly.
6. **System.** :meth:`StrandContact.system`: the Newton operator A + C (a Python shell,
   or assembled when the preconditioner needs the whole matrix, ``-lc_contact_pc
   coupled``: A's rows and C's pair blocks filled directly into one matrix) and the
   preconditioning matrix.

Pinned vertices get no contact gradient, band or C entries (their rows/columns stay
identity).
"""

from __future__ import annotations


import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from lc_petsc.elements import (compiled, compiled_band, compiled_ccd, compiled_cluster, compiled_contact, compiled_mult,
                               segment_barrier, segment_ccd, segment_contact)
from lc_petsc.elements.compiled_ccd import box_pairs
from lc_petsc.contact_pc import local_block
from lc_petsc.parallel import CONTACT_WORK, collectively, compile_in_turn, global_min, global_reduce, partition
from lc_petsc.petsc_capi import block_pattern, mpibaij_blocks, value_array

MODES = ("penalty", "ccd")
#: ``-lc_contact_work balanced``: a segment's share of the broad phase and limiter work,
#: in candidate pairs (per-rank CPU of box_pairs and order_candidates against their
#: segments and pairs, 2K ccd frames 30-33 on 2 ranks: ~1.9e-7 s per segment, ~0.9e-7 s
#: per candidate pair; docs/performance.md, "Contact work balanced by contact")
SEGMENT_WORK = 2
#: the contact energy on the pair distance: kernel module by name (same call signatures)
POTENTIALS = {"penalty": segment_contact, "barrier": segment_barrier}
#: limiter rounds that shrink the step fractions by the pairs' safe fractions before
#: the rounds that stop the offending vertices outright (limit_step)
SCALE_ROUNDS = 8
#: self-contact: segments of one wisp with less than NEIGHBOUR_GAP d0 of rest strand
#: between them are neighbours, never a pair (those sharing a vertex always; pi / 2 d0 is
#: the arc of the tightest hairpin of a strand of thickness d0, whose legs touch)
NEIGHBOUR_GAP = 0.5 * np.pi
#: the limiter's field: Lipschitz constant at most 1/2 (a pair of stopped free vertices
#: then keeps half its distance, docs/contact.md); a rigid motion has L = 2 sin(theta / 2),
#: so the head's serves up to MAX_RIGID_DEGREES of rotation per step
MAX_LIPSCHITZ = 0.5
#: limiter rounds before the pairs to test again come from a point -> pairs incidence
#: (built once per call) rather than a scan of all pairs
INCIDENCE_ROUND = 3
#: conservative advancement stops within ADVANCE_RTOL m of its floor: the step count is
#: discrete, so a looser stop (1e-3) made the fractions jump on round-off (6 wisps, 10
#: frames: 2 ranks left 1 rank by 9e-5; 1.8e-8 at 1e-12)
ADVANCE_RTOL = 1e-12
#: the head's rigid motion over a Newton step (the pinned vertices stay where the
#: frame's first iterate put them): the identity, i.e. the zero field
NEWTON_STEP_MOTION = (np.eye(3), np.zeros(3))
#: ccd limiter: the step fractions of two neighbours on a strand differ by at most
#: FRACTION_STRAIN L / |f| (L the edge's rest length, |f| the larger residual motion of
#: its two vertices), so a limited update stretches no edge by more than FRACTION_STRAIN
#: of its rest length beyond the longer of its start and target lengths (per-vertex
#: fractions tore strands: docs/contact.md "Torn strands")
FRACTION_STRAIN = 0.02
#: end-of-frame separation (ccd mode): after each Jacobi round's contact corrections, the
#: edges whose length left [L (1 - s), L (1 + s)] (L rest, s = SEPARATION_STRAIN) are
#: projected back into it
#: (:func:`bound_edge_lengths`); unbounded pushes tore the 2K hairball's strands
#: (docs/contact.md "Strain-aware separation")
SEPARATION_STRAIN = FRACTION_STRAIN
#: red-black sweeps of :func:`bound_edge_lengths` per separation round at most
EDGE_SWEEPS = 50
#: the separation's over-relaxation omega: a pair's correction is divided by the largest
#: number of violating pairs at one of its vertices over omega (at most by 1), the
#: successive over-relaxation of averaged Jacobi projections (Macklin et al., "Unified
#: particle physics for real-time applications", 2014: 1 <= omega <= 2).  With 1 (the
#: plain average) the 2K hairball's frame-end separations took 40-60 rounds and hit the
#: 60-round cap with pairs still below the floor; with 2 every call finishes, in 0.61x
#: the CPU time (docs/contact.md "The separation over-relaxed")
SEPARATION_OVERRELAXATION = 2.0
#: the frame path checks (:meth:`StrandContact.collision_free_frame`) reuse their ghosts
#: and candidate pairs while every segment's box stays inside its box of the call that
#: found them grown by LIMITER_SKIN d0: the frame end's checks after the first move
#: little (the separation's pushes, the holding back)
LIMITER_SKIN = 0.5
MAX_RIGID_DEGREES = float(np.degrees(2.0 * np.arcsin(0.5 * MAX_LIPSCHITZ)))
NB = 35          # per segment row: g0 g1 (6) H00 H01 H11 (27) count_diag count_offdiag (2)


class FrameTally:
    """Statistics by frame of a count recorded several times a frame (once per Newton
    iteration, say), so that they grow with the frames, not the iterations.

    Entry k of ``sums``, ``counts`` (records), ``maxima`` and ``lasts`` covers the k-th
    :meth:`start_frame` of the run (the integrator calls it at each step's start); entry
    0 holds what was recorded before the first one (the set-up, e.g. the rest-pose check)."""

    def __init__(self):
        self.sums, self.counts, self.maxima, self.lasts = [0], [0], [0], [0]

    def start_frame(self):
        """Open the next frame's entry."""
        for stat in (self.sums, self.counts, self.maxima, self.lasts):
            stat.append(0)

    def add(self, n):
        """Record the count ``n`` in the current frame."""
        self.sums[-1] += n
        self.counts[-1] += 1
        self.maxima[-1] = max(self.maxima[-1], n)
        self.lasts[-1] = n

    def means(self):
        """The mean count per record of every frame with records."""
        return [s / c for s, c in zip(self.sums, self.counts) if c]


class _OccupancyGrid:
    """A uniform grid common to all ranks over every segment box inflated by d0 (one
    ``Allreduce``).  The cell size is at least the largest box extent + 2 d0, so an
    inflated box touches at most 2 cells per axis, i.e. exactly the cells of its 8
    corners, and at least 1/128 of the scene's extent (at most 129^3 cells: the
    occupancy of a rank is a boolean array over all cells)."""

    def __init__(self, lo, hi, d0, comm):
        buf = global_reduce(comm, np.concatenate([-lo.min(axis=0, initial=np.inf),
                                                  hi.max(axis=0, initial=-np.inf),
                                                  [(hi - lo).max(initial=0.0)]]), "max")
        self.empty = not np.all(np.isfinite(buf))          # no segment on any rank
        if self.empty:
            return
        lo_all, hi_all = -buf[:3], buf[3:6]
        self.cell = max(buf[6] + 2.0 * d0, float((hi_all - lo_all).max()) / 128.0, 1e-6)
        self.origin = lo_all - d0
        self.dims = np.floor((hi_all + d0 - self.origin) / self.cell).astype(np.int64) + 1
        self.size = int(np.prod(self.dims))

    def corner_cells(self, lo, hi):
        """Flat cell ids (n, 8) of the 8 corners of boxes lo, hi (n, 3)."""
        return compiled_ccd.corner_cells(lo, hi, self.origin, self.cell, self.dims)

    def mask(self, cells):
        """Boolean occupancy (size,) of the flat cell ids ``cells``."""
        m = np.zeros(self.size, bool)
        m[cells.ravel()] = True
        return m


class _VertexGather:
    """A VecScatter from a PETSc Vec indexed by global vertex (block size ``bs``) to the
    sorted global vertices ``V`` that a rank's pairs touch (its own and ghosts), and
    back (reverse, with an insert mode such as ADD_VALUES or MAX_VALUES).  A context
    manager: the scatter and its work Vec are destroyed on exit."""

    def __init__(self, vec, V, bs):
        self.idx = PETSc.IS().createBlock(bs, np.asarray(V, PETSc.IntType), comm=PETSc.COMM_SELF)
        self.loc = PETSc.Vec().createSeq(bs * len(V), bsize=bs, comm=PETSc.COMM_SELF)
        self.scatter = PETSc.Scatter().create(vec, self.idx, self.loc, None)

    def gather(self, vec):
        """The values of ``vec`` at V, (bs len(V),) (a view of the work Vec)."""
        self.scatter.scatter(vec, self.loc, addv=PETSc.InsertMode.INSERT_VALUES)
        return self.loc.array

    def reverse(self, values, vec, addv):
        """Combine ``values`` (bs len(V),) into ``vec`` at V with ``addv``."""
        self.loc.array[:] = values
        self.scatter.scatter(self.loc, vec, addv=addv, mode=PETSc.ScatterMode.REVERSE)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        for obj in (self.scatter, self.loc, self.idx):
            obj.destroy()


class _BlockProduct:
    """y = M x or y + M x for a sequential BAIJ matrix M with 3x3 blocks, compiled.

    A square M whose blocks below the diagonal are exactly the transposes of those above
    (the strand matrix: the assembly stores them as such; C's rank-local block) is
    multiplied from a copy of its upper triangle (:func:`compiled_mult.bsr3_sym_mult`):
    about half the bytes per product (the 2,000-wisp hairball's band: 4 of 7 blocks per
    row), the same result bit for bit.  The copy (and the symmetry check, one pass over
    M's values) is made again whenever M's state changes.  Otherwise, or with
    ``symmetric`` False, :func:`compiled_mult.bsr3_mult` on M's value array.  A
    ``previous`` product of a matrix with the same pattern lends its upper pattern and
    copy (the strand matrix is reread every Newton iteration, its pattern unchanged)."""

    def __init__(self, M, symmetric=True, previous=None):
        self.M = M
        self.indptr, self.indices = block_pattern(M)
        self.n = 9 * len(self.indices)
        self.upper = None
        rows, cols = M.getSize()
        if previous is not None and previous.upper is not None and symmetric and \
                np.array_equal(previous.indptr, self.indptr) and np.array_equal(previous.indices, self.indices):
            self.upper, self.upper_values = previous.upper, previous.upper_values
        elif symmetric and rows == cols:
            upper = compiled_mult.bsr3_upper_pattern(self.indptr, self.indices)
            if upper[5]:                        # the pattern itself is symmetric
                self.upper = upper[:5]
                self.upper_values = np.empty(9 * len(upper[1]))
        self.state = None
        self.symmetric = False

    def __call__(self, x, y, add):
        if self.upper is not None and self.M.stateGet() != self.state:
            upper_indptr, upper_indices, source, lower, mirror = self.upper
            with value_array(self.M, self.n) as values:
                self.symmetric = compiled_mult.bsr3_upper_values(values, values.view(np.int64), source, lower,
                                                                 mirror, self.upper_values)
            self.state = self.M.stateGet()
        if self.symmetric:
            compiled_mult.bsr3_sym_mult(self.upper[0], self.upper[1], self.upper_values, x, y, add)
        else:
            with value_array(self.M, self.n) as values:
                compiled_mult.bsr3_mult(self.indptr, self.indices, values, x, y, add)


class SumOperator:
    """Python-shell context of the Newton operator A + C (C may be None): two matvecs,
    measured faster per CG iteration than one matvec with the assembled sum (see
    :meth:`StrandContact.system`).

    Both products run compiled (:class:`_BlockProduct`) where the matrices are BAIJ with
    3x3 blocks: the same products as PETSc's ``MatMult`` and ``MatMultAdd``, bit for bit,
    in a fraction of their time (:mod:`compiled_mult`).  A must have no entry outside the
    rank's diagonal block (the strand matrix: every wisp's band lies on one rank); C's
    entries in other ranks' columns (couplings across the partition) come through a
    scatter of their x values, as in PETSc's ``MatMultAdd_MPIBAIJ``.  Anything else goes
    through PETSc.  Call :meth:`refresh` when A's nonzero pattern may have changed;
    setting C (a new matrix every Newton iteration) rereads C's.  A's values are reread
    when its state changes (``MatAssemblyEnd`` advances it; a caller that writes A's
    value array in place assembles A, as the assembler does)."""

    def __init__(self, A):
        self.A = A
        self._C = None
        self._band = None          # A's compiled product (a _BlockProduct) or False
        self._band_kept = None     # the last one, lent to the next when A's pattern is the same
        self._contact = None       # C's: ([diagonal, off-diagonal block's _BlockProduct], scatter, ghosts) or False

    @property
    def C(self):
        """The contact matrix (None: no contact pairs)."""
        return self._C

    @C.setter
    def C(self, C):
        self._forget_contact()
        self._C = C

    def refresh(self):
        """Forget A's and C's patterns (read again at the next product; A's upper copy is
        kept for a pattern that did not change)."""
        if self._band:
            self._band_kept = self._band
        self._band = None
        self._forget_contact()

    def _forget_contact(self):
        if self._contact:
            for obj in self._contact[1:]:
                if obj is not None:
                    obj.destroy()
        self._contact = None

    def destroy(self, mat=None):
        """Destroy the ghost scatter (PETSc calls this when the shell is destroyed)."""
        self._forget_contact()

    @staticmethod
    def _bsr3(M):
        return compiled.available() and M.getType() in (PETSc.Mat.Type.SEQBAIJ, PETSc.Mat.Type.MPIBAIJ) \
            and M.getBlockSize() == 3

    def _read_band(self):
        A = self.A
        if not self._bsr3(A):
            return False
        A_loc = local_block(A)
        # every rank decides alike: a rank left in MatMult would wait for the others' ghosts
        local = A.getInfo(PETSc.Mat.InfoType.LOCAL)["nz_used"] == A_loc.getInfo()["nz_used"]
        if not A.getComm().tompi4py().allreduce(local, op=MPI.LAND):
            return False
        return _BlockProduct(A_loc, previous=self._band_kept)

    def _read_contact(self, x):
        """C's compiled product (collective), its ghost scatter made for vectors like x."""
        C = self._C
        if not self._bsr3(C):
            return False
        if C.getComm().getSize() == 1:
            return [_BlockProduct(C)], None, None
        diag, off, columns = mpibaij_blocks(C)
        dofs = (3 * columns.astype(np.int64)[:, None] + np.arange(3)).ravel().astype(PETSc.IntType)
        ghosts = PETSc.Vec().createSeq(len(dofs), comm=PETSc.COMM_SELF)
        where = PETSc.IS().createGeneral(dofs, comm=PETSc.COMM_SELF)
        try:
            scatter = PETSc.Scatter().create(x, where, ghosts, None)
        finally:
            where.destroy()
        return [_BlockProduct(diag), _BlockProduct(off, symmetric=False)], scatter, ghosts

    def mult(self, mat, x, y):
        """y = (A + C) x."""
        if self._band is None:
            self._band = self._read_band()
        if self._C is not None and self._contact is None:
            self._contact = self._read_contact(x)
        forward = PETSc.InsertMode.INSERT_VALUES, PETSc.ScatterMode.FORWARD
        scatter, ghosts = self._contact[1:] if self._contact else (None, None)
        if scatter is not None:         # C's off-rank columns, started first as in PETSc
            scatter.begin(x, ghosts, *forward)
        if not self._band:
            self.A.mult(x, y)
        if self._band or self._contact:
            xa, ya = x.getArray(readonly=True), y.getArray()
            if self._band:
                self._band(xa, ya, False)
            if self._contact:
                self._contact[0][0](xa, ya, True)
                if scatter is not None:
                    scatter.end(x, ghosts, *forward)
                    self._contact[0][1](ghosts.getArray(readonly=True), ya, True)
        if self._C is not None and not self._contact:
            self._C.multAdd(x, y, y)

    def getDiagonal(self, mat, d):
        """The diagonal of A (C has no diagonal blocks)."""
        self.A.getDiagonal(d)


def _local_first(own, received, keep):
    """This rank's rows ``own`` it keeps, then the ``received`` ones, local rows first:
    ``keep`` = (mine, order) of :meth:`StrandContact._gather_segments`, each None when it
    changes nothing (the owner rule: every own row kept, none given)."""
    mine, order = keep
    rows = np.concatenate([own if mine is None else own[mine], received])
    return rows if order is None else rows[order]


class StrandContact:
    """Contact between segments of different wisps, for one rank's wisps.

    ``comm``: mpi4py communicator; ``pcomm``: the PETSc one (same group).
    ``thickness`` d0 (cm), ``stiffness`` k (dyn/cm), ``filter`` the Hessian filter of
    :mod:`segment_contact` (``analytic`` = Gauss-Newton).  ``potential``: ``penalty``
    (:mod:`segment_contact`) or ``barrier`` (:mod:`segment_barrier`, ccd mode only, its
    stiffness ``barrier_stiffness``, default
    :func:`segment_barrier.penalty_matched_stiffness` of k).  ``self_contact``: also
    pairs of one wisp that are not neighbours along it (:data:`NEIGHBOUR_GAP`).
    ``work``: which rank computes a pair (:data:`CONTACT_WORK`).
    """

    def __init__(self, scene, comm, pcomm, timers, thickness, stiffness, filter="analytic",
                 mat_type="baij", coupled_pc=True, mode="penalty", min_separation=0.25,
                 potential="penalty", barrier_stiffness=None, self_contact=False, work="owner"):
        if scene.bandwidth < 1:
            raise ValueError("strand_collision needs the stretch term (the contact blocks of a "
                             "segment live in the strand band); add 'stretch' to physics.terms")
        self.scene, self.comm, self.pcomm, self.timers = scene, comm, pcomm, timers
        self.d0, self.k, self.filter = float(thickness), float(stiffness), filter
        nv = scene.nv
        self.seg = np.concatenate([np.arange(scene.offsets[w], scene.offsets[w + 1] - 1)
                                   for w in range(scene.n_wisps)]).astype(np.int64)
        wid = np.repeat(np.arange(scene.n_wisps), np.diff(scene.offsets))
        self.vertex_wisp = wid.astype(np.int64)                 # local wisp of each local vertex
        # local wisp w's segments: seg[seg_offsets[w]:seg_offsets[w + 1]]
        self.seg_offsets = compiled_ccd.strand_edge_offsets(scene.offsets)
        self.seg_wisp = (scene.first_wisp + wid[self.seg]).astype(np.int64)
        self.seg_gv = (scene.first_vertex + self.seg).astype(np.int64)
        free = ~scene.pinned
        self.seg_free = np.stack([free[self.seg], free[self.seg + 1]], axis=1)
        self.N = int(scene.n_vertices_global)
        self.P_rest = np.stack([scene.x_rest[self.seg], scene.x_rest[self.seg + 1]], axis=1)
        self.rest_seg_length = np.linalg.norm(self.P_rest[:, 1] - self.P_rest[:, 0], axis=1)
        # self-contact: rest arc length along the wisp at both ends of each segment (a
        # wisp lives on one rank, so ghosts never pair with a segment of their own wisp)
        self.self_contact = bool(self_contact)
        #: the start check's finding a run goes on with (strand_rest_overlap = "exempt"), for
        #: the job's warnings (lc_petsc.diagnostics.term_warnings); None: none
        self.start_warning = None
        self.neighbour_gap = NEIGHBOUR_GAP * self.d0
        edge = np.linalg.norm(self.P_rest[:, 1] - self.P_rest[:, 0], axis=1)
        first = np.r_[True, self.seg_wisp[1:] != self.seg_wisp[:-1]]
        start = np.cumsum(edge) - edge
        start -= np.maximum.accumulate(np.where(first, start, 0.0))
        self.seg_arc = np.stack([start, start + edge], axis=1)
        if work not in CONTACT_WORK:
            raise ValueError(f"-lc_contact_work {work!r}: use one of {', '.join(CONTACT_WORK)}")
        self.work = work
        #: per local segment, the rank that computes its pairs with segments of the same or
        #: a higher contact rank (:meth:`_gather_segments`); :meth:`start_frame` sets it
        self.contact_rank = np.full(len(self.seg), comm.rank, np.int64)
        self._local_arc = self.seg_arc            # the last gather's local rows' arc
        self.n_wisps_global = int(comm.allreduce(scene.n_wisps))
        #: ``balanced``: per global wisp, its contact work in the frame so far (_safe_fractions)
        self.wisp_work = np.zeros(self.n_wisps_global, np.int64)
        # an edge's index along its wisp, mod 2 (bound_edge_lengths' red-black sweeps)
        self.seg_colour = (self.seg - scene.offsets[wid[self.seg]]) % 2
        #: the separation's edge-length bounds (lo, hi) (:meth:`separate`; ccd mode only:
        #: penalty mode's pushes keep their measured trajectories, and tore no strand there)
        self.edge_bounds = self.edge_work = None
        if mode == "ccd":
            L = self.rest_seg_length
            self.edge_bounds = (L * (1.0 - SEPARATION_STRAIN), L * (1.0 + SEPARATION_STRAIN))
            # the rounds after the first queue the edges at the vertices they moved
            self.edge_work = compiled_ccd.EdgeWork(self.seg, nv)
        self.vec = PETSc.Vec().createMPI((NB * nv, NB * self.N), bsize=NB, comm=pcomm)
        self.mat_type, self.coupled_pc = mat_type, bool(coupled_pc)
        # separation (see :meth:`separate`): positions + inverse mass per vertex, and the
        # position corrections, indexed by global vertex
        self.state = PETSc.Vec().createMPI((5 * nv, 5 * self.N), bsize=5, comm=pcomm)
        self.correction = PETSc.Vec().createMPI((4 * nv, 4 * self.N), bsize=4, comm=pcomm)
        self.inverse_mass = np.where(scene.pinned, 0.0, 1.0 / scene.mass)
        self.C = None                   # contact cross blocks (pattern changes every call)
        self.op = None                  # the assembled Newton matrix A + C (coupled_pc)
        self.shell = self.shell_ctx = None      # the shell A + C (strand-only pmat)
        self.last_pairs, self.last_min_distance = 0, np.inf
        # per frame, not per call (they are made every Newton iteration): ghost segments
        # received per exchange, active pairs straddling ranks per assemble
        self.ghosts_received = FrameTally()
        self.cross_pairs = FrameTally()
        self._pairs_cache = None          # (x, pairs, far_min) of the last _pairs call
        self._limited = None              # the last limiter call's end and candidates (_reached)
        self._path_cache = None           # the frame path checks' ghosts and candidates (_safe_fractions)
        self._path_ends = None            # the last skin > 0 path check's path ends and held points (_first_round)
        self.path_checks_reused = 0       # frame path checks that reused them (of the run)
        self.last_separation = (0, 0, 0)
        if mode not in MODES:
            raise ValueError(f"strand contact mode {mode!r}: use one of {', '.join(MODES)}")
        self.mode, self.min_separation = mode, float(min_separation)
        if potential not in POTENTIALS:
            raise ValueError(f"strand contact potential {potential!r}: use one of {', '.join(POTENTIALS)}")
        if potential == "barrier" and mode != "ccd":
            raise ValueError("the barrier potential needs mode 'ccd' (collision-free steps: the "
                             "barrier is infinite where segments touch)")
        self.potential, self.kernel = potential, POTENTIALS[potential]
        self.barrier_stiffness = None
        if potential == "barrier":
            self.barrier_stiffness = float(segment_barrier.penalty_matched_stiffness(self.k)
                                           if barrier_stiffness is None else barrier_stiffness)
        #: the stiffness the potential's kernel takes (k or kappa)
        self.kernel_stiffness = self.k if potential == "penalty" else self.barrier_stiffness
        #: seconds compiling (or loading from Numba's cache) the compiled broad phase and
        #: limiter kernels, at set-up (not in any frame)
        self.compile_seconds = compile_in_turn(comm, compiled_ccd.warm_up, compiled_contact.warm_up,
                                               compiled_mult.warm_up, compiled_band.warm_up,
                                               compiled_cluster.warm_up)
        # ccd mode (see limit_step): per-vertex step fractions, in a Vec by global vertex
        self.step_fraction = self.shrink = None
        #: per vertex, the fraction beta of the last limiter pass (:meth:`_safe_fractions`)
        self.path_fraction = None
        if mode == "ccd":
            self.step_fraction = PETSc.Vec().createMPI((nv, self.N), comm=pcomm)
            self.shrink = PETSc.Vec().createMPI((nv, self.N), comm=pcomm)
        # the limiter's statistics by frame (FrameTally): vertices whose step was cut (per
        # limiter pass: two in a limit_step call that replaced its update), the rounds of
        # a pass, vertices held back on the frame paths (per
        # collision_free_frame call, 2 a frame), pairs left unresolved and candidate pairs
        # over all ranks (per _safe_fractions call)
        self.limited_vertices, self.limit_rounds = FrameTally(), FrameTally()
        # ccd mode with a Newton tolerance: nonlinear updates replaced by the linear step
        # (limit_step), and the last call's outcome
        self.updates_replaced = FrameTally()
        self.replaced = self.last_cut = False
        self.frame_fixes, self.unresolved_pairs = FrameTally(), FrameTally()
        self.limiter_candidates = FrameTally()

    def system(self, A, strand_pmat=None, strand_blocks=None):
        """(operator, preconditioning matrix) of the Newton system A + C, after
        :meth:`assemble` and the strand matrix A's ``commit``.  Collective.

        * ``coupled_pc``: the sum is assembled into a new matrix (A keeps its fixed
          pattern) that is both operator and preconditioning matrix, so a direct solver
          or AMG sees the contact couplings.  With ``strand_blocks`` (a callable giving
          A's local rows as block CSR, :meth:`Assembler.local_block_csr`) it is filled
          directly: A's rows and C's pair blocks added into a matrix preallocated for
          both (:meth:`_summed_matrix`); without, by ``MatAXPY`` with a different
          nonzero pattern (entry by entry through ``MatGetRow``; for SBAIJ through a
          conversion to BAIJ and back).  Measured on the 2K hairball's frame 90, 2
          ranks, MUMPS Cholesky: ``MatAXPY`` + ``MatConvert`` 0.28 s per Newton
          iteration, the direct fill 0.15 s, most of it the page faults of the new
          matrix's memory (docs/contact_solver.md, "MUMPS").
        * otherwise: the operator is a Python-shell matrix applying A x + C x, and the
          preconditioning matrix is the strand matrix (``strand_pmat``, else A): one
          exact block per wisp, blind to the couplings.  Measured on the 2,000-wisp
          hairball, 1 rank: 13 ms per shell matvec against 25 ms for the assembled sum
          (whose assembly also costs 0.15-0.44 s per Newton iteration), hence the shell
          wherever the sum need not be assembled."""
        with self.timers("collision"):
            if self.op is not None:
                self.op.destroy()
                self.op = None
            if not self.coupled_pc:
                if self.shell is None:
                    self.shell_ctx = SumOperator(A)
                    self.shell = PETSc.Mat().createPython(A.getSizes(), context=self.shell_ctx,
                                                          comm=self.pcomm)
                    self.shell.setUp()
                self.shell_ctx.C = self.C
                self.shell_ctx.refresh()
                return self.shell, (strand_pmat or A)
            op = A
            if self.C is not None and strand_blocks is not None:
                op = self.op = self._summed_matrix(A, *strand_blocks())
            elif self.C is not None:
                op = self.op = A.duplicate(copy=True)
                op.axpy(1.0, self.C, structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
                op.setOption(PETSc.Mat.Option.SYMMETRIC, True)      # MatAXPY drops the flag
            return op, op

    def _summed_matrix(self, A, rowptr, cols, values):
        """A + C in a new matrix of A's type and layout: preallocated for A's local block
        rows (``rowptr`` (nb + 1,), global block ``cols`` (k,), row-major 3x3 ``values``
        (9 k,); A has no entry in another rank's columns) plus C's counts, then A's rows
        and C's pair blocks (those of the last :meth:`assemble`, wherever they were
        computed) added, one blocked call each.  Collective."""
        dn, on, ra, rb, cross_ab, cross_ba = self._c_fill
        nv = self.scene.nv
        d_nnz = np.minimum(np.diff(rowptr) + dn, nv)
        o_nnz = np.minimum(on, self.N - nv)
        if self.mat_type == "aij":
            nnz = (np.repeat(3 * d_nnz, 3), np.repeat(3 * o_nnz, 3))
        else:
            nnz = (d_nnz, o_nnz)
        S = PETSc.Mat().create(comm=self.pcomm)
        S.setSizes(A.getSizes(), bsize=3)
        S.setType(A.getType())
        S.setPreallocationNNZ(tuple(n.astype(PETSc.IntType) for n in nnz))
        try:
            S.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
            add = PETSc.InsertMode.ADD_VALUES
            S.setValuesBlockedCSR(rowptr, cols, values, addv=add)
            if len(ra):
                S.setValuesBlockedRCV(ra, rb, cross_ab, addv=add)
                if cross_ba is not None:
                    S.setValuesBlockedRCV(rb, ra, cross_ba, addv=add)
            S.assemble()
        except BaseException:
            S.destroy()
            raise
        S.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        return S

    # ------------------------------------------------------------- exchange
    def _gather_segments(self, x, extra=(), inflate=None, boxes=None, masks=None):
        """Local + ghost segments: (list of P (m, 2, 3), one per configuration ``x`` and
        ``extra`` (each (nv, 3)), rest P, global first vertex, wisp, free (m, 2), owner
        rank, n_local).  A segment's box covers all its configurations (swept bounds
        when ``extra`` holds the end of a step); ghosts are the segments whose box comes
        within ``inflate`` (default d0) of a box of the receiving rank; ``boxes`` (lo,
        hi) (m, 3) replace the segments' own boxes, and come back as a last (m, 2, 3)
        array of the list (lo, hi) for the ghosts too.  ``masks``, a list, receives the
        segments sent to each rank and the received rows' order, for :meth:`_exchange`.

        The local segments (the first n_local) are those whose pairs this rank computes
        (:attr:`contact_rank`: its own, and with ``-lc_contact_work balanced`` other
        ranks' wisps it was given, whose rows come first among the received ones); the
        ghosts are the segments of a higher contact rank near them."""
        comm = self.comm
        d0 = self.d0 if inflate is None else float(inflate)
        Ps = [compiled_ccd.segment_ends(a, self.seg) for a in (x, *extra)]
        if boxes is None:
            allP = Ps[0] if len(Ps) == 1 else np.concatenate(Ps, axis=1)
            lo, hi = allP.min(axis=1), allP.max(axis=1)
        else:
            lo, hi = boxes
            Ps.append(np.stack([lo, hi], axis=1))
        # Occupancy (see the module doc and _OccupancyGrid): per contact rank, the cells
        # touched by the boxes of its segments inflated by d0, as sorted flat ids
        crank = self.contact_rank
        send = [None] * comm.size
        mine = np.ones(len(self.seg), bool)       # this rank's own rows it keeps
        masks = [] if masks is None else masks
        if comm.size > 1:
            grid = _OccupancyGrid(lo, hi, d0, comm)
            own = [] if grid.empty else [
                (int(c), np.flatnonzero(grid.mask(grid.corner_cells(lo[crank == c] - d0, hi[crank == c] + d0)))
                 .astype(np.int32)) for c in np.unique(crank)]
            occ = [[] for _ in range(comm.size)]
            for parts in comm.allgather(own):
                for c, cells in parts:
                    occ[c].append(cells)
            if not grid.empty:
                keys = grid.corner_cells(lo, hi)
            for q in range(comm.size):
                # to rank q: the segments of contact rank q, and those of a higher one
                # near q's (their pairs are q's)
                m = crank == q
                if not grid.empty and occ[q] and np.any(crank > q):
                    m |= (crank > q) & _any_column(grid.mask(np.concatenate(occ[q]))[keys])
                if q == comm.rank:
                    mine = m
                    masks.append(None)
                    continue
                m = m if np.any(m) else None
                masks.append(m)
                if m is not None:
                    send[q] = np.concatenate([self.seg_gv[m, None], self.seg_wisp[m, None],
                                              self.seg_free[m], self.P_rest[m].reshape(-1, 6),
                                              crank[m, None], self.seg_arc[m]]
                                             + [P[m].reshape(-1, 6) for P in Ps], axis=1)
        recv = comm.alltoall(send) if comm.size > 1 else [None]
        owner = [np.full(int(mine.sum()), comm.rank)]
        for q, r in enumerate(recv):
            if r is not None and len(r):
                owner.append(np.full(len(r), q))
        parts = [r for r in recv if r is not None and len(r)]
        G = np.concatenate(parts) if parts else np.zeros((0, 13 + 6 * len(Ps)))
        # local rows first: this rank's own, then those it was given, in rank order
        local = np.concatenate([crank[mine] == comm.rank, G[:, 10] == comm.rank])
        n_local = int(local.sum())
        # the owner rule (the default) keeps all its rows, already local first: no copies
        keep = (None if mine.all() else mine,
                None if local[:n_local].all() else np.r_[np.flatnonzero(local), np.flatnonzero(~local)])
        masks.append(keep)
        self.ghosts_received.add(len(local) - n_local)
        Pall = [_local_first(P, G[:, 13 + 6 * k:19 + 6 * k].reshape(-1, 2, 3), keep) for k, P in enumerate(Ps)]
        Prest = _local_first(self.P_rest, G[:, 4:10].reshape(-1, 2, 3), keep)
        gv = _local_first(self.seg_gv, G[:, 0].astype(np.int64), keep)
        wisp = _local_first(self.seg_wisp, G[:, 1].astype(np.int64), keep)
        free = _local_first(self.seg_free, G[:, 2:4].astype(bool), keep)
        self._local_arc = _local_first(self.seg_arc, G[:, 11:13], keep)[:n_local]
        owner = np.concatenate(owner)       # its own rows already the kept ones
        return Pall, Prest, gv, wisp, free, owner if keep[1] is None else owner[keep[1]], n_local

    def _exchange(self, Ps, masks):
        """The arrays Ps (each (m, 2, 3), this rank's segments) with the ghosts' rows
        appended, for the send masks ``masks`` of an earlier :meth:`_gather_segments`
        call on every rank (the ghosts in that call's order)."""
        comm = self.comm
        if comm.size == 1:
            return Ps
        send = [None if m is None else np.concatenate([P[m].reshape(-1, 6) for P in Ps], axis=1)
                for m in masks[:-1]]
        parts = [r for r in comm.alltoall(send) if r is not None and len(r)]
        G = np.concatenate(parts) if parts else np.zeros((0, 6 * len(Ps)))
        return [_local_first(P, G[:, 6 * k:6 * k + 6].reshape(-1, 2, 3), masks[-1]) for k, P in enumerate(Ps)]

    def self_pairs(self, n):
        """``box_pairs``' keywords for the first n segments of :meth:`_gather_segments`
        (local, then ghosts): with self-contact, the segments' rest arc lengths (0 for
        ghosts: a ghost pairs with no segment of its own wisp) and the neighbour gap."""
        if not self.self_contact:
            return {}
        arc = np.zeros((n, 2))
        arc[:len(self._local_arc)] = self._local_arc
        return {"arc": arc, "min_gap": self.neighbour_gap}

    @staticmethod
    def candidates(P, wisp, n_local, d0, **self_pairs):
        """Index pairs (i, j), i < j, of segments of different wisps (and, with the
        keywords of :meth:`self_pairs`, non-neighbours of one wisp) that may be closer
        than d0 (at least one of them local): their boxes grown by d0 / 2 overlap
        (:func:`compiled_ccd.box_pairs`, exact)."""
        if len(P) < 2:
            return np.zeros((0, 2), np.int64)
        return box_pairs(np.minimum(P[:, 0], P[:, 1]) - 0.5 * d0, np.maximum(P[:, 0], P[:, 1]) + 0.5 * d0,
                         group=wisp, n_local=n_local, **self_pairs)

    def _pairs(self, x, far=False):
        """Pairs as (X (n, 4, 3), gvA, gvB, freeA, freeB, ownerA, ownerB, d), the segment
        with the smaller global index first: the pairs closer than d0 that are not exempt,
        in the order of (gvA, gvB) (the same whatever produced the candidates).  With
        ``far``, (pairs, far_min): also the smallest distance of the other candidates
        at d0 or more (inf if none; for the minimum distance; exemption only concerns
        pairs closer than d0), without their X (2.5M of them at 8K).  The result of the
        last call is kept: the line search evaluates the energy at the point just
        assembled, and the separation works on the pairs the end-of-frame measurement
        just found (each rank compares x with its cached copy bit for bit, and the cache
        is used only if that holds on every rank).  Positions that a limiter call just
        produced (ccd mode) take their candidates from that call (:meth:`_reached`)
        instead of a new ghost exchange and broad phase."""
        cache = self._pairs_cache
        if cache is not None and (not far or cache[2] is not None):
            if global_min(self.comm, int(np.array_equal(cache[0], x))):       # the same on all ranks
                return (cache[1], cache[2]) if far else cache[1]
        out = None
        reached = self._reached(x)
        if reached is not None:
            out, far_min = self._close_pairs(*reached, far)
            # the limiter's candidates hold every pair closer than d0 but not every
            # farther pair whose grown boxes overlap: the minimum over candidates is the
            # broad phase's only while some pair is closer than d0
            if far and self.comm.allreduce(len(out[-1])) == 0:
                out = None
        if out is None:
            (P,), Prest, gv, wisp, free, owner, n_local = self._gather_segments(x)
            ij = self.candidates(P, wisp, n_local, self.d0, **self.self_pairs(len(P)))
            i, j = ij[:, 0], ij[:, 1]
            if self.mode != "ccd":      # penalty mode has no limiter: its broad phase's work
                self._count_work(wisp, i, j, n_local)
            swap = gv[i] > gv[j]
            i, j = np.where(swap, j, i), np.where(swap, i, j)
            out, far_min = self._close_pairs(P, Prest, gv, free, owner, i, j, None, far)
        self._pairs_cache = (x.copy(), out, far_min)
        return (out, far_min) if far else out

    def _count_work(self, wisp, i, j, n_local):
        """``-lc_contact_work balanced``: add a broad phase's work to :attr:`wisp_work`,
        its candidate pairs (i, j) (each its lower wisp's, see :meth:`start_frame`) and
        its n_local segments, at :data:`SEGMENT_WORK` pairs each (``wisp``: the wisp of
        each gathered segment).  ccd mode counts the limiter's broad phases, penalty mode
        the pairs' (it has no limiter: on main a83e279 it counted nothing, and ``balanced``
        ran the owner rule)."""
        if self.work == "balanced":
            self.wisp_work += np.bincount(np.minimum(wisp[i], wisp[j]), minlength=self.n_wisps_global)
            self.wisp_work += SEGMENT_WORK * np.bincount(wisp[:n_local], minlength=self.n_wisps_global)

    def _close_pairs(self, P, Prest, gv, free, owner, i, j, d, far):
        """(the :meth:`_pairs` tuple, far_min) of the candidates (i, j) (gv[i] < gv[j]) of
        the segments P (m, 2, 3) (rest Prest, first global vertex gv, free, owner rank) at
        distances d (None: computed here); far_min (``far``, else None): the smallest
        distance of the candidates at d0 or more."""
        if d is None:
            d = compiled_ccd.pair_distances(P, i, j)
        close = d < self.d0
        # exemption: pairs already within the thickness in the rest pose (docs/contact.md)
        sel = np.flatnonzero(close)
        if len(sel):
            close[sel] = compiled_ccd.pair_distances(Prest, i[sel], j[sel]) >= self.d0
        sel = np.flatnonzero(close)
        # a canonical order: the assembly's sums do not depend on the candidates' order
        sel = sel[np.argsort(gv[i[sel]] * self.N + gv[j[sel]])]
        far_min = float(np.min(d, where=d >= self.d0, initial=np.inf)) if far else None
        i, j = i[sel], j[sel]
        X = np.concatenate([P[i], P[j]], axis=1)
        return (X, gv[i], gv[j], free[i], free[j], owner[i], owner[j], d[sel]), far_min

    def _reached(self, x):
        """(P, Prest, gv, free, owner, i, j, d) as :meth:`_pairs` needs them (d: the pairs'
        distances), from the limiter call that produced x (bit for bit on every rank),
        else None.  The limiter's candidates are chosen with a reach of at least d0 (:meth:`_safe_fractions`), so
        they hold every pair closer than d0 at the end of its path, and the segments'
        positions there are known on every rank (ghosts included): the candidates whose
        boxes grown by d0 / 2 overlap there are exactly those of :meth:`candidates`
        among the pairs closer than d0."""
        if self._limited is None:
            return None
        x_end, P, Prest, gv, free, owner, i, j = self._limited
        if not global_min(self.comm, int(np.array_equal(x_end, x))):
            return None
        i, j, d = compiled_ccd.near_pair_distances(P, np.minimum(P[:, 0], P[:, 1]), np.maximum(P[:, 0], P[:, 1]),
                                                   i, j, 0.5 * self.d0)
        return P, Prest, gv, free, owner, i, j, d

    # ------------------------------------------------------------- ccd mode
    def limit_step(self, x, target, linear=None):
        """The Newton update from x towards ``target`` (x + alpha dx, or its edge-length
        retraction or corotational update).  ``penalty`` mode: ``target``.  ``ccd`` mode:
        x + beta (target - x) with per-vertex fractions beta of :meth:`_safe_fractions`,
        so that on the linear path from x no two segments of different wisps come closer
        than min_separation d0 (or half their distance at x, if already closer).  Per
        vertex rather than one global minimum: one pair about to touch would otherwise
        stop the whole scene's step.  ``linear`` (x + alpha dx, when ``target`` is a
        nonlinear update of it): if any vertex of ``target``'s path is cut, the linear
        update is limited instead (fractions of a retracted step stretch the edges they
        cut more: measured on six touching wisps, docs/contact.md), so the nonlinear
        update is taken whole or not at all; ``replaced`` then says so (and
        ``updates_replaced`` counts it; ``limited_vertices`` counts both calls' cuts),
        ``last_cut`` whether the positions returned were cut.  Collective (the counts
        are global)."""
        self.replaced = self.last_cut = False
        if self.mode != "ccd":
            return target
        with self.timers("collision"):
            limited, n_limited, rounds = self._safe_fractions(
                x, target, self.min_separation * self.d0, NEWTON_STEP_MOTION)
            if n_limited and linear is not None:
                self.replaced = True
                self.updates_replaced.add(1)
                self.limited_vertices.add(n_limited)        # the nonlinear target's cut
                self.limit_rounds.add(rounds)
                limited, n_limited, rounds = self._safe_fractions(
                    x, linear, self.min_separation * self.d0, NEWTON_STEP_MOTION)
            self.last_cut = bool(n_limited)
            self.limited_vertices.add(n_limited)
            self.limit_rounds.add(rounds)
        return limited

    def collision_free_frame(self, x_old, x, motion=None, reuse=True):
        """(positions, vertices held back over all ranks): positions whose linear path
        from ``x_old`` (the previous frame) is collision-free (``ccd`` mode; else ``x``,
        0), for the frame's first Newton iterate (xhat = x_old + dt v with the pinned
        vertices moved by the head: inertia alone would carry wisps through each other)
        and for its end (each Newton step is limited, but the straight path x_old -> x
        can still cross).  The free vertices of pairs that meet on it are held back:
        H + beta (x - H), beta from :meth:`_safe_fractions`, H = x_old carried by
        ``motion`` (Q, q), the head's rigid motion x -> Q x + q between the two frame
        times (:meth:`HeadMotion.rigid_motion`; the pinned vertices follow it exactly,
        so their residual is 0 and a pair is always resolvable by its free vertices),
        or by the fitted field (:meth:`_motion_field`) without one or when the head
        turns by more than :data:`MAX_RIGID_DEGREES` in the step.  ``reuse``: the check
        keeps (or takes) the ghosts and candidate pairs of boxes grown by
        :data:`LIMITER_SKIN` d0 for the checks after it (the frame end's); the first
        iterate's check passes False: the Newton steps move the hair by more than the
        skin, so the frame end never reused its pairs (2K and 8K hairballs, docs/contact.md),
        and the grown boxes cost 3x the pairs.  It leaves the last cache alone (the frame
        end's first check may still reuse the previous frame end's, in a scene that barely
        moves), and neither uses nor records :meth:`_first_round`'s path ends.  Collective."""
        if self.mode != "ccd":
            return x, 0
        with self.timers("collision"):
            skin = LIMITER_SKIN * self.d0 if reuse else 0.0
            limited, n_limited, _ = self._safe_fractions(x_old, x, 0.05 * self.d0, motion, skin=skin)
            self.frame_fixes.add(n_limited)
        return limited, n_limited

    def _motion_field(self, S, T, motion=None):
        """(A, b, L): the affine field u(x) = A x + b of the limiter's fallback S + u(S)
        and its Lipschitz constant L = ||A||_2.  ``motion`` (Q, q), a rigid motion
        x -> Q x + q (the head's between two frame times): u(S) = (Q - I) S + q, with
        L = 2 sin(theta / 2), theta the rotation angle, used while L <= 1/2 (theta
        <= :data:`MAX_RIGID_DEGREES`); the same on every rank bit for bit (no
        reduction).  Otherwise the field fitted to the displacements T - S (nv, 3) of
        all vertices of all ranks (least squares; L capped at 1/2 by
        :func:`segment_ccd.affine_field`): the sums are allreduced and rank 0's
        solution is broadcast.  One field for all ranks (the broad phase's proof
        needs the same u on both sides of a pair).  Collective."""
        if motion is not None:
            A = np.asarray(motion[0], float) - np.eye(3)
            L = float(np.linalg.norm(A, 2))
            if L <= MAX_LIPSCHITZ:
                return A, np.asarray(motion[1], float), L
        M, R = segment_ccd.affine_sums(S, T - S)
        buf = global_reduce(self.comm, np.concatenate([M.ravel(), R.ravel()]), "sum")
        field = segment_ccd.affine_field(buf[:16].reshape(4, 4), buf[16:].reshape(4, 3),
                                         MAX_LIPSCHITZ) if self.comm.rank == 0 else None
        return self.comm.bcast(field, root=0)

    def _safe_fractions(self, S, T, min_distance, motion=None, skin=0.0):
        """(E, vertices limited over all ranks, rounds): the positions E = H + beta (T - H)
        (nv, 3) (exactly T where beta = 1), with per-vertex fractions beta in [0, 1] and
        fallback positions H such that on the linear path from S to E no pair of
        segments of different wisps (rest-exempt pairs excepted) comes closer than
        ``min_distance``, or half its distance at S when already closer (but not below
        :data:`compiled_ccd.HOLD_FLOOR` ``min_distance`` unless it starts there: then its
        distance at S).  H = S + u(S),
        u the affine field fitted to the whole step (:meth:`_motion_field`): a held-back
        vertex is carried along with the bulk of the hair instead of being left behind,
        and only its residual motion f = T - H is cut.  Pinned vertices keep beta = 1 (their motion is prescribed).
        Collective.

        1. Broad phase on relative motion: whatever the fractions, every vertex moves by
           u(S) + beta f, so relative to the field a segment's points stay in the hull
           of its vertices at S and at S + f, and a pair can come within m only if the
           boxes of :func:`segment_ccd.field_boxes` around those hulls (grown by
           (m / 2 + L rho) / (1 - L), rho = the segment's largest |f|, L the field's
           Lipschitz constant; proof there) overlap.  They select the ghosts
           (:meth:`_gather_segments`: a rank gets every segment that can reach its own
           during the step, for any fractions), :func:`box_pairs` the candidates, one
           set for all rounds.  Hair swinging with the head moves by u,
           not by f: the boxes are set by how much a segment moves relative to the bulk.
           The boxes are built for a reach of d0 (more than m): the candidates then hold
           every pair closer than d0 at the path's end, which the contact's next pair
           search at the limited positions takes (:meth:`_reached`); the pair test gets
           those within reach m (the boxes shrunk by the growths' difference).  The
           frame path checks (``skin`` > 0) exchange ghosts within 2 ``skin`` and pair
           the boxes grown by ``skin``; a later check whose boxes all lie inside those
           grown boxes (on every rank) reuses both and only exchanges the ghosts'
           positions (:meth:`_exchange`): the pairs it tests are the same.
        2. Pair test (:func:`compiled_ccd.limit_pairs`, compiled): on the pair's current
           path, swept spheres around the centre paths discard most candidates without
           a distance; the others get conservative advancement with up to
           compiled_ccd.MAX_STEPS steps (no Tight-Inclusion: see docs/contact.md).
        3. Rounds: a pair whose current path comes closer than half its floor m
           (min_distance, or half its distance at S, see above) multiplies the fractions of its
           free vertices by its safe fraction at m (the first SCALE_ROUNDS rounds; its
           path then keeps m, clear of the m / 2 test, so round-off cannot flip its
           fate), later by 0, i.e. they move by u alone.  A pair whose free vertices
           all move by u keeps at least (1 - L) of its distance plus its pinned
           vertices' residuals; with L <= 1/2 and no pinned vertex it stays clear of
           the m / 2 test, so each round after the scaling ones stops at least one more
           vertex and the loop ends.  The smallest factor per vertex is taken over all
           ranks (a reverse scatter with MAX_VALUES of 1 - factor to the vertex owner),
           and the new fractions come back to every pair through a scatter.  Only pairs
           with a changed vertex are tested again.  After each round the fractions are
           smoothed along the strands (:func:`smooth_fractions`, FRACTION_STRAIN): a
           vertex held back holds its neighbours back too, so the limited update stretches
           no edge by more than that (per-vertex fractions tore strands, docs/contact.md
           "Torn strands"); they only go down, and their pairs are tested again in the
           next round like any other change.  A pair whose free vertices are all
           stopped can still be hit by its pinned vertices' residual motion (a root
           segment turning with the head differently from the fitted field): such pairs
           are left as they are and counted in ``unresolved_pairs``."""
        nv, d0 = self.scene.nv, self.d0
        md = float(min_distance)
        A, b, L = self._motion_field(S, T, motion)
        H = S + (S @ A.T + b)
        F = T - H
        # reach d0, not just md (and 1e-6 more, for round-off): the candidates then also
        # hold every pair closer than d0 at the path's end, so the next _pairs call at the
        # limited positions reuses them (_reached) instead of its own broad phase
        reach = max(md, d0 * (1.0 + 1e-6))
        lo, hi = compiled_ccd.field_boxes(S, F, self.seg, L, reach)
        cache = self._path_cache if skin > 0.0 else None
        if cache is not None and global_min(self.comm, int(np.all(lo >= cache[0]) and np.all(hi <= cache[1]))):
            # every box inside its skin: the ghosts and box pairs of the call that built it
            # hold every segment and pair these boxes can reach (a superset, filtered below)
            PS, PT, PH, PB = self._exchange([compiled_ccd.segment_ends(a, self.seg) for a in (S, T, H)] + [
                                             np.stack([lo, hi], axis=1)], cache[2])
            Prest, gv, wisp, free, owner, n_local, ij = cache[3]
            self.path_checks_reused += 1
            hulls = None        # its first round tests few pairs (_first_round): no hull test
        else:
            # ghosts within 2 skin of a box of the receiving rank, pairs of boxes grown by skin
            masks = []
            (PS, PT, PH, PB), Prest, gv, wisp, free, owner, n_local = \
                self._gather_segments(S, (T, H), inflate=2.0 * skin, boxes=(lo, hi), masks=masks)
            ij = box_pairs(PB[:, 0] - skin, PB[:, 1] + skin, group=wisp, n_local=n_local,
                           **self.self_pairs(len(PB)))
            if skin > 0.0:
                self._path_cache = (lo - skin, hi + skin, masks,
                                    (Prest, gv, wisp, free, owner, n_local, ij))
            hulls = (PS, PT, PH, L, md)
        # the pairs with a local segment, the smaller global segment first (on any
        # partition); the pair test needs those within reach md only, whose boxes are
        # these shrunk by the difference of the growths (the same for every segment), and
        # with a free vertex (pinned pairs move rigidly); shrunk by a hair less, so that
        # round-off cannot drop a pair that boxes built for md would keep; and of those,
        # the pairs whose hulls a separating axis does not prove md apart (the boxes keep
        # 2.7x the pairs the hulls do at 2K; the others would all get tau = 1)
        shrink = 0.5 * (reach - md) / (1.0 - L) * (1.0 - 1e-9)
        ci, cj, keep, dist = compiled_ccd.order_candidates(ij, n_local, gv, PB[:, 0], PB[:, 1], shrink, free,
                                                           hulls=hulls)
        self._count_work(wisp, ci, cj, n_local)
        # the segments' vertices: V sorted global vertices, sv (m, 2) their index in V;
        # the kept pairs (i, j) and their points inv (k, 4) in V
        V, sv = compiled_ccd.segment_vertices(gv)
        i, j, inv = compiled_ccd.kept_pair_points(ci, cj, keep, sv)
        SV, TV, HV, fV = compiled_ccd.segment_points(sv, len(V), PS, PT, PH, free)
        exempt = np.zeros(len(inv), np.int8)      # rest-exempt: 0 unknown, 1 no, 2 yes
        first = self._first_round(skin, md, V, SV, HV, TV, inv)
        self.step_fraction.set(1.0)
        beta = self.step_fraction.array           # this rank's vertices, a view
        limited = np.zeros(nv, bool)
        slack = compiled_ccd.edge_slack(F, self.seg, self.rest_seg_length, FRACTION_STRAIN)
        free_vertex = ~self.scene.pinned
        rounds = 0
        with _VertexGather(self.step_fraction, V, 1) as vg:
            tau, factor = np.ones(len(inv)), np.ones(len(inv))
            # d(S) of the hull test, the pair test's bit for bit (NaN: computed when needed)
            start_distance = dist[keep] if hulls is not None else np.full(len(inv), np.nan)
            seen = np.zeros(len(inv), bool)
            incidence = None
            act = np.zeros(0, np.int64)         # the pairs acted on in the last round
            bV_prev = None
            E = TV.copy()                       # the paths' ends: every fraction starts at 1
            while True:
                bV = vg.gather(self.step_fraction).copy()
                # only pairs with a vertex whose fraction changed have a new path (the
                # fractions only go down: a changed one is below 1)
                if bV_prev is None:
                    redo = first
                else:
                    changed = bV != bV_prev
                    ch = np.flatnonzero(changed)
                    E[ch] = HV[ch] + bV[ch, None] * (TV[ch] - HV[ch])
                    if incidence is None and rounds >= INCIDENCE_ROUND:
                        incidence = compiled_ccd.point_pairs(inv, len(V))
                    if incidence is None:
                        redo = compiled_ccd.changed_pairs(inv, changed)
                    else:
                        redo = compiled_ccd.pairs_at_points(incidence, ch, seen)
                bV_prev = bV
                compiled_ccd.limit_pairs(SV, E, inv, redo, md, rounds < SCALE_ROUNDS, tau, factor,
                                         start_distance, rtol=ADVANCE_RTOL)
                hit = redo[tau[redo] < 1.0]     # only the tested pairs' tau changed
                new = hit[exempt[hit] == 0]
                if len(new):     # rest-exempt pairs (docs/contact.md) are not limited
                    Xr = np.concatenate([Prest[i[new]], Prest[j[new]]], axis=1)
                    exempt[new] = np.where(segment_contact.distance(Xr) < d0, 2, 1)
                # acted on: the pairs hit now, and those of the last round not tested again
                # (no vertex changed: still hit, and still with a vertex left to stop)
                seen[redo] = True
                act = np.concatenate([act[~seen[act]], hit[exempt[hit] != 2]])
                seen[redo] = False
                # held back as far as it goes: only the pinned vertices' residual motion
                # moves the pair closer (counted below, not fixable by the free vertices)
                iv = inv[act]
                act = act[_any_column((bV[iv] != 0.0) & fV[iv])]
                if self.comm.allreduce(len(act)) == 0:
                    break
                fmin = np.ones(len(V))
                f_ = factor[act] if rounds < SCALE_ROUNDS else np.zeros(len(act))
                np.minimum.at(fmin, inv[act].ravel(), np.repeat(f_, 4))
                fmin[~fV] = 1.0                 # pinned vertices keep their prescribed motion
                self.shrink.zeroEntries()
                vg.reverse(1.0 - fmin, self.shrink, PETSc.InsertMode.MAX_VALUES)
                # beta *= 1 - shrink, then along each strand: a vertex held back holds its
                # neighbours back too, so no edge stretches by more than FRACTION_STRAIN
                # (the changed vertices' pairs are tested again next round)
                compiled_ccd.shrink_and_smooth(beta, self.shrink.array, limited, slack, self.seg,
                                               self.seg_offsets, self.vertex_wisp, free_vertex)
                rounds += 1
            held = np.flatnonzero((tau < 1.0) & (exempt != 2))
            iv = inv[held]
            stopped = held[~_any_column((bV[iv] != 0.0) & fV[iv])]
            # a stopped pair moving with the field stays apart (it only misses its hold
            # target by the field's shear); the rest may cross and are counted
            stuck = int(np.sum(~kept_apart_by_field(SV, E, inv[stopped], start_distance[stopped], A, b, L)))
        beta = np.where(self.scene.pinned, 1.0, beta)
        # per vertex: a move made to T before this check is in E times beta (the
        # integrator leaves the kept part of its head lift out of the velocity)
        self.path_fraction = beta
        if skin > 0.0:
            held_points = np.zeros(len(V), bool)
            held_points[inv[tau < 1.0].ravel()] = True
            self._path_ends = (md, V, SV, HV, E, held_points)
        # E: the path's end on every pair vertex, equal to the positions bit for bit
        positions = _held_back(H, T, beta)
        self._limited = (positions.copy(), E[sv], Prest, gv, free, owner, ci, cj)
        # the statistics in one reduction at the end: each reduction is a point where
        # the ranks wait for the slowest (2 fewer per call)
        n_candidates, n_stuck, n_limited = (int(v) for v in self.comm.allreduce(
            np.array([len(i), stuck, int(limited.sum())], np.int64)))
        self.limiter_candidates.add(n_candidates)
        self.unresolved_pairs.add(n_stuck)
        return positions, n_limited, rounds

    def _first_round(self, skin, md, V, SV, HV, TV, inv):
        """The pairs of ``inv`` the first round of a path check (``skin`` > 0) tests: all,
        or after a path check with the same floor ``md``, points ``V``, starts ``SV`` and
        fallbacks ``HV`` (bit for bit: the frame end's checks after its first), only
        those with a point whose path end ``TV`` differs from that check's final one or
        that was in a pair it left held (tau < 1).  Any other pair would get tau = 1: its
        four points' path ends are that check's final ones, so its path is one of the
        paths of that check's family.  If that check kept the pair, the pair was last
        tested on that very path and got tau = 1 (tau depends on SV, E at its points and
        md only; a pair whose point changed is always tested again before a check ends).
        If that check did not keep it (its boxes, which hold these boxes, prove the
        distance stays above md on every path of the family), conservative advancement
        at m / 2 <= md / 2 reaches t = 1 with every gap above md / 2 (it would need a
        relative motion of MAX_STEPS md / 2 to run out of steps).  So skipping it changes
        no bit (2.3M such pairs took 0.3 s a check at 8K), as long as ADVANCE_RTOL and
        MAX_STEPS stay the same between checks.  Only path checks with a skin record and
        use this; the first iterate's (``reuse=False``) tests every pair."""
        prev = self._path_ends
        if skin > 0.0 and prev is not None and prev[0] == md and np.array_equal(prev[1], V) \
                and np.array_equal(prev[2], SV) and np.array_equal(prev[3], HV):
            return compiled_ccd.changed_pairs(inv, _any_column(TV != prev[4]) | prev[5])
        return np.arange(len(inv))

    # ------------------------------------------------------------- public
    def energy(self, x):
        """Contact energy summed over all ranks (collective)."""
        with self.timers("collision"):
            with collectively(self.comm, "strand contact (energy)"):
                X = self._pairs(x)[0]
                e = float(self.kernel.energy(X, self.d0, self.kernel_stiffness).sum()) if len(X) else 0.0
            return self.comm.allreduce(e)

    def start_frame(self):
        """A new frame: the per-frame statistics start new entries; with ``balanced``
        contact work, the wisps' contact ranks from the last frame's work (candidate
        pairs and segments; the same on every rank: one allreduce).  Collective."""
        if self.work == "balanced":
            work = global_reduce(self.comm, self.wisp_work, "sum")
            self.wisp_work[:] = 0
            if work.sum() > 0:
                # contiguous runs of wisps (a region of the head each: the internal order
                # follows a space-filling curve of the roots) of equal work, each candidate
                # pair counted for its lower wisp: contact ranks do not decrease along the
                # wisps, so the lower wisp's rank is the one computing the pair
                ranges = partition(work.astype(np.int64), self.comm.size)
                self.contact_rank = np.searchsorted(ranges, self.seg_wisp, side="right") - 1
        for tally in (self.ghosts_received, self.cross_pairs, self.limited_vertices, self.limit_rounds,
                      self.frame_fixes, self.unresolved_pairs, self.limiter_candidates,
                      self.updates_replaced):
            tally.start_frame()

    def measure(self, x):
        """(active pairs, pairs closer than d0 / 2, minimum distance over candidate
        pairs) over all ranks (exempt pairs excluded); the minimum is inf when no two
        segments of different wisps are within the search radius."""
        with self.timers("collision"):
            with collectively(self.comm, "strand contact (measure)"):
                pairs, far_min = self._pairs(x, far=True)
                d = pairs[-1]
            n, deep = self.comm.allreduce(np.array([len(d), np.sum(d < 0.5 * self.d0)]))
            dmin = global_min(self.comm, min(float(d.min(initial=np.inf)), far_min))
        return int(n), int(deep), dmin

    def min_distance(self, x, dmin, hint=np.inf):
        """The smallest distance at x between two segments that may be in contact (of
        different wisps; with self-contact also non-neighbours of one wisp), exempt pairs
        closer than d0 left out; inf when there is no such pair.  ``dmin`` is
        :meth:`measure`'s at x: exact below d0 (every pair closer than d0 is a
        candidate), else only the closest candidate of the d0 broad phase (from_file
        frame 5: 0.2527 cm for a true 0.1379).  Then broad phases of a growing reach m
        (from ``hint``, the last frame's value, or 2 d0) until one holds a pair closer
        than m: all pairs closer than m are its candidates.  Collective."""
        if dmin < self.d0:
            return dmin
        span = global_reduce(self.comm, np.concatenate([-x.min(axis=0, initial=np.inf),
                                                        x.max(axis=0, initial=-np.inf)]), "max")
        span = float(np.linalg.norm(span[:3] + span[3:]))
        m = min(dmin, max(1.05 * hint if hint < np.inf else 0.0, 2.0 * self.d0))
        with self.timers("collision"):
            while True:
                reach = m * (1.0 + 1e-9)            # the closest candidate counts as found
                found = self._closest_within(x, reach)
                if found <= reach or (found == np.inf and reach > span):
                    return found
                m = found if found < np.inf else 2.0 * reach

    def _closest_within(self, x, reach):
        """The smallest distance of the candidates of a broad phase of reach ``reach`` at
        x, over all ranks, pairs closer than d0 left out (with no pair closer than d0 that
        is not exempt, those are exempt); inf when there is none.  Collective."""
        with collectively(self.comm, "strand contact (minimum distance)"):
            (P,), _, _, wisp, _, _, n_local = self._gather_segments(x, inflate=reach)
            ij = self.candidates(P, wisp, n_local, reach, **self.self_pairs(len(P)))
            d = compiled_ccd.pair_distances(P, ij[:, 0], ij[:, 1])
            local = float(np.min(d, where=d >= self.d0, initial=np.inf))
        return global_min(self.comm, local)

    def separate(self, x, floor=0.5, target=0.6, max_iterations=20, max_step=0.25):
        """Positions (nv, 3) with no pair closer than ``floor`` d0: pairs closer than
        (floor + target) / 2 d0 are pushed apart towards ``target`` d0 (rest-exempt pairs
        excepted) until none is closer than ``floor`` d0 (1 + 1e-3); returns (positions,
        pairs that were closer than ``floor`` d0, iterations).  Collective.  The gap
        between the threshold and the target keeps projected pairs away from the
        threshold, so round-off cannot flip a pair's fate (runs on different rank counts
        stay equal to round-off).

        Run once per frame after the Newton iterations: a fixed number of Newton steps
        does not converge the contact set (docs/contact.md), and its last step, never
        re-assembled, can push pairs deep into each other.  Jacobi iterations of the
        mass-weighted projection :func:`segment_contact.separation` over the pairs closer
        than d0 at the start.  Per round, each pair's correction is capped at
        ``max_step`` d0 (a pair with pinned vertices can demand more) and divided by
        the largest number of violating pairs at one of its four vertices, counted over
        all ranks, over :data:`SEPARATION_OVERRELAXATION` omega (divided by 1 at least):
        no vertex moves more than omega ``max_step`` d0 per round, the result does not
        depend on the partition, and linear momentum is conserved (pinned vertices
        excepted).  Counts and corrections are summed by global vertex in PETSc Vecs
        (off-process vertices travel to their owners); the pair vertices' positions and
        counts come back through a VecScatter.  Per round, the distances of the pairs with
        a vertex that moved, the pairs to push and the count below the floor are one
        compiled pass over the gathered positions (:class:`compiled_ccd.PairDistances`),
        the Vec assemblies carry the hit pairs' vertices only, and the shift and the edge
        bounds below are one compiled pass on the state array
        (:func:`compiled_ccd.shift_and_bound`, the edges queued from the vertices the
        round moved): a round with a few pairs left costs little more than its two
        scatters.

        ccd mode (``edge_bounds``): after each round's corrections, the edges whose
        length left [L (1 - s), L (1 + s)] (L rest, s = :data:`SEPARATION_STRAIN`) are
        projected back into it (:func:`bound_edge_lengths`, mass-weighted, pinned
        vertices fixed; a wisp lives on one rank, so no communication): a push that
        would tear a strand moves its neighbours along instead, and edges already torn
        (by the limiter holding vertices back) are pulled back too (bounding them by
        their length at the call instead left 13 edges beyond +-10% at frame 40 of the
        2K hairball, docs/contact.md "Strain-aware separation")."""
        d0, nv = self.d0, self.scene.nv
        with self.timers("collision"):
            with collectively(self.comm, "strand contact (separation)"):
                gA, gB = self._pairs(x)[1:3]
                V, inv = np.unique(np.stack([gA, gA + 1, gB, gB + 1], axis=1), return_inverse=True)
                inv = inv.reshape(-1, 4)
            st = self.state.array.reshape(nv, 5)         # x, y, z, 1 / mass, count
            st[:, :3] = x
            st[:, 3] = self.inverse_mass
            x = st[:, :3]                                # the rounds move the state's positions
            Vi = V.astype(PETSc.IntType)
            first = below = it = 0

            def add_by_vertex(rows, values):    # values (len(V), 4), summed by global vertex
                self.correction.zeroEntries()      # over its rows (the others are zero)
                self.correction.setValuesBlocked(Vi[rows], values[rows].ravel(),
                                                 addv=PETSc.InsertMode.ADD_VALUES)
                self.correction.assemblyBegin()
                self.correction.assemblyEnd()
                return self.correction.array.reshape(nv, 4)

            # per round, only the pairs with a vertex that moved get a new distance
            distances = compiled_ccd.PairDistances(inv, len(V))
            with _VertexGather(self.state, V, 5) as vg:
                for it in range(max_iterations + 1):
                    Y = vg.gather(self.state).reshape(-1, 5)
                    hit, below = distances.refresh(Y, 0.5 * (floor + target) * d0, floor * d0 * (1.0 + 1e-3))
                    below = self.comm.allreduce(below)
                    if it == 0:
                        first = below
                    if below == 0 or it == max_iterations:
                        break
                    acc = np.zeros((len(V), 4))
                    acc[:, 3] = np.bincount(inv[hit].ravel(), minlength=len(V))
                    rows = np.flatnonzero(acc[:, 3])       # the hit pairs' vertices
                    st[:, 4] = add_by_vertex(rows, acc)[:, 3]
                    count = vg.gather(self.state).reshape(-1, 5)[:, 4]
                    with collectively(self.comm, "strand contact (separation)"):
                        dx = segment_contact.separation(Y[inv[hit], :3], Y[inv[hit], 3], target * d0)
                        # at most max_step d0 per pair (a pair with pinned vertices can ask
                        # for more), then / (the largest count at its vertices / omega), by 1
                        # at least: a vertex then moves at most omega max_step d0 per round;
                        # one factor per pair keeps sum m dx = 0
                        step = np.sqrt(np.einsum("pvc,pvc->pv", dx, dx)).max(axis=1, initial=0.0)
                        scale = np.minimum(1.0, max_step * d0 / np.maximum(step, 1e-300))
                        scale *= np.minimum(1.0, SEPARATION_OVERRELAXATION
                                            / np.maximum(count[inv[hit]].max(axis=1, initial=1.0), 1.0))
                        dx *= scale[:, None, None]
                        acc[:] = 0.0
                        for c in range(3):
                            acc[:, c] = np.bincount(inv[hit].ravel(), weights=dx[:, :, c].ravel(),
                                                    minlength=len(V))
                    shift = add_by_vertex(rows, acc)
                    if self.edge_bounds is None:
                        x += shift[:, :3]
                    else:
                        # after the first round, only the edges at a vertex this round
                        # moved can have left their bounds
                        compiled_ccd.shift_and_bound(x, shift, self.seg, self.seg_colour, *self.edge_bounds,
                                                     self.inverse_mass, it == 0, EDGE_SWEEPS, self.edge_work)
            x = x.copy()
        self.last_separation = (first, it, below)
        return x, first, it

    def assemble(self, x, asm):
        """Contact gradient (nv, 3) (pinned rows zero) of this rank's vertices; adds the
        band blocks to ``asm`` (before its ``commit``) and rebuilds the contact matrix C.
        Collective."""
        sc = self.scene
        with self.timers("collision"):
            with collectively(self.comm, "strand contact"):
                X, gA, gB, fA, fB, oA, oB, d = self._pairs(x)
                m = len(X)
                free = np.concatenate([fA, fB], axis=1)                          # (m, 4)
                if self.potential == "penalty" and self.filter == "analytic":
                    # the same values, compiled and fused (no (m, 12, 12) Hessians)
                    rows, cross_ab, cross_ba = compiled_contact.penalty_rows(X, self.d0, self.kernel_stiffness,
                                                                             free, oA, oB)
                else:
                    g, H = self.kernel.gradient_hessian(X, self.d0, self.kernel_stiffness, filter=self.filter) \
                        if m else (np.zeros((0, 4, 3)), np.zeros((0, 12, 12)))
                    pin = np.flatnonzero(~free.all(axis=1))
                    if len(pin):          # pinned vertices: no contact rows or columns
                        fr = np.repeat(free[pin], 3, axis=1).astype(float)
                        g[pin] *= free[pin, :, None]
                        H[pin] *= fr[:, :, None] * fr[:, None, :]
                    rows = compiled_ccd.pair_rows(g, H, oA, oB)          # (2m, NB)
                    cross_ab = np.ascontiguousarray(H[:, 0:6, 6:12]).reshape(m, 36)
                    cross_ba = np.ascontiguousarray(H[:, 6:12, 0:6]).reshape(m, 36)
                idx = np.concatenate([gA, gB]).astype(PETSc.IntType)
                self.last_min_distance = float(d.min(initial=np.inf))
            vec = self.vec
            vec.zeroEntries()
            if m:
                vec.setValuesBlocked(idx, rows.ravel(), addv=PETSc.InsertMode.ADD_VALUES)
            vec.assemblyBegin()
            vec.assemblyEnd()
            loc = vec.getArray(readonly=True).reshape(-1, NB)
            gc = np.zeros_like(x)
            gc += loc[:, 0:3]
            gc[1:] += loc[:-1, 3:6]                     # a wisp's last row is all zero
            hit = np.flatnonzero(loc[:, 33] + loc[:, 34])       # segment rows with pairs
            Lh = loc[hit]
            asm.add_band_blocks(hit, Lh[:, 6:15].reshape(-1, 3, 3), Lh[:, 15:24].reshape(-1, 3, 3),
                                Lh[:, 24:33].reshape(-1, 3, 3))
            gc[sc.pinned] = 0.0
            # contact matrix: exact preallocation from the counts, cross blocks only
            nv = sc.nv
            dn = np.zeros(nv)
            on = np.zeros(nv)
            dn += loc[:, 33]
            dn[1:] += loc[:-1, 33]
            on += loc[:, 34]
            on[1:] += loc[:-1, 34]
            n_global, n_cross = self.comm.allreduce(np.array([m, int(np.sum(oA != oB))]))
            self.last_pairs = int(n_global)
            self.cross_pairs.add(int(n_cross))
            self.last_min_distance = global_min(self.comm, self.last_min_distance)
            self._rebuild_matrix(n_global, dn, on, cross_ab, cross_ba, gA, gB)
        return gc

    def _rebuild_matrix(self, n_global, dn, on, cross_ab, cross_ba, gA, gB):
        """C: the cross blocks (segment A x segment B, ``cross_ab`` (m, 36), and its
        transpose, ``cross_ba``, each pair's 6 x 6 block row-major) of the active pairs, in
        a matrix of the strand matrix's type (for SBAIJ the A x B blocks only: A's wisp
        precedes B's, so they are all above the diagonal)."""
        if self.shell_ctx is not None:      # never leave a destroyed C inside the shell
            self.shell_ctx.C = None
        if self.C is not None:
            self.C.destroy()
            self.C = None
        if n_global == 0:
            return
        nv, N = self.scene.nv, self.N
        upper = self.mat_type == "sbaij"
        d_nnz = np.minimum(dn, nv)             # (an upper bound for SBAIJ as well)
        o_nnz = np.minimum(on, N - nv)
        size = ((3 * nv, 3 * N), (3 * nv, 3 * N))
        if self.mat_type == "aij":
            C = PETSc.Mat().createAIJ(size=size, bsize=3, comm=self.pcomm,
                                      nnz=(np.repeat(3 * d_nnz, 3).astype(PETSc.IntType),
                                           np.repeat(3 * o_nnz, 3).astype(PETSc.IntType)))
        else:
            create = PETSc.Mat().createSBAIJ if upper else PETSc.Mat().createBAIJ
            C = create(size=size, bsize=3, comm=self.pcomm,
                       nnz=(d_nnz.astype(PETSc.IntType), o_nnz.astype(PETSc.IntType)))
        C.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
        ra = np.stack([gA, gA + 1], axis=1).astype(PETSc.IntType)
        rb = np.stack([gB, gB + 1], axis=1).astype(PETSc.IntType)
        if len(gA):
            add = PETSc.InsertMode.ADD_VALUES
            C.setValuesBlockedRCV(ra, rb, cross_ab, addv=add)
            if not upper:
                C.setValuesBlockedRCV(rb, ra, cross_ba, addv=add)
        C.assemble()
        self.C = C
        # what the coupled operator's direct fill adds (_summed_matrix)
        self._c_fill = (dn, on, ra, rb, cross_ab, None if upper else cross_ba) if self.coupled_pc else None

    def destroy(self):
        """Destroy the contact's PETSc objects (collective)."""
        if self.shell_ctx is not None:
            self.shell_ctx.C = None
        for m in (self.shell, self.op, self.C, self.vec, self.state, self.correction,
                  self.step_fraction, self.shrink):
            if m is not None:
                m.destroy()
        self.shell = self.op = self.C = self.vec = self.state = self.correction = None
        self.step_fraction = self.shrink = None


def kept_apart_by_field(SV, E, points, start, A, b, L):
    """Boolean (k,): whether each pair, its four points ``points`` (k, 4) into the starts
    ``SV`` and path ends ``E`` (n, 3), provably stays apart on its straight path when the
    points move with the affine field u(x) = A x + b (``L`` = ||A||_2 < 1) up to residuals
    r = E - (S + u(S)): the pair's difference at t is (I + t A)(p - q) + t (r_p - r_q)
    for points p, q of its two segments, so its distance stays at least (1 - L) d(S) -
    2 max |r| (d(S) = ``start`` (k,), NaN where not computed: not proven), which must be
    positive by more than round-off: such a pair cannot touch, let alone cross.  (The
    field's L <= 1/2, so without residuals it keeps half its start distance, the limiter's
    own threshold for a pair held at the floor, which conservative advancement bounding
    the motion by the corners' displacement could not prove: the stopped pairs at the hold
    floor under the head's turn, docs/contact.md "Known gap")."""
    if len(points) == 0:
        return np.zeros(0, bool)
    S4 = SV[points]
    residual = np.sqrt(np.sum((E[points] - (S4 + S4 @ A.T + b)) ** 2, axis=2)).max(axis=1)
    round_off = 1e-12 * (1.0 + np.abs(S4).max(axis=(1, 2)))
    with np.errstate(invalid="ignore"):
        return (1.0 - L) * start > 2.0 * (residual + round_off)


def _any_column(flags):
    """Rows of flags (n, k) bool with a True: ``flags.any(axis=1)``, column by column
    (NumPy's reduction along a short last axis is several times slower)."""
    out = flags[:, 0].copy()
    for c in range(1, flags.shape[1]):
        out |= flags[:, c]
    return out


def _held_back(start, end, beta):
    """start + beta (end - start) per vertex (nv, 3) (``start``: the limiter's fallback
    positions), and exactly ``end`` where beta = 1:
    an unlimited vertex keeps its update to the last bit (no round-off from the
    limiter, and the bit-identical pair cache stays valid)."""
    out = end.copy()
    k = beta < 1.0
    out[k] = start[k] + beta[k, None] * (end[k] - start[k])
    return out
