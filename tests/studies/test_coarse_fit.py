"""lc_petsc.studies.coarse_fit: how much of a difference coarse rigid turns explain
(scripts/fixed_count_errors.py; docs/newton.md, "Twenty-first round")."""

import numpy as np

from lc_petsc.root_rotation import rotate, turn
from lc_petsc.studies.coarse_fit import best_rotation, explained, turned_fit


def _wisp(n=13, seed=4):
    rng = np.random.default_rng(seed)
    return np.cumsum(rng.normal(size=(n, 3)), axis=0)


def test_the_best_rotation_is_the_rotation_that_made_the_points():
    a = _wisp()
    R = rotate(np.eye(3), np.tile([0.4, -1.1, 0.7], (3, 1))).T      # rotate's rows: R e_i
    b = a @ R.T
    assert np.abs(best_rotation(a, b) - R).max() < 1e-13
    assert abs(np.linalg.det(best_rotation(a, -b)) - 1.0) < 1e-13      # a rotation, not a reflection


def test_a_chain_of_rigid_pieces_is_explained_whole_and_a_stretch_is_not():
    """A wisp turned about its pivot, its outer half then turned about its middle vertex:
    the root turn alone leaves a part, the two pieces fitted as a chain none.  A
    stretch along the wisp is left by every rigid fit."""
    x = _wisp()
    n = len(x) - 1
    hinge = n // 2
    ref = turn(x, np.tile([0.2, 0.1, -0.3], (n, 1)), np.zeros(n, int), np.arange(1, n + 1))
    ref = turn(ref, np.tile([-0.5, 0.4, 0.2], (n - hinge, 1)), np.full(n - hinge, hinge),
               np.arange(hinge + 1, n + 1))
    assert np.abs(turned_fit(x, ref, [hinge]) - ref).max() < 1e-12
    assert np.sum((turned_fit(x, ref) - ref) ** 2) > 1e-2 * np.sum((x - ref) ** 2)
    # two wisps (pinned first vertex; the second all pinned: not counted), split by thirds
    offsets = np.array([0, len(x), len(x) + 3])
    pinned = np.r_[np.eye(1, len(x), 0, dtype=bool)[0], np.ones(3, bool)]
    run = np.vstack([x, np.zeros((3, 3))])
    out = explained(run, np.vstack([ref, np.ones((3, 3))]), offsets, pinned)
    assert np.isclose(out["total"], np.sum((ref - x) ** 2), rtol=1e-14, atol=0.0)
    assert np.isclose(out["root third"] + out["middle third"] + out["tip third"], out["total"], rtol=1e-14)
    assert out["2 rigid pieces"] < 1e-20
    assert out["root turn"] > 1e-2 * out["total"]
    stretched = x.copy()
    stretched[1:] = x[0] + 1.05 * (x[1:] - x[0])
    out = explained(np.vstack([x, np.zeros((3, 3))]), np.vstack([stretched, np.ones((3, 3))]), offsets, pinned)
    assert np.isclose(out["root turn"], out["total"], rtol=1e-12, atol=0.0)
    assert min(out["2 rigid pieces"], out["3 rigid pieces"]) > 0.25 * out["total"]
