"""The root turn's fixed work compiled (lc_petsc.elements.compiled_turn) against its NumPy
reference (bit for bit: the same arithmetic in the same order) and against plain
arithmetic (round-off): the model's per-wisp sums, the conjugate gradients, the turn."""

import math

import numpy as np
import pytest

from lc_petsc.elements import compiled_turn
from lc_petsc.root_rotation import ANGLE_STEP, _turn_numpy, axis_angle, root_pivots, rotate, turn


def _case(seed, sizes=None):
    """Random wisps (1-400 vertices; one with every vertex pinned, some without a pin),
    positions over five decades: (layout, x, outer, unit, gnear, pivot)."""
    rng = np.random.default_rng(seed)
    sizes = rng.integers(1, 400, rng.integers(1, 15)) if sizes is None else np.asarray(sizes)
    nw = len(sizes)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    nv = int(offsets[-1])
    pinned = np.zeros(nv, bool)
    for w in range(nw):
        pinned[offsets[w]:offsets[w] + rng.integers(0, 4)] = True
    if nw > 3:
        pinned[offsets[3]:offsets[4]] = True
    pivot = root_pivots(offsets, pinned)
    wisp = np.repeat(np.arange(nw), sizes)
    moved = (pivot[wisp] >= 0) & (np.arange(nv) > pivot[wisp])
    near = np.unique(np.concatenate([np.arange(p - 1, p + 3) for p in pivot if p >= 1] + [np.zeros(0, int)]))
    near = near[near < nv]
    layout = compiled_turn.turn_layout(moved.astype(float), np.where(pivot >= 0, pivot, 0)[wisp], offsets,
                                       near, moved[near])
    x = rng.normal(size=(nv, 3)) * 10 ** rng.uniform(-3, 2, (nv, 1))
    return (layout, x, rng.normal(size=(nv, 3)) * 1e5, rng.uniform(1, 1e4, nv) * ~pinned,
            rng.normal(size=(len(near), 3)) * 1e6, pivot)


@pytest.mark.parametrize("seed", range(40))
def test_compiled_sums_are_numpys_bit_for_bit(seed):
    args = _case(seed)[:5]
    for got, want in zip(compiled_turn.turn_sums(*args), compiled_turn.turn_sums_numpy(*args)):
        assert got.shape == want.shape
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("sizes", [[1], [2], [7, 8, 9], [128, 129, 136], [1000, 3], [300] * 3])
def test_sums_per_wisp_are_plain_sums_to_round_off(sizes):
    """Short wisps (a single vertex, fewer than 8 terms), NumPy's block of 128 and its
    halves above: the sums against exactly rounded ones (math.fsum) of each vertex's
    terms, to round-off of the largest term."""
    layout, x, outer, unit, gnear, _ = _case(5, sizes)
    mask, pivot_of, offsets, near, near_moved = layout
    r, b, T, M = compiled_turn.turn_sums(layout, x, outer, unit, gnear)
    q = outer * mask[:, None]
    q[near] += gnear * near_moved[:, None]
    m = unit * mask
    assert np.array_equal(r, (x - x[pivot_of]) * mask[:, None])
    terms = (np.cross(r, q), r[:, :, None] * (m[:, None] * r - q)[:, None, :],
             (m[:, None] * r)[:, :, None] * r[:, None, :])
    for got, per in zip((b, T, M), terms):
        for w, (lo, hi) in enumerate(zip(offsets[:-1], offsets[1:])):
            seg = per[lo:hi].reshape(hi - lo, -1)
            want = np.array([math.fsum(seg[:, c]) for c in range(seg.shape[1])])
            assert np.abs(got[w].ravel() - want).max() <= 1e-13 * max(np.abs(seg).max(), 1e-300)


@pytest.mark.parametrize("seed", range(30))
def test_compiled_curvature_is_numpys_bit_for_bit(seed):
    """A and P from T and M (traces of either sign: signed zeros off the diagonal kept)
    and the across vertices' r x HJ summed into their wisps' columns in order."""
    rng = np.random.default_rng(seed)
    nw, k = 1 + seed % 7, 3 * seed
    T = rng.normal(size=(nw, 3, 3)) * 10 ** rng.uniform(-5, 5, (nw, 1, 1))
    T[0] = -np.abs(T[0])
    M = rng.normal(size=(nw, 3, 3))
    args = (T, M, rng.normal(size=(3, k, 3)) * 1e4, rng.normal(size=(k, 3)), np.sort(rng.integers(0, nw, k)))
    for got, want in zip(compiled_turn.turn_curvature(*args), compiled_turn.turn_curvature_numpy(*args)):
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(np.signbit(got), np.signbit(want))
    A, _ = compiled_turn.turn_curvature(T, M, *args[2:])
    want = np.trace(T, axis1=1, axis2=2)[:, None, None] * np.eye(3) - 0.5 * (T + T.transpose(0, 2, 1))
    for j, w in enumerate(args[4]):
        want[w] += np.stack([np.cross(args[3][j], args[2][c, j]) for c in range(3)], axis=1)
    assert np.abs(A - want).max() <= 1e-12 * np.abs(want).max()


def _systems(seed, n):
    """Per wisp an SPD P and an A (a third indefinite), b over six decades, 80% held."""
    rng = np.random.default_rng(seed)
    B = rng.normal(size=(n, 3, 3)) * 10 ** rng.uniform(-3, 3, (n, 1, 1))
    P = B @ B.transpose(0, 2, 1) + 1e-6 * np.eye(3)
    C = rng.normal(size=(n, 3, 3)) * 10 ** rng.uniform(-3, 3, (n, 1, 1))
    A = C @ C.transpose(0, 2, 1)
    shift = np.where(np.arange(n) % 3 == 0, rng.uniform(0, 2, n), 0.0)
    A = A - (shift * np.trace(A, axis1=1, axis2=2) / 3)[:, None, None] * np.eye(3)
    held = rng.uniform(size=n) < 0.8
    P[~held] = np.eye(3)
    return A, P, rng.normal(size=(n, 3)) * 10 ** rng.uniform(-3, 3, (n, 1)), held


@pytest.mark.parametrize("seed", range(30))
def test_compiled_pcg_is_numpys_bit_for_bit(seed):
    A, P, b, held = _systems(seed, 1 + seed)
    got = compiled_turn.turn_pcg(A, P, b, held)
    np.testing.assert_array_equal(got, compiled_turn.turn_pcg_numpy(A, P, b, held))
    assert np.all(got[~held] == 0.0)


def test_pcg_solves_a_definite_wisp_and_stops_on_negative_curvature():
    """Three steps solve a definite 3x3 system exactly (to round-off); a wisp whose
    first direction has curvature <= 0 keeps no turn; one in the span of a negative
    direction after a positive step keeps that first step."""
    A, P, b, _ = _systems(3, 3)
    A[0] = np.diag([2.0, 3.0, 5.0])
    P[0] = np.diag([1.0, 1.0, 1.0])
    A[1] = -np.eye(3)
    A[2] = np.diag([1.0, -1.0, 1.0])
    P[1] = P[2] = np.eye(3)
    b[2] = [1.0, 1e-3, 0.0]
    theta = compiled_turn.turn_pcg(A, P, b, np.ones(3, bool))
    assert np.abs(theta[0] - np.linalg.solve(A[0], -b[0])).max() <= 1e-15 * np.abs(theta[0]).max()
    assert np.all(theta[1] == 0.0)
    # first step along d = -b: curvature 1 - 1e-6 > 0, alpha = (1 + 1e-6) / (1 - 1e-6)
    alpha = (1.0 + 1e-6) / (1.0 - 1e-6)
    assert theta[2] == pytest.approx(-alpha * b[2], rel=1e-14)


def test_compiled_turn_of_the_vertices_is_turns_bit_for_bit():
    layout, x, _, _, _, pivot = _case(7, [30, 5, 60, 2])
    mask, pivot_of = layout[:2]
    idx = np.flatnonzero(mask)
    wisp = np.repeat(np.arange(4), [30, 5, 60, 2])[idx]
    theta = np.random.default_rng(1).normal(size=(4, 3)) * np.array([[1.0], [1e-9], [0.0], [3.0]])
    axis, c, s = axis_angle(theta)
    got = compiled_turn.turn_vertices(x, idx, pivot_of[idx], axis[wisp], c[wisp], s[wisp])
    np.testing.assert_array_equal(got, turn(x, theta[wisp], pivot_of[idx], idx))
    np.testing.assert_array_equal(got, _turn_numpy(x, idx, pivot_of[idx], axis[wisp], c[wisp], s[wisp]))
    assert np.array_equal(got[mask == 0], x[mask == 0])
    # rigid: distances among each wisp's pivot and turned vertices kept
    for w in (0, 2):
        v = np.concatenate([[pivot[w]], idx[wisp == w]])
        d0 = np.linalg.norm(x[v][:, None] - x[v][None], axis=2)
        d1 = np.linalg.norm(got[v][:, None] - got[v][None], axis=2)
        assert np.abs(d1 - d0).max() <= 1e-13 * d0.max()


def test_no_wisps_and_bad_arguments():
    layout = compiled_turn.turn_layout(np.zeros(0), np.zeros(0, int), [0], np.zeros(0, int), np.zeros(0))
    r, b, T, M = compiled_turn.turn_sums(layout, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)))
    assert r.shape == (0, 3) and b.shape == (0, 3) and T.shape == M.shape == (0, 3, 3)
    assert compiled_turn.turn_pcg(np.zeros((0, 3, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)),
                                  np.zeros(0, bool)).shape == (0, 3)
    layout, x, outer, unit, gnear, _ = _case(1, [5, 6])
    mask, pivot_of, offsets, near, near_moved = layout
    with pytest.raises(ValueError, match="offsets must rise from 0"):
        compiled_turn.turn_layout(mask, pivot_of, [0, 5, 5, 11], near, near_moved)
    with pytest.raises(ValueError, match="pivot_of must index the 11 vertices"):
        compiled_turn.turn_layout(mask, pivot_of + 20, offsets, near, near_moved)
    with pytest.raises(ValueError, match="near must be sorted and distinct"):
        compiled_turn.turn_layout(mask, pivot_of, offsets, near[::-1], near_moved)
    with pytest.raises(ValueError, match=r"x must have shape \(11, 3\)"):
        compiled_turn.turn_sums(layout, x[:-1], outer, unit, gnear)
    with pytest.raises(ValueError, match="A, P .* must match"):
        compiled_turn.turn_pcg(np.zeros((2, 3, 3)), np.zeros((2, 3, 3)), np.zeros((2, 3)), np.ones(3, bool))
    with pytest.raises(ValueError, match=r"T, M .* must match"):
        compiled_turn.turn_curvature(np.zeros((2, 3, 3)), np.zeros((2, 3, 3)), np.zeros((3, 1, 3)), np.zeros((1, 3)),
                                     [2])
    with pytest.raises(ValueError, match="idx, pivot"):
        compiled_turn.turn_vertices(x, [0, 11], [0, 0], np.zeros((2, 3)), np.ones(2), np.zeros(2))


@pytest.mark.parametrize("seed", range(20))
def test_compiled_turned_copies_are_numpys_bit_for_bit(seed):
    """The central differences' turned copies of the across vertices (and the unturned
    copy last): random turns and the model's own six, the identity (the unturned copy's
    bits), vertices at their pivot (zero arms), none turned (a wisp pinned throughout)."""
    layout, x, _, _, _, _ = _case(seed)
    mask, pivot_of, offsets, near, near_moved = layout
    rng = np.random.default_rng(seed)
    eye = np.eye(3)
    six = np.stack([rotate(eye, np.broadcast_to(s * ANGLE_STEP * e, (3, 3)))
                    for s in (1, -1) for e in eye])
    x[pivot_of[near[::3]]] = x[near[::3]]                 # some arms exactly zero
    for turns in (six, rng.normal(size=(int(rng.integers(1, 5)), 3, 3)), eye[None]):
        got = compiled_turn.turn_copies(layout, x, turns)
        want = compiled_turn.turn_copies_numpy(layout, x, turns)
        assert got.shape == ((len(turns) + 1) * len(near), 3)
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(np.signbit(got), np.signbit(want))
        np.testing.assert_array_equal(got[-len(near):], x[near])
        unmoved = np.tile(near_moved == 0.0, len(turns) + 1)
        np.testing.assert_array_equal(got[unmoved], np.tile(x[near], (len(turns) + 1, 1))[unmoved])
    # to round-off, each copy is its vertices' Rodrigues turn about their pivots
    got = compiled_turn.turn_copies(layout, x, six).reshape(7, len(near), 3)
    moved = near_moved != 0.0
    for j, (s, e) in enumerate((s, e) for s in (1, -1) for e in eye):
        arm = x[near] - x[pivot_of[near]]
        want = x[pivot_of[near]] + rotate(arm, np.broadcast_to(s * ANGLE_STEP * e, arm.shape))
        assert np.abs(got[j][moved] - want[moved]).max(initial=0.0) <= 1e-14 * max(np.abs(x).max(), 1.0)
    none = compiled_turn.turn_layout(np.zeros_like(mask), pivot_of, offsets, near, np.zeros_like(near_moved))
    np.testing.assert_array_equal(compiled_turn.turn_copies(none, x, six), np.tile(x[near], (7, 1)))
    with pytest.raises(ValueError, match=r"turns must have shape \(J, 3, 3\)"):
        compiled_turn.turn_copies(layout, x, eye)


@pytest.mark.parametrize("seed", range(20))
def test_compiled_vertex_terms_are_numpys_bit_for_bit(seed):
    """Inertia and gravity per vertex, potentials and gradient: random states over ten
    decades, pinned vertices (zeros), vertices at their target (signed zeros kept), no
    gravity; against plain arithmetic to round-off."""
    rng = np.random.default_rng(seed)
    nv = int(rng.integers(1, 300))
    x = rng.normal(size=(nv, 3)) * 10 ** rng.uniform(-5, 5, (nv, 1))
    xhat = x + rng.normal(size=(nv, 3)) * 10 ** rng.uniform(-8, 1, (nv, 1))
    xhat[::4] = x[::4]
    mass = rng.uniform(1e-4, 1.0, nv)
    f_ext = mass[:, None] * np.array([0.0, 0.0, -981.0]) * (seed % 3 != 0)
    free = rng.uniform(size=nv) < 0.8
    dt = [1 / 30, 1 / 240, 0.1][seed % 3]
    got = compiled_turn.vertex_terms(x, xhat, mass, f_ext, free, dt)
    want = compiled_turn.vertex_terms_numpy(x, xhat, mass, f_ext, free, dt)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)
        np.testing.assert_array_equal(np.signbit(g), np.signbit(w))
    per, grad = got
    assert np.all(per[~free] == 0.0) and np.all(grad[~free] == 0.0)
    d = x - xhat
    plain = 0.5 * mass * np.einsum("ij,ij->i", d, d) / dt ** 2 - np.einsum("ij,ij->i", f_ext, x)
    scale = 0.5 * mass * np.einsum("ij,ij->i", d, d) / dt ** 2 + np.abs(np.einsum("ij,ij->i", f_ext, x))
    assert np.all(np.abs(per - plain)[free] <= 1e-15 * scale[free] + 1e-300)
    np.testing.assert_allclose(grad[free], (mass[:, None] * d / dt ** 2 - f_ext)[free], rtol=1e-15, atol=0.0)
    with pytest.raises(ValueError, match=r"xhat must have shape"):
        compiled_turn.vertex_terms(x, xhat[:-1], mass, f_ext, free, dt)
