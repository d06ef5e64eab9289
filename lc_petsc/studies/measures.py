"""Error and quality measures on gathered (global) positions, plus the collective
trajectory recorder the studies attach to a simulator.

All position arrays are (n_vertices, 3) in global vertex order; ``offsets`` are the
wisp offsets (n_wisps + 1).
"""

from __future__ import annotations

import numpy as np

from lc_petsc.crossings import edge_strain
from lc_petsc.parallel import global_max
from lc_petsc.scene.state import vertex_wisp_length, wisp_lengths  # noqa: F401  (re-exported)


def stretch_strain(x, rest, offsets):
    """Largest |l / l0 - 1| over all edges (:func:`lc_petsc.crossings.edge_strain`)."""
    return float(np.max(np.abs(edge_strain(x, rest, offsets)), initial=0.0))


def curl_radius(x, offsets, free=None):
    """Mean circumradius of consecutive vertex triples (i-1, i, i+1) inside wisps,
    over free interior vertices whose triple is not (nearly) collinear; None if none.

    On the 4C helix (5 vertices per turn) this is a fixed multiple of the helix radius,
    so its ratio to the rest value measures how much of the curl is retained.
    """
    n = len(x)
    inner = np.ones(n, bool)
    inner[np.asarray(offsets[:-1], int)] = False
    inner[np.asarray(offsets[1:], int) - 1] = False
    if free is not None:
        inner &= free
    idx = np.flatnonzero(inner)
    if len(idx) == 0:
        return None
    a = x[idx] - x[idx - 1]
    b = x[idx + 1] - x[idx]
    c = x[idx + 1] - x[idx - 1]
    cr = np.linalg.norm(np.cross(a, b), axis=1)
    la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
    ok = cr > 1e-9 * np.maximum(la * lb, 1e-300)
    if not ok.any():
        return None
    return float(np.mean(la[ok] * lb[ok] * lc[ok] / (2.0 * cr[ok])))


class TrajectoryRecorder:
    """Collective callback: every ``every``-th step, gather positions (rank 0) and the
    elastic + kinetic energy (all ranks); checks for blow-up after each capture.

    ``blowup``: a vertex further than ``blowup`` x (longest wisp length) from its rest
    position raises :class:`BlowUp` on every rank.
    """

    def __init__(self, sim, every=1, blowup=5.0):
        self.sim, self.every, self.blowup = sim, int(every), float(blowup)
        comm = sim.comm
        self.offsets = sim.wisp_offsets()
        self.rest = _gather(comm, sim.scene.x_rest)
        self.pinned = _gather(comm, sim.scene.pinned)
        lengths = wisp_lengths(self.rest, self.offsets) if comm.rank == 0 else None
        self.max_length = comm.bcast(float(lengths.max()) if lengths is not None else None)
        self.times, self.positions, self.energies = [], [], []
        self.capture(sim)           # the initial state (t = 0)

    def energy(self, sim):
        """Elastic plus kinetic energy of the simulator's state (collective)."""
        sc, integ = sim.scene, sim.integrator
        free = ~sc.pinned
        local = float(sim.assembler.energy(sim.x))
        local += 0.5 * float(np.sum(sc.mass[free, None] * integ.v[free] ** 2))
        return sim.comm.allreduce(local)

    def capture(self, sim):
        """Record the current frame (gathered on rank 0); :class:`BlowUp` for non-finite positions."""
        comm = sim.comm
        disp = float(np.abs(sim.x - sim.scene.x_rest).max(initial=0.0)) if np.all(np.isfinite(sim.x)) \
            else float("inf")
        disp = global_max(comm, disp)
        if not np.isfinite(disp):
            raise BlowUp(f"non-finite positions at frame {sim.integrator.frame}")
        X = sim.gather_positions()
        e = self.energy(sim)
        if comm.rank == 0:
            self.times.append(sim.integrator.t)
            self.positions.append(X)
            self.energies.append(e)
        if not disp <= self.blowup * self.max_length:
            raise BlowUp(f"blow-up at frame {sim.integrator.frame} (t = {sim.integrator.t:.4g} s): "
                         f"a vertex moved {disp:.3g} cm from rest, more than {self.blowup:g} x the "
                         f"longest wisp ({self.max_length:.3g} cm)")

    def __call__(self, sim):
        """Frame callback: capture every ``every``-th frame."""
        if sim.integrator.frame % self.every == 0:
            self.capture(sim)


class BlowUp(ArithmeticError):
    """Positions left any plausible range (a vertex moved many wisp lengths)."""


def _gather(comm, a):
    parts = comm.gather(np.asarray(a), root=0)
    return np.concatenate(parts) if comm.rank == 0 else None


def compare_trajectories(var, ref, rest, offsets, pinned):
    """Errors of a variant trajectory against the reference at their common times.

    ``var``/``ref``: dicts with ``times``, ``positions`` (list of arrays), ``energies``.
    Returns a dict: rms_rel_error (RMS over the common times after the first (the shared
    initial state) and vertices of |x - x_ref|
    divided by the mean wisp length), max_rel_error (max of |x - x_ref| / the vertex's
    wisp length), final_rms_rel_error, energy_rel_error (max over times of
    |E - E_ref| / max_t E_ref, E = elastic + kinetic), n_common_times.
    """
    rt = np.round(np.asarray(ref["times"]), 9)
    vt = np.round(np.asarray(var["times"]), 9)
    # the shared initial state is equal by construction: counting it diluted the RMS by
    # sqrt(n / (n + 1)) (13% on a study of 3 outputs)
    common = [t for t in vt if t in set(rt) and t > min(rt[0], vt[0])]
    if not common:
        return {"n_common_times": 0}
    ri = {t: i for i, t in enumerate(rt)}
    vi = {t: i for i, t in enumerate(vt)}
    L = vertex_wisp_length(rest, offsets)
    Lmean = float(np.mean(wisp_lengths(rest, offsets)))
    sq, mx, final = [], 0.0, None
    e_err = 0.0
    e_scale = max(float(np.max(np.abs(ref["energies"]))), 1e-300)
    for t in common:
        d = np.linalg.norm(var["positions"][vi[t]] - ref["positions"][ri[t]], axis=1)
        sq.append(np.mean(d * d))
        mx = max(mx, float(np.max(d / L)))
        final = float(np.sqrt(np.mean(d * d))) / Lmean
        e_err = max(e_err, abs(var["energies"][vi[t]] - ref["energies"][ri[t]]) / e_scale)
    return {"rms_rel_error": float(np.sqrt(np.mean(sq))) / Lmean, "max_rel_error": mx,
            "final_rms_rel_error": final, "energy_rel_error": float(e_err),
            "n_common_times": len(common)}


def quality(traj, rest, offsets, pinned):
    """Quality measures of one trajectory: max stretch strain over the captured times
    after t = 0 (the initial, possibly perturbed, state is common to all runs), curl-radius
    retention at the last captured time (ratio to the rest curl radius)."""
    later = traj["positions"][1:] or traj["positions"]      # t = 0 is common to all runs
    strain = max(stretch_strain(x, rest, offsets) for x in later)
    r0 = curl_radius(rest, offsets, ~pinned)
    r1 = curl_radius(traj["positions"][-1], offsets, ~pinned)
    return {"max_stretch_strain": strain,
            "curl_retention": (r1 / r0) if (r0 and r1) else None}
