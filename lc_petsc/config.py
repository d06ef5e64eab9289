"""Validated configuration: dataclasses mirroring the TOML tables of DESIGN section 3,
and :func:`load_config` reading a scene file into them.

Every table is a dataclass whose ``validate()`` raises :class:`ConfigError` (a
``ValueError``) naming the offending key, its value and what is allowed.
:func:`load_config` adds what only a file can get wrong: unknown tables and keys, wrong
TOML types, TOML syntax errors, missing files.  ``SimConfig`` bundles the tables and is
what :func:`lc_petsc.simulator.build_simulator` takes.

Units are CGS (cm, g, s; Young's modulus in dyn/cm^2).  Relative paths inside a config
file (``scene.path``, ``solver.options_file``) are relative to the config file's folder.
"""

from __future__ import annotations

import math
import os
import shlex
from dataclasses import dataclass, field, asdict, fields, replace
from pathlib import Path
from typing import Optional, Sequence

from lc_petsc.errors import ConfigError

SCENE_KINDS = ("wisp4c", "hairball", "straight", "file", "usd")
PERTURBATIONS = ("none", "smash", "jitter", "straighten")
STRAND_CONTACT_MODES = ("penalty", "ccd")
STRAND_REST_OVERLAP = ("error", "exempt")
#: physics.strand_contact_potential: the penalty 1/2 k (d0 - d)^2 or the IPC log barrier
STRAND_CONTACT_POTENTIALS = ("penalty", "barrier")
#: terms with element kernels (lc_petsc/elements), in assembly order
ELASTIC_TERMS = ("stretch", "bend", "twist")
#: terms evaluated per vertex or per contact pair
OTHER_TERMS = ("gravity", "head_collision", "strand_collision")
TERMS = ELASTIC_TERMS + OTHER_TERMS
HEAD_MOTIONS = ("static", "shake", "translate")
from lc_petsc.elements.common import FILTERS as ELEMENT_FILTERS  # noqa: E402
#: solver.filter: an element filter, or the exact Hessian with the analytic filter as
#: fallback when the Newton matrix is indefinite
FILTERS = ELEMENT_FILTERS + ("exact_or_analytic",)
#: solver.exact_fallback: what replaces a failed exact step of "exact_or_analytic": the
#: analytic filter's step, or first the exact Hessian shifted by tau M/dt^2; "shifted" also
#: shifts each wisp whose exact block is indefinite before the solve and, without strand
#: contact, searches the exact steps wisp by wisp (docs/newton.md)
EXACT_FALLBACKS = ("analytic", "shifted")
#: time.frames above this is refused (a billion frames at 1/30 s is a year of motion)
MAX_FRAMES = 10 ** 9
#: time.dt below this is refused: the mass term M/dt^2 then swamps every elastic term in
#: double precision (at dt = 1e-300 it overflows to inf)
MIN_DT = 1.0e-6
#: moduli above this are refused (steel is 2e12 dyn/cm^2; 1e300 overflows the Hessians)
MAX_MODULUS = 1.0e15
#: material.density and a groom file's /density outside this range (g/cm^3) are refused, not
#: warned about: the motion depends on the density only through E / density (and the head's and
#: strand contact's stiffness / density), so a density 1000 times off (1300 in kg/m^3, 0.0013 in
#: g/mm^3) runs a scene as if 1000 times softer or stiffer, without an error: smash at 1300 looks
#: like a slow recovery (docs/design_notes.md "Densities: refused outside 0.1-10 g/cm^3"). Hair is
#: 1.3 g/cm^3, every shipped config says so; fibres from polypropylene (0.9) to steel (7.9) fit
DENSITY_RANGE = (0.1, 10.0)
#: radii, rest edges and segment lengths below this (an atom's size, 1 angstrom, in cm) are
#: refused: no strand is that thin or finely sampled (a groom's radius of 1e-300 made every
#: mass 0, a wisp shrunk to 1e-10 cm stiffnesses 1e27 times its mass term: both failed
#: in frame 0, after it was written)
MIN_LENGTH = 1.0e-8
#: head_radius + head_margin above this are refused: double precision then places the
#: sphere's surface no closer than MIN_LENGTH (1e308 made the head's depths inf in frame 0)
MAX_HEAD_EXTENT = MIN_LENGTH / 2.220446049250313e-16


def _positive(name: str, value, allow_zero: bool = False) -> None:
    try:
        if isinstance(value, (str, bool)):
            raise TypeError
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number, got {value!r}") from None
    ok = math.isfinite(v) and (v >= 0 if allow_zero else v > 0)
    if not ok:
        kind = "non-negative" if allow_zero else "positive"
        raise ConfigError(f"{name} must be a finite {kind} number, got {value!r}")


def density_problem(name: str, value: float):
    """The message refusing a density ``value`` (g/cm^3) outside :data:`DENSITY_RANGE`,
    ``name`` saying whose (``material.density =``, a file's ``/density``), or None."""
    lo, hi = DENSITY_RANGE
    if lo <= value <= hi:
        return None
    likely = ("it looks like kg/cm^3 or g/mm^3 (hair: 1.3 g/cm^3 = 0.0013 g/mm^3)" if value < lo else
              "it looks like kg/m^3 (hair: 1300 kg/m^3 = 1.3 g/cm^3)")
    return (f"{name} {value:g} g/cm^3 is outside {lo:g} to {hi:g} g/cm^3: {likely}; a density 1000 times "
            "off runs the scene as if 1000 times softer or stiffer, without an error; give it in g/cm^3 "
            "(stiffness is set by the Young's modulus)")


def _at_least_length(name: str, value) -> None:
    """A length (cm) below :data:`MIN_LENGTH` is refused (checked after :func:`_positive`)."""
    if float(value) < MIN_LENGTH:
        raise ConfigError(f"{name} = {value!r} cm is below {MIN_LENGTH:g} cm (an atom's size): no strand "
                          "is that thin or finely sampled; lc_petsc's lengths are in cm")


def _int_at_least(name: str, value, lo: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < lo:
        raise ConfigError(f"{name} must be an integer >= {lo}, got {value!r}")


@dataclass
class SceneConfig:
    """``[scene]``: which geometry to build.

    kind: ``wisp4c`` (one 101-vertex 4C wisp hanging from the origin along -y),
    ``hairball`` (``n_wisps`` 4C wisps on the upper half of the head sphere),
    ``straight`` (one straight strand of ``n_vertices`` from the origin along
    ``direction``), ``file`` (HDF5 strands file at ``path``, DESIGN section 3), ``usd``
    (BasisCurves of the USD file at ``path``, optionally only those at or under
    ``prim_path``; :mod:`lc_petsc.scene.usd_source`).
    perturbation: initial-state change of SPEC section 6 applied to free vertices
    (``smash``: x scaled by ``smash_factor``; ``jitter``: uniform offsets in
    [-jitter, jitter] cm; ``straighten``: free vertices put on a vertical line).
    description: free text (what the scene shows), echoed into the outputs.
    """

    kind: str = "wisp4c"
    n_wisps: int = 1
    n_vertices: int = 101
    seed: int = 0
    n_pinned: int = 4
    path: Optional[str] = None
    prim_path: Optional[str] = None         # usd: a BasisCurves prim or an ancestor of some
    segment_length: float = 0.6            # straight strands and the 4C stem
    direction: Sequence[float] = (0.0, -1.0, 0.0)   # straight strand direction
    perturbation: str = "none"
    smash_factor: float = 0.4
    jitter: float = 0.5
    description: str = ""

    def validate(self) -> None:
        """Raise :class:`ConfigError` naming the key unless every value of this table is allowed."""
        if self.kind not in SCENE_KINDS:
            raise ConfigError(f"scene.kind must be one of {SCENE_KINDS}, got {self.kind!r}")
        _int_at_least("scene.n_wisps", self.n_wisps, 1)
        _int_at_least("scene.n_vertices", self.n_vertices, 4)
        _int_at_least("scene.seed", self.seed, 0)
        _int_at_least("scene.n_pinned", self.n_pinned, 0)
        _positive("scene.segment_length", self.segment_length)
        _at_least_length("scene.segment_length", self.segment_length)
        if self.kind == "file":
            if not self.path:
                raise ConfigError("scene.path must name an HDF5 strands file when scene.kind = 'file'")
            if not os.path.isfile(self.path):
                raise ConfigError(f"scene.path = {self.path!r}: no such file (an HDF5 strands file "
                                  "with /positions and /wisp_offsets is expected)")
        if self.kind == "usd":
            if not self.path:
                raise ConfigError("scene.path must name a USD file (.usd, .usda, .usdc) when "
                                  "scene.kind = 'usd'")
            if not os.path.isfile(self.path):
                raise ConfigError(f"scene.path = {self.path!r}: no such file (a USD file with "
                                  "BasisCurves is expected)")
        if self.prim_path is not None:
            if self.kind != "usd":
                raise ConfigError(f"scene.prim_path = {self.prim_path!r} only applies to scene.kind = "
                                  f"'usd', not {self.kind!r}")
            if not isinstance(self.prim_path, str) or not self.prim_path.startswith("/"):
                raise ConfigError(f"scene.prim_path must be an absolute USD prim path such as "
                                  f"'/Groom/wisps', got {self.prim_path!r}")
        if len(tuple(self.direction)) != 3 or not all(math.isfinite(float(c)) for c in self.direction) \
                or math.hypot(*map(float, self.direction)) == 0.0:
            raise ConfigError(f"scene.direction must be a non-zero finite 3-vector, got {self.direction!r}")
        if self.perturbation not in PERTURBATIONS:
            raise ConfigError(f"scene.perturbation must be one of {PERTURBATIONS}, got {self.perturbation!r}")
        _positive("scene.smash_factor", self.smash_factor)
        _positive("scene.jitter", self.jitter, allow_zero=True)
        if not math.isfinite(2.0 * float(self.jitter)):
            # numpy's uniform(-jitter, jitter) raised OverflowError: a traceback, exit 1
            raise ConfigError(f"scene.jitter = {self.jitter!r} cm is beyond half the largest float; "
                              "the offsets are in cm (a wisp is a few cm to tens of cm long)")


@dataclass
class MaterialConfig:
    """``[material]``: Young's and shear modulus (dyn/cm^2), density (g/cm^3), radii (cm).

    Radii taper linearly from ``root_radius`` to ``tip_radius`` along each wisp.  For the
    hairball, ``radius_scale_with_count`` scales both by sqrt(2000 / n_wisps) (SPEC 6).
    ``shear_modulus = None`` means E / 3 (incompressible isotropic).
    ``twist_rest_sine``: a twist element whose rest stencil is straight has no rest
    torsion; its stiffness is 0 up to half this sine of the smaller rest bend angle and
    full from it on (``twist.rest_weight``; 0: every element at full stiffness,
    docs/elements.md).
    """

    youngs_modulus: float = 1.0e9
    shear_modulus: Optional[float] = None
    density: float = 1.3
    root_radius: float = 0.35
    tip_radius: float = 0.07
    radius_scale_with_count: bool = True
    twist_rest_sine: float = 0.05

    def validate(self) -> None:
        """Raise :class:`ConfigError` naming the key unless every value of this table is allowed."""
        _positive("material.youngs_modulus", self.youngs_modulus)
        if self.shear_modulus is not None:
            _positive("material.shear_modulus", self.shear_modulus)
        for name in ("youngs_modulus", "shear_modulus"):
            v = getattr(self, name)
            if v is not None and float(v) > MAX_MODULUS:
                raise ConfigError(f"material.{name} = {v!r} dyn/cm^2 is beyond {MAX_MODULUS:g} (steel is "
                                  "2e12; hair keratin about 4e10): the element Hessians would lose all "
                                  "precision; give the modulus in dyn/cm^2 (CGS)")
        _positive("material.density", self.density)
        problem = density_problem("material.density =", float(self.density))
        if problem:
            raise ConfigError(problem)
        _positive("material.root_radius", self.root_radius)
        _positive("material.tip_radius", self.tip_radius)
        _at_least_length("material.root_radius", self.root_radius)
        _at_least_length("material.tip_radius", self.tip_radius)
        sine = self.twist_rest_sine
        if isinstance(sine, bool) or not isinstance(sine, (int, float)) or not 0.0 <= sine < 1.0:
            raise ConfigError(f"material.twist_rest_sine must be a number in [0, 1) (the sine of the "
                              f"rest bend angle below which twist fades out; 0 turns the fading "
                              f"off), got {sine!r}")

    @property
    def G(self) -> float:
        """Shear modulus: ``shear_modulus``, or E / 3 (incompressible) when it is not given."""
        return self.youngs_modulus / 3.0 if self.shear_modulus is None else float(self.shear_modulus)


@dataclass
class PhysicsConfig:
    """``[physics]``: modelled terms, gravity, head sphere.

    head_collision is a penalty 1/2 k d^2 on the depth d of a free vertex inside the
    sphere (radius ``head_radius`` + ``head_margin``); ``head_stiffness`` k in dyn/cm;
    ``head_push_out``: a vertex a step leaves deeper than its strand radius (less its
    edges' sagitta) is put back on the sphere, the length projection keeps it there, and a
    vertex's straight path between frames that cuts under the curved head is lifted out
    (its end moved out by at most 4 strand radii, its wisp's rest lengths set again, the
    velocity leaving the lift out), also after the strand contact's frame end.
    The head (sphere and pinned roots) follows ``head_motion``: ``static``, ``shake``
    (rotate back and forth about z, then y, then x; ``head_amplitude`` rad, each axis for
    ``head_period`` s; ``head_smooth``: each axis's swing starts and ends at rest, so the
    head's angular velocity never jumps) or ``translate`` (constant ``head_velocity``
    cm/s).
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
    head_smooth: bool = False
    head_velocity: Sequence[float] = (0.0, 0.0, 0.0)
    # after each step's Newton iterations, free vertices deeper in the sphere than their
    # strand radius are put back on it: a fixed Newton count can end with a vertex the
    # last step moved in before the penalty saw it (docs/contact.md, "Hair and the head")
    head_push_out: bool = True
    # strand_collision (docs/contact.md): penalty 1/2 k (d0 - d)^2 on the distance d of two
    # segments of different wisps below the thickness d0 (None: twice the smallest vertex
    # radius of the scene, i.e. twice the tip radius); k in dyn/cm
    strand_thickness: Optional[float] = None
    strand_stiffness: float = 1.0e5
    # after each frame's Newton iterations, push pairs closer than d0 / 2 apart
    # (StrandContact.separate)
    strand_separation: bool = True
    # "penalty": the penalty (+ separation) alone, wisps can pass through each other
    # within a step; "ccd": every position update limited so that no two segments of
    # different wisps meet on its linear path (docs/contact.md, "Intersection-free
    # contact"); the shipped hairball configs use "ccd"
    strand_contact_mode: str = "penalty"
    # ccd mode: the Newton steps keep pairs at least this fraction of d0 apart
    strand_min_separation: float = 0.25
    # ccd mode: rest-pose pairs of different wisps closer than d0 stop the run ("error")
    # or are exempt from contact ("exempt", as in penalty mode)
    strand_rest_overlap: str = "error"
    # the contact energy on the pair distance d: "penalty" 1/2 k (d0 - d)^2, or "barrier"
    # -kappa (d - d0)^2 ln(d / d0) (IPC's, infinite at d = 0; needs strand_contact_mode =
    # "ccd"), kappa = strand_barrier_stiffness (dyn/cm; None: strand_stiffness / (1 + 2 ln 2),
    # the barrier's force then equals the penalty's at d = d0 / 2); docs/contact.md, "Barrier"
    strand_contact_potential: str = "penalty"
    strand_barrier_stiffness: Optional[float] = None
    # also pairs of segments of one wisp that are not neighbours along it (less than
    # pi / 2 d0 of rest strand between them): penalty/barrier, ccd limiter, rest-pose
    # check (docs/contact.md, "Self-contact")
    strand_self_contact: bool = False

    def validate(self) -> None:
        """Raise :class:`ConfigError` naming the key unless every value of this table is allowed."""
        terms = tuple(self.terms)
        for t in terms:
            if t not in TERMS:
                raise ConfigError(f"physics.terms: unknown term {t!r}; expected some of {TERMS}")
            if terms.count(t) > 1:
                raise ConfigError(f"physics.terms lists {t!r} {terms.count(t)} times; list each term once")
        for name in ("gravity", "head_center", "head_velocity"):
            v = tuple(getattr(self, name))
            if len(v) != 3 or not all(math.isfinite(float(c)) for c in v):
                raise ConfigError(f"physics.{name} must be a finite 3-vector, got {v!r}")
        _positive("physics.head_radius", self.head_radius)
        _positive("physics.head_margin", self.head_margin, allow_zero=True)
        _positive("physics.head_stiffness", self.head_stiffness)
        extent = float(self.head_radius) + float(self.head_margin)
        if extent > MAX_HEAD_EXTENT:
            raise ConfigError(f"physics.head_radius + head_margin = {extent:g} cm is beyond {MAX_HEAD_EXTENT:.3g} "
                              f"cm: double precision places a sphere that large no closer than "
                              f"{MIN_LENGTH:g} cm to its surface (a head is about 15 cm); give them in cm")
        if self.head_motion not in HEAD_MOTIONS:
            raise ConfigError(f"physics.head_motion must be one of {HEAD_MOTIONS}, got {self.head_motion!r}")
        _positive("physics.head_amplitude", self.head_amplitude, allow_zero=True)
        _positive("physics.head_period", self.head_period)
        if self.strand_thickness is not None:
            _positive("physics.strand_thickness", self.strand_thickness)
        _positive("physics.strand_stiffness", self.strand_stiffness)
        if not isinstance(self.strand_separation, bool):
            raise ConfigError(f"physics.strand_separation must be true or false, "
                              f"got {self.strand_separation!r}")
        if not isinstance(self.head_push_out, bool):
            raise ConfigError(f"physics.head_push_out must be true or false, got {self.head_push_out!r}")
        if not isinstance(self.head_smooth, bool):
            raise ConfigError(f"physics.head_smooth must be true or false, got {self.head_smooth!r}")
        if self.strand_contact_mode not in STRAND_CONTACT_MODES:
            raise ConfigError(f"physics.strand_contact_mode must be one of {STRAND_CONTACT_MODES}, "
                              f"got {self.strand_contact_mode!r}")
        m = self.strand_min_separation
        if isinstance(m, bool) or not isinstance(m, (int, float)) or not 0.0 < m < 1.0:
            raise ConfigError(f"physics.strand_min_separation must be a number in (0, 1) (a fraction "
                              f"of the contact thickness), got {m!r}")
        if self.strand_rest_overlap not in STRAND_REST_OVERLAP:
            raise ConfigError(f"physics.strand_rest_overlap must be one of {STRAND_REST_OVERLAP}, "
                              f"got {self.strand_rest_overlap!r}")
        if self.strand_contact_potential not in STRAND_CONTACT_POTENTIALS:
            raise ConfigError(f"physics.strand_contact_potential must be one of "
                              f"{STRAND_CONTACT_POTENTIALS}, got {self.strand_contact_potential!r}")
        if self.strand_contact_potential == "barrier" and self.strand_contact_mode != "ccd" and \
                "strand_collision" in terms:
            raise ConfigError("physics.strand_contact_potential = \"barrier\" needs "
                              "physics.strand_contact_mode = \"ccd\" (the barrier is infinite where "
                              "segments touch, and only the ccd limiter keeps every step "
                              f"collision-free); got strand_contact_mode = {self.strand_contact_mode!r}")
        if self.strand_barrier_stiffness is not None:
            _positive("physics.strand_barrier_stiffness", self.strand_barrier_stiffness)
        if not isinstance(self.strand_self_contact, bool):
            raise ConfigError(f"physics.strand_self_contact must be true or false, "
                              f"got {self.strand_self_contact!r}")


#: Newton's first iterate: x_n + dt v_n, or that projected onto the rest edge lengths.
INITIAL_GUESSES = ("inertial", "follow_the_leader")
#: How a Newton step updates positions: x + dx, with the edge lengths retracted, or so
#: and with each edge of an exact step also turned by its neighbourhood's rotation
#: (lc_petsc/integrator.py).
NEWTON_UPDATES = ("linear", "edge_retraction", "corotational")
#: time.newton: the Newton iteration's globalisation: filtered steps (solver.filter, the
#: paper's), or a trust region on the exact Hessian (lc_petsc/trust_region.py)
NEWTON_MODES = ("filtered", "trust_region")
#: time.newton_stop: Newton stops on the last increment, or also on the error estimated
#: from two quadratic exact steps in a row, or on that and the next increment measured by
#: a chord step (lc_petsc/integrator.py, docs/newton.md)
NEWTON_STOPS = ("increment", "quadratic_estimate", "chord_estimate")
#: time.unconverged: a frame whose Newton misses the tolerance at the deepest cutback
UNCONVERGED = ("accept", "error")
#: time.max_substeps above this is refused (dt / 1024 is a millisecond at 1/30 s)
MAX_SUBSTEPS = 1024
#: time.newton_iterations above this is refused: without a tolerance every one of them
#: runs (1e18 ran until killed); the scenes and studies use at most 100
MAX_NEWTON_ITERATIONS = 10_000
#: time.jolt_frames above this is refused: every frame looks back over that many frames'
#: head motions (a jolt's window of 100 frames is over 3 s at 1/30 s)
MAX_JOLT_FRAMES = 100


@dataclass
class TimeConfig:
    """``[time]``: BDF-1 step and Newton settings.

    Newton stops after ``newton_iterations`` iterations or as soon as the largest vertex
    increment relative to its wisp's rest length is below ``newton_increment_tol``
    and/or the absolute one below ``newton_tol`` cm (``None``: fixed count, the paper's
    setting), whichever comes first.  ``line_search`` enables Armijo backtracking on the
    incremental potential G; ``newton_stop = "quadratic_estimate"`` (with
    ``solver.filter = "exact_or_analytic"`` and ``newton_increment_tol`` alone) also stops
    once three full exact steps in a row predict an error below a tenth of the tolerance;
    ``"chord_estimate"`` (same conditions) stops on that, or, after two full exact steps
    that contract, once a solve with the last exact matrix from the new iterate (a chord
    step) moves no vertex by the tolerance.
    ``newton_update``, ``initial_guess``, ``carry_with_head`` (the first iterate follows
    the head's change of motion over the step), ``jolt_first_iterate`` (a step across a
    jump of the head's velocity, the start from rest and each change of axis of the
    unsmoothed shake, starts from the start's first iterate: the head's change of motion
    carried near the roots only, then follow-the-leader; summary ``newton_jolt_starts``
    per frame; docs/newton.md "The head's jolts' first iterate") and
    ``length_projection`` (final positions onto the rest edge lengths) and ``newton``
    (``"filtered"`` steps or ``"trust_region"`` on the exact Hessian): see
    lc_petsc/integrator.py, lc_petsc/trust_region.py and docs/newton.md.
    ``root_rotation`` (a fixed count only): after the iterations each root-held wisp is
    turned rigidly about its last pinned vertex by the Newton step of G over the turn's
    three angles, a turn that raises its wisp's share of G halved, at most twice, then
    dropped (lc_petsc/root_rotation.py; docs/newton.md "Fourteenth round", "Sixteenth round").
    ``newton_extend_above`` (a fixed count only; None: off): a frame whose last increment
    (largest vertex move / wisp length) after ``newton_iterations`` is still above it takes
    more iterations, until one is at or below it or the frame has taken
    ``newton_extend_cap``; the root turn follows the last (docs/newton.md "Eighteenth round").
    ``start_increment_tol`` (a fixed count only; None: off): the first ``start_frames``
    frames (the start from rest) run to that relative increment tolerance, at most
    ``start_iterations`` iterations, on the recommended converging path
    (:meth:`SimConfig.start_config`); the frames after them run the fixed count
    (docs/newton.md "Twenty-second round").  ``jolt_above`` (cm/s^2, with
    ``start_increment_tol`` only; None: off): later frames where the head's acceleration
    at its farthest root changes from the frame before by more than this (a jolt: a
    shake's change of axis), and the ``jolt_frames - 1`` frames after each, run like the
    start frames (docs/newton.md "Twenty-third round").

    With a tolerance and a config file that does not name ``solver.filter``,
    ``newton_update`` defaults to ``"corotational"`` and, without strand contact,
    ``jolt_first_iterate`` to true and (with ``newton_increment_tol`` alone)
    ``newton_stop`` to ``"chord_estimate"`` (the converging path,
    :func:`tolerance_defaults`; :class:`SolverConfig`).

    Step cutback (only with a tolerance): a frame whose Newton misses it within the cap
    is redone as 2 steps of dt / 2, each cut again if it fails, up to ``max_substeps``
    (a power of 2; 1: off) steps in the frame; a frame still missing it is accepted and
    reported (``unconverged = "accept"``) or ends the run (``"error"``).
    """

    dt: float = 1.0 / 30.0
    frames: int = 1
    newton_iterations: int = 3
    newton_tol: Optional[float] = None
    newton_increment_tol: Optional[float] = None
    line_search: bool = False
    initial_guess: str = "inertial"
    carry_with_head: bool = True
    jolt_first_iterate: bool = False
    newton_update: str = "edge_retraction"
    newton: str = "filtered"
    newton_stop: str = "increment"
    length_projection: bool = False
    root_rotation: bool = False
    newton_extend_above: Optional[float] = None
    newton_extend_cap: int = 12
    start_increment_tol: Optional[float] = None
    start_frames: int = 2
    start_iterations: int = 30
    jolt_above: Optional[float] = None
    jolt_frames: int = 1
    max_substeps: int = 8
    unconverged: str = "accept"

    @property
    def newton_converges(self) -> bool:
        """Newton iterates to a tolerance (``newton_tol`` or ``newton_increment_tol``), not
        a fixed count: the linear solves default to a tighter ``-ksp_rtol``
        (lc_petsc/solver_plan.py)."""
        return self.newton_tol is not None or self.newton_increment_tol is not None

    def validate(self) -> None:
        """Raise :class:`ConfigError` naming the key unless every value of this table is allowed."""
        _positive("time.dt", self.dt)
        if float(self.dt) < MIN_DT:
            raise ConfigError(f"time.dt = {self.dt!r} s is below {MIN_DT:g} s: the inertia term M/dt^2 "
                              "would swamp every elastic force in double precision; steps are in "
                              "seconds (1/30 is a video frame)")
        _int_at_least("time.frames", self.frames, 0)
        if self.frames > MAX_FRAMES:
            raise ConfigError(f"time.frames = {self.frames!r} is more than {MAX_FRAMES:,} frames "
                              f"({MAX_FRAMES * float(self.dt) / 86400:.3g} days of simulated time at "
                              f"time.dt = {self.dt:g} s); run fewer frames")
        if not math.isfinite(float(self.dt) * max(self.frames, 1)):
            # the head's motion and the frame times at t = k dt overflowed: a traceback
            raise ConfigError(f"time.dt = {self.dt!r} s times time.frames = {self.frames} is beyond the "
                              "largest float: the frame times cannot be represented; steps are in "
                              "seconds (1/30 is a video frame)")
        _int_at_least("time.newton_iterations", self.newton_iterations, 1)
        if self.newton_iterations > MAX_NEWTON_ITERATIONS:
            raise ConfigError(f"time.newton_iterations = {self.newton_iterations!r} is more than "
                              f"{MAX_NEWTON_ITERATIONS:,} Newton iterations per frame (without a "
                              "tolerance each frame runs every one of them; 3 is the paper's count, "
                              "30 a cap with time.newton_increment_tol)")
        if self.newton_tol is not None:
            _positive("time.newton_tol", self.newton_tol)
        if self.newton_increment_tol is not None:
            _positive("time.newton_increment_tol", self.newton_increment_tol)
        if self.initial_guess not in INITIAL_GUESSES:
            raise ConfigError(f"time.initial_guess must be one of {INITIAL_GUESSES}, "
                              f"got {self.initial_guess!r}")
        if self.newton_update not in NEWTON_UPDATES:
            raise ConfigError(f"time.newton_update must be one of {NEWTON_UPDATES}, "
                              f"got {self.newton_update!r}")
        if self.newton not in NEWTON_MODES:
            raise ConfigError(f"time.newton must be one of {NEWTON_MODES}, got {self.newton!r}")
        if self.newton_stop not in NEWTON_STOPS:
            raise ConfigError(f"time.newton_stop must be one of {NEWTON_STOPS}, got {self.newton_stop!r}")
        if self.newton_stop != "increment" and (self.newton_increment_tol is None
                                                 or self.newton_tol is not None):
            raise ConfigError(f"time.newton_stop = {self.newton_stop!r} estimates the relative "
                              "increment: set time.newton_increment_tol and leave time.newton_tol "
                              "unset, or use time.newton_stop = \"increment\"")
        if self.newton != "filtered" and self.line_search:
            raise ConfigError("time.line_search = true with time.newton = \"trust_region\": the "
                              "trust region is the globalisation; set time.line_search = false")
        if not isinstance(self.carry_with_head, bool):
            raise ConfigError(f"time.carry_with_head must be true or false, "
                              f"got {self.carry_with_head!r}")
        if not isinstance(self.jolt_first_iterate, bool):
            raise ConfigError(f"time.jolt_first_iterate must be true or false, "
                              f"got {self.jolt_first_iterate!r}")
        if not isinstance(self.length_projection, bool):
            raise ConfigError(f"time.length_projection must be true or false, "
                              f"got {self.length_projection!r}")
        if not isinstance(self.root_rotation, bool):
            raise ConfigError(f"time.root_rotation must be true or false, got {self.root_rotation!r}")
        if self.root_rotation and self.newton_converges:
            raise ConfigError("time.root_rotation = true turns the wisps after a fixed count of Newton "
                              "iterations; with time.newton_tol or time.newton_increment_tol set Newton "
                              "converges the frame itself: set time.root_rotation = false or drop the "
                              "tolerance")
        self._validate_extension()
        self._validate_start()
        _int_at_least("time.max_substeps", self.max_substeps, 1)
        if self.max_substeps & (self.max_substeps - 1) or self.max_substeps > MAX_SUBSTEPS:
            raise ConfigError(f"time.max_substeps must be a power of 2 (1, 2, 4, ... {MAX_SUBSTEPS}; "
                              f"a failed step is halved), got {self.max_substeps!r}")
        if float(self.dt) / self.max_substeps < MIN_DT:
            raise ConfigError(f"time.max_substeps = {self.max_substeps} makes the smallest step "
                              f"time.dt / {self.max_substeps} = {float(self.dt) / self.max_substeps:.3g} s, "
                              f"below {MIN_DT:g} s; use a smaller time.max_substeps")
        if self.unconverged not in UNCONVERGED:
            raise ConfigError(f"time.unconverged must be one of {UNCONVERGED}, got {self.unconverged!r}")

    def _validate_start(self) -> None:
        """``start_increment_tol`` / ``start_frames`` / ``start_iterations`` (:meth:`validate`)."""
        _int_at_least("time.start_frames", self.start_frames, 1)
        _int_at_least("time.start_iterations", self.start_iterations, 1)
        if self.start_iterations > MAX_NEWTON_ITERATIONS:
            raise ConfigError(f"time.start_iterations = {self.start_iterations!r} is more than "
                              f"{MAX_NEWTON_ITERATIONS:,} Newton iterations per start frame (30 is a cap "
                              "that the start from rest reaches 1e-3 well within)")
        _int_at_least("time.jolt_frames", self.jolt_frames, 1)
        if self.jolt_frames > MAX_JOLT_FRAMES:
            raise ConfigError(f"time.jolt_frames = {self.jolt_frames!r} is more than {MAX_JOLT_FRAMES} frames "
                              "converged after each jolt of the head (1: the jolt's own frames, 2: and the "
                              "frame after each)")
        if self.jolt_above is not None:
            _positive("time.jolt_above", self.jolt_above)
            if self.newton_converges:   # not "set start_increment_tol": a tolerance refuses that too
                raise ConfigError(f"time.jolt_above = {self.jolt_above!r} converges the frames where the head "
                                  "jolts within a fixed count of Newton iterations; with time.newton_tol or "
                                  "time.newton_increment_tol set every frame already converges: drop "
                                  "time.jolt_above")
            if self.start_increment_tol is None:
                raise ConfigError(f"time.jolt_above = {self.jolt_above!r} converges the frames where the head "
                                  "jolts to time.start_increment_tol, which is not set: set "
                                  "time.start_increment_tol (e.g. 1e-3) or drop time.jolt_above")
        if self.start_increment_tol is None:
            return
        _positive("time.start_increment_tol", self.start_increment_tol)
        if self.newton_converges:
            raise ConfigError("time.start_increment_tol converges the first frames of a fixed count of Newton "
                              "iterations; with time.newton_tol or time.newton_increment_tol set every frame "
                              "already converges: drop one of them")
        if self.newton != "filtered":
            raise ConfigError("time.start_increment_tol runs the start frames on the filtered path with exact "
                              "steps (solver.filter = \"exact_or_analytic\"), not the trust region: set "
                              "time.newton = \"filtered\" or drop time.start_increment_tol")

    def _validate_extension(self) -> None:
        """``newton_extend_above`` / ``newton_extend_cap`` (:meth:`validate`)."""
        _int_at_least("time.newton_extend_cap", self.newton_extend_cap, 1)
        if self.newton_extend_above is None:
            return
        _positive("time.newton_extend_above", self.newton_extend_above)
        if self.newton_converges:
            raise ConfigError("time.newton_extend_above extends a fixed count of Newton iterations; with "
                              "time.newton_tol or time.newton_increment_tol set Newton already iterates to "
                              "that tolerance (time.newton_iterations is its cap): drop one of them")
        if self.newton_extend_cap <= self.newton_iterations:
            raise ConfigError(f"time.newton_extend_cap = {self.newton_extend_cap} is the most iterations an "
                              f"extended frame takes: it must be above time.newton_iterations = "
                              f"{self.newton_iterations} (or leave time.newton_extend_above unset)")


@dataclass
class SolverConfig:
    """``[solver]``: PETSc options and the Hessian filter.

    ``options_file`` (PETSc options, one or more per line, ``#`` comments) is read first,
    then the ``options`` string; a later option wins over an earlier one, and options
    on the command line win over both.  ``exact_fallback`` (with ``filter =
    "exact_or_analytic"``): ``"analytic"`` replaces a failed exact step by the analytic
    filter's, ``"shifted"`` first tries the exact Hessian + tau M/dt^2 (docs/newton.md
    "Seventh round"), and gives every wisp whose exact block is indefinite its own shift
    before the solve (docs/newton.md "Avoiding the saddle"); without strand contact its
    exact steps are searched wisp by wisp, a wisp whose search fails shifted further on
    its own (docs/newton.md "Frame 0 wisp by wisp").  ``exact_stay`` (same
    filter): after a full, unshifted exact step the next step is exact too, whatever its
    increment (docs/newton.md "Eighth round").  ``wisp_trust`` (with ``exact_fallback =
    "shifted"``, without strand contact): a trust region per wisp on those wisp-by-wisp
    exact steps: each wisp's mass shift is carried from one exact step to the next
    (raised where its step was cut, dropped where its quadratic model held), exact
    steps start at a relative increment of 1e-2 (not between two filtered steps that
    undo each other: ``wisp_trust.exact_switch``) and, once one is kept, every later step
    of the solve is exact (lc_petsc/wisp_trust.py; docs/newton.md "A trust region per
    wisp", "The whole runs").

    The defaults here are the paper's path.  A config file that sets a tolerance
    (``time.newton_increment_tol`` / ``newton_tol``) and does not name ``filter`` runs
    the converging path instead: ``filter``, ``exact_fallback``, ``exact_stay`` and
    ``time.newton_update`` it leaves unset take :data:`TOLERANCE_PATH`'s values, and without
    strand contact ``wisp_trust``, ``time.newton_stop`` and ``time.jolt_first_iterate`` too
    (:func:`tolerance_defaults`, summary.json ``solver_path_defaulted``).  A config built
    in Python takes these defaults as written.
    """

    options: str = ""
    options_file: Optional[str] = None
    filter: str = "analytic"
    exact_fallback: str = "analytic"
    exact_stay: bool = False
    wisp_trust: bool = False

    def validate(self) -> None:
        """Raise :class:`ConfigError` naming the key unless every value of this table is allowed."""
        if not isinstance(self.options, str):
            raise ConfigError(f"solver.options must be a string of PETSc options, got {self.options!r}")
        _check_options("solver.options", self.options)
        if self.options_file is not None:
            if not os.path.isfile(self.options_file):
                raise ConfigError(f"solver.options_file = {self.options_file!r}: no such file "
                                  "(a file of PETSc options is expected)")
            _check_options(f"solver.options_file ({self.options_file})", self._file_text())
        if self.filter not in FILTERS:
            raise ConfigError(f"solver.filter must be one of {FILTERS}, got {self.filter!r}")
        if self.exact_fallback not in EXACT_FALLBACKS:
            raise ConfigError(f"solver.exact_fallback must be one of {EXACT_FALLBACKS}, "
                              f"got {self.exact_fallback!r}")
        if self.exact_fallback != "analytic" and self.filter != "exact_or_analytic":
            raise ConfigError(f"solver.exact_fallback = {self.exact_fallback!r} applies to the exact "
                              f"steps of solver.filter = \"exact_or_analytic\" (got solver.filter = "
                              f"{self.filter!r}); set that filter or drop solver.exact_fallback")
        if not isinstance(self.exact_stay, bool):
            raise ConfigError(f"solver.exact_stay must be true or false, got {self.exact_stay!r}")
        if self.exact_stay and self.filter != "exact_or_analytic":
            raise ConfigError(f"solver.exact_stay = true applies to the exact steps of solver.filter = "
                              f"\"exact_or_analytic\" (got solver.filter = {self.filter!r}); set that "
                              f"filter or drop solver.exact_stay")
        if not isinstance(self.wisp_trust, bool):
            raise ConfigError(f"solver.wisp_trust must be true or false, got {self.wisp_trust!r}")
        if self.wisp_trust and self.exact_fallback != "shifted":
            raise ConfigError(f"solver.wisp_trust = true carries the per-wisp shifts of solver.exact_fallback = "
                              f"\"shifted\" (got {self.exact_fallback!r}); set solver.filter = "
                              f"\"exact_or_analytic\" and solver.exact_fallback = \"shifted\", or drop "
                              f"solver.wisp_trust")

    def _file_text(self) -> str:
        return read_options_file(self.options_file, "solver.options_file = ")

    def effective_options(self) -> str:
        """The options file's options followed by ``options`` (later ones win)."""
        parts = [self._file_text()] if self.options_file else []
        parts.append(self.options)
        return " ".join(p for p in parts if p.strip())


def element_filter(solver_filter):
    """The element kernels' filter of ``solver.filter`` (``exact_or_analytic`` assembles
    the exact Hessian first, see Integrator)."""
    return "analytic" if solver_filter == "exact_or_analytic" else solver_filter


def read_options_file(path, where="") -> str:
    """The options of the PETSc options file at ``path`` (``#`` comments dropped), one
    string.  A file that cannot be read or is not UTF-8 text is a ConfigError naming it
    (``where``: what names it, e.g. the config key); a binary file was a
    UnicodeDecodeError traceback."""
    try:
        text = Path(str(path)).read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(f"{where}{str(path)!r}: not a text file of PETSc options ({e.reason} at byte "
                          f"{e.start})") from None
    except OSError as e:
        raise ConfigError(f"{where}{str(path)!r}: cannot read the options file: {e.strerror or e}") from None
    return " ".join(line.split("#", 1)[0] for line in text.splitlines()).strip()


def _check_options(where: str, text: str) -> None:
    try:
        toks = shlex.split(text)
    except ValueError as e:
        raise ConfigError(f"{where}: cannot parse {text!r}: {e}") from None
    if toks and not toks[0].startswith("-"):
        raise ConfigError(f"{where}: expected PETSc options starting with '-', got {toks[0]!r} "
                          f"in {text!r}")


VIEWS = ("front", "side", "top")


@dataclass
class OutputConfig:
    """``[output]``: what the main job writes (DESIGN section 3).

    ``dir``: output folder ("" = ``out/<config file name>``; ``--out`` wins), relative to
    the working directory.  Frame 0 (the initial state) and every ``every``-th frame are
    written to ``frames.h5``.  ``xdmf``: write ``frames.xdmf`` for ParaView.
    ``previews``: PNG renderings of the frames ``preview_frames`` (simulation frame
    numbers, rounded down to a written frame; negative counts from the end, -1 = last)
    and a contact sheet of ``contact_sheet`` panels over time (0: none), seen from
    ``view`` (``front``: x-y plane, ``side``: z-y, ``top``: x-z).
    ``checkpoint_every``: write a restart checkpoint to ``<dir>/checkpoints`` every that
    many simulation frames (0: none; see :mod:`lc_petsc.io.checkpoint`);
    ``checkpoints_kept``: how many of the newest checkpoints are kept.
    ``usd``: write ``frames.usdc`` (BasisCurves for DCC tools, :mod:`lc_petsc.io.usd`)
    from ``frames.h5`` at the end of the run; ``render_hairs``: N interpolated hairs
    per wisp in it (0: none), offsets seeded by ``render_hair_seed`` and spread over
    ``render_hair_spread`` x the wisp radius (:mod:`lc_petsc.io.render_hairs`).
    ``check_crossings``: at the end, count the crossings along the straight paths
    between the written frames (:func:`lc_petsc.crossings.check_run`) into the summary,
    with a warning naming the keys to change when there are any.
    """

    dir: str = ""
    every: int = 1
    xdmf: bool = True
    previews: bool = True
    preview_frames: Sequence[int] = (0, -1)
    contact_sheet: int = 12
    view: str = "front"
    checkpoint_every: int = 0
    checkpoints_kept: int = 2
    usd: bool = True
    render_hairs: int = 0
    render_hair_seed: int = 0
    render_hair_spread: float = 1.0
    check_crossings: bool = True

    def validate(self) -> None:
        """Raise :class:`ConfigError` naming the key unless every value of this table is allowed."""
        if not isinstance(self.dir, str):
            raise ConfigError(f"output.dir must be a string (a folder), got {self.dir!r}")
        _int_at_least("output.every", self.every, 1)
        for name in ("xdmf", "previews", "usd", "check_crossings"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"output.{name} must be true or false, got {getattr(self, name)!r}")
        for f in self.preview_frames:
            if isinstance(f, bool) or not isinstance(f, int):
                raise ConfigError(f"output.preview_frames must be a list of frame numbers (integers), "
                                  f"got {list(self.preview_frames)!r}")
        _int_at_least("output.contact_sheet", self.contact_sheet, 0)
        if self.view not in VIEWS:
            raise ConfigError(f"output.view must be one of {VIEWS}, got {self.view!r}")
        _int_at_least("output.checkpoint_every", self.checkpoint_every, 0)
        _int_at_least("output.checkpoints_kept", self.checkpoints_kept, 1)
        _int_at_least("output.render_hairs", self.render_hairs, 0)
        _int_at_least("output.render_hair_seed", self.render_hair_seed, 0)
        _positive("output.render_hair_spread", self.render_hair_spread)
        if self.render_hairs and not self.usd:
            raise ConfigError(f"output.render_hairs = {self.render_hairs} needs output.usd = true "
                              "(render hairs are written into the USD export only)")


@dataclass
class SimConfig:
    """The whole configuration of a run: one dataclass per TOML table."""

    #: warnings for keys of the file that have no effect (set by config_from_dict; not a field)
    key_warnings = ()
    #: the keys :func:`tolerance_defaults` resolved to the converging path, dotted (set by
    #: config_from_dict; not a field): summary.json's ``solver_path_defaulted``
    solver_path_defaulted = ()
    scene: SceneConfig = field(default_factory=SceneConfig)
    material: MaterialConfig = field(default_factory=MaterialConfig)
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    time: TimeConfig = field(default_factory=TimeConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    def validate(self) -> "SimConfig":
        """Validate every table (:class:`ConfigError` on the first problem); returns self."""
        for part in (self.scene, self.material, self.physics, self.time, self.solver, self.output):
            part.validate()
        if self.time.newton_stop != "increment" and self.solver.filter != "exact_or_analytic":
            raise ConfigError(f"time.newton_stop = {self.time.newton_stop!r} estimates the error from "
                              f"the exact steps of solver.filter = \"exact_or_analytic\" (got "
                              f"solver.filter = {self.solver.filter!r}); set that filter or use "
                              f"time.newton_stop = \"increment\"")
        if self.time.newton_stop == "chord_estimate" and "strand_collision" in self.physics.terms:
            raise ConfigError("time.newton_stop = \"chord_estimate\" measures the next increment "
                              "from a gradient without the strand-contact force; with "
                              "strand_collision in physics.terms use time.newton_stop = "
                              "\"quadratic_estimate\" or \"increment\"")
        if self.solver.wisp_trust and "strand_collision" in self.physics.terms:
            raise ConfigError("solver.wisp_trust = true needs exact steps searched wisp by wisp, which "
                              "strand contact couples; remove strand_collision from physics.terms or "
                              "drop solver.wisp_trust")
        if self.time.newton != "filtered":
            if self.solver.filter not in ("analytic", "numerical", "abs"):
                raise ConfigError(f"time.newton = \"trust_region\" preconditions with the filtered "
                                  f"Hessian of solver.filter, which must be positive semi-definite: "
                                  f"use analytic, numerical or abs, not {self.solver.filter!r}")
            if "strand_collision" in self.physics.terms:
                raise ConfigError("time.newton = \"trust_region\" does not support strand contact "
                                  "(its Newton matrix is the contact code's operator): remove "
                                  "strand_collision from physics.terms or use time.newton = \"filtered\"")
        if self.scene.kind in ("wisp4c", "straight") and self.scene.n_pinned > self.scene.n_vertices:
            raise ConfigError(f"scene.n_pinned = {self.scene.n_pinned} is more than the wisp's "
                              f"{self.scene.n_vertices} vertices (scene.n_vertices)")
        return self

    def start_config(self) -> "SimConfig":
        """The configuration of the start frames (``time.start_increment_tol``): Newton to
        that relative increment tolerance, capped at ``time.start_iterations``, on the
        recommended converging path (docs/newton.md): the exact Hessian near the solution
        (``exact_or_analytic``), the shifted fallback, exact steps kept once taken
        (``exact_stay``), the corotational update, the increment stop; no root turn, no
        extension.  Not ``wisp_trust``: its earlier exact steps cost hairball10's frame 0
        1.6x the CPU (17 iterations against 16) (docs/newton.md "Twenty-second round").  The
        scene, physics, step cutback and PETSc options are the run's."""
        t = self.time
        time = replace(t, newton_increment_tol=t.start_increment_tol, newton_tol=None,
                       newton_iterations=t.start_iterations, newton_update="corotational", line_search=False,
                       newton_stop="increment", root_rotation=False, newton_extend_above=None,
                       start_increment_tol=None, jolt_above=None, jolt_frames=1)
        solver = replace(self.solver, filter="exact_or_analytic", exact_fallback="shifted", exact_stay=True,
                         wisp_trust=False)
        return replace(self, time=time, solver=solver)

    def to_dict(self) -> dict:
        """The resolved configuration as plain dicts (summary.json's ``config``)."""
        return asdict(self)


# --------------------------------------------------------------------------- TOML
TABLES = {"scene": SceneConfig, "material": MaterialConfig, "physics": PhysicsConfig,
          "time": TimeConfig, "solver": SolverConfig, "output": OutputConfig}
# keys holding file paths: resolved relative to the config file's folder
PATH_KEYS = {("scene", "path"), ("solver", "options_file")}

_TOML_TYPES = {bool: "a boolean (true/false)", int: "an integer", float: "a float",
               str: "a string", list: "an array", dict: "a table"}


def _toml_type(v) -> str:
    for t, name in _TOML_TYPES.items():
        if type(v) is t:
            return name
    return type(v).__name__


def _convert(key: str, annotation: str, value):
    """Check a TOML value against a field's annotation; return the field value."""
    base = annotation.replace("Optional[", "").rstrip("]") if annotation.startswith("Optional[") \
        else annotation

    def fail(expected):
        raise ConfigError(f"{key} = {value!r}: expected {expected}, got {_toml_type(value)}")

    for text in (value if isinstance(value, list) else [value]):
        if isinstance(text, str) and "\x00" in text:
            raise ConfigError(f"{key} = {value!r}: contains a NUL character (\\0), which the HDF5 "
                              "outputs cannot hold; remove it")

    if base == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            fail("a number")
        return float(value)
    if base == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            fail("an integer")
        return value
    if base == "bool":
        if not isinstance(value, bool):
            fail("true or false")
        return value
    if base == "str":
        if not isinstance(value, str):
            fail("a string")
        return value
    if base == "Sequence[float]":
        if not isinstance(value, list) or len(value) != 3 or \
                any(isinstance(c, bool) or not isinstance(c, (int, float)) for c in value):
            fail("an array of 3 numbers, e.g. [0.0, -981.0, 0.0]")
        return tuple(float(c) for c in value)
    if base == "Sequence[str]":
        if not isinstance(value, list) or any(not isinstance(c, str) for c in value):
            fail("an array of strings")
        return tuple(value)
    if base == "Sequence[int]":
        if not isinstance(value, list) or any(isinstance(c, bool) or not isinstance(c, int) for c in value):
            fail("an array of integers")
        return tuple(value)
    raise AssertionError(f"no TOML conversion for {key}: {annotation}")   # pragma: no cover


def config_from_dict(data: dict, base_dir=None) -> SimConfig:
    """A validated :class:`SimConfig` from the parsed TOML ``data``.

    Relative paths of :data:`PATH_KEYS` are taken relative to ``base_dir``.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"a config is a set of TOML tables, got {_toml_type(data)}")
    parts = {}
    for table, value in data.items():
        if table not in TABLES:
            raise ConfigError(f"unknown table [{table}]; allowed tables: "
                              + ", ".join(f"[{t}]" for t in TABLES))
        if not isinstance(value, dict):
            raise ConfigError(f"{table} = {value!r}: expected the table [{table}], got {_toml_type(value)}")
        cls = TABLES[table]
        known = {f.name: f for f in fields(cls)}
        kwargs = {}
        for key, v in value.items():
            if key not in known:
                raise ConfigError(f"unknown key {table}.{key} (= {v!r}); allowed keys of [{table}]: "
                                  + ", ".join(known))
            v = _convert(f"{table}.{key}", str(known[key].type), v)
            if (table, key) in PATH_KEYS and base_dir is not None:
                v = str((Path(base_dir) / os.path.expanduser(v)).resolve())
            kwargs[key] = v
        parts[table] = cls(**kwargs)
    cfg = SimConfig(**parts)
    given = {(table, key) for table, value in data.items() for key in value}
    cfg.solver_path_defaulted = tolerance_defaults(cfg, given)
    cfg.validate()
    cfg.key_warnings = keys_without_effect(cfg, data) + implausible_values(cfg, data)
    return cfg


#: config keys a restart may change: they touch neither the trajectory nor frames.h5's rows
#: (here, not in lc_petsc.job, so that reading summaries needs no PETSc)
RESTART_FREE_KEYS = {"time.frames", "output.dir", "output.xdmf", "output.previews",
                     "output.preview_frames", "output.contact_sheet", "output.view",
                     "output.checkpoint_every", "output.checkpoints_kept",
                     "output.usd", "output.render_hairs", "output.render_hair_seed",
                     "output.render_hair_spread", "output.check_crossings", "scene.description"}


#: the converging path a run with a tolerance takes where its file leaves the keys unset
#: (:func:`tolerance_defaults`): the exact Hessian once close with the analytic filter before,
#: the shifted fallback, exact steps kept once taken, the corotational update (docs/newton.md
#: "The default for tolerance runs"); a fixed count keeps the dataclass defaults, the paper's path
TOLERANCE_PATH = {("solver", "filter"): "exact_or_analytic", ("solver", "exact_fallback"): "shifted",
                  ("solver", "exact_stay"): True, ("time", "newton_update"): "corotational"}
#: added without strand contact (which refuses the first two): the per-wisp trust region
#: (with the shifted fallback) and the chord stop (with ``newton_increment_tol`` alone),
#: hairball10 30 frames at 1e-6: 202 iterations, worst frame 14, against 248 and 21, the
#: same CPU; and the start's first iterate at a jump of the head's velocity, the demo
#: without strand contact 90 frames: worst frame 15 against 17, median 6; with strand
#: contact it bought nothing measurable (the demo at 1e-4 on 1, 2 and 3 ranks: 2,879
#: iterations against 2,728, the jumps' frames 252 against 248), so not there
#: (docs/newton.md "The default for tolerance runs", "The jolts' first iterate with strand
#: contact and at a fixed count")
TOLERANCE_PATH_WITHOUT_STRAND_CONTACT = {("solver", "wisp_trust"): True, ("time", "newton_stop"): "chord_estimate",
                                         ("time", "jolt_first_iterate"): True}


def tolerance_defaults(cfg: SimConfig, given) -> tuple:
    """Resolve the Newton path of a run with a tolerance (``time.newton_increment_tol`` or
    ``newton_tol``) whose file does not name ``solver.filter``: each key of
    :data:`TOLERANCE_PATH` (and, without strand contact, of
    :data:`TOLERANCE_PATH_WITHOUT_STRAND_CONTACT` where its conditions hold: the shifted
    fallback, ``newton_increment_tol`` alone) that is not in ``given`` (the file's (table,
    key) pairs) takes the converging path's value, in place.  With the analytic filter the paper's path
    barely converges (hairball10, 90 frames at 1e-6: 28,116 iterations, every frame cut
    back, against 724; docs/newton.md "The default for tolerance runs").  A file that
    names ``solver.filter``, a fixed count and ``time.newton = "trust_region"`` keep the
    defaults as they are.  Returns the resolved keys, dotted ("solver.filter", ...)."""
    if not cfg.time.newton_converges or cfg.time.newton != "filtered" or ("solver", "filter") in given:
        return ()
    path = dict(TOLERANCE_PATH)
    if "strand_collision" not in cfg.physics.terms:
        path.update(TOLERANCE_PATH_WITHOUT_STRAND_CONTACT)
    out = []
    for (table, key), value in path.items():
        if (table, key) in given or (key == "wisp_trust" and cfg.solver.exact_fallback != "shifted") or \
                (key == "newton_stop" and cfg.time.newton_tol is not None):
            continue
        setattr(getattr(cfg, table), key, value)
        out.append(f"{table}.{key}")
    return tuple(out)


def without_tolerance_defaults(cfg: SimConfig) -> SimConfig:
    """``cfg`` with the keys :func:`tolerance_defaults` resolved (``solver_path_defaulted``)
    back at their dataclass defaults, in place: for a study that sets its own tolerance or
    fixed count and Newton path on a config file's scene (lc_petsc/studies/newton.py and
    tradeoff.py ``configure``).  Otherwise the file's tolerance's defaults stayed in every
    variant: ``time.newton_stop = "chord_estimate"`` refused a fixed count or a named
    analytic filter, so such a file's study stopped on a ConfigError.  Returns ``cfg``."""
    names: tuple[str, ...] = cfg.solver_path_defaulted
    for name in names:
        table, key = name.split(".")
        setattr(getattr(cfg, table), key, getattr(type(getattr(cfg, table))(), key))
    cfg.solver_path_defaulted = ()
    return cfg


#: keys that only act for some settings: (table, key) -> (predicate on the config, when)
_CONDITIONAL_KEYS = {
    ("scene", "n_wisps"): (lambda c: c.scene.kind == "hairball", "scene.kind = 'hairball'"),
    ("scene", "n_vertices"): (lambda c: c.scene.kind in ("wisp4c", "straight"),
                              "scene.kind = 'wisp4c' or 'straight'"),
    ("scene", "seed"): (lambda c: c.scene.kind == "hairball" or c.scene.perturbation == "jitter",
                        "scene.kind = 'hairball' or scene.perturbation = 'jitter'"),
    ("scene", "path"): (lambda c: c.scene.kind in ("file", "usd"), "scene.kind = 'file' or 'usd'"),
    ("scene", "segment_length"): (lambda c: c.scene.kind == "straight", "scene.kind = 'straight'"),
    ("scene", "direction"): (lambda c: c.scene.kind == "straight", "scene.kind = 'straight'"),
    ("scene", "smash_factor"): (lambda c: c.scene.perturbation == "smash", "scene.perturbation = 'smash'"),
    ("scene", "jitter"): (lambda c: c.scene.perturbation == "jitter", "scene.perturbation = 'jitter'"),
    ("material", "radius_scale_with_count"): (lambda c: c.scene.kind == "hairball",
                                              "scene.kind = 'hairball'"),
    ("time", "start_frames"): (lambda c: c.time.start_increment_tol is not None, "time.start_increment_tol set"),
    ("time", "start_iterations"): (lambda c: c.time.start_increment_tol is not None,
                                   "time.start_increment_tol set"),
    ("time", "jolt_above"): (lambda c: c.physics.head_motion != "static", "physics.head_motion is not 'static'"),
    ("time", "jolt_frames"): (lambda c: c.time.jolt_above is not None, "time.jolt_above set"),
    ("time", "jolt_first_iterate"): (lambda c: c.physics.head_motion == "translate" or (
        c.physics.head_motion == "shake" and not c.physics.head_smooth),
        "a head whose velocity jumps: physics.head_motion = 'shake' without physics.head_smooth, or 'translate'"),
    ("physics", "head_amplitude"): (lambda c: c.physics.head_motion == "shake",
                                    "physics.head_motion = 'shake'"),
    ("physics", "head_period"): (lambda c: c.physics.head_motion == "shake",
                                 "physics.head_motion = 'shake'"),
    ("material", "twist_rest_sine"): (lambda c: "twist" in c.physics.terms,
                                      "'twist' in physics.terms"),
    ("physics", "head_smooth"): (lambda c: c.physics.head_motion == "shake",
                                 "physics.head_motion = 'shake'"),
    ("physics", "head_velocity"): (lambda c: c.physics.head_motion == "translate",
                                   "physics.head_motion = 'translate'"),
    ("physics", "head_stiffness"): (lambda c: "head_collision" in c.physics.terms,
                                    "'head_collision' in physics.terms"),
    ("physics", "head_margin"): (lambda c: "head_collision" in c.physics.terms,
                                 "'head_collision' in physics.terms"),
    ("physics", "head_push_out"): (lambda c: "head_collision" in c.physics.terms,
                                   "'head_collision' in physics.terms"),
    ("physics", "gravity"): (lambda c: "gravity" in c.physics.terms, "'gravity' in physics.terms"),
    ("physics", "strand_thickness"): (lambda c: "strand_collision" in c.physics.terms,
                                      "'strand_collision' in physics.terms"),
    ("physics", "strand_stiffness"): (lambda c: "strand_collision" in c.physics.terms,
                                      "'strand_collision' in physics.terms"),
    ("physics", "strand_separation"): (lambda c: "strand_collision" in c.physics.terms,
                                       "'strand_collision' in physics.terms"),
    ("physics", "strand_contact_potential"): (lambda c: "strand_collision" in c.physics.terms,
                                              "'strand_collision' in physics.terms"),
    ("physics", "strand_self_contact"): (lambda c: "strand_collision" in c.physics.terms,
                                         "'strand_collision' in physics.terms"),
    ("physics", "strand_contact_mode"): (lambda c: "strand_collision" in c.physics.terms,
                                         "'strand_collision' in physics.terms"),
    ("physics", "strand_rest_overlap"): (lambda c: "strand_collision" in c.physics.terms,
                                         "'strand_collision' in physics.terms"),
    ("physics", "strand_min_separation"): (
        lambda c: "strand_collision" in c.physics.terms and c.physics.strand_contact_mode == "ccd",
        "'strand_collision' in physics.terms and physics.strand_contact_mode = 'ccd'"),
    ("physics", "strand_barrier_stiffness"): (
        lambda c: "strand_collision" in c.physics.terms and c.physics.strand_contact_potential == "barrier",
        "'strand_collision' in physics.terms and physics.strand_contact_potential = 'barrier'"),
}


def keys_without_effect(cfg: SimConfig, data: dict):
    """Warnings for keys set in the TOML ``data`` that the chosen scene and terms ignore."""
    out = []
    for (table, key), (applies, when) in _CONDITIONAL_KEYS.items():
        if key in (data.get(table) or {}) and not applies(cfg):
            out.append(f"{table}.{key} is set but has no effect: it only acts with {when}")
    return out


_MODULUS_RANGE = (1.0e6, 1.0e12, "dyn/cm^2",
                  "it looks like MPa or GPa (hair keratin: about 4 GPa = 4e10 dyn/cm^2; "
                  "1 Pa = 10 dyn/cm^2)",
                  "stiffer than any hair (keratin about 4e10 dyn/cm^2, steel 2e12); check that "
                  "it is in dyn/cm^2 (1 Pa = 10 dyn/cm^2)")
_RADIUS_RANGE = (5.0e-4, 2.0, "cm",
                 "thinner than any hair; it looks like metres (a 40 um hair: 4e-5 m = 0.004 cm)",
                 "it looks like millimetres or micrometres (3.5 mm = 0.35 cm, 40 um = 0.004 cm)")
#: (table, key) -> (low, high, unit, likely mistake below, above): the range a hair scene's
#: value lies in; outside it the run goes on with a warning (a wrong unit is the usual cause)
PLAUSIBLE_RANGES = {
    ("material", "youngs_modulus"): _MODULUS_RANGE,
    ("material", "shear_modulus"): _MODULUS_RANGE,
    ("material", "root_radius"): _RADIUS_RANGE,
    ("material", "tip_radius"): _RADIUS_RANGE,
    ("time", "dt"): (MIN_DT, 1.0, "s", "",
                     "it looks like milliseconds (33 ms = 0.033 s; one frame at 30 fps is 1/30 s)"),
    ("physics", "head_radius"): (1.0, 100.0, "cm", "it looks like metres (0.15 m = 15 cm)",
                                 "it looks like millimetres (152.5 mm = 15.25 cm)"),
}
#: |physics.gravity| of a hair scene (cm/s^2), and the likely mistakes outside
GRAVITY_RANGE = (100.0, 5000.0, "cm/s^2", "it looks like m/s^2 (9.81 m/s^2 = 981 cm/s^2)",
                 "it looks like mm/s^2 (9810 mm/s^2 = 981 cm/s^2)")


def _outside(name, value, plausible):
    """The warning for ``value`` of the key ``name`` outside ``plausible`` (a
    :data:`PLAUSIBLE_RANGES` entry), or None."""
    lo, hi, unit, below, above = plausible
    if lo <= value <= hi:
        return None
    return (f"{name} = {value:g} {unit} is outside the plausible range for hair, {lo:g} to "
            f"{hi:g} {unit}: {below if value < lo else above}; lc_petsc's units are cm, g, s")


def implausible_values(cfg: SimConfig, data: dict):
    """Warnings for values set in the TOML ``data`` that are valid but far outside what a
    hair scene uses (:data:`PLAUSIBLE_RANGES`, :data:`GRAVITY_RANGE` when gravity acts),
    naming the likely unit mistake; the run still goes ahead."""
    out = []
    for (table, key), plausible in PLAUSIBLE_RANGES.items():
        if key in (data.get(table) or {}) and (key != "head_radius"
                                               or "head_collision" in cfg.physics.terms):
            out.append(_outside(f"{table}.{key}", float(getattr(getattr(cfg, table), key)), plausible))
    g = math.hypot(*cfg.physics.gravity)
    if "gravity" in (data.get("physics") or {}) and "gravity" in cfg.physics.terms and g > 0:
        out.append(_outside("|physics.gravity|", g, GRAVITY_RANGE))
    return [w for w in out if w]


def load_config(path) -> SimConfig:
    """Read a TOML scene file (DESIGN section 3) into a validated :class:`SimConfig`.

    Raises :class:`ConfigError` whose message starts with the file name and names the
    key, its value and what is allowed; a missing or unreadable file and TOML syntax
    errors are ConfigErrors too.
    """
    import tomllib
    path = Path(path)
    if path.exists() and not path.is_file():
        raise ConfigError(f"{path}: not a regular file (a TOML scene file is expected)")
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot read the config file: {e.strerror or e}") from None
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not a UTF-8 text file ({e.reason} at byte {e.start})") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: invalid TOML: {e}") from None
    if not data:        # a zero-length file (a failed copy) ran the defaults' 1-wisp scene
        raise ConfigError(f"{path}: the config file is empty ({len(raw)} bytes, no key): a scene file "
                          "names at least its [scene]; see configs/ for examples")
    try:
        return config_from_dict(data, base_dir=path.resolve().parent)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None
