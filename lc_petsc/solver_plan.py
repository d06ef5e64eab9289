"""The solver plan: which linear solver a simulator uses, resolved once.

PETSc reads its solver choices from the options database, in layers (a later layer
wins):

1. code defaults (:data:`DEFAULTS`, set on the KSP before ``setFromOptions``, and the
   per-wisp sub-solver default of :func:`sub_solver_defaults`);
2. the config's ``solver.options_file``, then its ``solver.options`` string;
3. the command line (and ``PETSC_OPTIONS``): already in the database when a plan is
   resolved.

:meth:`SolverPlan.resolve` reads those layers once and derives from them what lc_petsc
decides itself, before any PETSc object exists:

* the operator's matrix type (``baij`` unless ``-mat_type``; MUMPS and GAMG refuse BAIJ,
  so they get ``sbaij`` / ``aij``);
* the type of a separate preconditioning matrix (``-lc_pmat_type``; an AIJ copy where
  block Jacobi would extract many blocks from BAIJ);
* the per-wisp block Jacobi (``-lc_wisp_blocks fused|separate``, None for another
  preconditioner);
* with strand contact, what the preconditioner is built from (``-lc_contact_pc
  coupled|strands|clusters``; ``clusters``: lc_petsc/contact_pc.py, with its caps
  ``-lc_cluster_max_wisps``, ``-lc_cluster_max_blocks``, its fallback threshold
  ``-lc_cluster_min_captured``, the ordering of its LU ``-lc_cluster_ordering`` and
  ``-lc_cluster_span global|rank``: clusters across ranks or inside each, and the
  factor of the wisps outside clusters ``-lc_band_factor cholesky|ilu``);
* the factorisation defaults: MUMPS gets the AMF ordering (``-mat_mumps_icntl_7 2``)
  unless the options say otherwise;
* lc_petsc's own build choices read from the same database: the element kernels
  (``-lc_element_kernels compiled|numpy``), the wisp order of the partition
  (``-lc_wisp_order spatial|input``), which rank computes a contact pair
  (``-lc_contact_work owner|balanced``) and the Newton monitor (``-lc_newton_monitor``).

The plan is frozen and built once per simulator; the assembler, the linear solver, the
strand contact and the run summary read it instead of the database.  Its config
options are put into the database only while PETSc objects read them
(:meth:`SolverPlan.active`) and removed afterwards, so several plans in one process (a
solver-comparison study, the tests) never see each other's options.  A plan may carry
an options prefix (``-<prefix>ksp_type``...); the main job's is empty, so every
documented option keeps its name.  The plan also records which options were read, for
the summary's ``petsc_options_used`` and the warning about options nothing used.

Option errors raise :class:`lc_petsc.errors.ConfigError`.  This module is the only one
that reads the PETSc options database (besides PETSc's own ``setFromOptions``).
"""

from __future__ import annotations

import shlex
from contextlib import contextmanager
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping, Optional

from petsc4py import PETSc

from lc_petsc.contact_pc import BAND_FACTORS, MAX_BLOCKS, MAX_WISPS, MIN_CAPTURED, ORDERINGS, SPANS
from lc_petsc.errors import ConfigError
from lc_petsc.options import option_pairs
from lc_petsc.parallel import CONTACT_WORK, WISP_ORDERS
from lc_petsc.petsc_capi import option_used

#: the paper's solver (SPEC 5): CG with one exact block-Jacobi block per wisp (its
#: tolerance: :data:`KSP_RTOL_FIXED_COUNT` / :data:`KSP_RTOL_CONVERGING`)
DEFAULTS = MappingProxyType({"ksp_type": "cg", "ksp_max_it": "1000", "pc_type": "bjacobi"})
#: ``-ksp_rtol`` default of a fixed-count Newton (``time.newton_tol`` and
#: ``newton_increment_tol`` unset, the paper's 3 iterations): its truncation error
#: dwarfs the linear solve's.  Measured on the 2K hairball's ccd frames 90 and 100
#: (docs/contact_solver.md, "The linear tolerance a truncated Newton needs"): one frame
#: from the same state with 1e-4 lies 2.4e-3 / 3.5e-3 cm (RMS) from the exact solves'
#: frame, a fourth Newton iteration moves it 4.2e-2 cm and six 9.0e-2 cm; CG needs 45
#: instead of 96-106 iterations per solve.
KSP_RTOL_FIXED_COUNT = "1e-4"
#: ``-ksp_rtol`` default of a Newton that converges to a tolerance: tight, so
#: that the linear error does not stall the last, quadratic, iterations
KSP_RTOL_CONVERGING = "1e-6"


def default_ksp_rtol(newton_converges: bool) -> str:
    """The code default of ``-ksp_rtol`` for a Newton that converges to a tolerance
    (:attr:`TimeConfig.newton_converges`) or runs a fixed count."""
    return KSP_RTOL_CONVERGING if newton_converges else KSP_RTOL_FIXED_COUNT
WISP_BLOCK_MODES = ("fused", "separate")
CONTACT_PC_MODES = ("coupled", "strands", "clusters")
#: ``-lc_element_kernels``: the compiled (Numba) kernels or the NumPy reference kernels
ELEMENT_KERNELS = ("compiled", "numpy")
#: operator types the assembler can fill
SUPPORTED_MAT_TYPES = ("baij", "sbaij", "aij")
#: lc_petsc's own options (read by the plan from the same database)
LC_OPTIONS = ("lc_wisp_blocks", "lc_pmat_type", "lc_contact_pc", "lc_cluster_max_wisps",
              "lc_cluster_max_blocks", "lc_cluster_min_captured", "lc_cluster_ordering",
              "lc_cluster_span", "lc_band_factor", "lc_element_kernels", "lc_wisp_order",
              "lc_contact_work", "lc_newton_monitor")


def base_type(mat_type: str) -> str:
    """PETSc matrix type without its ``seq`` / ``mpi`` prefix (``mpibaij`` -> ``baij``)."""
    t = mat_type.lower()
    for prefix in ("seq", "mpi"):
        if t.startswith(prefix):
            t = t[len(prefix):]
    return t


def parse_options(text: str):
    """'-a 1 -flag -b x' -> [('a', '1'), ('flag', ''), ('b', 'x')] (leading dashes removed)."""
    try:
        return option_pairs(shlex.split(text or ""), what="solver.options")
    except ValueError as e:
        raise ConfigError(str(e)) from None


def sub_solver_defaults(mat_type: str) -> dict:
    """Default sub-solver of the per-wisp blocks: exact on a full band (ILU(0) = LU; PETSc
    would pick ICC(0) with a Manteuffel shift for a symmetric matrix, which is not exact
    here); PETSc's native SBAIJ factorisations were measured to be inexact too, so SBAIJ
    gets MUMPS Cholesky."""
    if base_type(mat_type) == "sbaij":
        return {"sub_pc_type": "cholesky", "sub_pc_factor_mat_solver_type": "mumps"}
    return {"sub_pc_type": "ilu"}


def factor_defaults(layers: "_Layers") -> dict:
    """Code defaults of a factorisation the options select: MUMPS (``-pc_type cholesky|lu
    -pc_factor_mat_solver_type mumps``) gets the AMF ordering (``-mat_mumps_icntl_7 2``;
    measured on the recorded 2K systems with contact: 0.72x the default CG time, against
    1.7x with MUMPS's own default ordering, issue 18); a ``-mat_mumps_icntl_7`` of the
    config or command line wins."""
    pc = (layers.lookup("pc_type") or "").lower()
    package = (layers.lookup("pc_factor_mat_solver_type") or "").lower()
    if package == "mumps" and pc in ("cholesky", "lu"):
        return {"mat_mumps_icntl_7": "2"}
    return {}


class _Layers:
    """The config's options over the database (command line), and which were read.

    ``lookup`` prefers the database (the command line wins); a config option found by
    it counts as used.  ``active`` inserts the config options (and ``extra`` defaults)
    that the database does not hold and removes exactly those again, noting first which
    of them PETSc read in the meantime.
    """

    def __init__(self, config_options: str, prefix: str):
        self.prefix = prefix
        self.options = dict(parse_options(config_options))
        self.used: set[str] = set()

    def _db(self):
        return PETSc.Options(self.prefix or None)

    def lookup(self, key):
        opts = self._db()
        if opts.hasName(key):
            return opts.getString(key, "")
        if key in self.options:
            self.used.add(key)
        return self.options.get(key)

    @contextmanager
    def active(self, extra):
        opts = self._db()
        added = []
        layers = dict(extra)
        layers.update(self.options)
        for k, v in layers.items():
            if not opts.hasName(k):
                opts.setValue(k, v)
                added.append(k)
        try:
            yield
        finally:
            for k in added:
                if k not in self.used and option_used(self.prefix + k):   # known: no C call
                    self.used.add(k)
                opts.delValue(k)


@dataclass(frozen=True)
class SolverPlan:
    """What the linear solver of one simulator is; see the module doc.

    ``options``: the config's options (options file, then string; later wins), without
    dashes; ``mat_type``: the operator's type (the assembler's request to PETSc);
    ``pmat_type``: the separate preconditioning matrix's type, None for the operator
    itself; ``pc_type``: the preconditioner (lower case); ``wisp_blocks``: ``fused`` /
    ``separate`` per-wisp block Jacobi, None for another preconditioner;
    ``contact_pc``: ``coupled`` / ``strands`` / ``clusters`` with strand contact, else
    None; ``cluster_caps``: (max wisps, max cross blocks, min captured share, LU
    ordering, span, the singletons' band factor) of the clusters with ``clusters``, else None;
    ``sub_solver``: the per-wisp blocks' default sub-solver options; ``factor``: the
    factorisation defaults (:func:`factor_defaults`);
    ``element_kernels``: ``compiled`` / ``numpy``; ``wisp_order``: ``spatial`` / ``input``;
    ``contact_work``: ``owner`` / ``balanced`` (which rank computes a contact pair);
    ``ksp_rtol``: the code default of ``-ksp_rtol`` (the options win), by the Newton's
    stopping rule (:data:`KSP_RTOL_FIXED_COUNT`, :data:`KSP_RTOL_CONVERGING`);
    ``newton_monitor``: ``-lc_newton_monitor`` was given (a line per Newton iteration on
    rank 0's standard output, like ``-snes_monitor``).
    """

    prefix: str
    options: Mapping[str, str]
    mat_type: str
    pmat_type: Optional[str]
    pc_type: str
    wisp_blocks: Optional[str]
    contact_pc: Optional[str]
    cluster_caps: Optional[tuple[int, int, float, str, str, str]]
    sub_solver: Mapping[str, str]
    factor: Mapping[str, str]
    element_kernels: str
    wisp_order: str
    contact_work: str
    ksp_rtol: str
    newton_monitor: bool
    _layers: _Layers = field(repr=False, compare=False)

    @classmethod
    def resolve(cls, config_options: str = "", strand_contact: bool = False,
                prefix: str = "", newton_converges: bool = False) -> "SolverPlan":
        """The plan of the config options ``config_options`` (a string of PETSc options)
        over the options database; ``strand_contact``: the simulation has strand-strand
        contact; ``newton_converges``: Newton iterates to a tolerance
        (:attr:`TimeConfig.newton_converges`), not a fixed count, which tightens the
        default ``-ksp_rtol``.  Raises :class:`ConfigError` for options that contradict
        each other or lc_petsc's own options with a bad value."""
        layers = _Layers(config_options, prefix)
        mat_type = _operator_type(layers)
        wisp_blocks = _wisp_block_mode(layers)
        contact_pc = _contact_pc(layers, mat_type, wisp_blocks) if strand_contact else None
        pmat_type = _pmat_type(layers, mat_type, strand_pc=contact_pc == "strands")
        pc_type = (layers.lookup("pc_type") or DEFAULTS["pc_type"]).lower()
        caps = _cluster_caps(layers, mat_type, wisp_blocks) if contact_pc == "clusters" else None
        return cls(prefix=prefix, options=MappingProxyType(dict(layers.options)),
                   mat_type=mat_type, pmat_type=pmat_type, pc_type=pc_type,
                   wisp_blocks=wisp_blocks, contact_pc=contact_pc, cluster_caps=caps,
                   sub_solver=MappingProxyType(sub_solver_defaults(mat_type)),
                   factor=MappingProxyType(factor_defaults(layers)),
                   element_kernels=_choice(layers, "lc_element_kernels", ELEMENT_KERNELS,
                                           "compiled (Numba, the default) or numpy (the reference kernels)"),
                   wisp_order=_choice(layers, "lc_wisp_order", WISP_ORDERS,
                                      "spatial (wisps ordered along a space-filling curve of their "
                                      "roots, the default) or input (the scene's order)"),
                   contact_work=_choice(layers, "lc_contact_work", CONTACT_WORK,
                                        "owner (a pair's work on the lower rank owning its wisps, "
                                        "the default) or balanced (on ranks cut by contact work)"),
                   ksp_rtol=default_ksp_rtol(newton_converges),
                   newton_monitor=_flag(layers, "lc_newton_monitor",
                                        "a line per Newton iteration on standard output"),
                   _layers=layers)

    @contextmanager
    def active(self, extra=None):
        """The plan's config options, sub-solver and factorisation defaults (and the
        code defaults ``extra``, {key: value} without dashes) in the options database
        (the command line's win) while PETSc objects are created, set from options,
        set up and used; removed again on exit."""
        with self._layers.active({**self.sub_solver, **self.factor, **(extra or {})}):
            yield

    def effective(self):
        """The config options' values in effect, the command line's winning (without
        marking any as used)."""
        db = PETSc.Options().getAll()
        p = self.prefix
        return {k: (db[p + k] or "") if p + k in db else v for k, v in sorted(self.options.items())}

    def options_used(self, command_line, mat_type):
        """The options in effect, as recorded in summary.json's ``petsc_options_used``:
        code defaults < sub-solver and factorisation defaults < config < command line, and
        the operator's actual ``mat_type``."""
        used = dict(DEFAULTS, ksp_rtol=self.ksp_rtol)
        used.update(self.sub_solver)
        used.update(self.factor)
        used.update(self.options)
        used.update(command_line)
        used["mat_type"] = mat_type
        return dict(sorted(used.items()))

    def unused_options(self, given=()):
        """Options of the config and of ``given`` (the command line) that nothing ever
        read: typos, or options of a solver that is not selected (PETSc's
        ``-options_left``)."""
        names = {self.prefix + k: k for k in self.options}     # database name -> config key
        for k in given:
            names.setdefault(k, None)
        used = self._layers.used
        return sorted(n for n, k in names.items()
                      if (k is None or k not in used) and not option_used(n))


@contextmanager
def command_line_options(command_line):
    """``command_line`` ({key: value}) in the options database for the duration: needed
    when PETSc was initialised before the command line was parsed (several runs in one
    process, the tests).  Entries it adds are removed and values it changes are restored
    on exit, so one run's options never reach the next.  Yields every option given
    (what the database held before, overridden by ``command_line``)."""
    opts = PETSc.Options()
    before = opts.getAll()     # (not hasName: that would mark the option as used)
    added, changed = [], {}
    for k, v in command_line.items():
        if k not in before:
            opts.setValue(k, v)
            added.append(k)
        elif (before.get(k) or "") != v:
            opts.setValue(k, v)
            changed[k] = before[k]
    given = {k: (v or "") for k, v in before.items()}
    given.update(command_line)
    try:
        yield given
    finally:
        for k in added:
            opts.delValue(k)
        for k, v in changed.items():
            opts.setValue(k, v)


# ---------------------------------------------------------------- derived choices
def _operator_type(layers: _Layers, default="baij") -> str:
    """The operator's matrix type: ``-mat_type``, else ``sbaij`` for MUMPS Cholesky,
    ``aij`` for MUMPS LU and GAMG (both refuse BAIJ), else ``default``."""
    explicit = layers.lookup("mat_type")
    pc = (layers.lookup("pc_type") or "").lower()
    package = (layers.lookup("pc_factor_mat_solver_type") or "").lower()
    mumps = package == "mumps" and pc in ("cholesky", "lu")
    gamg = pc == "gamg"
    if explicit:
        t = explicit.lower()
        if t.endswith("baij") and not t.endswith("sbaij") and (mumps or gamg):
            need = "-mat_type sbaij or -mat_type aij" if pc == "cholesky" else "-mat_type aij"
            what = "MUMPS" if mumps else "GAMG"
            raise ConfigError(f"{what} does not accept BAIJ matrices (-mat_type {explicit}); "
                              f"add {need}")
        return explicit
    if mumps:
        return "sbaij" if pc == "cholesky" else "aij"
    if gamg:
        return "aij"
    return default


def _pmat_type(layers: _Layers, mat_type: str, strand_pc: bool = False):
    """Matrix type of a separate preconditioning matrix, or None to use the operator.

    ``-lc_pmat_type aij|same``; by default an AIJ copy (same values) is made only where
    block Jacobi would extract several blocks per rank from a BAIJ operator (separate
    per-wisp blocks, or blocks set by ``-pc_bjacobi_*blocks``): PETSc 3.18 extracts each
    block from SeqBAIJ with a column map as wide as the whole matrix
    (``Assembler._create_pmat``).  The fused per-wisp blocks factor the operator's rank
    block itself (no extraction; BAIJ's 3x3-block ILU(0) is the cheaper one), except
    when the preconditioner is built from the strand matrix under strand contact
    (``strand_pc``): CG then runs tens to hundreds of iterations, and the point ILU of
    the AIJ copy avoids the block ILU's explicit 3x3 pivot inverses, whose round-off
    made runs on different rank counts drift apart faster on one machine
    (docs/design_notes.md has the measurements).
    """
    explicit = layers.lookup("lc_pmat_type")
    if explicit:
        if explicit not in ("aij", "same"):
            raise ConfigError(f"-lc_pmat_type {explicit!r}: use aij or same")
        return None if explicit == "same" else explicit
    pc = (layers.lookup("pc_type") or DEFAULTS["pc_type"]).lower()
    extracts = pc == "bjacobi" and (_wisp_block_mode(layers) != "fused" or strand_pc)
    return "aij" if extracts and base_type(mat_type) == "baij" else None


def _choice(layers: _Layers, key, choices, meaning):
    """The value of option ``key`` among ``choices`` (the first is the default)."""
    value = layers.lookup(key) or choices[0]
    if value not in choices:
        raise ConfigError(f"-{key} {value!r}: use {meaning}")
    return value


def _flag(layers: _Layers, key, meaning):
    """Whether the flag option ``key`` is on: given without a value, or with true / 1 /
    yes (false / 0 / no: off; absent: off)."""
    value = layers.lookup(key)
    if value is None:
        return False
    value = value.strip().lower()
    if value in ("", "1", "true", "yes", "on"):
        return True
    if value in ("0", "false", "no", "off"):
        return False
    raise ConfigError(f"-{key} {value!r}: give it without a value to turn it on ({meaning}), "
                      f"or with true / false (1 / 0, yes / no, on / off)")


def _wisp_block_mode(layers: _Layers):
    """``"fused"`` or ``"separate"`` (``-lc_wisp_blocks``, default fused) when the
    preconditioner is the per-wisp block Jacobi; None for another ``-pc_type`` or when
    ``-pc_bjacobi_blocks`` / ``-pc_bjacobi_local_blocks`` set the blocks instead."""
    mode = layers.lookup("lc_wisp_blocks") or WISP_BLOCK_MODES[0]
    if mode not in WISP_BLOCK_MODES:
        raise ConfigError(f"-lc_wisp_blocks {mode!r}: use fused (one factorisation of all the "
                          f"rank's wisps, the default) or separate (one PETSc block per wisp)")
    pc = (layers.lookup("pc_type") or DEFAULTS["pc_type"]).lower()
    if pc != "bjacobi" or layers.lookup("pc_bjacobi_blocks") or layers.lookup("pc_bjacobi_local_blocks"):
        return None
    return mode


def _contact_pc(layers: _Layers, mat_type, wisp_blocks):
    """What the preconditioner of a run with strand contact is built from.

    ``-lc_contact_pc coupled|strands|clusters``: the whole Newton matrix A + C, the
    strand matrix A without the contact couplings between wisps, or exact blocks of the
    groups of wisps coupled by contact (lc_petsc/contact_pc.py).  Default: ``clusters``
    for the default block Jacobi on BAIJ with fused per-wisp blocks (measured on the
    demo hairball, 90 frames, 2 ranks: CG 44.4 -> 10.5 per solve, solve 33.8 -> 15.7 s;
    on the 2K hairball 86 -> 29 CG per frame; where contact is too dense for clusters it
    falls back to the per-wisp blocks, docs/contact_solver.md), ``strands`` for other
    block Jacobi set-ups (one exact block per wisp; an ILU(0) of the coupled rank block
    was measured to be indefinite, DIVERGED_INDEFINITE_PC, on the 2,000-wisp hairball),
    ``coupled`` for every other preconditioner (a direct solver then solves the Newton
    system exactly, AMG sees the whole matrix)."""
    bjacobi = (layers.lookup("pc_type") or DEFAULTS["pc_type"]).lower() == "bjacobi"
    if bjacobi:
        default = "clusters" if base_type(mat_type) == "baij" and wisp_blocks == "fused" else "strands"
    else:
        default = "coupled"
    mode = layers.lookup("lc_contact_pc") or default
    if mode not in CONTACT_PC_MODES:
        raise ConfigError(f"-lc_contact_pc {mode!r}: use coupled (precondition with the "
                          f"whole Newton matrix, contact couplings included), strands (the "
                          f"strand matrix alone) or clusters (exact blocks of wisps coupled "
                          f"by contact, lc_petsc/contact_pc.py)")
    if mode in ("strands", "clusters") and (layers.lookup("ksp_type") or "").lower() == "preonly":
        raise ConfigError(f"strand_collision with -lc_contact_pc {mode}: the preconditioner "
                          f"leaves out contact couplings, so -ksp_type preonly would not "
                          f"solve the Newton system; use a Krylov method (e.g. -ksp_type cg) or "
                          f"-lc_contact_pc coupled")
    if mode == "clusters" and not bjacobi:
        raise ConfigError(f"-lc_contact_pc clusters grows the per-wisp blocks of block Jacobi "
                          f"into clusters of wisps; it cannot be combined with -pc_type "
                          f"{layers.lookup('pc_type')}: drop -pc_type or use -pc_type bjacobi")
    return mode


def _positive_int(layers: _Layers, key, default):
    value = layers.lookup(key)
    if value is None:
        return default
    try:
        n = int(value)
    except ValueError:
        n = 0
    if n < 1 or str(n) != value.strip():
        raise ConfigError(f"-{key} {value!r}: use a whole number >= 1")
    return n


def _cluster_caps(layers: _Layers, mat_type, wisp_blocks):
    """(max wisps, max cross blocks, min captured share, LU ordering, span, band factor) of
    the clusters of ``-lc_contact_pc clusters``, after checking that the cluster preconditioner can run
    with the other options."""
    if base_type(mat_type) != "baij":
        raise ConfigError(f"-lc_contact_pc clusters reads the block (BAIJ) matrices; drop "
                          f"-mat_type {mat_type} (or use -mat_type baij)")
    if wisp_blocks != "fused":
        raise ConfigError("-lc_contact_pc clusters sets the block Jacobi blocks itself (the "
                          "per-wisp blocks fused, grown into clusters); drop "
                          "-pc_bjacobi_blocks / -pc_bjacobi_local_blocks / -lc_wisp_blocks separate")
    share = layers.lookup("lc_cluster_min_captured")
    try:
        captured = MIN_CAPTURED if share is None else float(share)
    except ValueError:
        captured = -1.0
    if not 0.0 <= captured <= 1.0:
        raise ConfigError(f"-lc_cluster_min_captured {share!r}: use a number from 0 (always "
                          f"cluster) to 1 (cluster only when every coupling fits)")
    return (_positive_int(layers, "lc_cluster_max_wisps", MAX_WISPS),
            _positive_int(layers, "lc_cluster_max_blocks", MAX_BLOCKS), captured,
            _choice(layers, "lc_cluster_ordering", ORDERINGS,
                    f"one of {', '.join(ORDERINGS)} (the PETSc ordering of the clusters' LU)"),
            _choice(layers, "lc_cluster_span", SPANS,
                    "global (clusters may hold wisps of several ranks) or rank (only "
                    "couplings inside one rank)"),
            _choice(layers, "lc_band_factor", BAND_FACTORS,
                    "cholesky (the compiled block Cholesky of each wisp's band) or ilu "
                    "(PETSc's ILU(0) of the band)"))
