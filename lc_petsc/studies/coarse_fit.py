"""How much of a difference between two states of the same wisps coarse rigid motions
explain: per wisp, the best turn about its root pivot and chains of rigid pieces turned
about their joints (least squares, Kabsch's SVD).  Used by
``scripts/fixed_count_errors.py`` (docs/newton.md, "Twenty-first round").
"""

from __future__ import annotations

import numpy as np

from lc_petsc.root_rotation import root_pivots


def best_rotation(a, b):
    """The rotation R minimising sum_i |R a_i - b_i|^2 over the rows of a and b (n, 3)."""
    U, _, Vt = np.linalg.svd(a.T @ b)
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    return Vt.T @ flip @ U.T


def turned_fit(x, r, hinges=()):
    """x (a wisp's pivot, then its free vertices, (n, 3)) moved towards r by a chain of
    rigid turns: the piece up to the first hinge (indices into x, increasing) and all
    beyond it turned about x[0] by the best turn of that piece, then the next piece and
    all beyond it about the (moved) hinge by the best turn of that piece, and so on, the
    last piece's turn fitted to the rest.  Returns the moved positions."""
    y = np.array(x, dtype=float)
    cuts = [0, *hinges, len(y) - 1]
    for a, b in zip(cuts[:-1], cuts[1:]):
        R = best_rotation(y[a + 1:b + 1] - y[a], r[a + 1:b + 1] - y[a])
        y[a + 1:] = y[a] + (y[a + 1:] - y[a]) @ R.T
    return y


#: the coarse motions of :func:`explained`: (name, hinges as fractions of the wisp's free
#: part)
MOTIONS = (("root turn", ()), ("2 rigid pieces", (0.5,)), ("3 rigid pieces", (1 / 3, 2 / 3)))


def explained(run, ref, offsets, pinned):
    """Squared differences ref - run summed over the root-held wisps' pivots and free
    vertices: {"total", "root third", "middle third", "tip third", and per name of
    :data:`MOTIONS` what is left after its best fit per wisp}."""
    piv = root_pivots(offsets, np.asarray(pinned, bool))
    out = dict.fromkeys(["total", "root third", "middle third", "tip third", *(m[0] for m in MOTIONS)], 0.0)
    for w, p in enumerate(piv):
        if p < 0:
            continue
        x, r = run[p:offsets[w + 1]], ref[p:offsets[w + 1]]
        d = np.sum((r - x) ** 2, axis=1)[1:]
        n = len(d)
        s = np.arange(1, n + 1) / n
        out["total"] += d.sum()
        out["root third"] += d[s <= 1 / 3].sum()
        out["middle third"] += d[(s > 1 / 3) & (s <= 2 / 3)].sum()
        out["tip third"] += d[s > 2 / 3].sum()
        for name, fractions in MOTIONS:
            out[name] += np.sum((r - turned_fit(x, r, [int(f * n) for f in fractions])) ** 2)
    return out
