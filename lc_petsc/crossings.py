"""Swept-box broad phase and the edge-edge crossing counter over frames.

* :func:`lc_petsc.elements.compiled_ccd.box_pairs`: all pairs of overlapping boxes,
  exact, through a uniform grid in a compiled loop.  The one broad phase of the
  project: the penalty contact's (segment boxes grown by d0 / 2), the limiter's and
  this counter's (boxes relative to the fitted affine field,
  :func:`segment_ccd.field_boxes`).
* :func:`count_crossings`: edge-edge crossings between segments of different wisps
  (optionally between non-adjacent segments of one wisp) on the linear path between
  two configurations (two consecutive frames): the relative broad phase, conservative
  advancement at distance 0 (:func:`compiled_ccd.screen_paths`) to discard pairs that
  cannot meet, and IPC Toolkit's Tight-Inclusion CCD (``ipctk``, min distance 0) on
  the rest.
* ``scripts/count_crossings.py`` runs it over a ``frames.h5``; :func:`check_run` is the
  main job's end-of-run check (``output.check_crossings``): the crossings and the
  largest edge strain of a run's frames, the steps shared by the ranks.
* :func:`min_distance`: the smallest distance between two wisps at one frame, exact
  (``scripts/count_crossings.py``'s per-step figure).
* :func:`rest_exempt_pairs`: which crossing pairs strand contact exempts (closer than
  its thickness at rest), so that the check does not blame the ccd limiter for them.
* :func:`edge_strain`: every edge's strain against the rest pose
  (``scripts/edge_strain.py`` per frame of a ``frames.h5``: torn strands, issue 13).
"""

from __future__ import annotations

import numpy as np

from lc_petsc.elements.compiled_ccd import box_pairs, pair_distances, safe_fraction, screen_paths
from lc_petsc.elements.segment_contact import distance as segment_distance
from lc_petsc.elements.segment_ccd import affine_field, affine_sums, field_boxes, tight_inclusion_toi


def segments(offsets):
    """(first vertex (m,), wisp (m,)) of every segment of wisps given by ``offsets``."""
    offsets = np.asarray(offsets, np.int64)
    seg = np.concatenate([np.arange(offsets[w], offsets[w + 1] - 1)
                          for w in range(len(offsets) - 1)] or [np.zeros(0, np.int64)])
    wisp = np.repeat(np.arange(len(offsets) - 1), np.maximum(np.diff(offsets) - 1, 0))
    return seg.astype(np.int64), wisp.astype(np.int64)


def candidate_pairs(X0, X1, offsets, self_contact=False, margin=0.0, stop=None):
    """Segment pairs (k, 2) of global first vertices that can come within ``margin`` on
    the linear path X0 -> X1 (n_vertices, 3) (the relative broad phase of
    :func:`segment_ccd.field_boxes`, with the affine field fitted to X1 - X0); different
    wisps, or with ``self_contact`` also segments of one wisp sharing no vertex.  None
    once ``stop()`` is true (looked at between parts of the broad phase, box_pairs, and
    every SCREEN_CHUNK of its pairs)."""
    seg, wisp = segments(offsets)
    A, b, L = affine_field(*affine_sums(X0, X1 - X0))
    f = X1 - X0 - (X0 @ A.T + b)
    ij = box_pairs(*field_boxes(np.stack([X0[seg], X0[seg + 1]], axis=1),
                                np.stack([f[seg], f[seg + 1]], axis=1), L, margin),
                   group=None if self_contact else wisp, stop=stop)
    if ij is None:
        return None
    out, n = np.empty((len(ij), 2), np.int64), 0     # filled in place: a concatenation took 4 s
    for a in range(0, len(ij), SCREEN_CHUNK):   # 10 s for a wild step's 68M pairs at once
        if a and stop is not None and stop():
            return None
        i, j = ij[a:a + SCREEN_CHUNK, 0], ij[a:a + SCREEN_CHUNK, 1]
        keep = wisp[i] != wisp[j]
        if self_contact:
            keep |= np.abs(seg[i] - seg[j]) > 1
        k = int(keep.sum())
        out[n:n + k, 0], out[n:n + k, 1] = seg[i[keep]], seg[j[keep]]
        n += k
    return out[:n]


def pair_positions(X, pairs):
    """(k, 4, 3) points of the segment pairs (first vertices) at positions X."""
    a, b = pairs[:, 0], pairs[:, 1]
    return np.stack([X[a], X[a + 1], X[b], X[b + 1]], axis=1)


#: a Tight-Inclusion hit is dropped when conservative advancement (up to CLEAR_STEPS
#: steps) proves the pair's distance stays above CLEAR_DISTANCE x (its largest coordinate
#: + 1) on the whole path
CLEAR_DISTANCE = 1e-9
CLEAR_STEPS = 100000


#: pairs given to Tight-Inclusion (and the clear-path proof) between two looks at
#: ``stop`` in :func:`crossing_pairs`: each pair is bounded (1e5 splits, 0.09 s, and two
#: proofs of 1e5 steps), so a signal waits for this many at most, not for a wild step's
#: thousands of undecided pairs
CROSSING_CHUNK = 32


def crossing_pairs(S, E, tolerance=1e-6, max_iterations=100000, stop=None):
    """Boolean (k,): whether each pair (start S, end E, (k, 4, 3)) meets on its linear
    path: :func:`segment_ccd.tight_inclusion_toi` at min distance 0 (pairs touching at
    the start count as meeting; a pair still undecided after ``max_iterations``
    interval splits counts as meeting: conservative), less the hits that conservative
    advancement proves to stay CLEAR_DISTANCE (relative) apart: Tight-Inclusion's
    undecided answer is a hit, and a pair of a 60-wisp hairball step 4.45e-6 cm apart on
    its whole path was one (with 1e5 splits; 1e4 and 1e6 answer no), a crossing the
    ccd limiter had not let through in the end-of-run check.  ``stop``: callable, looked
    at every :data:`CROSSING_CHUNK` pairs; None is returned once it is true."""
    S, E = np.asarray(S, float), np.asarray(E, float)
    if stop is None:
        return _meets(S, E, tolerance, max_iterations)
    hit = np.zeros(len(S), bool)
    for a in range(0, len(S), CROSSING_CHUNK):
        if stop():
            return None
        hit[a:a + CROSSING_CHUNK] = _meets(S[a:a + CROSSING_CHUNK], E[a:a + CROSSING_CHUNK], tolerance,
                                           max_iterations)
    return hit


def _meets(S, E, tolerance, max_iterations):
    """:func:`crossing_pairs` of the pairs S, E (k, 4, 3), without looks at a stop."""
    hit = tight_inclusion_toi(S, E, 0.0, tolerance=tolerance, max_iterations=max_iterations)[0]
    k = np.flatnonzero(hit)
    if len(k):
        S, E = S[k], E[k]
        scale = np.abs(np.concatenate([S, E], axis=1)).reshape(len(k), -1).max(axis=1) + 1.0
        clear = safe_fraction(S, E, CLEAR_DISTANCE * scale, max_steps=CLEAR_STEPS, exact=True) >= 1.0
        r = np.flatnonzero(~clear)
        if len(r):      # nearly parallel pairs sliding along each other close by
            PS, PE = across_pairs(S[r], E[r])
            clear[r] = safe_fraction(PS, PE, CLEAR_DISTANCE * scale[r], max_steps=CLEAR_STEPS, exact=True) >= 1.0
        hit[k[clear]] = False
    return hit


def across_pairs(S, E):
    """The pairs S, E (k, 4, 3) projected onto the plane normal to each pair's mean
    direction u (of A's and B's vectors at both ends, B's turned to A's side).  The
    projection is linear and shortens no distance, so the projected pair moves on
    straight paths and its distance is a lower bound of the pair's at every t: for two
    nearly parallel segments sliding along each other 1e-6 apart it drops the sliding,
    which the motion bound counts in full (1e6 advancement steps for a 1 cm slide).  A
    pair without a direction (u = 0) is left as it is."""
    dA = S[:, 1] - S[:, 0] + E[:, 1] - E[:, 0]
    dB = S[:, 3] - S[:, 2] + E[:, 3] - E[:, 2]
    u = dA + np.where(np.einsum("ij,ij->i", dA, dB) < 0.0, -1.0, 1.0)[:, None] * dB
    n = np.linalg.norm(u, axis=1)
    u = np.where(n[:, None] > 0.0, u / np.where(n > 0.0, n, 1.0)[:, None], 0.0)[:, None, :]
    return S - np.einsum("kpc,kqc->kp", S, u)[:, :, None] * u, E - np.einsum("kpc,kqc->kp", E, u)[:, :, None] * u


#: candidate pairs sorted out and screened at a time between two looks at ``stop``
#: (about 0.6 s on this machine; a scrambled 200-wisp step has 68M candidates, 43 s to
#: screen; the broad phase that finds them looks every compiled_ccd.BOX_TESTS box tests)
SCREEN_CHUNK = 1 << 20


def count_crossings(X0, X1, offsets, self_contact=False, stop=None):
    """Crossings on the linear path X0 -> X1 (n_vertices, 3) of wisps ``offsets``:
    dict with ``crossings`` (number of segment pairs that meet), ``pairs`` (k, 2) of
    their first global vertices, ``same_wisp`` (k,) whether each is of one wisp,
    ``within`` (how many are).  ``stop``: callable, looked at between parts
    of the broad phase (:data:`compiled_ccd.BOX_TESTS` box tests), every SCREEN_CHUNK
    candidate pairs and every :data:`CROSSING_CHUNK` pairs left for Tight-Inclusion;
    None is returned once it is true."""
    X0, X1 = np.asarray(X0, float), np.asarray(X1, float)
    if X0.shape != X1.shape or X0.ndim != 2 or X0.shape[1] != 3:
        raise ValueError(f"count_crossings: positions must both be (n_vertices, 3), got "
                         f"{X0.shape} and {X1.shape}")
    pairs = candidate_pairs(X0, X1, offsets, self_contact, stop=stop)
    if pairs is None:
        return None
    may_meet = np.empty(len(pairs), bool)
    for a in range(0, len(pairs), SCREEN_CHUNK):
        if stop is not None and stop():
            return None
        may_meet[a:a + SCREEN_CHUNK] = screen_paths(X0, X1, pairs[a:a + SCREEN_CHUNK])[0]
    near = pairs[may_meet]
    hit = crossing_pairs(pair_positions(X0, near), pair_positions(X1, near), stop=stop)
    if hit is None:
        return None
    seg, wisp = segments(offsets)
    wid = np.full(len(X0), -1, np.int64)
    wid[seg] = wisp
    hits = near[hit]
    same = wid[hits[:, 0]] == wid[hits[:, 1]]
    return {"crossings": int(hit.sum()), "pairs": hits, "same_wisp": same, "within": int(same.sum())}


def min_distance(X, offsets, reach=0.0):
    """The smallest distance between two segments of different wisps at positions X
    (n_vertices, 3) of wisps ``offsets``, exact; None with fewer than two wisps.  Broad
    phases of the segments' boxes grown by m / 2 (every pair closer than m is then a
    candidate), m from ``reach`` (or the median segment length) and growing to the
    closest candidate's distance until one is within m."""
    seg, wisp = segments(offsets)
    X = np.asarray(X, float)
    if len(seg) == 0 or wisp[0] == wisp[-1]:
        return None
    P = np.stack([X[seg], X[seg + 1]], axis=1)
    lo, hi = P.min(axis=1), P.max(axis=1)
    span = float(np.linalg.norm(hi.max(axis=0) - lo.min(axis=0)))
    m = max(reach, float(np.median(np.linalg.norm(P[:, 1] - P[:, 0], axis=1))), 1e-12 * span, 1e-300)
    while True:
        ij = box_pairs(lo - 0.5 * m, hi + 0.5 * m, group=wisp)
        found = float(pair_distances(P, ij[:, 0], ij[:, 1]).min(initial=np.inf))
        if found <= m or m > span:      # beyond the span every pair is a candidate
            return found
        m = found * (1.0 + 1e-9) if found < np.inf else 2.0 * m   # the closest one counts as found


def rest_exempt_pairs(rest, pairs, thickness):
    """Boolean (k,): whether each segment pair (first global vertices, (k, 2)) is closer
    than ``thickness`` in the rest positions ``rest``: strand contact exempts such pairs
    (penalty mode always, ccd mode with ``physics.strand_rest_overlap = "exempt"``;
    the test of ``StrandContact``), so they may pass through each other."""
    if len(pairs) == 0:
        return np.zeros(0, bool)
    return segment_distance(pair_positions(np.asarray(rest, float), pairs)) < thickness


def edge_strain(x, rest, offsets):
    """Strain |e| / |e_rest| - 1 of every edge of every wisp (n_vertices - n_wisps,), x and
    rest (n_vertices, 3), wisps ``offsets`` (n_wisps + 1,)."""
    x, rest = np.asarray(x, float), np.asarray(rest, float)
    if x.shape != rest.shape or x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"edge_strain: positions and rest positions must both be (n_vertices, 3), "
                         f"got {x.shape} and {rest.shape}")
    inner = np.ones(len(x) - 1, bool)
    inner[np.asarray(offsets, np.int64)[1:-1] - 1] = False      # no edge between two wisps
    length = np.linalg.norm(np.diff(x, axis=0), axis=1)[inner]
    return length / np.linalg.norm(np.diff(rest, axis=0), axis=1)[inner] - 1.0


def frames_layout(r, with_rest=False):
    """``/wisp_offsets`` of frames.h5 open in the
    :class:`lc_petsc.io.frames_read.FramesReader` ``r`` (and with ``with_rest`` its
    ``/rest_positions``), after checking the datasets' shapes
    (:func:`lc_petsc.io.frames_read.layout_problem`) and the offsets
    (:attr:`lc_petsc.io.frames_read.FramesReader.offsets`): a ValueError names a
    file that is not a run's frames (a strands file, say); a KeyError a missing
    dataset."""
    off = r.offsets         # (checked, after the shapes)
    if not with_rest:
        return off
    return off, np.asarray(r.dataset("rest_positions"), float)


def count_frames(path, self_contact=False, progress=None):
    """Per frame step of a ``frames.h5`` (step k: rows k -> k + 1): list of dicts with
    ``step``, ``frames`` (the simulation frames of its two rows), ``crossings`` and
    ``min_distance`` (the smallest distance between two segments of different wisps at
    the later frame, :func:`min_distance`; None with one wisp), and the run's
    ``physics.strand_thickness`` (0 when the config has none, the first reach of
    min_distance); steps from or to a row that holds no frame (lost in a recovery,
    ``/frame_valid``) are left out.  ``progress(dict)`` is called per step."""
    import json
    from lc_petsc.io.frames_read import FramesReader
    with FramesReader(path) as r:
        off = frames_layout(r)
        every = r.every                            # row k is simulation frame k * every
        cfg = json.loads(r.f.attrs["config"]) if "config" in r.f.attrs else {}
        d0 = float((cfg.get("physics") or {}).get("strand_thickness") or 0.0)
        out = []
        for k, prev, cur in step_rows(r, valid_steps(r.valid)):
            c = count_crossings(prev, cur, off, self_contact)
            out.append({"step": k, "frames": (k * every, (k + 1) * every), "crossings": c["crossings"],
                        "min_distance": min_distance(cur, off, reach=d0)})
            if progress is not None:
                progress(out[-1])
    return out, d0


#: an edge stretched or compressed by more than this fraction of its rest length is
#: visibly torn or crushed hair (scripts/edge_strain.py counts them too)
STRAIN_WARN = 0.10


def check_run(path, comm, self_contact=False, rest_exempt=None, stop=None, contact_within=True):
    """The crossings along the straight paths between consecutive frames of the closed
    ``frames.h5`` at ``path`` (what a viewer interpolating the frames shows), and the
    edges' strain in the frames after the first, for the run's end-of-run check.
    Collective over the mpi4py communicator ``comm``: each rank reads its own contiguous
    share of the frame steps (read-only, serial h5py).

    Returns a dict, the same on every rank: ``steps`` checked (steps from or to a row
    lost in a recovery are not checked); ``between_wisps`` and ``steps_between``
    (crossings of segments of different wisps, and the steps that have any),
    ``first_between`` (first such step, step k: rows k -> k + 1, or None); with
    ``self_contact`` also ``within_wisps``, ``steps_within`` and ``first_within``
    (segments of one wisp sharing no vertex), else those are None; with ``rest_exempt``
    (the run's contact thickness d0) ``between_exempt`` and ``within_exempt``: how many of
    those crossings are of pairs closer than d0 at rest, which the contact exempts
    (:func:`rest_exempt_pairs`), else None; ``within_exempt`` is None too where the run's
    contact does not act within a wisp (``contact_within`` False: no
    ``physics.strand_self_contact``, so a wisp's crossings of itself are no exemption's,
    however close its segments were at rest); ``largest_strain``
    (the largest |edge length / rest length - 1| over the rows that end a step),
    ``largest_strain_row`` and ``rows_over_strain`` (rows with an edge beyond
    :data:`STRAIN_WARN`); ``initial_strain``: the same measure of row 0, the initial
    state (None when its step is not checked); ``head``: how deep the hair sinks into the head sphere
    (:func:`lc_petsc.head_check.summarize`; None when the scene has no head sphere).
    ``{"error": message}`` when the file cannot be read.

    ``stop``: a :class:`lc_petsc.stop_notice.StopNotice` or None; a signal on any rank
    stops every rank's share at its next step, and the answer is ``{"interrupted": steps
    done}`` on every rank (the ranks wait for each other looking for signals)."""
    from lc_petsc.head_check import summarize
    rows, problem, n_steps = [], None, 0     # (step, between, within, strain, ...) of this rank's steps
    try:
        rows, n_steps = _count_share(path, comm.rank, comm.size, self_contact, rest_exempt, stop)
    except Exception as e:  # noqa: BLE001 - never a reason to lose the run's summary, and
        # one rank's failure must be every rank's answer (the others wait in allgather)
        problem = f"{path}: {e}" if isinstance(e, (OSError, KeyError, ValueError)) else \
            f"{path}: {type(e).__name__}: {e}"
    if stop is not None:
        stop.barrier()
    parts = comm.allgather((rows, problem, n_steps, stop is not None and stop.requested()))
    problems = [p for _, p, _, _ in parts if p]
    if problems:
        return {"error": problems[0]}
    if any(s for _, _, _, s in parts):
        return {"interrupted": sum(len(part) for part, _, _, _ in parts)}
    rows = [r for part, _, _, _ in parts for r in part]
    n_steps = max(n for _, _, n, _ in parts)
    between = [r for r in rows if r[1]]
    within = [r for r in rows if r[2]]
    worst = max(rows, key=lambda r: r[3], default=None)
    return {"steps": n_steps,
            "between_wisps": sum(r[1] for r in rows), "steps_between": len(between),
            "first_between": between[0][0] if between else None,
            "within_wisps": sum(r[2] for r in rows) if self_contact else None,
            "steps_within": len(within) if self_contact else None,
            "first_within": (within[0][0] if within else None) if self_contact else None,
            "between_exempt": sum(r[4] for r in rows) if rest_exempt is not None else None,
            "within_exempt": (sum(r[5] for r in rows) if rest_exempt is not None and self_contact and contact_within
                              else None),
            "largest_strain": worst[3] if worst else None,
            "largest_strain_row": worst[0] + 1 if worst else None,
            "initial_strain": next((r[7] for r in rows if r[0] == 0), None),
            "rows_over_strain": sum(r[3] > STRAIN_WARN for r in rows),
            "head": summarize([(r[0], r[6]) for r in rows if r[6] is not None])}


def valid_steps(held):
    """The steps k (rows k -> k + 1) between two rows that hold a frame (``held``: bool per
    row, :func:`lc_petsc.io.frames.valid_rows`): a row lost in a recovery has no step."""
    return [k for k in range(len(held) - 1) if held[k] and held[k + 1]]


def step_rows(r, steps):
    """(k, positions of row k, of row k + 1) for each step k of ``steps`` (ascending) of
    frames.h5 open in the :class:`lc_petsc.io.frames_read.FramesReader` ``r``; each row is
    read once, in blocks of consecutive rows (a damaged row is a ValueError,
    :meth:`~lc_petsc.io.frames_read.FramesReader.rows`)."""
    wanted = set(steps)
    last = None                                  # (row, its positions)
    for k, x in r.rows(sorted(wanted | {k + 1 for k in wanted})):
        if last is not None and last[0] == k - 1 and k - 1 in wanted:
            yield k - 1, last[1], x
        last = (k, x)


def _count_share(path, rank, size, self_contact, rest_exempt=None, stop=None):
    """(rows, steps) for :func:`check_run`: this rank's contiguous share of the steps, up
    to a signal (``stop``); a row is (step, between, within, strain, exempt between,
    exempt within, head figures (:func:`lc_petsc.head_check.step_depths`, None without a
    head sphere), row 0's strain (step 0 only, else None))."""
    from lc_petsc.head_check import file_head, step_depths
    from lc_petsc.io.frames_read import FramesReader
    with FramesReader(path) as f:
        off, rest = frames_layout(f, with_rest=True)
        steps = valid_steps(f.valid)
        head = file_head(f)
        times = f.times if head is not None else None
        rows = []
        for k, prev, cur in step_rows(f, steps[len(steps) * rank // size:len(steps) * (rank + 1) // size]):
            if stop is not None and stop.requested():
                break
            r = count_crossings(prev, cur, off, self_contact, stop=None if stop is None else stop.requested)
            if r is None:
                break
            sunk = None if head is None else step_depths(head[0], prev, cur, times[k], times[k + 1], off,
                                                         head[1], head[2])
            strain = float(np.abs(edge_strain(cur, rest, off)).max(initial=0.0))
            # the initial state's own strain (a perturbation's), not judged but told apart
            start = float(np.abs(edge_strain(prev, rest, off)).max(initial=0.0)) if k == 0 else None
            ex_between = ex_within = 0
            if rest_exempt is not None and r["crossings"]:
                exempt, same = rest_exempt_pairs(rest, r["pairs"], rest_exempt), r["same_wisp"]
                ex_between, ex_within = int(np.sum(exempt & ~same)), int(np.sum(exempt & same))
            rows.append((k, r["crossings"] - r["within"], r["within"], strain, ex_between, ex_within, sunk, start))
    return rows, len(steps)
