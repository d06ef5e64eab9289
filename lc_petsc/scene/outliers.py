"""Vertices of a groom file that lie far off their wisp: damage, not hair.

A groom file carries no checksum: one flipped exponent bit in a vertex coordinate
(``configs/data/fringe.h5``) ran without an error, the vertex scaled by a power of two
away from its wisp and the crossings it caused exempted as rest overlaps.  Hair is
sampled evenly enough that a vertex many median edges away from both of its neighbours,
which themselves lie close together, is no hair shape (:data:`DISPLACED`).  Such a
vertex is refused, naming the wisp and the vertex; an edge merely far longer than its
wisp's median edge (an end vertex, or uneven sampling) is a warning (:func:`lc_petsc.diagnostics.groom_edge_warnings`).
"""

from __future__ import annotations

import numpy as np

#: an interior vertex at least this many of its wisp's median edges from both of its
#: neighbours, while they lie closer to each other than half that distance, is refused
#: as displaced; an edge this long elsewhere is warned about.  The shipped and generated
#: grooms' longest edges are 1.73 (fringe) and 1.006 (hairball) times their wisp's
#: median; of every single exponent-bit flip of a fringe.h5 coordinate, 58% are refused
#: with it, 3.2% warned, 1.6% not finite; the 37% that pass moved their vertex by at most
#: 5.7 median edges (docs/elements.md, "A displaced vertex")
DISPLACED = 5.0


def edge_ratios(x):
    """(edges / median edge, median edge) of one wisp's vertices ``x`` (n, 3)."""
    e = np.linalg.norm(np.diff(x, axis=0), axis=1)
    m = float(np.median(e))
    return e / m, m


def displaced_vertex(x):
    """(vertex, far, gap, median) of the most displaced interior vertex of one wisp
    ``x`` (n, 3) (:data:`DISPLACED`), else None: ``far`` its distance to the nearer
    neighbour, ``gap`` the neighbours' distance to each other."""
    ratio, m = edge_ratios(x)
    near = np.minimum(ratio[:-1], ratio[1:]) * m
    gap = np.linalg.norm(x[2:] - x[:-2], axis=1)
    hit = (near >= DISPLACED * m) & (gap < 0.5 * near)
    if not hit.any():
        return None
    k = int(np.argmax(np.where(hit, near, -1.0)))
    return k + 1, float(near[k]), float(gap[k]), m


def displaced_vertex_problems(batch):
    """Messages for the wisps of ``batch`` (a :class:`WispBatch` of finite positions
    without coincident vertices) with a displaced vertex, naming wisp and vertex."""
    out = []
    ids = batch.ids()
    for w in range(batch.n_wisps):
        a, b = int(batch.offsets[w]), int(batch.offsets[w + 1])
        found = displaced_vertex(batch.positions[a:b])
        if found is None:
            continue
        k, far, gap, m = found
        out.append(f"wisp {ids[w]}, vertex {k}: it lies {far:.3g} cm or more from both of its neighbours "
                   f"({far / m:.0f} times the wisp's median edge, {m:.3g} cm), which are {gap:.3g} cm "
                   f"apart, at {batch.positions[a + k].tolist()}: a displaced vertex (a damaged file, "
                   f"e.g. a flipped bit), not a hair shape; restore or remove that vertex")
    return out
