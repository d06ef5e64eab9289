"""Head-sphere penalty: the exact Hessian (finite differences), the filtered one (its PSD
part), and the exact Newton's convergence with it on a strand resting on the head."""

import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.config import (MaterialConfig, PhysicsConfig, SceneConfig, SimConfig,
                             SolverConfig, TimeConfig)
from lc_petsc.elements import head_contact
from lc_petsc.studies.newton import iterations_to, run_history


def _points():
    rng = np.random.default_rng(4)
    c = np.array([1.0, -2.0, 0.5])
    x = c + rng.normal(size=(40, 3)) * 0.9
    return x, c, 2.0, 7.0e3


def test_exact_head_hessian_matches_finite_differences():
    x, c, R, k = _points()
    inside = head_contact.active(x, c, R)
    assert 5 < inside.sum() < 40                  # both sides of the sphere are tested
    H = head_contact.hessian(x, c, R, k, filter="none")
    h = 1e-6
    fd = np.stack([(head_contact.gradient(x + h * e, c, R, k)
                    - head_contact.gradient(x - h * e, c, R, k)) / (2 * h) for e in np.eye(3)],
                  axis=2)
    assert np.abs(fd - H).max() < 1e-6 * np.abs(H).max()
    assert np.array_equal(H[~inside], np.zeros((int((~inside).sum()), 3, 3)))


def test_active_is_a_positive_depth_bit_for_bit(monkeypatch):
    """active (no normals built: not through _geometry) is the depth > 0 of the
    penalty's geometry on random points, points at the sphere's radius to an ulp, the
    centre, NaN and infinity."""
    x, c, R, _ = _points()
    u = np.array([0.6, 0.0, -0.8])
    edge = [c + u * np.nextafter(R, s) for s in (0.0, np.inf)] + [c + u * R, c, c + 1e-300 * u,
                                                                  np.full(3, np.nan), np.full(3, np.inf)]
    x = np.concatenate([x, edge])
    with np.errstate(invalid="ignore"):         # the normals of NaN and infinity
        want = head_contact._geometry(x, c, R)[0] > 0
    monkeypatch.setattr(head_contact, "_geometry", None)
    got = head_contact.active(x, c, R)
    assert got.dtype == bool and np.array_equal(got, want)
    assert 5 < want.sum() < len(x) - 5 and want[-4] and want[-3] and not want[-2] and not want[-1]


def test_filtered_head_hessian_is_the_psd_part_of_the_exact_one():
    x, c, R, k = _points()
    exact = np.linalg.eigh(head_contact.hessian(x, c, R, k, filter="none"))
    projected = np.einsum("nij,nj,nkj->nik", exact[1], np.maximum(exact[0], 0.0), exact[1])
    filtered = head_contact.hessian(x, c, R, k)
    assert np.abs(filtered - projected).max() < 1e-9 * k
    assert np.linalg.eigvalsh(filtered).min() > -1e-9 * k
    # inside, the exact one has negative tangential curvature -k d / |x - c|
    inside = head_contact.active(x, c, R)
    assert (exact[0][inside, 0] < 0).all()


def test_head_hessian_bad_filter_is_error():
    x, c, R, k = _points()
    with pytest.raises(ValueError, match="head contact: unknown Hessian filter"):
        head_contact.hessian(x, c, R, k, filter="abs")


def test_exact_newton_with_exact_head_hessian_converges_quadratically():
    """A straight strand draped over the head (tests/test_sim_physics.py), resting from
    frame 7 on: exact_or_analytic reaches 1e-10 wisp lengths in at most 5 iterations per
    frame (measured 3-5; with the Gauss-Newton head Hessian the exact steps converge
    linearly: 4-8, median 7)."""
    cfg = SimConfig(scene=SceneConfig(kind="straight", n_vertices=30, n_pinned=2,
                                      direction=(1, 0, 0), segment_length=0.5),
                    material=MaterialConfig(youngs_modulus=1e7, root_radius=0.05, tip_radius=0.05),
                    physics=PhysicsConfig(terms=("stretch", "bend", "gravity", "head_collision"),
                                          head_radius=5.0, head_center=(8.0, -5.05, 0.0),
                                          head_stiffness=1e5),
                    time=TimeConfig(frames=20, newton_iterations=25),
                    solver=SolverConfig(filter="exact_or_analytic"))
    rows, _ = run_history(cfg.validate(), MPI.COMM_WORLD)
    its = iterations_to(rows, 1e-10)
    assert all(i is not None for i in its), its
    assert max(its[7:]) <= 5, its
