"""Check that a run's output folder agrees with itself, as the tools that read it see it.

    .venv/bin/python scripts/check_outputs.py OUT [OUT ...] [--crossings]

For each output folder of ``drivers/simulate.py``: ``frames.h5`` read with plain h5py
against DESIGN section 3 (datasets, dtypes, shapes) and against ``summary.json``
(``frames`` / ``output.every`` rows, ``/time`` = row x dt x every, ``dofs``, ``wisps``,
``output.frames_written``, one per-frame entry per frame of the run; a summary.json that
says ``running``, the one a run keeps while it goes, is reported as not finished, with
what the folder's lock says (``running (pid P on host H, alive ...)``, ``killed after
frame N (its lock ... is stale ...)`` or no lock file, ``failed after frame N: its final
summary.json ... could not be written``, or not known for a run on another host:
``lc_petsc.io.history.running_state``), and not checked further); ``frames.usdc`` read with pxr (centimetres, Y up,
``timeCodesPerSecond`` 1 / (dt x every), one curve per wisp, a time sample per row,
points equal to ``frames.h5``'s to float32 after the prim's transform, widths twice the
radii); ``frames.xdmf`` read with VTK's XDMF reader (a time step per row at ``/time``,
the last one's points equal to the last row); a preview per ``output.preview_frames``
entry (the frame written at or before it). ``--crossings`` also counts the crossings
between consecutive rows (``lc_petsc.crossings``) and compares them with the end-of-run
check in ``summary.json``. One line per folder: ``ok`` or its problems; exit status 1 if
any folder has one, 2 for a folder that cannot be read.

Written for the output audit of 2026-12-07 (docs/design_notes.md, "What a user sees"):
every shipped config on 1 and 2 ranks, restarts across 1 -> 2 -> 3 ranks and runs killed
at random moments, all ok.
"""

import argparse
import json
import sys
from pathlib import Path

import h5py
import numpy as np

#: DESIGN section 3: dataset -> dtype (shapes checked in :func:`frames_problems`)
DATASETS = {"positions": "float64", "time": "float64", "wisp_offsets": "int64",
            "rest_positions": "float64", "pinned": "bool"}


def frames_problems(f, s):
    """frames.h5 (an open h5py File) against DESIGN section 3 and summary.json ``s``."""
    out = []
    missing = [k for k in DATASETS if k not in f]
    if missing:
        return [f"frames.h5 has no {', '.join('/' + k for k in missing)}"]
    offsets = f["wisp_offsets"][...]
    rows, nv = f["positions"].shape[0], int(offsets[-1])
    shapes = {"positions": (rows, nv, 3), "time": (rows,), "wisp_offsets": (s["wisps"] + 1,),
              "rest_positions": (nv, 3), "pinned": (nv,)}
    for k, dtype in DATASETS.items():
        if (str(f[k].dtype), f[k].shape) != (dtype, shapes[k]):
            out.append(f"/{k} is {f[k].dtype} {f[k].shape}, DESIGN: {dtype} {shapes[k]}")
    dt, every = s["config"]["time"]["dt"], s["config"]["output"]["every"]
    if rows != 1 + s["frames"] // every:
        out.append(f"frames.h5 has {rows} rows, summary.json's {s['frames']} frames every {every}: "
                   f"{1 + s['frames'] // every}")
    if s["output"].get("frames_written") != rows:
        out.append(f"summary.json output.frames_written {s['output'].get('frames_written')}, rows {rows}")
    if s["dofs"] != 3 * nv:
        out.append(f"summary.json dofs {s['dofs']}, frames.h5 {3 * nv}")
    time = f["time"][...]
    if not np.allclose(time, np.arange(rows) * dt * every, rtol=1e-12, atol=1e-12):
        out.append(f"/time is not row x dt x every ({time[:3]} ...)")
    run = s.get("frames_this_run", s["frames"])
    for key in ("newton_iterations", "newton_converged", "newton_increment"):
        if len(s.get(key, [])) != run:
            out.append(f"summary.json {key} has {len(s.get(key, []))} entries for {run} frames of this run")
    return out


def usd_problems(path, positions, offsets, radius, dt, every):
    """frames.usdc against frames.h5 (pxr)."""
    from pxr import Usd, UsdGeom
    stage = Usd.Stage.Open(str(path))
    out = []
    if UsdGeom.GetStageMetersPerUnit(stage) != 0.01 or UsdGeom.GetStageUpAxis(stage) != "Y":
        out.append(f"{path.name}: metersPerUnit {UsdGeom.GetStageMetersPerUnit(stage)}, up axis "
                   f"{UsdGeom.GetStageUpAxis(stage)} (DESIGN: 0.01, Y)")
    if abs(stage.GetTimeCodesPerSecond() * dt * every - 1.0) > 1e-9:
        out.append(f"{path.name}: timeCodesPerSecond {stage.GetTimeCodesPerSecond()}, 1 / (dt x every) "
                   f"{1 / (dt * every):g}")
    curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/Groom/wisps"))
    if not curves:
        return out + [f"{path.name}: no BasisCurves prim /Groom/wisps"]
    if not np.array_equal(np.asarray(curves.GetCurveVertexCountsAttr().Get()), np.diff(offsets)):
        out.append(f"{path.name}: curveVertexCounts are not the diff of /wisp_offsets")
    rows = len(positions)
    samples = list(curves.GetPointsAttr().GetTimeSamples())
    if samples != list(range(rows)):
        out.append(f"{path.name}: {len(samples)} time samples, frames.h5 {rows} rows")
    cache = UsdGeom.XformCache()
    scale = max(1.0, float(np.abs(positions[0]).max()))
    for row in sorted({0, rows // 2, rows - 1}):
        cache.SetTime(Usd.TimeCode(row))
        m = np.array(cache.GetLocalToWorldTransform(curves.GetPrim()))
        pts = np.asarray(curves.GetPointsAttr().Get(Usd.TimeCode(row)), float) @ m[:3, :3] + m[3, :3]
        err = float(np.abs(pts - positions[row]).max()) if pts.shape == positions[row].shape else np.inf
        if err > 1e-6 * scale:
            out.append(f"{path.name}: time code {row} is {err:.3g} cm from frames.h5's row")
    if radius is not None and not np.allclose(np.asarray(curves.GetWidthsAttr().Get(), float), 2 * radius,
                                              rtol=1e-6):
        out.append(f"{path.name}: widths are not twice /radius")
    return out


def xdmf_problems(path, positions, time):
    """frames.xdmf read back by VTK's XDMF reader (ParaView's)."""
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy
    reader = vtk.vtkXdmfReader()
    reader.SetFileName(str(path))
    reader.UpdateInformation()
    steps = reader.GetOutputInformation(0).Get(vtk.vtkStreamingDemandDrivenPipeline.TIME_STEPS()) or ()
    if not np.allclose(steps, time):
        return [f"frames.xdmf has {len(steps)} time steps, frames.h5 {len(time)} rows"]
    reader.UpdateTimeStep(steps[-1])
    reader.Update()
    pts = vtk_to_numpy(reader.GetOutputDataObject(0).GetPoints().GetData())
    if pts.shape != positions[-1].shape or np.abs(pts - positions[-1]).max() > 0:
        return ["frames.xdmf's last time step is not frames.h5's last row"]
    return []


def preview_problems(out, s):
    """A previews/frame_NNNNN.png per output.preview_frames entry (the frame drawn)."""
    o, frames = s["config"]["output"], s["frames"]
    if not o.get("previews", True) or s.get("preempted") or s.get("error"):
        return []
    every, drawn = o["every"], set()
    for f in o.get("preview_frames", []):
        frame = frames + 1 + f if f < 0 else f
        drawn.add(min(max(frame, 0), frames) // every * every)
    return [f"previews/frame_{k:05d}.png missing" for k in sorted(drawn)
            if not (out / "previews" / f"frame_{k:05d}.png").is_file()]


def check(out, crossings=False, retries=1):
    """The problems of the output folder ``out`` (a list of lines; empty: consistent)."""
    from lc_petsc.io.history import running_state
    out = Path(out)
    s = json.loads((out / "summary.json").read_text())
    if s.get("status") == "running":
        # the summary a run keeps while it goes: the run is going (it holds the folder's
        # lock), was killed, or could not write its final summary; its end-of-run
        # outputs are not there to check
        state, said = running_state(out, s)
        if state == "ended" and retries > 0:
            return check(out, crossings, retries - 1)
        then = {"running": "", "unknown": "", "ended": ""}.get(state, "; --restart latest continues it")
        return [f"not finished: summary.json says running, {s.get('frames')} frames recorded: {said}{then}"]
    with h5py.File(out / "frames.h5", "r") as f:
        problems = frames_problems(f, s)
        if problems and "/positions" in problems[0]:
            return problems
        positions, time = f["positions"][...], f["time"][...]
        offsets = f["wisp_offsets"][...]
        radius = f["radius"][...] if "radius" in f else None
    dt, every = s["config"]["time"]["dt"], s["config"]["output"]["every"]
    usd = sorted(out.glob("frames.usd*"))
    if s["config"]["output"].get("usd", True) and not s.get("preempted"):
        problems += usd_problems(usd[0], positions, offsets, radius, dt, every) if usd else ["no frames.usdc"]
    if s["config"]["output"].get("xdmf", True):
        problems += xdmf_problems(out / "frames.xdmf", positions, time)
    problems += preview_problems(out, s)
    if crossings and s.get("crossings") and "between_wisps" in s["crossings"]:
        from lc_petsc.crossings import count_frames
        steps, _ = count_frames(str(out / "frames.h5"))
        n = sum(r["crossings"] for r in steps)
        if n != s["crossings"]["between_wisps"]:
            problems.append(f"{n} crossings between wisps in frames.h5, summary.json "
                            f"{s['crossings']['between_wisps']}")
    return problems


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", nargs="+", help="output folders of drivers/simulate.py")
    ap.add_argument("--crossings", action="store_true", help="recount the crossings between the rows")
    a = ap.parse_args(argv)
    status = 0
    for out in a.out:
        try:
            problems = check(out, a.crossings)
        except (OSError, KeyError, ValueError) as e:
            print(f"check_outputs.py: error: {out}: not a readable output folder ({e})", file=sys.stderr)
            return 2
        print(f"{out}: " + ("ok" if not problems else "; ".join(problems)))
        status = status or int(bool(problems))
    return status


if __name__ == "__main__":
    sys.exit(main())
