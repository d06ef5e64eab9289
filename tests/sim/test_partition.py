"""The partition stays local for any wisp order (``-lc_wisp_order spatial``, the
default): wisps are numbered along a Hilbert curve of their roots, ranks get contiguous
runs of that numbering, and outputs keep the scene's order.  Run serially and (the
mpi-marked tests) by tests/test_mpi_launch.py under mpiexec -n 2 and -n 3."""

from pathlib import Path

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc import parallel
from lc_petsc.config import (MaterialConfig, PhysicsConfig, SceneConfig, SimConfig, SolverConfig,
                             TimeConfig)
from lc_petsc.scene.sources import FileSource, ReorderedSource, wisp_roots
from lc_petsc.simulator import build_simulator

FRINGE = Path(__file__).resolve().parents[2] / "configs" / "data" / "fringe.h5"
comm = MPI.COMM_WORLD


def test_hilbert_order_walks_face_neighbours():
    """On a full 8 x 8 x 8 grid every step along the curve moves to a face neighbour."""
    g = np.arange(8.0)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    rng = np.random.default_rng(0)
    pts = pts[rng.permutation(len(pts))]
    order = parallel.hilbert_order(pts, bits=3)
    assert np.array_equal(np.sort(order), np.arange(len(pts)))
    steps = np.abs(np.diff(pts[order], axis=0)).sum(axis=1)
    assert np.all(steps == 1.0)
    # rotated and scaled copies of the same points: still a permutation, deterministic
    assert np.array_equal(parallel.hilbert_order(pts * 3.0 + 7.0, bits=3), order)
    with pytest.raises(ValueError, match="finite"):
        parallel.hilbert_order(np.array([[0.0, np.nan, 0.0]]))
    assert len(parallel.hilbert_order(np.zeros((0, 3)))) == 0


def test_order_is_a_clear_choice():
    src = FileSource(FRINGE)
    with pytest.raises(ValueError, match="-lc_wisp_order 'random'.*spatial.*input"):
        parallel.order_wisps(src, "random")
    same, order = parallel.order_wisps(src, "input")
    assert same is src and np.array_equal(order, np.arange(src.n_wisps))
    with pytest.raises(ValueError, match="permutation"):
        ReorderedSource(src, np.zeros(src.n_wisps, np.int64))


@pytest.mark.parametrize("max_runs", [32, 1])
def test_reordered_source_loads_the_scene_wisps(max_runs, monkeypatch):
    """Run by run or as a covering range: the same wisps, in the new order, with their
    scene numbers."""
    src = FileSource(FRINGE)
    monkeypatch.setattr(ReorderedSource, "MAX_RUNS", max_runs)
    order = np.random.default_rng(1).permutation(src.n_wisps)
    re = ReorderedSource(src, order)
    assert np.array_equal(re.sizes, src.sizes[order])
    batch = re.load(3, 11)
    assert batch.first_wisp == 3 and np.array_equal(batch.ids(), order[3:11])
    for j, w in enumerate(order[3:11]):
        one = src.load(int(w), int(w) + 1)
        a, b = batch.offsets[j], batch.offsets[j + 1]
        assert np.array_equal(batch.positions[a:b], one.positions)
        assert np.array_equal(batch.radius[a:b], one.radius)
        assert np.array_equal(batch.pinned[a:b], one.pinned)
    assert np.array_equal(wisp_roots(re), wisp_roots(src)[order])


def write_shuffled(path, perm):
    """The fringe groom with its wisps in the order ``perm`` (wisp j of the new file is
    wisp perm[j] of the fringe)."""
    with h5py.File(FRINGE, "r") as f:
        off = f["wisp_offsets"][:]
        data = {k: f[k][:] for k in ("positions", "radius", "pinned")}
    rows = np.concatenate([np.arange(off[w], off[w + 1]) for w in perm])
    sizes = np.diff(off)[perm]
    with h5py.File(path, "w") as f:
        for k, v in data.items():
            f[k] = v[rows]
        f["wisp_offsets"] = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    return rows


def _config(path, order, frames=4, contact=True):
    terms = ("stretch", "bend", "twist", "gravity") + (("strand_collision",) if contact else ())
    return SimConfig(scene=SceneConfig(kind="file", path=str(path)),
                     material=MaterialConfig(youngs_modulus=2.5e8),
                     # thicker than the fringe's closest wisps at rest (0.22 cm): contact from frame 0
                     physics=PhysicsConfig(terms=terms, strand_stiffness=1e5, strand_thickness=0.3),
                     time=TimeConfig(frames=frames),
                     solver=SolverConfig(options=f"-lc_wisp_order {order} -ksp_rtol 1e-12"))


def _run(cfg, c):
    sim = build_simulator(cfg, comm=c)
    try:
        sim.run()
        return sim.gather_positions(), sim.wisp_offsets(), sim.summary()
    finally:
        sim.close()


def test_shuffled_groom_gives_the_ordered_groom_run(tmp_path):
    """A groom with its wisps shuffled: the same motion as the ordered groom, wisp by
    wisp, with strand contact (both are numbered along the same curve), and frames in
    the shuffled file's own order.  (Serial: run inside the 3-rank MPI suite this
    comparison failed once on a loaded machine while it passes on its own on 2 and 3
    ranks; rank invariance with the spatial order is covered by test_mpi_sim.py and
    test_mpi_contact.py.)"""
    path, perm = tmp_path / "shuffled.h5", np.random.default_rng(5).permutation(24)
    write_shuffled(path, perm)
    with h5py.File(FRINGE, "r") as f:
        off = f["wisp_offsets"][:]
        rest = f["positions"][:]
    rows = np.concatenate([np.arange(off[w], off[w + 1]) for w in perm])
    X_ord, _, s_ord = _run(_config(FRINGE, "spatial"), MPI.COMM_SELF)
    X_shuf, off_shuf, _ = _run(_config(path, "spatial"), MPI.COMM_SELF)
    assert np.array_equal(off_shuf, np.concatenate([[0], np.cumsum(np.diff(off)[perm])]))
    assert np.abs(X_shuf - X_ord[rows]).max() <= 1e-10 * np.abs(X_ord).max()
    assert np.abs(X_ord - rest).max() > 0.1                        # it moved
    assert sum(s_ord["contact"]["pairs_per_frame"]) > 0


def _share_extent(source, mode, n_ranks):
    """Sum over ranks of the bounding-box diagonal of the roots of the rank's wisps."""
    src, _ = parallel.order_wisps(source, mode)
    roots = wisp_roots(src)
    ranges = parallel.partition(src.sizes, n_ranks)
    return sum(float(np.linalg.norm(np.ptp(roots[a:b], axis=0)))
               for a, b in zip(ranges[:-1], ranges[1:]))


@pytest.mark.parametrize("n_ranks", [2, 3, 4])
def test_spatial_order_keeps_rank_shares_compact(tmp_path, n_ranks):
    """With the spatial order the shuffled groom gets exactly the ordered groom's
    shares (the order depends on the roots only), about as compact as the fringe's own
    row-by-column order (measured 0.90-1.08x the sum of share diagonals on 2-4 ranks);
    in the file's order they spread over the whole patch (measured 1.49-1.71x)."""
    perm = np.random.default_rng(5).permutation(24)
    write_shuffled(tmp_path / "shuffled.h5", perm)
    ordered, shuffled = FileSource(FRINGE), FileSource(tmp_path / "shuffled.h5")
    ext = {"ordered": _share_extent(ordered, "input", n_ranks),
           "shuffled": _share_extent(shuffled, "input", n_ranks),
           "ordered_spatial": _share_extent(ordered, "spatial", n_ranks),
           "shuffled_spatial": _share_extent(shuffled, "spatial", n_ranks)}
    assert ext["shuffled"] > 1.4 * ext["ordered"], ext
    assert ext["shuffled_spatial"] == ext["ordered_spatial"], ext
    assert ext["shuffled_spatial"] <= 1.2 * ext["ordered"], ext


@pytest.mark.mpi
def test_user_layout_round_trip():
    """Rows move to the scene's order and back; the user layout is contiguous."""
    src = FileSource(FRINGE)
    order = np.random.default_rng(2).permutation(src.n_wisps)
    sizes = src.sizes
    inner_sizes = sizes[order]
    ranges = parallel.partition(inner_sizes, comm.size)
    r = comm.rank
    inner_off = np.concatenate([[0], np.cumsum(inner_sizes)])
    user_off = np.concatenate([[0], np.cumsum(sizes)])

    class Local:
        pass
    sc = Local()
    # every internal row carries its scene vertex number
    rows = np.concatenate([user_off[order[i]] + np.arange(sizes[order[i]])
                           for i in range(ranges[r], ranges[r + 1])]).astype(float)
    sc.x_rest = np.stack([rows, -rows, 2 * rows], axis=1)
    sc.pinned = rows.astype(np.int64) % 3 == 0
    sc.radius = rows + 0.5
    lay = parallel.UserLayout(comm, order, sizes, ranges, sc)
    expect = np.arange(lay.first_vertex, lay.first_vertex + lay.nv, dtype=float)
    assert np.array_equal(lay.x_rest[:, 0], expect) and np.array_equal(lay.x_rest[:, 1], -expect)
    assert np.array_equal(lay.pinned, expect.astype(np.int64) % 3 == 0)
    assert np.array_equal(lay.radius, expect + 0.5)
    assert np.array_equal(lay.from_user(lay.x_rest), sc.x_rest)
    assert comm.allreduce(lay.nv) == user_off[-1]
    assert comm.allgather(lay.first_vertex)[0] == 0
    # messages name wisps and vertices in the scene's numbering
    i = 5
    assert lay.scene_numbers((i, int(inner_off[i]) + 2)) == (int(order[i]), int(user_off[order[i]]) + 2)
