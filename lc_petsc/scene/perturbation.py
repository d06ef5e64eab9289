"""SPEC 6's initial perturbation of the wisps (``scene.perturbation``)."""

from __future__ import annotations

import numpy as np


def apply_perturbation(batch, scene_cfg):
    """Initial positions of this rank's wisps after SPEC 6's perturbation (free vertices).

    ``smash`` scales each free vertex's coordinate along its wisp's axis (root -> last
    vertex direction; the paper's x for a wisp lying along x) about the root by
    ``smash_factor``; ``jitter`` adds seeded uniform offsets (stream [seed, wisp, 1]);
    ``straighten`` puts the free vertices on the vertical line (-y) below the last pinned
    vertex of the wisp, keeping rest edge lengths.
    """
    x = batch.positions.copy()
    kind = scene_cfg.perturbation
    if kind == "none":
        return x
    off = batch.offsets
    for w in range(batch.n_wisps):
        a, b = int(off[w]), int(off[w + 1])
        xw = x[a:b]
        free = ~batch.pinned[a:b]
        if kind == "smash":
            axis = xw[-1] - xw[0]
            axis /= np.linalg.norm(axis)
            s = (xw - xw[0]) @ axis
            xw[free] -= ((1.0 - scene_cfg.smash_factor) * s[free])[:, None] * axis
        elif kind == "jitter":
            rng = np.random.default_rng([scene_cfg.seed, int(batch.ids()[w]), 1])
            xw[free] += rng.uniform(-scene_cfg.jitter, scene_cfg.jitter, size=(int(free.sum()), 3))
        elif kind == "straighten":
            L = np.linalg.norm(np.diff(batch.positions[a:b], axis=0), axis=1)
            pinned_idx = np.flatnonzero(~free)
            p = int(pinned_idx[-1]) if len(pinned_idx) else 0
            for i in range(p + 1, b - a):
                xw[i] = xw[i - 1] + np.array([0.0, -L[i - 1], 0.0])
        x[a:b] = xw
    return x


def perturbation_problems(batch, x, scene_cfg):
    """Messages naming the first wisp of ``batch`` whose perturbed positions ``x`` (from
    :func:`apply_perturbation`) or edge lengths are not finite, with the key that did it
    (``smash_factor = 1e308`` went on to frame 0 and failed there, exit 3; a wisp whose
    last vertex is its root has no smash axis)."""
    if scene_cfg.perturbation == "none":
        return []
    with np.errstate(over="ignore", invalid="ignore"):
        edges = np.linalg.norm(np.diff(x, axis=0), axis=1)
    off = batch.offsets
    ids = batch.ids()
    for w in range(batch.n_wisps):
        a, b = int(off[w]), int(off[w + 1])
        bad = ~np.isfinite(x[a:b]).all(axis=1)
        bad[1:] |= ~np.isfinite(edges[a:b - 1])
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            key = {"smash": "scene.smash_factor", "jitter": "scene.jitter"}.get(scene_cfg.perturbation)
            size = f" ({key} = {getattr(scene_cfg, key.split('.')[1])!r})" if key else ""
            return [f"scene.perturbation = {scene_cfg.perturbation!r}{size} moves wisp {ids[w]}, vertex {i} "
                    f"to {x[a + i].tolist()}, whose position or edge length is not a finite number; use a "
                    f"smaller value (cm for jitter, a factor for smash)"]
    return []
