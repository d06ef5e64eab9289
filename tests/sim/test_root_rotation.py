"""The root turn after a fixed count (``time.root_rotation``, lc_petsc/root_rotation.py;
docs/newton.md, "Fourteenth round")."""

import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.config import ConfigError, MaterialConfig, PhysicsConfig, SceneConfig, SimConfig, TimeConfig
from lc_petsc.elements import head_contact
from lc_petsc.root_rotation import root_pivots, turn
from lc_petsc.simulator import build_simulator
from tests.sim_helpers import run_positions, small_hairball_config

SELF = MPI.COMM_SELF


def test_the_pivot_is_the_last_of_a_wisps_leading_pins():
    offsets = np.array([0, 5, 10, 15, 20, 25])
    pinned = np.zeros(25, bool)
    pinned[0:3] = True            # wisp 0: held at its root -> pivot 2
    # wisp 1: no pin -> not turned
    pinned[11] = True             # wisp 2: a pin that is not the first vertex -> not turned
    pinned[15:20] = True          # wisp 3: all pinned -> nothing to turn
    pinned[20] = pinned[24] = True    # wisp 4: root and tip pinned -> not turned
    assert root_pivots(offsets, pinned).tolist() == [2, -1, -1, -1, -1]


def test_a_turn_is_rigid_about_the_pivot():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(8, 3))
    idx = np.arange(3, 8)
    theta = np.tile([0.3, -0.2, 0.5], (5, 1))
    y = turn(x, theta, np.full(5, 2), idx)
    assert np.array_equal(y[:3], x[:3])
    d0 = np.linalg.norm(x[2:, None] - x[None, 2:], axis=2)
    d1 = np.linalg.norm(y[2:, None] - y[None, 2:], axis=2)
    assert np.abs(d1 - d0).max() < 1e-14
    # a quarter turn about z takes (1, 0, 0) to (0, 1, 0)
    q = turn(np.array([[0.0, 0, 0], [1.0, 0, 0]]), np.array([[0, 0, np.pi / 2]]), np.array([0]), np.array([1]))
    assert np.allclose(q[1], [0.0, 1.0, 0.0], atol=1e-15)


def _settled(terms, frames=3):
    """A small shaking hairball after ``frames`` frames of the default, with the root
    turn set up: (simulator, the step's state set for G at the next step)."""
    cfg = small_hairball_config(n_wisps=3, frames=frames, terms=terms, root_rotation=True)
    sim = build_simulator(cfg.validate(), comm=SELF)
    sim.integrator.root_turn, turner = None, sim.integrator.root_turn
    sim.run()
    it = sim.integrator
    # G of the next step at its first iterate (xhat, dt and the head as the step sets them)
    it.dt, it.t_next, it.xhat = it.cfg.time.dt, it.t + it.cfg.time.dt, it.x + it.cfg.time.dt * it.v
    return sim, turner


@pytest.mark.parametrize("terms", [("stretch", "bend", "twist", "gravity"),
                                   ("stretch", "bend", "twist", "gravity", "head_collision")])
def test_the_model_is_Gs_slope_and_curvature_along_the_turns(terms):
    """b and A of the model equal G's first and second differences along each wisp's
    turns (the rotation curve, not a straight line: a linearised turn stretches the
    edges), to the differences' own error."""
    sim, turner = _settled(terms)
    try:
        it = sim.integrator
        x = it.xhat.copy()
        unit = np.where(it.free, it.scene.mass / it.dt ** 2, 0.0)
        b, A, _ = turner.model(x, it._turn_terms, unit)
        idx = turner.idx
        piv = turner.pivot[turner.wisp[idx]]

        def G(w, th):
            theta = np.zeros((len(turner.pivot), 3))
            theta[w] = th
            return it.incremental_potential(turn(x, theta[turner.wisp[idx]], piv, idx))

        h = 1e-4
        eye = np.eye(3)
        for w in range(len(turner.pivot)):
            G0 = G(w, np.zeros(3))
            slope = np.array([(G(w, h * e) - G(w, -h * e)) / (2 * h) for e in eye])
            curv = np.array([[(G(w, h * (e + f)) - G(w, h * (e - f)) - G(w, h * (f - e)) + G(w, -h * (e + f)))
                              / (4 * h * h) if k != m else (G(w, h * e) - 2 * G0 + G(w, -h * e)) / (h * h)
                              for m, f in enumerate(eye)] for k, e in enumerate(eye)])
            assert np.abs(b[w] - slope).max() <= 1e-5 * np.abs(b[w]).max() + 1e-6 * np.abs(A[w]).max()
            assert np.abs(A[w] - curv).max() <= 1e-4 * np.abs(A[w]).max()
    finally:
        sim.close()


def _rms(X, ref):
    return float(np.sqrt(np.mean(np.sum((X - ref) ** 2, axis=1))))


def test_the_root_turn_brings_a_fixed_count_near_the_converged_run():
    """Three filtered iterations leave the wisps turned short of the step's solution; the
    root turn takes half of that back at the same Newton count (3-wisp shaking hairball,
    10 frames, against Newton converged to 1e-9 cm: RMS 0.997 cm -> 0.476 cm)."""
    def run(**time):
        X, summ = run_positions(small_hairball_config(n_wisps=3, frames=10, **time).validate(), comm=SELF)
        return X, summ

    ref, _ = run(newton_iterations=100, newton_tol=1e-9)
    plain, s_plain = run()
    turned, s_turned = run(root_rotation=True)
    e_plain, e_turned = _rms(plain, ref), _rms(turned, ref)
    print(f"\nRMS distance to the converged run: 3 iterations {e_plain:.3e} cm, with the root turn "
          f"{e_turned:.3e} cm")
    assert sum(s_turned["newton_iterations"]) == sum(s_plain["newton_iterations"]) == 30
    assert e_turned < 0.55 * e_plain


def test_a_wisp_hanging_straight_is_turned_without_error():
    """A wisp on one line has no inertia about it (the turn's preconditioner P is
    singular: np.linalg.solve raised LinAlgError in frame 0).  Hanging straight under
    gravity it is at rest: 40 frames with the turn keep it within 1e-9 cm of the run
    without, straight and finite."""
    def run(turn):
        cfg = SimConfig(scene=SceneConfig(kind="wisp4c", n_vertices=20, perturbation="straighten"),
                        material=MaterialConfig(youngs_modulus=1e9, root_radius=0.1, tip_radius=0.05),
                        physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity")),
                        time=TimeConfig(frames=40, root_rotation=turn))
        sim = build_simulator(cfg.validate(), comm=SELF)
        try:
            sim.run()
            return sim.integrator.x.copy(), sim.integrator.root_turn
        finally:
            sim.close()
    plain, _ = run(False)
    turned, turner = run(True)
    assert turner is not None and np.all(np.isfinite(turned))
    assert np.abs(turned - plain).max() <= 1e-9


def test_the_root_turn_needs_a_fixed_count():
    with pytest.raises(ConfigError, match="time.root_rotation"):
        TimeConfig(root_rotation=True, newton_increment_tol=1e-6).validate()
    with pytest.raises(ConfigError, match="time.root_rotation must be true or false"):
        TimeConfig(root_rotation="yes").validate()
    TimeConfig(root_rotation=True).validate()


@pytest.mark.parametrize("terms", [("stretch", "bend", "twist", "gravity"),
                                   ("stretch", "bend", "twist", "gravity", "head_collision")])
def test_the_compiled_model_and_turn_are_numpys_bit_for_bit(terms):
    """The model's sums compiled (the default) or in NumPy (RootRotation's ``kernels``):
    the same b, A, P and turned positions, bit for bit, on the settled hairball pushed
    off its step's target; an unknown kernels name is a ValueError."""
    from lc_petsc.root_rotation import RootRotation
    sim, turner = _settled(terms)
    try:
        it = sim.integrator
        assert turner._turn_sums.__name__ == "turn_sums"
        stencils = {n: t.k for n, t in it.scene.terms.items()}
        ref = RootRotation(it.scene.offsets, it.scene.pinned, it.asm.elements, stencils, kernels="numpy")
        x = it.x + 0.01 * np.random.default_rng(2).standard_normal(it.x.shape) * it.free[:, None]
        unit = np.where(it.free, it.scene.mass / it.dt ** 2, 0.0)
        for got, want in zip(turner.model(x, it._turn_terms, unit), ref.model(x, it._turn_terms, unit)):
            assert np.abs(want).max() > 0.0
            np.testing.assert_array_equal(got, want)
        y = turner.step(x, it._turn_terms, unit, it._vertex_potentials)
        assert turner.turned == 3 and np.abs(y - x).max() > 1e-6
        np.testing.assert_array_equal(y, ref.step(x, it._turn_terms, unit, it._vertex_potentials))
        with pytest.raises(ValueError, match="kernels 'fortran': use one of compiled, numpy"):
            RootRotation(it.scene.offsets, it.scene.pinned, it.asm.elements, stencils, kernels="fortran")
    finally:
        sim.close()


def _far_turned_start(terms, angle):
    """The settled 3-wisp hairball with the step's inertial target xhat its own wisps
    turned by ``angle`` (rad) about their pivots: the turn G wants is far beyond where
    its quadratic model at x holds.  (simulator, turner, x, unit)"""
    sim, turner = _settled(terms)
    it = sim.integrator
    x = it.x.copy()
    idx = turner.idx
    axis = np.array([0.3, 0.4, 0.866])
    it.xhat = turn(x, np.tile(angle * axis / np.linalg.norm(axis), (len(idx), 1)),
                   turner.pivot[turner.wisp[idx]], idx)
    return sim, turner, x, np.where(it.free, it.scene.mass / it.dt ** 2, 0.0)


def _change(it):
    """Per vertex the change of the terms of one vertex of G from x to y."""
    return lambda x, y: it._vertex_potentials(y) - it._vertex_potentials(x)


def test_the_share_change_is_the_change_of_the_wisps_potentials():
    """RootRotation.share_change (the vertex terms and the elements across the root)
    equals the change of Integrator.wisp_potentials (every element) over a turn."""
    sim, turner, x, unit = _far_turned_start(("stretch", "bend", "twist", "gravity", "head_collision"), 2.5)
    try:
        it = sim.integrator
        y = turner.step(x, it._turn_terms, unit)
        exact = it.wisp_potentials(y) - it.wisp_potentials(x)
        cheap = turner.share_change(x, y, _change(it))
        assert np.abs(exact).min() > 1.0          # a real change on every wisp
        assert np.abs(cheap - exact).max() <= 1e-9 * np.abs(it.wisp_potentials(x)).max()
    finally:
        sim.close()


def test_the_share_change_takes_one_compiled_energy_call(monkeypatch):
    """share_change evaluates every term's across elements before and after the turn in
    one compiled pass (compiled.vertex_energy; three NumPy kernel calls before: the fixed
    per-call cost weighed on the 10-wisp hairball, docs/newton.md "Nineteenth round"),
    within round-off of the NumPy kernels' energies; the six central-difference turns of
    ``model`` are Rodrigues turns of the same angles."""
    from lc_petsc import root_rotation
    from lc_petsc.elements import bend, compiled, stretch, twist
    sim, turner, x, unit = _far_turned_start(("stretch", "bend", "twist", "gravity", "head_collision"), 2.5)
    try:
        it = sim.integrator
        y = turner.step(x, it._turn_terms, unit)
        calls = []
        real = compiled.vertex_energy
        monkeypatch.setattr(compiled, "vertex_energy", lambda *a: calls.append(1) or real(*a))
        cheap = turner.share_change(x, y, _change(it))
        assert len(calls) == 1
        # the reference: the NumPy kernels, each term's elements at y and at x
        ref = turner._sums(_change(it)(x, y) * turner.mask)
        kernels = {"stretch": stretch.energy, "bend": bend.energy, "twist": twist.energy}
        n = len(turner.near)
        assert set(turner.across) == set(kernels)
        for name, (start, rest, stiffness) in turner.across.items():
            assert len(start) >= len(turner.offsets) - 1      # at least one per wisp and term
            vertices = turner.near[start[:, None] + np.arange(compiled._K[name])]
            e = kernels[name](y[vertices], rest, stiffness) - kernels[name](x[vertices], rest, stiffness)
            ref += np.bincount(turner.wisp[vertices[:, 0]], e, minlength=len(ref))
            assert np.array_equal(turner.across2[name][0], np.concatenate([start, start + n]))
        assert np.abs(cheap - ref).max() <= 1e-12 * np.abs(ref).max()
        v = np.random.default_rng(0).standard_normal((4, 3))
        for j, (sign, e) in enumerate((s, e) for s in (1, -1) for e in np.eye(3)):
            theta = np.broadcast_to(sign * root_rotation.ANGLE_STEP * e, v.shape)
            assert np.abs(v @ turner.turns6[j] - root_rotation.rotate(v, theta)).max() <= 1e-15
    finally:
        sim.close()


def test_a_turn_evaluates_the_heads_penalty_twice(monkeypatch):
    """One root turn (model and guard, nothing halved) evaluates the head's penalty at x
    once for the model's gradient, Hessians and the guard's start, and once at the turned
    positions (three times before: the guard took x's again); the turned positions are
    those of a guard given fresh potentials at x."""
    sim, turner = _settled(("stretch", "bend", "twist", "gravity", "head_collision"))
    try:
        it = sim.integrator
        x = it.x + 0.001 * np.random.default_rng(1).standard_normal(it.x.shape) * it.free[:, None]
        # each wisp's first free vertex pressed into the head (its penalty active)
        c = it.head.sphere_center(it.t_next)
        first = turner.pivot + 1
        out = x[first] - c
        x[first] = c + out * (0.995 * (it.head.radius + it.cfg.physics.head_margin)
                              / np.linalg.norm(out, axis=1))[:, None]
        unit = np.where(it.free, it.scene.mass / it.dt ** 2, 0.0)
        assert len(it._contact_terms(x, False)[1]) > 0           # the head touches wisps
        fresh = turner.step(x, it._turn_terms, unit, it._vertex_potentials)
        assert turner.reduced == 0 and turner.turned == 3
        calls = []
        real = head_contact.active          # one call per pass of the head's penalty
        monkeypatch.setattr(head_contact, "active", lambda *a, **k: calls.append(1) or real(*a, **k))
        it.root_turn = turner
        y = it._last_turn(True, x)
        assert len(calls) == 2
        assert np.array_equal(y, fresh)
    finally:
        sim.close()


def test_a_turn_that_raises_a_wisps_share_of_G_is_cut():
    """With the inertial target 2.5 rad away G along a turn is far from its quadratic
    model at x (a cosine, not a parabola): the model's turn raises two of the three
    wisps' shares of G (by 6.6e3 and 2.3e3).  The guard halves those turns (then would
    drop them), so no share rises and both wisps end lower than the unguarded turn
    left them; the third wisp's turn is kept as it was."""
    sim, turner, x, unit = _far_turned_start(("stretch", "bend", "twist", "gravity", "head_collision"), 2.5)
    try:
        it = sim.integrator
        W0 = it.wisp_potentials(x)
        unguarded = it.wisp_potentials(turner.step(x, it._turn_terms, unit)) - W0
        assert turner.reduced == 0
        guarded = it.wisp_potentials(turner.step(x, it._turn_terms, unit, it._vertex_potentials)) - W0
        print(f"\nshare change per wisp: unguarded {unguarded}, guarded {guarded}")
        rose = unguarded > 1e3
        assert rose.tolist() == [False, True, True]
        assert turner.turned == 3 and turner.reduced == 2
        assert (guarded < -1e3).all()
        assert guarded[~rose] == unguarded[~rose]
    finally:
        sim.close()


def test_the_numpy_element_kernels_option_reaches_the_turn():
    """``-lc_element_kernels numpy`` (the NumPy reference kernels) runs the root turn's
    fixed work in NumPy too; the default compiles it.  Three frames of each give the same
    positions bit for bit (the compiled kernels keep NumPy's order of operations)."""
    from lc_petsc.config import SolverConfig
    out = {}
    for kernels in ("compiled", "numpy"):
        cfg = small_hairball_config(n_wisps=3, frames=3, root_rotation=True)
        cfg.solver = SolverConfig(options=f"-lc_element_kernels {kernels}")
        sim = build_simulator(cfg.validate(), comm=SELF)
        try:
            want = "turn_sums" if kernels == "compiled" else "turn_sums_numpy"
            assert sim.integrator.root_turn._turn_sums.__name__ == want
            sim.run()
            out[kernels] = sim.integrator.x.copy()
        finally:
            sim.close()
    np.testing.assert_allclose(out["numpy"], out["compiled"], rtol=0, atol=1e-9)


def test_a_turned_frame_times_the_turn_once_and_computes_the_head_once_per_time(monkeypatch):
    """The turn's two head passes (at x and at the turned positions) are timed with the
    turn as one ``update`` entry, not one ``collision`` entry each (the timer had been
    most of those small passes' samples), and the head's rotation is computed once per
    time asked (20 per frame before: every head pass, the first iterate and the frame
    end asked again).  The phases stay the run's: the turn's time is in ``update``."""
    from lc_petsc import timing
    from lc_petsc.scene import kinematics
    frames = 4
    cfg = small_hairball_config(n_wisps=3, frames=frames, root_rotation=True)
    sim = build_simulator(cfg.validate(), comm=SELF)
    try:
        it = sim.integrator
        entries, in_turn, rotations = [], [False], []
        real_call, real_rotation, real_step = timing.Timers.__call__, kinematics._rotation, it.root_turn.step
        monkeypatch.setattr(timing.Timers, "__call__",
                            lambda self, phase: entries.append((in_turn[0], phase)) or real_call(self, phase))
        monkeypatch.setattr(kinematics, "_rotation", lambda *a: rotations.append(a) or real_rotation(*a))

        def step(*a):
            in_turn[0] = True
            try:
                return real_step(*a)
            finally:
                in_turn[0] = False
        monkeypatch.setattr(it.root_turn, "step", step)
        heads = []
        real_active = head_contact.active   # one call per pass of the head's penalty
        monkeypatch.setattr(head_contact, "active", lambda *a: heads.append(in_turn[0]) or real_active(*a))
        update_before = sim.timers.cpu_dict()["update"]
        sim.run()
        assert it.frame == frames and it.cfg.time.newton_iterations == 3
        # per frame: the turn's two head passes (nothing halved), timed by no entry of their own
        assert sum(heads) == 2 * frames and it.root_turns_reduced == [0] * frames
        assert [p for inside, p in entries if inside] == []
        # the turn is one update entry per frame, besides the three iterations' updates
        assert sum(p == "update" for _, p in entries) == 4 * frames
        # one head pass per Newton iteration, for the gradient and the matrix, in one
        # collision entry (the gradient had had a pass and an entry of its own)
        assert len(heads) - sum(heads) == 3 * frames
        assert sum(p == "collision" for _, p in entries) == 3 * frames
        assert sim.timers.cpu_dict()["update"] > update_before
        # the times asked: 0 and each frame's end, once each, and the last frame's
        # t - dt (the step before's, for the carry with the head) 3 dt - dt, which is
        # not 2 dt to the bit (0.22294344764321833 against ...27)
        angles = sorted(float(angle) for _, angle in rotations)
        assert len(rotations) == frames + 2 and angles[2] != angles[3] and np.isclose(angles[2], angles[3])
    finally:
        sim.close()
