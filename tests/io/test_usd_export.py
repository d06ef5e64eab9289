"""USD export (lc_petsc.io.usd, drivers/to_usd.py, output.usd of the main job): frames.usdc
read back with Pixar's pxr: points exact to float32, counts, widths, primvars, time codes,
stage units and up axis, the head's animated transform, render-hair counts; the
converter command; a USD export that cannot be written loses nothing else."""

import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from mpi4py import MPI
from pxr import Usd, UsdGeom

from lc_petsc.batch import main
from lc_petsc.config import PhysicsConfig
from lc_petsc.io.frames import row_digest, vertex_digest
from lc_petsc.io.usd import export_failed, head_matrix, write_usd
from lc_petsc.scene import geometry
from lc_petsc.scene.kinematics import HeadMotion

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(Path(__file__).parent))
from sim_helpers import hairball_toml  # noqa: E402

N_HAIRS = 3


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A 5-wisp shaking hairball, 6 frames written every 2, with 3 render hairs per wisp."""
    d = tmp_path_factory.mktemp("usd_run")
    (d / "s.toml").write_text(hairball_toml(frames=6, output=f"every = 2\npreviews = false\n"
                                                              f"render_hairs = {N_HAIRS}"))
    assert main([str(d / "s.toml"), "--out", str(d / "out"), "--quiet"], comm=MPI.COMM_SELF) == 0
    return d / "out"


def _frames(out):
    with h5py.File(out / "frames.h5") as f:
        return {k: f[k][...] for k in ("positions", "time", "wisp_offsets", "rest_positions", "pinned")} | \
            {"config": json.loads(f.attrs["config"])}


def test_export_read_back(run):
    F = _frames(run)
    stage = Usd.Stage.Open(str(run / "frames.usdc"))
    assert UsdGeom.GetStageMetersPerUnit(stage) == 0.01
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    dt = F["config"]["time"]["dt"]
    assert stage.GetTimeCodesPerSecond() == pytest.approx(1.0 / (dt * 2), rel=1e-12)
    assert stage.GetFramesPerSecond() == stage.GetTimeCodesPerSecond()
    n = len(F["time"])
    assert n == 4 and stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == n - 1
    assert stage.GetDefaultPrim().GetPath() == "/Groom"
    c = UsdGeom.BasisCurves(stage.GetPrimAtPath("/Groom/wisps"))
    assert c.GetTypeAttr().Get() == "linear"
    assert list(c.GetCurveVertexCountsAttr().Get()) == np.diff(F["wisp_offsets"]).tolist()
    pts = c.GetPointsAttr()
    assert pts.GetTimeSamples() == list(range(n))
    for k in range(n):
        P = np.asarray(pts.Get(k))
        assert P.dtype == np.float32 and np.array_equal(P, F["positions"][k].astype(np.float32)), k
        # time code k is row k: its seconds are k / timeCodesPerSecond
        assert k / stage.GetTimeCodesPerSecond() == pytest.approx(F["time"][k], abs=1e-12)
    assert np.array_equal(np.asarray(pts.Get()), F["rest_positions"].astype(np.float32))   # default: rest
    # widths: 2 x the hairball radii (0.35 -> 0.07 along each 101-vertex wisp)
    radius = np.tile(geometry.tapered_radius(101, 0.35, 0.07), 5)
    assert c.GetWidthsInterpolation() == "vertex"
    assert np.array_equal(np.asarray(c.GetWidthsAttr().Get()), (2 * radius).astype(np.float32))
    with h5py.File(run / "frames.h5") as f:       # the radii the export reads
        assert np.allclose(f["radius"][...], radius, rtol=1e-15, atol=0)
    pv = UsdGeom.PrimvarsAPI(c.GetPrim())
    assert list(pv.GetPrimvar("wisp_index").Get()) == list(range(5))
    assert pv.GetPrimvar("wisp_index").GetInterpolation() == "uniform"
    assert np.array_equal(np.asarray(pv.GetPrimvar("pinned").Get()) != 0, F["pinned"])
    # extent holds every point at every frame
    for k in range(n):
        lo, hi = np.asarray(c.GetExtentAttr().Get(k))
        P = F["positions"][k]
        assert np.all(lo <= P.min(0)) and np.all(hi >= P.max(0))


def test_export_head_transform(run):
    """The head sphere's transform carries the pinned roots: M(t) applied to
    (x_rest - c) is each pinned vertex at t (the same rigid motion, independently)."""
    F = _frames(run)
    stage = Usd.Stage.Open(str(run / "frames.usdc"))
    head = UsdGeom.Sphere(stage.GetPrimAtPath("/Groom/head"))
    phys = F["config"]["physics"]
    assert head.GetRadiusAttr().Get() == phys["head_radius"]
    c = np.asarray(phys["head_center"])
    pin = F["pinned"]
    moved = 0
    for k in range(len(F["time"])):
        M = np.array(head.ComputeLocalToWorldTransform(k))
        local = F["rest_positions"][pin] - c
        world = local @ M[:3, :3] + M[3, :3]
        assert np.abs(world - F["positions"][k][pin]).max() < 1e-9, k
        moved += not np.allclose(M, np.eye(4))
    assert moved >= 2          # the head did turn


def test_head_matrix_convention():
    hm = HeadMotion(PhysicsConfig(head_motion="shake", head_center=(1.0, 2.0, 3.0), head_amplitude=0.4))
    p = np.array([0.3, -0.2, 0.9])
    M = head_matrix(hm, 2.1)
    assert np.allclose(np.append(p, 1.0) @ M, np.append(hm.pinned_positions(p + hm.center, 2.1), 1.0))


def test_export_render_hairs(run):
    F = _frames(run)
    stage = Usd.Stage.Open(str(run / "frames.usdc"))
    h = UsdGeom.BasisCurves(stage.GetPrimAtPath("/Groom/render_hairs"))
    counts = np.asarray(h.GetCurveVertexCountsAttr().Get())
    assert len(counts) == 5 * N_HAIRS and np.all(counts == 101)
    guide = np.asarray(UsdGeom.PrimvarsAPI(h.GetPrim()).GetPrimvar("guide_wisp").Get())
    assert guide.tolist() == np.repeat(np.arange(5), N_HAIRS).tolist()
    radius = np.tile(geometry.tapered_radius(101, 0.35, 0.07), 5)
    for k in (0, 3):
        H = np.asarray(h.GetPointsAttr().Get(k)).reshape(5, N_HAIRS, 101, 3)
        X = F["positions"][k].reshape(5, 1, 101, 3)
        d = np.linalg.norm(H - X, axis=-1)
        # within the wisp radius (spread 1), plus float32 rounding of |x| <= 60 cm
        assert np.all(d <= radius.reshape(5, 1, 101) + 1e-5)
        assert d.max() > 0.2 * radius.max()       # and not all on the guide


def _world(prim, attr, k):
    """Points of ``attr`` at time code ``k`` in world space (float64), as a DCC places them."""
    M = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(k), float)
    return np.asarray(attr.Get(k), float) @ M[:3, :3] + M[3, :3]


def test_a_groom_far_from_the_origin_keeps_its_detail(run, tmp_path):
    """The run moved 1e5 cm along x: its float32 points were off by up to 0.0039 cm (13%
    of a 0.03 cm strand radius).  Now they are relative to a double translate, which pxr
    applies: the world positions equal frames.h5 to float32 of the groom's own size."""
    shift = np.array([1e5, -3e4, 2e5])
    far = tmp_path / "far.h5"
    far.write_bytes((run / "frames.h5").read_bytes())
    with h5py.File(far, "r+") as f:
        f["positions"][...] = f["positions"][...] + shift
        f["rest_positions"][...] = f["rest_positions"][...] + shift
        # the moved rows' digests, as the writer makes them (a row read is checked against it)
        f["row_digest"][...] = [row_digest([vertex_digest(f["positions"][k], 0)], k, f["time"][k])
                                for k in range(f["time"].shape[0])]
    write_usd(far, tmp_path / "far.usdc")
    F, near = _frames(run), Usd.Stage.Open(str(run / "frames.usdc"))
    stage = Usd.Stage.Open(str(tmp_path / "far.usdc"))
    c = stage.GetPrimAtPath("/Groom/wisps")
    pts = UsdGeom.BasisCurves(c).GetPointsAttr()
    side = np.ptp(F["positions"], axis=1).max()
    for k in range(4):
        err = np.abs(_world(c, pts, k) - (F["positions"][k] + shift)).max()
        assert err <= 2.5 * side * 2.0 ** -24, (k, err)       # main: 0.0039 cm (0.0078 at 2e5)
        assert np.abs(np.asarray(pts.Get(k))).max() < 2.5 * side   # local points: the groom's size
    rest = _world(c, pts, Usd.TimeCode.Default())
    assert np.abs(rest - (F["rest_positions"] + shift)).max() <= 2.5 * side * 2.0 ** -24
    # the render hairs too: the near export's, moved by the shift
    h, hn = stage.GetPrimAtPath("/Groom/render_hairs"), near.GetPrimAtPath("/Groom/render_hairs")
    hp, hnp = UsdGeom.BasisCurves(h).GetPointsAttr(), UsdGeom.BasisCurves(hn).GetPointsAttr()
    assert np.abs(_world(h, hp, 3) - (_world(hn, hnp, 3) + shift)).max() < 1e-5
    # near the origin the translate is 0 and the points are the world's (readers that
    # ignore transforms still place them)
    assert np.abs(_world(near.GetPrimAtPath("/Groom/wisps"),
                         UsdGeom.BasisCurves(near.GetPrimAtPath("/Groom/wisps")).GetPointsAttr(), 2)
                  - np.asarray(UsdGeom.BasisCurves(near.GetPrimAtPath("/Groom/wisps")).GetPointsAttr().Get(2),
                               float)).max() == 0.0


def test_converter_matches_job_and_stride(run, tmp_path):
    """--stride 2 of 4 rows: samples 0 and 2, the stage ends at 2 (main: 3, past the last
    sample); --out into a missing folder creates it."""
    out = tmp_path / "new" / "conv.usda"
    p = subprocess.run([sys.executable, str(ROOT / "drivers" / "to_usd.py"), str(run / "frames.h5"),
                        "--out", str(out), "--render-hairs", "2", "--stride", "2", "--quiet"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "2 frames of 5 wisps, 10 render hairs" in p.stdout
    a = Usd.Stage.Open(str(out))
    b = Usd.Stage.Open(str(run / "frames.usdc"))
    pa = UsdGeom.BasisCurves(a.GetPrimAtPath("/Groom/wisps")).GetPointsAttr()
    pb = UsdGeom.BasisCurves(b.GetPrimAtPath("/Groom/wisps")).GetPointsAttr()
    assert pa.GetTimeSamples() == [0.0, 2.0]
    assert (a.GetStartTimeCode(), a.GetEndTimeCode()) == (0.0, 2.0)
    assert np.array_equal(np.asarray(pa.Get(2)), np.asarray(pb.Get(2)))
    ha = UsdGeom.BasisCurves(a.GetPrimAtPath("/Groom/render_hairs"))
    assert len(ha.GetCurveVertexCountsAttr().Get()) == 10
    # the first 2 hairs of each wisp are the job's first 2 (same seed, same stream)
    Ha = np.asarray(ha.GetPointsAttr().Get(2)).reshape(5, 2, 101, 3)
    Hb = np.asarray(UsdGeom.BasisCurves(b.GetPrimAtPath("/Groom/render_hairs")).GetPointsAttr().Get(2))
    assert np.array_equal(Ha, Hb.reshape(5, N_HAIRS, 101, 3)[:, :2])


def test_converter_errors(tmp_path):
    bad = tmp_path / "x.h5"
    with h5py.File(bad, "w") as f:
        f["positions"] = np.zeros((1, 4, 3))
    p = subprocess.run([sys.executable, str(ROOT / "drivers" / "to_usd.py"), str(bad)],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "not an lc_petsc frames file (no /time)" in p.stderr
    p = subprocess.run([sys.executable, str(ROOT / "drivers" / "to_usd.py"), str(tmp_path / "none.h5")],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "cannot open the frames file" in p.stderr
    assert not list(tmp_path.glob("*.usd*"))


def test_write_usd_argument_errors(run, tmp_path):
    with pytest.raises(ValueError, match="must end in .usdc, .usd or .usda"):
        write_usd(run / "frames.h5", tmp_path / "a.abc")
    with pytest.raises(ValueError, match="stride must be an integer >= 1"):
        write_usd(run / "frames.h5", tmp_path / "a.usdc", stride=0)
    with pytest.raises(ValueError, match="render hairs per wisp must be an integer >= 0"):
        write_usd(run / "frames.h5", tmp_path / "a.usdc", render_hairs=-1)
    assert not list(tmp_path.iterdir())


def test_job_usd_off_and_failure_keeps_outputs(tmp_path, capsys):
    (tmp_path / "s.toml").write_text(hairball_toml(frames=2, output="previews = false\nusd = false"))
    out = tmp_path / "out"
    out.mkdir()
    (out / "frames.usdc").write_text("stale")               # an earlier run's export goes
    assert main([str(tmp_path / "s.toml"), "--out", str(out), "--quiet"], comm=MPI.COMM_SELF) == 0
    assert not (out / "frames.usdc").exists()
    s = json.loads((out / "summary.json").read_text())
    assert "frames.usdc" not in s["output"]["files"] and s["output"]["usd_s"] == 0.0
    # a scene whose strands file vanished after the run: frames.h5's /radius suffices
    from lc_petsc.io.usd import export_run
    from lc_petsc.config import OutputConfig
    with h5py.File(out / "frames.h5", "r+") as f:
        cfg = json.loads(f.attrs["config"])
        cfg["scene"].update(kind="file", path=str(tmp_path / "gone.h5"))
        f.attrs["config"] = json.dumps(cfg)
    files, _ = export_run(OutputConfig(), out / "frames.h5", out)
    assert files == ["frames.usdc"]
    (out / "frames.usdc").unlink()
    # a frames file from before /radius: rebuilt from the vanished file, so no USD, a
    # warning, the rest intact
    with h5py.File(out / "frames.h5", "r+") as f:
        del f["radius"]
    files, _ = export_run(OutputConfig(), out / "frames.h5", out)
    assert files == [] and not list(out.glob("*.usdc"))
    assert "USD export failed, frames.h5 is intact" in capsys.readouterr().err
    with h5py.File(out / "frames.h5") as f:
        assert f["positions"].shape[0] == 3


def test_job_on_two_ranks_writes_the_same_export(run, tmp_path):
    """Under mpiexec -n 2 rank 0 writes frames.usdc once the collective frames.h5 is
    closed: the same curves as the 1-rank run, points to the frames' round-off."""
    from sim_helpers import MPI_ENV
    (tmp_path / "s.toml").write_text(hairball_toml(frames=6, output=f"every = 2\npreviews = false\n"
                                                                     f"render_hairs = {N_HAIRS}"))
    p = subprocess.run(["mpiexec", "--oversubscribe", "-n", "2", sys.executable,
                        str(ROOT / "drivers" / "simulate.py"), "s.toml", "--out", "two", "--quiet"],
                       capture_output=True, text=True, env=MPI_ENV, timeout=150, cwd=tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    a = Usd.Stage.Open(str(run / "frames.usdc"))
    b = Usd.Stage.Open(str(tmp_path / "two" / "frames.usdc"))
    for prim in ("/Groom/wisps", "/Groom/render_hairs"):
        ca, cb = UsdGeom.BasisCurves(a.GetPrimAtPath(prim)), UsdGeom.BasisCurves(b.GetPrimAtPath(prim))
        assert list(ca.GetCurveVertexCountsAttr().Get()) == list(cb.GetCurveVertexCountsAttr().Get())
        assert ca.GetPointsAttr().GetTimeSamples() == cb.GetPointsAttr().GetTimeSamples() == [0, 1, 2, 3]
        for k in range(4):
            assert np.abs(np.asarray(ca.GetPointsAttr().Get(k)) - np.asarray(cb.GetPointsAttr().Get(k))).max() < 1e-5


def test_a_failed_export_says_whether_frames_h5_is_there(tmp_path):
    # the output folder removed mid-run: the warning said "frames.h5 is intact (write it
    # later with drivers/to_usd.py ...)" about a file that was gone
    frames = tmp_path / "frames.h5"
    gone = export_failed(frames, "OSError: no such file")
    assert "is missing" in gone and "intact" not in gone and "to_usd.py" not in gone, gone
    frames.write_bytes(b"")
    kept = export_failed(frames, "OSError: disk full")
    assert "frames.h5 is intact" in kept and f"drivers/to_usd.py {frames}" in kept, kept


def _lose_a_chunk(src, dst, row):
    """A copy of frames.h5 ``src`` whose /positions chunk of ``row`` is missing, as in a
    file whose chunk index was damaged: libhdf5 reads the row as the fill value (NaN)
    without an error."""
    with h5py.File(src) as f, h5py.File(dst, "w") as g:
        for k, v in f.attrs.items():
            g.attrs[k] = v
        for k in f:
            if k != "positions":
                f.copy(k, g)
        pos = f["positions"]
        d = g.create_dataset("positions", shape=pos.shape, dtype=pos.dtype, chunks=(1,) + pos.shape[1:],
                             fillvalue=np.nan, maxshape=(None,) + pos.shape[1:])
        for r in range(pos.shape[0]):
            if r != row:
                d[r] = pos[r]


def test_a_row_missing_from_a_damaged_file_is_refused_by_every_reader(run, tmp_path):
    """Row 1 (frame 2) read as NaN: to_usd had written it as a frame (exit 0) and the
    crossing count had ended in a LinAlgError traceback; now every reader names the row."""
    from lc_petsc.crossings import check_run, count_frames
    from lc_petsc.io.previews import render_previews
    bad = tmp_path / "frames.h5"
    _lose_a_chunk(run / "frames.h5", bad, 1)
    with h5py.File(bad) as f:
        assert np.isnan(f["positions"][1]).all() and np.isfinite(f["positions"][2]).all()
    # the chunk index is looked up before any row is read (frames.index_problem)
    why = (r"/positions row 1 \(frame 2\): its chunk is missing from the chunk index \(a read returns the fill "
           r"value, NaN\): the file's chunk index \(which has no checksum in the HDF5 1.8 format\) is damaged")
    with pytest.raises(ValueError, match=why):
        write_usd(bad, tmp_path / "x.usdc")
    assert not list(tmp_path.glob("*.usd*"))
    p = subprocess.run([sys.executable, str(ROOT / "drivers" / "to_usd.py"), str(bad), "--quiet"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "row 1 (frame 2)" in p.stderr and "Traceback" not in p.stderr
    with pytest.raises(ValueError, match=why):
        count_frames(bad)
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "count_crossings.py"), str(bad)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "row 1 (frame 2)" in p.stderr and "Traceback" not in p.stderr
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "edge_strain.py"), str(bad)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "row 1 (frame 2)" in p.stderr and "Traceback" not in p.stderr
    assert "row 1 (frame 2)" in check_run(bad, MPI.COMM_SELF)["error"]
    with pytest.raises(ValueError, match=why):
        render_previews(bad, tmp_path / "prev", [1])


def _time_chunk_size(src, dst, size):
    """A copy of frames.h5 ``src`` whose /time chunk index entry (in a version-1 B-tree
    node, which has no checksum) says the chunk is ``size`` bytes: key = stored size (4
    bytes), filter mask (4), 2 offsets of 8, then the chunk's address."""
    dst.write_bytes(src.read_bytes())
    with h5py.File(dst) as f:
        addr = f["time"].id.get_chunk_info(0).byte_offset.to_bytes(8, "little")
    data = bytearray(dst.read_bytes())
    node = data.find(b"TREE")
    while data.find(addr, node, node + 4096) < 0:
        node = data.find(b"TREE", node + 4)
    key = data.find(addr, node) - 24
    data[key:key + 4] = size.to_bytes(4, "little")
    dst.write_bytes(bytes(data))


@pytest.mark.parametrize("size", [1, 1 << 30])
def test_a_damaged_time_index_is_named_before_time_is_read(run, tmp_path, size):
    """to_usd.py and head_depth.py read /time before the file's chunk index was checked:
    a /time chunk of stored size 1 crashed both (a segfault in libhdf5, exit -11), one of
    1 GB gave HDF5's own "Can't read data (addr overflow ...)".  Now the index is checked
    first and both say what is damaged."""
    bad = tmp_path / "frames.h5"
    _time_chunk_size(run / "frames.h5", bad, size)
    why = (f"{bad}: /time chunk at (0,): its chunk index entry is damaged (stored size {size} bytes, not "
           f"{8 * 4 + 4}; filter mask 0; at byte ")
    for script in ("drivers/to_usd.py", "scripts/head_depth.py"):
        p = subprocess.run([sys.executable, str(ROOT / script), str(bad)] + (["--quiet"] if "usd" in script else []),
                           capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)
        assert p.returncode == 2 and why in p.stderr and "Traceback" not in p.stderr, (script, p.returncode,
                                                                                          p.stderr[-800:])
    assert not list(tmp_path.glob("*.usd*"))
