"""PNG previews of a run, rendered from ``frames.h5`` with matplotlib (Agg, no display):
single frames and a contact sheet over time, so a person can look at a run without
ParaView.  Runs on one rank after the frames file is closed (it reads only the frames
it draws).

Orthographic views (``front``: x right, y up, seen from +z; ``side``: z right, y up,
seen from -x; ``top``: x right, z down, seen from +y).  Every wisp is cut into pieces of
4 edges (a coil turn), drawn far to near (painter's algorithm) so near strands cover
far ones; the nearer a piece, the more saturated, opaque and thick it is (far ones fade
into the background; depth is scaled over the frame's strands), on a per-wisp hue of
hair colours.  The pieces are drawn in DEPTH_LEVELS depth bins of HUE_LEVELS hue bins,
one compound path per bin (:func:`_stroke`): the 2K hairball's previews and contact
sheet took 7.9 s with a path per piece, 3.7 s so.  The head sphere, when the scene has one,
is drawn as a Lambert-shaded sphere (light from the upper left, in front); pieces
whose middle lies behind its visible surface are hidden, the others are drawn over it
(so occlusion is exact to a piece, about 1 cm for the 4C wisps).
All images of a run share the same axis limits, so motion between them is visible.
"""

from __future__ import annotations

import math
import os

import numpy as np

VIEW_AXES = {"front": (0, 1, "x (cm)", "y (cm)"), "side": (2, 1, "z (cm)", "y (cm)"),
             "top": (0, 2, "x (cm)", "z (cm)")}
# unit vector from the scene towards the viewer (screen right x screen up)
VIEW_TOWARD = {"front": np.array([0.0, 0.0, 1.0]), "side": np.array([-1.0, 0.0, 0.0]),
               "top": np.array([0.0, 1.0, 0.0])}
# a wisp is drawn in pieces of this many edges (one coil turn of a 4C wisp), each at its
# mean depth: 5x fewer paths than single edges for the same ordering at the coils' scale
PIECE_EDGES = 4
#: previews draw the pieces in this many depth bins, each in HUE_LEVELS hue bins
DEPTH_LEVELS = 32
HUE_LEVELS = 16
HEAD_RGB = np.array([0.82, 0.74, 0.66])
LIGHT = np.array([-0.45, 0.6, 0.66])          # screen coordinates (right, up, toward viewer)


def _pyplot():
    import matplotlib
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    return plt


def _pieces(offsets, piece=PIECE_EDGES):
    """Vertex indices (n_pieces, piece + 1) of the wisps cut into pieces of ``piece``
    edges (the last piece of a wisp repeats its tip vertex), and the wisp of each."""
    offsets = np.asarray(offsets, np.int64)
    sizes = np.diff(offsets)
    n_pieces = np.where(sizes > 1, -(-(sizes - 1) // piece), 0)
    wisp = np.repeat(np.arange(len(sizes)), n_pieces)
    first = np.concatenate([[0], np.cumsum(n_pieces)])[:-1]
    k = np.arange(len(wisp)) - first[wisp]
    start = offsets[:-1][wisp] + piece * k
    idx = np.minimum(start[:, None] + np.arange(piece + 1), (offsets[1:] - 1)[wisp][:, None])
    return idx, wisp


def _wisp_hue(n_w):
    """A per-wisp position (n_w,) in [0, 1] on the hair colours (:func:`_hair_rgb`),
    shuffled so neighbours differ."""
    return np.random.default_rng(12345).permutation(max(n_w, 1))[:n_w] / max(n_w - 1, 1)


def _hair_rgb(hue):
    """Hair colours (n, 3) of hues (n,) in [0, 1]: browns to auburn."""
    import matplotlib.pyplot as plt
    return plt.get_cmap("copper")(0.35 + 0.6 * np.asarray(hue, float))[:, :3]


def _stroke(ax, seg, near, hue, lw):
    """Draw the pieces ``seg`` (n, k, 2) far to near: nearer (``near`` (n,) in [0, 1])
    is more saturated, opaque and thick, on the hue (n,) of its wisp.  The pieces are
    binned by depth (DEPTH_LEVELS) and hue (HUE_LEVELS) and each bin is one compound
    path, drawn in depth order: matplotlib's cost is per path, so a 2,000-wisp frame
    (50k pieces) draws in a fraction of the time of a path per piece, with the order and
    the colours quantised to bins finer than the eye tells apart."""
    from matplotlib.collections import PathCollection
    from matplotlib.path import Path
    from matplotlib.transforms import IdentityTransform
    if not len(seg):
        return
    level = np.minimum((near * DEPTH_LEVELS).astype(int), DEPTH_LEVELS - 1)
    tone = np.minimum((hue * HUE_LEVELS).astype(int), HUE_LEVELS - 1)
    key = level * HUE_LEVELS + tone
    order = np.argsort(key, kind="stable")
    keys, first = np.unique(key[order], return_index=True)
    bounds = np.append(first, len(order))
    k = seg.shape[1]
    codes = np.full(k, Path.LINETO, dtype=Path.code_type)
    codes[0] = Path.MOVETO
    paths = [Path(seg[order[a:b]].reshape(-1, 2), np.tile(codes, b - a)) for a, b in zip(bounds[:-1], bounds[1:])]
    s = ((keys // HUE_LEVELS) + 0.5) / DEPTH_LEVELS
    rgba = np.empty((len(keys), 4))
    rgba[:, :3] = np.clip(_hair_rgb(((keys % HUE_LEVELS) + 0.5) / HUE_LEVELS) * (0.3 + 0.7 * s)[:, None]
                          + 0.12 * s[:, None] ** 4, 0.0, 1.0)
    rgba[:, 3] = 0.35 + 0.65 * s
    # paths in data coordinates (no offsets): the collection's transform is the axes' data
    pc = PathCollection(paths, facecolors="none", edgecolors=rgba, linewidths=lw * (0.4 + 0.6 * s),
                        capstyle="round", joinstyle="round", zorder=3, transform=ax.transData,
                        offset_transform=IdentityTransform())
    ax.add_collection(pc)


def _sphere_image(radius, view, n=256):
    """RGBA image (n, n, 4) of a Lambert-shaded sphere of ``radius``, rows along the
    view's second data axis (``origin="lower"``), transparent outside the disc."""
    g = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    px, py = np.meshgrid(g, g)
    up = -py if view == "top" else py          # the top view's data axis points down
    rr = px ** 2 + up ** 2
    nz = np.sqrt(np.clip(1.0 - rr, 0.0, 1.0))
    light = LIGHT / np.linalg.norm(LIGHT)
    lam = np.clip(px * light[0] + up * light[1] + nz * light[2], 0.0, 1.0)
    shade = 0.38 + 0.62 * lam
    img = np.zeros((n, n, 4))
    img[..., :3] = HEAD_RGB * shade[..., None]
    img[..., 3] = np.clip((1.0 - np.sqrt(rr)) * n / 2.0, 0.0, 1.0)     # anti-aliased rim
    return img


def _draw(ax, x, offsets, view, limits, head=None, lw=None):
    """Draw one frame: positions ``x`` (n_vertices, 3) of the wisps ``offsets``, depth
    ordered and shaded; ``head`` = (centre, radius) or None."""
    x = np.asarray(x, float)
    a, b = VIEW_AXES[view][:2]
    toward = VIEW_TOWARD[view]
    n_w = len(offsets) - 1
    if lw is None:
        lw = max(0.3, min(1.5, 60.0 / math.sqrt(max(n_w, 1))))
    idx_v, wisp = _pieces(offsets)
    seg = x[idx_v][:, :, [a, b]]
    mid = x[idx_v].mean(axis=1)
    depth = mid @ toward                         # larger = nearer the viewer
    visible = np.ones(len(seg), bool)
    if head is not None:
        c, r = np.asarray(head[0], float), float(head[1])
        d2 = (mid[:, a] - c[a]) ** 2 + (mid[:, b] - c[b]) ** 2
        front = c @ toward + np.sqrt(np.clip(r * r - d2, 0.0, None))
        visible = ~((d2 < r * r) & (depth < front))
        ax.imshow(_sphere_image(r, view), extent=(c[a] - r, c[a] + r, c[b] - r, c[b] + r),
                  origin="lower", interpolation="bilinear", zorder=2)
    if len(depth):
        lo, hi = np.percentile(depth, [1, 99])
        near = np.clip((depth - lo) / (hi - lo), 0.0, 1.0) if hi > lo else np.ones_like(depth)
    else:
        near = depth
    idx = np.flatnonzero(visible)
    _stroke(ax, seg[idx], near[idx], _wisp_hue(n_w)[wisp[idx]], lw)
    ax.set_xlim(limits[0])
    ax.set_ylim(limits[1])
    if view == "top":
        ax.invert_yaxis()
    ax.set_aspect("equal")
    ax.set_facecolor("0.97")


def _limits(arrays, view, head_discs):
    a, b = VIEW_AXES[view][:2]
    lo = np.min([x.min(axis=0) for x in arrays], axis=0)
    hi = np.max([x.max(axis=0) for x in arrays], axis=0)
    for c, r in head_discs:
        lo = np.minimum(lo, np.asarray(c) - r)
        hi = np.maximum(hi, np.asarray(c) + r)
    pad = 0.05 * max(float((hi - lo)[[a, b]].max()), 1e-6)
    return ((lo[a] - pad, hi[a] + pad), (lo[b] - pad, hi[b] + pad))


def _save(fig, path, **kw):
    """``fig`` as a PNG at ``path``, written aside and renamed when complete (like the
    checkpoints): a failure mid-write (a full disk) used to leave a partial PNG there,
    which a viewer showed as the run's image until a restart rewrote it."""
    from lc_petsc.io.disk import written_aside
    with written_aside(path) as tmp:
        fig.savefig(tmp, format="png", **kw)


def render_previews(frames_path, out_dir, preview_rows, contact_panels=12, view="front",
                    title="", head=None, every=1, stop=None):
    """Render ``preview_rows`` (row indices of ``/positions``) to
    ``out_dir/previews/frame_NNNNN.png`` (NNNNN the simulation frame number) and a
    contact sheet of ``contact_panels`` rows evenly spaced over the run to
    ``out_dir/contact_sheet.png``.  Only rows that hold a frame (``/frame_valid``) are
    drawn: a lost row's preview is the nearest valid row's.  ``head``: callable t ->
    (centre, radius) or None.  ``stop``: called before each image (the main job's raises
    :class:`lc_petsc.stop_notice.Stopped` on a signal), or None.  Returns the paths written."""
    from lc_petsc.io.frames_read import FramesReader
    plt = _pyplot()
    with FramesReader(frames_path) as f:
        n = f.f["positions"].shape[0]
        held = np.flatnonzero(f.valid)
        if len(held) == 0:
            return []
        offsets = f.offsets
        times = f.times
        rows = sorted({int(held[np.abs(held - int(r) % n).argmin()]) for r in preview_rows})
        sheet = sorted(set(held[np.linspace(0, len(held) - 1, min(contact_panels, len(held)))
                                .round().astype(int)].tolist())) if contact_panels > 0 else []
        needed = sorted(set(rows) | set(sheet))
        if not needed:          # output.preview_frames = [] and contact_sheet = 0: nothing to draw
            return []
        X = dict(f.rows(needed))
    discs = [head(times[r]) for r in needed] if head is not None else []
    limits = _limits(list(X.values()), view, discs)
    xl, yl = VIEW_AXES[view][2:]
    written = []
    os.makedirs(os.path.join(out_dir, "previews"), exist_ok=True)
    for r in rows:
        if stop is not None:
            stop()
        fig, ax = plt.subplots(figsize=(7, 7), dpi=100)
        _draw(ax, X[r], offsets, view, limits, head(times[r]) if head else None)
        ax.set_title(f"{title}  frame {r * every}, t = {times[r]:.3f} s".strip())
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        path = os.path.join(out_dir, "previews", f"frame_{r * every:05d}.png")
        _save(fig, path, bbox_inches="tight")
        plt.close(fig)
        written.append(path)
    if sheet and stop is not None:
        stop()
    if sheet:
        cols = min(len(sheet), 4)
        nrows = math.ceil(len(sheet) / cols)
        fig, axes = plt.subplots(nrows, cols, figsize=(3 * cols, 3 * nrows), dpi=100, squeeze=False)
        for ax in axes.ravel():
            ax.set_axis_off()
        for ax, r in zip(axes.ravel(), sheet):
            _draw(ax, X[r], offsets, view, limits, head(times[r]) if head else None,
                  lw=min(0.8, 30.0 / math.sqrt(len(offsets))))
            ax.set_title(f"frame {r * every}, t = {times[r]:.2f} s", fontsize=9)
        if title:
            fig.suptitle(title)
        fig.tight_layout()
        path = os.path.join(out_dir, "contact_sheet.png")
        _save(fig, path)
        plt.close(fig)
        written.append(path)
    return written
