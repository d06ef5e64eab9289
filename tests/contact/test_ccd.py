"""Continuous collision detection: the limiter's conservative advancement, the
Tight-Inclusion crossing test (ipctk) against a brute-force NumPy reference, the swept
box broad phase against all pairs, the crossing counter."""

import numpy as np
import pytest

from ccd_reference import crossing_reference
from lc_petsc.crossings import count_crossings, crossing_pairs, pair_positions
from lc_petsc.elements.compiled_ccd import box_pairs
from lc_petsc.elements import compiled_ccd, segment_ccd
from lc_petsc.elements.segment_contact import distance


def random_motions(n, seed):
    """Pairs (start, end) of unit-ish segments moving by ~1 unit: random ones
    cross rarely.  Includes parallel pairs (moving through each other or sliding), pairs
    nearly touching at the start and moving apart, and pairs moving rigidly together."""
    rng = np.random.default_rng(seed)
    S = rng.normal(size=(n, 4, 3))
    S[:, 2:] += rng.normal(scale=0.3, size=(n, 1, 3))
    E = S + rng.normal(size=(n, 4, 3))
    k = n // 8
    # parallel pairs: B = A shifted; half of them pass through A sideways
    S[:k, 2:] = S[:k, :2] + np.array([0.3, 0.0, 0.0])
    E[:k, :2] = S[:k, :2]
    E[:k, 2:] = S[:k, 2:] + (np.where(np.arange(k)[:, None] % 2 == 0, -0.6, 0.2) * np.array([1.0, 0, 0]))[:, None, :]
    # nearly touching at the start (B's end 1e-3 above A's middle), moving apart along
    # A x B's normal
    j = slice(k, 2 * k)
    d1 = S[j, 1] - S[j, 0]
    nrm = np.cross(d1, rng.normal(size=(k, 3)))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    u = S[j, 3] - S[j, 2]
    u *= np.sign(np.einsum("ij,ij->i", u, nrm))[:, None]        # B on the + side
    S[j, 2] = 0.5 * (S[j, 0] + S[j, 1]) + 1e-3 * nrm
    S[j, 3] = S[j, 2] + u
    E[j, :2] = S[j, :2]
    E[j, 2:] = S[j, 2:] + 0.5 * nrm[:, None, :]
    # rigid common translation
    r = slice(2 * k, 3 * k)
    E[r] = S[r] + rng.normal(size=(k, 1, 3))
    return S, E


def test_tight_inclusion_matches_brute_force_on_random_motions():
    S, E = random_motions(160, 3)
    ref = crossing_reference(S, E)
    # pairs whose minimum distance along the path is within 1e-6 of zero are ambiguous
    # for any CCD; keep the clear ones (at most 5 of the 160)
    t = np.linspace(0, 1, 2001)
    dmin = np.array([distance(S[k] + t[:, None, None] * (E[k] - S[k])).min() for k in range(len(S))])
    clear = ref | (dmin > 1e-4)
    got = crossing_pairs(S, E)
    k = len(S) // 8
    assert ref[3 * k:].sum() >= 5, ref.sum()             # random pairs that cross
    np.testing.assert_array_equal(got[clear], ref[clear])
    assert clear.sum() >= 155
    k = len(S) // 8
    assert ref[:k:2].all() and not ref[1:k:2].any()        # parallel: through / sliding
    assert not ref[k:2 * k].any() and not ref[2 * k:3 * k].any()   # apart, rigid


# a pair of a 60-wisp hairball step (physics.strand_separation = false), 4.45e-6 cm apart
# on its whole path: Tight-Inclusion with the counter's 1e5 interval splits leaves it
# undecided, which counts as meeting (t = 0.53; with 1e4 or 1e6 splits it answers no),
# and the end-of-run check counted a crossing the ccd limiter had not let through
FAR_PAIR_START = [[-17.78548960252841, 2.54372939470802, -4.403008766842811],
                  [-17.699275804440088, 2.038000349691919, -4.115022959171849],
                  [-17.753865553648875, 2.216348754348881, -4.16919377932501],
                  [-17.471712465758962, 1.7009246481015707, -4.2562807212310245]]
FAR_PAIR_END = [[-17.929254126044498, 1.1558746120856656, -4.403008766842811],
                [-17.80405488295513, 0.6583609585206993, -4.115022959171849],
                [-17.872320150918572, 0.8319352865540846, -4.16919377932501],
                [-17.551020131162897, 0.3399610274595124, -4.2562807212310245]]


def test_undecided_tight_inclusion_hits_proven_clear_are_no_crossings():
    """The near-touching pair Tight-Inclusion leaves undecided is no crossing (brute-force
    reference, sampled distance, crossing_pairs' advancement proof), and random motions
    moved 20 units away give the same answers as at the origin."""
    S, E = np.array([FAR_PAIR_START]), np.array([FAR_PAIR_END])
    t = np.linspace(0.0, 1.0, 20001)
    assert distance(S[0] + t[:, None, None] * (E[0] - S[0])).min() > 4e-6
    assert not crossing_reference(S, E)[0]
    assert not crossing_pairs(S, E)[0]
    S, E = random_motions(160, 3)
    shift = np.array([-17.0, 12.0, -9.0])
    np.testing.assert_array_equal(crossing_pairs(S + shift, E + shift), crossing_pairs(S, E))


def test_safe_fraction_is_safe_and_tight():
    S, E = random_motions(300, 5)
    m = 0.05
    t, unresolved = segment_ccd.safe_fraction(S, E, m)
    d0 = distance(S)
    assert np.all(t[d0 < m] == 0.0)
    ts = np.linspace(0, 1, 401)
    for k in range(len(S)):
        tt = ts * t[k]
        d = distance(S[k] + tt[:, None, None] * (E[k] - S[k]))
        assert d.min() >= m * (1 - 1e-9) or d0[k] < m, (k, d.min())
    # rigid translations are never limited
    k = len(S) // 8
    assert np.all(t[2 * k:3 * k][d0[2 * k:3 * k] >= m] == 1.0)
    # where resolved and below 1, t is the time of impact to 0.1 % of m
    ok = (t < 1) & ~unresolved & (d0 > m)
    assert ok.sum() > 30
    dd = distance(S[ok] + t[ok][:, None, None] * (E[ok] - S[ok]))
    np.testing.assert_allclose(dd, m, rtol=2e-3)
    # Tight-Inclusion (with a min distance) is a conservative lower bound of that time
    hit, ti = segment_ccd.tight_inclusion_toi(S[ok], E[ok], m)
    assert hit.all()
    assert np.all(ti <= t[ok] + 2e-3) and np.all(ti > 0.25 * t[ok])
    # pairs the motion bound shows never come within m are not hit, and keep t = 1
    rel = segment_ccd.relative_motion(S, E)
    far = d0 - m > rel
    hit, ti = segment_ccd.tight_inclusion_toi(S[far], E[far], m)
    assert far.sum() > 30 and not hit.any() and np.all(ti == 1.0)


def test_safe_fraction_input_errors():
    S = np.zeros((2, 4, 3))
    with pytest.raises(ValueError, match="differ in shape"):
        segment_ccd.safe_fraction(S, np.zeros((3, 4, 3)), 0.1)
    with pytest.raises(ValueError, match="min_distance"):
        segment_ccd.safe_fraction(S, S, -1.0)


def test_box_pairs_against_all_pairs():
    rng = np.random.default_rng(1)
    n = 600
    c = rng.uniform(0, 10, size=(n, 3))
    e = rng.uniform(0, 0.5, size=(n, 3))
    e[:20] *= 20                          # a few big boxes (fast segments)
    e[20:25] = 0.0                        # and points
    lo, hi = c - e, c + e
    lo[30], hi[30] = lo[31] - [0, 0, 1], lo[31]          # touching at a corner: overlap
    group = rng.integers(0, 40, n)
    i, j = np.triu_indices(n, 1)
    touch = np.all((hi[i] >= lo[j]) & (hi[j] >= lo[i]), axis=1)
    assert touch.sum() > 400
    def sort(p):
        return p[np.lexsort((p[:, 1], p[:, 0]))]
    np.testing.assert_array_equal(sort(box_pairs(lo, hi)), np.stack([i[touch], j[touch]], axis=1))
    other = touch & (group[i] != group[j])
    np.testing.assert_array_equal(sort(box_pairs(lo, hi, group)), np.stack([i[other], j[other]], axis=1))
    assert [30, 31] in box_pairs(lo, hi).tolist()
    # boxes over more than BIG_CELLS cells are tested against all: one spans the scene
    lo[40], hi[40] = -1.0, 11.0
    lo[41], hi[41] = [-1.0, 2.0, 2.0], [11.0, 3.0, 3.0]
    touch = np.all((hi[i] >= lo[j]) & (hi[j] >= lo[i]), axis=1)
    np.testing.assert_array_equal(sort(box_pairs(lo, hi)), np.stack([i[touch], j[touch]], axis=1))
    assert (touch & ((i == 40) | (j == 40))).sum() == n - 1
    assert box_pairs(lo[:1], hi[:1]).shape == (0, 2)
    # n_local (a rank's own boxes first, then its ghosts): no pair of two ghosts, big
    # boxes included (40 and 41 are local, 500 made big is a ghost), in the same order
    lo[500], hi[500] = [-1.0, 5.0, -1.0], [11.0, 6.0, 11.0]
    touch = np.all((hi[i] >= lo[j]) & (hi[j] >= lo[i]), axis=1)
    for n_local in (0, 1, 450, n):
        got, full = box_pairs(lo, hi, group, n_local=n_local), box_pairs(lo, hi, group)
        np.testing.assert_array_equal(got, full[full.min(axis=1) < n_local])
        want = touch & (group[i] != group[j]) & (i < n_local)
        np.testing.assert_array_equal(sort(got), np.stack([i[want], j[want]], axis=1))



def _strand_boxes(seed=7):
    """(lo, hi, group, arc, n_local) of 60 coiled strands of 1-30 segments (0.1 long,
    turning along a helix, a few strands crossing), two wild segments inside runs, and
    n_local cutting a run (and a strand)."""
    rng = np.random.default_rng(seed)
    sizes = rng.integers(1, 31, 60)
    group = np.repeat(np.arange(len(sizes)), sizes)
    t = np.concatenate([np.arange(k) for k in sizes]) * 0.6
    base = rng.uniform(0, 3, (len(sizes), 3))[group]
    a = base + 0.15 * np.stack([np.cos(t), np.sin(t), 0.15 * t], axis=1)
    b = base + 0.15 * np.stack([np.cos(t + 0.6), np.sin(t + 0.6), 0.15 * (t + 0.6)], axis=1)
    lo, hi = np.minimum(a, b) - 0.02, np.maximum(a, b) + 0.02
    lo[[17, 300]] -= 20.0                                  # wild segments inside runs
    hi[[17, 300]] += 20.0
    seg_len = np.linalg.norm(b - a, axis=1)
    arc0 = np.concatenate([np.r_[0.0, np.cumsum(seg_len[group == w])[:-1]] for w in range(len(sizes))])
    return lo, hi, group, np.stack([arc0, arc0 + seg_len], axis=1), int(np.cumsum(sizes)[40] - 5)


@pytest.mark.parametrize("args", [{}, {"group": True}, {"group": True, "n_local": True},
                                  {"group": True, "arc": True, "min_gap": 0.35, "n_local": True}])
def test_box_pairs_in_parts_are_the_same_pairs_and_stop_between_parts(monkeypatch, args):
    """A wild step's broad phase (the end-of-run check of a shuffled 200-wisp file: 83 s)
    was one compiled call a signal could not stop: it now runs in parts of BOX_TESTS box
    tests, looking at ``stop`` before each (the grid's cells, the big boxes, the strand
    runs' members); the pairs are the same, in the same order, in any part size, and
    None comes back once stop() is true."""
    lo, hi, group, arc, n_local = _strand_boxes()
    kw = {"group": group if args.get("group") else None, "arc": arc if args.get("arc") else None,
          "min_gap": args.get("min_gap", 0.0), "n_local": n_local if args.get("n_local") else None}
    whole = box_pairs(lo, hi, **kw)
    assert len(whole) > 1000
    monkeypatch.setattr(compiled_ccd, "BOX_TESTS", 1 << 62)
    looks = []
    np.testing.assert_array_equal(box_pairs(lo, hi, **kw, stop=lambda: looks.append(1) and False), whole)
    one_part = len(looks)                   # the grid's cells and the big boxes (+ the runs' members)
    assert one_part == (2 if kw["group"] is None else 3), one_part
    counts = []
    for size in (1000, 37, 1):
        monkeypatch.setattr(compiled_ccd, "BOX_TESTS", size)
        looks.clear()
        np.testing.assert_array_equal(box_pairs(lo, hi, **kw, stop=lambda: looks.append(1) and False), whole)
        counts.append(len(looks))
    # 10-15, 187-311 and 769-3400 looks here
    assert 10 <= counts[0] and 15 * counts[0] < counts[1] and 3 * counts[1] < counts[2], counts
    looks.clear()
    assert box_pairs(lo, hi, **kw, stop=lambda: len(looks) > 4 or looks.append(1)) is None
    assert len(looks) == 5


@pytest.mark.parametrize("min_gap", [np.inf, 0.0, 0.35, 2.0])
def test_box_pairs_through_strand_runs_against_all_pairs(monkeypatch, min_gap):
    """Strands (consecutive boxes of one group, runs of up to CHUNK paired as one box
    first): the same pairs as brute force and as the boxes paired one by one (CHUNK =
    1), each once, i < j, with ghosts after n_local (no ghost pair), self pairs at an arc
    gap of at least min_gap (inside one run too: 0 and 0.35 keep pairs 1-4 segments
    apart; 2 keeps none here), strands of 1-30 segments, a run cut at n_local, and wild segments over more
    than BIG_CELLS cells inside runs."""
    from lc_petsc.elements import compiled_ccd
    lo, hi, group, arc, n_local = _strand_boxes()
    n = len(group)
    i, j = np.triu_indices(n, 1)
    touch = np.all((hi[i] >= lo[j]) & (hi[j] >= lo[i]), axis=1)
    along = np.maximum(arc[j, 0] - arc[i, 1], arc[i, 0] - arc[j, 1])
    want = touch & (i < n_local) & ((group[i] != group[j]) | (along >= min_gap))
    self_pairs = (want & (group[i] == group[j])).sum()
    assert self_pairs == 0 if min_gap == np.inf else self_pairs > {0.0: 500, 0.35: 20, 2.0: -1}[min_gap], self_pairs
    args = dict(group=group, arc=None if min_gap == np.inf else arc, min_gap=min_gap, n_local=n_local)
    got = box_pairs(lo, hi, **args)
    assert np.all(got[:, 0] < got[:, 1]) and len(got) == len({tuple(p) for p in got.tolist()})
    np.testing.assert_array_equal(got[np.lexsort((got[:, 1], got[:, 0]))], np.stack([i[want], j[want]], axis=1))
    np.testing.assert_array_equal(box_pairs(lo, hi, **args), got)              # the same order again
    monkeypatch.setattr(compiled_ccd, "CHUNK", 1)
    one = box_pairs(lo, hi, **args)
    np.testing.assert_array_equal(np.sort(one[:, 0] * n + one[:, 1]), np.sort(got[:, 0] * n + got[:, 1]))


def _brute_box_pairs(lo, hi, group, arc, min_gap, n_local):
    """All overlapping box pairs (i < j) with a box before n_local, of different groups or
    at least min_gap apart along the strand (a NaN gap counts as far; none of one group
    for min_gap = inf, box_pairs without arcs), by brute force."""
    i, j = np.triu_indices(len(lo), 1)
    touch = np.all((hi[i] >= lo[j]) & (hi[j] >= lo[i]), axis=1)
    gap = np.maximum(arc[j, 0] - arc[i, 1], arc[i, 0] - arc[j, 1])
    far = ~(gap < min_gap) & (min_gap != np.inf)
    want = touch & (i < n_local) & ((group[i] != group[j]) | far)
    return np.stack([i[want], j[want]], axis=1)


@pytest.mark.parametrize("n_local", [0, 5, 8, 16, 21, 40])
@pytest.mark.parametrize("min_gap", [np.inf, 0.0, 1.5, -1.0])
def test_box_pairs_runs_with_overlapping_ghost_runs(n_local, min_gap):
    """Every box overlaps every other (ghost runs overlap ghost runs): n_local at a run
    start (8, 16), inside a run (5, 21), 0 and n: exactly the pairs with a local box
    (a ghost run starting at n_local taken as local fails this; from the review)."""
    group = np.repeat(np.arange(5), 8)
    n = len(group)
    lo, hi = np.zeros((n, 3)), np.ones((n, 3))
    arc0 = np.tile(np.arange(8.0), 5)
    arc = np.stack([arc0, arc0 + 1.0], axis=1)
    got = box_pairs(lo, hi, group=group, arc=None if min_gap == np.inf else arc, min_gap=min_gap,
                    n_local=n_local)
    assert np.all(got[:, 0] < got[:, 1]) and len(got) == len({tuple(p) for p in got.tolist()})
    np.testing.assert_array_equal(got[np.lexsort((got[:, 1], got[:, 0]))],
                                  _brute_box_pairs(lo, hi, group, arc, min_gap, n_local))


@pytest.mark.parametrize("seed", range(12))
def test_box_pairs_random_strands_against_brute_force(seed):
    """Random walks as strands of 1-19 segments, a wild segment every 4th seed, n_local
    anywhere, with and without self pairs; NaN arcs (a pair kept, as the grid does)."""
    rng = np.random.default_rng(seed)
    sizes = rng.integers(1, 20, rng.integers(1, 12))
    group = np.repeat(np.arange(len(sizes)), sizes)
    n = len(group)
    a = np.cumsum(rng.normal(scale=0.1, size=(n, 3)), axis=0)
    b = a + rng.normal(scale=0.1, size=(n, 3))
    lo, hi = np.minimum(a, b) - 0.05, np.maximum(a, b) + 0.05
    if seed % 4 == 0:
        k = rng.integers(0, n)
        lo[k] -= 100.0
        hi[k] += 100.0
    arc0 = np.concatenate([np.arange(s, dtype=float) for s in sizes])
    arc = np.stack([arc0, arc0 + 1.0], axis=1)
    if seed % 3 == 0:
        arc[rng.random(n) < 0.1] = np.nan
    n_local = int(rng.integers(0, n + 1))
    for min_gap in (np.inf, 0.0, 1.0, 2.5):
        got = box_pairs(lo, hi, group=group, arc=None if min_gap == np.inf else arc, min_gap=min_gap,
                        n_local=n_local)
        assert len(got) == len({tuple(p) for p in got.tolist()})
        want = _brute_box_pairs(lo, hi, group, arc, min_gap, n_local)
        np.testing.assert_array_equal(got[np.lexsort((got[:, 1], got[:, 0]))], want)


def test_box_pairs_with_more_pairs_than_its_first_guess():
    """A dense cluster (every box overlaps every other: n (n - 1) / 2 pairs, past the
    8 n rows box_pairs starts with) and one big box: all pairs, each once, in one pass
    (the output grows inside the loop)."""
    rng = np.random.default_rng(3)
    n = 80
    c = rng.uniform(0, 0.1, size=(n, 3))
    lo, hi = c - 0.5, c + 0.5
    lo[0], hi[0] = -50.0, 50.0                             # over more than BIG_CELLS cells
    lo[1:10] += 3.0                                        # a few boxes away from the cluster
    hi[1:10] += 3.0
    i, j = np.triu_indices(n, 1)
    touch = np.all((hi[i] >= lo[j]) & (hi[j] >= lo[i]), axis=1)
    assert touch.sum() > 8 * n
    got = box_pairs(lo, hi)
    assert len(got) == len({tuple(p) for p in got.tolist()})
    np.testing.assert_array_equal(got[np.lexsort((got[:, 1], got[:, 0]))], np.stack([i[touch], j[touch]], axis=1))

def rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def relative_candidates(S, T, seg, m):
    """The limiter's broad phase (contact.StrandContact._safe_fractions) on one rank:
    (candidate pairs, fallback H, absolute-box pairs)."""
    A, b, L = segment_ccd.affine_field(*segment_ccd.affine_sums(S, T - S))
    H = S + S @ A.T + b
    F = T - H
    c0 = 0.5 * (S[seg] + S[seg + 1])
    h = 0.5 * np.linalg.norm(S[seg + 1] - S[seg], axis=1)
    lo, hi = segment_ccd.field_boxes(np.stack([S[seg], S[seg + 1]], axis=1),
                                     np.stack([F[seg], F[seg + 1]], axis=1), L, m)
    dn = np.linalg.norm(T - S, axis=1)
    absolute = (h + np.maximum(dn[seg], dn[seg + 1]) + 0.5 * m)[:, None]
    return box_pairs(lo, hi), H, box_pairs(c0 - absolute, c0 + absolute)


@pytest.mark.parametrize("motion", ["random", "rigid", "rigid_plus_noise", "shear"])
def test_relative_broad_phase_keeps_every_pair_that_comes_close(motion):
    """Every pair of segments that comes within m on the path S -> H + beta (T - H), for
    any per-vertex fractions beta (0, 1, random), is a candidate of the relative broad
    phase (brute force over all pairs, the path sampled at 81 times); for hair moving
    rigidly the candidates are far fewer than with absolute swept balls."""
    rng = np.random.default_rng({"random": 1, "rigid": 2, "rigid_plus_noise": 3, "shear": 4}[motion])
    n = 160                                     # segments, as 2-vertex wisps
    a = rng.uniform(0, 4, size=(n, 3))
    S = np.concatenate([a, a + rng.normal(scale=0.25, size=(n, 3))]).reshape(2, n, 3)
    S = S.transpose(1, 0, 2).reshape(-1, 3)
    seg = np.arange(0, 2 * n, 2)
    if motion == "random":
        T = S + rng.normal(scale=0.4, size=S.shape)
    elif motion == "shear":                     # relative motion grows with distance
        T = S + 0.3 * S[:, [1]] * np.array([1.0, 0, 0]) + rng.normal(scale=0.05, size=S.shape)
    else:
        T = (S - 2.0) @ rotation([0.3, 1, 0.2], 0.35).T + 2.0 + np.array([1.5, -0.8, 0.6])
        if motion == "rigid_plus_noise":
            T += rng.normal(scale=0.08, size=S.shape)
    m = 0.05
    cand, H, absolute = relative_candidates(S, T, seg, m)
    found = {tuple(p) for p in cand.tolist()}
    i, j = np.triu_indices(n, 1)
    ts = np.linspace(0.0, 1.0, 81)
    betas = [np.zeros(2 * n), np.ones(2 * n), rng.uniform(size=2 * n), rng.uniform(size=2 * n) ** 4]
    close = 0
    for beta in betas:
        E = H + beta[:, None] * (T - H)
        X0 = np.stack([S[seg[i]], S[seg[i] + 1], S[seg[j]], S[seg[j] + 1]], axis=1)
        X1 = np.stack([E[seg[i]], E[seg[i] + 1], E[seg[j]], E[seg[j] + 1]], axis=1)
        dmin = np.full(len(i), np.inf)
        for t in ts:
            dmin = np.minimum(dmin, distance(X0 + t * (X1 - X0)))
        near = np.flatnonzero(dmin < m)
        close += len(near)
        missing = [k for k in near if (i[k], j[k]) not in found]
        assert not missing, (motion, len(missing))
    assert close > 5                        # the check is not vacuous
    if motion == "rigid":
        assert len(cand) < 0.2 * len(absolute), (len(cand), len(absolute))


def test_affine_field_recovers_a_rigid_motion_and_caps_its_lipschitz_constant():
    rng = np.random.default_rng(7)
    x = rng.uniform(-3, 3, size=(200, 3))
    R = rotation([1, 2, 0.5], 0.3)
    D = x @ R.T + np.array([0.2, -1.0, 0.5]) - x
    A, b, L = segment_ccd.affine_field(*segment_ccd.affine_sums(x, D))
    np.testing.assert_allclose(x @ A.T + b, D, atol=1e-10)
    np.testing.assert_allclose(L, np.linalg.norm(R - np.eye(3), 2), rtol=1e-10)
    # a large deformation is scaled down to L = 1/2 (A and b alike)
    A2, b2, L2 = segment_ccd.affine_field(*segment_ccd.affine_sums(x, 3.0 * x))
    assert L2 == 0.5
    np.testing.assert_allclose(A2, 0.5 * np.eye(3), atol=1e-10)
    # nothing to fit: u = 0
    A0, b0, L0 = segment_ccd.affine_field(*segment_ccd.affine_sums(np.zeros((0, 3)), np.zeros((0, 3))))
    assert L0 == 0.0 and not A0.any() and not b0.any()


def test_count_crossings_two_wisps():
    """Two 3-vertex wisps: B sweeps down through A (one crossing of its two segments
    with A's); moving B sideways instead crosses nothing."""
    A = np.array([[-1.0, 0, 0], [0.05, 0, 0], [1.0, 0, 0]])
    B0 = np.array([[0.3, 1.0, -1.0], [0.3, 1.0, 0.05], [0.3, 1.0, 1.0]])
    off = [0, 3, 6]
    X0 = np.concatenate([A, B0])
    down = np.concatenate([A, B0 - [0, 2.0, 0]])
    r = count_crossings(X0, down, off)
    assert r["crossings"] == 1
    assert r["pairs"].tolist() == [[1, 3]]          # A (0.05..1) x B (-1..0.05) at x = 0.3
    side = np.concatenate([A, B0 + [3.0, 0, 0]])
    assert count_crossings(X0, side, off)["crossings"] == 0
    with pytest.raises(ValueError, match="n_vertices, 3"):
        count_crossings(X0, down[:4], off)


def test_path_screen_drops_only_pairs_that_cannot_touch():
    """compiled_ccd.screen_paths (the crossing counter's conservative advancement before
    Tight-Inclusion):
    on random segment pairs, many of which cross, touch at the start or just graze,
    the screened count equals Tight-Inclusion on every pair, and its end distances are
    segment_contact.distance's."""
    rng = np.random.default_rng(11)
    n = 4000
    X0 = rng.uniform(-1, 1, (4 * n, 3))
    X1 = X0 + rng.normal(0, 0.6, X0.shape) * rng.uniform(0, 1, (4 * n, 1))
    X0[6:8] = X0[4:6]                              # pair 1: its segments coincide at the start
    pairs = np.stack([np.arange(0, 4 * n, 4), np.arange(2, 4 * n, 4)], axis=1)
    S, E = pair_positions(X0, pairs), pair_positions(X1, pairs)
    every = crossing_pairs(S, E)
    may_meet, d_end = compiled_ccd.screen_paths(X0, X1, pairs)
    screened = np.zeros(n, bool)
    screened[may_meet] = crossing_pairs(S[may_meet], E[may_meet])
    assert np.array_equal(screened, every) and 50 < every.sum() < n - 50, every.sum()
    assert every[1] and may_meet[1]
    # it leaves Tight-Inclusion little more than the crossings (measured 291 for 288;
    # the start distance against the motion bound alone left 3,122)
    assert may_meet.sum() <= every.sum() + 20, (may_meet.sum(), every.sum())
    np.testing.assert_allclose(d_end, distance(E), rtol=1e-12, atol=1e-15)


def test_path_screen_keeps_pairs_that_meet_at_the_end_of_their_bound():
    """A segment falling through another by just more than its start distance (it meets
    it at t = 0.999, 0.9999999, its start distance just under the motion bound) is kept
    by the screen and counted; one stopping just short of it is dropped."""
    pairs, X0, X1 = [], [], []
    for k, reach in enumerate((1.001, 1.0000001, 0.99)):
        a = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
        b = np.array([[0.0, 0.3, -1.0], [0.0, 0.3, 1.0]])          # 0.3 cm above a, across it
        X0 += [a, b]
        X1 += [a, b - [0.0, 0.3 * reach, 0.0]]
        pairs.append([4 * k, 4 * k + 2])
    X0, X1, pairs = np.concatenate(X0), np.concatenate(X1), np.array(pairs)
    may_meet, _ = compiled_ccd.screen_paths(X0, X1, pairs)
    assert may_meet.tolist() == [True, True, False]
    S, E = pair_positions(X0, pairs), pair_positions(X1, pairs)
    assert crossing_pairs(S, E).tolist() == [True, True, False]


def test_compiled_advancement_matches_the_numpy_reference():
    """compiled_ccd.safe_fraction is segment_ccd.safe_fraction pair by pair (given as
    many steps), and its limiter test (limit_pairs) gives the NumPy fractions at m / 2
    and m of each pair's floor min(m, max(d(S) / 2, min(d(S), HOLD_FLOOR m))), 1 for pairs whose swept spheres stay
    apart."""
    from lc_petsc.elements import compiled_ccd
    S, E = random_motions(800, 11)
    m = 0.05
    ref, unresolved = segment_ccd.safe_fraction(S, E, m, iterations=100000)
    assert not unresolved.any()
    got = compiled_ccd.safe_fraction(S, E, m, max_steps=100000)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    assert 50 < (ref < 1).sum() < len(S) - 50
    # with the default steps the result is never larger (still safe), equal here
    assert np.all(compiled_ccd.safe_fraction(S, E, m) <= got + 1e-15)
    n = len(S)
    SV, EV = S.reshape(-1, 3), E.reshape(-1, 3)
    inv = np.arange(4 * n).reshape(n, 4)
    for scale in (True, False):
        tau, factor = np.full(n, -1.0), np.full(n, -1.0)
        compiled_ccd.limit_pairs(SV, EV, inv, np.arange(n), m, scale, tau, factor)
        d = distance(S)
        mp = np.minimum(m, np.maximum(0.5 * d, np.minimum(d, compiled_ccd.HOLD_FLOOR * m)))
        half = segment_ccd.safe_fraction(S, E, 0.5 * mp, iterations=100000)[0]
        full = segment_ccd.safe_fraction(S, E, mp, iterations=100000)[0]
        np.testing.assert_allclose(tau, half, atol=1e-12)
        np.testing.assert_allclose(factor, np.where(half < 1, full if scale else 0.0, 1.0), atol=1e-12)
    # only the pairs in redo are written
    tau = np.full(n, -1.0)
    compiled_ccd.limit_pairs(SV, EV, inv, np.array([3, 5]), m, True, tau, np.ones(n))
    assert np.flatnonzero(tau != -1.0).tolist() == [3, 5]


def test_a_pair_pushed_together_in_every_call_keeps_a_floor():
    """A pair already closer than the floor m gets half its distance per limiter call, but
    not below HOLD_FLOOR m: pushed through each other in every call (a tangle the elastic
    forces pull through itself, configs/jitter.toml with self-contact) it used to be
    halved each time, to round-off and through (real crossings after 45 frames)."""
    from lc_petsc.elements import compiled_ccd
    m = 0.01
    A = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    B = np.array([[0.0, -1.0, 0.004], [0.0, 1.0, 0.004]])     # 0.4 m above A, crossing it
    inv = np.arange(4).reshape(1, 4)
    dist = []
    for _ in range(60):
        S = np.concatenate([A, B])
        T = S.copy()
        T[2:, 2] -= 1.0                                         # B pushed down through A
        tau, factor = np.ones(1), np.ones(1)
        compiled_ccd.limit_pairs(S, T, inv, np.arange(1), m, True, tau, factor)
        f = factor[0] if tau[0] < 1.0 else 1.0
        B = S[2:] + f * (T[2:] - S[2:])
        dist.append(B[0, 2])
    assert min(dist) > 0.0                                      # never through A
    assert min(dist) >= compiled_ccd.HOLD_FLOOR * m * (1.0 - 1e-9), min(dist)
    assert dist[-1] < 2.0 * compiled_ccd.HOLD_FLOOR * m         # the halving reached the hold


def test_compiled_advancement_is_safe_on_sampled_paths():
    """Every fraction keeps the pair at least m apart on [0, t] (paths sampled at 401
    times), including sliding parallel pairs that need thousands of steps."""
    from lc_petsc.elements import compiled_ccd
    S, E = random_motions(300, 12)
    m = 0.05
    t = compiled_ccd.safe_fraction(S, E, m)
    d0 = distance(S)
    ts = np.linspace(0, 1, 401)
    for k in range(len(S)):
        tt = ts * t[k]
        d = distance(S[k] + tt[:, None, None] * (E[k] - S[k]))
        assert d.min() >= m * (1 - 1e-9) or d0[k] < m, (k, d.min())
    # a pair sliding along each other at 1.2 m: the motion bound is loose, many steps
    A = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    Sp = np.concatenate([A, A + [0, 1.2 * m, 0]])[None]
    Ep = np.concatenate([A, A + [-3.0, 1.2 * m, 0]])[None]
    assert compiled_ccd.safe_fraction(Sp, Ep, m)[0] == 1.0
    assert segment_ccd.safe_fraction(Sp, Ep, m, iterations=100)[1][0]      # NumPy's 100: open


def test_compiled_field_boxes_and_candidate_order_match_numpy():
    """compiled_ccd.field_boxes against the reference segment_ccd.field_boxes (the proof's
    boxes), and compiled_ccd.order_candidates against its definition in NumPy."""
    rng = np.random.default_rng(11)
    S = rng.normal(size=(300, 3))
    F = rng.normal(scale=0.3, size=(300, 3))
    seg = np.flatnonzero(np.arange(299) % 10 != 9)          # wisps of 10 vertices
    lo, hi = compiled_ccd.field_boxes(S, F, seg, 0.3, 0.05)
    rlo, rhi = segment_ccd.field_boxes(np.stack([S[seg], S[seg + 1]], axis=1),
                                       np.stack([F[seg], F[seg + 1]], axis=1), 0.3, 0.05)
    np.testing.assert_allclose(lo, rlo, rtol=0, atol=1e-15)
    np.testing.assert_allclose(hi, rhi, rtol=0, atol=1e-15)
    n_local = 200
    gv = rng.permutation(len(seg))
    free = rng.uniform(size=(len(seg), 2)) < 0.7
    ij = box_pairs(lo, hi, seg // 10)
    shrink = 0.04
    ci, cj, near, _ = compiled_ccd.order_candidates(ij, n_local, gv, lo, hi, shrink, free)
    i, j = ij[:, 0], ij[:, 1]
    loc = (i < n_local) | (j < n_local)
    i, j = i[loc], j[loc]
    swap = gv[i] > gv[j]
    i, j = np.where(swap, j, i), np.where(swap, i, j)
    np.testing.assert_array_equal(ci, i)
    np.testing.assert_array_equal(cj, j)
    want = ((lo[i] + shrink <= hi[j] - shrink) & (lo[j] + shrink <= hi[i] - shrink)).all(axis=1)
    want &= free[i].any(axis=1) | free[j].any(axis=1)
    np.testing.assert_array_equal(near, want)
    assert 0 < near.sum() < len(near) and len(ci) < len(ij)       # both filters bite
    # near_pair_distances: box_pairs' test on the boxes grown by 0.02 (the contact's reuse),
    # in the candidates' order, with the kept pairs' distances
    grown = box_pairs(lo - 0.02, hi + 0.02, seg // 10)
    k = rng.integers(0, len(seg), size=(400, 2))
    P = np.stack([S[seg], S[seg + 1]], axis=1)
    ki, kj, d = compiled_ccd.near_pair_distances(P, lo, hi, k[:, 0], k[:, 1], 0.02)
    listed = {tuple(p) for p in grown.tolist()}
    same_wisp = seg[k[:, 0]] // 10 == seg[k[:, 1]] // 10
    want = np.array([(min(a, b), max(a, b)) in listed for a, b in k])
    ov = ((lo[k[:, 0]] - 0.02 <= hi[k[:, 1]] + 0.02) & (lo[k[:, 1]] - 0.02 <= hi[k[:, 0]] + 0.02)).all(axis=1)
    np.testing.assert_array_equal(ov[~same_wisp], want[~same_wisp])
    np.testing.assert_array_equal(ki, k[ov, 0])
    np.testing.assert_array_equal(kj, k[ov, 1])
    assert np.array_equal(d, compiled_ccd.pair_distances(P, ki, kj))
    assert 0 < len(ki) < len(k)


def test_pair_distances_match_the_numpy_distance():
    """The contact's compiled distance pass against segment_contact.distance: random,
    parallel, touching, crossing and zero-length segments, pairs sharing segments."""
    S, E = random_motions(400, 3)
    X = np.concatenate([S, E, S[:, [0, 1, 0, 1]]])            # the last block: A on itself
    X[:50, 3] = X[:50, 2]                                       # zero-length B
    X[50:60, 2:] = X[50:60, :2] + 1e-9                          # parallel, almost touching
    P = X.reshape(-1, 2, 3)                                     # segment A of pair p is 2p, B 2p + 1
    rng = np.random.default_rng(4)
    i = np.concatenate([2 * np.arange(len(X)), rng.integers(0, len(P), 300)])
    j = np.concatenate([2 * np.arange(len(X)) + 1, rng.integers(0, len(P), 300)])   # shared segments
    d = compiled_ccd.pair_distances(P, i, j)
    ref = distance(np.concatenate([P[i], P[j]], axis=1))
    assert d.shape == (len(i),) and np.all(np.isfinite(d))
    assert np.allclose(d, ref, rtol=1e-12, atol=1e-13)
    assert np.all(d[len(X) - len(S):len(X)] == 0.0)            # a segment against itself


def test_changed_pairs_match_numpy():
    rng = np.random.default_rng(4)
    inv = rng.integers(0, 300, size=(5000, 4))
    for p in (0.0, 0.001, 0.05, 1.0):
        changed = rng.random(300) < p
        want = np.flatnonzero(changed[inv].any(axis=1))
        np.testing.assert_array_equal(compiled_ccd.changed_pairs(inv, changed), want)
    assert compiled_ccd.changed_pairs(inv[:0], changed).shape == (0,)


def test_pair_rows_match_the_numpy_slices():
    """The contact assembly's rows: gradient, own Hessian blocks and counts per segment."""
    rng = np.random.default_rng(6)
    m = 50
    g, H = rng.normal(size=(m, 4, 3)), rng.normal(size=(m, 12, 12))
    oA, oB = rng.integers(0, 3, m), rng.integers(0, 3, m)
    want = np.zeros((2 * m, 35))
    for side, (o, own, oth) in enumerate(((0, oA, oB), (2, oB, oA))):
        R = want[side * m:(side + 1) * m]
        R[:, 0:6] = g[:, o:o + 2].reshape(m, 6)
        Hs = H[:, 3 * o:3 * o + 6, 3 * o:3 * o + 6]
        R[:, 6:15] = Hs[:, 0:3, 0:3].reshape(m, 9)
        R[:, 15:24] = Hs[:, 0:3, 3:6].reshape(m, 9)
        R[:, 24:33] = Hs[:, 3:6, 3:6].reshape(m, 9)
        R[:, 33] = np.where(own == oth, 2.0, 0.0)
        R[:, 34] = np.where(own == oth, 0.0, 2.0)
    np.testing.assert_array_equal(compiled_ccd.pair_rows(g, H, oA, oB), want)
    assert compiled_ccd.pair_rows(g[:0], H[:0], oA[:0], oB[:0]).shape == (0, 35)


def test_corner_cells_match_the_numpy_grid():
    """The occupancy grid's compiled corner cells against the NumPy formula they
    replaced: boxes inside, on cell faces and outside the grid (clamped)."""
    rng = np.random.default_rng(11)
    origin, cell, dims = np.array([-1.0, 0.5, 2.0]), 0.25, np.array([7, 5, 9])
    lo = origin + rng.uniform(-0.5, 2.5, size=(500, 3))
    hi = lo + rng.uniform(0.0, 0.6, size=(500, 3))
    lo[:50] = origin + cell * rng.integers(0, 6, size=(50, 3))         # on cell faces
    top = dims - 1
    a = np.clip(np.floor((lo - origin) / cell).astype(np.int64), 0, top)
    b = np.clip(np.floor((hi - origin) / cell).astype(np.int64), 0, top)
    want = np.empty((len(lo), 8), np.int64)
    for c in range(8):
        v = [b[:, k] if (c >> k) & 1 else a[:, k] for k in range(3)]
        want[:, c] = (v[0] * dims[1] + v[1]) * dims[2] + v[2]
    got = compiled_ccd.corner_cells(lo, hi, origin, cell, dims)
    assert np.array_equal(got, want)
    assert got.min() == 0 and got.max() == dims.prod() - 1             # clamped at both ends


def _rotation_z(theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_stopped_pairs_moving_with_the_field_are_proven_apart():
    """The limiter's stopped pairs at the hold floor under a head turn (two parallel
    segments 1e-5 cm apart, 15 cm from the axis, turned by 6 degrees) are proven to stay
    apart, which conservative advancement could not show within its steps; a residual
    that drives them through each other, or a start distance never computed, is not."""
    from lc_petsc.contact import kept_apart_by_field
    Q = _rotation_z(np.radians(6.0))
    A, b = Q - np.eye(3), np.array([0.2, -0.1, 0.05])
    L = float(np.linalg.norm(A, 2))
    S = np.array([[15.0, 0.0, 0.0], [15.0, 0.03, 0.0], [15.0, 0.0, 1e-5], [15.0, 0.03, 1e-5]])
    E = S + S @ A.T + b
    points, start = np.arange(4)[None, :], np.array([1e-5])
    assert kept_apart_by_field(S, E, points, start, A, b, L).tolist() == [True]
    through = E.copy()
    through[2:, 2] -= 2e-5               # the second segment ends below the first: crossed
    assert kept_apart_by_field(S, through, points, start, A, b, L).tolist() == [False]
    assert kept_apart_by_field(S, E, points, np.array([np.nan]), A, b, L).tolist() == [False]
    assert kept_apart_by_field(S, E, np.zeros((0, 4), int), np.zeros(0), A, b, L).shape == (0,)


def test_field_bound_holds_on_sampled_paths():
    """Property: for random affine fields (L <= 1/2) and small residuals, every pair
    proven apart keeps at least (1 - L) d(S) - 2 max |r| > 0 at 201 sampled instants of
    its straight path (the bound the proof uses), and some are proven, some not."""
    from lc_petsc.contact import kept_apart_by_field
    rng = np.random.default_rng(7)
    proven = 0
    for _ in range(300):
        A = rng.normal(size=(3, 3))
        A *= rng.uniform(0.0, 0.5) / np.linalg.norm(A, 2)
        b = rng.normal(size=3)
        L = float(np.linalg.norm(A, 2))
        S = rng.normal(size=(4, 3))
        r = rng.normal(size=(4, 3)) * 10.0 ** rng.uniform(-4, 0)
        E = S + S @ A.T + b + r
        d0 = distance(S[None])[0]
        ok = kept_apart_by_field(S, E, np.arange(4)[None, :], np.array([d0]), A, b, L)[0]
        if ok:
            proven += 1
            t = np.linspace(0.0, 1.0, 201)[:, None, None]
            path = distance(S[None] + t * (E - S)[None])
            bound = (1.0 - L) * d0 - 2.0 * np.linalg.norm(r, axis=1).max()
            assert path.min() >= bound * (1.0 - 1e-9) and bound > 0.0
    assert 20 < proven < 280, proven
