"""Run diagnostics, collective over the simulator's communicator:

* :func:`term_warnings`: terms that are switched on but can have no effect in the
  scene, and settings known to spoil a term (the main job prints them and records them
  in summary.json);
* :func:`shape_measures`: the curl-shape measure used to choose and test the material
  parameters of the shipped scenes (mean curl radius and mean root-to-tip length of
  the wisps, relative to the rest shape).

Curl radius of a wisp: slide a window of ``turn`` consecutive vertices (5 = one turn of
the 4C helix) along it; the window's centroid lies on the coil axis, the axis direction
is the difference of the neighbouring windows' centroids, and the window's radius is the
mean distance of its vertices from that axis.  The wisp's curl radius is the mean over
its windows.  It is invariant to rigid motion, so the head may move.
"""

from __future__ import annotations

import json

import numpy as np

from lc_petsc.config import TOLERANCE_PATH, TOLERANCE_PATH_WITHOUT_STRAND_CONTACT
from lc_petsc.parallel import global_max, global_min, global_reduce


def wisp_curl_radius(x, turn=5):
    """Mean coil radius of one wisp's vertices x (n, 3) (NaN if fewer than turn + 2)."""
    n = len(x)
    if n < turn + 2:
        return float("nan")
    c = np.lib.stride_tricks.sliding_window_view(x, (turn, 3))[:, 0].mean(axis=1)  # (n-turn+1, 3)
    a = c[2:] - c[:-2]
    norm = np.linalg.norm(a, axis=1, keepdims=True)
    a = np.divide(a, norm, out=np.zeros_like(a), where=norm > 0)
    win = np.lib.stride_tricks.sliding_window_view(x, (turn, 3))[1:-1, 0]        # (m, turn, 3)
    d = win - c[1:-1, None, :]
    perp = d - np.einsum("mtk,mk->mt", d, a)[..., None] * a[:, None, :]
    return float(np.linalg.norm(perp, axis=2).mean())


def shape_measures(comm, x, x_rest, offsets, turn=5):
    """Mean curl radius and mean root-to-tip length of all wisps, now (x) and at rest.

    ``x``, ``x_rest``: this rank's positions; ``offsets``: its local wisp offsets.
    Returns a dict with ``curl_radius``, ``curl_radius_rest``, ``curl_radius_ratio``,
    ``wisp_length``, ``wisp_length_rest``, ``wisp_length_ratio`` and the largest
    per-wisp deviation of each ratio from 1 (``*_max_dev``); radius entries are None
    when the wisps are not curled (rest curl radius below 1e-6 of their length).
    """
    sums = np.zeros(8)   # r, r_rest, nr, L, L_rest, nL, max|r/r0-1|, max|L/L0-1|
    for w in range(len(offsets) - 1):
        a, b = int(offsets[w]), int(offsets[w + 1])
        L = float(np.linalg.norm(x[b - 1] - x[a]))
        L0 = float(np.linalg.norm(x_rest[b - 1] - x_rest[a]))
        sums[3:6] += (L, L0, 1)
        if L0 > 0:
            sums[7] = max(sums[7], abs(L / L0 - 1))
        r0 = wisp_curl_radius(x_rest[a:b], turn)
        if np.isfinite(r0) and r0 > 1e-6 * max(L0, 1e-300):
            r = wisp_curl_radius(x[a:b], turn)
            sums[0:3] += (r, r0, 1)
            sums[6] = max(sums[6], abs(r / r0 - 1))
    tot = global_reduce(comm, sums[:6], "sum")
    mx = global_reduce(comm, sums[6:], "max")
    out = {"wisp_length": tot[3] / max(tot[5], 1), "wisp_length_rest": tot[4] / max(tot[5], 1)}
    out["wisp_length_ratio"] = out["wisp_length"] / out["wisp_length_rest"] if tot[4] > 0 else None
    out["wisp_length_max_dev"] = float(mx[1])
    if tot[2] > 0:
        out.update(curl_radius=tot[0] / tot[2], curl_radius_rest=tot[1] / tot[2],
                   curl_radius_ratio=tot[0] / tot[1], curl_radius_max_dev=float(mx[0]))
    else:
        out.update(curl_radius=None, curl_radius_rest=None, curl_radius_ratio=None,
                   curl_radius_max_dev=None)
    return out


def newton_warnings(cfg):
    """Messages for Newton settings that cannot deliver what they ask: a tolerance with a
    filtered Hessian alone (the analytic, numerical or abs filter, no exact steps), whose
    iteration converges linearly (docs/newton.md "Twelfth round").  A config file reaches it
    only by naming that filter: without ``solver.filter`` a tolerance takes the converging
    path (:func:`lc_petsc.config.tolerance_defaults`).  A loose increment
    tolerance with a step above 1/30 s is no longer warned: its stops are now checked
    against the energy's quadratic model, and every stop measured at dt 0.15-0.2 was
    within the tolerance (docs/newton.md "Stopping rule")."""
    t, filt = cfg.time, cfg.solver.filter
    asked = [f"time.{k} = {getattr(t, k):g}" for k in ("newton_increment_tol", "newton_tol")
             if getattr(t, k) is not None]
    if asked and filt in ("analytic", "numerical", "abs") and t.newton == "filtered":
        cutback = (f"step cutback then splits each such frame into up to time.max_substeps = "
                   f"{t.max_substeps} steps of up to time.newton_iterations = {t.newton_iterations} "
                   "iterations each (the demo cut to 10 wisps at 1e-3, 5 frames: 45 iterations a "
                   "frame with 3, none converged; 379-395 with 30, each frame in 8 substeps; "
                   "exact_or_analytic: 15-64 in 1-2)" if t.max_substeps > 1 else
                   "with time.max_substeps = 1 they are reported unconverged")
        path, extra = (", ".join(f"{table}.{key} = {json.dumps(value)}" for (table, key), value in keys.items())
                       for keys in (TOLERANCE_PATH, TOLERANCE_PATH_WITHOUT_STRAND_CONTACT))
        return [f"{' and '.join(asked)} with solver.filter = {filt!r}: the filtered Newton "
                "converges linearly (about 0.97 per iteration on the demo hairball), so frames "
                "often miss the tolerance within time.newton_iterations, and above a tolerance of "
                "1e-5 (of the shortest wisp for time.newton_tol) its stops are refused "
                "(its steps do not decrease G as their quadratic model predicts: such stops had "
                f"been 4-31x the tolerance from the solution); {cutback} "
                "(docs/newton.md, \"Twelfth round\" and \"Stopping rule\"); leave solver.filter unset "
                f"(with a tolerance the default is then the converging path: {path}, and without strand contact "
                f"{extra}; docs/newton.md "
                "\"The default for tolerance runs\") to converge"
                + (", or time.max_substeps = 1 to keep this filter without the cutback"
                   if t.max_substeps > 1 else "")]
    return []


def term_warnings(sim):
    """Messages for terms (and head settings) that are on but can have no effect, for
    ccd contact with the inertial first iterate (torn strands), and for a tangled initial
    state run with ``strand_rest_overlap = "exempt"``."""
    cfg, sc, comm = sim.config, sim.scene, sim.comm
    phys = cfg.physics
    terms = set(phys.terms)
    out = []
    if sim.strand is not None and sim.strand.start_warning:      # the same on every rank
        out.append(sim.strand.start_warning)
    n_free = int(comm.allreduce(int((~sc.pinned).sum())))
    if n_free == 0:
        # name the setting that pins them: the bare message left the user to guess
        longest = int(global_max(comm, int(np.diff(sc.offsets).max(initial=0))))
        out.append(f"every vertex is pinned: no term has an effect (nothing moves but the head); "
                   f"scene.n_pinned = {cfg.scene.n_pinned} pins the first vertices of each wisp (the "
                   f"longest has {longest}), unless a groom file's /pinned or primvars:pinned does: "
                   f"pin only the roots, e.g. scene.n_pinned below {longest}")
    if "gravity" in terms and not np.any(np.asarray(phys.gravity, float)):
        out.append("physics.terms has 'gravity' but physics.gravity is [0, 0, 0]: it has no effect")
    if not terms & {"stretch", "bend", "twist"}:
        out.append("physics.terms has no elastic term (stretch, bend, twist): the vertices move "
                   "independently")
    has_pins = bool(comm.allreduce(int(sc.pinned.any())))
    if "head_collision" in terms and n_free:
        # The pinned roots move rigidly with the head, so a wisp anchored at pinned vertices
        # stays within its arc length of them: if that never reaches the sphere, contact
        # can never happen (free wisps without pins may fall anywhere: not checked).
        reach = 1
        if phys.head_motion != "translate" or not np.any(phys.head_velocity):
            reach = 0
            R = phys.head_radius + phys.head_margin
            c = np.asarray(phys.head_center, float)
            for w in range(sc.n_wisps):
                a, b = int(sc.offsets[w]), int(sc.offsets[w + 1])
                pin = sc.pinned[a:b]
                x = sc.x_rest[a:b]
                if not pin.any():
                    reach = 1
                    break
                arc = float(np.linalg.norm(np.diff(x, axis=0), axis=1).sum())
                gap = float(np.min(np.linalg.norm(x[pin] - c, axis=1)) - R)
                if gap <= arc:
                    reach = 1
                    break
        if not global_max(comm, reach):
            out.append("physics.terms has 'head_collision' but no wisp can reach the head sphere "
                       f"(radius {phys.head_radius + phys.head_margin:g} cm at {list(phys.head_center)}): "
                       "it has no effect")
    if "head_collision" in terms and n_free:
        # free vertices that start inside the sphere get the full penalty force at once
        # (k times the depth) and are thrown out in the first frames
        R = phys.head_radius + phys.head_margin
        c = np.asarray(phys.head_center, float)
        depth = R - np.linalg.norm(sim.x - c, axis=1)
        inside = (~sc.pinned) & (depth > 1e-9 * R)
        n_in = int(comm.allreduce(int(inside.sum())))
        if n_in:
            wisp_of = np.searchsorted(sc.offsets, np.arange(len(depth)), side="right") - 1
            wisps = np.unique(sim.wisp_order[np.unique(wisp_of[inside]) + sc.first_wisp])
            n_w = int(comm.allreduce(len(wisps)))
            first_w = int(global_min(comm, int(wisps[0]) if len(wisps) else 1 << 62))
            deepest = float(global_max(comm, float(depth[inside].max(initial=0.0))))
            out.append(f"{n_in} free vertices of {n_w} wisp(s) (the first: wisp {first_w}) start "
                       f"inside the head sphere (physics.head_radius + physics.head_margin = {R:g} cm "
                       f"at physics.head_center = {list(phys.head_center)}), up to {deepest:.3g} cm "
                       "deep: head_collision will push them out violently in the first frames; move "
                       "the wisps or the sphere")
    if ("strand_collision" in terms and phys.strand_contact_mode == "ccd"
            and cfg.time.initial_guess == "inertial"):
        out.append("physics.strand_contact_mode = \"ccd\" with time.initial_guess = \"inertial\": "
                   "the step limiter holds vertices back at the frame's first iterate, whose edges "
                   "inertia stretches, so strands tear in the first frames (docs/contact.md, \"Torn "
                   "strands\"); set time.initial_guess = \"follow_the_leader\" as the shipped "
                   "hairball scenes do")
    if ("strand_collision" in terms and phys.strand_contact_mode == "ccd"
            and not phys.strand_separation):
        out.append("physics.strand_contact_mode = \"ccd\" with physics.strand_separation = false: "
                   "the frame end's separation is what pushes the pairs the limiter holds at its "
                   "floor apart again and pulls their stretched edges back; without it they pile "
                   "up and edges stay stretched (29% on 60 soft wisps, docs/contact.md, \"Edges the "
                   "frame end leaves stretched\"); set physics.strand_separation = true")
    if phys.head_motion != "static" and not has_pins and "head_collision" not in terms:
        out.append(f"physics.head_motion = {phys.head_motion!r} has no effect: no vertex is pinned "
                   "and head_collision is off")
    if "gravity" in terms and np.any(phys.gravity) and not has_pins and "head_collision" not in terms:
        out.append("no vertex is pinned and head_collision is off: gravity makes every wisp fall "
                   "freely; pin the roots (scene.n_pinned, or /pinned or primvars:pinned in a groom file)")
    return out + sim.material_warnings + groom_radius_warnings(sim) + groom_edge_warnings(sim) + \
        groom_scale_warnings(sim)


def groom_material_warnings(comm, batch, where):
    """The per-wisp ``/youngs_modulus`` of a strands file (``batch``: this rank's wisps;
    ``where``: the file, for the message) outside the plausible range for hair
    (:data:`lc_petsc.config.PLAUSIBLE_RANGES`, as ``material.youngs_modulus``), naming how
    many wisps, the first (the scene's numbering) and its value: the config's key was warned
    about, a file's values (a groom written in Pa) were not.  (A ``/density`` outside its
    range is refused: :data:`lc_petsc.config.DENSITY_RANGE`.)  Collective (every rank the
    same warnings)."""
    from lc_petsc.config import PLAUSIBLE_RANGES
    lo, hi, unit, below, above = PLAUSIBLE_RANGES[("material", "youngs_modulus")]
    values = batch.youngs_modulus
    bad = np.zeros(0, int) if values is None else np.flatnonzero((values < lo) | (values > hi))
    n = int(comm.allreduce(len(bad)))
    if not n:
        return []
    w, v = min(comm.allgather((int(batch.ids()[bad[0]]), float(values[bad[0]])) if len(bad) else
                              (np.iinfo(np.int64).max, 0.0)))
    return [f"{where}: {n} wisp(s) have a /youngs_modulus outside the plausible range for hair, {lo:g} to {hi:g} "
            f"{unit}; the first: wisp {w}, {v:g} {unit}: {below if v < lo else above}; lc_petsc's units "
            "are cm, g, s"]


def groom_radius_warnings(sim):
    """The radii a strands or USD file gives, outside the plausible range for hair
    (:data:`lc_petsc.config.PLAUSIBLE_RANGES`, as ``material.root_radius``), naming the
    file: a groom written in mm or um (or m)."""
    from lc_petsc.config import PLAUSIBLE_RANGES
    cfg, comm = sim.config, sim.comm
    if cfg.scene.kind not in ("file", "usd"):
        return []
    lo, hi, _, below, above = PLAUSIBLE_RANGES[("material", "root_radius")]
    rmin = global_min(comm, float(sim.scene.radius.min(initial=np.inf)))
    rmax = global_max(comm, float(sim.scene.radius.max(initial=0.0)))
    if lo <= rmin and rmax <= hi:
        return []
    return [f"the radii of {cfg.scene.path} range from {rmin:.3g} to {rmax:.3g} cm, outside the "
            f"plausible range for hair, {lo:g} to {hi:g} cm: {below if rmin < lo else above}; "
            "lc_petsc's units are cm (USD: the stage's metersPerUnit converts widths)"]


#: a groom edge shorter than this fraction of its wisp's median edge is warned about: a
#: near-duplicate vertex (1e-3 cm in a fringe wisp of 0.5 cm edges) made the first frames'
#: linear solves fail (DIVERGED_INDEFINITE_PC) with advice about solvers, not the groom;
#: the shipped grooms' shortest edges are 0.5 of their median
SHORT_EDGE = 1e-2


def groom_edge_warnings(sim):
    """Edges of a strands or USD file far shorter than the rest of their wisp
    (:data:`SHORT_EDGE`), naming the file, the shortest one (wisp, edge, length) and how
    many wisps have one: near-duplicate vertices (the exactly coincident ones are an
    error of the rest state) leave the Newton matrix so ill-conditioned that its solves
    fail.  And edges far longer (:data:`lc_petsc.scene.outliers.DISPLACED`), the longest
    named: a displaced end vertex or a gap in the wisp (a displaced interior vertex is an
    error of the build)."""
    from lc_petsc.scene.outliers import DISPLACED
    cfg, sc, comm = sim.config, sim.scene, sim.comm
    if cfg.scene.kind not in ("file", "usd"):
        return []
    worst, n_short = (np.inf, 0, 0, 0.0, 0.0), 0
    longest, n_long = (-np.inf, 0, 0, 0.0, 0.0), 0
    for w in range(sc.n_wisps):
        L = _rest_edges(sc, w)
        med = float(np.median(L))
        wisp = int(sim.wisp_order[sc.first_wisp + w])
        j = int(np.argmin(L))
        if L[j] < SHORT_EDGE * med:
            n_short += 1
            worst = min(worst, (float(L[j] / med), wisp, j, float(L[j]), med))
        j = int(np.argmax(L))
        if L[j] >= DISPLACED * med:
            n_long += 1
            longest = max(longest, (float(L[j] / med), -wisp, j, float(L[j]), med))
    n_short, n_long = int(comm.allreduce(n_short)), int(comm.allreduce(n_long))
    out = []
    if n_short:
        out.append(_edge_note(cfg.scene.path, n_short, f"shorter than {SHORT_EDGE:g} of their wisp's median edge",
                              "shortest", min(comm.allgather(worst)),
                              ": a near-duplicate vertex, which makes the Newton matrix so ill-conditioned that "
                              "its linear solves can fail; remove the vertex or resample the wisp"))
    if n_long:
        found = max(comm.allgather(longest))
        out.append(_edge_note(cfg.scene.path, n_long, f"{DISPLACED:g} or more times their wisp's median edge",
                              "longest", found[:1] + (-found[1],) + found[2:],
                              f" ({found[0]:.3g} times): a displaced vertex (a damaged file, e.g. a flipped bit) or "
                              "a gap in the wisp, not hair's even sampling; check that vertex, or resample the wisp"))
    return out


def _edge_note(path, n, what, which, found, why):
    """The warning about ``n`` wisps of the groom ``path`` with an edge ``what``, naming
    the ``which`` one ``found`` = (ratio, wisp, edge, length, median), then ``why``."""
    _, wisp, j, length, med = found
    return (f"{path}: {n} wisp(s) have an edge {what}; the {which}: wisp {wisp}, edge {j} (vertices {j}, "
            f"{j + 1}), rest length {length:.3g} cm against a median of {med:.3g} cm{why}")


def _rest_edges(sc, w):
    """The rest lengths of wisp ``w``'s edges (``sc``: the rank's scene)."""
    return np.linalg.norm(np.diff(sc.x_rest[sc.offsets[w]:sc.offsets[w + 1]], axis=0), axis=1)


#: a wisp of a groom file whose median edge is below this fraction of the groom's (the
#: median of the wisps' median edges) and below its own median radius is warned about as
#: in other units: one fringe wisp in metres (x 0.01) is at 0.0078 of the groom and 0.073
#: of its radius; the shipped scenes' wisps at least 0.66 and 2.84 (docs/elements.md)
SMALL_WISP = 1.0 / 30.0
#: a wisp whose median edge is this many times the groom's, or 1/this, is in other units
#: when its root, scaled about the origin by the power of ten nearest that ratio, lands
#: in the box of the other wisps' roots (:func:`_unit_wisp`): one fringe wisp in
#: millimetres (x 10) is at 6.7-17 times the groom; the shipped and test grooms' wisps at
#: most 1.7 (docs/elements.md)
UNIT_WISP = 5.0
#: the plausible median wisp length (cm) of a groom file: the fringe's 38 cm is 380 in
#: millimetres, 0.38 in metres; a wisp :data:`UNIT_WISP` times finer than its groom and
#: shorter than the low end is warned about too (a fringe wisp in metres: 0.17-0.91 cm)
GROOM_LENGTH = (1.0, 200.0)


def _box_distance(p, lo, hi):
    """Distance from ``p`` to the box [lo, hi]."""
    return float(np.linalg.norm(np.maximum(lo - p, 0.0) + np.maximum(p - hi, 0.0)))


def _unit_wisp(ratio, roots, i):
    """Why wisp ``i`` of the wisps rooted at ``roots`` (n, 3), whose median edge is
    ``ratio`` times the groom's, looks written in other units than the others, else None:
    its edges a power of ten u off (within a factor :data:`UNIT_WISP`), its root far
    outside the box of their roots (by a quarter of its diagonal) and ``root / u`` (where
    it was in centimetres) inside it or twice as close.  A long wisp among short ones
    keeps its root among theirs."""
    if len(roots) < 3 or 1.0 / UNIT_WISP < ratio < UNIT_WISP:
        return None
    root, others = roots[i], np.delete(roots, i, axis=0)     # (a copy: only for an odd wisp)
    u = 10.0 ** round(float(np.log10(ratio)))
    lo, hi = others.min(axis=0), others.max(axis=0)
    d, back = _box_distance(root, lo, hi), _box_distance(root / u, lo, hi)
    if d <= 0.25 * float(np.linalg.norm(hi - lo)) or back >= 0.5 * d:
        return None
    return (f"and its root lies {d:.3g} cm outside the box of the other wisps' roots, "
            f"{back:.3g} cm when scaled by {1 / u:g}")


def groom_scale_warnings(sim):
    """Wisps of a strands or USD file in other units than the rest of the groom, and a
    whole groom of implausible length (collective).  A wisp: far smaller than the groom
    with edges shorter than its strands are thick (:data:`SMALL_WISP`), or a power of ten
    off with its root outside the other roots where scaled back it fits
    (:data:`UNIT_WISP`); a groom: its median wisp length outside :data:`GROOM_LENGTH`.
    Each ran unnamed."""
    cfg, sc, comm = sim.config, sim.scene, sim.comm
    if cfg.scene.kind not in ("file", "usd"):
        return []
    mine = []
    for w in range(sc.n_wisps):
        edges = _rest_edges(sc, w)
        radius = float(np.median(sc.radius[sc.offsets[w]:sc.offsets[w + 1]]))
        mine.append((float(np.median(edges)), radius, float(edges.sum()), sc.x_rest[sc.offsets[w]].tolist(),
                     int(sim.wisp_order[sc.first_wisp + w])))
    wisps = sorted((m for part in comm.allgather(mine) for m in part), key=lambda m: m[4])
    if not wisps:
        return []
    out = []
    length = float(np.median([m[2] for m in wisps]))
    lo, hi = GROOM_LENGTH
    if not lo <= length <= hi:
        out.append(f"{cfg.scene.path}: its wisps are {length:.3g} cm long (the median), outside the plausible "
                   f"range for hair, {lo:g} to {hi:g} cm: it looks like "
                   f"{'millimetres' if length > hi else 'metres'}; lc_petsc's units are cm (scale the groom; "
                   "a USD stage: its metersPerUnit)")
    groom = float(np.median([m[0] for m in wisps]))
    roots = np.array([m[3] for m in wisps])
    odd = []
    for i, (e, r, wisp_length, _, wisp) in enumerate(wisps):
        ratio = e / groom
        why = f"and shorter than its strand radius ({r:.3g} cm)" if ratio < SMALL_WISP and e < r else \
            f"and {wisp_length:.3g} cm long, shorter than hair ({lo:g} cm)" \
            if ratio <= 1.0 / UNIT_WISP and wisp_length < lo else \
            _unit_wisp(ratio, roots, i)
        if why:
            odd.append((-abs(np.log(ratio)), wisp, ratio, e, why))
    if not odd:
        return out
    _, wisp, ratio, edge, why = min(odd)
    more = f" (and {len(odd) - 1} more wisp(s))" if len(odd) > 1 else ""
    size = f"{1 / ratio:.3g} times smaller" if ratio < 1 else f"{ratio:.3g} times larger"
    return out + [f"{cfg.scene.path}: wisp {wisp}{more} is {size} than the groom: its median edge is {edge:.3g} cm "
                  f"against the groom's {groom:.3g} cm, {why}; a wisp written in other units "
                  f"({'metres' if ratio < 1 else 'millimetres'}?) than the rest; lc_petsc's units are cm "
                  "(scale that wisp)"]


def unwritten_frames_warnings(cfg):
    """Frames simulated after the last one written: with ``time.frames`` not a multiple of
    ``output.every`` the run's last frames, its final state among them, are in neither
    frames.h5 nor frames.usdc (nor in any checkpoint unless ``output.checkpoint_every``
    divides ``time.frames``).  Main ran them without a word: smash with ``every = 5`` and
    ``--frames 3`` simulated 3 frames and wrote frame 0 alone."""
    n, every, ck = cfg.time.frames, cfg.output.every, cfg.output.checkpoint_every
    tail = n % every
    if not tail:
        return []
    last = n - tail
    kept = (f"the checkpoint of frame {n} keeps its final state" if ck and n % ck == 0 else
            "no file keeps its final state")
    frames = f"frame {n} is" if tail == 1 else f"frames {last + 1} to {n} are"
    files = "frames.h5 and frames.usdc end" if cfg.output.usd else "frames.h5 ends"
    runs = f"{last + every} frames (or {last})" if last else f"{every} frames"
    return [f"time.frames = {n} (time.frames / --frames) is not a multiple of output.every = {every}: "
            f"{frames} simulated but not written ({files} at frame {last}; {kept}); run {runs} to "
            f"have the run's end written"]


def preview_warnings(cfg):
    """``output.preview_frames`` outside the run's frames (a scene's list kept when the run
    is cut with ``--frames``): such a frame is drawn as the nearest end, which used to
    happen without a word (the demo's [0, 30, 60, -1] at 20 frames drew frame 20 for 30
    and 60).  With ``output.every`` > 1 the frames drawn are the frames written: the last
    is the last multiple of ``every`` (main named the run's last frame, which frames.h5
    does not hold), and a frame between two written ones is drawn as the one before it."""
    n, out = cfg.time.frames, cfg.output
    if not out.previews:
        return []
    every = out.every
    last = n - n % every        # the last frame of frames.h5 (frame 0, then every every-th)
    late = [f for f in out.preview_frames if f > n]
    early = [f for f in out.preview_frames if f < -(n + 1)]
    skipped = [f for f in out.preview_frames if 0 <= f <= n and f % every]
    if not late and not early and not skipped:
        return []
    what = ([f"{late} lie after its last frame ({n}), drawn as frame {last}"] if late else []) + \
           ([f"{early} lie before frame 0, drawn as frame 0"] if early else []) + \
           ([f"{skipped} are not written (output.every = {every}), each drawn as the frame written "
             f"before it"] if skipped else [])
    ask = f"0..{n}" if every == 1 else f"0, {every}, ... {last} (the frames written)"
    return [f"output.preview_frames = {list(out.preview_frames)}: the run has frames 0 to {n} "
            f"(time.frames / --frames), and {'; '.join(what)}; ask for frames in {ask} "
            f"(or -1 .. -{n + 1} from the end)"]
