"""The crossing counter on nearly parallel segment pairs: the parallel rule of the
clamped closest-point algorithm (s = 0 where sin^2 of the angle < PARALLEL_TOL) gives
an upper bound of the distance, and the counter's screen, Tight-Inclusion's first test
and its clear-path proof on it missed crossings of such pairs."""

import numpy as np

from ccd_reference import lstsq_distances
from lc_petsc.crossings import count_crossings, crossing_pairs
from lc_petsc.elements import compiled_ccd
from lc_petsc.elements.segment_ccd import exact_distance


def _through(angle, h, go):
    """A: (-1, 0, 0) -> (1, 0, 0); B: A turned by ``angle`` in the xy-plane about its
    middle, ``h`` above it in z, moving down by ``go`` h (2: through A at t = 1/2, the
    segments then crossing at their middles; 0.5: stopping h / 2 above)."""
    c, s = np.cos(angle), np.sin(angle)
    X0 = np.array([[-1.0, 0, 0], [1.0, 0, 0], [-c, -s, h], [c, s, h]])
    X1 = X0.copy()
    X1[2:, 2] -= go * h
    return X0, X1


def test_nearly_parallel_crossing_segments_are_counted():
    """Segments 1e-6 rad apart crossing at their middles: distance 0 (it was 1e-6),
    and the pair moving through A by 2e-7 .. 2e-6 is one crossing (was 0: the screen,
    Tight-Inclusion's first test and the clear-path proof all took 1e-6 for the
    distance); stopping half way it is none."""
    X0, _ = _through(1e-6, 0.0, 0.0)
    assert lstsq_distances(X0[None])[0] < 1e-15
    assert exact_distance(X0[None])[0] < 1e-15
    for angle, h in ((1e-6, 1e-7), (1e-6, 3e-7), (1e-6, 1e-6), (3e-6, 1e-6), (1e-5, 2e-6)):
        X0, X1 = _through(angle, h, 2.0)
        assert count_crossings(X0, X1, [0, 2, 4])["crossings"] == 1, (angle, h)
        assert crossing_pairs(X0[None], X1[None])[0], (angle, h)
        X0, X1 = _through(angle, h, 0.5)
        assert count_crossings(X0, X1, [0, 2, 4])["crossings"] == 0, (angle, h)


def test_exact_distance_against_least_squares_on_nearly_parallel_pairs():
    """exact_distance (NumPy) and the counter's compiled distance (screen_paths' end
    distance) equal an independent least-squares distance on random nearly parallel
    pairs (angles 1e-9 .. 1e-3 rad, offsets 1e-9 .. 1e-2; to 1e-9 of unit coordinates), and both equal the clamped
    algorithm's distance on pairs that are not nearly parallel."""
    rng = np.random.default_rng(5)
    n = 400
    P = np.empty((n, 4, 3))
    for k in range(n):
        a0, u = rng.normal(size=3), rng.normal(size=3)
        a1 = a0 + u
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        ang = 10 ** rng.uniform(-9, -3) if k < n // 2 else rng.uniform(0.1, 3.0)
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        R = np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K
        mid = 0.5 * (a0 + a1) + rng.uniform(-0.7, 0.7) * u
        b = (np.stack([a0, a1]) - 0.5 * (a0 + a1)) @ R.T + mid + rng.normal(size=3) * 10 ** rng.uniform(-9, -2)
        P[k] = [a0, a1, b[0], b[1]]
    ref = lstsq_distances(P)
    np.testing.assert_allclose(exact_distance(P), ref, rtol=1e-6, atol=1e-9)
    X = P.reshape(-1, 3)
    pairs = np.stack([np.arange(0, 4 * n, 4), np.arange(2, 4 * n, 4)], axis=1)
    d_end = compiled_ccd.screen_paths(X, X, pairs)[1]
    np.testing.assert_allclose(d_end, ref, rtol=1e-6, atol=1e-9)
    # the nearly parallel half: the clamped algorithm's parallel rule was off (by up to
    # ~1e-3 here); the other half kept its bits
    from lc_petsc.elements.segment_contact import distance
    assert np.abs(distance(P[:n // 2]) - ref[:n // 2]).max() > 1e-5
    np.testing.assert_array_equal(exact_distance(P[n // 2:]), distance(P[n // 2:]))
