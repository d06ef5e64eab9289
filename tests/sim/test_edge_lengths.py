"""The compiled edge-length passes of the Newton update (lc_petsc.elements.compiled.
edge_lengths, behind predictors.retract_edge_lengths and project_rest_lengths) against
the vectorised NumPy code they replaced (kept here as the reference), to round-off, on
random and degenerate chains: pinned roots and inner pins, wisps without a pinned
vertex (mean removal), one-vertex wisps, zero-length edges and non-positive lengths."""

import numpy as np
import pytest

from lc_petsc.elements import compiled
from lc_petsc.predictors import project_rest_lengths, retract_edge_lengths


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


# ---------------------------------------------------------------- around the head
def _ref_onto_head(q, y, L, R):
    a = np.linalg.norm(q)
    u = q / a
    if a + L <= R:
        return q + L * u
    h = (a * a + R * R - L * L) / (2 * a)
    w = y - (y @ u) * u
    if np.linalg.norm(w) <= 1e-12 * L:
        k = np.zeros(3)
        k[np.argmin(np.abs(u))] = 1.0
        w = k - (k @ u) * u
    return h * u + np.sqrt(max(R * R - h * h, 0.0)) * w / np.linalg.norm(w)


def _ref_set_around_head(x, length, free, offsets, center, R, allow):
    """Vertex by vertex from each root: the edge's direction kept, its length set; on a
    wisp with a pinned vertex, a vertex that lands deeper than ``allow`` in the sphere
    goes on the sphere at its edge's length from its predecessor, closest to where it
    landed."""
    y = x.copy()
    for lo, hi in zip(offsets[:-1], offsets[1:]):
        held = not free[lo:hi].all()
        for v in range(lo + 1, hi):
            if not free[v]:
                continue
            d = x[v] - x[v - 1]
            n = np.linalg.norm(d)
            ok = n > 0 and length[v - 1] > 0
            y[v] = y[v - 1] + (d * (length[v - 1] / n) if ok else d)
            if ok and held and np.linalg.norm(y[v] - center) < R - allow[v]:
                y[v] = center + _ref_onto_head(y[v - 1] - center, y[v] - center, length[v - 1], R)
    return y


@pytest.mark.parametrize("seed", range(4))
def test_rest_lengths_set_around_the_head(seed):
    """time.length_projection with the head (physics.head_push_out): against the
    vertex-by-vertex reference; the rest lengths hold and every free vertex of a held
    wisp ends no deeper than allowed, except where its predecessor is too deep for the
    sphere to be reached (then straight out from the centre); wisps without a pinned
    vertex as without the head unless that leaves one too deep (then a second walk)."""
    rng = np.random.default_rng(seed)
    x, dx, free, off, mass, length = _scene(rng)
    x = 0.3 * (x + dx)
    center = x.mean(axis=0) + rng.normal(size=3)
    R = float(np.median(np.linalg.norm(x - center, axis=1)))     # half the vertices inside
    allow = rng.uniform(0.0, 0.2, size=len(x))
    got = project_rest_lengths(x, free, off, length, mass, head=(center, R, allow))
    ref = _ref_set_around_head(x, length, free, off, center, R, allow)
    held = np.repeat(np.bincount(np.repeat(np.arange(len(off) - 1), np.diff(off)),
                                 weights=~free, minlength=len(off) - 1) > 0, np.diff(off))
    assert np.abs(got[held] - ref[held]).max() <= 1e-12 * np.abs(x).max()
    # wisps without a pinned vertex: as without the head (the momentum's mean removal),
    # unless that leaves a vertex too deep: then walked around the head from their first
    # vertex (pushed onto the sphere if too deep), without the mean removal
    plain = project_rest_lengths(x, free, off, length, mass)
    again = 0
    for lo, hi in zip(off[:-1], off[1:]):
        if held[lo] or hi == lo:
            continue
        sunk = R - np.linalg.norm(plain[lo:hi] - center, axis=1) > allow[lo:hi]
        if not sunk.any():
            assert np.array_equal(got[lo:hi], plain[lo:hi])
            continue
        again += 1
        start = plain[lo:hi].copy()
        if sunk[0]:
            start[0] = center + (start[0] - center) * (R / np.linalg.norm(start[0] - center))
        anchored = np.r_[False, np.ones(hi - lo - 1, bool)]
        want = _ref_set_around_head(start, length[lo:hi - 1], anchored, np.array([0, hi - lo]), center, R,
                                    allow[lo:hi])
        assert np.abs(got[lo:hi] - want).max() <= 1e-12 * np.abs(x).max()
    assert again >= 1                           # the second walk does act
    edge = np.linalg.norm(np.diff(got, axis=0), axis=1)
    inner = free[1:] & ~np.isin(np.arange(1, len(x)), off)
    assert np.abs(edge[inner] - length[inner]).max() <= 1e-12 * length.max()
    dist = np.linalg.norm(got - center, axis=1)
    moved = free & held & (R - np.linalg.norm(project_rest_lengths(x, free, off, length, mass) - center,
                                              axis=1) > allow)
    assert moved.sum() >= 5                     # the sphere does act
    short = np.concatenate([[False], dist[:-1] + length <= R])   # the predecessor cannot reach it
    ok = free & ~short & ~np.isin(np.arange(len(x)), off)   # a wisp's first vertex stays
    assert np.all(R - dist[ok] <= allow[ok] + 1e-12 * R), (R - dist[ok] - allow[ok]).max()


def test_rest_lengths_around_the_head_edge_into_the_centre():
    """An edge pointing straight at the centre (no side to turn to): it is turned to a
    fixed side and its vertex lands on the sphere at its length."""
    x = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 9.0], [0.0, 0.0, 8.0]])
    free = np.array([False, True, True])
    y = project_rest_lengths(x, free, np.array([0, 3]), np.ones(2), np.ones(3),
                             head=(np.zeros(3), 9.5, np.zeros(3)))
    assert np.allclose(np.linalg.norm(y, axis=1), [10.0, 9.5, 9.5], atol=1e-12)
    assert np.allclose(np.linalg.norm(np.diff(y, axis=0), axis=1), 1.0, atol=1e-12)
    assert np.allclose(y, _ref_set_around_head(x, np.ones(2), free, np.array([0, 3]), np.zeros(3), 9.5,
                                               np.zeros(3)), atol=1e-12)


def test_edge_lengths_rejects_a_bad_head():
    x = np.zeros((4, 3))
    free = np.ones(4, bool)
    with pytest.raises(ValueError, match="head must be"):
        compiled.edge_lengths(x, None, np.ones(3), free, np.array([0, 4]), None,
                              head=(np.zeros(3), -1.0, np.zeros(4)))
    with pytest.raises(ValueError, match="head must be"):
        compiled.edge_lengths(x, None, np.ones(3), free, np.array([0, 4]), None,
                              head=(np.zeros(3), 1.0, np.zeros(3)))
