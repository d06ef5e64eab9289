"""Strands from a USD file: ``scene.kind = "usd"`` reads ``UsdGeom.BasisCurves`` (the
format Houdini, Blender, Maya and Unreal exchange grooms in) as wisps.

Which prims: ``scene.prim_path`` names a BasisCurves prim, or a prim whose BasisCurves
descendants are all read (stage order); without it the stage must hold exactly one
BasisCurves prim (several are an error that lists them).  Every curve is one wisp, in
the order of the prims and of ``curveVertexCounts``.

What is read, all at one time code: ``points`` at the default time when it has a default
value (lc_petsc's own export stores the rest pose there), else at its first time sample
(an animated groom's first frame); ``curveVertexCounts``, ``widths`` and the prim's
local-to-world transform at that same time.  Positions are brought into lc_petsc's
frame: the world transform applied, scaled from the stage's ``metersPerUnit`` to cm
(USD's fallback is 0.01, i.e. cm; Blender writes 1, i.e. m), and a Z-up stage turned to
Y-up by (x, y, z) -> (x, z, -y), so gravity (0, -981, 0) points down in both.

Radii: ``widths`` / 2 (constant, uniform, varying or vertex interpolation), scaled like
the positions (by the cube root of the world transform's determinant); without widths
the config's ``material.root_radius`` -> ``tip_radius`` taper.  Pinned roots: an int or
bool primvar ``pinned`` (vertex or varying interpolation, non-zero = pinned; linear
curves only) on a prim that has it, else the first ``scene.n_pinned`` vertices of each
curve.

Cubic curves are resampled to polyline vertices by evaluating the curve with its USD
basis: each segment contributes the points at u = j / vstep, j = 0 .. vstep - 1 (vstep
3 for ``bezier``, 1 for ``bspline`` and ``catmullRom``), and the last segment its end
u = 1.  A bezier curve of 3k + 1 control points thus gives 3k + 1 vertices; a
nonperiodic bspline or catmullRom curve of n points has n - 3 segments and gives n - 2
vertices, with ``wrap = "pinned"`` (phantom end points 2 P0 - P1, 2 P(n-1) - P(n-2)) n
vertices, the first and last at the curve's ends.  Vertex-interpolated widths are
evaluated with the same basis, varying ones linearly between segment ends.  Periodic
(closed) curves cannot be strands and are refused.

Every problem (no such prim, not BasisCurves, counts that do not add up to the points,
too few vertices, non-finite points, widths of the wrong length or not positive, a
pinned primvar of the wrong type or length) is a ValueError naming the file, the prim,
the curve and what to fix, as for the HDF5 strands file.  Every rank reads the whole
file (USD has no partial reads; a groom of thousands of curves reads in well under a
second) and keeps its own wisps' slices.
"""

from __future__ import annotations

import numpy as np

from lc_petsc.errors import SceneError
from lc_petsc.scene.sources import ArraySource

CUBIC_VSTEP = {"bezier": 3, "bspline": 1, "catmullRom": 1}


def cubic_weights(basis, u):
    """Weights (len(u), 4) of a cubic segment's 4 control points at parameters ``u``."""
    u = np.asarray(u, float)[:, None]
    if basis == "bezier":
        w = [(1 - u) ** 3, 3 * u * (1 - u) ** 2, 3 * u ** 2 * (1 - u), u ** 3]
        return np.hstack(w)
    if basis == "bspline":
        w = [(1 - u) ** 3, 3 * u ** 3 - 6 * u ** 2 + 4, -3 * u ** 3 + 3 * u ** 2 + 3 * u + 1, u ** 3]
        return np.hstack(w) / 6.0
    if basis == "catmullRom":
        w = [-u ** 3 + 2 * u ** 2 - u, 3 * u ** 3 - 5 * u ** 2 + 2, -3 * u ** 3 + 4 * u ** 2 + u, u ** 3 - u ** 2]
        return np.hstack(w) / 2.0
    raise SceneError(f"unknown cubic basis {basis!r}")


def cubic_segments(n, basis, wrap):
    """Number of segments of a cubic curve of ``n`` control points, or None when ``n``
    does not make a valid curve."""
    if basis == "bezier":
        return (n - 1) // 3 if n >= 4 and (n - 4) % 3 == 0 else None
    if wrap == "pinned":
        return n - 1 if n >= 2 else None
    return n - 3 if n >= 4 else None


def resample_cubic(P, basis, wrap):
    """Polyline vertices of cubic curves: ``P`` (n_curves, n, d) control points (any
    trailing coordinates: positions, widths) -> (n_curves, m, d) with m = segments *
    vstep + 1 (module docstring)."""
    P = np.asarray(P, float)
    n = P.shape[1]
    if basis != "bezier" and wrap == "pinned":
        P = np.concatenate([2 * P[:, :1] - P[:, 1:2], P, 2 * P[:, -1:] - P[:, -2:-1]], axis=1)
    vstep = CUBIC_VSTEP[basis]
    nseg = cubic_segments(n, basis, wrap)
    W = cubic_weights(basis, np.arange(vstep) / vstep)                  # (vstep, 4)
    starts = vstep * np.arange(nseg)
    idx = starts[:, None] + np.arange(4)                                 # (nseg, 4)
    inner = np.einsum("jk,csk...->csj...", W, P[:, idx])                 # (c, nseg, vstep, d)
    inner = inner.reshape(P.shape[0], nseg * vstep, *P.shape[2:])
    end = np.einsum("k,ck...->c...", cubic_weights(basis, [1.0])[0], P[:, idx[-1]])
    return np.concatenate([inner, end[:, None]], axis=1)


def _varying_to_vertices(v, nseg, vstep):
    """Varying values (n_curves, nseg + 1) at segment ends -> (n_curves, nseg * vstep + 1)."""
    u = np.arange(nseg * vstep + 1) / vstep
    s = np.minimum(np.floor(u).astype(int), nseg - 1)
    f = u - s
    return v[:, s] * (1 - f) + v[:, s + 1] * f


def _pxr():
    try:
        from pxr import Tf, Usd, UsdGeom
    except ImportError as e:           # pragma: no cover - usd-core is a dependency
        raise SceneError(f"scene.kind = 'usd' needs Pixar's USD (pip install usd-core): {e}") from None
    return Tf, Usd, UsdGeom


class UsdCurves:
    """The curves of one BasisCurves prim, read and converted (module docstring):
    ``positions`` (n_vertices, 3) cm, ``offsets`` (n_curves + 1,), ``radius``
    (n_vertices,) or None, ``pinned`` (n_vertices,) bool or None."""

    def __init__(self, where, prim, scale, up_z):
        Tf, Usd, UsdGeom = _pxr()
        self.where = where = f"{where}, prim {prim.GetPath()}"
        curves = UsdGeom.BasisCurves(prim)
        pts_attr = curves.GetPointsAttr()
        t = Usd.TimeCode.Default()
        if pts_attr.Get(t) is None:
            samples = pts_attr.GetTimeSamples()
            if not samples:
                raise SceneError(f"{where}: has no points (neither a default value nor time samples)")
            t = Usd.TimeCode(samples[0])
        pts = np.asarray(pts_attr.Get(t), float).reshape(-1, 3)
        counts = curves.GetCurveVertexCountsAttr().Get(t)
        if counts is None or len(counts) == 0:
            raise SceneError(f"{where}: has no curveVertexCounts (one vertex count per curve is needed)")
        counts = np.asarray(counts, np.int64)
        if np.any(counts <= 0) or counts.sum() != len(pts):
            raise SceneError(f"{where}: curveVertexCounts add up to {int(counts.sum())} (smallest "
                             f"{int(counts.min())}) but there are {len(pts)} points; they must add up to "
                             "the point count, each at least 1")
        bad = ~np.isfinite(pts).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            c = int(np.searchsorted(np.cumsum(counts), i, side="right"))
            raise SceneError(f"{where}: point {i} (curve {c}) is not finite: {pts[i].tolist()}")
        kind = curves.GetTypeAttr().Get(t)
        basis = curves.GetBasisAttr().Get(t)
        wrap = curves.GetWrapAttr().Get(t)
        if wrap == "periodic":
            raise SceneError(f"{where}: wrap = 'periodic' (closed curves) cannot be hair strands; "
                             "export open curves (wrap 'nonperiodic' or 'pinned')")
        if kind not in ("linear", "cubic"):
            raise SceneError(f"{where}: type {kind!r} is not 'linear' or 'cubic'")
        if kind == "cubic" and basis not in CUBIC_VSTEP:
            raise SceneError(f"{where}: cubic basis {basis!r} is not one of {tuple(CUBIC_VSTEP)}")

        widths = curves.GetWidthsAttr().Get(t)
        w_interp = curves.GetWidthsInterpolation()
        if widths is not None and len(widths) == 0:
            widths = None
        if widths is not None:
            widths = np.asarray(widths, float)
        n_curves = len(counts)
        nseg = None
        if kind == "cubic":
            nseg = np.array([cubic_segments(int(n), basis, wrap) if cubic_segments(int(n), basis, wrap)
                             is not None else -1 for n in counts])
            if np.any(nseg < 0):
                c = int(np.flatnonzero(nseg < 0)[0])
                need = ("3k + 1 control points (4, 7, 10, ...)" if basis == "bezier"
                        else "at least 2 control points" if wrap == "pinned" else "at least 4 control points")
                raise SceneError(f"{where}: curve {c} has {int(counts[c])} control points; a {basis} "
                                 f"curve with wrap {wrap!r} needs {need}")
        pinned = self._pinned(curves, t, kind, len(pts), UsdGeom)

        # widths to one value per point (linear) or per control point / segment end (cubic)
        n_varying = int(len(pts) if kind == "linear" else (nseg + 1).sum())
        expected = {"constant": 1, "uniform": n_curves, "varying": n_varying,
                    "faceVarying": n_varying, "vertex": len(pts)}
        if widths is not None:
            if w_interp not in expected:
                raise SceneError(f"{where}: widths interpolation {w_interp!r} is not supported")
            if len(widths) != expected[w_interp]:
                fits = [k for k, n in expected.items() if n == len(widths)]
                raise SceneError(f"{where}: {len(widths)} widths with {w_interp!r} interpolation; "
                                 f"expected {expected[w_interp]}"
                                 + (f" (that many widths fit {fits[0]!r} interpolation: set the widths' "
                                    f"interpolation to it)" if fits else ""))
            if not np.all(np.isfinite(widths) & (widths > 0)):
                i = int(np.flatnonzero(~(np.isfinite(widths) & (widths > 0)))[0])
                raise SceneError(f"{where}: width {i} is {widths[i]!r}; widths must be finite and positive")

        # world transform, units, up axis
        M = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t), float)
        pts = pts @ M[:3, :3] + M[3, :3]
        if up_z:
            pts = np.column_stack([pts[:, 0], pts[:, 2], -pts[:, 1]])
        pts *= scale
        width_scale = scale * abs(float(np.linalg.det(M[:3, :3]))) ** (1.0 / 3.0)

        starts = np.concatenate([[0], np.cumsum(counts)])
        if kind == "linear":
            self.positions, sizes = pts, counts
            r = None
            if widths is not None:
                if w_interp == "constant":
                    r = np.full(len(pts), widths[0])
                elif w_interp == "uniform":
                    r = np.repeat(widths, counts)
                else:
                    r = widths
        else:
            vstep = CUBIC_VSTEP[basis]
            out_pts, out_r, sizes = [None] * n_curves, [None] * n_curves, vstep * nseg + 1
            vstarts = np.concatenate([[0], np.cumsum(nseg + 1)])
            for n in np.unique(counts):
                cs = np.flatnonzero(counts == n)
                idx = starts[cs][:, None] + np.arange(n)
                P = pts[idx]
                if widths is not None and w_interp == "vertex":
                    P = np.concatenate([P, widths[idx][..., None]], axis=2)
                Q = resample_cubic(P, basis, wrap)
                for k, c in enumerate(cs):
                    out_pts[c] = Q[k, :, :3]
                if widths is None:
                    continue
                m = Q.shape[1]
                if w_interp == "vertex":
                    rr = Q[:, :, 3]
                elif w_interp == "constant":
                    rr = np.full((len(cs), m), widths[0])
                elif w_interp == "uniform":
                    rr = np.repeat(widths[cs][:, None], m, axis=1)
                else:
                    s = int(nseg[cs[0]])
                    vv = widths[vstarts[cs][:, None] + np.arange(s + 1)]
                    rr = _varying_to_vertices(vv, s, vstep)
                for k, c in enumerate(cs):
                    out_r[c] = rr[k]
            self.positions = np.concatenate(out_pts)
            r = np.concatenate(out_r) if widths is not None else None
            if r is not None and not np.all(r > 0):
                c = int(np.searchsorted(np.cumsum(sizes), int(np.flatnonzero(r <= 0)[0]), side="right"))
                raise SceneError(f"{where}: curve {c}: the widths evaluated on the cubic curve are not "
                                 "positive (vertex widths overshoot); use varying or uniform widths")
        self.radius = None if r is None else 0.5 * width_scale * np.asarray(r, float)
        self.pinned = pinned
        self.offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        short = np.flatnonzero(np.diff(self.offsets) < 4)
        if len(short):
            c = int(short[0])
            extra = f" (resampled from {int(counts[c])} {basis} control points)" if kind == "cubic" else ""
            raise SceneError(f"{where}: curve {c} has {int(self.offsets[c + 1] - self.offsets[c])} "
                             f"vertices{extra}; a wisp needs at least 4")

    def _pinned(self, curves, t, kind, n_points, UsdGeom):
        pv = UsdGeom.PrimvarsAPI(curves.GetPrim()).GetPrimvar("pinned")
        if not pv or not pv.HasValue():
            return None
        where = self.where
        if kind != "linear":
            raise SceneError(f"{where}: primvars:pinned is read on linear curves only; remove it "
                             "(the first scene.n_pinned vertices of each curve are then pinned) or "
                             "export linear curves")
        tname = str(pv.GetTypeName())
        if tname not in ("int[]", "bool[]"):
            raise SceneError(f"{where}: primvars:pinned has type {tname}; expected int[] or bool[] "
                             "(non-zero = pinned)")
        if pv.GetInterpolation() not in ("vertex", "varying"):
            raise SceneError(f"{where}: primvars:pinned has {pv.GetInterpolation()!r} interpolation; "
                             "expected 'vertex' (one value per point)")
        v = pv.Get(t)
        v = np.asarray(v if v is not None else [], np.int64)
        if len(v) != n_points:
            raise SceneError(f"{where}: primvars:pinned has {len(v)} values; expected one per point "
                             f"({n_points})")
        return v != 0


def _stage_curves(path, prim_path):
    """The BasisCurves prims to read, and (scale to cm, Z-up?) of the stage."""
    Tf, Usd, UsdGeom = _pxr()
    where = f"USD file {path}"
    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as e:
        # USD's text is "Error in '<C++ function>' at line N in file <source> : '<reason>'",
        # one per line, the most specific first (a truncated .usda: its parse error, then
        # only "Failed to open layer", which was all the message said)
        from lc_petsc.io.usd import usd_reasons
        reason = "; ".join(usd_reasons(e))
        raise SceneError(f"{where}: cannot open it as USD ({reason}): damaged, truncated or not USD; "
                         "scene.path must be a .usd, .usda or .usdc file") from None
    if stage is None:
        raise SceneError(f"{where}: cannot open it as USD")
    every = [p for p in stage.Traverse() if p.IsA(UsdGeom.BasisCurves)]
    listing = ", ".join(str(p.GetPath()) for p in every[:10]) + (" ..." if len(every) > 10 else "")
    if prim_path:
        prim = stage.GetPrimAtPath(prim_path)
        if not prim or not prim.IsValid():
            raise SceneError(f"{where}: no prim at scene.prim_path = {prim_path!r}; BasisCurves prims "
                             f"in the file: {listing or 'none'}")
        chosen = [p for p in Usd.PrimRange(prim) if p.IsA(UsdGeom.BasisCurves)]
        if not chosen:
            raise SceneError(f"{where}: scene.prim_path = {prim_path!r} is a {prim.GetTypeName() or 'typeless'} "
                             f"prim with no BasisCurves at or under it; BasisCurves prims in the file: "
                             f"{listing or 'none'}")
    else:
        if not every:
            kinds = sorted({str(p.GetTypeName()) for p in stage.Traverse() if p.GetTypeName()})
            raise SceneError(f"{where}: holds no BasisCurves prim (prim types found: "
                             f"{', '.join(kinds) or 'none'}); export the groom as USD curves "
                             "(BasisCurves)")
        if len(every) > 1:
            raise SceneError(f"{where}: holds {len(every)} BasisCurves prims ({listing}); set "
                             "scene.prim_path to the one to read, or to a prim above those to read")
        chosen = every
    mpu = float(UsdGeom.GetStageMetersPerUnit(stage))
    up_z = UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    return stage, chosen, mpu / 0.01, up_z


class UsdSource(ArraySource):
    """``scene.kind = "usd"``: the BasisCurves of the USD file ``path`` (module docstring)."""

    def __init__(self, path, prim_path=None, n_pinned=4, root_radius=0.05, tip_radius=0.05):
        self.path, self.prim_path = str(path), prim_path
        self.description = f"USD file {self.path}"
        stage, prims, scale, up_z = _stage_curves(self.path, prim_path)
        parts = [UsdCurves(self.description, p, scale, up_z) for p in prims]
        pos = np.concatenate([c.positions for c in parts])
        offsets = np.concatenate([[0]] + [c.offsets[1:] + s for c, s in
                                          zip(parts, np.cumsum([0] + [c.offsets[-1] for c in parts[:-1]]))])
        have_r = [c.radius is not None for c in parts]
        radius = None
        if any(have_r):
            if not all(have_r):
                missing = [str(p.GetPath()) for p, h in zip(prims, have_r) if not h]
                raise SceneError(f"{self.description}: prims {', '.join(missing)} have no widths while "
                                 "others have; give every prim widths, or none (then material.root_radius "
                                 "-> tip_radius is used)")
            radius = np.concatenate([c.radius for c in parts])
        pinned = None
        if any(c.pinned is not None for c in parts):
            from lc_petsc.scene.sources import _pin_first
            pinned = np.concatenate([c.pinned if c.pinned is not None else
                                     _pin_first(np.diff(c.offsets), n_pinned) for c in parts])
        del stage
        super().__init__(pos, offsets, radius=radius, pinned=pinned, n_pinned=n_pinned,
                         root_radius=root_radius, tip_radius=tip_radius)
