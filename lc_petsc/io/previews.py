"""PNG previews of a run, rendered from ``frames.h5`` with matplotlib (Agg, no display):
single frames and a contact sheet over time, so a person can look at a run without
ParaView.  Runs on one rank after the frames file is closed (it reads only the frames
it draws).

Each wisp is drawn as a polyline in an orthographic view (``front``: x right, y up;
``side``: z right, y up; ``top``: x right, z down), coloured by wisp index; the head
sphere, when the scene has one, is drawn as a grey disc.  All images of a run share
the same axis limits, so motion between them is visible.
"""

from __future__ import annotations

import math
import os

import numpy as np

VIEW_AXES = {"front": (0, 1, "x (cm)", "y (cm)"), "side": (2, 1, "z (cm)", "y (cm)"),
             "top": (0, 2, "x (cm)", "z (cm)")}


def _pyplot():
    import matplotlib
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    return plt


def _segments(x, offsets, view):
    a, b = VIEW_AXES[view][:2]
    return [x[offsets[w]:offsets[w + 1]][:, [a, b]] for w in range(len(offsets) - 1)]


def _draw(ax, x, offsets, view, limits, head=None, lw=None):
    from matplotlib.collections import LineCollection
    import matplotlib.pyplot as plt
    n_w = len(offsets) - 1
    colors = plt.get_cmap("twilight")(np.linspace(0.05, 0.95, max(n_w, 1)))
    if lw is None:
        lw = max(0.3, min(1.5, 60.0 / math.sqrt(max(n_w, 1))))
    if head is not None:
        c, r = head
        a, b = VIEW_AXES[view][:2]
        ax.add_patch(plt.Circle((c[a], c[b]), r, color="0.85", zorder=0))
    ax.add_collection(LineCollection(_segments(x, offsets, view), colors=colors, linewidths=lw))
    ax.set_xlim(limits[0])
    ax.set_ylim(limits[1])
    if view == "top":
        ax.invert_yaxis()
    ax.set_aspect("equal")


def _limits(arrays, view, head_discs):
    a, b = VIEW_AXES[view][:2]
    lo = np.min([x.min(axis=0) for x in arrays], axis=0)
    hi = np.max([x.max(axis=0) for x in arrays], axis=0)
    for c, r in head_discs:
        lo = np.minimum(lo, np.asarray(c) - r)
        hi = np.maximum(hi, np.asarray(c) + r)
    pad = 0.05 * max(float((hi - lo)[[a, b]].max()), 1e-6)
    return ((lo[a] - pad, hi[a] + pad), (lo[b] - pad, hi[b] + pad))


def render_previews(frames_path, out_dir, preview_rows, contact_panels=12, view="front",
                    title="", head=None, every=1):
    """Render ``preview_rows`` (row indices of ``/positions``) to
    ``out_dir/previews/frame_NNNNN.png`` (NNNNN the simulation frame number) and a
    contact sheet of ``contact_panels`` rows evenly spaced over the run to
    ``out_dir/contact_sheet.png``.  ``head``: callable t -> (centre, radius) or None.
    Returns the paths written."""
    import h5py
    plt = _pyplot()
    with h5py.File(frames_path, "r") as f:
        n = f["positions"].shape[0]
        if n == 0:
            return []
        offsets = f["wisp_offsets"][...]
        times = f["time"][...]
        rows = sorted({int(r) % n for r in preview_rows})
        sheet = sorted(set(np.linspace(0, n - 1, min(contact_panels, n)).round().astype(int).tolist())) \
            if contact_panels > 0 else []
        needed = sorted(set(rows) | set(sheet))
        X = {r: f["positions"][r] for r in needed}
    discs = [head(times[r]) for r in needed] if head is not None else []
    limits = _limits(list(X.values()), view, discs)
    xl, yl = VIEW_AXES[view][2:]
    written = []
    os.makedirs(os.path.join(out_dir, "previews"), exist_ok=True)
    for r in rows:
        fig, ax = plt.subplots(figsize=(7, 7), dpi=100)
        _draw(ax, X[r], offsets, view, limits, head(times[r]) if head else None)
        ax.set_title(f"{title}  frame {r * every}, t = {times[r]:.3f} s".strip())
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        path = os.path.join(out_dir, "previews", f"frame_{r * every:05d}.png")
        fig.savefig(path, bbox_inches="tight")
        plt.close(fig)
        written.append(path)
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
        fig.savefig(path)
        plt.close(fig)
        written.append(path)
    return written
