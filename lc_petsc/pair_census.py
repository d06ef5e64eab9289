"""Census of strand-contact pairs per frame of a frames.h5: how many, how close, how old
(docs/contact.md, "Contact-pair pile-up in ccd mode"; ``scripts/pair_census.py``).

Per frame: the pairs of segments of different wisps closer than d0, rest-exempt pairs
(closer than d0 in the rest pose) counted apart; their distance histogram relative to
d0 (:data:`EDGES`); how many are held far inside (d < 0.05 d0, the ccd frame path's
floor; d < 0.25 d0, the Newton floor); how many are nearly parallel (|cos| > 0.9); how
many were already closer than d0 in the previous frame and for how many frames in a row
(age); the distinct segments and wisps involved; the penalty force k (d0 - d) they
would carry.  Serial; reads one frame at a time.
"""

import json

import numpy as np

from lc_petsc.crossings import frames_layout, pair_positions, segments
from lc_petsc.elements.compiled_ccd import box_pairs
from lc_petsc.elements.segment_contact import distance

#: histogram edges of d / d0
EDGES = (0.0, 0.01, 0.05, 0.1, 0.25, 0.5, 0.75, 1.0)


def close_pairs(X, seg, wisp, d0):
    """Segments of different wisps closer than d0 at positions X (n, 3); ``seg`` (m,)
    first global vertex and ``wisp`` (m,) wisp of each segment (:func:`segments`).
    Returns (pairs (k, 2) of first global vertices, smaller first, sorted; d (k,))."""
    P = np.stack([X[seg], X[seg + 1]], axis=1)
    ij = box_pairs(P.min(axis=1) - 0.5 * d0, P.max(axis=1) + 0.5 * d0, group=wisp)
    pairs = np.sort(np.stack([seg[ij[:, 0]], seg[ij[:, 1]]], axis=1), axis=1)
    d = distance(pair_positions(X, pairs)) if len(pairs) else np.zeros(0)
    keep = d < d0
    pairs, d = pairs[keep], d[keep]
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    return pairs[order], d[order]


def frame_census(X, rest, seg, wisp, wid, d0, k, prev_age):
    """One frame's figures (dict) at positions X (n, 3) with rest positions ``rest``
    (n, 3) and ``wid`` (n,) the wisp of each vertex, and the age (frames in a row closer
    than d0, this one included) of each pair, a dict keyed by its (a, b) first vertices;
    ``prev_age`` is the previous frame's."""
    pairs, d = close_pairs(X, seg, wisp, d0)
    exempt = distance(pair_positions(rest, pairs)) < d0 if len(pairs) else np.zeros(0, bool)
    A = X[pairs[:, 0] + 1] - X[pairs[:, 0]]
    B = X[pairs[:, 1] + 1] - X[pairs[:, 1]]
    cos = np.abs(np.einsum("ij,ij->i", A, B)) / np.maximum(
        np.linalg.norm(A, axis=1) * np.linalg.norm(B, axis=1), 1e-300)
    age = {}
    ages = np.zeros(len(pairs), np.int64)
    for n, (a, b) in enumerate(map(tuple, pairs.tolist())):
        ages[n] = age[(a, b)] = prev_age.get((a, b), 0) + 1
    act = ~exempt
    r = d[act] / d0
    hist = np.histogram(r, bins=EDGES)[0]
    out = {
        "pairs": int(act.sum()), "exempt": int(exempt.sum()),
        "hist_edges": list(EDGES), "hist": [int(h) for h in hist],
        "below_0.05": int(np.sum(r < 0.05)), "below_0.25": int(np.sum(r < 0.25)),
        "below_0.5": int(np.sum(r < 0.5)),
        "median_d_over_d0": float(np.median(r)) if len(r) else None,
        "min_d_over_d0": float(r.min()) if len(r) else None,
        "parallel": int(np.sum(cos[act] > 0.9)),
        "kept_from_previous": int(np.sum(ages[act] > 1)),
        "age_ge_5": int(np.sum(ages[act] >= 5)), "age_ge_10": int(np.sum(ages[act] >= 10)),
        "median_age": float(np.median(ages[act])) if act.any() else None,
        "segments": int(len(np.unique(pairs[act]))),
        "wisps": int(len(np.unique(wid[pairs[act]]))),
        "penalty_force_sum": float(k * np.sum(d0 - d[act])),
        "penalty_force_per_pair": float(k * np.mean(d0 - d[act])) if act.any() else 0.0,
    }
    return out, age


def census_frames(path, thickness=None, stiffness=None, every=1, progress=None):
    """Per frame of the ``frames.h5`` at ``path`` (every ``every``-th; ages count only
    with every = 1): list of :func:`frame_census` dicts with ``frame``, and (d0, k).
    d0: ``thickness``, else the run's ``physics.strand_thickness``, else the simulator's
    default, twice the smallest vertex radius; k: ``stiffness``, else the run's
    ``physics.strand_stiffness``.  Rows that hold no frame (lost in a recovery,
    ``/frame_valid``) are left out.  ``progress(dict)`` is called per frame."""
    from lc_petsc.io.frames_read import FramesReader
    if every < 1:
        raise ValueError(f"every = {every}: give a frame stride of at least 1")
    with FramesReader(path) as fr:
        f = fr.f
        cfg = json.loads(f.attrs["config"]) if "config" in f.attrs else {}
        phys = cfg.get("physics") or {}
        d0 = float(thickness or phys.get("strand_thickness") or 2.0 * float(np.min(fr.dataset("radius"))))
        k = float(stiffness or phys.get("strand_stiffness") or 1.0e5)
        off, rest = frames_layout(fr, with_rest=True)
        seg, wisp = segments(off)
        wid = np.repeat(np.arange(len(off) - 1), np.diff(off))
        rows, age = [], {}
        held = fr.valid
        picked = range(0, len(held), every)
        frames = fr.rows([t for t in picked if held[t]])
        for t in picked:
            if not held[t]:            # lost in a recovery: no census, ages start again
                age = {}
                continue
            X = next(frames)[1]
            r, age = frame_census(X, rest, seg, wisp, wid, d0, k, age if every == 1 else {})
            r["frame"] = t
            rows.append(r)
            if progress is not None:
                progress(r)
    return rows, d0, k
