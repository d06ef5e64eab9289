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


def place(local: np.ndarray, root, axis, spin: float = 0.0) -> np.ndarray:
    return np.asarray(root, float) + local @ frame_about(axis, spin).T


def wisp4c(n_vertices: int = 101, root=(0.0, 0.0, 0.0), axis=(0.0, -1.0, 0.0), spin: float = 0.0):
    """The 4C wisp hanging from ``root`` along ``axis`` (default: down, -y)."""
    return place(wisp4c_local(n_vertices), root, axis, spin)


def straight(n_vertices: int, segment: float = 0.6, root=(0.0, 0.0, 0.0), direction=(0.0, -1.0, 0.0)):
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    return np.asarray(root, float) + segment * np.arange(n_vertices)[:, None] * d


def hairball_root(w: int, n_wisps: int, seed: int):
    """Root normal and spin of hairball wisp ``w``: a jittered Fibonacci point set.

    Points k + 1/2 of a Fibonacci spiral on the upper (y >= 0) hemisphere are evenly
    spread with a minimum spacing of about sqrt(2 pi / N) (blue-noise like, shrinking
    with the wisp count); each gets a seeded tangential jitter of at most a quarter of
    that spacing and a seeded random spin about its normal.  The random stream of wisp
    ``w`` is ``default_rng([seed, w])``: independent of every other wisp.
    """
    rng = np.random.default_rng([int(seed), int(w)])
    y = 1.0 - (w + 0.5) / n_wisps
    r = np.sqrt(max(0.0, 1.0 - y * y))
    phi = w * GOLDEN_ANGLE
    n = np.array([r * np.cos(phi), y, r * np.sin(phi)])
    spacing = np.sqrt(2.0 * np.pi / n_wisps)
    t = rng.normal(size=3)
    t -= t.dot(n) * n
    t *= 0.25 * spacing * rng.uniform() / max(np.linalg.norm(t), 1e-300)
    n = n + t
    n[1] = abs(n[1])
    n /= np.linalg.norm(n)
    spin = rng.uniform(0.0, 2.0 * np.pi)
    return n, spin


def tapered_radius(n_vertices: int, root_radius: float, tip_radius: float) -> np.ndarray:
    return np.linspace(root_radius, tip_radius, n_vertices)
