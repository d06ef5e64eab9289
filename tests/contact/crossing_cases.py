"""Adversarial segment-pair motions for the crossing counter, by category (tests only):
each returns (S, E) (n, 4, 3) of pairs on the linear path S -> E."""

import numpy as np


def _rotation(rng, angle):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _frame(rng):
    """A segment a0 -> a1 (length 0.1 .. 2), its unit direction u and a unit normal."""
    length = rng.uniform(0.1, 2.0)
    a0, u = rng.normal(size=3), rng.normal(size=3)
    u /= np.linalg.norm(u)
    nrm = np.cross(u, rng.normal(size=3))
    nrm /= np.linalg.norm(nrm)
    return a0, a0 + length * u, u, nrm, length


def near_parallel(rng):
    """B: A turned by 1e-8 .. 1e-3 rad about a point of A, h above it, moving through A
    (2 h) or stopping half way."""
    a0, a1, u, nrm, length = _frame(rng)
    h = 10 ** rng.uniform(-9, -3)
    mid = 0.5 * (a0 + a1) + rng.uniform(-0.4, 0.4) * length * u
    b = (np.stack([a0, a1]) - 0.5 * (a0 + a1)) @ _rotation(rng, 10 ** rng.uniform(-8, -3)).T + mid + h * nrm
    S = np.stack([a0, a1, b[0], b[1]])
    E = S.copy()
    E[2:] -= rng.choice([2.0, 0.5]) * h * nrm
    return S, E


def parallel(rng):
    """B = A shifted by ~1e-3, moving through A (-2 shifts) or half way, sometimes with
    a 1e-4 twist of its end."""
    a0, a1, *_ = _frame(rng)
    off = rng.normal(size=3) * 1e-3
    S = np.stack([a0, a1, a0 + off, a1 + off])
    E = S.copy()
    E[2:] += rng.choice([-2.0, 0.5]) * off
    E[3] += rng.normal(size=3) * 1e-4 * rng.choice([0, 1])
    return S, E


def coincident(rng):
    """B = A shifted, moving by -2 shifts: the two coincide on their whole length at
    t = 1/2 (the pair that kept Tight-Inclusion busy for minutes); sometimes B's end
    moves 1e-4 aside too (then they cross or pass at up to ~1e-4)."""
    a0, a1, *_ = _frame(rng)
    off = rng.normal(size=3) * 10 ** rng.uniform(-5, -2)
    S = np.stack([a0, a1, a0 + off, a1 + off])
    E = S.copy()
    E[2:] -= 2.0 * off
    E[2:] += rng.normal(size=3) * 1e-4 * rng.choice([0, 1])
    return S, E


def parallel_sliding(rng):
    """B = A shifted by 1e-7 .. 1e-3 (not along A), sliding along A by up to 2 lengths
    and towards it by up to 90% of the gap: never meeting (translated copies, as
    generated hairball wisps are)."""
    a0, a1, u, nrm, length = _frame(rng)
    gap = 10 ** rng.uniform(-7, -3)
    S = np.stack([a0, a1, a0 + gap * nrm, a1 + gap * nrm])
    E = S.copy()
    E[2:] += rng.uniform(-2, 2) * length * u - rng.uniform(0, 0.9) * gap * nrm
    return S, E


def endpoint_touch(rng):
    """B starts (or ends) at A's end vertex, moving away (towards) it."""
    a0, a1, *_ = _frame(rng)
    b1 = a1 + rng.normal(size=3)
    tt = rng.choice([0.0, 1.0])
    D = rng.normal(size=3) * 0.3
    S = np.stack([a0, a1, a1 - tt * D, b1 - tt * D])
    E = np.stack([a0, a1, a1 + (1 - tt) * D, b1 + (1 - tt) * D])
    return S, E


def collinear(rng):
    """B on A's line beyond its end, 1e-9 .. 1e-4 off it, moving into overlap and through
    the line (or half way)."""
    a0, a1, u, nrm, length = _frame(rng)
    eps = 10 ** rng.uniform(-9, -4)
    S = np.stack([a0, a1, a1 + 0.1 * length * u + eps * nrm, a1 + 1.1 * length * u + eps * nrm])
    E = S.copy()
    E[2:] += -0.5 * length * u - rng.choice([2.0, 0.5]) * eps * nrm
    return S, E


def _crossing_segment(rng, a0, a1, u, nrm):
    P = a0 + rng.uniform(0.2, 0.8) * (a1 - a0)
    w = np.cross(u, nrm)
    return P - 0.3 * w, P + 0.5 * w


def cross_at_instant(rng):
    """B crosses A exactly at t = 0 or t = 1 (moving off / onto it)."""
    a0, a1, u, nrm, _ = _frame(rng)
    B0, B1 = _crossing_segment(rng, a0, a1, u, nrm)
    V = rng.normal(size=3)
    tt = rng.choice([0.0, 1.0])
    S = np.stack([a0, a1, B0 - tt * V, B1 - tt * V])
    E = np.stack([a0, a1, B0 + (1 - tt) * V, B1 + (1 - tt) * V])
    return S, E


def long_step(rng):
    """B moves 10 .. 1000 units, through A or back to where it started from the same side."""
    a0, a1, u, nrm, _ = _frame(rng)
    B0, B1 = _crossing_segment(rng, a0, a1, u, nrm)
    V = nrm * rng.uniform(10, 1000)
    back = rng.choice([1.0, -0.5])
    S = np.stack([a0, a1, B0 + V, B1 + V])
    E = np.stack([a0, a1, B0 - back * V, B1 - back * V])
    return S, E


def rotate_through(rng):
    """B turns through A about its middle while both move together."""
    a0, a1, u, nrm, _ = _frame(rng)
    B0, B1 = _crossing_segment(rng, a0, a1, u, nrm)
    V = rng.normal(size=3)
    S = np.stack([a0, a1, B0 + nrm * 0.2, B1 - nrm * 0.2])
    E = np.stack([a0 + V, a1 + V, B0 - nrm * 0.2 + V, B1 + nrm * 0.2 + V])
    return S, E


def far_small(rng):
    """~100 units from the origin, B passes 1e-6 through A (or half way back)."""
    a0, a1, u, nrm, _ = _frame(rng)
    B0, B1 = _crossing_segment(rng, a0, a1, u, nrm)
    go = rng.choice([1.0, -0.5])
    shift = rng.normal(size=3) * 100
    S = np.stack([a0, a1, B0 + 1e-6 * nrm, B1 + 1e-6 * nrm]) + shift
    E = np.stack([a0, a1, B0 - go * 1e-6 * nrm, B1 - go * 1e-6 * nrm]) + shift
    return S, E


def random_pairs(rng):
    """Unit-ish segments near each other, each vertex moving by ~1 unit."""
    S = rng.normal(size=(4, 3))
    S[2:] += rng.normal(scale=0.3, size=3)
    return S, S + rng.normal(size=(4, 3))


CATEGORIES = {f.__name__: f for f in (near_parallel, parallel, coincident, parallel_sliding, endpoint_touch,
                                      collinear, cross_at_instant, long_step, rotate_through, far_small,
                                      random_pairs)}


def cases(name, n, seed=0):
    """(S, E) (n, 4, 3) of ``n`` pairs of category ``name``."""
    rng = np.random.default_rng([seed, list(CATEGORIES).index(name)])
    pairs = [CATEGORIES[name](rng) for _ in range(n)]
    return np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
