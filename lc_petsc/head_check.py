"""Hair inside the head: how deep the strands sink into the head sphere in a run's frames.

The head is the sphere of ``physics.head_radius`` about
:meth:`~lc_petsc.scene.kinematics.HeadMotion.sphere_center` (the sphere the previews and
the USD export draw; ``head_collision`` pushes vertices out of the larger
``head_radius + head_margin``).  A penalty lets vertices sink in, and an edge between
two vertices outside can still cut through the sphere (its chord).  Per frame row:

* the deepest free vertex: depth = head_radius - |x - c|;
* the deepest point of any edge with a free vertex (the point of the segment closest to
  the centre); an edge from a pinned vertex counts only what it sinks below that vertex
  (a groom may root its hairs under the scalp; the roots follow the head rigidly);
* each depth over the strand's radius there (``/radius``, interpolated along the
  edge): beyond 1 the whole strand's cross-section is under the scalp, i.e. the hair
  visibly vanishes into the head (:data:`SUNK`).

Per step between rows: each free vertex's straight path between the two frames (what a
viewer interpolating them draws), relative to the sphere's centre.  The centre moves on
a straight line (``translate``) or not at all (``shake`` turns the head about its
centre, which leaves the sphere where it is), so the relative path is straight too and
is the path in the head's moving frame: its deepest point may be deeper than either
frame shows (a vertex passing through the head between frames).
"""

from __future__ import annotations

import numpy as np

from lc_petsc.elements.head_contact import segment_depth

#: a strand whose centreline is deeper than this many of its radii is entirely inside
#: the head: the hair is seen to vanish into the scalp (the end-of-run warning's limit)
SUNK = 1.0


def _best_point(p0, d, r0, dr, radius, lam):
    """The parameter s in [0, 1] (k,) maximising depth(s) - lam r(s) along segments
    p0 + s d (relative to the centre) with strand radius r(s) = r0 + s dr: the depth is
    concave in s and r linear, so the maximum is at the clamped stationary point
    (|p(s)| = -(b + a s) / (lam dr), squared: a quadratic) or an end."""
    a = np.einsum("ij,ij->i", d, d)
    b = np.einsum("ij,ij->i", p0, d)
    c = np.einsum("ij,ij->i", p0, p0)
    q = a - (lam * dr) ** 2
    ok = (q > 0) & (a > 0)
    root = np.sqrt(np.divide(np.maximum(a * c - b * b, 0.0), q, out=np.zeros_like(a), where=ok))
    st = np.clip(np.divide(-b - lam * dr * root, a, out=np.zeros_like(a), where=ok), 0.0, 1.0)
    cand = np.stack([np.zeros_like(a), np.ones_like(a), st])            # (3, k)
    val = [radius - np.linalg.norm(p0 + s[:, None] * d, axis=1) - lam * (r0 + s * dr) for s in cand]
    return cand[np.argmax(val, axis=0), np.arange(len(a))]


def depth_ratio(p0, p1, r0, r1, radius, iterations=30):
    """The largest depth over strand radius along each segment p0 -> p1 (k, 3), relative
    to the sphere's centre, radii r0 -> r1 linear along it (0 where it stays outside):
    Dinkelbach's iteration lam <- depth(s) / r(s), s maximising depth - lam r
    (:func:`_best_point`), from the deepest point's ratio; it rises monotonically to
    the maximum (superlinearly; a few steps on hair's slowly tapering radii)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    r0, r1 = np.asarray(r0, float), np.asarray(r1, float)
    d, dr = p1 - p0, r1 - r0
    radius = np.broadcast_to(np.asarray(radius, float), (len(p0),))
    depth, t = segment_depth(p0, p1, radius)
    lam = np.maximum(depth, 0.0) / (r0 + t * dr)
    k = np.flatnonzero(depth > 0)
    for _ in range(iterations if len(k) else 0):
        s = _best_point(p0[k], d[k], r0[k], dr[k], radius[k], lam[k])
        new = (radius[k] - np.linalg.norm(p0[k] + s[:, None] * d[k], axis=1)) / (r0[k] + s * dr[k])
        done = new <= lam[k] * (1.0 + 1e-14)
        lam[k] = np.maximum(lam[k], new)
        k = k[~done]
        if not len(k):
            break
    return lam


def frame_depths(x, center, radius, offsets, pinned, strand_radius):
    """The head depths of one frame ``x`` (n, 3) for a sphere of ``radius`` at ``center``:
    dict with ``vertex`` (deepest free vertex, cm, 0 when none is inside), ``vertex_at``
    (its index, -1 when none is inside), ``edge`` (deepest point of an edge with a free
    vertex, less the depth of a pinned end), ``edge_at`` (its first vertex, -1), ``ratio``
    (the largest depth over the strand radius at the same point, over free vertices and
    every point of those edges), ``sunk`` (edges with a point deeper than :data:`SUNK`
    strand radii: the strand entirely inside the head there), ``sunk_chords`` (how many
    of those have no vertex that deep: their straight chord dips under the curved scalp)
    and ``chord_length``, ``chord_radius`` (the deepest such chord's length and strand
    radius; 0 without one)."""
    x = np.asarray(x, float)
    p = x - np.asarray(center, float)
    free = ~np.asarray(pinned, bool)
    rad = np.asarray(strand_radius, float)
    depth = radius - np.sqrt(np.einsum("ij,ij->i", p, p))      # every vertex's
    vd = np.where(free, depth, -np.inf)
    inner = np.ones(max(len(x) - 1, 0), bool)
    inner[np.asarray(offsets, np.int64)[1:-1] - 1] = False      # no edge between two wisps
    a = np.flatnonzero(inner & (free[:-1] | free[1:]))
    ed = segment_depth(p[a], p[a + 1], radius)[0]
    pinned_depth = np.where(free, 0.0, np.maximum(depth, 0.0))
    held = np.maximum(pinned_depth[a], pinned_depth[a + 1])
    ed = ed - held
    # an edge from a pinned vertex: its depth below that vertex's, over the radius
    er = depth_ratio(p[a], p[a + 1], rad[a], rad[a + 1], radius - held)
    ratio = max(float(np.max(vd / rad, initial=0.0)), float(np.max(er, initial=0.0)))
    iv = int(np.argmax(vd)) if len(vd) and vd.max() > 0 else -1
    ie = int(np.argmax(ed)) if len(ed) and ed.max() > 0 else -1
    # a sunk edge whose two vertices are not (a pinned one is held by the groom): its
    # straight chord dips under the curved scalp between them, up to the sagitta L^2 / (8 R)
    # of its length L with both ends on the sphere; the head contact holds vertices only
    out_v = np.where(free, depth <= SUNK * rad, True)
    chord = (er > SUNK) & out_v[a] & out_v[a + 1]
    k = int(np.argmax(np.where(chord, er, -np.inf))) if chord.any() else -1
    return {"vertex": max(float(vd[iv]), 0.0) if iv >= 0 else 0.0, "vertex_at": iv,
            "edge": float(ed[ie]) if ie >= 0 else 0.0, "edge_at": int(a[ie]) if ie >= 0 else -1,
            "ratio": ratio, "sunk": int(np.sum(er > SUNK)), "sunk_chords": int(chord.sum()),
            # the deepest (in strand radii) of those chords: its length, its strand radius
            "chord_length": float(np.linalg.norm(p[a[k] + 1] - p[a[k]])) if k >= 0 else 0.0,
            "chord_radius": float(0.5 * (rad[a[k]] + rad[a[k] + 1])) if k >= 0 else 0.0}


def path_depths(x0, x1, c0, c1, radius, pinned, strand_radius):
    """The free vertices' straight paths x0 -> x1 (n, 3) against the sphere of ``radius``
    moving from ``c0`` to ``c1`` (relative to its centre: see the module's docstring): dict
    with ``depth`` (the deepest point of any path, cm, 0 when none enters), ``beyond``
    (the largest depth a path reaches beyond both its ends) and ``through`` (free
    vertices whose path goes deeper than :data:`SUNK` strand radii while neither frame
    shows it that deep: hair passing through the head between frames)."""
    free = np.flatnonzero(~np.asarray(pinned, bool))
    p0 = np.asarray(x0, float)[free] - np.asarray(c0, float)
    p1 = np.asarray(x1, float)[free] - np.asarray(c1, float)
    depth = segment_depth(p0, p1, radius)[0]
    ends = np.maximum(radius - np.linalg.norm(p0, axis=1), radius - np.linalg.norm(p1, axis=1))
    lim = SUNK * np.asarray(strand_radius, float)[free]
    return {"depth": max(float(depth.max(initial=0.0)), 0.0),
            "beyond": float(np.max(depth - np.maximum(ends, 0.0), initial=0.0)),
            "through": int(np.sum((depth > lim) & (ends <= lim)))}


def file_head(r):
    """(HeadMotion, strand radius (n,), pinned (n,)) of frames.h5 open in the
    :class:`lc_petsc.io.frames_read.FramesReader` ``r``, from its
    ``config`` attribute, ``/radius`` and ``/pinned`` (radius rebuilt from the scene when
    the file has none), or None when the run's scene has no head sphere (no
    ``head_collision`` and not a hairball: the same rule as the previews and USD)."""
    import json
    from lc_petsc.io.usd import config_tables, has_head_sphere, scene_radius
    from lc_petsc.scene.kinematics import HeadMotion
    f = r.f
    tables = config_tables(json.loads(f.attrs["config"]) if "config" in f.attrs else {})
    if not has_head_sphere(tables["physics"], tables["scene"]):
        return None
    off = r.offsets
    rad = (np.asarray(r.dataset("radius"), float) if "radius" in f else
           scene_radius(tables, np.diff(off)))
    pinned = np.asarray(r.dataset("pinned"), bool) if "pinned" in f else np.zeros(int(off[-1]), bool)
    return HeadMotion(tables["physics"]), rad, pinned


def step_depths(head, prev, cur, t0, t1, offsets, strand_radius, pinned):
    """The head figures of one step between frames ``prev`` (at ``t0``) and ``cur`` (at
    ``t1``): :func:`frame_depths` of ``cur`` and :func:`path_depths` of the step, in one
    dict (the path's keys prefixed ``path_``)."""
    c1 = head.sphere_center(t1)
    out = frame_depths(cur, c1, head.radius, offsets, pinned, strand_radius)
    path = path_depths(prev, cur, head.sphere_center(t0), c1, head.radius, pinned, strand_radius)
    out.update({f"path_{k}": v for k, v in path.items()})
    return out


def summarize(steps):
    """The run's head figures from ``steps``: (step k, :func:`step_depths` dict of rows
    k -> k + 1) over every step checked: the deepest free vertex and edge point
    (``vertex_depth``, ``edge_depth``, cm, and their rows), the largest depth over the
    strand radius (``ratio``, its row), ``rows_sunk`` (rows with a strand deeper than
    :data:`SUNK` radii, ``first_sunk_row``), ``rows_sunk_by_chords`` (those of them in
    which only edges between vertices no deeper than that are, the straight chord under
    the curved scalp) with the longest such chord's ``chord_length`` and
    ``chord_radius``, the deepest point of a vertex's path between frames
    (``path_depth``), the most a path goes beyond its two ends (``path_beyond``),
    ``paths_through`` (vertex paths through the head between frames, over all steps) with
    ``steps_through`` and ``first_through`` (step), and ``depth_per_row``: per row after
    the first (row 0 is the user's initial state), the deeper of its vertex and edge
    depths (None for a row not checked)."""
    steps = sorted(steps, key=lambda s: s[0])
    if not steps:
        return None

    def worst(key):
        k, r = max(steps, key=lambda s: s[1][key])
        return r[key], k + 1

    per_row = [None] * (steps[-1][0] + 1)
    for k, r in steps:
        per_row[k] = max(r["vertex"], r["edge"])
    (vd, vrow), (ed, erow), (ratio, rrow) = worst("vertex"), worst("edge"), worst("ratio")
    sunk = [k + 1 for k, r in steps if r["sunk"]]
    chords = [r for _, r in steps if r["sunk"] and r["sunk"] == r.get("sunk_chords", 0)]
    longest = max(chords, key=lambda r: r["chord_length"], default=None)
    through = [k for k, r in steps if r["path_through"]]
    return {"vertex_depth": vd, "vertex_row": vrow, "edge_depth": ed, "edge_row": erow,
            "ratio": ratio, "ratio_row": rrow, "rows_sunk": len(sunk),
            "rows_sunk_by_chords": len(chords),
            "chord_length": longest["chord_length"] if longest else None,
            "chord_radius": longest["chord_radius"] if longest else None,
            "first_sunk_row": sunk[0] if sunk else None,
            "path_depth": max(r["path_depth"] for _, r in steps),
            "path_beyond": max(r["path_beyond"] for _, r in steps),
            "paths_through": sum(r["path_through"] for _, r in steps), "steps_through": len(through),
            "first_through": through[0] if through else None, "depth_per_row": per_row}
