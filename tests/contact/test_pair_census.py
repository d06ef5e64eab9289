"""scripts/pair_census.py: the per-frame census of contact pairs on a crafted frame."""

import importlib.util
from pathlib import Path

import numpy as np

from lc_petsc.crossings import segments

_spec = importlib.util.spec_from_file_location(
    "pair_census", Path(__file__).resolve().parents[2] / "scripts" / "pair_census.py")
pair_census = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(pair_census)


def test_census_counts_histogram_exemption_and_age():
    d0, k = 0.2, 1.0e3
    off = np.array([0, 3, 6, 9])
    base = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    # wisp 1 at 0.5 d0 above wisp 0 (2 parallel segments close to each -> pairs), wisp 2 far
    X = np.concatenate([base, base + [0, 0.5 * d0, 0], base + [0, 10.0, 0]])
    rest = np.concatenate([base, base + [0, 5.0, 0], base + [0, 10.0, 0]])
    seg, wisp = segments(off)
    wid = np.repeat(np.arange(3), 3)
    r, age = pair_census.frame_census(X, rest, seg, wisp, wid, d0, k, {})
    # segments 0-1, 1-2 of wisp 0 against 3-4, 4-5 of wisp 1: 4 pairs at d = 0.5 d0 (the
    # two diagonal ones touch at a shared end point, also 0.5 d0)
    assert r["pairs"] == 4 and r["exempt"] == 0
    assert r["hist"] == [0, 0, 0, 0, 0, 4, 0] and r["below_0.05"] == 0 and r["below_0.5"] == 0
    assert r["parallel"] == 4 and r["wisps"] == 2 and r["segments"] == 4
    np.testing.assert_allclose(r["penalty_force_sum"], 4 * k * 0.5 * d0)
    r2, _ = pair_census.frame_census(X, rest, seg, wisp, wid, d0, k, age)
    assert r2["kept_from_previous"] == 4 and r2["median_age"] == 2
    # the same pairs close at rest: exempt, not counted
    r3, _ = pair_census.frame_census(X, X, seg, wisp, wid, d0, k, {})
    assert r3["pairs"] == 0 and r3["exempt"] == 4
