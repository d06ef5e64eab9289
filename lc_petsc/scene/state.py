"""Rank-local scene: rest state, masses and per-element arrays of the wisps a rank owns.

``LocalScene.build`` takes this rank's :class:`WispBatch` (from a scene source and the
partition) and computes, for the enabled terms only:

* stretch elements (i, i+1): rest length Lbar, k_s = E A_e / Lbar (A_e from the mean of
  the two vertex radii);
* bend elements (i-1, i, i+1): rest angle via ``bend.angle``, k_b = E I_i / l_i with
  the Voronoi length l_i = (Lbar_{i-1} + Lbar_i) / 2;
* twist elements (i .. i+3): rest angle via ``twist.angle``, k_t = G J / Lbar_mid with
  the middle edge's mean radius, times ``twist.rest_weight`` (0 where the rest stencil
  is straight: no rest torsion);
* lumped masses: each edge gives 1/2 rho A_e Lbar_e to both of its vertices.

Element arrays store the *first vertex* (``start``) of each element; an element's
vertices are ``start + 0..k-1``, all in one wisp.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict

import numpy as np

from lc_petsc.config import DENSITY_RANGE, MAX_MODULUS, MIN_LENGTH, density_problem
from lc_petsc.elements import bend, twist, weights

TERM_K = {"stretch": 2, "bend": 3, "twist": 4}


def wisp_lengths(rest, offsets):
    """Rest arc length of every wisp (n_wisps,)."""
    seg = np.linalg.norm(np.diff(rest, axis=0), axis=1)
    out = np.empty(len(offsets) - 1)
    for w in range(len(out)):
        a, b = int(offsets[w]), int(offsets[w + 1])
        out[w] = seg[a:b - 1].sum()
    return out


def vertex_wisp_length(rest, offsets):
    """Rest length of each vertex's wisp (n_vertices,)."""
    return np.repeat(wisp_lengths(rest, offsets), np.diff(offsets))


def _first(mask, wisp_of):
    """(index, wisp) of the first True of ``mask``; ``wisp_of``: each entry's local wisp."""
    j = int(np.flatnonzero(mask)[0])
    return j, int(wisp_of[j])


@dataclass
class TermData:
    """One elastic term's elements on this rank: first vertices, rest values, stiffnesses."""

    name: str
    k: int
    start: np.ndarray       # (n,) local index of the element's first vertex
    rest: np.ndarray        # (n,) rest length / rest angle
    stiffness: np.ndarray   # (n,)

    def gather(self, x):
        """Element positions (n, k, 3) from local positions x (nv, 3)."""
        return x[self.start[:, None] + np.arange(self.k)]


@dataclass
class LocalScene:
    """This rank's wisps: rest state, masses, pins, radii and the elements of each enabled term."""

    first_wisp: int
    n_wisps_global: int
    first_vertex: int
    n_vertices_global: int
    offsets: np.ndarray         # local wisp offsets (n_wisps_local + 1,)
    x_rest: np.ndarray          # (nv, 3)
    radius: np.ndarray
    pinned: np.ndarray
    mass: np.ndarray            # (nv,) lumped
    terms: Dict[str, TermData] = field(default_factory=dict)

    @property
    def nv(self) -> int:
        """Number of local vertices."""
        return len(self.x_rest)

    @property
    def n_wisps(self) -> int:
        """Number of local wisps."""
        return len(self.offsets) - 1

    @property
    def bandwidth(self) -> int:
        """Half bandwidth in vertices of the enabled terms' Hessian (0: mass only)."""
        return max([TERM_K[t] - 1 for t in self.terms] or [0])

    @staticmethod
    def starts(offsets, k):
        """Local first vertices of all k-vertex stencils inside the wisps."""
        parts = [np.arange(offsets[w], offsets[w + 1] - k + 1) for w in range(len(offsets) - 1)]
        return (np.concatenate(parts) if parts else np.zeros(0)).astype(np.int64)

    @classmethod
    def build(cls, batch, material, terms, n_wisps_global, first_vertex, n_vertices_global):
        """Validate ``batch`` and compute the rest state.  Returns (scene, problems):
        ``problems`` lists messages (naming wisp and value) instead of raising, so the
        caller can raise collectively."""
        problems = []
        off = batch.offsets
        x = batch.positions
        nw = batch.n_wisps
        wid = np.repeat(np.arange(nw), np.diff(off))
        ids = batch.ids()             # wisp numbers in the scene's order, for messages
        for w in range(nw):
            n = int(off[w + 1] - off[w])
            if n < 4:
                problems.append(f"wisp {ids[w]} has {n} vertices; a wisp needs at least 4 "
                                "(remove the wisp from the groom or resample it)")
        bad = ~np.isfinite(x).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            w = int(wid[i])
            problems.append(f"wisp {ids[w]}, vertex {i - off[w]} (global vertex "
                            f"{first_vertex + i}): position {x[i].tolist()} is not finite")
        bad = ~(np.isfinite(batch.radius) & (batch.radius > 0))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            w = int(wid[i])
            problems.append(f"wisp {ids[w]}, vertex {i - off[w]}: radius "
                            f"{batch.radius[i]!r} must be finite and positive")
        elif (batch.radius < MIN_LENGTH).any():
            # a radius of 1e-300 made the wisp's masses 0: exit 3 in frame 0
            i, w = _first(batch.radius < MIN_LENGTH, wid)
            problems.append(f"wisp {ids[w]}, vertex {i - off[w]}: radius {batch.radius[i]!r} cm is below "
                            f"{MIN_LENGTH:g} cm (an atom's size): no strand is that thin; the radii are in "
                            "cm (or the file is damaged)")
        E = np.full(nw, float(material.youngs_modulus))
        if batch.youngs_modulus is not None:
            E = np.asarray(batch.youngs_modulus, float)
        rho = np.full(nw, float(material.density))
        if batch.density is not None:
            rho = np.asarray(batch.density, float)
        G = E * (material.G / material.youngs_modulus)
        for name, arr in (("Young's modulus (stiffness)", E), ("density", rho)):
            badw = ~(np.isfinite(arr) & (arr > 0))
            if badw.any():
                w = int(np.flatnonzero(badw)[0])
                problems.append(f"wisp {ids[w]}: {name} {arr[w]!r} must be finite and positive")
        lo, hi = DENSITY_RANGE
        outside = np.isfinite(rho) & (rho > 0) & ((rho < lo) | (rho > hi))
        if batch.density is not None and outside.any():
            # a wrong unit ran without an error (config.DENSITY_RANGE); the key is checked by the config
            w = int(np.flatnonzero(outside)[0])
            problems.append(f"wisp {ids[w]}: " + density_problem("/density", float(rho[w])))
        if batch.youngs_modulus is not None and (E > MAX_MODULUS).any():
            # the config's bound (1e300 overflowed the Hessians in frame 0)
            w = int(np.flatnonzero(E > MAX_MODULUS)[0])
            problems.append(f"wisp {ids[w]}: Young's modulus {E[w]!r} dyn/cm^2 is beyond {MAX_MODULUS:g} (steel "
                            "is 2e12; hair keratin about 4e10): give the moduli in dyn/cm^2 (CGS)")
        if problems:
            return None, problems

        es = cls.starts(off, 2)
        Lbar = np.linalg.norm(x[es + 1] - x[es], axis=1)
        # round-off at the edge's own coordinates (a scene-wide scale blamed the normal
        # edges of every other wisp when one wisp lay far away)
        scale = np.maximum(1.0, np.maximum(np.abs(x[es]).max(axis=1), np.abs(x[es + 1]).max(axis=1)))
        zero = Lbar <= 1e-12 * scale
        if zero.any():
            j = int(np.flatnonzero(zero)[0])
            w = int(wid[es[j]])
            far = f", below round-off at coordinates of {scale[j]:.3g}" if Lbar[j] > 0 else ""
            problems.append(f"wisp {ids[w]}, edge {es[j] - off[w]}: rest length "
                            f"{Lbar[j]!r} is zero (coincident vertices{far}); remove the "
                            "duplicate vertex from the groom")
            return None, problems
        # an overflowing rest length: the assembler's check of the same raised on this rank
        # alone, the others waited for it in a collective call (mpiexec hung); one below an
        # atom (a wisp shrunk to 1e-10 cm passed, its edges above round-off, and its
        # stiffnesses, 1e27 times its mass term, failed the solve in frame 0)
        for bad, what in ((~np.isfinite(Lbar), lambda j: f"overflows to {Lbar[j]!r} (vertices at "
                                                         f"coordinates up to {scale[j]:.3g})"),
                          (Lbar < MIN_LENGTH, lambda j: f"{Lbar[j]:.3g} cm is below {MIN_LENGTH:g} cm (an "
                                                        "atom's size): no hair shape")):
            if bad.any():
                j, w = _first(bad, wid[es])
                problems.append(f"wisp {ids[w]}, edge {es[j] - off[w]}: rest length {what(j)}: the groom's "
                                "positions are not in cm (or the file is damaged); scale the wisp to hair size")
                return None, problems
        r_e = 0.5 * (batch.radius[es] + batch.radius[es + 1])
        A_e = np.pi * r_e ** 2
        m_e = 0.5 * rho[wid[es]] * A_e * Lbar
        mass = np.zeros(len(x))
        np.add.at(mass, es, m_e)
        np.add.at(mass, es + 1, m_e)
        # edge lookup: local edge index of the edge starting at vertex v
        edge_of = np.full(len(x), -1, np.int64)
        edge_of[es] = np.arange(len(es))

        td = {}
        if "stretch" in terms:
            td["stretch"] = TermData("stretch", 2, es, Lbar,
                                     weights.stretch_stiffness(E[wid[es]], r_e, Lbar))
        if "bend" in terms:
            s = cls.starts(off, 3)
            xe = x[s[:, None] + np.arange(3)]
            vor = 0.5 * (Lbar[edge_of[s]] + Lbar[edge_of[s + 1]])
            td["bend"] = TermData("bend", 3, s, bend.angle(xe),
                                  weights.bend_stiffness(E[wid[s]], batch.radius[s + 1], vor))
        if "twist" in terms:
            s = cls.starts(off, 4)
            xe = x[s[:, None] + np.arange(4)]
            mid = edge_of[s + 1]
            k_t = (weights.twist_stiffness(G[wid[s]], r_e[mid], Lbar[mid])
                   * twist.rest_weight(xe, float(material.twist_rest_sine)))
            td["twist"] = TermData("twist", 4, s, twist.angle(xe), k_t)
        for t in td.values():
            badk = ~(np.isfinite(t.stiffness) & (t.stiffness >= 0))
            if badk.any():
                j = int(np.flatnonzero(badk)[0])
                w = int(wid[t.start[j]])
                problems.append(f"wisp {ids[w]}: {t.name} stiffness "
                                f"{t.stiffness[j]!r} of element {t.start[j] - off[w]} is invalid")
            badr = ~np.isfinite(t.rest)
            if badr.any():      # (the assembler raised it on this rank alone, as above)
                j, w = _first(badr, wid[t.start])
                problems.append(f"wisp {ids[w]}: the rest {'length' if t.name == 'stretch' else 'angle'} "
                                f"of {t.name} element {t.start[j] - off[w]} is {t.rest[j]!r} (vertices at "
                                f"{np.abs(t.gather(x)[j]).max():.3g} cm): not a hair shape in cm")
        if problems:
            return None, problems
        return cls(first_wisp=batch.first_wisp, n_wisps_global=n_wisps_global,
                   first_vertex=first_vertex, n_vertices_global=n_vertices_global,
                   offsets=off.copy(), x_rest=x.copy(), radius=batch.radius.copy(),
                   pinned=batch.pinned.copy(), mass=mass, terms=td), []


def inertia_problems(scene, batch, cfg):
    """Messages naming the first wisp of this rank whose lumped masses, mass term M/dt^2
    (at the smallest substep, dt / time.max_substeps) or weight M g are not finite
    positive normal floats: ``material.density = 1e308`` passed every check, overflowed
    M/dt^2 and failed frame 0 after writing it.  ``batch``: the scene's WispBatch (its
    per-wisp densities name the file's, else the key)."""
    dt = float(cfg.time.dt) / cfg.time.max_substeps
    g = float(np.max(np.abs(cfg.physics.gravity))) if "gravity" in cfg.physics.terms else 0.0
    m = scene.mass
    tiny = np.finfo(float).tiny
    with np.errstate(over="ignore", under="ignore"):
        term, weight = m / dt ** 2, m * g
    bad = ~((m >= tiny) & np.isfinite(term) & (term >= tiny) & np.isfinite(weight))
    if not bad.any():
        return []
    i = int(np.flatnonzero(bad)[0])
    w = int(np.searchsorted(scene.offsets, i, side="right") - 1)
    rho = (f"the file's /density {float(batch.density[w])!r} g/cm^3 of wisp {batch.ids()[w]}"
           if batch.density is not None else f"material.density = {cfg.material.density!r} g/cm^3")
    return [f"{rho} gives wisp {batch.ids()[w]}, vertex {i - scene.offsets[w]} (radius {scene.radius[i]!r} cm) "
            f"a mass of {m[i]!r} g, a mass term M/dt^2 of {term[i]!r} (dt / time.max_substeps = {dt:g} s) "
            f"and a weight M g of {weight[i]!r}: not all finite positive numbers in double precision; hair is "
            "about 1.3 g/cm^3 (the units are g and cm)"]
