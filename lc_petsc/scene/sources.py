"""Scene sources: where the wisps come from, loadable wisp range by wisp range.

A source knows the number of wisps and their vertex counts (one integer per wisp, the
only global array any rank holds) and builds or reads the rest geometry of any
contiguous range of wisps.  ``parallel.partition`` decides the range of each rank.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from lc_petsc.scene import geometry


@dataclass
class WispBatch:
    """Rest geometry of the contiguous wisps ``first_wisp .. first_wisp + n - 1``."""

    first_wisp: int
    offsets: np.ndarray             # (n_wisps_local + 1,) local vertex offsets
    positions: np.ndarray           # (n_vertices_local, 3) rest positions
    radius: np.ndarray              # (n_vertices_local,)
    pinned: np.ndarray              # (n_vertices_local,) bool
    youngs_modulus: Optional[np.ndarray] = None   # (n_wisps_local,) overrides
    density: Optional[np.ndarray] = None          # (n_wisps_local,) overrides

    @property
    def n_wisps(self) -> int:
        return len(self.offsets) - 1

    @property
    def n_vertices(self) -> int:
        return int(self.offsets[-1])


class SceneSource:
    n_wisps: int
    sizes: np.ndarray

    def load(self, w0: int, w1: int) -> WispBatch:  # pragma: no cover - interface
        raise NotImplementedError


def _pin_first(sizes, n_pinned):
    parts = []
    for n in sizes:
        p = np.zeros(int(n), bool)
        p[: min(n_pinned, int(n))] = True
        parts.append(p)
    return np.concatenate(parts) if parts else np.zeros(0, bool)


class ArraySource(SceneSource):
    """Wisps given as global arrays (tests, small user scenes)."""

    def __init__(self, positions, offsets, radius=None, pinned=None, n_pinned: int = 2,
                 youngs_modulus=None, density=None, root_radius=0.05, tip_radius=0.05):
        self.positions = np.asarray(positions, float)
        self.offsets = np.asarray(offsets, np.int64)
        if self.offsets.ndim != 1 or len(self.offsets) < 2 or self.offsets[0] != 0 \
                or np.any(np.diff(self.offsets) < 0) or self.offsets[-1] != len(self.positions):
            raise ValueError(
                "wisp_offsets must start at 0, be non-decreasing and end at the vertex count "
                f"{len(self.positions)}, got {self.offsets[:5]}...{self.offsets[-3:]}")
        if self.positions.ndim != 2 or self.positions.shape[1] != 3:
            raise ValueError(f"positions must have shape (n_vertices, 3), got {self.positions.shape}")
        self.sizes = np.diff(self.offsets)
        self.n_wisps = len(self.sizes)
        if radius is None:
            radius = np.concatenate([geometry.tapered_radius(int(n), root_radius, tip_radius)
                                     for n in self.sizes])
        self.radius = np.asarray(radius, float)
        self.pinned = (np.asarray(pinned, bool) if pinned is not None
                       else _pin_first(self.sizes, n_pinned))
        self.youngs = None if youngs_modulus is None else np.asarray(youngs_modulus, float)
        self.dens = None if density is None else np.asarray(density, float)

    def load(self, w0, w1):
        a, b = int(self.offsets[w0]), int(self.offsets[w1])
        return WispBatch(
            first_wisp=w0, offsets=self.offsets[w0:w1 + 1] - a,
            positions=self.positions[a:b].copy(), radius=self.radius[a:b].copy(),
            pinned=self.pinned[a:b].copy(),
            youngs_modulus=None if self.youngs is None else self.youngs[w0:w1].copy(),
            density=None if self.dens is None else self.dens[w0:w1].copy())


class FileSource(SceneSource):
    """HDF5 strands file (DESIGN section 3): ``/positions``, ``/wisp_offsets``, optional
    ``/radius``, ``/pinned``; extension: optional per-wisp ``/youngs_modulus`` and
    ``/density``.  Each rank reads only its own wisps' slices."""

    def __init__(self, path, n_pinned=4, root_radius=0.05, tip_radius=0.05):
        import h5py
        self.path = str(path)
        self.n_pinned, self.root_radius, self.tip_radius = n_pinned, root_radius, tip_radius
        with h5py.File(self.path, "r") as f:
            for key in ("positions", "wisp_offsets"):
                if key not in f:
                    raise ValueError(f"strands file {self.path}: missing dataset /{key}")
            self.offsets = np.asarray(f["wisp_offsets"][...], np.int64)
            nv = f["positions"].shape[0]
            if f["positions"].ndim != 2 or f["positions"].shape[1] != 3:
                raise ValueError(f"strands file {self.path}: /positions must be (n_vertices, 3), "
                                 f"got {f['positions'].shape}")
        if self.offsets.ndim != 1 or len(self.offsets) < 2 or self.offsets[0] != 0 \
                or np.any(np.diff(self.offsets) < 0) or self.offsets[-1] != nv:
            raise ValueError(f"strands file {self.path}: /wisp_offsets must start at 0, be "
                             f"non-decreasing and end at {nv}")
        self.sizes = np.diff(self.offsets)
        self.n_wisps = len(self.sizes)

    def load(self, w0, w1):
        import h5py
        a, b = int(self.offsets[w0]), int(self.offsets[w1])
        with h5py.File(self.path, "r") as f:
            pos = np.asarray(f["positions"][a:b], float)
            if "radius" in f:
                rad = np.asarray(f["radius"][a:b], float)
            else:
                rad = np.concatenate([geometry.tapered_radius(int(n), self.root_radius, self.tip_radius)
                                      for n in self.sizes[w0:w1]] or [np.zeros(0)])
            pin = (np.asarray(f["pinned"][a:b], bool) if "pinned" in f
                   else _pin_first(self.sizes[w0:w1], self.n_pinned))
            ym = np.asarray(f["youngs_modulus"][w0:w1], float) if "youngs_modulus" in f else None
            de = np.asarray(f["density"][w0:w1], float) if "density" in f else None
        return WispBatch(first_wisp=w0, offsets=self.offsets[w0:w1 + 1] - a, positions=pos,
                         radius=rad, pinned=pin, youngs_modulus=ym, density=de)


class GeneratedSource(SceneSource):
    """``wisp4c``, ``straight`` and ``hairball`` scenes, built wisp by wisp."""

    def __init__(self, kind, n_wisps=1, n_vertices=101, seed=0, n_pinned=4,
                 segment=0.6, direction=(0.0, -1.0, 0.0), root_radius=0.35, tip_radius=0.07,
                 head_radius=15.0):
        self.kind, self.seed, self.n_pinned = kind, seed, n_pinned
        self.segment, self.direction = segment, direction
        self.root_radius, self.tip_radius, self.head_radius = root_radius, tip_radius, head_radius
        self.n_wisps = int(n_wisps) if kind == "hairball" else 1
        nv = 101 if kind == "hairball" else int(n_vertices)
        self.sizes = np.full(self.n_wisps, nv, np.int64)

    def wisp(self, w):
        n = int(self.sizes[w])
        if self.kind == "wisp4c":
            x = geometry.wisp4c(n)
        elif self.kind == "straight":
            x = geometry.straight(n, self.segment, direction=self.direction)
        elif self.kind == "hairball":
            normal, frame = geometry.hairball_root(w, self.n_wisps, self.seed)
            x = geometry.place(geometry.wisp4c_local(n), self.head_radius * normal, normal, frame=frame)
        else:
            raise ValueError(f"unknown generated scene kind {self.kind!r}")
        return x

    def load(self, w0, w1):
        xs = [self.wisp(w) for w in range(w0, w1)]
        sizes = self.sizes[w0:w1]
        off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        rad = np.concatenate([geometry.tapered_radius(int(n), self.root_radius, self.tip_radius)
                              for n in sizes] or [np.zeros(0)])
        return WispBatch(first_wisp=w0, offsets=off,
                         positions=np.concatenate(xs) if xs else np.zeros((0, 3)),
                         radius=rad, pinned=_pin_first(sizes, self.n_pinned))


def source_from_config(scene, material, physics) -> SceneSource:
    """Scene source of a validated :class:`lc_petsc.config.SimConfig`'s tables."""
    rr, tr = material.root_radius, material.tip_radius
    if scene.kind == "file":
        return FileSource(scene.path, n_pinned=scene.n_pinned, root_radius=rr, tip_radius=tr)
    if scene.kind == "hairball" and material.radius_scale_with_count:
        s = min(1.0, float(np.sqrt(2000.0 / scene.n_wisps)))
        rr, tr = rr * s, tr * s
    # roots sit on a sphere of radius 15 (SPEC 6): the head sphere (15.25) encloses them
    return GeneratedSource(scene.kind, n_wisps=scene.n_wisps, n_vertices=scene.n_vertices,
                           seed=scene.seed, n_pinned=scene.n_pinned, segment=scene.segment_length,
                           direction=scene.direction, root_radius=rr, tip_radius=tr, head_radius=15.0)
