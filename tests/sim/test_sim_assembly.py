"""The assembled PETSc matrix and gradient against a brute-force dense reference."""

import dataclasses

import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc

from lc_petsc.assembly import KERNELS
from lc_petsc.config import PhysicsConfig, SceneConfig, SimConfig, SolverConfig, TimeConfig
from lc_petsc.simulator import build_simulator


def _dense_reference(sim, x, dt):
    sc = sim.scene
    n = 3 * sc.nv
    K = np.zeros((n, n))
    for name, t in sc.terms.items():
        H = KERNELS[name].hessian(t.gather(x), t.rest, t.stiffness, filter=sim.assembler.filter)
        idx = (3 * (t.start[:, None] + np.arange(t.k))[:, :, None] + np.arange(3)).reshape(len(t.start), -1)
        for e in range(len(t.start)):
            K[np.ix_(idx[e], idx[e])] += H[e]
    K += np.diag(np.repeat(sc.mass / dt ** 2, 3))
    pin = np.repeat(sc.pinned, 3)
    K[pin, :] = 0
    K[:, pin] = 0
    K[pin, pin] = 1.0
    return K


@pytest.mark.parametrize("kernels", ["compiled", "numpy"])
@pytest.mark.parametrize("mat_type", ["baij", "sbaij", "aij"])
@pytest.mark.parametrize("terms", [("stretch",), ("stretch", "bend"), ("stretch", "bend", "twist")])
def test_matrix_matches_dense_reference(mat_type, terms, kernels):
    cfg = SimConfig(scene=SceneConfig(kind="hairball", n_wisps=2, perturbation="jitter", jitter=0.2),
                    physics=PhysicsConfig(terms=terms + ("gravity",)),
                    solver=SolverConfig(options=f"-mat_type {mat_type} -lc_element_kernels {kernels}"))
    sim = build_simulator(cfg, comm=MPI.COMM_SELF)
    try:
        x = sim.x
        dt = cfg.time.dt
        asm = sim.assembler
        assert asm.b == max(len(t) for t in [terms]) and asm.mat_type == mat_type
        assert asm.kernels == kernels
        # BAIJ values are written in place (probed storage order); SBAIJ / AIJ by CSR call
        assert (asm.mat_block is not None) == (mat_type == "baij")
        # the compiled pass writes straight into the BAIJ value array
        assert asm.direct == (mat_type == "baij" and kernels == "compiled")
        g_fused = asm.assemble(x)
        assert np.abs(g_fused - asm.gradient(x)).max() <= 1e-12 * np.abs(g_fused).max()
        asm.add_mass(sim.scene.mass / dt ** 2)
        A = asm.commit()
        v = np.sin(np.arange(3 * sim.scene.nv))
        xv, yv = A.createVecs()
        xv.array[:] = v
        A.mult(xv, yv)
        K = _dense_reference(sim, x, dt)
        ref = K @ v
        assert np.abs(yv.array - ref).max() < 1e-12 * np.abs(ref).max()
        # the mass added inside the element pass (the Newton iteration's call): the same
        # matrix to the bit as add_mass after
        if mat_type == "sbaij":     # its rows are read as their upper parts
            A.setOption(PETSc.Mat.Option.GETROW_UPPERTRIANGULAR, True)
        separate = A.getValuesCSR()[2].copy()
        asm.assemble(x, sim.scene.mass / dt ** 2)
        assert np.array_equal(asm.commit().getValuesCSR()[2], separate)
        # gradient of G against central differences of G
        it = sim.integrator
        it.xhat = sim.scene.x_rest.copy()
        it.t_next = 0.0
        g = it.gradient(x)
        d = np.random.default_rng(1).normal(size=x.shape)
        d[sim.scene.pinned] = 0
        h = 1e-6
        fd = (it.incremental_potential(x + h * d) - it.incremental_potential(x - h * d)) / (2 * h)
        assert abs(fd - np.sum(g * d)) < 1e-5 * abs(fd)
    finally:
        sim.close()


def test_preconditioning_matrix_is_an_exact_aij_copy():
    """BAIJ operator + separate per-wisp blocks: the PC is built from an AIJ copy (same
    values).  And -lc_pmat_type same (the BAIJ operator itself) reaches the same Newton
    iterate.  (The default, fused blocks, factors the operator itself:
    tests/sim/test_sim_wisp_blocks.py.)
    """
    cfg = SimConfig(scene=SceneConfig(kind="hairball", n_wisps=3, perturbation="jitter", jitter=0.2),
                    physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity")),
                    time=TimeConfig(frames=2))
    separate = "-lc_wisp_blocks separate"
    sims = [build_simulator(dataclasses.replace(cfg, solver=SolverConfig(options=separate)),
                            comm=MPI.COMM_SELF),
            build_simulator(dataclasses.replace(
                cfg, solver=SolverConfig(options=separate + " -lc_pmat_type same")), comm=MPI.COMM_SELF)]
    try:
        A, P = sims[0].solver.ksp.getOperators()
        assert A.getType() == "seqbaij" and P.getType() == "seqaij"
        A2, P2 = sims[1].solver.ksp.getOperators()
        assert P2.getType() == "seqbaij"
        assert sims[0].assembler.pmat_block is not None     # the copy is filled in place
        for sim in sims:
            sim.run()
        v = np.cos(np.arange(A.getSize()[0]))
        xa, ya = A.createVecs()
        xp, yp = P.createVecs()
        xa.array[:] = v
        xp.array[:] = v
        A.mult(xa, ya)
        P.mult(xp, yp)
        assert np.abs(ya.array - yp.array).max() <= 1e-13 * np.abs(ya.array).max()
        assert np.abs(sims[0].x - sims[1].x).max() <= 1e-9 * np.abs(sims[0].x).max()
    finally:
        for sim in sims:
            sim.close()


@pytest.mark.mpi
@pytest.mark.parametrize("blocks", ["fused", "separate"])
def test_in_place_values_refresh_the_preconditioner(blocks):
    """Values written in place into PETSc's arrays (Assembler._probe_value_arrays) must
    reach the factorisation of every later Newton iteration: the per-wisp block Jacobi
    is exact without contact, so after two frames P^-1 (A v) = v holds only if the PC
    was refactored from the current matrix (a stale factor from the build misses it by
    far: the check is made against the frame-0 matrix too)."""
    cfg = SimConfig(scene=SceneConfig(kind="hairball", n_wisps=3, perturbation="jitter", jitter=0.2),
                    physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity")),
                    time=TimeConfig(frames=2),
                    solver=SolverConfig(options=f"-lc_wisp_blocks {blocks}"))
    sim = build_simulator(cfg, comm=MPI.COMM_WORLD)     # also run on 2 and 3 ranks
    try:
        A, P = sim.solver.ksp.getOperators()
        first = A.duplicate(copy=True)
        sim.run()
        A, P = sim.solver.ksp.getOperators()
        xv, yv = A.createVecs()
        zv = yv.duplicate()
        v = np.cos(np.arange(*A.getOwnershipRange()))       # the same vector on any rank count
        xv.array[:] = v
        assert sim.assembler.mat_block is not None
        assert (sim.assembler.pmat_block is not None) == (blocks == "separate")
        pc = sim.solver.ksp.getPC()
        A.mult(xv, yv)
        pc.apply(yv, zv)
        err_now = MPI.COMM_WORLD.allreduce(float(np.abs(zv.array - v).max(initial=0.0)), op=MPI.MAX)
        first.mult(xv, yv)
        pc.apply(yv, zv)
        err_first = MPI.COMM_WORLD.allreduce(float(np.abs(zv.array - v).max(initial=0.0)), op=MPI.MAX)
        assert err_now <= 1e-9 * np.abs(v).max() < 1e-6 * np.abs(v).max() < err_first
        first.destroy()
    finally:
        sim.close()


def _local_dense(asm):
    """The rank's diagonal block of the assembled operator as a dense array."""
    return _dense(asm.mat.getDiagonalBlock())


def _dense(block):
    n = block.getSize()[0]
    return block.getValues(range(n), range(n))


@pytest.mark.mpi
@pytest.mark.parametrize("pmat", ["same", "aij"])
def test_direct_fill_matches_the_numpy_scatter(pmat):
    """The compiled pass writing into PETSc's BAIJ value array (BlockLayout, no band),
    with mass, head-contact diagonal blocks, strand-contact band blocks and pinned rows
    on top, gives the NumPy kernels' scatter through the band to round-off, on random
    and on degenerate positions (a straight and a folded wisp: sin theta = 0), and a
    filter the compiled kernels lack (abs: the band path) in between; on 1, 2 and 3
    ranks.  The AIJ preconditioning copy gets the same values.  Control: a stale value
    (the previous iterate's matrix) is far off."""
    comm = MPI.COMM_WORLD
    options = f"-lc_pmat_type {pmat} -lc_wisp_blocks separate"
    sims = {k: build_simulator(SimConfig(
        scene=SceneConfig(kind="hairball", n_wisps=5, perturbation="jitter", jitter=0.2),
        physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity")),
        solver=SolverConfig(options=f"{options} -lc_element_kernels {k}")), comm=comm)
        for k in ("compiled", "numpy")}
    try:
        asm, ref = sims["compiled"].assembler, sims["numpy"].assembler
        assert asm.direct and not ref.direct
        sc = sims["compiled"].scene
        rng = np.random.default_rng(7 + sc.first_vertex)
        x0 = sims["compiled"].x.copy()
        wisps = [(sc.offsets[w], sc.offsets[w + 1]) for w in range(sc.n_wisps)]
        degenerate = x0.copy()
        for w, (lo, hi) in enumerate(wisps[:2]):
            n = hi - lo
            t = np.arange(n, dtype=float) * 0.1
            line = degenerate[lo] + np.outer(t, [1.0, 0.0, 0.0])
            if w == 1:              # folded back on itself: cos theta = -1
                line[1::2] = degenerate[lo] + np.array([0.1, 0.0, 0.0])
            degenerate[lo:hi] = line
        previous = None
        for x, filt in ((x0 + 0.05 * rng.normal(size=x0.shape), "analytic"),
                        (degenerate, "analytic"), (x0, "abs"),
                        (x0 + 0.1 * rng.normal(size=x0.shape), "none")):
            mats = []
            for a in (asm, ref):
                a.filter = filt
                g = a.assemble(x)
                a.add_mass(sc.mass)
                idx = np.arange(0, sc.nv, 7)
                a.add_diagonal(idx, np.broadcast_to(np.diag([1.0, 2.0, 3.0]), (len(idx), 3, 3)))
                # consecutive segments too: their shared vertex's block gets two sums
                seg = np.array([v for lo, hi in wisps if hi - lo > 4 for v in (lo + 1, lo + 2)])
                h = np.arange(9.0).reshape(3, 3) + 1.0
                a.add_band_blocks(seg, *(np.broadcast_to(m, (len(seg), 3, 3)) for m in (h, 0.5 * h, h.T)))
                a.commit()
                mats.append((_local_dense(a), g))
                if a.pmat is not None:
                    P = _dense(a.pmat.getDiagonalBlock())
                    assert np.abs(P - mats[-1][0]).max() <= 1e-13 * np.abs(mats[-1][0]).max()
            (A, ga), (R, gr) = mats
            scale = np.abs(R).max()
            assert np.abs(A - R).max() <= 1e-12 * scale, filt
            assert np.abs(ga - gr).max() <= 1e-12 * np.abs(gr).max()
            if previous is not None:
                assert np.abs(previous - R).max() > 1e-6 * scale
            previous = A
    finally:
        for s_ in sims.values():
            s_.close()


@pytest.mark.parametrize("filter", ["analytic", "abs"])
@pytest.mark.parametrize("options", ["", "-lc_pmat_type aij"])
def test_mass_in_the_pass_once_in_operator_and_pmat(filter, options):
    """assemble(x, mass) (the mass added in the element pass) gives assemble(x) +
    add_mass(mass) to the bit in the operator and in a separate AIJ preconditioning
    matrix, also with the ``abs`` filter (which the compiled kernels hand to NumPy) and
    on a second call over the first call's values (the mass must not pile up)."""
    cfg = SimConfig(scene=SceneConfig(kind="hairball", n_wisps=2, perturbation="jitter", jitter=0.2),
                    physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity")),
                    solver=SolverConfig(filter=filter, options=f"-lc_element_kernels compiled {options}"))
    sim = build_simulator(cfg, comm=MPI.COMM_SELF)
    try:
        asm, x = sim.assembler, sim.x
        mass = sim.scene.mass / cfg.time.dt ** 2
        assert (asm.pmat is not None) == bool(options)

        def values():
            A = asm.commit()
            mats = [A] + ([asm.pmat] if asm.pmat is not None else [])
            return [M.getValuesCSR()[2].copy() for M in mats]

        asm.assemble(x)
        asm.add_mass(mass)
        separate = values()
        for _ in range(2):
            asm.assemble(x, mass)
            fused = values()
            assert len(fused) == len(separate)
            for a, b in zip(fused, separate):
                assert np.array_equal(a, b)
    finally:
        sim.close()


def test_segment_blocks_equal_the_numpy_adds_bit_for_bit():
    """compiled.add_segment_blocks against the four NumPy fancy-index adds it replaces, on
    column-major 3x3 blocks of a band of half width 2, with consecutive segments (the
    block of their shared vertex gets sums from two passes, in NumPy's order), values of
    mixed scale; out-of-range first vertices are refused."""
    from lc_petsc.elements import compiled
    rng = np.random.default_rng(4)
    nv, b = 40, 2
    block_index = rng.permutation(nv * (2 * b + 1)).reshape(nv, 2 * b + 1)
    values = rng.normal(size=9 * nv * (2 * b + 1)) * 10.0 ** rng.integers(-8, 8, 9 * nv * (2 * b + 1))
    idx = np.array([0, 1, 2, 5, 6, 10, 20, 21, 22, 23, 38])
    h00, h01, h11 = (rng.normal(size=(len(idx), 3, 3)) * 10.0 ** rng.integers(-8, 8, (len(idx), 3, 3))
                     for _ in range(3))
    want = values.copy()
    view = want.reshape(-1, 3, 3).transpose(0, 2, 1)
    view[block_index[idx, b]] += h00
    view[block_index[idx + 1, b]] += h11
    view[block_index[idx, b + 1]] += h01
    view[block_index[idx + 1, b - 1]] += h01.transpose(0, 2, 1)
    got = values.copy()
    compiled.add_segment_blocks(got, block_index, idx, b, h00, h01, h11)
    assert np.array_equal(got.view(np.int64), want.view(np.int64))
    assert np.sum(got != values) > 30 * len(idx)
    with pytest.raises(ValueError, match="add_segment_blocks"):
        compiled.add_segment_blocks(got, block_index, np.array([nv - 1]), b, h00[:1], h01[:1], h11[:1])
    with pytest.raises(ValueError, match="add_segment_blocks"):
        compiled.add_segment_blocks(got, block_index, idx, b, h00[:-1], h01, h11)
    # SBAIJ stores the upper triangle only: the (v + 1, v) blocks (index -1) are skipped, and
    # no value outside the stored blocks moves (a -1 read as the last block did)
    upper = block_index.copy()
    upper[:, :b] = -1
    got = values.copy()
    compiled.add_segment_blocks(got, upper, idx, b, h00, h01, h11)
    want = values.copy()
    view = want.reshape(-1, 3, 3).transpose(0, 2, 1)
    view[upper[idx, b]] += h00
    view[upper[idx + 1, b]] += h11
    view[upper[idx, b + 1]] += h01
    assert np.array_equal(got.view(np.int64), want.view(np.int64))


def test_segment_blocks_into_sbaij_match_the_numpy_kernels():
    """Strand contact's segment blocks added to an SBAIJ Newton matrix (MUMPS Cholesky's
    default type), whose compiled pass stores the upper triangle only: the compiled and
    NumPy kernels give the same matrix to round-off, consecutive segments included (an
    unstored lower block once went into the rank's last diagonal block)."""
    mats = {}
    for k in ("compiled", "numpy"):
        sim = build_simulator(SimConfig(
            scene=SceneConfig(kind="hairball", n_wisps=2, perturbation="jitter", jitter=0.2),
            physics=PhysicsConfig(terms=("stretch", "bend", "gravity")),
            solver=SolverConfig(options=f"-mat_type sbaij -lc_element_kernels {k}")), comm=MPI.COMM_SELF)
        try:
            a = sim.assembler
            a.assemble(sim.x)
            seg = np.array([1, 2, 5, 40, 41])
            h = np.arange(9.0).reshape(3, 3) + 1.0
            blocks = (np.broadcast_to(m, (len(seg), 3, 3)).copy() for m in (1e3 * h, 5e2 * h, 1e3 * h.T))
            a.add_band_blocks(seg, *blocks)
            A = a.commit()
            x, y = A.createVecs()
            M = np.zeros((A.getSize()[0],) * 2)
            for i in range(len(M)):
                x.set(0.0)
                x.setValue(i, 1.0)
                x.assemble()
                A.mult(x, y)
                M[:, i] = y.array
            mats[k] = M
            x.destroy()
            y.destroy()
        finally:
            sim.close()
    C, R = mats["compiled"], mats["numpy"]
    assert np.abs(C - R).max() <= 1e-12 * np.abs(R).max()
    assert np.abs(R[120:123, 123:126]).max() > 1e2 and np.array_equal(R, R.T)     # the blocks are in, symmetric


def _vertices_in_the_head():
    """(the simulator of a 3-wisp hairball after 4 frames, its positions with every 7th free
    vertex moved 0.05 cm into the head, the head's centre and radius (with its margin)):
    the hairball has no vertex on the head by itself.  The caller closes the simulator."""
    from sim_helpers import small_hairball_config
    sim = build_simulator(small_hairball_config(n_wisps=3, frames=4).validate(), comm=MPI.COMM_SELF)
    sim.run(4)
    it = sim.integrator
    x = it.x.copy()
    c, R = it.head.sphere_center(it.t_next), it.head.radius + it.cfg.physics.head_margin
    for i in np.flatnonzero(it.free)[::7]:
        x[i] = c + (R - 0.05) * (x[i] - c) / np.linalg.norm(x[i] - c)
    return sim, x, c, R


@pytest.mark.parametrize("keep", [False, True])
def test_the_newton_system_takes_its_gradient_from_its_own_head_pass(keep):
    """The Newton system's gradient and matrix come from one pass of the head's penalty
    (the gradient had a pass of its own, the same values computed twice): with vertices
    on the head, the system's gradient equals grad G computed apart bit for bit, and the
    matrix has the head's blocks once (``keep``: the exact system that keeps its elements'
    diagonal, the shifted fallback's)."""
    sim, x, _, _ = _vertices_in_the_head()
    try:
        it = sim.integrator
        assert len(it._contact_terms(x, True)[1]) > 10
        g = it._assemble_system(x, 0, filter="none", keep=keep)
        assert np.array_equal(g, it.gradient(x))
        A = it.asm.mat.copy()
        it._assemble_system(x, 0, filter="none")
        assert A.equal(it.asm.mat)
    finally:
        sim.close()


def _dense(mat):
    """The sequential matrix ``mat`` as a dense array (its own values, no product)."""
    n = mat.getSize()[0]
    return mat.getValues(range(n), range(n))


def test_the_newton_system_adds_the_heads_blocks_and_gradient_once():
    """The head's share of the Newton system against the head kernel called apart: with
    vertices in the head, the matrix with head contact is the matrix without it plus
    :func:`head_contact.hessian`'s blocks of the active vertices on their diagonal, and the
    gradient the one without it plus :func:`head_contact.gradient`, bit for bit (the head's
    terms are added last).  Held for the three places that add the blocks: the fresh
    system, the one that keeps its elements' diagonal (the shifted fallback's) and its
    reuse at the same x with another mass shift (:meth:`Integrator._exact_assembly`).
    The gradient-and-matrix test above compares the system with itself assembled again, so
    blocks added twice by every assembly passed it."""
    from lc_petsc.elements import head_contact
    sim, x, c, R = _vertices_in_the_head()
    try:
        it = sim.integrator
        idx = np.flatnonzero(it.free & head_contact.active(x, c, R))
        assert len(idx) > 10
        k = it.cfg.physics.head_stiffness
        blocks = np.zeros((3 * len(x), 3 * len(x)))
        for v, h in zip(idx, head_contact.hessian(x[idx], c, R, k, filter="none")):
            blocks[3 * v:3 * v + 3, 3 * v:3 * v + 3] = h
        grad = np.zeros_like(x)
        grad[idx] = head_contact.gradient(x[idx], c, R, k)
        assert np.abs(blocks).max() > 1e4 and np.abs(grad).max() > 1e2       # the head's terms are not small

        def systems():
            """(grad G, matrix) fresh, kept and reused with the mass shifted by 0.5."""
            out = [(it._assemble_system(x, 0, filter="none"), _dense(it.asm.mat))]
            out.append((it._assemble_system(x, 0, filter="none", keep=True), _dense(it.asm.mat)))
            out.append((it._exact_assembly(x, 0, 0.5), _dense(it.asm.mat)))
            return out

        with_head = systems()
        it.contact = False
        try:
            without = systems()
        finally:
            it.contact = True
        assert not np.array_equal(without[0][1], without[2][1])             # the shift changed the matrix
        for (g, A), (g0, A0) in zip(with_head, without):
            assert np.array_equal(A, A0 + blocks)
            assert np.array_equal(g, g0 + grad)
    finally:
        sim.close()


def test_the_root_turns_vertex_terms_are_the_integrators_bit_for_bit():
    """The root turn's terms at x (``Integrator._turn_terms``: inertia and gravity in one
    compiled pass, ``compiled_turn.vertex_terms``, plus the head's) and
    ``_vertex_potentials`` equal grad G with a zero elastic gradient (``gradient``) and the
    per-vertex potentials in NumPy's expressions, bit for bit, with vertices in the head."""
    sim, x, _, _ = _vertices_in_the_head()
    try:
        it = sim.integrator
        g, head, per = it._turn_terms(x)
        assert head is not None and len(head[0]) > 10
        d = x - it.xhat
        want = np.where(it.free, 0.5 / it.dt ** 2 * it.scene.mass * np.sum(d * d, axis=1)
                        - np.sum(it.f_ext * x, axis=1), 0.0)
        e, idx = it._contact_terms(x, False, per_vertex=True)[:2]
        want[idx] += e
        assert np.abs(d).max() > 0.0 and np.abs(e).max() > 0.0
        np.testing.assert_array_equal(per, want)
        np.testing.assert_array_equal(it._vertex_potentials(x), want)
        np.testing.assert_array_equal(g, it.gradient(x, np.zeros_like(x)))
    finally:
        sim.close()
