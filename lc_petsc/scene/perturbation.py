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
