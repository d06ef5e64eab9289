"""The compiled element kernels (lc_petsc.elements.compiled) against the NumPy ones.

The NumPy kernels are the tested reference; the compiled ones must give the same
energies, gradients and Hessians (every filter they implement) to round-off on random and degenerate
elements (straight and folded bends, collinear twist edges, planar twists, theta and phi
near 0 and pi, tiny edges), raise the same ElementError on bad input, write the band
layout of the assembler (full and upper-only), and assemble the same PETSc matrix.
Their Hessian is also checked against finite differences of their own gradient where
the analytic filter is exact (stretch under tension, bend and twist at rest).
"""

from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc

from lc_petsc.config import MaterialConfig, PhysicsConfig, SceneConfig, SimConfig, SolverConfig
from lc_petsc.elements import ElementError, bend, compiled, stretch, twist
from lc_petsc.elements.angle import STRAIGHT_TOL
from lc_petsc.simulator import build_simulator

import compiled_elements as ce
import element_helpers as eh

MODULES = {"stretch": stretch, "bend": bend, "twist": twist}
#: agreement "to round-off": relative to the largest entry of the element's array
RTOL = 1e-12


def _compare(term, x, rest, k, filter, rtol=RTOL):
    """Compiled vs NumPy energy, gradient and ``filter``-ed Hessian of elements x
    (n, k, 3); returns the largest relative differences (energy, gradient, Hessian)."""
    ref = MODULES[term]
    e0 = ref.energy(x, rest, k)
    g0, h0 = ref.gradient_hessian(x, rest, k, filter=filter)
    e1 = ce.energy(term, x, rest, k)
    # the per-vertex pass writes each element's energy as the summed pass returns it
    assert np.array_equal(ce.vertex_energy(term, x, rest, k), e1)
    g1, h1 = ce.gradient_hessian(term, x, rest, k, filter=filter)
    n = len(x)
    # Reference magnitudes from the element's Hessian (H ~ k / L^2): near rest the energy
    # and gradient are round-off themselves, so they are compared on the scale of H L^2
    # and H L (L the element's longest edge).
    L = np.abs(np.diff(x, axis=1)).max(axis=(1, 2))
    h_size = np.abs(h0.reshape(n, -1)).max(axis=1)
    sizes = (np.maximum(np.abs(e0), h_size * L * L),
             np.maximum(np.abs(g0.reshape(n, -1)).max(axis=1), h_size * L), h_size)
    errs = [np.abs(e0 - e1),
            np.abs((g0 - g1).reshape(n, -1)).max(axis=1),
            np.abs((h0 - h1).reshape(n, -1)).max(axis=1)]
    for what, err, size in zip(("energy", "gradient", "Hessian"), errs, sizes):
        assert np.all(err <= rtol * size), f"{term} {what}: differences {err / np.where(size > 0, size, 1)}"
    assert np.isfinite(h1).all() and np.isfinite(g1).all()
    errs = [e / np.where(size > 0, size, 1) for e, size in zip(errs, sizes)]
    return [float(e.max()) for e in errs]


@pytest.mark.parametrize("filter", compiled.FILTERS)
@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e2])
@pytest.mark.parametrize("term", eh.TERMS)
def test_random_elements_match_numpy(term, scale, filter):
    rng = np.random.default_rng(7 + eh.TERMS.index(term))
    x, rest, k = eh.random_case(term, rng, 300, scale)
    k[::17] = 0.0                        # zero stiffness (e.g. padding) gives exact zeros
    _compare(term, x, rest, k, filter)


def _rotated(x, seed):
    R = eh.random_rotation(np.random.default_rng(seed))
    return x @ R.T + np.array([0.3, -1.2, 2.0])


def _bend_cases():
    """Bends at and near the cone points theta = pi, 0, and with tiny edges."""
    cases = []
    for s in [0.0, 1e-12, 0.5 * STRAIGHT_TOL, 2 * STRAIGHT_TOL, 1e-6, 1e-3]:
        c = np.sqrt(1 - s * s)
        cases.append(eh.bend_from_units(np.array([1.0, 0, 0]), np.array([-c, s, 0])))      # ~pi
        cases.append(eh.bend_from_units(np.array([1.0, 0, 0]), np.array([c, s, 0]), L1=0.5))  # ~0
    cases.append(eh.bend_from_units(np.array([0, 1.0, 0]), np.array([0.6, 0.8, 0]), L0=1e-9, L1=1e-9))
    cases.append(eh.bend_from_units(np.array([0, 1.0, 0]), np.array([0.6, -0.8, 0]), L0=1e-9, L1=2.0))
    return np.stack([_rotated(x, i) for i, x in enumerate(cases)])


def _twist_cases():
    """Twists: straight, collinear outer edges, planar (phi = 0, pi), near planar, tiny."""
    e1 = np.array([0.0, 0.0, 1.0])
    a = np.array([1.0, 0.0, 0.0])
    cases = [np.array([[0, 0, -1.0], [0, 0, 0], [0, 0, 1.0], [0, 0, 2.0]])]    # straight
    for r in [0.0, 1e-9, 0.5e-6, 2e-6, 1e-4]:      # a outer edge (nearly) along e1
        cases.append(eh.twist_from_ab(r * a, np.array([0, 1.0, 0]), e1))
    for phi in [0.0, 1e-12, 1e-9, 0.5 * STRAIGHT_TOL, 1e-7, 1e-4, np.pi - 1e-9, np.pi, -np.pi + 1e-12]:
        b = np.array([np.cos(phi), np.sin(phi), 0.0]) * 0.7
        cases.append(eh.twist_from_ab(a, b, e1))
    cases.append(eh.twist_from_ab(1e-9 * a, 1e-9 * np.array([0.0, 1.0, 0]), 1e-9 * e1))
    return np.stack([_rotated(x, 100 + i) for i, x in enumerate(cases)])


def _stretch_cases():
    e = np.array([0.6, 0.0, 0.8])
    return np.stack([_rotated(np.array([np.zeros(3), L * e]), 200 + i)
                     for i, L in enumerate([1e-9, 1e-3, 0.5, 1.0, 2.0, 1e3])])


@pytest.mark.parametrize("filter", compiled.FILTERS)
@pytest.mark.parametrize("rest_kind", ["at_rest", "pi", "random"])
@pytest.mark.parametrize("term", eh.TERMS)
def test_degenerate_elements_match_numpy(term, rest_kind, filter):
    x = {"stretch": _stretch_cases, "bend": _bend_cases, "twist": _twist_cases}[term]()
    n = len(x)
    current = {"stretch": stretch.length, "bend": bend.angle, "twist": twist.angle}[term](x)
    rng = np.random.default_rng(3)
    if rest_kind == "at_rest":
        rest = current.copy()
    elif rest_kind == "pi":
        rest = np.full(n, np.pi) if term != "stretch" else current * 1.5
    else:
        rest = (current * rng.uniform(0.5, 1.5, n) if term == "stretch"
                else rng.uniform(-np.pi, np.pi, n) if term == "twist" else rng.uniform(0, np.pi, n))
    k = rng.uniform(0.5, 2.0, n)
    _compare(term, x, rest, k, filter)


def test_twist_rest_angles_far_outside_pi_wrap_as_numpy():
    """The compiled twist wraps phi - phibar with selects where pi - (phi - phibar) lies
    in (-2 pi, 4 pi) and with fmod beyond: rest angles of several turns (both paths in
    one batch) give NumPy's energy, gradient and Hessian."""
    rng = np.random.default_rng(5)
    x, _, k = eh.random_case("twist", rng, 300, 1.0)
    rest = rng.uniform(-4 * np.pi, 6 * np.pi, len(x))
    wr = np.pi - (twist.angle(x) - rest)
    assert ((wr <= -2 * np.pi) | (wr >= 4 * np.pi)).sum() > 50 and (np.abs(wr - np.pi) < np.pi).sum() > 50
    for filter in compiled.FILTERS:
        _compare("twist", x, rest, k, filter)


def test_atan2_within_two_ulps_of_libm():
    """The batches' atan2 (arithmetic and selects, so the loops vectorise) against
    libm's: within 1 unit in the last place over random quadrants and magnitudes, within
    2 on unit-circle arguments of ratio 0.41-0.66 (Cephes' polynomial beyond
    tan(pi / 8), where a few in 10^5 are 2 ulps off), and exactly libm's at the signed
    zeros, the axes, the diagonals, pi and NaN."""
    import math

    import numba

    @numba.njit(error_model="numpy")
    def batch_atan2(y, x):
        out = np.empty(len(y))
        for j in range(len(y)):
            out[j] = compiled._vatan2(y[j], x[j])
        return out

    rng = np.random.default_rng(17)
    theta = rng.uniform(-np.pi, np.pi, 200_000)
    size = 10.0 ** rng.uniform(-12, 3, (2, len(theta)))
    y, x = np.sin(theta) * size[0], np.cos(theta) * size[1]
    y[:1000] *= 1e-14                               # near the x axis, both sides
    x[1000:2000] *= 1e-14                           # near the y axis
    ref = np.array([math.atan2(a, b) for a, b in zip(y, x)])
    got = batch_atan2(y, x)
    ulps = np.abs(got - ref) / np.spacing(np.abs(ref))
    assert ulps.max() <= 1.0 and np.mean(got == ref) > 0.9
    theta = rng.uniform(np.arctan(0.41), np.arctan(0.66), 400_000)    # what the kernels pass
    y, x = np.sin(theta), np.cos(theta)
    ref = np.array([math.atan2(a, b) for a, b in zip(y, x)])
    ulps = np.abs(batch_atan2(y, x) - ref) / np.spacing(np.abs(ref))
    assert ulps.max() <= 2.0, ulps.max()
    nan = np.array([(0.0, np.nan), (-0.0, np.nan), (np.nan, 0.0), (np.nan, np.nan)]).T
    assert np.isnan(batch_atan2(*nan)).all(), batch_atan2(*nan)
    special = [(0.0, 1.0), (-0.0, 1.0), (0.0, -1.0), (-0.0, -1.0), (0.0, 0.0), (0.0, -0.0),
               (-0.0, 0.0), (-0.0, -0.0), (1.0, 0.0), (-1.0, -0.0), (2.5, 2.5), (-2.5, 2.5),
               (2.5, -2.5), (-2.5, -2.5), (1e-300, -1.0), (-1e-300, -1.0), (3.0, 1e-300)]
    sy, sx = np.array(special).T
    got = batch_atan2(sy, sx)
    want = np.array([math.atan2(a, b) for a, b in special])
    assert np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))
    assert np.isnan(batch_atan2(np.array([np.nan, 1.0]), np.array([1.0, np.nan]))).all()


@pytest.mark.parametrize("term", eh.TERMS)
def test_bad_elements_raise_the_numpy_error(term):
    kv = eh.NVERT[term]
    rng = np.random.default_rng(5)
    x, rest, k = eh.random_case(term, rng, 4, 1.0)
    xv = np.ascontiguousarray(x.reshape(-1, 3))
    start = np.arange(4, dtype=np.int64) * kv
    arrays = {term: compiled.element_arrays(term, start, rest, k)}
    for bad, what in [(np.nan, "non-finite"), (np.inf, "non-finite"), ("zero", "zero length")]:
        y = xv.copy()
        if bad == "zero":
            y[2 * kv + 1] = y[2 * kv]         # element 2: its first edge has zero length
        else:
            y[2 * kv + 1, 1] = bad
        with pytest.raises(ElementError) as numpy_error:
            MODULES[term].energy(y.reshape(4, kv, 3), rest, k)
        assert what in str(numpy_error.value) and "element 2" in str(numpy_error.value)
        for call in (lambda: compiled.energy(arrays, y),
                     lambda: compiled.add_gradient(arrays, y, np.zeros_like(y)),
                     lambda: compiled.add_gradient_hessian(arrays, y, np.zeros_like(y),
                                                           np.zeros((len(y), 3, 21)), 3, False)):
            with pytest.raises(ElementError) as compiled_error:
                call()
            assert str(compiled_error.value) == str(numpy_error.value)


@pytest.mark.parametrize("term", eh.TERMS)
def test_bad_element_past_the_first_batch_raises_the_numpy_error(term):
    """Bend and twist elements are evaluated in batches of compiled.BATCH: a zero-length
    edge in a later batch stops the pass at that element, with the NumPy error."""
    kv = eh.NVERT[term]
    n = 2 * compiled.BATCH + 5
    x, rest, k = eh.random_case(term, np.random.default_rng(11), n, 1.0)
    xv = np.ascontiguousarray(x.reshape(-1, 3))
    arrays = {term: compiled.element_arrays(term, np.arange(n, dtype=np.int64) * kv, rest, k)}
    bad = compiled.BATCH + 3
    xv[bad * kv + 1] = xv[bad * kv]
    with pytest.raises(ElementError) as numpy_error:
        MODULES[term].energy(xv.reshape(n, kv, 3), rest, k)
    assert f"element {bad}" in str(numpy_error.value)
    for call in (lambda: compiled.energy(arrays, xv),
                 lambda: compiled.add_gradient_hessian(arrays, xv, np.zeros_like(xv),
                                                       np.zeros((len(xv), 3, 21)), 3, False)):
        with pytest.raises(ElementError) as compiled_error:
            call()
        assert str(compiled_error.value) == str(numpy_error.value)


def test_bad_arguments_are_value_errors():
    start = np.array([0, 2, 1], np.int64)
    with pytest.raises(ValueError, match="nondecreasing"):
        compiled.element_arrays("bend", start, np.ones(3), np.ones(3))
    with pytest.raises(ValueError, match="unknown term"):
        compiled.element_arrays("shear", start, np.ones(3), np.ones(3))
    with pytest.raises(ElementError, match="stiffness"):
        compiled.element_arrays("bend", np.arange(3), np.ones(3), -np.ones(3))
    arrays = {"twist": compiled.element_arrays("twist", np.arange(2), np.zeros(2), np.ones(2))}
    x = np.random.default_rng(0).normal(size=(5, 3))
    with pytest.raises(ValueError, match="filters"):
        compiled.add_gradient_hessian(arrays, x, np.zeros_like(x), np.zeros((5, 3, 21)), 3, False,
                                      filter="numerical")
    assert "numerical" not in compiled.FILTERS and "abs" not in compiled.FILTERS
    with pytest.raises(ValueError, match="half bandwidth"):
        compiled.add_gradient_hessian(arrays, x, np.zeros_like(x), np.zeros((5, 3, 15)), 2, False)
    with pytest.raises(ValueError, match="reach vertex"):
        compiled.energy(arrays, x[:4])


def test_band_layout_of_a_wisp_full_and_upper():
    """Several terms on one curly wisp: the band (full, and upper-only for SBAIJ) equals
    the sum of the NumPy element Hessians scattered into a dense matrix."""
    rng = np.random.default_rng(11)
    wisp = eh.helix_wisp(30)
    x = wisp + rng.normal(scale=0.05, size=wisp.shape)
    nv, b = len(x), 3
    dense = np.zeros((3 * nv, 3 * nv))
    g_ref = np.zeros((nv, 3))
    arrays = {}
    for term, kv in eh.NVERT.items():
        start = np.arange(nv - kv + 1)
        xe = x[start[:, None] + np.arange(kv)]
        cur = {"stretch": stretch.length, "bend": bend.angle, "twist": twist.angle}[term](xe)
        rest = cur * 1.1 if term == "stretch" else cur + rng.uniform(-0.3, 0.3, len(cur))
        k = rng.uniform(0.5, 2.0, len(start))
        arrays[term] = compiled.element_arrays(term, start, rest, k)
        ge, he = MODULES[term].gradient_hessian(xe, rest, k)
        for e, s in enumerate(start):
            dense[3 * s:3 * (s + kv), 3 * s:3 * (s + kv)] += he[e]
            g_ref[s:s + kv] += ge[e]
    for upper in (False, True):
        band = np.empty((nv, 3, 3 * (2 * b + 1)))
        g = np.zeros((nv, 3))
        compiled.add_gradient_hessian(arrays, x, g, band, b, upper)
        got = ce.band_to_dense(band, b, upper)
        assert np.abs(got - dense).max() <= RTOL * np.abs(dense).max()
        assert np.abs(g - g_ref).max() <= RTOL * np.abs(g_ref).max()
        if upper:   # the lower band stays zero
            assert not band[:, :, :3 * b].any()
    # straight into value arrays full of NaN (as a reused PETSc array may hold stale
    # values): the pass zeroes every stored block itself, those outside the matrix too
    offsets = np.arange(-b, b + 1)
    inside = (np.arange(nv)[:, None] + offsets >= 0) & (np.arange(nv)[:, None] + offsets < nv)
    for stored in (np.ones((nv, 2 * b + 1), bool), inside):      # the full band; a wisp's
        for upper in (False, True):
            mask = stored & (offsets >= 0) if upper else stored
            layout = compiled.BlockLayout.block_csr(mask, b)
            values = np.full(layout.size(), np.nan)
            compiled.add_gradient_hessian_into(arrays, x, np.zeros((nv, 3)), values, layout, upper)
            assert not np.isnan(values).any(), (upper, int(np.isnan(values).sum()))
            got = np.zeros_like(dense)
            for i, d in zip(*np.nonzero(mask & inside)):
                j = i + d - b
                block = values[layout.base[i, d]:layout.base[i, d] + 9].reshape(3, 3).T
                got[3 * i:3 * i + 3, 3 * j:3 * j + 3] = block
            block_upper = np.kron(np.triu(np.ones((nv, nv))), np.ones((3, 3))) > 0
            want = np.where(block_upper, dense, 0.0) if upper else dense
            assert np.abs(got - want).max() <= RTOL * np.abs(dense).max()


@pytest.mark.parametrize("nv", [1, 2, 3, 4, 9])
def test_mass_in_the_pass_is_added_once_on_the_diagonal(nv):
    """``diag`` (the mass term) added in the pass equals the pass without it plus diag[i] I
    on every diagonal block, bit for bit, for wisps of 1 to 9 vertices, in a wisp's
    layout, full and upper (SBAIJ), with the value arrays reused (a second pass over the
    first's values must not add it twice)."""
    rng = np.random.default_rng(nv)
    x = eh.helix_wisp(nv) + rng.normal(scale=0.05, size=(nv, 3))
    arrays = {}
    for term, kv in eh.NVERT.items():
        start = np.arange(max(nv - kv + 1, 0))
        rest = rng.uniform(0.3, 1.2, len(start)) if term == "stretch" else rng.uniform(-1, 1, len(start))
        arrays[term] = compiled.element_arrays(term, start, rest, rng.uniform(0.5, 2.0, len(start)))
    b = 3
    offsets = np.arange(-b, b + 1)
    inside = (np.arange(nv)[:, None] + offsets >= 0) & (np.arange(nv)[:, None] + offsets < nv)
    diag = rng.uniform(1.0, 5.0, nv)
    for upper in (False, True):
        layout = compiled.BlockLayout.block_csr(inside & (offsets >= 0) if upper else inside, b)
        plain = np.zeros(layout.size())
        compiled.add_gradient_hessian_into(arrays, x, np.zeros((nv, 3)), plain, layout, upper)
        with_mass = np.full(layout.size(), np.nan)
        for _ in range(2):
            compiled.add_gradient_hessian_into(arrays, x, np.zeros((nv, 3)), with_mass, layout, upper,
                                               diag=diag)
        want = plain.copy()
        for i in range(nv):
            for r in range(3):
                want[layout.base[i, b] + 4 * r] += diag[i]
        np.testing.assert_array_equal(with_mass, want)


def test_vertex_energy_of_wisps_matches_numpy():
    """compiled.vertex_energy on two wisps of 150 and 3 vertices (all three terms sharing
    vertices, bend and twist past one batch, a straight run whose twists are degenerate)
    is the NumPy kernels' per-element energies summed at each element's first vertex, to
    round-off; its sum is compiled.energy's; bad elements raise the NumPy error."""
    rng = np.random.default_rng(11)
    x = np.concatenate([eh.helix_wisp(150) + rng.normal(scale=0.05, size=(150, 3)), eh.helix_wisp(3)])
    x[40:46] = x[40] + np.arange(6)[:, None] * np.array([0.3, 0.1, -0.2])    # straight: degenerate twists
    offsets = [0, 150, 153]
    arrays, want = {}, np.zeros(len(x))
    for term, kv in eh.NVERT.items():
        start = np.concatenate([np.arange(a, b - kv + 1) for a, b in zip(offsets[:-1], offsets[1:])])
        rest = rng.uniform(0.3, 1.2, len(start)) if term == "stretch" else rng.uniform(-3, 3, len(start))
        arrays[term] = compiled.element_arrays(term, start, rest, rng.uniform(0.5, 2.0, len(start)))
        want += np.bincount(start, MODULES[term].energy(x[start[:, None] + np.arange(kv)], *arrays[term][1:]),
                            minlength=len(x))
    assert len(arrays["twist"][0]) > 2 * compiled.BATCH
    got = compiled.vertex_energy(arrays, x)
    assert got.shape == (len(x),) and np.all(want[np.r_[0:149, 150:152]] != 0.0)     # not the tips
    assert got[149] == got[152] == 0.0
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14 * np.abs(want).max())
    assert got.sum() == pytest.approx(compiled.energy(arrays, x), rel=1e-13)
    x[60] = np.nan
    with pytest.raises(ElementError):
        compiled.vertex_energy(arrays, x)


@pytest.mark.parametrize("term", eh.TERMS)
def test_hessian_vs_fd_of_gradient_where_the_filter_is_exact(term):
    """Stretch under tension, bend and twist at rest: the analytic filter keeps the exact
    Hessian there, so the compiled Hessian must match central differences of the compiled
    gradient with an error shrinking as h^2."""
    rng = np.random.default_rng(21)
    x, rest, k = eh.random_case(term, rng, 5, 1.0)
    if term == "stretch":
        rest = stretch.length(x) * 0.8
    else:
        rest = {"bend": bend.angle, "twist": twist.angle}[term](x)
    mod = ce.module(term)
    H = mod.hessian(x, rest, k)
    # not the trivial zero: at rest the angle terms keep k grad(theta) grad(theta)^T
    assert np.all(np.linalg.norm(H.reshape(5, -1), axis=1) > 0.1 * k.min())
    hs = np.array([8e-3, 4e-3, 2e-3, 1e-3])
    errs = []
    for h in hs:
        Hfd = eh.fd_hessian_of_gradient(lambda y: mod.gradient(y, rest, k), x, h)
        errs.append(np.linalg.norm((Hfd - H).reshape(5, -1), axis=1)
                    / np.linalg.norm(H.reshape(5, -1), axis=1))
    errs = np.array(errs)
    for e in range(5):
        eh.assert_h2_convergence(hs, errs[:, e], f"compiled {term} Hessian, element {e}",
                                 final_max=1e-4)


def _simulator(kernels, kind, mat_type, filter="analytic"):
    scene = (SceneConfig(kind="hairball", n_wisps=3, perturbation="jitter", jitter=0.2)
             if kind == "hairball" else SceneConfig(kind="straight", n_vertices=12))
    cfg = SimConfig(scene=scene, material=MaterialConfig(youngs_modulus=1e9),
                    physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity")),
                    solver=SolverConfig(options=f"-mat_type {mat_type} -lc_element_kernels {kernels}",
                                        filter=filter))
    return build_simulator(cfg, comm=MPI.COMM_SELF)


def _assembled(sim, x):
    asm = sim.assembler
    g = asm.assemble(x)
    asm.add_mass(sim.scene.mass / sim.config.time.dt ** 2)
    A = asm.commit()
    if asm.mat_type == "sbaij":
        A.setOption(PETSc.Mat.Option.GETROW_UPPERTRIANGULAR, True)
    rowptr, cols, vals = A.getValuesCSR()
    return g, asm.gradient(x), asm.energy(x), (rowptr.copy(), cols.copy(), vals.copy())


@pytest.mark.parametrize("filter", ["analytic", "none", "abs"])
@pytest.mark.parametrize("mat_type", ["baij", "sbaij"])
@pytest.mark.parametrize("kind", ["hairball", "straight"])
def test_assembled_matrix_matches_numpy_kernels(kind, mat_type, filter):
    """The Newton matrix, gradient and energy from the compiled kernels equal the NumPy
    kernels' (a filter they do not implement falls back to NumPy: the same values)."""
    sims = {kv: _simulator(kv, kind, mat_type, filter) for kv in ("numpy", "compiled")}
    try:
        x = sims["numpy"].x
        if kind == "straight":     # straight strand: every bend at pi, every twist dropped
            assert np.allclose(bend.angle(x[np.arange(len(x) - 2)[:, None] + np.arange(3)]), np.pi)
        ref, got = (_assembled(sims[kv], x) for kv in ("numpy", "compiled"))
        for a, b_ in zip(ref[:2], got[:2]):
            assert np.abs(a - b_).max() <= RTOL * max(np.abs(a).max(), 1e-300)
        assert abs(ref[2] - got[2]) <= RTOL * max(abs(ref[2]), 1e-300)
        (p0, c0, v0), (p1, c1, v1) = ref[3], got[3]
        assert np.array_equal(p0, p1) and np.array_equal(c0, c1)
        assert np.abs(v0 - v1).max() <= RTOL * np.abs(v0).max()
        # which path ran: compiled elements only for the filters they implement
        asm = sims["compiled"].assembler
        assert (asm._padded is None) == (filter in compiled.FILTERS)
    finally:
        for s in sims.values():
            s.close()


def test_unknown_kernels_option_is_a_clear_error():
    with pytest.raises(ValueError, match="-lc_element_kernels 'fortran'.*compiled.*numpy"):
        _simulator("fortran", "straight", "baij")


def test_kernel_cache_is_versioned_by_every_element_module(tmp_path, monkeypatch):
    """Numba keys a cached kernel on its own file; the cache folder changes with any
    module of the folder (the helpers and constants a kernel inlines), and follows
    NUMBA_CACHE_DIR; the kernels of this process are cached in it."""
    import numba
    assert numba.config.CACHE_DIR == compiled.kernel_cache_dir()
    (tmp_path / "a.py").write_text("X = 1\n")
    (tmp_path / "b.py").write_text("def f():\n    return 1\n")
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    first = compiled.kernel_cache_dir(tmp_path)
    assert first.startswith(str(tmp_path / "__pycache__" / "kernels-"))
    assert compiled.kernel_cache_dir(tmp_path) == first
    (tmp_path / "a.py").write_text("X = 2\n")              # a constant another module inlines
    second = compiled.kernel_cache_dir(tmp_path)
    assert second != first
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    assert compiled.kernel_cache_dir(tmp_path) == str(tmp_path / "cache" / Path(second).name)


def test_setup_warms_every_kernel_and_names_a_failed_half(monkeypatch):
    """``python -m lc_petsc.elements.warm`` (scripts/setup.sh) compiles or loads both
    halves of the kernels; a failing child half is an error naming its exit status, not a
    silent cold cache for the first run."""
    from lc_petsc.elements import warm
    assert warm.warm_all() > 0.0
    monkeypatch.setattr(warm, "_CHILD", "raise SystemExit(3)")
    with pytest.raises(RuntimeError, match=r"exit 3"):
        warm.warm_all()
