"""Scene sources: where the wisps come from, loadable wisp range by wisp range.

A source knows the number of wisps and their vertex counts (one integer per wisp, the
only global array any rank holds) and builds or reads the rest geometry of any
contiguous range of wisps.  ``parallel.partition`` decides the range of each rank.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from lc_petsc.errors import ConfigError, SceneError
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
    #: (n_wisps_local,) the wisps' numbers in the scene's own order (default: contiguous
    #: from first_wisp); differs when the simulator renumbers them (ReorderedSource)
    scene_ids: Optional[np.ndarray] = None

    @property
    def n_wisps(self) -> int:
        """Number of wisps in the batch."""
        return len(self.offsets) - 1

    def ids(self) -> np.ndarray:
        """The wisps' numbers in the scene's order: for messages and per-wisp seeds."""
        if self.scene_ids is not None:
            return self.scene_ids
        return np.arange(self.first_wisp, self.first_wisp + self.n_wisps)

    @property
    def n_vertices(self) -> int:
        """Number of vertices in the batch."""
        return int(self.offsets[-1])


class SceneSource:
    """Where wisps come from: ``n_wisps``, their vertex counts ``sizes`` and :meth:`load`."""

    n_wisps: int
    sizes: np.ndarray
    #: where the wisps come from, for messages ("strands file PATH", "USD file PATH");
    #: empty for generated and in-memory scenes
    description: str = ""

    def load(self, w0: int, w1: int) -> WispBatch:  # pragma: no cover - interface
        """The wisps ``w0 .. w1 - 1`` (global indices) as a :class:`WispBatch`."""
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
            raise SceneError(
                "wisp_offsets must start at 0, be non-decreasing and end at the vertex count "
                f"{len(self.positions)}, got {self.offsets[:5]}...{self.offsets[-3:]}")
        if self.positions.ndim != 2 or self.positions.shape[1] != 3:
            raise SceneError(f"positions must have shape (n_vertices, 3), got {self.positions.shape}")
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
        """The wisps ``w0 .. w1 - 1`` (global indices) as a :class:`WispBatch`."""
        a, b = int(self.offsets[w0]), int(self.offsets[w1])
        return WispBatch(
            first_wisp=w0, offsets=self.offsets[w0:w1 + 1] - a,
            positions=self.positions[a:b].copy(), radius=self.radius[a:b].copy(),
            pinned=self.pinned[a:b].copy(),
            youngs_modulus=None if self.youngs is None else self.youngs[w0:w1].copy(),
            density=None if self.dens is None else self.dens[w0:w1].copy())


#: memory a run needs per vertex, a lower estimate (element Hessians and gradients, the
#: BAIJ matrix and its ILU factor, the state vectors); :func:`memory_shortfall` refuses a
#: strands file or a generated scene whose vertex count cannot fit in the memory of the
#: job's nodes even at this rate
BYTES_PER_VERTEX = 4096
#: rows read at a time when the whole of a dataset is checked (constant memory)
_CHECK_ROWS = 1 << 20
#: dataset -> (kinds allowed, their description), numpy dtype kinds
_KINDS = {"positions": ("f", "real floating-point numbers (float32/float64)"),
          "wisp_offsets": ("iu", "integers"),
          "radius": ("f", "real floating-point numbers"),
          "pinned": ("biu", "booleans (or integers 0/1)"),
          "youngs_modulus": ("f", "real floating-point numbers"),
          "density": ("f", "real floating-point numbers")}


def machine_memory() -> int:
    """Physical memory of this machine in bytes."""
    import os
    return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def job_nodes(environ=None) -> int:
    """Number of machines (nodes) this MPI job spans, from the launcher's environment,
    without communicating (the strands-file check runs before any collective).

    Open MPI (the only MPI here) exports the job's rank count and the rank count on this
    node: nodes = ceil(world / local), assuming ranks spread evenly, as mpiexec does by
    default.  Slurm's ``SLURM_JOB_NUM_NODES`` is used where Open MPI's are missing; a
    process started without either is one node."""
    import os
    env = os.environ if environ is None else environ
    try:
        world = int(env.get("OMPI_COMM_WORLD_SIZE", 0))
        local = int(env.get("OMPI_COMM_WORLD_LOCAL_SIZE", 0))
        if world > 0 and local > 0:
            return max(1, -(-world // local))
        return max(1, int(env.get("SLURM_JOB_NUM_NODES", 1)))
    except ValueError:
        return 1


def memory_shortfall(n_vertices, n_wisps):
    """None when a run of ``n_vertices`` vertices in ``n_wisps`` wisps fits in the memory
    of the job's nodes (:func:`job_nodes` of this machine's size) at
    :data:`BYTES_PER_VERTEX`, else what it needs against what there is (for the caller's
    message, which names the key or dataset)."""
    # the run's memory is spread over every node of the job, not held by one
    nodes = job_nodes()
    need, have = BYTES_PER_VERTEX * n_vertices + 8 * (n_wisps + 1), machine_memory() * nodes
    if need <= have:
        return None
    on = "this machine has" if nodes == 1 else f"this job's {nodes} nodes have"
    return (f"a run needs at least {BYTES_PER_VERTEX} bytes per vertex, {need / 1e9:.3g} GB, "
            f"and {on} {have / 1e9:.3g} GB of memory")


def _chunks(dset, n):
    for a in range(0, n, _CHECK_ROWS):
        yield dset[a:min(n, a + _CHECK_ROWS)]


def check_strands_file(path):
    """Validate the strands file ``path`` before anything large is read; returns the wisp
    offsets (n_wisps + 1,).  Every problem is a one-line SceneError naming the file and
    the dataset: not HDF5, empty or truncated; a dataset that is missing, a group, a soft
    or external link, stored in external files or virtual; the wrong type (complex,
    strings, float offsets or pins); the wrong shape or length; values out of range; a
    vertex count whose run cannot fit in the memory of the job's nodes (:func:`job_nodes`
    of this machine's size)."""
    import os
    import h5py
    where = f"strands file {path}"
    try:
        size = os.path.getsize(path)
    except OSError as e:
        raise SceneError(f"{where}: cannot be read ({e.strerror or e})") from None
    if size == 0:
        raise SceneError(f"{where}: the file is empty (0 bytes), not an HDF5 strands file")
    try:
        if not h5py.is_hdf5(path):
            raise SceneError(f"{where}: not an HDF5 file (a strands file has /positions and /wisp_offsets)")
        f = h5py.File(path, "r")
    except OSError as e:
        raise SceneError(f"{where}: unreadable or truncated HDF5 file ({str(e).split(' (')[0]})") from None
    try:
        with f:
            dsets = {}
            for name in _KINDS:
                link = f.get(name, getlink=True)
                if link is None:
                    if name in ("positions", "wisp_offsets"):
                        raise SceneError(f"{where}: missing dataset /{name}")
                    continue
                if isinstance(link, (h5py.SoftLink, h5py.ExternalLink)):
                    kind = "a soft link" if isinstance(link, h5py.SoftLink) else "an external link"
                    raise SceneError(f"{where}: /{name} is {kind}; store the dataset itself in the file")
                d = f.get(name)
                if not isinstance(d, h5py.Dataset):
                    raise SceneError(f"{where}: /{name} is a {type(d).__name__.lower()}, not a dataset")
                if d.is_virtual or d.id.get_create_plist().get_external_count() > 0:
                    raise SceneError(f"{where}: /{name} keeps its data in other files (external or "
                                     "virtual storage); store the dataset itself in the file")
                kinds, what = _KINDS[name]
                if d.dtype.kind not in kinds or d.dtype.fields is not None:
                    raise SceneError(f"{where}: /{name} has type {d.dtype}, expected {what}")
                dsets[name] = d
            pos, off = dsets["positions"], dsets["wisp_offsets"]
            if pos.ndim != 2 or pos.shape[1] != 3:
                raise SceneError(f"{where}: /positions must be (n_vertices, 3), got {pos.shape}")
            nv = int(pos.shape[0])
            if off.ndim != 1 or off.shape[0] < 2:
                raise SceneError(f"{where}: /wisp_offsets must be 1-D with n_wisps + 1 >= 2 entries, "
                                 f"got shape {off.shape}")
            nw = int(off.shape[0]) - 1
            short = memory_shortfall(nv, nw)
            if short:
                raise SceneError(f"{where}: /positions declares {nv:,} vertices; {short}; run on more "
                                 "nodes or use a smaller groom")
            for name, n in (("radius", nv), ("pinned", nv), ("youngs_modulus", nw), ("density", nw)):
                if name in dsets and dsets[name].shape != (n,):
                    per = "vertex" if n == nv else "wisp"
                    raise SceneError(f"{where}: /{name} must have one entry per {per}, shape ({n},), "
                                     f"got {dsets[name].shape}")
            try:
                offsets = np.asarray(off[...], np.int64)
                if offsets[0] != 0 or np.any(np.diff(offsets) < 0) or offsets[-1] != nv:
                    raise SceneError(f"{where}: /wisp_offsets must start at 0, be non-decreasing and end "
                                     f"at the vertex count {nv}")
                for k, a in enumerate(_chunks(pos, nv)):
                    bad = ~np.isfinite(a).all(axis=1)
                    if bad.any():
                        # the row and its wisp: a groom of 1e5 vertices is not searched by hand
                        j = int(np.flatnonzero(bad)[0])
                        i = k * _CHECK_ROWS + j
                        w = int(np.searchsorted(offsets, i, side="right")) - 1
                        raise SceneError(f"{where}: /positions must be finite; vertex {i} (wisp {w}, "
                                         f"its vertex {i - int(offsets[w])}) has {a[j].tolist()}")
                for name, per in (("radius", "vertex"), ("youngs_modulus", "wisp"), ("density", "wisp")):
                    if name in dsets:
                        for k, a in enumerate(_chunks(dsets[name], dsets[name].shape[0])):
                            bad = ~(np.isfinite(a) & (a > 0))
                            if bad.any():
                                i = k * _CHECK_ROWS + int(np.flatnonzero(bad)[0])
                                raise SceneError(f"{where}: /{name} must be finite and positive; "
                                                 f"{per} {i} has {a[i - k * _CHECK_ROWS]!r}")
                if "pinned" in dsets and dsets["pinned"].dtype.kind != "b":
                    for a in _chunks(dsets["pinned"], nv):
                        if not np.isin(a, (0, 1)).all():
                            raise SceneError(f"{where}: /pinned holds values other than 0 and 1")
            except OSError as e:
                raise SceneError(f"{where}: a dataset cannot be read, the file is truncated or "
                                 f"corrupt ({str(e).split(' (')[0]})") from None
            return offsets
    except ValueError:
        raise
    except (OSError, RuntimeError, KeyError) as e:
        raise SceneError(f"{where}: unreadable HDF5 file ({str(e).split(' (')[0]})") from None


class FileSource(SceneSource):
    """HDF5 strands file (DESIGN section 3): ``/positions``, ``/wisp_offsets``, optional
    ``/radius``, ``/pinned``; extension: optional per-wisp ``/youngs_modulus`` and
    ``/density``.  The whole file is checked first (:func:`check_strands_file`, every
    rank reaching the same verdict); then each rank reads only its own wisps' slices."""

    def __init__(self, path, n_pinned=4, root_radius=0.05, tip_radius=0.05):
        self.path = str(path)
        self.description = f"strands file {self.path}"
        self.n_pinned, self.root_radius, self.tip_radius = n_pinned, root_radius, tip_radius
        self.offsets = check_strands_file(self.path)
        self.sizes = np.diff(self.offsets)
        self.n_wisps = len(self.sizes)

    def load(self, w0, w1):
        """The wisps ``w0 .. w1 - 1`` (global indices) as a :class:`WispBatch`."""
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
    """``wisp4c``, ``straight`` and ``hairball`` scenes, built wisp by wisp; one whose run
    cannot fit in memory (:func:`memory_shortfall`) is a ConfigError naming the key."""

    def __init__(self, kind, n_wisps=1, n_vertices=101, seed=0, n_pinned=4,
                 segment=0.6, direction=(0.0, -1.0, 0.0), root_radius=0.35, tip_radius=0.07,
                 head_radius=15.0):
        self.kind, self.seed, self.n_pinned = kind, seed, n_pinned
        self.segment, self.direction = segment, direction
        self.root_radius, self.tip_radius, self.head_radius = root_radius, tip_radius, head_radius
        self.n_wisps = int(n_wisps) if kind == "hairball" else 1
        nv = 101 if kind == "hairball" else int(n_vertices)
        # before anything of that size is allocated (an absurd n_wisps built for hours)
        short = memory_shortfall(self.n_wisps * nv, self.n_wisps)
        if short:
            what = (f"scene.n_wisps = {self.n_wisps}: {self.n_wisps:,} wisps of {nv} vertices "
                    f"({self.n_wisps * nv:,} vertices); {short}; use fewer wisps" if kind == "hairball"
                    else f"scene.n_vertices = {nv}: {short}; use fewer vertices")
            raise ConfigError(f"{what} or run on more nodes")
        self.sizes = np.full(self.n_wisps, nv, np.int64)

    def wisp(self, w):
        """Rest positions (n, 3) of wisp ``w``, from the seed and ``w`` alone (any rank can build it)."""
        n = int(self.sizes[w])
        if self.kind == "wisp4c":
            x = geometry.wisp4c(n)
        elif self.kind == "straight":
            x = geometry.straight(n, self.segment, direction=self.direction)
        elif self.kind == "hairball":
            normal, frame = geometry.hairball_root(w, self.n_wisps, self.seed)
            x = geometry.place(geometry.wisp4c_local(n), self.head_radius * normal, normal, frame=frame)
        else:
            raise SceneError(f"unknown generated scene kind {self.kind!r}")
        return x

    def load(self, w0, w1):
        """The wisps ``w0 .. w1 - 1`` (global indices) as a :class:`WispBatch`."""
        xs = [self.wisp(w) for w in range(w0, w1)]
        sizes = self.sizes[w0:w1]
        off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        rad = np.concatenate([geometry.tapered_radius(int(n), self.root_radius, self.tip_radius)
                              for n in sizes] or [np.zeros(0)])
        return WispBatch(first_wisp=w0, offsets=off,
                         positions=np.concatenate(xs) if xs else np.zeros((0, 3)),
                         radius=rad, pinned=_pin_first(sizes, self.n_pinned))


def wisp_roots(source, chunk=512):
    """First vertex (n_wisps, 3) of every wisp of ``source``, read ``chunk`` wisps at a
    time (memory bounded by the chunk)."""
    roots = np.empty((source.n_wisps, 3))
    for w0 in range(0, source.n_wisps, chunk):
        w1 = min(source.n_wisps, w0 + chunk)
        batch = source.load(w0, w1)
        roots[w0:w1] = batch.positions[batch.offsets[:-1]]
    return roots


class ReorderedSource(SceneSource):
    """``source`` with its wisps renumbered: wisp i here is wisp ``order[i]`` there.

    A rank's wisps are loaded as runs of consecutive source wisps; when they are
    scattered (a shuffled groom), as one covering range that is then cut (at most the
    whole scene's rest state, transiently)."""

    #: more runs than this: load the covering range instead of run by run
    MAX_RUNS = 32

    def __init__(self, source, order):
        self.source = source
        self.description = source.description
        self.order = np.asarray(order, np.int64)
        if not np.array_equal(np.sort(self.order), np.arange(source.n_wisps)):
            raise ValueError(f"a wisp order must be a permutation of the {source.n_wisps} wisps")
        self.n_wisps = source.n_wisps
        self.sizes = np.asarray(source.sizes)[self.order]

    def _load(self, w0, w1):
        want = self.order[w0:w1]
        if len(want) == 0:
            return _renumbered(self.source.load(0, 0), [], w0)
        breaks = np.flatnonzero(np.diff(want) != 1) + 1
        if len(breaks) + 1 <= self.MAX_RUNS:
            parts = []
            for run in np.split(want, breaks):
                b = self.source.load(int(run[0]), int(run[-1]) + 1)
                parts.append((b, np.arange(len(run))))
            return _concat([_renumbered(b, idx, 0) for b, idx in parts], w0)
        lo, hi = int(want.min()), int(want.max()) + 1
        return _renumbered(self.source.load(lo, hi), want - lo, w0)

    def load(self, w0, w1):
        """Wisps w0:w1 in the partition's order, with their scene numbers."""
        batch = self._load(w0, w1)
        batch.scene_ids = self.order[w0:w1].copy()
        return batch


def _renumbered(batch, idx, first_wisp):
    """The wisps ``idx`` (in that order) of ``batch`` as a new batch."""
    idx = np.asarray(idx, np.int64)
    off = batch.offsets
    rows = (np.concatenate([np.arange(off[i], off[i + 1]) for i in idx]) if len(idx)
            else np.zeros(0, np.int64))
    sizes = off[idx + 1] - off[idx]
    return WispBatch(first_wisp=first_wisp,
                     offsets=np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
                     positions=batch.positions[rows], radius=batch.radius[rows],
                     pinned=batch.pinned[rows],
                     youngs_modulus=None if batch.youngs_modulus is None else batch.youngs_modulus[idx],
                     density=None if batch.density is None else batch.density[idx])


def _concat(batches, first_wisp):
    """Batches one after the other as one batch starting at wisp ``first_wisp``."""
    sizes = np.concatenate([np.diff(b.offsets) for b in batches])

    def cat(name):
        vals = [getattr(b, name) for b in batches]
        return None if any(v is None for v in vals) else np.concatenate(vals)
    return WispBatch(first_wisp=first_wisp,
                     offsets=np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
                     positions=np.concatenate([b.positions for b in batches]),
                     radius=cat("radius"), pinned=cat("pinned"),
                     youngs_modulus=cat("youngs_modulus"), density=cat("density"))


def source_from_config(scene, material, physics) -> SceneSource:
    """Scene source of a validated :class:`lc_petsc.config.SimConfig`'s tables."""
    rr, tr = material.root_radius, material.tip_radius
    if scene.kind == "file":
        return FileSource(scene.path, n_pinned=scene.n_pinned, root_radius=rr, tip_radius=tr)
    if scene.kind == "usd":
        from lc_petsc.scene.usd_source import UsdSource
        return UsdSource(scene.path, prim_path=scene.prim_path, n_pinned=scene.n_pinned,
                         root_radius=rr, tip_radius=tr)
    if scene.kind == "hairball" and material.radius_scale_with_count:
        s = min(1.0, float(np.sqrt(2000.0 / scene.n_wisps)))
        rr, tr = rr * s, tr * s
    # roots sit on a sphere of radius 15 (SPEC 6): the head sphere (15.25) encloses them
    return GeneratedSource(scene.kind, n_wisps=scene.n_wisps, n_vertices=scene.n_vertices,
                           seed=scene.seed, n_pinned=scene.n_pinned, segment=scene.segment_length,
                           direction=scene.direction, root_radius=rr, tip_radius=tr, head_radius=15.0)
