"""The compiled passes along strands (lc_petsc.elements.compiled_ccd: smooth_fractions,
the limiter's strain bound on its per-vertex fractions, and bound_edge_lengths, the
separation's edge projection) against their NumPy references (tests/strand_pass_reference.py),
on random strands with pinned roots, inner pins, single-edge wisps, vertices that do
not move, stopped vertices and torn or crushed edges."""

import numpy as np
import pytest

from lc_petsc.elements import compiled_ccd
from lc_petsc.elements.compiled_ccd import bound_edge_lengths, smooth_fractions
from lc_petsc.elements.segment_contact import distance
from strand_pass_reference import bound_edge_lengths_reference, smooth_fractions_reference


def strands(rng, n_wisps=40):
    """Local strand arrays of wisps of 2-30 vertices: (offsets, seg, colour, free)."""
    sizes = rng.integers(2, 31, n_wisps)
    offsets = np.r_[0, np.cumsum(sizes)]
    seg = np.concatenate([np.arange(offsets[w], offsets[w + 1] - 1) for w in range(n_wisps)])
    wid = np.repeat(np.arange(n_wisps), sizes)
    colour = (seg - offsets[wid[seg]]) % 2
    free = np.ones(offsets[-1], bool)
    free[offsets[:-1]] = rng.random(n_wisps) < 0.8          # most roots pinned
    free[rng.random(offsets[-1]) < 0.03] = False           # a few inner pins
    return offsets, seg, colour, free


@pytest.mark.parametrize("seed", range(6))
def test_smooth_fractions_equals_the_jacobi_sweeps(seed):
    rng = np.random.default_rng(seed)
    offsets, seg, _, free = strands(rng)
    nv = offsets[-1]
    beta = np.where(rng.random(nv) < 0.1, 0.0, 1.0)        # stopped vertices
    beta[rng.random(nv) < 0.2] = rng.random()              # and partly limited ones
    F = rng.normal(size=(nv, 3)) * rng.choice([0.0, 1e-3, 0.3], size=(nv, 1))
    L = rng.uniform(0.2, 0.8, len(seg))
    got = smooth_fractions(beta, F, seg, L, free, 0.02)
    want = smooth_fractions_reference(beta, F, seg, L, free, 0.02)
    np.testing.assert_array_equal(got, want)
    assert np.all(got <= beta) and np.all(got[~free] == beta[~free])
    assert (got < beta).sum() > 10                         # the transform did something


@pytest.mark.parametrize("seed", range(6))
def test_bound_edge_lengths_equals_the_red_black_sweeps(seed):
    rng = np.random.default_rng(100 + seed)
    offsets, seg, colour, free = strands(rng)
    nv = offsets[-1]
    inverse_mass = np.where(free, rng.uniform(0.5, 2.0, nv), 0.0)
    x = np.cumsum(rng.normal(size=(nv, 3)) * 0.5, axis=0)
    L = np.linalg.norm(x[seg + 1] - x[seg], axis=1)
    x += rng.normal(size=(nv, 3)) * rng.choice([0.0, 0.05, 0.3], size=(nv, 1))    # tear, crush
    lo, hi = 0.98 * L, 1.02 * L
    check = None if seed % 2 else rng.random(len(seg)) < 0.5
    for sweeps in (1, 3, 50):
        got, n = bound_edge_lengths(x, seg, colour, lo, hi, inverse_mass,
                                    None if check is None else check.copy(), sweeps)
        want, n_ref = bound_edge_lengths_reference(x, seg, colour, lo, hi, inverse_mass,
                                                   None if check is None else check.copy(), sweeps)
        assert n == n_ref
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)
    assert np.all(got[~free] == x[~free])
    strain = np.linalg.norm(got[seg + 1] - got[seg], axis=1) / L - 1.0
    movable = free[seg] | free[seg + 1]
    assert np.abs(strain[movable]).max() < 0.02 + 1e-9 or n == 50
    # momentum is kept on the wisps without a pinned vertex
    unpinned = np.flatnonzero(np.minimum.reduceat(free, offsets[:-1]))
    assert len(unpinned) > 3
    m = 1.0 / np.where(free, inverse_mass, 1.0)
    for w in unpinned:
        v = slice(offsets[w], offsets[w + 1])
        np.testing.assert_allclose((m[v, None] * (got - x)[v]).sum(axis=0), 0.0, atol=1e-12)


@pytest.mark.parametrize("first_round", [True, False])
def test_shift_and_bound_is_the_shift_then_the_edge_pass(first_round):
    """The separation's fused round update, in place on the positions' columns of its
    (nv, 5) state array: equal bit for bit to x + shift followed by bound_edge_lengths
    over all movable edges (first round) or the edges at a shifted vertex."""
    from lc_petsc.elements.compiled_ccd import shift_and_bound
    rng = np.random.default_rng(7)
    offsets, seg, colour, free = strands(rng)
    nv = offsets[-1]
    inverse_mass = np.where(free, rng.uniform(0.5, 2.0, nv), 0.0)
    x = np.cumsum(rng.normal(size=(nv, 3)) * 0.5, axis=0)
    L = np.linalg.norm(x[seg + 1] - x[seg], axis=1)
    x += rng.normal(size=(nv, 3)) * rng.choice([0.0, 0.05], size=(nv, 1))
    shift = np.zeros((nv, 4))
    moved = rng.random(nv) < 0.1
    shift[moved, :3] = rng.normal(scale=0.2, size=(moved.sum(), 3)) * inverse_mass[moved, None]
    moved = (shift[:, :3] != 0.0).any(axis=1)      # pinned vertices do not move
    shift[:, 3] = 5.0                              # a count column, not a position
    state = np.zeros((nv, 5))
    state[:, :3] = x
    n = shift_and_bound(state[:, :3], shift, seg, colour, 0.98 * L, 1.02 * L, inverse_mass, first_round, 50)
    check = None if first_round else moved[seg] | moved[seg + 1]
    want, n_ref = bound_edge_lengths(x + shift[:, :3], seg, colour, 0.98 * L, 1.02 * L, inverse_mass, check, 50)
    assert n == n_ref
    assert np.array_equal(state[:, :3], want) and np.all(state[:, 3:] == 0.0)
    assert not np.array_equal(want, x + shift[:, :3])      # the edge pass did something


@pytest.mark.parametrize("sweeps", [1, 2, 50])
def test_shift_and_bound_queued_from_the_moved_vertices_equals_the_scan(sweeps):
    """The separation's rounds after the first queue the edges at the vertices the shift
    moved (EdgeWork) instead of scanning all edges: the same positions and sweeps bit for
    bit as the scan (bound_edge_lengths over the edges at a shifted vertex), the work
    flags left all False (also when the sweeps run out with edges queued),
    so the next round starts clean; on strided positions as in the separation."""
    from lc_petsc.elements.compiled_ccd import EdgeWork, shift_and_bound
    rng = np.random.default_rng(sweeps)
    offsets, seg, colour, free = strands(rng)
    nv = offsets[-1]
    inverse_mass = np.where(free, rng.uniform(0.5, 2.0, nv), 0.0)
    x = np.cumsum(rng.normal(size=(nv, 3)) * 0.5, axis=0)
    L = np.linalg.norm(x[seg + 1] - x[seg], axis=1)
    work = EdgeWork(seg, nv)
    changed = 0
    for trial in range(5):
        shift = np.zeros((nv, 4))
        moved = rng.random(nv) < 0.2
        shift[moved, :3] = rng.normal(scale=0.2, size=(moved.sum(), 3)) * inverse_mass[moved, None]
        a, b = np.zeros((nv, 5)), np.zeros((nv, 5))
        b[:, :3] = x
        # the reference: the scan of all edges for those at a shifted vertex
        shifted = (shift[:, :3] != 0.0).any(axis=1)
        a[:, :3], n_scan = bound_edge_lengths(x + shift[:, :3], seg, colour, 0.98 * L, 1.02 * L, inverse_mass,
                                              shifted[seg] | shifted[seg + 1], sweeps)
        n_work = shift_and_bound(b[:, :3], shift, seg, colour, 0.98 * L, 1.02 * L, inverse_mass, False, sweeps,
                                 work)
        assert n_work == n_scan and np.array_equal(a, b)
        assert not work.check.any()
        changed += not np.array_equal(a[:, :3], x + shift[:, :3])
        x = a[:, :3].copy()
    assert changed                              # the edge pass did something


def test_pair_distances_refresh_equals_the_distances_of_every_pair():
    """The separation's per-round pass (PairDistances.refresh): only the pairs with a
    point that moved get a new distance, yet the distances, the pairs listed below one
    threshold and the count below another equal those of all pairs recomputed
    (pair_distances on the same points), round after round, with points moving, coinciding
    and NaN."""
    from lc_petsc.elements.compiled_ccd import PairDistances
    rng = np.random.default_rng(2)
    n = 60
    Y = rng.normal(size=(n, 5))
    inv = rng.integers(0, n, (300, 4))
    inv[:5, 2:] = inv[:5, :2]                   # coincident segments (distance 0)
    pairs = PairDistances(inv, n)
    for r in range(8):
        hit, below = pairs.refresh(Y, 1.0, 0.6)
        P = Y[inv, :3].reshape(-1, 2, 3)            # pair p: segments 2p, 2p + 1
        d = compiled_ccd.pair_distances(P, 2 * np.arange(len(inv)), 2 * np.arange(len(inv)) + 1)
        np.testing.assert_array_equal(pairs.d, d)
        np.testing.assert_array_equal(hit, np.flatnonzero(d < 1.0))
        assert below == int(np.sum(d < 0.6))
        moved = rng.random(n) < 0.15
        Y[moved, :3] += rng.normal(scale=0.2, size=(moved.sum(), 3))
        Y[moved, 3:] += 1.0                     # other columns are not positions
        if r == 5:
            Y[7, 0] = np.nan                    # a NaN point moves every round
    assert np.isnan(pairs.d).any()


@pytest.mark.parametrize("seed", range(4))
def test_shrink_and_smooth_equals_shrinking_then_smoothing_every_strand(seed):
    """The limiter's round update smooths only the strands with a vertex shrunk; over
    rounds of random shrinks it equals beta *= 1 - shrink followed by smooth_fractions
    over all strands, to the bit, and flags the same vertices as limited."""
    rng = np.random.default_rng(seed)
    offsets, seg, _, free = strands(rng)
    # an empty strand and a one-vertex strand among them (no edges)
    offsets = np.concatenate([offsets[:5], offsets[4:5], offsets[4:5] + 1, offsets[5:] + 1])
    nv, n_wisps = offsets[-1], len(offsets) - 1
    seg = np.concatenate([np.arange(offsets[w], offsets[w + 1] - 1) for w in range(n_wisps)])
    free = np.insert(free, offsets[4], True)
    wid = np.repeat(np.arange(n_wisps), np.diff(offsets)).astype(np.int64)
    seg_offsets = compiled_ccd.strand_edge_offsets(offsets)
    assert seg_offsets[4] == seg_offsets[5] == seg_offsets[6] and seg_offsets[-1] == len(seg)
    np.testing.assert_array_equal(np.diff(seg_offsets), np.maximum(np.diff(offsets) - 1, 0))
    F = rng.normal(size=(nv, 3)) * rng.choice([0.0, 1e-3, 0.3], size=(nv, 1))
    L = rng.uniform(0.2, 0.8, len(seg))
    slack = compiled_ccd.edge_slack(F, seg, L, 0.02)
    beta, want = np.ones(nv), np.ones(nv)
    limited, want_limited = np.zeros(nv, bool), np.zeros(nv, bool)
    skipped = 0
    for _ in range(6):
        shrink = np.where((rng.random(nv) < 0.03) & free, rng.uniform(0.0, 1.0, nv), 0.0)
        compiled_ccd.shrink_and_smooth(beta, shrink, limited, slack, seg, seg_offsets, wid, free)
        want *= 1.0 - shrink
        want_limited |= shrink > 0.0
        smooth = smooth_fractions(want, F, seg, L, free, 0.02)
        want_limited |= smooth < want
        want = smooth
        skipped += n_wisps - len(np.unique(wid[shrink > 0.0]))
        np.testing.assert_array_equal(beta, want)
        np.testing.assert_array_equal(limited, want_limited)
    assert skipped > 0 and want_limited.sum() > 20           # strands were left alone, others limited


@pytest.mark.parametrize("seed", range(3))
def test_pairs_at_points_equals_the_scan_of_all_pairs(seed):
    rng = np.random.default_rng(seed)
    n_points = 500
    inv = rng.integers(0, n_points, (3000, 4))
    incidence = compiled_ccd.point_pairs(inv, n_points)
    seen = np.zeros(len(inv), bool)
    for frac in (0.0, 0.002, 0.05, 1.0):
        changed = rng.random(n_points) < frac
        got = compiled_ccd.pairs_at_points(incidence, np.flatnonzero(changed), seen)
        want = compiled_ccd.changed_pairs(inv, changed)
        assert len(got) == len(set(got.tolist()))            # each pair once
        np.testing.assert_array_equal(np.sort(got), want)
        assert not seen.any()                                # the work array is left clean


def test_kept_pair_points_equals_the_numpy_gathers():
    rng = np.random.default_rng(1)
    sv = rng.integers(0, 1000, (400, 2))
    ci, cj = rng.integers(0, 400, 2000), rng.integers(0, 400, 2000)
    keep = rng.random(2000) < 0.6
    i, j, inv = compiled_ccd.kept_pair_points(ci, cj, keep, sv)
    np.testing.assert_array_equal(i, ci[keep])
    np.testing.assert_array_equal(j, cj[keep])
    np.testing.assert_array_equal(inv, np.concatenate([sv[ci[keep]], sv[cj[keep]]], axis=1))


@pytest.mark.parametrize("order", ["ascending", "ghosts", "shuffled"])
def test_segment_vertices_equal_numpy_unique(order):
    """The limiter's vertex numbering (segment_vertices) is np.unique's, bit for bit: on a
    rank's segments (ascending, strands back to back and apart), with ghosts from later
    ranks appended (still ascending), and in any order (NumPy's sort taken)."""
    rng = np.random.default_rng(4)
    offsets, seg, _, _ = strands(rng, n_wisps=50)
    gv = seg + 7
    if order == "ghosts":
        gv = np.r_[gv, offsets[-1] + 20 + seg[rng.random(len(seg)) < 0.2]]
    elif order == "shuffled":
        gv = rng.permutation(gv)
    V, sv = compiled_ccd.segment_vertices(gv)
    want_V, want_inv = np.unique(np.stack([gv, gv + 1], axis=1), return_inverse=True)
    np.testing.assert_array_equal(V, want_V)
    np.testing.assert_array_equal(sv, want_inv.reshape(-1, 2))
    np.testing.assert_array_equal(V[sv], np.stack([gv, gv + 1], axis=1))
    assert compiled_ccd.segment_vertices(np.zeros(0, np.int64))[0].shape == (0,)


def test_limit_pairs_start_distances_kept_across_rounds():
    """The limiter's pair test with the start distances kept from an earlier round gives
    the same bits as computing them again; it fills them where it computes them (pairs
    past the swept-sphere test), and refuses a wrong-sized array."""
    rng = np.random.default_rng(5)
    n = 3000
    SV = rng.random((4 * n, 3))
    EV = SV + 0.05 * rng.normal(size=SV.shape)
    inv = rng.integers(0, 4 * n, (n, 4))
    redo = np.arange(n)
    tau0, factor0 = np.ones(n), np.ones(n)
    compiled_ccd.limit_pairs(SV, EV, inv, redo, 0.03, True, tau0, factor0)
    kept = np.full(n, np.nan)
    tau1, factor1 = np.ones(n), np.ones(n)
    compiled_ccd.limit_pairs(SV, EV, inv, redo, 0.03, True, tau1, factor1, kept)
    filled = np.isfinite(kept)
    assert 0 < filled.sum() < n and (tau1 < 1).sum() > 10
    np.testing.assert_allclose(kept[filled], distance(SV[inv[filled]]), rtol=0, atol=1e-14)
    # a later round: new path ends for some points, the kept start distances reused
    EV2 = EV.copy()
    EV2[rng.random(len(EV)) < 0.3] += 0.05
    tau2, factor2 = np.ones(n), np.ones(n)
    compiled_ccd.limit_pairs(SV, EV2, inv, redo, 0.03, False, tau2, factor2)
    tau3, factor3 = np.ones(n), np.ones(n)
    compiled_ccd.limit_pairs(SV, EV2, inv, redo, 0.03, False, tau3, factor3, kept)
    np.testing.assert_array_equal(tau3, tau2)
    np.testing.assert_array_equal(factor3, factor2)
    np.testing.assert_array_equal(tau1, tau0)
    np.testing.assert_array_equal(factor1, factor0)
    with pytest.raises(ValueError, match="start_distance"):
        compiled_ccd.limit_pairs(SV, EV, inv, redo, 0.03, True, tau1, factor1, np.zeros(n - 1))


def test_segment_ends_and_near_pair_distances_equal_the_numpy_gathers():
    """The pair search's segment end points (segment_ends) and its reuse of the limiter's
    candidates (near_pair_distances: box overlap, then distance) against NumPy."""
    rng = np.random.default_rng(3)
    offsets, seg, colour, free = strands(rng, n_wisps=30)
    x = rng.normal(size=(offsets[-1], 3))
    P = compiled_ccd.segment_ends(x, seg)
    np.testing.assert_array_equal(P, np.stack([x[seg], x[seg + 1]], axis=1))
    lo, hi = P.min(axis=1), P.max(axis=1)
    i, j = rng.integers(0, len(seg), 3000), rng.integers(0, len(seg), 3000)
    ki, kj, d = compiled_ccd.near_pair_distances(P, lo, hi, i, j, 0.1)
    ov = ((lo[i] - 0.1 <= hi[j] + 0.1) & (lo[j] - 0.1 <= hi[i] + 0.1)).all(axis=1)
    np.testing.assert_array_equal(ki, i[ov])
    np.testing.assert_array_equal(kj, j[ov])
    np.testing.assert_allclose(d, distance(np.concatenate([P[ki], P[kj]], axis=1)), rtol=1e-12, atol=1e-13)
    assert 0 < ov.sum() < len(ov)


def test_segment_points_equals_the_numpy_scatter():
    """The limiter's points by index from its segments' ends (each interior vertex is the
    end of two segments; ghosts come after the local segments)."""
    rng = np.random.default_rng(5)
    nv = 500
    x, t, h = (rng.normal(size=(nv, 3)) for _ in range(3))
    pinned = rng.random(nv) < 0.1
    gv = np.unique(rng.integers(0, nv - 1, 300))             # first vertices of segments
    gv = np.concatenate([gv, gv[rng.integers(0, len(gv), 40)]])   # ghost copies repeat some
    V, sv = np.unique(np.stack([gv, gv + 1], axis=1), return_inverse=True)
    sv = sv.reshape(-1, 2)
    ends = np.stack([gv, gv + 1], axis=1)
    SV, TV, HV, fV = compiled_ccd.segment_points(sv, len(V), x[ends], t[ends], h[ends], ~pinned[ends])
    np.testing.assert_array_equal(SV, x[V])
    np.testing.assert_array_equal(TV, t[V])
    np.testing.assert_array_equal(HV, h[V])
    np.testing.assert_array_equal(fV, ~pinned[V])
    with pytest.raises(ValueError, match="segment_points"):
        compiled_ccd.segment_points(sv, len(V) - 1, x[ends], t[ends], h[ends], ~pinned[ends])
    with pytest.raises(ValueError, match="segment_ends"):
        compiled_ccd.segment_ends(x[:gv.max() + 1], gv)      # the last segment's end is missing


def test_edge_work_and_pair_distances_refuse_arrays_of_other_sizes():
    """The compiled passes do no bounds checks: work arrays built for other strands, or
    positions with another number of points, are refused with a message, not read out of
    bounds."""
    from lc_petsc.elements.compiled_ccd import EdgeWork, PairDistances, shift_and_bound
    rng = np.random.default_rng(0)
    offsets, seg, colour, free = strands(rng, n_wisps=5)
    nv = offsets[-1]
    x, shift, L = np.zeros((nv, 3)), np.zeros((nv, 4)), np.ones(len(seg))
    with pytest.raises(ValueError, match="EdgeWork"):
        shift_and_bound(x, shift, seg, colour, L, L, np.ones(nv), False, 5, EdgeWork(seg[:-1], nv - 1))
    pairs = PairDistances(np.zeros((0, 4), np.int64), 10)
    with pytest.raises(ValueError, match=r"\(10, >= 3\)"):
        pairs.refresh(np.zeros((9, 5)), 1.0, 0.5)
    assert len(pairs.refresh(np.zeros((10, 3)), 1.0, 0.5)[0]) == 0
