"""USD export of a run (DESIGN section 3, "USD export"): ``frames.usdc`` from ``frames.h5``,
for DCC tools (Houdini, Blender, Maya, Unreal, usdview) through Pixar's ``pxr``.

Stage layout (``metersPerUnit`` 0.01: centimetres; up axis Y; default prim ``/Groom``):

* ``/Groom/wisps``: ``UsdGeom.BasisCurves``, type ``linear``, one curve per wisp in global
  wisp order.  ``curveVertexCounts`` = diff of ``/wisp_offsets``; ``points`` (float32)
  time-sampled at every written frame, with the rest pose as its default (un-animated)
  value, relative to the prim's ``xformOp:translate`` (double, time-sampled with them:
  :func:`local_origin`, 0 for a groom near the origin), so a groom far from the origin
  keeps the detail float32 has at its own size (a groom 1e5 cm away lost 0.0039 cm, 13%
  of a strand radius, to float32 before); ``widths`` = 2 x the radii (vertex
  interpolation); ``primvars:wisp_index`` (int, uniform: the wisp of each curve);
  ``primvars:pinned`` (int 0/1, vertex: the pinned roots, read back by the ``usd`` scene
  kind); ``extent`` time-sampled, in the points' local space.
* ``/Groom/head``: ``UsdGeom.Sphere`` of the head radius with the head's motion
  (:class:`lc_petsc.scene.kinematics.HeadMotion`) as a time-sampled ``xformOp:transform``;
  present when the scene has a head sphere (head contact on, or a hairball).
* ``/Groom/render_hairs`` (``output.render_hairs`` > 0): a second linear BasisCurves of
  N interpolated hairs per wisp (:mod:`lc_petsc.io.render_hairs`), ``primvars:guide_wisp``
  (int, uniform), time-sampled ``points`` relative to a translate as the wisps'.

Time: row k of ``frames.h5`` (simulation frame k * every) is time code k;
``timeCodesPerSecond`` = ``framesPerSecond`` = 1 / (dt * every), so a DCC plays the run
at its real speed; start and end time codes are 0 and n_frames - 1.  A row that holds
no frame (lost in a recovery, ``/frame_valid`` False) has no time sample: a DCC holds
the samples around it, nothing is made up for it.

Radii are not in ``frames.h5``: they are rebuilt from the resolved config stored in its
``config`` attribute with the scene source the run used (a strands or USD file must
still be at its path).  The export streams: one frame is read, converted and appended
to the crate file at a time (``Usd.Stage.Save`` per frame writes the new samples and
frees them), so memory stays at a few frames whatever the run length (a text ``.usda``
is saved once at the end and held in memory until then).  The file is written as
``<name>.tmp.<ext>`` and renamed when complete.
"""

from __future__ import annotations

import json
import re
import sys
import time
from dataclasses import fields
from pathlib import Path

import numpy as np

from lc_petsc.io.disk import written_aside

USD_NAME = "frames.usdc"


def config_tables(config_dict):
    """Scene, material, physics and output dataclasses from a resolved config dict
    (keys unknown to this version are dropped, missing ones take their defaults)."""
    from lc_petsc import config as C
    out = {}
    for name, cls in (("scene", C.SceneConfig), ("material", C.MaterialConfig),
                      ("physics", C.PhysicsConfig), ("output", C.OutputConfig)):
        known = {f.name for f in fields(cls)}
        out[name] = cls(**{k: v for k, v in config_dict.get(name, {}).items() if k in known})
    return out


def has_head_sphere(physics, scene) -> bool:
    """The scene has a head sphere to show: head contact is modelled, or it is a hairball
    (the same rule as the previews)."""
    return "head_collision" in tuple(physics.terms) or scene.kind == "hairball"


def scene_radius(tables, sizes):
    """Per-vertex radii (n_vertices,) of the run's scene, rebuilt from its config with the
    scene source the run used; ``sizes`` (n_wisps,) from frames.h5 must match."""
    from lc_petsc.scene.sources import source_from_config
    scene = tables["scene"]
    try:
        source = source_from_config(scene, tables["material"], tables["physics"])
    except (OSError, ValueError) as e:
        raise ValueError(f"cannot rebuild the wisps' radii from the run's scene ({scene.kind}"
                         f"{', ' + str(scene.path) if scene.path else ''}): {e}") from None
    if not np.array_equal(np.asarray(source.sizes), sizes):
        raise ValueError(f"the run's scene ({scene.kind}) now has {len(source.sizes)} wisps of other "
                         f"sizes than the {len(sizes)} of frames.h5; was its strands file changed?")
    return np.asarray(source.load(0, source.n_wisps).radius, float)


def head_matrix(motion, t):
    """USD row-vector matrix (4x4) of the head at time ``t``: p -> c + T + R p."""
    R, T = motion.transform(t)
    M = np.eye(4)
    M[:3, :3] = R.T
    M[3, :3] = motion.center + T
    return M


def _define_curves(stage, path, counts, widths, Vt, UsdGeom):
    curves = UsdGeom.BasisCurves.Define(stage, path)
    curves.CreateTypeAttr(UsdGeom.Tokens.linear)
    curves.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
    curves.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(counts, np.int32)))
    curves.CreateWidthsAttr(Vt.FloatArray.FromNumpy(np.ascontiguousarray(widths, np.float32)))
    curves.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    return curves


def _int_primvar(curves, name, values, interpolation, Vt, UsdGeom, Sdf):
    pv = UsdGeom.PrimvarsAPI(curves.GetPrim()).CreatePrimvar(name, Sdf.ValueTypeNames.IntArray,
                                                             interpolation)
    pv.Set(Vt.IntArray.FromNumpy(np.ascontiguousarray(values, np.int32)))
    return pv


def local_origin(x):
    """The translate of a frame's points (n, 3): the centre of their bounding box rounded
    to a multiple of q, the power of two at least twice its largest side, so the local
    points stay below 2.5 sides (float32 keeps them to 1.5e-7 of the groom's size) and a
    groom within q/2 of the origin keeps the origin (its points are the world's)."""
    x = np.asarray(x, float)
    if not len(x):
        return np.zeros(3)
    lo, hi = x.min(axis=0), x.max(axis=0)
    side = max(float((hi - lo).max()), 1e-6)
    q = 2.0 ** (np.ceil(np.log2(side)) + 1)
    return np.round((lo + hi) / 2 / q) * q


def _extent(p32, half_width):
    lo = p32.min(axis=0) - half_width
    hi = p32.max(axis=0) + half_width
    return np.stack([lo, hi]).astype(np.float32)


def write_usd(frames_path, usd_path=None, *, render_hairs=None, render_hair_seed=None,
              render_hair_spread=None, stride=1, progress=None):
    """Write the USD export of ``frames_path`` (a closed ``frames.h5``) to ``usd_path``
    (default ``frames.usdc`` beside it; a missing folder is created).  ``render_hairs``
    (hairs per wisp), the seed and the spread default to the run's ``output`` config;
    ``stride`` k writes every k-th row of frames.h5 (time codes stay row numbers; rows
    lost in a recovery are left out; the stage's start and end time codes are the first
    and last row written).  ``progress``: callable(done, total) or None.  Returns a dict
    of what was written and how long it took (seconds)."""
    from pxr import Gf, Sdf, Usd, UsdGeom, Vt
    from lc_petsc.io.frames_read import FramesReader, naming
    from lc_petsc.io.render_hairs import RenderHairs, root_normals
    from lc_petsc.scene.kinematics import HeadMotion

    t_start = time.perf_counter()
    frames_path = Path(frames_path)
    usd_path = Path(usd_path) if usd_path is not None else frames_path.with_name(USD_NAME)
    if usd_path.suffix not in (".usd", ".usdc", ".usda"):
        raise ValueError(f"USD output {str(usd_path)!r}: the name must end in .usdc, .usd or .usda")
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise ValueError(f"stride must be an integer >= 1, got {stride!r}")
    try:
        r = FramesReader(frames_path)
    except (OSError, ValueError) as e:
        raise ValueError(f"{frames_path}: cannot open the frames file ({e})") from None
    with r:
        f = r.f
        for key in ("positions", "time", "wisp_offsets", "rest_positions", "pinned"):
            if key not in f:
                raise ValueError(f"{frames_path}: not an lc_petsc frames file (no /{key})")
        if "config" not in f.attrs or "dt" not in f.attrs:
            raise ValueError(f"{frames_path}: has no 'config'/'dt' attributes (not written by the main job)")
        with naming(frames_path):     # the chunk index first: a damaged /time entry crashed libhdf5
            held = r.valid
        config_dict = json.loads(f.attrs["config"])
        tables = config_tables(config_dict)
        dt, every = float(f.attrs["dt"]), int(f.attrs.get("every", 1))
        with naming(frames_path):
            static = {k: r.dataset(k) for k in ("rest_positions", "pinned", "radius") if k in f}
            times = r.times
            offsets = r.offsets
        sizes = np.diff(offsets)
        rest = np.asarray(static["rest_positions"], float)
        pinned = np.asarray(static["pinned"], bool)
        n_rows = len(times)
        rows = [k for k in range(0, n_rows, int(stride)) if held[k]]
        # the run's radii; frames files written before /radius existed: from its config
        radius = static["radius"] if "radius" in static else scene_radius(tables, sizes)
        out_cfg = tables["output"]
        n_hairs = out_cfg.render_hairs if render_hairs is None else render_hairs
        seed = out_cfg.render_hair_seed if render_hair_seed is None else render_hair_seed
        spread = out_cfg.render_hair_spread if render_hair_spread is None else render_hair_spread
        if isinstance(n_hairs, bool) or not isinstance(n_hairs, (int, np.integer)) or n_hairs < 0:
            raise ValueError(f"render hairs per wisp must be an integer >= 0, got {n_hairs!r}")
        if not (np.isfinite(spread) and spread > 0):
            raise ValueError(f"render hair spread must be a positive number, got {spread!r}")

        # a crate file (.usdc, .usd) takes the frames one by one; a text .usda is written
        # whole, so it is saved once at the end
        incremental = usd_path.suffix != ".usda"
        # a missing folder is created, as the main job's --out does (said in to_usd.py --help)
        usd_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = usd_path.with_name(usd_path.stem + ".tmp" + usd_path.suffix)
        tmp.unlink(missing_ok=True)
        with written_aside(usd_path, tmp):
            # inside: on a full disk CreateNew fails after creating the file (empty)
            stage = Usd.Stage.CreateNew(str(tmp))
            UsdGeom.SetStageMetersPerUnit(stage, 0.01)
            UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
            tcps = 1.0 / (dt * every)
            stage.SetTimeCodesPerSecond(tcps)
            stage.SetFramesPerSecond(tcps)
            # the range of the samples written (with --stride the last row may be skipped:
            # an end past the last sample made players hold it over frames that are none)
            stage.SetStartTimeCode(float(rows[0] if rows else 0))
            stage.SetEndTimeCode(float(rows[-1] if rows else 0))
            root = UsdGeom.Xform.Define(stage, "/Groom")
            stage.SetDefaultPrim(root.GetPrim())
            stage.GetRootLayer().customLayerData = {
                "lc_petsc:frames_file": str(frames_path.resolve()), "lc_petsc:dt": dt,
                "lc_petsc:every": every, "lc_petsc:description": str(tables["scene"].description)}

            wisps = _define_curves(stage, "/Groom/wisps", sizes, 2.0 * radius, Vt, UsdGeom)
            _int_primvar(wisps, "wisp_index", np.arange(len(sizes)), UsdGeom.Tokens.uniform, Vt, UsdGeom, Sdf)
            _int_primvar(wisps, "pinned", pinned.astype(np.int32), UsdGeom.Tokens.vertex, Vt, UsdGeom, Sdf)
            pts_attr = wisps.GetPointsAttr()
            origin = local_origin(rest)
            pts_attr.Set(Vt.Vec3fArray.FromNumpy((rest - origin).astype(np.float32)))     # default: rest pose
            # double precision: the points' offset in the world, exact wherever the groom is
            moves = [wisps.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)]
            ext_attr = wisps.CreateExtentAttr()
            half_w = float(radius.max(initial=0.0))

            motion = HeadMotion(tables["physics"])     # moves the head and the hairs' root frames
            head = None
            if has_head_sphere(tables["physics"], tables["scene"]):
                head = UsdGeom.Sphere.Define(stage, "/Groom/head")
                head.CreateRadiusAttr(motion.radius)
                head.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-motion.radius), Gf.Vec3f(motion.radius)]))
                head.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(0.72, 0.62, 0.55)]))
                head_op = head.AddTransformOp()

            hairs = None
            if n_hairs > 0:
                hairs = RenderHairs(offsets, radius, n_hairs, seed=seed, spread=spread)
                hc = _define_curves(stage, "/Groom/render_hairs", hairs.curve_vertex_counts(),
                                    hairs.widths(), Vt, UsdGeom)
                _int_primvar(hc, "guide_wisp", hairs.guide_wisp(), UsdGeom.Tokens.uniform, Vt, UsdGeom, Sdf)
                hair_attr, hair_ext = hc.GetPointsAttr(), hc.CreateExtentAttr()
                moves.append(hc.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble))
                normal_rest = root_normals(rest, offsets)
                hair_buf = np.empty((hairs.n_points, 3), np.float32)
            for op in moves:
                op.Set(Gf.Vec3d(*origin.tolist()))
            stage.Save()

            t_hairs = 0.0
            with naming(frames_path):       # (a damaged row read in the loop names the file)
                for done, (k, world) in enumerate(r.rows(rows)):
                    origin = local_origin(world)
                    x = world - origin          # the render hairs follow a translation exactly
                    p32 = x.astype(np.float32)
                    for op in moves:
                        op.Set(Gf.Vec3d(*origin.tolist()), float(k))
                    pts_attr.Set(Vt.Vec3fArray.FromNumpy(p32), float(k))
                    ext_attr.Set(Vt.Vec3fArray.FromNumpy(_extent(p32, half_w)), float(k))
                    if head is not None:
                        head_op.Set(Gf.Matrix4d(head_matrix(motion, times[k]).tolist()), float(k))
                    if hairs is not None:
                        t0 = time.perf_counter()
                        R = motion.transform(times[k])[0]
                        hairs.points(x, normal_rest @ R.T, out=hair_buf)
                        t_hairs += time.perf_counter() - t0
                        hair_attr.Set(Vt.Vec3fArray.FromNumpy(hair_buf), float(k))
                        hair_ext.Set(Vt.Vec3fArray.FromNumpy(_extent(hair_buf, half_w)), float(k))
                    if incremental:
                        stage.Save()         # appends this frame's samples to the file, frees them
                    if progress is not None:
                        progress(done + 1, len(rows))
            stage.Save()
            del stage
    return {"path": str(usd_path), "frames": len(rows), "wisps": int(len(sizes)),
            "points": int(offsets[-1]), "render_hairs": int(n_hairs) * int(len(sizes)),
            "render_hair_points": int(n_hairs) * int(offsets[-1]),
            "time_codes_per_second": 1.0 / (dt * every), "bytes": usd_path.stat().st_size,
            "seconds": time.perf_counter() - t_start, "render_hair_seconds": t_hairs}


def usd_reasons(error):
    """The reasons in the text of a USD error (pxr's ``Tf.ErrorException``: one line
    "Error in '<C++ function>' at line N in file <source> : '<reason>'" per error, the
    most specific first), without the C++ places; another error's text as one reason."""
    text = str(error).strip()
    reasons = [re.sub(r"pxrInternal_\w+::", "", line.rsplit(" : ", 1)[-1].strip().strip("'").strip())
               for line in text.split("\n\tError in ") if " : " in line]
    return [r for r in reasons if r] or [" ".join(text.split())]


def usd_failure(error, more_at):
    """One line for a USD error: its first (most specific) reason, and how many more USD
    gave and where they are (``more_at``: "summary.json's output.usd_error", say); pxr's
    text is a line per C++ error (a full disk gave 7, the crate file's unpacking errors
    after the write's)."""
    reasons = usd_reasons(error)
    more = f" ({len(reasons) - 1} more from USD: {more_at})" if len(reasons) > 1 else ""
    return reasons[0] + more


def export_failed(frames_path, error, target=None, more_at="summary.json's output.usd_error"):
    """The warning of a failed export of ``frames_path`` (to ``target``), one line: what
    failed (:func:`usd_failure`), that frames.h5 is intact, and the command that writes the
    export later; or, where frames.h5 itself is gone (the output folder removed mid-run),
    that there is nothing to export from."""
    why = (f"{target}: " if target is not None else "") + usd_failure(error, more_at)
    if not Path(frames_path).is_file():
        return (f"USD export failed: {frames_path} is missing (the output folder was changed during "
                f"the run?), so there is nothing to write it from: {why}")
    return f"USD export failed, frames.h5 is intact (write it later with drivers/to_usd.py {frames_path}): {why}"


def export_run(output, frames_path, out_dir, stop=None, warn=None, detail=None):
    """The main job's USD export (rank 0, after ``frames.h5`` is closed): writes
    ``out_dir/frames.usdc`` when ``output.usd`` is on, else removes a stale one.  A
    failure is a warning, given to ``warn`` (the main job's records it in summary.json;
    None: printed on stderr) in one line, USD's own text (a line per C++ error) to
    ``detail`` (the main job keeps it in summary.json; None: dropped); the run's other
    outputs are unaffected.
    Returns (files written relative to ``out_dir``, seconds).  ``stop``: called after
    each frame (the main job's raises :class:`lc_petsc.stop_notice.Stopped` on a signal:
    the temporary file is removed, no frames.usdc written), or None."""
    if warn is None:
        def warn(text):
            print(f"simulate.py: warning: {text}", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    target = Path(out_dir) / USD_NAME
    if not output.usd:
        target.unlink(missing_ok=True)
        return [], 0.0
    try:
        from pxr import Tf
        failures = (OSError, ValueError, Tf.ErrorException)
    except ImportError as e:
        warn(f"no USD export ({e}; install usd-core or set output.usd = false)")
        return [], time.perf_counter() - t0
    try:
        write_usd(frames_path, target, progress=None if stop is None else lambda done, total: stop())
    except failures as e:
        warn(export_failed(frames_path, e, target))
        if detail is not None:
            detail(str(e).strip())
        return [], time.perf_counter() - t0
    return [USD_NAME], time.perf_counter() - t0
