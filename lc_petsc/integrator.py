"""BDF-1 (backward Euler) Newton on the incremental potential (SPEC 4).

Each frame solves  G(x) = 1/(2 dt^2) (x - xhat)^T M (x - xhat) + V(x) - f_ext^T x
(+ the head-sphere penalty), xhat = x_n + dt v_n, by Newton steps
(M/dt^2 + K^+) dx = -grad G with K^+ the filtered element Hessians.

* Initial iterate: xhat for free vertices; pinned vertices are moved to their prescribed
  position at t_{n+1} first, so their Newton increments are zero (identity rows/cols,
  zero right-hand side) and the prescribed motion enters through the elements.
* Termination: ``newton_iterations`` steps (default 3, the paper) or, when
  ``newton_tol`` is set, as soon as max_i |dx_i| < newton_tol (cm), whichever first.
* Optional Armijo backtracking on G (``line_search``): alpha halves from 1 until
  G(x + alpha dx) <= G(x) + 1e-4 alpha grad G . dx, at most 20 halvings.
* v_{n+1} = (x_{n+1} - x_n) / dt.
* Strand-strand contact (``strand``, a :class:`lc_petsc.contact.StrandContact`, set by
  the simulator when ``strand_collision`` is on) adds its penalty to G, its gradient,
  its band blocks to the Newton matrix and rebuilds the contact matrix every Newton
  iteration; its calls are collective, so they run outside the rank-local guarded
  blocks.  After the Newton iterations the active pairs and the minimum segment
  distance are measured; pairs closer than half the thickness are pushed apart
  (``physics.strand_separation``, :meth:`StrandContact.separate`, at most 3 rounds of
  separate + measure; the pairs found are counted in ``contact_separated``), and the
  figures at the final positions are recorded (``contact_pairs``,
  ``contact_deep_pairs`` closer than half the thickness, ``contact_min_distance``).
* ``physics.strand_contact_mode = "ccd"``: the first iterate, every Newton update
  (``StrandContact.limit_step``: per-vertex step lengths) and the frame's end
  (``StrandContact.collision_free_frame``) are limited so that no two segments of
  different wisps meet on the straight path (docs/contact.md); in ``penalty`` mode
  these calls change nothing.
"""

from __future__ import annotations

import numpy as np

from lc_petsc.elements import head_contact
from lc_petsc.parallel import collectively


class Integrator:
    def __init__(self, scene, assembler, solver, comm, timers, config, head):
        self.scene, self.asm, self.solver, self.comm = scene, assembler, solver, comm
        self.timers, self.cfg, self.head = timers, config, head
        terms = set(config.physics.terms)
        self.gravity = np.asarray(config.physics.gravity, float) if "gravity" in terms else np.zeros(3)
        self.contact = "head_collision" in terms
        self.free = ~scene.pinned
        self.f_ext = scene.mass[:, None] * self.gravity[None, :]
        self.x = scene.x_rest.copy()
        self.v = np.zeros_like(self.x)
        self.t = 0.0
        self.frame = 0
        self.newton_iterations = []
        self.ksp_iterations = []
        self.line_search_alphas = []
        self.xv, self.bv = assembler.mat.createVecs()
        self.strand = None
        self.contact_pairs = []
        self.contact_deep_pairs = []
        self.contact_min_distance = []
        self.contact_separated = []

    # -------------------------------------------------------------- potential
    def _contact_terms(self, x, need_hessian):
        if not self.contact:
            return 0.0, None, None
        with self.timers("collision"):
            c = self.head.sphere_center(self.t_next)
            R = self.head.radius + self.cfg.physics.head_margin
            k = self.cfg.physics.head_stiffness
            idx = np.flatnonzero(self.free & head_contact.active(x, c, R))
            if len(idx) == 0:
                return 0.0, idx, None
            xi = x[idx]
            e = float(head_contact.energy(xi, c, R, k).sum())
            g = head_contact.gradient(xi, c, R, k)
            H = head_contact.hessian(xi, c, R, k) if need_hessian else None
            return e, idx, (g, H)

    def incremental_potential(self, x):
        """G(x), summed over all ranks."""
        dt = self.cfg.time.dt
        with collectively(self.comm, f"frame {self.frame}: incremental potential"):
            d = (x - self.xhat)[self.free]
            m = self.scene.mass[self.free]
            local = 0.5 / dt ** 2 * float(np.sum(m[:, None] * d * d))
            local += self.asm.energy(x)
            local -= float(np.sum(self.f_ext[self.free] * x[self.free]))
            local += self._contact_terms(x, False)[0]
        total = self.comm.allreduce(local)
        if self.strand is not None:
            total += self.strand.energy(x)
        return total

    def gradient(self, x, elastic=None):
        """grad G at x (pinned rows zeroed); ``elastic`` reuses an elastic gradient."""
        dt = self.cfg.time.dt
        if elastic is None:
            elastic = self.asm.gradient(x)
        g = self.scene.mass[:, None] * (x - self.xhat) / dt ** 2 + elastic - self.f_ext
        _, idx, cg = self._contact_terms(x, False)
        if cg is not None:
            g[idx] += cg[0]
        g[~self.free] = 0.0
        return g

    # -------------------------------------------------------------- one frame
    def step(self):
        cfg, sc, asm = self.cfg, self.scene, self.asm
        dt = cfg.time.dt
        self.t_next = self.t + dt
        x_old = self.x.copy()
        self.xhat = self.x + dt * self.v
        x = self.xhat.copy()
        pin = ~self.free
        if pin.any():
            x[pin] = self.head.pinned_positions(sc.x_rest[pin], self.t_next)
        if self.strand is not None:             # ccd mode: no crossing on x_old -> first iterate
            x = self.strand.collision_free_frame(x_old, x)
        n_it = 0
        for it in range(cfg.time.newton_iterations):
            n_it += 1
            with collectively(self.comm, f"frame {self.frame}, Newton iteration {it}"):
                g = self.gradient(x, elastic=asm.assemble(x))
                with self.timers("assembly"):
                    asm.add_mass(sc.mass / dt ** 2)
                _, idx, cg = self._contact_terms(x, True)
                if cg is not None:
                    with self.timers("collision"):
                        asm.add_diagonal(idx, cg[1])
            if self.strand is not None:
                g += self.strand.assemble(x, asm)
            asm.commit()
            if self.strand is not None:         # the Newton matrix is A + C (contact.py)
                self.solver.ksp.setOperators(*self.strand.system(asm.mat, asm.pmat))
            with self.timers("solve"):
                self.bv.array[:] = -g.ravel()
                self.solver.solve(self.bv, self.xv, self.frame, it)
                dx = self.xv.array.reshape(-1, 3).copy()
            dx[pin] = 0.0
            alpha = 1.0
            if cfg.time.line_search:
                G0 = self.incremental_potential(x)
                slope = self.comm.allreduce(float(np.sum(g * dx)))
                for _ in range(20):
                    if self.incremental_potential(x + alpha * dx) <= G0 + 1e-4 * alpha * slope:
                        break
                    alpha *= 0.5
                self.line_search_alphas.append(alpha)
            if self.strand is not None:         # ccd mode: per-vertex, collision-free
                alpha = self.strand.limit_step(x, dx, alpha)
            x = x + alpha * dx
            if cfg.time.newton_tol is not None:
                step = self.comm.allreduce(float(np.abs(alpha * dx).max(initial=0.0)), op=_max())
                if step < cfg.time.newton_tol:
                    break
        badv = np.flatnonzero(~np.isfinite(x).all(axis=1))
        first_bad = sc.first_vertex + int(badv[0]) if len(badv) else -1
        bad_any = self.comm.allgather(first_bad)
        if max(bad_any) >= 0:
            raise FloatingPointError(f"frame {self.frame}: non-finite position at global vertex "
                                     f"{min(b for b in bad_any if b >= 0)}")
        self.newton_iterations.append(n_it)
        if self.strand is not None:
            pairs, deep, dmin = self.strand.measure(x)
            if cfg.physics.strand_separation:
                n_sep = 0
                self.strand.last_separation = (0, 0, 0)
                # a separation's corrections can bring pairs it did not see within d0/2,
                # and its Jacobi rounds are capped: re-measure, and separate again if so
                for _ in range(3):
                    if deep == 0:
                        break
                    x, n, _ = self.strand.separate(x)
                    n_sep = max(n_sep, n)
                    pairs, deep, dmin = self.strand.measure(x)
                self.contact_separated.append(n_sep)
            if self.strand.mode == "ccd":       # the straight path x_old -> x must not cross
                x = self.strand.collision_free_frame(x_old, x)
                pairs, deep, dmin = self.strand.measure(x)
            self.contact_pairs.append(pairs)
            self.contact_deep_pairs.append(deep)
            self.contact_min_distance.append(dmin)
        self.v = (x - x_old) / dt
        self.x = x
        self.t = self.t_next
        self.frame += 1


def _max():
    from mpi4py import MPI
    return MPI.MAX
