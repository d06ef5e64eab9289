"""Hair kept out of the head at a frame's end (physics.head_push_out): what runs after
the push-out must not put a vertex back in, and a fast slide's straight path between
frames (what a viewer interpolates) must not cut under the scalp (docs/contact.md
"Hair and the head")."""

import numpy as np
import pytest
from mpi4py import MPI

import lc_petsc.simulator as simmod
from lc_petsc.config import MaterialConfig, PhysicsConfig, SceneConfig, SimConfig, TimeConfig
from lc_petsc.contact import SEPARATION_STRAIN
from lc_petsc.crossings import count_crossings
from lc_petsc.elements import head_contact
from lc_petsc.frame_end import FrameEnd
from lc_petsc.scene.kinematics import HeadMotion
from lc_petsc.scene.sources import ArraySource
from lc_petsc.predictors import project_rest_lengths
from sim_helpers import falling_strand, head_figures, small_hairball_config

R = 5.0                 # head sphere about the origin
PHI = 0.5               # polar angle of the draped wisp's tip
LIFT = head_contact.LIFT_RADII
ALONG = 0.6             # where A crosses the path of B's last edge


def draped_source(blocker):
    """Wisp B draped from the head's top (pinned root on the y axis) down to polar angle
    PHI on the sphere, 4 vertices; wisp A, all pinned, 4 vertices along the radius
    through the midpoint of the chord of B's last edge's point ALONG when B turns by
    ``blocker`` rad about y (None: A far away): A crosses the surface that edge sweeps
    inside it, so a lift of the tip by a few strand radii still meets it."""
    pol = np.linspace(0.0, PHI, 4)
    B = R * np.stack([np.sin(pol), np.cos(pol), np.zeros(4)], 1)
    if blocker is None:
        A = np.stack([np.linspace(20.0, 21.5, 4), np.zeros(4), np.zeros(4)], 1)
    else:
        p = B[-2] + ALONG * (B[-1] - B[-2])
        mid = 0.5 * (p + p @ turn(blocker).T)
        A = np.outer(np.linspace(4.4, 5.2, 4), mid / np.linalg.norm(mid))
    return ArraySource(np.concatenate([A, B]), [0, 4, 8], pinned=[True] * 5 + [False] * 3,
                       root_radius=0.05, tip_radius=0.05)


def turn(psi):
    """The rotation by ``psi`` about y."""
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def draped_sim(monkeypatch, blocker, mode="ccd"):
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: draped_source(blocker))
    cfg = SimConfig(scene=SceneConfig(kind="straight"), material=MaterialConfig(youngs_modulus=1e9),
                    physics=PhysicsConfig(terms=("stretch", "bend", "head_collision", "strand_collision"),
                                          head_radius=R, head_center=(0.0, 0.0, 0.0), strand_thickness=0.2,
                                          strand_contact_mode=mode),
                    time=TimeConfig(frames=1, length_projection=True))
    sim = simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
    sim.integrator.frame_end.begin_step(cfg.time.dt)     # the frame end's head sphere (static)
    return sim


def test_frame_end_path_check_leaves_no_vertex_in_the_head(monkeypatch):
    """B's free part turns 3 cm (at its tip) along the scalp and meets A, embedded in the
    scalp across the middle of its path: the strand path check holds B back on its
    straight path, whose chord cuts under the scalp.  Before scalp53 the tip ended 0.226
    cm deep (4.5 strand radii, allowed 0.033); since, it was pushed out after the path
    check, and its path from the last frame then went 0.039 cm deep (A crossing the tip's
    own path: 0.036); now the frame end lifts before each path check: every free vertex
    and every path within the allowed depth, at rest length, without a crossing."""
    sim = draped_sim(monkeypatch, 3.0 / (R * np.sin(PHI)))
    try:
        itg, sc = sim.integrator, sim.scene
        free = np.flatnonzero(~sc.pinned)
        x_old = sim.x.copy()
        x = x_old.copy()
        x[free] = x_old[free] @ turn(3.0 / (R * np.sin(PHI))).T
        assert np.allclose(np.linalg.norm(x[free], axis=1), R)        # both ends on the scalp
        deep = itg.strand.measure(x)[1]
        out = itg.frame_end.collision_free_end(x_old, x, itg.head.rigid_motion(0.0, itg.frame_end.t_next), deep, 0.0)[0]
        depth = R - np.linalg.norm(out[free], axis=1)
        allow = itg.frame_end.allowed_depth[free]
        assert np.all(depth <= allow + 1e-12), (depth, allow)
        assert np.all(path_depth(x_old, out, free) <= allow + 1e-12), path_depth(x_old, out, free)
        assert np.linalg.norm(out[free[-1]] - x[free[-1]]) > 1.0           # it was held back
        edge = np.linalg.norm(np.diff(out[free[0] - 1:free[-1] + 1], axis=0), axis=1)
        rest = np.linalg.norm(np.diff(x_old[free[0] - 1:free[-1] + 1], axis=0), axis=1)
        assert np.abs(edge / rest - 1).max() < 1e-9
        assert count_crossings(x_old, out, sc.offsets)["crossings"] == 0
    finally:
        sim.close()


def test_fast_slide_path_kept_out_without_strain():
    """The falling strand on a head shaking with a 0.5 s period: the part lying on the
    scalp slides along it, 1.5-2 cm a frame, and the straight path between two frames
    cuts under it (on main: 26 vertex paths through in 6 of 20 steps, 0.123 cm deep for
    a 0.05 cm strand, lifts of up to 1 radius leaving edges 1.27% long, largest kinetic
    energy 203.3).  The lift of up to LIFT_RADII radii in rounds with the length
    projection mends all of them at the rest lengths, without a kick (213.4: the
    lifted hair takes another course, its velocity leaves the lift out)."""
    cfg = falling_strand(dict(head_motion="shake", head_period=0.5, head_amplitude=0.5),
                         dict(frames=20, length_projection=True))
    sim = simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
    try:
        ratio, through, ke, x = head_figures(sim)
        assert through == 0
        assert max(ratio) <= 1.0 and max(ratio) > 0.5, max(ratio)     # it does rest on the head
        edge = np.linalg.norm(np.diff(x, axis=0), axis=1)
        assert np.abs(edge / 0.5 - 1).max() < 1e-9
        assert max(ke) < 225.0, max(ke)
    finally:
        sim.close()


@pytest.mark.parametrize("motion, frames", [("static", 10), ("translate", 5)])
def test_strand_without_a_pinned_vertex_kept_out(motion, frames):
    """The falling strand with no pinned vertex (the length projection keeps its
    momentum with a mean shift, which took pushed vertices back in): on main 3.91 strand
    radii deep (frame 7) on the still head and 1.43 (frame 3) on the head translating at
    30 cm/s; now within the radius, at the rest lengths."""
    cfg = falling_strand(dict(head_motion=motion, head_velocity=(0.0, 30.0, 0.0)),
                         dict(frames=frames, length_projection=True), n_pinned=0)
    sim = simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
    try:
        ratio, _, _, x = head_figures(sim)
        assert max(ratio) <= 1.0 and max(ratio) > 0.5, max(ratio)
        edge = np.linalg.norm(np.diff(x, axis=0), axis=1)
        assert np.abs(edge / 0.5 - 1).max() < 1e-9
    finally:
        sim.close()


def slid_draped(monkeypatch, slide, blocker):
    """(sim, x_old, x): the draped wisp B turned about y so that its tip slides ``slide``
    cm along the scalp (both ends on it), with A across that path (``blocker``) or far."""
    psi = slide / (R * np.sin(PHI))
    sim = draped_sim(monkeypatch, psi if blocker else None)
    free = np.flatnonzero(~sim.scene.pinned)
    x_old = sim.x.copy()
    x = x_old.copy()
    x[free] = x_old[free] @ turn(psi).T
    return sim, x_old, x


def path_depth(x_old, x, free):
    """The deepest point of each free vertex's straight path x_old -> x in the head."""
    return head_contact.segment_depth(x_old[free], x[free], R)[0]


@pytest.mark.parametrize("blocker", [False, True])
def test_frame_end_keeps_paths_out_of_the_head(monkeypatch, blocker):
    """The frame end's input has B's tip sliding 1.5 cm along the scalp, whose straight
    path cuts 0.055 cm under it (strand radius 0.05, allowed 0.033), as after a
    separation move along the scalp.  On main the frame end pushed vertices out but did
    not lift paths: the tip's path stayed 0.0547 cm deep.  Now each round lifts before
    its path check: every path within the allowed depth, 0 crossings, rest lengths;
    with A across the path the tip is held back on its lifted path and keeps only that
    fraction of its lift, which is what the velocity leaves out (on main all of it)."""
    sim, x_old, x = slid_draped(monkeypatch, 1.5, blocker)
    try:
        itg, sc = sim.integrator, sim.scene
        free = np.flatnonzero(~sc.pinned)
        assert path_depth(x_old, x, free)[-1] > 0.054
        made = []
        lift = itg.frame_end.lift_head_paths
        monkeypatch.setattr(itg.frame_end, "lift_head_paths",
                            lambda *a: (lambda r: (made.append(r[1]), r)[1])(lift(*a)))
        deep = itg.strand.measure(x)[1]
        motion = itg.head.rigid_motion(0.0, itg.frame_end.t_next)
        out, *_, kept = itg.frame_end.collision_free_end(x_old, x, motion, deep, 0.0)
        allow = itg.frame_end.allowed_depth[free]
        assert np.all(path_depth(x_old, out, free) <= allow + 1e-12), path_depth(x_old, out, free)
        assert np.all(R - np.linalg.norm(out[free], axis=1) <= allow + 1e-12)
        edge = np.linalg.norm(np.diff(out[free[0] - 1:free[-1] + 1], axis=0), axis=1)
        rest = np.linalg.norm(np.diff(x_old[free[0] - 1:free[-1] + 1], axis=0), axis=1)
        # the separation (A held B back to its floor) keeps edges within SEPARATION_STRAIN
        assert np.abs(edge / rest - 1).max() <= (SEPARATION_STRAIN if blocker else 0.0) + 1e-9
        assert count_crossings(x_old, out, sc.offsets)["crossings"] == 0
        tip = free[-1]
        made = sum(m for m in made if m is not None)
        assert np.linalg.norm(made[tip]) > 0.04                # lifted (about one radius)
        if blocker:
            assert np.linalg.norm(out[tip] - x[tip]) > 0.8      # held back on its path
            # the path checks' fractions beta times the lift (1.0 on main)
            beta = np.linalg.norm(kept[tip]) / np.linalg.norm(made[tip])
            assert 0.2 < beta < 0.8, beta
            np.testing.assert_allclose(kept[tip], beta * made[tip], rtol=1e-12)
        else:
            np.testing.assert_array_equal(kept, made)
    finally:
        sim.close()


def test_keep_lengths_projects_only_the_touched_wisps():
    """FrameEnd.keep_lengths runs the length projection around the head on the touched wisps'
    vertices only: the same bits as projecting every wisp and keeping theirs (what it
    did before), with the others' bits untouched."""
    cfg = small_hairball_config(n_wisps=6, frames=1, length_projection=True)
    sim = simmod.build_simulator(cfg, comm=MPI.COMM_SELF)
    try:
        itg, sc = sim.integrator, sim.scene
        itg.frame_end.begin_step(cfg.time.dt)     # the frame end's head sphere
        rng = np.random.default_rng(5)
        c, Rh, allow = itg.frame_end.head_sphere()
        x = sim.x + rng.normal(scale=0.3, size=sim.x.shape) * (~sc.pinned)[:, None]
        y = x - c                   # some free vertices well inside the head
        x[::7] = c + y[::7] * ((Rh - 0.5) / np.linalg.norm(y[::7], axis=1))[:, None]
        x[sc.pinned] = sim.x[sc.pinned]
        moved = np.flatnonzero(~sc.pinned & (np.arange(sc.nv) >= sc.offsets[2]) & (np.arange(sc.nv) < sc.offsets[4]))
        moved = moved[::5]
        full = project_rest_lengths(x, itg.free, sc.offsets, itg.rest_edge, sc.mass, itg.frame_end.head_sphere())
        touched = np.isin(itg.vertex_wisp, itg.vertex_wisp[moved])
        expect = x.copy()
        expect[touched] = full[touched]
        out = itg.frame_end.keep_lengths(x, moved)
        assert touched.sum() < sc.nv and np.abs(out[touched] - x[touched]).max() > 0.01
        np.testing.assert_array_equal(out, expect)
    finally:
        sim.close()


@pytest.mark.parametrize("slide, later, mended", [(1.5, 0.6, True), (2.0, 0.6, False)])
def test_lifts_of_a_step_add_up_to_at_most_lift_radii(monkeypatch, slide, later, mended):
    """Two rounds of the head's frame end in one step (:meth:`FrameEnd.head_end`), the wisp slid
    a further ``later`` cm along the scalp between them (as a separation or path check
    moves it): each round's lift used to be bounded from where the vertex then was, so
    after a first lift of 3.2 radii (a 2 cm slide) the second took B's tip 6.89 radii
    above its height before the first round.  Now all the step's lifts together keep it
    within LIFT_RADII radii of that height; a path that would need more is left (to the
    warning), one that needs less (1.0 radius, then 3.75 in all) is still mended."""
    sim, x_old, x = slid_draped(monkeypatch, slide, False)
    try:
        itg = sim.integrator
        free = np.flatnonzero(~sim.scene.pinned)
        tip, r = free[-1], sim.scene.radius[free]
        height = np.linalg.norm(x[free], axis=1)
        x1, lifted = itg.frame_end.head_end(x_old, x, 0.0)
        first = (np.linalg.norm(x1[tip]) - height[-1]) / r[-1]
        assert first > (3.0 if not mended else 0.9), first
        x2 = x1.copy()
        x2[free] = x1[free] @ turn(later / (R * np.sin(PHI))).T
        out = itg.frame_end.head_end(x_old, x2, 0.0, lifted)[0]
        gain = (np.linalg.norm(out[free], axis=1) - height) / r
        assert gain.max() <= head_contact.LIFT_RADII + 1e-9, gain
        tip_path = path_depth(x_old, out, free)[-1]
        if mended:       # (the last length projection moves the lifted tip back by 2e-6 cm)
            assert gain[-1] > 3.5 and tip_path <= itg.frame_end.allowed_depth[tip] + 1e-5, (gain, tip_path)
        else:
            assert tip_path > 0.08, tip_path            # it needs more than the room left
    finally:
        sim.close()


def test_lift_room_counts_from_the_sphere_for_a_vertex_under_it():
    """The step's lift budget (FrameEnd.lift_room): LIFT_RADII strand radii above a
    vertex's distance from the head's centre before the step's first lift round, but
    above the sphere (radius + margin) for a vertex that was under it then: its later
    rise onto the sphere (a push-out) is not a lift.  Counted from its depth (lift54's
    first version), a tip 0.84 radii deep was refused the 3.2 radii its path needed (3
    paths through the head in 2 steps of the soft hairball).  Three vertices on rays
    from the centre: a pinned root on the sphere, one 0.84 radii under it, one 1.5
    radii above it; radii 0.05, 0.07, 0.1."""
    margin, dt = 0.3, 1.0 / 30.0
    head = HeadMotion(PhysicsConfig(head_radius=R, head_center=(0.0, 0.0, 0.0), head_margin=margin))
    Rs = R + margin                     # the sphere the push-out and the lift keep to
    r = np.array([0.05, 0.07, 0.1])
    dirs = np.array([[0.0, 1.0, 0.0], [0.1, 1.0, 0.0], [0.2, 1.0, 0.0]])
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    x = dirs * np.array([Rs, Rs - 0.84 * r[1], Rs + 1.5 * r[2]])[:, None]
    free = np.array([False, True, True])
    rest_edge = np.linalg.norm(np.diff(x, axis=0), axis=1)
    fe = FrameEnd(MPI.COMM_SELF, head, None, free, np.array([0, 3]), np.ones(3), r, rest_edge, np.zeros(3, int),
                  head_collision=True, margin=margin, push_out=True, separation=False, length_projection=False)
    fe.begin_step(dt)
    room = fe.lift_room(x)
    # under the sphere: 4 radii above it, 4.84 above where it is; above it: 4 radii
    np.testing.assert_allclose(room[1:] / r[1:], [LIFT + 0.84, LIFT], rtol=1e-12)
    # pushed onto the sphere and the other lifted 1 radius: the push spends nothing
    y = x.copy()
    y[1] = dirs[1] * Rs
    y[2] = dirs[2] * (Rs + 2.5 * r[2])
    np.testing.assert_allclose(fe.lift_room(y)[1:] / r[1:], [LIFT, LIFT - 1.0], rtol=1e-12)
    # the next step measures from where its vertices are then
    fe.begin_step(2 * dt)
    np.testing.assert_allclose(fe.lift_room(y)[1:] / r[1:], [LIFT, LIFT], rtol=1e-12)


def test_penalty_frame_end_lifts_after_the_separation(monkeypatch):
    """Penalty mode (separation on), one step of the draped wisp at rest, whose
    separation moves it 1.5 cm along the scalp (as the soft hairball's separation moved
    lifted tips, docs/contact.md "The frame end and the head agree"): the tip's straight
    path from the last frame then cuts 0.055 cm under the scalp (allowed 0.033).  Before
    head54 (cf91ae9) nothing ran after the separation and the frame kept that path; now
    the head's push-out and lift follow it: every path and vertex within the allowed
    depth, B at its rest lengths, and the velocity without the lift (no outward kick)."""
    sim = draped_sim(monkeypatch, None, mode="penalty")
    try:
        itg, sc = sim.integrator, sim.scene
        assert sim.config.physics.strand_separation
        free = np.flatnonzero(~sc.pinned)
        x_old = sim.x.copy()
        slid = x_old.copy()
        slid[free] = x_old[free] @ turn(1.5 / (R * np.sin(PHI))).T
        assert path_depth(x_old, slid, free)[-1] > 0.054
        seen = []

        def separate(x, pairs, deep, dmin):         # the wisp, at rest, moved along the scalp
            seen.append(np.abs(x - x_old).max())
            y = x.copy()
            y[free] = x[free] @ turn(1.5 / (R * np.sin(PHI))).T
            return y, pairs, deep, dmin, 0
        monkeypatch.setattr(itg.frame_end, "separate", separate)
        sim.step()
        out, allow = sim.x, itg.frame_end.allowed_depth[free]
        assert seen and seen[0] < 1e-6, seen                 # Newton left it where it was
        assert np.all(path_depth(x_old, out, free) <= allow + 1e-5), path_depth(x_old, out, free)
        assert np.all(R - np.linalg.norm(out[free], axis=1) <= allow + 1e-12)
        tip = free[-1]
        assert np.linalg.norm(out[tip]) - R > 0.04               # lifted (about one radius)
        edge = np.linalg.norm(np.diff(out[free[0] - 1:free[-1] + 1], axis=0), axis=1)
        rest = np.linalg.norm(np.diff(x_old[free[0] - 1:free[-1] + 1], axis=0), axis=1)
        assert np.abs(edge / rest - 1).max() < 1e-9
        # the velocity leaves the lift out (its move / dt: 1.5 cm/s at the tip): the slide's
        kick = np.abs(itg.v - (slid - x_old) / sim.config.time.dt).max()
        assert kick < 1e-3 < np.linalg.norm(out[tip] - slid[tip]) / sim.config.time.dt, kick
    finally:
        sim.close()
