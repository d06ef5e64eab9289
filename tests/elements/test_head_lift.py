"""The head's push-out helpers (lc_petsc.elements.head_contact): the depth a vertex may
rest at (its radius less its edges' sagitta) and the lift of a path's end that keeps the
straight path out of the head, against dense sampling of the paths."""

import numpy as np

from lc_petsc.elements import head_contact
from lc_petsc.head_check import segment_depth


def _sampled_depth(p0, p1, R, n=20001):
    s = np.linspace(0.0, 1.0, n)[None, :, None]
    pts = p0[:, None, :] + s * (p1 - p0)[:, None, :]
    return R - np.linalg.norm(pts, axis=2).min(axis=1)


def test_allowed_depth_is_the_radius_less_the_sagitta():
    radius = np.array([0.1, 0.1, 0.1, 0.2, 0.2])
    rest_edge = np.array([0.4, 0.8, 9.0, 0.4])         # the third joins two wisps: unused
    got = head_contact.allowed_depth(radius, rest_edge, np.array([0, 3, 5]), 10.0)
    s = lambda L: L * L / 80.0                          # noqa: E731 (L^2 / (8 R))
    assert np.allclose(got, [0.1 - s(0.4), 0.1 - s(0.8), 0.1 - s(0.8), 0.2 - s(0.4), 0.2 - s(0.4)], rtol=1e-14)
    assert head_contact.allowed_depth(radius, rest_edge, np.array([0, 3, 5]), 0.1).max() == 0.0


def test_lift_keeps_sliding_paths_out_of_the_head():
    """Vertices sliding along a sphere of radius 15 (ends within 0.05 cm of its surface,
    moves of 1-5 cm: chords up to 0.2 cm deep): every path the lift takes stays within
    the allowed depth on 20,001 samples, moved straight out by at most the strand radius;
    the others keep their ends."""
    rng = np.random.default_rng(3)
    n, R = 400, 15.0
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    t = rng.normal(size=(n, 3))
    t -= np.einsum("ij,ij->i", t, u)[:, None] * u
    t /= np.linalg.norm(t, axis=1)[:, None]
    ang = rng.uniform(1.0, 5.0, n) / R
    w = u * np.cos(ang)[:, None] + t * np.sin(ang)[:, None]
    p0 = u * (R + rng.uniform(-0.05, 0.05, n))[:, None]
    p1 = w * (R + rng.uniform(-0.05, 0.05, n))[:, None]
    allow = np.full(n, 0.06)
    strand = np.full(n, 0.1)
    free = np.ones(n, bool)
    free[:5] = False
    before = _sampled_depth(p0, p1, R)
    got, moved = head_contact.lift_paths(p0, p1, R, allow, strand, free)
    assert 50 < len(moved) < n and not np.isin(np.arange(5), moved).any()
    after = _sampled_depth(p0, got, R)
    assert np.all(before[moved] > allow[moved])
    assert after[moved].max() <= allow[0] + 1e-9, after[moved].max()
    assert np.all(segment_depth(p0[moved], got[moved], R)[0] < allow[moved])
    lift = np.linalg.norm(got, axis=1) - np.linalg.norm(p1, axis=1)
    assert np.all(lift[moved] > 0) and lift.max() <= 0.1
    direction = got[moved] / np.linalg.norm(got[moved], axis=1)[:, None]
    assert np.allclose(direction, p1[moved] / np.linalg.norm(p1[moved], axis=1)[:, None], atol=1e-14)
    kept = np.setdiff1d(np.arange(n), moved)
    assert np.array_equal(got[kept], p1[kept])
    # kept: within the allowed depth already, an end deeper than allowed (the push-out's),
    # a pinned vertex, or a path that a lift by the strand radius does not mend
    ends = np.maximum(R - np.linalg.norm(p0, axis=1), R - np.linalg.norm(p1, axis=1)) <= allow
    too_far = kept[(before[kept] > allow[kept]) & free[kept] & ends[kept]]
    assert len(too_far) > 10
    up = p1[too_far] * (1.0 + 0.1 / np.linalg.norm(p1[too_far], axis=1))[:, None]
    assert np.all(_sampled_depth(p0[too_far], up, R) > allow[too_far])


def test_lift_leaves_deep_ends_and_paths_around_the_head():
    """An end deeper than allowed (the push-out's) and a path across the sphere (no lift of
    the end can mend it) are left alone."""
    R = 5.0
    p0 = np.array([[0.0, 5.0, 0.0], [0.0, 5.0, 0.0]])
    p1 = np.array([[0.5, 4.8, 0.0], [0.0, -5.0, 0.0]])
    got, moved = head_contact.lift_paths(p0, p1, R, np.full(2, 0.05), np.full(2, 0.05), np.ones(2, bool))
    assert len(moved) == 0 and np.array_equal(got, p1)
