"""Write the example USD groom configs/data/fringe.usda (used by configs/from_usd.toml)
from configs/data/fringe.h5, the way a DCC tool such as Blender would hand it over: Z
up, metres, each wisp a cubic Catmull-Rom curve through its vertices (wrap "pinned",
so the curve starts at the root and ends at the tip) with per-vertex widths, under a
transformed parent Xform, and no pinned primvar (the scene pins the first 3 vertices).

Importing it (scene.kind = "usd") gives fringe.h5's wisps back: Catmull-Rom curves pass
through their control points, the transform and units are undone, to float32 round-off.

  .venv/bin/python scripts/make_groom_usd.py [OUT.usda]
"""

import argparse
import sys
from pathlib import Path

import h5py
import numpy as np
from pxr import Gf, Usd, UsdGeom, Vt

ROOT = Path(__file__).resolve().parents[1]
# the parent's transform: a translation of 0.5 m along the stage's z (up)
LIFT_M = 0.5


def main(out):
    with h5py.File(ROOT / "configs" / "data" / "fringe.h5") as f:
        x, off, r = f["positions"][...], f["wisp_offsets"][...], f["radius"][...]
    # lc_petsc's Y-up cm -> Z-up m: (x, y, z) -> (x, -z, y) / 100, then below the parent's lift
    q = np.column_stack([x[:, 0], -x[:, 2], x[:, 1]]) / 100.0 - [0.0, 0.0, LIFT_M]
    Path(out).unlink(missing_ok=True)
    stage = Usd.Stage.CreateNew(str(out))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/fringe")
    root.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.0, LIFT_M))
    stage.SetDefaultPrim(root.GetPrim())
    c = UsdGeom.BasisCurves.Define(stage, "/fringe/guides")
    c.CreateTypeAttr(UsdGeom.Tokens.cubic)
    c.CreateBasisAttr(UsdGeom.Tokens.catmullRom)
    c.CreateWrapAttr(UsdGeom.Tokens.pinned)
    c.CreateCurveVertexCountsAttr(Vt.IntArray(np.diff(off).tolist()))
    c.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(q.astype(np.float32)))
    c.CreateWidthsAttr(Vt.FloatArray.FromNumpy((2.0 * r / 100.0).astype(np.float32)))
    c.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    stage.GetRootLayer().documentation = ("lc_petsc example groom: fringe.h5's 24 curly wisps as "
                                          "Catmull-Rom curves, Z up, metres (scripts/make_groom_usd.py)")
    stage.GetRootLayer().Save()
    print(f"wrote {out}: {len(off) - 1} curves, {off[-1]} control points")


def cli(argv=None):
    """The command line: an optional output path (``--help`` is help, not a file name);
    a USD layer's suffix is checked before anything is removed."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", nargs="?", default=str(ROOT / "configs" / "data" / "fringe.usda"),
                    help="USD file to write, .usda, .usdc or .usd (default configs/data/fringe.usda)")
    out = ap.parse_args(argv).out
    if Path(out).suffix not in (".usda", ".usdc", ".usd"):
        ap.error(f"{out}: give a USD file name ending in .usda, .usdc or .usd")
    if Path(out).is_dir():
        ap.error(f"{out} is a folder: give the path of the USD file to write")
    if not Path(out).resolve().parent.is_dir():
        ap.error(f"{out}: no such folder {Path(out).parent}")
    main(out)
    return 0


if __name__ == "__main__":
    sys.exit(cli())
