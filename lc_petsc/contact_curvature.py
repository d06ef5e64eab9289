"""Whether a Newton stop with strand contact is a saddle of G through the coupling of
wisps (docs/newton.md, "A saddle over contact-coupled wisps").

The per-wisp check (lc_petsc/curvature.py) sees each wisp's block of the Newton matrix
A + C alone.  Contact's cross blocks C couple wisps, and A + C can be indefinite while
every wisp block is definite: the six touching wisps in phase stopped on a saddle whose
negative mode (-0.517 in units of M/dt^2) spread over three wisps whose own blocks have
lowest eigenvalues 0.67-0.78.

The check: Lanczos on B^-1 (A + C) on the free DoFs, B the wisps' own blocks (A's
rank-local block, factored by the contact preconditioner's compiled band Cholesky; it
is definite where this check runs: the per-wisp check passed), from a fixed random
vector over the global vertex numbering (the same on any partition).  B^-1 (A + C) has
the inertia of A + C (Sylvester), and every Ritz value is a Rayleigh quotient of it,
so a negative Ritz value proves the saddle (no false positive beyond round-off); an
extreme outlier is found in a few iterations.  A positive verdict is not a proof: the
iteration stops once the lowest Ritz value has converged; where it has not by the cap,
the verdict is "unknown", not "minimum" (at the six wisps' minima the lowest eigenvalue
was found only after 21-54 iterations, behind a cluster of small ones: docs/newton.md
"The coupled check's iterations").  Collective: two reductions per iteration, the
verdict the same on every rank.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from mpi4py import MPI

from lc_petsc.elements.compiled_band import BandCholesky

#: the most Lanczos iterations per check (the six-wisp saddle is found in 3; the
#: lowest Ritz value at its minima converged after 8-54, and at 40 two of four had
#: not, one of them 32% above the lowest eigenvalue at 30: docs/newton.md "The
#: coupled check's iterations")
STEPS = 60
#: the lowest Ritz value has converged when its residual bound is below this share of it
CONVERGED = 1e-2
#: a Ritz value below -NEGATIVE times the largest one is negative curvature (round-off
#: of the Lanczos recurrence is far below it)
NEGATIVE = 1e-8
#: the start vector's seed (the same vector over the global vertex numbering on any run)
SEED = 20231207
#: a wisp is named in the verdict when it holds this share of the negative mode (in M)
NAMED_SHARE = 0.05


class Verdict(NamedTuple):
    """The check's result (the same on every rank): ``negative``: a saddle found;
    ``lowest``: the lowest Ritz value of B^-1 (A + C) (-inf where B itself is not
    definite); ``iterations``: Lanczos iterations; ``curvature``: where negative, the
    Ritz vector's Rayleigh quotient of A + C in units of M/dt^2 (an upper bound of
    dt^2 M^-1/2 (A + C) M^-1/2's lowest eigenvalue), else None; ``wisps``: where
    negative, the global wisps holding at least :data:`NAMED_SHARE` of it (by share);
    ``converged``: the lowest Ritz value converged (or a negative one proved the saddle);
    False: the cap came first, :attr:`unknown`."""

    negative: bool
    lowest: float
    iterations: int
    curvature: float | None = None
    wisps: tuple = ()
    converged: bool = True

    @property
    def unknown(self):
        """No negative Ritz value, but the lowest one had not converged at the cap: the
        lowest eigenvalue may lie below it, negative (neither a saddle nor a minimum)."""
        return not self.negative and not self.converged


class CoupledCurvature:
    """The check for one rank's wisps: ``offsets`` their local vertex offsets,
    ``first_wisp``, ``first_vertex`` the rank's first global wisp and vertex, ``free``
    (nv,) the free vertices, ``comm`` (mpi4py).  :meth:`check` runs it on an assembled
    matrix (the band Cholesky's layout is kept between checks)."""

    def __init__(self, offsets, first_vertex, free, comm):
        self.offsets = np.asarray(offsets, np.int64)
        self.first_vertex = int(first_vertex)
        self.free = np.repeat(np.asarray(free, bool), 3)
        self.comm = comm
        self.band = BandCholesky(self.offsets)
        self.n_global = int(comm.allreduce(int(self.offsets[-1])))
        self.start = self._start()      # the same at every check: drawn once

    def check(self, blocks, operator, unit, layout):
        """The verdict on ``operator`` (the PETSc Newton operator A + C) preconditioned
        by A's wisp blocks ``blocks`` (:meth:`Assembler.local_block_csr`: block rows,
        global block columns, row-major 3x3 values; upper blocks suffice);
        ``unit`` (nv,) M/dt^2 per vertex (for :attr:`Verdict.curvature`); ``layout``: an
        assembled matrix of the operator's layout (a Python-shell operator makes no
        vectors of its own).  Collective."""
        if not self._factor(*blocks):
            return Verdict(True, -np.inf, 0)
        xv, yv = layout.createVecs()
        try:
            def apply(u):
                xv.array[:] = u
                operator.mult(xv, yv)
                return yv.array * self.free

            alphas, betas, ritz, converged = self._lanczos(apply, self.start)
            if ritz[0] >= -NEGATIVE * max(abs(ritz[-1]), 1.0):
                return Verdict(False, float(ritz[0]), len(alphas), converged=converged)
            vector = self._ritz_vector(apply, alphas, betas)
            return self._negative(vector, apply, np.repeat(unit, 3), float(ritz[0]), len(alphas))
        finally:
            xv.destroy()
            yv.destroy()

    # ------------------------------------------------------------------ parts
    def _factor(self, rowptr, cols, values):
        """Factor the wisp blocks (from their upper blocks, mirrored into the lower
        triangle the band Cholesky reads); whether every rank's are definite."""
        rowptr, cols = np.asarray(rowptr, np.int64), np.asarray(cols, np.int64) - self.first_vertex
        rows = np.repeat(np.arange(len(rowptr) - 1), np.diff(rowptr))
        upper = cols >= rows
        # block (c, r) = block (r, c)^T; column-major storage of B^T is B row-major
        r, c = cols[upper], rows[upper]
        order = np.lexsort((c, r))
        r, c = r[order], c[order]
        vals = np.asarray(values, np.float64).reshape(-1, 9)[upper][order]
        indptr = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=len(rowptr) - 1))]).astype(np.int64)
        why = self.band.factor(indptr, c, np.ascontiguousarray(vals).ravel())
        return bool(self.comm.allreduce(why is None, op=MPI.LAND))

    def _start(self):
        """The start vector: uniform on [-1, 1] per global DoF from :data:`SEED` (the
        rank's slice), zero on pinned DoFs (every rank draws all 3 n_global of them)."""
        full = np.random.default_rng(SEED).uniform(-1.0, 1.0, 3 * self.n_global)
        return full[3 * self.first_vertex:3 * (self.first_vertex + int(self.offsets[-1]))] * self.free

    def _dot(self, a, b):
        return float(self.comm.allreduce(float(np.dot(a, b))))

    def _precondition(self, r):
        z = np.empty_like(r)
        self.band.apply(np.ascontiguousarray(r), z)
        return z * self.free

    def _recurrence(self, apply, start, steps, visit=None):
        """Preconditioned Lanczos from ``start`` (r-space): yields (alphas, betas) after
        each step, betas[j] the coupling of steps j and j + 1; ``visit(j, u_j)`` sees
        each x-space Lanczos vector u_j = B^-1 r_j / beta_j."""
        r = start
        z = self._precondition(r)
        beta = np.sqrt(max(self._dot(r, z), 0.0))
        alphas, betas = [], []
        p_prev = np.zeros_like(r)
        for j in range(steps):
            if not beta > 0.0:
                return
            u, p = z / beta, r / beta
            if visit is not None:
                visit(j, u)
            w = apply(u)
            alpha = self._dot(u, w)
            r = w - alpha * p - (betas[-1] if betas else 0.0) * p_prev
            z = self._precondition(r)
            beta = np.sqrt(max(self._dot(r, z), 0.0))
            alphas.append(alpha)
            betas.append(beta)
            p_prev = p
            yield alphas, betas

    def _lanczos(self, apply, start):
        """(alphas, betas, the Ritz values, converged) when a Ritz value is negative, the
        lowest has converged (its residual bound below :data:`CONVERGED` of it) or after
        :data:`STEPS` (converged False unless one of the first two held).  A recurrence
        that breaks down (beta 0: the Krylov space is invariant) has converged."""
        alphas, betas, ritz = [], [], np.zeros(1)
        converged = True
        for alphas, betas in self._recurrence(apply, start, STEPS):
            ritz, vectors = np.linalg.eigh(_tridiagonal(alphas, betas[:-1]))
            if ritz[0] < -NEGATIVE * max(abs(ritz[-1]), 1.0):
                break
            converged = bool(betas[-1] * abs(vectors[-1, 0]) <= CONVERGED * abs(ritz[0]))
            if converged:
                break
        return alphas, betas, ritz, converged

    def _ritz_vector(self, apply, alphas, betas):
        """The lowest Ritz vector (x-space): the recurrence run again (its vectors are
        not kept: on the 2K hairball 40 of them would take 200 MB a rank)."""
        s = np.linalg.eigh(_tridiagonal(alphas, betas[:-1]))[1][:, 0]
        vector = np.zeros(len(self.free))

        def visit(j, u):
            vector[:] += s[j] * u

        for _ in self._recurrence(apply, self.start, len(alphas), visit):
            pass
        return vector

    def _negative(self, vector, apply, unit, lowest, iterations):
        """The verdict of a negative Ritz value: the Rayleigh quotient in M/dt^2 units and
        the wisps holding the mode."""
        weighted = unit * vector ** 2
        curvature = self._dot(vector, apply(vector)) / self._dot(unit, vector ** 2)
        local = np.add.reduceat(weighted.reshape(-1, 3).sum(axis=1), self.offsets[:-1]) \
            if len(self.offsets) > 1 and self.offsets[-1] else np.zeros(len(self.offsets) - 1)
        local[np.diff(self.offsets) == 0] = 0.0
        shares = np.concatenate(self.comm.allgather(local))
        shares = shares / max(shares.sum(), np.finfo(float).tiny)
        named = [int(w) for w in np.argsort(-shares, kind="stable") if shares[w] >= NAMED_SHARE]
        return Verdict(True, lowest, iterations, float(curvature), tuple(named))


def _tridiagonal(alphas, off):
    T = np.diag(np.asarray(alphas, np.float64))
    if len(off):
        T += np.diag(off, 1) + np.diag(off, -1)
    return T
