"""lc_petsc.pair_census / scripts/pair_census.py on a tiny frames.h5 with known pairs."""

import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from lc_petsc.pair_census import census_frames

ROOT = Path(__file__).resolve().parents[2]


def _frames(path, heights):
    """Three wisps, d0 = 1 (twice the 0.5 radius): wisp 0 straight along x at y = 0
    (4 vertices, 3 unit segments), wisp 1 the same at y = h per frame (2 at rest), wisp 2
    one segment along z through (1.5, -0.2, 0): rest-exempt against wisp 0 (3 pairs)."""
    x = np.arange(4.0)
    w0 = np.stack([x, 0 * x, 0 * x], axis=1)
    w2 = np.array([[1.5, -0.2, -1.0], [1.5, -0.2, 1.0]])

    def pose(h):
        return np.concatenate([w0, w0 + [0.0, h, 0.0], w2])
    with h5py.File(path, "w") as f:
        f["wisp_offsets"] = np.array([0, 4, 8, 10])
        f["rest_positions"] = pose(2.0)
        f["positions"] = np.stack([pose(h) for h in heights])
        f["radius"] = np.full(10, 0.5)
        f.attrs["config"] = json.dumps({"physics": {"strand_stiffness": 10.0}})


def test_census_counts_distances_and_ages(tmp_path):
    p = tmp_path / "frames.h5"
    _frames(p, [2.0, 0.6, 0.03, 2.0, 0.6])
    rows, d0, k = census_frames(p)
    assert (d0, k) == (1.0, 10.0)
    assert [r["pairs"] for r in rows] == [0, 10, 10, 0, 10]
    assert [r["exempt"] for r in rows] == [3] * 5
    # wisp 1 at 0.6: 7 parallel pairs at 0.6 d0, wisp 2 at 0.8 and 2 x sqrt(0.89)
    assert rows[1]["hist"] == [0, 0, 0, 0, 0, 7, 3]
    assert rows[1]["parallel"] == 7 and rows[1]["kept_from_previous"] == 0
    assert rows[1]["penalty_force_sum"] == pytest.approx(10.0 * (7 * 0.4 + 0.2 + 2 * (1 - 0.89 ** 0.5)))
    # at 0.03: 7 pairs held far inside, wisp 2 at 0.23 and 2 x sqrt(0.3029); all kept
    r = rows[2]
    assert r["hist"] == [0, 7, 0, 1, 0, 2, 0]
    assert (r["below_0.05"], r["below_0.25"], r["below_0.5"]) == (7, 8, 8)
    assert r["min_d_over_d0"] == pytest.approx(0.03)
    assert (r["kept_from_previous"], r["median_age"], r["age_ge_5"]) == (10, 2.0, 0)
    assert (r["segments"], r["wisps"]) == (7, 3)
    # released at frame 3: back at frame 4 with age 1
    assert rows[4]["kept_from_previous"] == 0 and rows[4]["median_age"] == 1.0
    assert [r["frame"] for r in census_frames(p, every=2)[0]] == [0, 2, 4]
    assert census_frames(p, thickness=0.5)[0][2]["pairs"] == 8
    with pytest.raises(ValueError, match="stride"):
        census_frames(p, every=0)


def test_census_script(tmp_path):
    p = tmp_path / "frames.h5"
    _frames(p, [2.0, 0.03])
    js = tmp_path / "c.json"
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "pair_census.py"), str(p),
                          "--json", str(js)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "frame   1:     10 pairs (exempt 3)" in out.stdout
    assert json.loads(js.read_text())["rows"][1]["below_0.05"] == 7
    bad = tmp_path / "bad.h5"
    bad.write_text("not hdf5")
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "pair_census.py"), str(bad)],
                         capture_output=True, text=True)
    assert out.returncode == 2 and "not a readable frames.h5" in out.stderr
