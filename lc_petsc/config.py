"""Validated configuration dataclasses, mirroring the TOML tables of DESIGN section 3.

TOML parsing belongs to a later layer; here every table is a dataclass whose
``validate()`` raises ``ValueError`` naming the offending key and value.  ``SimConfig``
bundles them and is what :func:`lc_petsc.simulator.build_simulator` takes.

Units are CGS (cm, g, s; Young's modulus in dyn/cm^2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, asdict
from typing import Optional, Sequence

SCENE_KINDS = ("wisp4c", "hairball", "straight", "file")
PERTURBATIONS = ("none", "smash", "jitter", "straighten")
TERMS = ("stretch", "bend", "twist", "gravity", "head_collision", "strand_collision")
HEAD_MOTIONS = ("static", "shake", "translate")
FILTERS = ("analytic", "numerical", "none")


def _positive(name: str, value, allow_zero: bool = False) -> None:
    try:
        if isinstance(value, (str, bool)):
            raise TypeError
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    ok = math.isfinite(v) and (v >= 0 if allow_zero else v > 0)
    if not ok:
        kind = "non-negative" if allow_zero else "positive"
        raise ValueError(f"{name} must be a finite {kind} number, got {value!r}")


def _int_at_least(name: str, value, lo: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < lo:
        raise ValueError(f"{name} must be an integer >= {lo}, got {value!r}")


@dataclass
class SceneConfig:
    """``[scene]``: which geometry to build.

    kind: ``wisp4c`` (one 101-vertex 4C wisp hanging from the origin along -y),
    ``hairball`` (``n_wisps`` 4C wisps on the upper half of the head sphere),
    ``straight`` (one straight strand of ``n_vertices`` from the origin along
    ``direction``), ``file`` (HDF5 strands file at ``path``, DESIGN section 3).
    perturbation: initial-state change of SPEC section 6 applied to free vertices
    (``smash``: x scaled by ``smash_factor``; ``jitter``: uniform offsets in
    [-jitter, jitter] cm; ``straighten``: free vertices put on a vertical line).
    """

    kind: str = "wisp4c"
    n_wisps: int = 1
    n_vertices: int = 101
    seed: int = 0
    n_pinned: int = 4
    path: Optional[str] = None
    segment_length: float = 0.6            # straight strands and the 4C stem
    direction: Sequence[float] = (0.0, -1.0, 0.0)   # straight strand direction
    perturbation: str = "none"
    smash_factor: float = 0.4
    jitter: float = 0.5

    def validate(self) -> None:
        if self.kind not in SCENE_KINDS:
            raise ValueError(f"scene.kind must be one of {SCENE_KINDS}, got {self.kind!r}")
        _int_at_least("scene.n_wisps", self.n_wisps, 1)
        _int_at_least("scene.n_vertices", self.n_vertices, 1)
        _int_at_least("scene.seed", self.seed, 0)
        _int_at_least("scene.n_pinned", self.n_pinned, 0)
        _positive("scene.segment_length", self.segment_length)
        if self.kind == "file" and not self.path:
            raise ValueError("scene.path must name an HDF5 strands file when scene.kind = 'file'")
        if len(tuple(self.direction)) != 3 or not all(math.isfinite(float(c)) for c in self.direction) \
                or math.hypot(*map(float, self.direction)) == 0.0:
            raise ValueError(f"scene.direction must be a non-zero finite 3-vector, got {self.direction!r}")
        if self.perturbation not in PERTURBATIONS:
            raise ValueError(f"scene.perturbation must be one of {PERTURBATIONS}, got {self.perturbation!r}")
        _positive("scene.smash_factor", self.smash_factor)
        _positive("scene.jitter", self.jitter, allow_zero=True)


@dataclass
class MaterialConfig:
    """``[material]``: Young's and shear modulus (dyn/cm^2), density (g/cm^3), radii (cm).

    Radii taper linearly from ``root_radius`` to ``tip_radius`` along each wisp.  For the
    hairball, ``radius_scale_with_count`` scales both by sqrt(2000 / n_wisps) (SPEC 6).
    ``shear_modulus = None`` means E / 3 (incompressible isotropic).
    """

    youngs_modulus: float = 1.0e9
    shear_modulus: Optional[float] = None
    density: float = 1.3
    root_radius: float = 0.35
    tip_radius: float = 0.07
    radius_scale_with_count: bool = True

    def validate(self) -> None:
        _positive("material.youngs_modulus", self.youngs_modulus)
        if self.shear_modulus is not None:
            _positive("material.shear_modulus", self.shear_modulus)
        _positive("material.density", self.density)
        _positive("material.root_radius", self.root_radius)
        _positive("material.tip_radius", self.tip_radius)

    @property
    def G(self) -> float:
        return self.youngs_modulus / 3.0 if self.shear_modulus is None else float(self.shear_modulus)


@dataclass
class PhysicsConfig:
    """``[physics]``: modelled terms, gravity, head sphere.

    head_collision is a penalty 1/2 k d^2 on the depth d of a free vertex inside the
    sphere (radius ``head_radius`` + ``head_margin``); ``head_stiffness`` k in dyn/cm.
    The head (sphere and pinned roots) follows ``head_motion``: ``static``, ``shake``
    (rotate back and forth about z, then y, then x; ``head_amplitude`` rad, each axis for
    ``head_period`` s) or ``translate`` (constant ``head_velocity`` cm/s).
    """

    terms: Sequence[str] = ("stretch", "bend", "twist", "gravity")
    gravity: Sequence[float] = (0.0, -981.0, 0.0)
    head_radius: float = 15.25
    head_center: Sequence[float] = (0.0, 0.0, 0.0)
    head_margin: float = 0.0
    head_stiffness: float = 1.0e5
    head_motion: str = "static"
    head_amplitude: float = 0.5
    head_period: float = 6.0
    head_velocity: Sequence[float] = (0.0, 0.0, 0.0)

    def validate(self) -> None:
        terms = tuple(self.terms)
        for t in terms:
            if t not in TERMS:
                raise ValueError(f"physics.terms: unknown term {t!r}; expected some of {TERMS}")
        if "strand_collision" in terms:
            raise ValueError("physics.terms: 'strand_collision' is not implemented yet")
        for name in ("gravity", "head_center", "head_velocity"):
            v = tuple(getattr(self, name))
            if len(v) != 3 or not all(math.isfinite(float(c)) for c in v):
                raise ValueError(f"physics.{name} must be a finite 3-vector, got {v!r}")
        _positive("physics.head_radius", self.head_radius)
        _positive("physics.head_margin", self.head_margin, allow_zero=True)
        _positive("physics.head_stiffness", self.head_stiffness)
        if self.head_motion not in HEAD_MOTIONS:
            raise ValueError(f"physics.head_motion must be one of {HEAD_MOTIONS}, got {self.head_motion!r}")
        _positive("physics.head_amplitude", self.head_amplitude, allow_zero=True)
        _positive("physics.head_period", self.head_period)


@dataclass
class TimeConfig:
    """``[time]``: BDF-1 step and Newton settings.

    Newton stops after ``newton_iterations`` iterations or as soon as the largest vertex
    increment is below ``newton_tol`` cm (``None``: fixed count, the paper's setting),
    whichever comes first.  ``line_search`` enables Armijo backtracking on the
    incremental potential G.
    """

    dt: float = 1.0 / 30.0
    frames: int = 1
    newton_iterations: int = 3
    newton_tol: Optional[float] = None
    line_search: bool = False

    def validate(self) -> None:
        _positive("time.dt", self.dt)
        _int_at_least("time.frames", self.frames, 0)
        _int_at_least("time.newton_iterations", self.newton_iterations, 1)
        if self.newton_tol is not None:
            _positive("time.newton_tol", self.newton_tol)


@dataclass
class SolverConfig:
    """``[solver]``: PETSc options string (the command line wins) and Hessian filter."""

    options: str = ""
    filter: str = "analytic"

    def validate(self) -> None:
        if not isinstance(self.options, str):
            raise ValueError(f"solver.options must be a string of PETSc options, got {self.options!r}")
        if self.filter not in FILTERS:
            raise ValueError(f"solver.filter must be one of {FILTERS}, got {self.filter!r}")


@dataclass
class SimConfig:
    scene: SceneConfig = field(default_factory=SceneConfig)
    material: MaterialConfig = field(default_factory=MaterialConfig)
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    time: TimeConfig = field(default_factory=TimeConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)

    def validate(self) -> "SimConfig":
        for part in (self.scene, self.material, self.physics, self.time, self.solver):
            part.validate()
        return self

    def to_dict(self) -> dict:
        return asdict(self)
