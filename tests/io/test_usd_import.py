"""USD import (scene.kind = "usd", lc_petsc.scene.usd_source): hand-made BasisCurves files
(linear with widths and a pinned primvar; cubic bezier, bspline and catmullRom resampled
by their basis against independent evaluations; units, up axis and transforms), bad
inputs with clear errors, and the round trip export -> import -> simulate."""

import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from mpi4py import MPI
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from lc_petsc.batch import main
from lc_petsc.config import ConfigError, config_from_dict
from lc_petsc.scene.sources import ArraySource, source_from_config
from lc_petsc.scene.usd_source import UsdSource

sys.path.insert(0, str(Path(__file__).parent))
from sim_helpers import hairball_toml, run_positions  # noqa: E402


def _curves(path, counts, points, *, type_="linear", basis=None, wrap=None, widths=None,
            interp=None, pinned=None, mpu=None, up=None, xform=None, prim="/groom/curves", time=None):
    stage = Usd.Stage.CreateNew(str(path))
    if mpu is not None:
        UsdGeom.SetStageMetersPerUnit(stage, mpu)
    if up is not None:
        UsdGeom.SetStageUpAxis(stage, up)
    parent = UsdGeom.Xform.Define(stage, prim.rsplit("/", 1)[0])
    if xform is not None:
        parent.AddTransformOp().Set(Gf.Matrix4d(np.asarray(xform).tolist()))
    c = UsdGeom.BasisCurves.Define(stage, prim)
    c.CreateTypeAttr(type_)
    if basis:
        c.CreateBasisAttr(basis)
    if wrap:
        c.CreateWrapAttr(wrap)
    c.CreateCurveVertexCountsAttr(Vt.IntArray(list(map(int, counts))))
    t = Usd.TimeCode.Default() if time is None else time
    c.CreatePointsAttr().Set(Vt.Vec3fArray.FromNumpy(np.asarray(points, np.float32)), t)
    if widths is not None:
        c.CreateWidthsAttr(Vt.FloatArray(list(map(float, widths))))
        c.SetWidthsInterpolation(interp or "vertex")
    if pinned is not None:
        tname, values, pinterp = pinned
        pv = UsdGeom.PrimvarsAPI(c.GetPrim()).CreatePrimvar("pinned", tname, pinterp)
        pv.Set(values)
    stage.GetRootLayer().Save()
    return path


def _polyline(n, x0=0.0, z=0.0):
    s = np.arange(n, dtype=float)
    return np.column_stack([x0 + 0.3 * np.sin(s), -0.5 * s, z + 0.3 * np.cos(s)])


def test_linear_with_widths_and_pinned_primvar(tmp_path):
    P = np.concatenate([_polyline(6), _polyline(5, x0=2.0)])
    w = np.linspace(0.2, 0.1, 11)
    pin = [1, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0]
    f = _curves(tmp_path / "a.usda", [6, 5], P, widths=w,
                pinned=(Sdf.ValueTypeNames.IntArray, Vt.IntArray(pin), "vertex"))
    s = UsdSource(f)
    assert s.n_wisps == 2 and s.sizes.tolist() == [6, 5]
    assert np.array_equal(s.positions, P.astype(np.float32).astype(float))
    assert np.allclose(s.radius, w / 2, rtol=1e-7)
    assert s.pinned.tolist() == [bool(p) for p in pin]
    b = s.load(1, 2)
    assert b.offsets.tolist() == [0, 5] and b.pinned.tolist() == [True] + [False] * 4


def test_linear_defaults_units_up_axis_and_transform(tmp_path):
    """No widths: the config's taper; no pinned primvar: first n_pinned vertices; a Z-up
    stage in metres under a translated parent: (x, y, z) -> 100 (x, z, -y) after the
    transform; points only as a time sample: read at the first one."""
    P = _polyline(7)
    M = np.eye(4)
    M[3, :3] = [0.5, 0.25, 1.0]
    f = _curves(tmp_path / "b.usdc", [7], P, mpu=1.0, up=UsdGeom.Tokens.z, xform=M, time=3.0)
    s = UsdSource(f, n_pinned=2, root_radius=0.2, tip_radius=0.05)
    W = P.astype(np.float32).astype(float) + M[3, :3]
    assert np.allclose(s.positions, 100.0 * np.column_stack([W[:, 0], W[:, 2], -W[:, 1]]), rtol=1e-12)
    assert np.allclose(s.radius, np.linspace(0.2, 0.05, 7))
    assert s.pinned.tolist() == [True, True] + [False] * 5


def _bezier(P, u):
    """de Casteljau (independent of the basis-matrix form)."""
    Q = np.array(P, float)
    while len(Q) > 1:
        Q = (1 - u) * Q[:-1] + u * Q[1:]
    return Q[0]


def test_cubic_bezier_resampled_by_de_casteljau(tmp_path):
    rng = np.random.default_rng(0)
    P = rng.normal(size=(10, 3))           # 3 segments
    f = _curves(tmp_path / "c.usda", [10], P, type_="cubic", basis="bezier",
                widths=[0.1, 0.2, 0.3, 0.4], interp="varying")
    s = UsdSource(f)
    P32 = P.astype(np.float32).astype(float)
    expect = [_bezier(P32[3 * k:3 * k + 4], j / 3) for k in range(3) for j in range(3)] + [P32[-1]]
    assert s.sizes.tolist() == [10]
    assert np.allclose(s.positions, expect, atol=1e-12)
    # varying widths: one per segment end, linear in between
    assert np.allclose(2 * s.radius, np.interp(np.arange(10) / 3, [0, 1, 2, 3], [0.1, 0.2, 0.3, 0.4]))


def test_cubic_catmull_rom_passes_through_its_points(tmp_path):
    P = _polyline(9)
    f = _curves(tmp_path / "d.usda", [9], P, type_="cubic", basis="catmullRom")
    s = UsdSource(f)
    assert s.sizes.tolist() == [7]          # nonperiodic: P1 .. P7
    assert np.allclose(s.positions, P.astype(np.float32)[1:-1], atol=1e-6)
    f = _curves(tmp_path / "e.usda", [9], P, type_="cubic", basis="catmullRom", wrap="pinned")
    s = UsdSource(f)
    assert s.sizes.tolist() == [9] and np.allclose(s.positions, P.astype(np.float32), atol=1e-6)


def test_cubic_bspline(tmp_path):
    P = _polyline(8).astype(np.float32).astype(float)
    w = np.linspace(0.3, 0.1, 8)
    f = _curves(tmp_path / "f.usda", [8], P, type_="cubic", basis="bspline", widths=w)
    s = UsdSource(f)
    # uniform cubic B-spline at its knots: (P[i-1] + 4 P[i] + P[i+1]) / 6
    knots = (P[:-2] + 4 * P[1:-1] + P[2:]) / 6
    assert s.sizes.tolist() == [6] and np.allclose(s.positions, knots, atol=1e-6)
    assert np.allclose(2 * s.radius, (w[:-2] + 4 * w[1:-1] + w[2:]) / 6, atol=1e-7)
    f = _curves(tmp_path / "g.usda", [8], P, type_="cubic", basis="bspline", wrap="pinned")
    s = UsdSource(f)
    assert s.sizes.tolist() == [8]
    assert np.allclose(s.positions[[0, -1]], P[[0, -1]], atol=1e-6)     # pinned ends interpolate


def test_prim_path_selection(tmp_path):
    stage = Usd.Stage.CreateNew(str(tmp_path / "h.usda"))
    for name, x0 in (("a", 0.0), ("b", 3.0)):
        c = UsdGeom.BasisCurves.Define(stage, f"/root/{name}")
        c.CreateTypeAttr("linear")
        c.CreateCurveVertexCountsAttr(Vt.IntArray([5]))
        c.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(_polyline(5, x0=x0).astype(np.float32)))
    UsdGeom.Mesh.Define(stage, "/other")
    stage.GetRootLayer().Save()
    path = tmp_path / "h.usda"
    with pytest.raises(ValueError, match=r"holds 2 BasisCurves prims \(/root/a, /root/b\); set scene.prim_path"):
        UsdSource(path)
    assert UsdSource(path, prim_path="/root/b").positions[0, 0] == pytest.approx(3.0 + 0.0)
    both = UsdSource(path, prim_path="/root")
    assert both.n_wisps == 2 and both.positions[5, 0] == pytest.approx(3.0)
    with pytest.raises(ValueError, match=r"no prim at scene.prim_path = '/nope'; BasisCurves prims in "
                                         r"the file: /root/a, /root/b"):
        UsdSource(path, prim_path="/nope")
    with pytest.raises(ValueError, match=r"'/other' is a Mesh prim with no BasisCurves"):
        UsdSource(path, prim_path="/other")


@pytest.mark.parametrize("kwargs, message", [
    (dict(counts=[6, 4], points=_polyline(9)), r"curveVertexCounts add up to 10 .* there are 9 points"),
    (dict(counts=[6, 3], points=_polyline(9)), r"curve 1 has 3 vertices; a wisp needs at least 4"),
    (dict(counts=[5], points=np.vstack([_polyline(4), [[np.nan, 0, 0]]])),
     r"point 4 \(curve 0\) is not finite"),
    (dict(counts=[5], points=_polyline(5), wrap="periodic"), r"wrap = 'periodic' \(closed curves\)"),
    (dict(counts=[5], points=_polyline(5), widths=[0.1, 0.1]), r"2 widths with 'vertex' interpolation; expected 5$"),
    (dict(counts=[5, 5], points=_polyline(10), widths=[0.1, 0.2]),
     r"2 widths with 'vertex' interpolation; expected 10 \(that many widths fit 'uniform' interpolation"),
    (dict(counts=[5], points=_polyline(5), widths=[0.1, 0.1, -0.1, 0.1, 0.1]),
     r"width 2 is -0.1.*finite and positive"),
    (dict(counts=[8], points=_polyline(8), type_="cubic", basis="bezier"),
     r"curve 0 has 8 control points; a bezier curve .* needs 3k \+ 1 control points"),
    (dict(counts=[5], points=_polyline(5), type_="cubic", basis="bspline"),
     r"curve 0 has 3 vertices \(resampled from 5 bspline control points\); a wisp needs at least 4"),
    (dict(counts=[5], points=_polyline(5),
          pinned=(Sdf.ValueTypeNames.IntArray, Vt.IntArray([1, 1]), "vertex")),
     r"primvars:pinned has 2 values; expected one per point \(5\)"),
    (dict(counts=[5], points=_polyline(5),
          pinned=(Sdf.ValueTypeNames.FloatArray, Vt.FloatArray([1, 0, 0, 0, 0]), "vertex")),
     r"primvars:pinned has type float\[\]; expected int\[\] or bool\[\]"),
    (dict(counts=[7], points=_polyline(7), type_="cubic", basis="bezier",
          pinned=(Sdf.ValueTypeNames.BoolArray, Vt.BoolArray([True] * 7), "vertex")),
     r"primvars:pinned is read on linear curves only"),
])
def test_bad_curves_give_clear_errors(tmp_path, kwargs, message):
    counts, points = kwargs.pop("counts"), kwargs.pop("points")
    f = _curves(tmp_path / "bad.usda", counts, points, **kwargs)
    with pytest.raises(ValueError, match=message) as e:
        UsdSource(f)
    assert str(f) in str(e.value) and "/groom/curves" in str(e.value)


def test_bad_files_give_clear_errors(tmp_path):
    (tmp_path / "junk.usda").write_text("not usd at all")
    with pytest.raises(ValueError, match=r"junk.usda: cannot open it as USD") as e:
        UsdSource(tmp_path / "junk.usda")
    # USD's reason without its C++ function, line and source file
    assert "Error in" not in str(e.value) and "stage.cpp" not in str(e.value)
    assert str(e.value).endswith("scene.path must be a .usd, .usda or .usdc file")
    stage = Usd.Stage.CreateNew(str(tmp_path / "mesh.usda"))
    UsdGeom.Mesh.Define(stage, "/m")
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match=r"holds no BasisCurves prim \(prim types found: Mesh\)"):
        UsdSource(tmp_path / "mesh.usda")


def test_config_keys(tmp_path):
    f = _curves(tmp_path / "ok.usda", [5], _polyline(5))
    cfg = config_from_dict({"scene": {"kind": "usd", "path": "ok.usda", "prim_path": "/groom"}},
                           base_dir=tmp_path)
    assert cfg.scene.path == str(f)
    src = source_from_config(cfg.scene, cfg.material, cfg.physics)
    assert isinstance(src, UsdSource) and src.n_wisps == 1
    with pytest.raises(ConfigError, match=r"scene.path must name a USD file"):
        config_from_dict({"scene": {"kind": "usd"}})
    with pytest.raises(ConfigError, match=r"scene.path = .*missing.usda.*no such file"):
        config_from_dict({"scene": {"kind": "usd", "path": "missing.usda"}}, base_dir=tmp_path)
    with pytest.raises(ConfigError, match=r"scene.prim_path = '/g' only applies to scene.kind = 'usd'"):
        config_from_dict({"scene": {"prim_path": "/g"}})
    with pytest.raises(ConfigError, match=r"scene.prim_path must be an absolute USD prim path"):
        config_from_dict({"scene": {"kind": "usd", "path": "ok.usda", "prim_path": "groom"}},
                         base_dir=tmp_path)
    with pytest.raises(ConfigError, match=r"output.render_hairs = 4 needs output.usd = true"):
        config_from_dict({"output": {"render_hairs": 4, "usd": False}})
    with pytest.raises(ConfigError, match=r"output.render_hair_spread must be a finite positive"):
        config_from_dict({"output": {"render_hair_spread": 0.0}})


def test_round_trip_export_import_simulate(tmp_path, monkeypatch):
    """Run a hairball, export it, import the export as a usd scene and run that: the same
    rest pose (to float32), pins and radii (to float32), and the trajectory of the
    original scene rounded to float32, to round-off.  (Not the original trajectory
    itself: the hairball's top wisps stand up and buckle, and a 1e-7 cm change of their
    rest pose moves them by up to 1.8 cm within 4 frames; the others agree to 1e-5.)"""
    (tmp_path / "a.toml").write_text(hairball_toml(frames=4, output="previews = false\nrender_hairs = 2"))
    assert main([str(tmp_path / "a.toml"), "--out", str(tmp_path / "a"), "--quiet"], comm=MPI.COMM_SELF) == 0
    from lc_petsc.config import load_config
    cfg = load_config(tmp_path / "a.toml")
    original = source_from_config(cfg.scene, cfg.material, cfg.physics).load(0, 5)
    cfg.scene.kind, cfg.scene.path = "usd", str(tmp_path / "a" / "frames.usdc")
    cfg.scene.prim_path = "/Groom/wisps"          # the export also holds render hairs
    cfg.validate()
    src = source_from_config(cfg.scene, cfg.material, cfg.physics)
    with h5py.File(tmp_path / "a" / "frames.h5") as f:
        rest, pinned, X = f["rest_positions"][...], f["pinned"][...], f["positions"][-1]
    assert np.array_equal(src.positions, rest.astype(np.float32))
    assert np.array_equal(src.pinned, pinned) and pinned.sum() == 5 * 4
    assert np.array_equal(src.radius, (2 * original.radius).astype(np.float32) / 2)
    Y, summary = run_positions(cfg, comm=MPI.COMM_SELF)
    assert summary["converged"] and np.abs(Y - rest).max() > 1.0       # the run did something

    import lc_petsc.simulator
    rounded = ArraySource(original.positions.astype(np.float32), original.offsets,
                          radius=(2 * original.radius).astype(np.float32) / 2, pinned=original.pinned)
    monkeypatch.setattr(lc_petsc.simulator, "source_from_config", lambda *a: rounded)
    Z, _ = run_positions(cfg, comm=MPI.COMM_SELF)
    assert np.abs(Y - Z).max() <= 1e-12 * np.abs(Z).max()
    # wisps that do not buckle follow the original run closely (which ones buckle
    # depends on where the generator puts them: the standing ones)
    per_wisp = np.abs(Y - X).reshape(5, 101, 3).max(axis=(1, 2))
    assert (per_wisp < 1e-4).sum() >= 2, per_wisp


def test_shipped_usd_groom_is_the_fringe():
    """configs/from_usd.toml reads data/fringe.usda (Z up, metres, Catmull-Rom, under a
    transform) back into fringe.h5's wisps, radii and pins."""
    from lc_petsc.config import load_config
    root = Path(__file__).resolve().parents[2] / "configs"
    cfg = load_config(root / "from_usd.toml")
    assert not [w for w in cfg.key_warnings if "scene.path" in w], cfg.key_warnings
    src = source_from_config(cfg.scene, cfg.material, cfg.physics)
    with h5py.File(root / "data" / "fringe.h5") as f:
        x, off, r, pin = (f[k][...] for k in ("positions", "wisp_offsets", "radius", "pinned"))
    assert np.array_equal(src.offsets, off)
    assert np.abs(src.positions - x).max() < 2e-6 * np.abs(x).max()      # float32 of metres
    assert np.allclose(src.radius, r, rtol=1e-6)
    assert np.array_equal(src.pinned, pin)


def test_a_truncated_usd_groom_names_the_parse_error(tmp_path):
    """A .usda groom cut short (a failed copy) said only 'cannot open it as USD (Failed to
    open layer @...@)': USD's last, least specific line.  Now every reason USD gives is
    kept, the parse error with its line and column first."""
    good = Path(__file__).resolve().parents[2] / "configs" / "data" / "fringe.usda"
    cut = tmp_path / "cut.usda"
    cut.write_bytes(good.read_bytes()[:20000])
    with pytest.raises(ValueError) as e:
        UsdSource(cut)
    assert str(e.value).startswith(f"USD file {cut}: cannot open it as USD ({cut}:18:19461: parse error "), e.value
    assert str(e.value).endswith(f"; Failed to open layer @{cut}@): damaged, truncated or not USD; scene.path "
                                 "must be a .usd, .usda or .usdc file")
    assert "pxrInternal" not in str(e.value) and "Error in" not in str(e.value)
