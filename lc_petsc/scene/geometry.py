"""Wisp geometry of SPEC section 6: the 4C helix wisp, straight strands, hairball roots.

Everything here is per wisp and deterministic: a hairball wisp ``w`` depends only on
``(seed, w, n_wisps)``, so any rank can build exactly the wisps it owns and every rank
count sees the identical scene.
"""

from __future__ import annotations

import numpy as np

GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))

# 4C wisp of the paper's reference implementation (SPEC 6)
HELIX_RADIUS = 0.5          # cm
HELIX_STEP_DEG = 72.0       # 5 vertices per turn
HELIX_RISE = 0.1            # cm per vertex along the axis
STEM_VERTICES = 3           # straight stem below the first helix vertex
STEM_SEGMENT = 0.6          # cm, close to the helix edge (0.596 cm)


def wisp4c_local(n_vertices: int = 101) -> np.ndarray:
    """4C wisp in its local frame (columns u, w, a): root at the origin, axis +a.

    Vertices 0..2 form a straight stem of 0.6 cm edges along the axis; vertex 3 on is a
    helix of radius 0.5 cm (72 degrees and 0.1 cm of rise per vertex) whose first vertex
    continues the stem, so the helix axis is offset by -0.5 u from the stem.
    """
    n_stem = min(STEM_VERTICES, n_vertices)
    out = np.zeros((n_vertices, 3))
    out[:n_stem, 2] = STEM_SEGMENT * np.arange(n_stem)
    k = np.arange(n_vertices - n_stem)
    th = np.deg2rad(HELIX_STEP_DEG) * k
    out[n_stem:, 0] = HELIX_RADIUS * (np.cos(th) - 1.0)
    out[n_stem:, 1] = HELIX_RADIUS * np.sin(th)
    out[n_stem:, 2] = STEM_SEGMENT * n_stem + HELIX_RISE * k
    return out


def frame_about(axis, spin: float = 0.0) -> np.ndarray:
    """Orthonormal 3x3 matrix with columns (u, w, a), a = axis, (u, w) spun by ``spin``."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    ref = np.array([0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(a, ref)
    u /= np.linalg.norm(u)
    w = np.cross(a, u)
    c, s = np.cos(spin), np.sin(spin)
    return np.column_stack([c * u + s * w, -s * u + c * w, a])


def place(local: np.ndarray, root, axis, spin: float = 0.0, frame=None) -> np.ndarray:
    """``local`` (columns u, w, a) placed at ``root``: in ``frame`` (3, 3) if given, else
    in :func:`frame_about` ``(axis, spin)``."""
    F = frame_about(axis, spin) if frame is None else np.asarray(frame, float)
    return np.asarray(root, float) + local @ F.T


def wisp4c(n_vertices: int = 101, root=(0.0, 0.0, 0.0), axis=(0.0, -1.0, 0.0), spin: float = 0.0):
    """The 4C wisp hanging from ``root`` along ``axis`` (default: down, -y)."""
    return place(wisp4c_local(n_vertices), root, axis, spin)


def straight(n_vertices: int, segment: float = 0.6, root=(0.0, 0.0, 0.0), direction=(0.0, -1.0, 0.0)):
    """A straight wisp of ``n_vertices`` vertices ``segment`` apart from ``root`` along ``direction`` (n, 3)."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    return np.asarray(root, float) + segment * np.arange(n_vertices)[:, None] * d


def hairball_root(w: int, n_wisps: int, seed: int):
    """Root normal and frame of hairball wisp ``w``: a Fibonacci point set, all wisps in
    phase.

    Points k + 1/2 of a Fibonacci spiral on the upper (y >= 0) hemisphere are evenly
    spread with a spacing of about sqrt(2 pi / N) (times the head radius).  Every wisp's
    helix has the same phase in a frame field that varies smoothly over the hemisphere
    (:func:`smooth_frame`), so neighbouring helices are nearly translated copies of each
    other: two helices of equal radius, pitch and phase translated sideways never
    intersect, while random phases interlock neighbouring coils (measured at 2,000
    wisps: 53,866 pairs of segments of different wisps within the contact thickness
    0.14 cm with random spins and seeded root jitter, none in phase without jitter;
    docs/contact.md, "Rest state").  Returns (normal (3,), frame (3, 3) with columns
    u, w, a = normal).  ``seed`` is kept for the scene's other random streams (the
    perturbations); the roots no longer depend on it.
    """
    del seed
    y = 1.0 - (w + 0.5) / n_wisps
    r = np.sqrt(max(0.0, 1.0 - y * y))
    phi = w * GOLDEN_ANGLE
    n = np.array([r * np.cos(phi), y, r * np.sin(phi)])
    return n, smooth_frame(n)


def smooth_frame(normal) -> np.ndarray:
    """Frame (columns u, w, a = normal) obtained by the rotation taking +y to ``normal``
    along their great circle: smooth over the whole sphere but -y, so the upper
    hemisphere's wisps all get frames that turn smoothly with their roots."""
    a = np.asarray(normal, float)
    a = a / np.linalg.norm(a)
    ey = np.array([0.0, 1.0, 0.0])
    c = float(ey @ a)
    if c <= -1.0 + 1e-12:
        raise ValueError(f"smooth_frame: normal {normal!r} points down (-y), where the frame "
                         f"field is singular")
    v = np.cross(ey, a)
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    R = np.eye(3) + K + K @ K / (1.0 + c)
    u = R @ np.array([1.0, 0.0, 0.0])
    return np.column_stack([u, np.cross(a, u), a])


def tapered_radius(n_vertices: int, root_radius: float, tip_radius: float) -> np.ndarray:
    """Vertex radii (n_vertices,) tapering linearly from ``root_radius`` to ``tip_radius``."""
    return np.linspace(root_radius, tip_radius, n_vertices)
