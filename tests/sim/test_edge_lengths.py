"""The compiled edge-length passes of the Newton update (lc_petsc.elements.compiled.
edge_lengths, behind integrator.retract_edge_lengths and project_rest_lengths) against
the vectorised NumPy code they replaced (kept here as the reference), to round-off, on
random and degenerate chains: pinned roots and inner pins, wisps without a pinned
vertex (mean removal), one-vertex wisps, zero-length edges and non-positive lengths."""

import numpy as np
import pytest

from lc_petsc.elements import compiled
from lc_petsc.integrator import project_rest_lengths, retract_edge_lengths


# ---------------------------------------------------------------- the reference
def _ref_retract(x, dx, free, offsets, mass=None):
    out = x + dx
    if len(x) < 2:
        return out
    e = x[1:] - x[:-1]
    new = out[1:] - out[:-1]
    L = np.linalg.norm(e, axis=1)
    length = L + np.einsum("ij,ij->i", e, new - e) / np.where(L > 0, L, 1.0)
    return _ref_set(out, np.where(L > 0, length, 0.0), free, offsets, mass)


def _ref_set(x, length, free, offsets, mass=None):
    nv = len(x)
    off = np.asarray(offsets)
    sizes = np.diff(off)
    if nv < 2 or len(sizes) == 0:
        return x.copy()
    edge = x[1:] - x[:-1]
    n = np.linalg.norm(edge, axis=1)
    ok = (n > 0) & (length > 0)
    correction = np.zeros_like(x)
    correction[1:][ok] = edge[ok] * (length[ok] / n[ok] - 1.0)[:, None]
    reset = ~free.copy()
    reset[off[:-1]] = True
    correction[reset] = 0.0
    wisp = np.repeat(np.arange(len(sizes)), sizes)
    pos = np.arange(nv) - off[:-1][wisp]
    table = np.zeros((len(sizes), int(sizes.max()), 3))
    table[wisp, pos] = correction
    np.cumsum(table, axis=1, out=table)
    last_reset = np.maximum.accumulate(np.where(reset, np.arange(nv), 0))
    total = table[wisp, pos] - table[wisp, pos - (np.arange(nv) - last_reset)]
    if mass is not None:
        unpinned = np.bincount(wisp, weights=(~free).astype(float), minlength=len(sizes)) == 0
        if unpinned.any():
            m = np.bincount(wisp, weights=mass, minlength=len(sizes))
            mean = np.stack([np.bincount(wisp, weights=mass * total[:, c], minlength=len(sizes))
                             for c in range(3)], axis=1) / np.where(m > 0, m, 1.0)[:, None]
            total[unpinned[wisp]] -= mean[wisp[unpinned[wisp]]]
    return x + total


# ---------------------------------------------------------------- scenes
def _scene(rng, degenerate=False):
    sizes = rng.integers(1, 30, size=12)
    sizes[3] = 1
    off = np.concatenate([[0], np.cumsum(sizes)])
    nv = int(off[-1])
    x = np.cumsum(rng.normal(size=(nv, 3)), axis=0)
    free = rng.random(nv) > 0.1
    free[off[:-1][::2]] = False                   # half the wisps rooted, others free
    free[off[:-1][1::2]] = True
    free[off[5]:off[6]] = False                   # a wisp pinned throughout
    mass = rng.uniform(0.5, 2.0, size=nv)
    length = np.linalg.norm(np.diff(x, axis=0), axis=1) * rng.uniform(0.8, 1.2, size=nv - 1)
    dx = 0.1 * rng.normal(size=x.shape)
    dx[~free] = 0.0
    if degenerate:
        v = off[7] + 2 if sizes[7] > 3 else off[0] + 1
        x[v] = x[v - 1]                           # zero-length edges, before and after
        dx[v] = dx[v - 1]
        length[rng.integers(0, nv - 1, size=5)] = 0.0
        length[rng.integers(0, nv - 1, size=5)] = -1.0
    return x, dx, free, off, mass, length


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("degenerate", [False, True])
@pytest.mark.parametrize("with_mass", [False, True])
def test_compiled_edge_lengths_match_the_numpy_reference(seed, degenerate, with_mass):
    x, dx, free, off, mass, length = _scene(np.random.default_rng(seed), degenerate)
    m = mass if with_mass else None
    scale = np.abs(x).max()
    got = retract_edge_lengths(x, dx, free, off, m)
    ref = _ref_retract(x, dx, free, off, m)
    assert np.abs(got - ref).max() <= 1e-13 * scale
    assert np.array_equal(got[~free], x[~free])
    got = project_rest_lengths(x + dx, free, off, length, m) if with_mass else \
        compiled.edge_lengths(x + dx, None, length, free, off, None)
    ref = _ref_set(x + dx, length, free, off, m)
    assert np.abs(got - ref).max() <= 1e-13 * scale
    # control: the comparison sees a wrong length
    wrong = length.copy()
    inner = free[1:] & (length > 0) & ~np.isin(np.arange(1, len(x)), off) \
        & (np.linalg.norm(np.diff(x + dx, axis=0), axis=1) > 0)
    wrong[np.flatnonzero(inner)[0]] *= 1.001
    assert np.abs(compiled.edge_lengths(x + dx, None, wrong, free, off, m) - ref).max() > 1e-6


def test_edge_lengths_rejects_bad_offsets_and_lengths():
    x = np.zeros((4, 3))
    free = np.ones(4, bool)
    with pytest.raises(ValueError, match="offsets"):
        compiled.edge_lengths(x, x, None, free, np.array([0, 3]), None)
    with pytest.raises(ValueError, match="lengths"):
        compiled.edge_lengths(x, None, np.ones(2), free, np.array([0, 4]), None)
