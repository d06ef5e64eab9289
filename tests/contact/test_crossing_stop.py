"""A stop (a signal during the end-of-run check) is heard inside the crossing counter's
Tight-Inclusion work, every CROSSING_CHUNK pairs, not only between screen chunks: a wild
step with thousands of undecided pairs delayed a SIGTERM by minutes (hang56)."""

import numpy as np

import lc_petsc.crossings as crossings


def crossing_step(n):
    """n one-segment wisp pairs, 10 cm apart: B passes through A half way through the
    step (each pair meets, so the screen leaves every one to Tight-Inclusion)."""
    X0, X1 = [], []
    for k in range(n):
        o = np.array([10.0 * k, 0.0, 0.0])
        a = [o + [0.0, 0.0, 0.0], o + [1.0, 0.0, 0.0]]
        X0 += a + [o + [0.5, -0.5, 0.5], o + [0.5, 0.5, 0.5]]
        X1 += a + [o + [0.5, -0.5, -0.5], o + [0.5, 0.5, -0.5]]
    return np.array(X0), np.array(X1), np.arange(0, 4 * n + 1, 2)


def test_stop_is_heard_within_the_tight_inclusion_pairs(monkeypatch):
    X0, X1, off = crossing_step(100)
    assert crossings.count_crossings(X0, X1, off)["crossings"] == 100
    seen = []
    real = crossings.tight_inclusion_toi

    def counted(S, E, *a, **k):
        seen.append(len(S))
        return real(S, E, *a, **k)
    monkeypatch.setattr(crossings, "tight_inclusion_toi", counted)
    # the signal arrives once Tight-Inclusion has started on the step's pairs
    assert crossings.count_crossings(X0, X1, off, stop=lambda: bool(seen)) is None
    assert seen == [crossings.CROSSING_CHUNK]
    # a stop that never comes: the same answer, in chunks
    seen.clear()
    r = crossings.count_crossings(X0, X1, off, stop=lambda: False)
    assert r["crossings"] == 100
    assert seen == [32, 32, 32, 4]
    S, E = crossings.pair_positions(X0, r["pairs"]), crossings.pair_positions(X1, r["pairs"])
    assert crossings.crossing_pairs(S, E, stop=lambda: True) is None
