"""The contact-aware preconditioner (-lc_contact_pc clusters, lc_petsc/contact_pc.py) and
MUMPS's ordering default: clustering against a brute-force reference, the preconditioner
against dense solves of its cluster blocks, SPD, the fallback, plan errors, both contact
preconditioners on a run, and rank invariance of the solve (mpi)."""

import re

import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc

import lc_petsc.simulator as simmod
from lc_petsc.contact_pc import (cluster_labels, factor_cluster_matrix, self_blocks, self_coupled,
                                 wisp_couplings)
from lc_petsc.errors import ConfigError, SolverError
from lc_petsc.solver_plan import SolverPlan
from sim_helpers import touching_wisps_config, touching_wisps_source


def brute_force_clusters(n, pairs, weights, counts, max_wisps, max_blocks, own=None):
    """The greedy merge with explicit sets (the reference of cluster_labels; ``own``:
    each wisp's self-contact blocks, counted in its cluster's blocks)."""
    member = {w: {w} for w in range(n)}
    blocks = {w: 0 if own is None else int(own[w]) for w in range(n)}
    for e in sorted(range(len(pairs)), key=lambda e: (-weights[e], e)):
        a, b = (min(member[w]) for w in pairs[e])
        if a == b:
            continue
        # every pair between the two sets comes inside with the merge
        total = blocks[a] + blocks[b] + sum(counts[f] for f in range(len(pairs))
                                            if {min(member[w]) for w in pairs[f]} == {a, b})
        if len(member[a]) + len(member[b]) > max_wisps or total > max_blocks:
            continue
        merged = member[a] | member[b]
        for w in merged:
            member[w] = merged
        blocks[min(merged)] = total
    return np.array([min(member[w]) for w in range(n)])


@pytest.mark.parametrize("max_wisps, max_blocks, own", [
    (10 ** 6, 10 ** 9, False), (4, 10 ** 9, False), (64, 40, False), (3, 25, False), (64, 40, True)])
def test_clusters_equal_brute_force(max_wisps, max_blocks, own):
    rng = np.random.default_rng(3)
    n = 60
    pairs = np.unique(np.sort(rng.integers(0, n, (150, 2)), axis=1), axis=0)
    pairs = pairs[pairs[:, 0] < pairs[:, 1]]
    weights = rng.choice([1.0, 2.0, 3.0], len(pairs))          # ties on purpose
    counts = rng.integers(1, 12, len(pairs))
    own = rng.integers(0, 30, n) * (rng.random(n) < 0.5) if own else None   # self-contact blocks
    got = cluster_labels(n, pairs, weights, counts, max_wisps, max_blocks, own)
    ref = brute_force_clusters(n, pairs, weights, counts, max_wisps, max_blocks, own)
    np.testing.assert_array_equal(got, ref)
    # a cluster of several wisps holds at most max_blocks cross blocks, its pairs' and its
    # wisps' own (self-contact) ones; before, neither the own blocks nor a pair closing a
    # triangle inside counted (main: 58 blocks, 150 with the own ones, against the cap 40)
    inside = got[pairs[:, 0]] == got[pairs[:, 1]]
    held = np.bincount(got[pairs[inside, 0]], counts[inside], n)
    if own is not None:
        held += np.bincount(got, own, n)
    several = np.bincount(got, minlength=n) > 1
    assert held[several].max() <= max_blocks, held[several].max()
    sizes = np.bincount(got, minlength=n)
    assert sizes.max() <= max_wisps
    if max_wisps > n and max_blocks > counts.sum():     # no cap: the connected components
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components
        g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        _, comp = connected_components(g, directed=False)
        assert len(np.unique(comp)) == len(np.unique(got))
        for c in np.unique(comp):
            assert len(np.unique(got[comp == c])) == 1
    else:
        assert sizes.max() > 1      # the caps still let some clusters form


@pytest.mark.parametrize("max_wisps, max_blocks", [(64, 10 ** 9), (8, 60), (40, 200), (3, 10 ** 9)])
def test_compiled_clusters_equal_brute_force_on_strand_like_graphs(max_wisps, max_blocks):
    # lc_petsc/elements/compiled_cluster.py: the blocks between two clusters summed on
    # demand over the smaller side's pairs, stopped once past the room left under the cap;
    # contact-like graphs (mostly near neighbours, a few far) grow clusters of tens of
    # wisps, merged into each other many times (the member lists), with ties and own blocks
    from lc_petsc.elements.compiled_cluster import cluster_roots
    rng = np.random.default_rng(11)
    n = 150
    a = rng.integers(0, n, 700)
    b = np.clip(a + rng.integers(-6, 7, 700), 0, n - 1)
    far = rng.random(700) < 0.1
    b[far] = rng.integers(0, n, far.sum())
    pairs = np.unique(np.sort(np.stack([a, b], axis=1), axis=1), axis=0)
    pairs = pairs[pairs[:, 0] < pairs[:, 1]]
    weights = rng.choice([1.0, 2.0, 3.0, 4.0], len(pairs))
    counts = rng.integers(1, 9, len(pairs))
    own = rng.integers(0, 20, n) * (rng.random(n) < 0.3)
    ref = brute_force_clusters(n, pairs, weights, counts, max_wisps, max_blocks, own)
    got = cluster_labels(n, pairs, weights, counts, max_wisps, max_blocks, own)
    np.testing.assert_array_equal(got, ref)
    sizes = np.bincount(got, minlength=n)
    assert 1 < sizes.max() <= max_wisps and len(np.unique(got)) < n // 2 or max_wisps == 3
    # the kernel itself, with the order given: the same roots
    order = np.argsort(-weights, kind="stable")
    inner = own.astype(np.int64)
    roots = cluster_roots(n, pairs.astype(np.int64), counts.astype(np.int64), order, max_wisps,
                          max_blocks, inner)
    np.testing.assert_array_equal(roots, ref)
    # inner ends as each cluster's blocks at its root (own + pairs inside)
    inside = ref[pairs[:, 0]] == ref[pairs[:, 1]]
    held = np.bincount(ref[pairs[inside, 0]], counts[inside], n) + np.bincount(ref, own, n)
    np.testing.assert_array_equal(inner[np.unique(ref)], held[np.unique(ref)])


def test_wisp_couplings_sums_blocks_per_wisp_pair():
    # 4 vertices: wisps 0 (v0, v1), 1 (v2), 2 (v3); blocks (0,2) (1,2) (1,3) (2,0) (2,1) (3,1)
    rows = np.array([0, 1, 1, 2, 2, 3])
    cols = np.array([2, 2, 3, 0, 1, 1])
    blocks = np.arange(6, dtype=float)[:, None, None] * np.eye(3)
    vertex_wisp = np.array([0, 0, 1, 2])
    pairs, w, counts = wisp_couplings(vertex_wisp[rows], vertex_wisp[cols], blocks, 3)
    np.testing.assert_array_equal(pairs, [[0, 1], [0, 2]])
    np.testing.assert_allclose(w, [np.sqrt(3) * (0 + 1), np.sqrt(3) * 2])
    np.testing.assert_array_equal(counts, [2, 1])


def test_self_blocks_counts_each_vertex_pair_of_a_wisp_once():
    # wisps 0 (v0-v2), 1 (v3): blocks (0,2) (2,0) (1,2) (2,1) inside wisp 0, (2,3) (3,2) between
    vertex_wisp = np.array([0, 0, 0, 1])
    rows, cols = np.array([0, 2, 1, 2, 2, 3]), np.array([2, 0, 2, 1, 3, 2])
    got = self_blocks(vertex_wisp[rows], vertex_wisp[cols], rows, cols, 3)
    np.testing.assert_array_equal(got, [2, 0, 0])
    assert not self_blocks([], [], [], [], 2).any()


def test_self_coupled_finds_the_wisps_with_blocks_inside():
    # blocks (0,1) inside wisp 0, (1,2) between wisps 0 and 1, (3,3) inside wisp 2 but
    # zero (a pinned vertex's block): only wisp 0 has self-contact
    vertex_wisp = np.array([0, 0, 1, 2])
    rows, cols = np.array([0, 1, 1, 3]), np.array([1, 0, 2, 3])
    blocks = np.array([1.0, 1.0, 5.0, 0.0])[:, None, None] * np.eye(3)
    got = self_coupled(vertex_wisp[rows], vertex_wisp[cols], blocks, 3)
    np.testing.assert_array_equal(got, [True, False, False])
    assert not self_coupled([], [], np.zeros((0, 3, 3)), 2).any()


def dense(M):
    D = M.convert("dense", PETSc.Mat())
    try:
        return D.getDenseArray().copy()
    finally:
        D.destroy()


def one_frame(monkeypatch, options, comm=MPI.COMM_SELF, run=True):
    """The touching wisps' simulator after one frame (``run=False``: before it)."""
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: touching_wisps_source())
    cfg = touching_wisps_config(1, options=options)
    # the contact graphs measured: uncarried first iterate (time.carry_with_head); carried,
    # the first frame's pairs fit in 2-wisp clusters and nothing falls back
    cfg.time.carry_with_head = False
    sim = simmod.build_simulator(cfg, comm=comm)
    if run:
        sim.run()
    return sim


def test_cluster_pc_is_the_exact_inverse_of_its_cluster_blocks(monkeypatch):
    sim = one_frame(monkeypatch, "-ksp_rtol 1e-12 -lc_contact_pc clusters")
    try:
        pc = sim.solver.ksp.getPC()
        ctx = sim.solver.clusters
        assert pc.getType() == "python" and ctx.stats["clusters"] >= 1, ctx.stats
        op, _ = sim.solver.ksp.getOperators()
        A, C = dense(op.getPythonContext().A), dense(op.getPythonContext().C)
        K = A + C
        wisp = ctx.vertex_wisp.repeat(3)
        # the clusters of the last set-up, from the PC's own rows
        in_cluster = np.zeros(len(K), bool)
        in_cluster[ctx.dofs] = True
        rng = np.random.default_rng(0)
        r = rng.standard_normal(len(K))
        x, y = op.createVecs()
        x.array[:] = r
        pc.apply(x, y)
        got = y.array.copy()
        # singleton wisps: their block of A (the contact cross blocks never touch them);
        # two direct solves of one block agree to its condition number x eps in norm
        # (2.5e-9 measured after a change of the contact pairs' summation order; an entry
        # much smaller than the block's largest can differ by more, relatively: 1.4e-8 on
        # one of 90 after the first iterate changed), as the clusters'
        for w in np.unique(wisp[~in_cluster]):
            i = np.flatnonzero(wisp == w)
            sol = np.linalg.solve(A[np.ix_(i, i)], r[i])
            assert np.abs(got[i] - sol).max() <= 1e-8 * np.abs(sol).max()
        # clusters: the dense solve of the cluster's block of A + C (cluster = the wisps
        # coupled to each other inside the cluster rows)
        i = np.flatnonzero(in_cluster)
        sub = K[np.ix_(i, i)]
        np.testing.assert_allclose(got[i], np.linalg.solve(sub, r[i]), rtol=1e-8,
                                   atol=1e-12 * np.abs(got[i]).max())
        # P is SPD: the dense preconditioning matrix built from the same rule
        P = A.copy()
        P[np.ix_(i, i)] = sub
        assert np.abs(P - P.T).max() <= 1e-12 * np.abs(P).max()
        assert np.linalg.eigvalsh(P).min() > 0
        # and applying it is symmetric: u . P^-1 v == v . P^-1 u
        u, v = rng.standard_normal((2, len(K)))
        Pu, Pv = [], []
        for vec, out in ((u, Pu), (v, Pv)):
            x.array[:] = vec
            pc.apply(x, y)
            out.append(y.array.copy())
        assert abs(u @ Pv[0] - v @ Pu[0]) <= 1e-10 * abs(u @ Pv[0])
        # a control: the couplings matter (the per-wisp inverse is not the cluster one)
        assert np.abs(C[np.ix_(i, i)]).max() > 0
        x.destroy()
        y.destroy()
    finally:
        sim.close()


def stiff_chain(n, seed, mass=1e-4, stretch=1e3, contact=1e5):
    """The Newton matrix of a chain of ``n`` vertices as a stiffness ratio of 1e8 makes
    it (scenes56's DIVERGED_INDEFINITE_PC): a mass term ``mass`` per coordinate, springs
    ``stretch`` along the edges of a 4C-like helix and ``contact`` springs between random
    vertex pairs along random normals.  SPD, condition ~3e9, and 3x3 diagonal blocks of
    condition up to ~1e9 (stiff in two directions, only the mass in the third)."""
    rng = np.random.default_rng(seed)
    th = np.deg2rad(72.0) * np.arange(n)
    x = np.c_[0.5 * np.cos(th), -0.1 * np.arange(n), 0.5 * np.sin(th)]
    K = mass * np.eye(3 * n)
    for i in range(n - 1):
        t = (x[i + 1] - x[i]) / np.linalg.norm(x[i + 1] - x[i])
        w = np.zeros(n)
        w[i], w[i + 1] = 1.0, -1.0
        K += stretch * np.kron(np.outer(w, w), np.outer(t, t))
    for _ in range(n // 2):
        i, j = rng.choice(n, 2, replace=False)
        nrm = rng.standard_normal(3)
        nrm /= np.linalg.norm(nrm)
        w = np.zeros(n)
        w[i], w[j] = 1.0, -1.0
        K += contact * np.kron(np.outer(w, w), np.outer(nrm, nrm))
    return K


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("ordering", ["rcm", "qmd", "nd"])
def test_cluster_factor_solves_stiff_spd_blocks_accurately(seed, ordering):
    """The clusters' LU must solve an SPD cluster block to its condition number x eps,
    however ill-conditioned its 3x3 pivot blocks: PETSc's BAIJ LU of these matrices
    (condition 3-4e9) erred by 0.2-380 relative, non-symmetric and indefinite (CG:
    DIVERGED_INDEFINITE_PC on a dense stiffness-ratio-1e8 scene); the point LU by 1e-7."""
    n = 40
    K = stiff_chain(n, seed)
    assert np.linalg.eigvalsh(K).min() > 0 and np.linalg.cond(K) > 1e9
    worst_pivot = max(np.linalg.cond(K[3 * i:3 * i + 3, 3 * i:3 * i + 3]) for i in range(n))
    assert worst_pivot > 1e7
    blocks = K.reshape(n, 3, n, 3).transpose(0, 2, 1, 3)       # (row vertex, col vertex, 3, 3)
    r, c = np.nonzero(np.abs(blocks).sum(axis=(2, 3)))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=n))])
    M, pc = factor_cluster_matrix(indptr, c, blocks[r, c], ordering)
    try:
        assert np.abs(dense(M) - K).max() == 0.0                   # the matrix is K, bit for bit
        rhs = np.random.default_rng(10 + seed).standard_normal((2, 3 * n))
        x, y = M.createVecs()
        out = []
        for b in rhs:
            x.array[:] = b
            pc.apply(x, y)
            out.append(y.array.copy())
        for b, got in zip(rhs, out):
            ref = np.linalg.solve(K, b)
            assert np.abs(got - ref).max() <= 1e-5 * np.abs(ref).max()
        # symmetric application: u . P^-1 v == v . P^-1 u
        assert abs(rhs[0] @ out[1] - rhs[1] @ out[0]) <= 1e-6 * abs(rhs[0] @ out[1])
        x.destroy()
        y.destroy()
    finally:
        pc.destroy()
        M.destroy()


def rcm_factor(M, kind):
    """PETSc's factor ``kind`` of the sequential matrix ``M`` with the RCM ordering (a PC)."""
    pc = PETSc.PC().create(comm=PETSc.COMM_SELF)
    pc.setType(kind)
    pc.setFactorOrdering("rcm")
    pc.setOperators(M, M)
    pc.setUp()
    return pc


@pytest.mark.parametrize("n", [1, 2, 40])
def test_cluster_factor_is_a_cholesky_of_half_the_entries(n):
    """The clusters' factor is PETSc's Cholesky of the SPD point matrix (one triangle
    stored), not its LU (both): the factor holds one triangle of the LU's entries (on the
    2K frame-90 systems 0.52x of them, and its solve 0.5x the LU's CPU per CG iteration,
    docs/contact_solver.md, "One CG iteration against the memory bandwidth"), and solves
    to round-off, on a stiff chain of n vertices with contact-like couplings (1 and 2
    vertices: a lone vertex, the shortest wisp).  Fails on the LU (before 2026-12-08)."""
    K = stiff_chain(max(n, 2), 0)[:3 * n, :3 * n]
    blocks = K.reshape(n, 3, n, 3).transpose(0, 2, 1, 3)
    r, c = np.nonzero(np.abs(blocks).sum(axis=(2, 3)))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=n))])
    M, pc = factor_cluster_matrix(indptr, c, blocks[r, c])
    lu = rcm_factor(M, PETSc.PC.Type.LU)
    try:
        assert pc.getType() == PETSc.PC.Type.CHOLESKY
        entries = pc.getFactorMatrix().getInfo()["nz_used"]
        both = lu.getFactorMatrix().getInfo()["nz_used"]                # L and U, the same ordering
        assert (9 * len(r) + 3 * n) // 2 <= entries <= (both + 3 * n) // 2   # one triangle and the diagonal
        x, y = M.createVecs()
        x.array[:] = np.random.default_rng(n).standard_normal(3 * n)
        pc.apply(x, y)
        ref = np.linalg.solve(K, x.array)
        assert np.abs(y.array - ref).max() <= 1e-5 * np.abs(ref).max()
        x.destroy()
        y.destroy()
    finally:
        for obj in (lu, pc, M):
            obj.destroy()


def test_cluster_matrix_is_filled_as_aij_not_converted():
    """factor_cluster_matrix fills the point (AIJ) matrix from the blocks: the matrix
    PETSc's conversion of the BAIJ one gives (pattern, values, explicit zeros, block size)
    and the same Cholesky solve, bit for bit, without a BAIJ matrix converted (MatConvert
    took ~30-60 ms of a 2K set-up's ~220-460 ms CPU, docs/contact_solver.md, "Where the
    cluster set-up goes")."""
    rng = np.random.default_rng(3)
    n = 60                                                  # block rows
    r = np.repeat(np.arange(n), 5)
    c = np.clip(r + np.tile(np.arange(-2, 3), n), 0, n - 1)
    far = rng.integers(0, n, (2, 12))                       # a few contact-like couplings
    key = np.unique(np.r_[r * n + c, far[0] * n + far[1], far[1] * n + far[0]])
    r, c = key // n, key % n
    blocks = rng.standard_normal((len(r), 3, 3))
    blocks[rng.random(blocks.shape) < 0.2] = 0.0            # zeros inside blocks stay entries
    blocks[r == c] += 20.0 * np.eye(3)
    mirror = np.searchsorted(key, c * n + r)                # the matrix symmetric, as a cluster's is
    blocks = np.where((r > c)[:, None, None], blocks[mirror].transpose(0, 2, 1), blocks)
    blocks[r == c] = 0.5 * (blocks[r == c] + blocks[r == c].transpose(0, 2, 1))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=n))])
    PETSc.Log.begin()
    converts = PETSc.Log.Event("MatConvert").getPerfInfo()["count"]
    M, pc = factor_cluster_matrix(indptr, c, blocks)
    assert PETSc.Log.Event("MatConvert").getPerfInfo()["count"] == converts
    B = PETSc.Mat().createBAIJ(size=(3 * n, 3 * n), bsize=3, comm=PETSc.COMM_SELF,
                               csr=(indptr.astype(PETSc.IntType), c.astype(PETSc.IntType), blocks.ravel()))
    B = B.convert(PETSc.Mat.Type.SEQAIJ)
    ref = rcm_factor(B, PETSc.PC.Type.CHOLESKY)
    try:
        got, want = M.getValuesCSR(), B.getValuesCSR()
        assert len(got[2]) == 9 * len(r) and (got[2] == 0.0).sum() > 0
        for a, b in zip(got, want):
            assert np.array_equal(a, b)
        assert M.getType() == B.getType() and M.getBlockSizes() == B.getBlockSizes() == (3, 3)
        x, y = M.createVecs()
        z = y.duplicate()
        x.array[:] = rng.standard_normal(3 * n)
        pc.apply(x, y)
        ref.apply(x, z)
        assert np.array_equal(y.array, z.array) and np.abs(y.array).max() > 0
        for v in (x, y, z):
            v.destroy()
    finally:
        for obj in (ref, B, pc, M):
            obj.destroy()


def test_both_contact_preconditioners_same_trajectory_clusters_cut_iterations(monkeypatch):
    runs = {}
    for mode in ("strands", "clusters"):
        sim = one_frame(monkeypatch, f"-ksp_rtol 1e-12 -ksp_max_it 5000 -lc_contact_pc {mode}")
        try:
            sim.run(2)
            runs[mode] = (sim.gather_positions(), list(sim.solver.iterations),
                          sim.summary()["contact"]["pairs_per_frame"])
            if mode == "clusters":      # set up once per Newton solve, not more
                assert len(sim.solver.clusters.history) == len(sim.solver.iterations)
        finally:
            sim.close()
    (xs, its_s, pairs_s), (xc, its_c, pairs_c) = runs["strands"], runs["clusters"]
    assert pairs_s == pairs_c and sum(pairs_c) > 0
    assert np.abs(xs - xc).max() <= 1e-8 * np.abs(xs).max()
    assert max(its_c) <= 2, its_c     # exact: every coupled wisp in a cluster on one rank (rtol 1e-12)
    assert min(its_s[1:]) > 10, its_s       # control: blind to the couplings


def test_cluster_orderings_same_trajectory(monkeypatch):
    """The clusters' LU ordering (-lc_cluster_ordering, default rcm) changes only the
    round-off of the exact cluster solves: the same CG iterations and contact pairs, the
    same positions to round-off, and RCM's factor a little fuller than qmd's."""
    runs = {}
    for ordering in ("qmd", "rcm", None):
        extra = "" if ordering is None else f" -lc_cluster_ordering {ordering}"
        sim = one_frame(monkeypatch, "-ksp_rtol 1e-10 -lc_contact_pc clusters" + extra)
        try:
            sim.run(2)
            ctx = sim.solver.clusters
            assert ctx.ordering == (ordering or "rcm")
            runs[ordering] = (sim.gather_positions(), list(sim.solver.iterations),
                              sim.summary()["contact"]["pairs_per_frame"],
                              [h["fill"] for h in ctx.history if h["clusters"]])
        finally:
            sim.close()
    (xq, its_q, pairs_q, fill_q), (xr, its_r, pairs_r, fill_r) = runs["qmd"], runs["rcm"]
    assert runs[None][1] == its_r and np.array_equal(runs[None][0], xr)      # rcm is the default
    assert pairs_q == pairs_r and sum(pairs_r) > 0 and its_q == its_r
    assert len(fill_r) >= 1 and len(fill_r) == len(fill_q)
    assert all(r >= q - 1e-12 for q, r in zip(fill_q, fill_r)), (fill_q, fill_r)
    assert np.abs(xq - xr).max() <= 1e-10 * np.abs(xq).max()


def test_fallback_keeps_the_per_wisp_blocks(monkeypatch):
    # at most 2 wisps per cluster leaves couplings out; asking clusters to hold all of
    # the coupling weight makes the set-up fall back to the per-wisp blocks
    sim = one_frame(monkeypatch, "-ksp_rtol 1e-12 -lc_contact_pc clusters "
                                 "-lc_cluster_max_wisps 2 -lc_cluster_min_captured 1")
    try:
        st = sim.solver.clusters.stats
        assert st["fallback"] and st["clusters"] == 0 and st["captured"] < 1.0, st
        assert sim.solver.clusters.cluster is None
        assert sim.solver.iterations[-1] > 10      # the last solve ran with the fallback
    finally:
        sim.close()
    sim = one_frame(monkeypatch, "-ksp_rtol 1e-12 -lc_contact_pc clusters -lc_cluster_max_wisps 2 "
                                 "-lc_cluster_min_captured 0")
    try:
        st = sim.solver.clusters.stats
        assert not st["fallback"] and st["clusters"] >= 1 and st["largest"] <= 2, st
    finally:
        sim.close()


def test_failed_solve_says_which_couplings_the_clusters_left_out(monkeypatch):
    """A CG that fails with the cluster preconditioner names the contact couplings
    between wisps its last set-up left out (all of them under the fallback) and the
    caps to raise; with the default caps the same frame converges within the same
    iteration limit (the clusters hold every coupling: exact)."""
    limit = "-ksp_rtol 1e-12 -ksp_max_it 3 -lc_contact_pc clusters"
    for extra, said in (("-lc_cluster_max_wisps 2 -lc_cluster_min_captured 1",
                         r"could put only \d+% of the contact coupling weight into clusters \(below "
                         r"-lc_cluster_min_captured 1\), so it kept per-wisp blocks and left all \d+ coupled "
                         r"wisp pairs out at the caps -lc_cluster_max_wisps 2 -lc_cluster_max_blocks 1024"),
                        ("-lc_cluster_max_wisps 2 -lc_cluster_min_captured 0",
                         r"left \d+ of \d+ coupled wisp pairs out \(\d+% of the coupling weight\) at the "
                         r"caps -lc_cluster_max_wisps 2")):
        sim = one_frame(monkeypatch, f"{limit} {extra}", run=False)
        try:
            with pytest.raises(SolverError, match="DIVERGED_MAX_IT") as e:
                sim.run()
        finally:
            sim.close()
        print("\n" + str(e.value))
        assert re.search(said, str(e.value)), str(e.value)
        assert "larger caps put it into the clusters' exact solves" in str(e.value)
        assert "smaller physics.strand_barrier_stiffness" in str(e.value)
    sim = one_frame(monkeypatch, limit)         # the default caps: no failure
    try:
        assert max(sim.solver.iterations) <= 2 and sim.solver.clusters.left_out() == ""
    finally:
        sim.close()


@pytest.mark.parametrize("options, match", [
    ("-lc_contact_pc tiles", "use coupled"),
    ("-lc_contact_pc clusters -pc_type gamg", "cannot be combined with -pc_type gamg"),
    ("-lc_contact_pc clusters -ksp_type preonly", "preonly"),
    ("-lc_contact_pc clusters -mat_type aij", "BAIJ"),
    ("-lc_contact_pc clusters -lc_wisp_blocks separate", "sets the block Jacobi blocks"),
    ("-lc_contact_pc clusters -lc_cluster_max_wisps 0", "whole number >= 1"),
    ("-lc_contact_pc clusters -lc_cluster_max_blocks 2.5", "whole number >= 1"),
    ("-lc_contact_pc clusters -lc_cluster_min_captured 1.5", "from 0"),
    ("-lc_contact_pc clusters -lc_cluster_ordering amd", "one of rcm, qmd, nd"),
    ("-lc_contact_pc clusters -lc_cluster_span all", "global .* or rank"),
])
def test_plan_refuses_bad_cluster_options(options, match):
    with pytest.raises(ConfigError, match=match):
        SolverPlan.resolve(options, strand_contact=True)


def test_plan_cluster_caps_and_mumps_ordering_default():
    plan = SolverPlan.resolve("-lc_contact_pc clusters -lc_cluster_max_wisps 8", strand_contact=True)
    assert plan.contact_pc == "clusters" and plan.cluster_caps == (8, 1024, 0.9, "rcm", "global", "cholesky")
    assert plan.pmat_type is None               # the strand matrix itself, no AIJ copy
    # the default with contact: clusters for block Jacobi on BAIJ with fused blocks, the
    # per-wisp strand blocks where clusters cannot run, none without contact
    default = SolverPlan.resolve("", strand_contact=True)
    assert default.contact_pc == "clusters" and default.cluster_caps == (64, 1024, 0.9, "rcm", "global", "cholesky")
    for other in ("-lc_wisp_blocks separate", "-mat_type aij", "-lc_contact_pc strands"):
        plan = SolverPlan.resolve(other, strand_contact=True)
        assert plan.contact_pc == "strands" and plan.cluster_caps is None, other
    assert SolverPlan.resolve("-pc_type gamg", strand_contact=True).contact_pc == "coupled"
    assert SolverPlan.resolve("").cluster_caps is None
    mumps = "-ksp_type preonly -pc_type cholesky -pc_factor_mat_solver_type mumps"
    assert dict(SolverPlan.resolve(mumps).factor) == {"mat_mumps_icntl_7": "2"}
    assert dict(SolverPlan.resolve("").factor) == {}
    # the config's (or command line's) choice wins over the code default
    plan = SolverPlan.resolve(mumps + " -mat_mumps_icntl_7 5")
    assert plan.effective()["mat_mumps_icntl_7"] == "5"


def test_mumps_runs_with_amf_unless_told_otherwise(monkeypatch):
    mumps = "-ksp_type preonly -pc_type cholesky -pc_factor_mat_solver_type mumps"
    for extra, expected in (("", 2), (" -mat_mumps_icntl_7 0", 0)):
        sim = one_frame(monkeypatch, mumps + extra)
        try:
            F = sim.solver.ksp.getPC().getFactorMatrix()
            assert F.getMumpsIcntl(7) == expected
        finally:
            sim.close()


@pytest.mark.mpi
def test_cluster_solve_rank_invariant(monkeypatch):
    """Clusters span ranks (-lc_cluster_span global, the default): the preconditioner is
    the 1-rank one on any rank count, so CG needs the 1-rank iterations (<= 2 at rtol
    1e-13: every coupled wisp in a cluster) where rank-local clusters needed up to 33 on
    2 ranks, and the positions equal the 1-rank run's to round-off."""
    comm = MPI.COMM_WORLD
    options = "-ksp_rtol 1e-13 -ksp_max_it 5000 -lc_contact_pc clusters"
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: touching_wisps_source())
    sim = simmod.build_simulator(touching_wisps_config(2, options=options), comm=comm)
    try:
        sim.run()
        X = sim.gather_positions()
        its = sim.solver.iterations
        spanning = max(h["cross_rank_clusters"] for h in sim.solver.clusters.history)
    finally:
        sim.close()
    ok, msg = True, ""
    if comm.rank == 0:
        ref = simmod.build_simulator(touching_wisps_config(2, options=options), comm=MPI.COMM_SELF)
        try:
            ref.run()
            R = ref.gather_positions()
            ref_its = ref.solver.iterations
        finally:
            ref.close()
        err = float(np.abs(X - R).max() / np.abs(R).max())
        # a control: on several ranks the scene's clusters do cross the partition
        ok = err <= 1e-9 and max(its) <= 2 and max(ref_its) <= 2 and (comm.size == 1 or spanning >= 1)
        msg = (f"{comm.size} ranks: relative difference {err:.2e}, CG iterations {its} "
               f"(1 rank {ref_its}), clusters across ranks {spanning}")
    ok, msg = comm.bcast((ok, msg))
    assert ok, msg
