"""Compiled (Numba) element kernels fused with the assembly, and the edge-length pass of
the Newton update.

The same energies, gradients and filtered Hessians as :mod:`stretch`, :mod:`bend` and
:mod:`twist` (which stay the tested reference; ``tests/test_elements_compiled.py`` checks
these against them to round-off), evaluated element by element and written straight into
the matrix's block-CSR value array (:class:`BlockLayout`; PETSc's own SeqBAIJ array in
:class:`lc_petsc.assembly.Assembler`): no Hessian array of the whole term,
only scratch arrays for one batch of bend or twist elements.  Still plain Python,
compiled by Numba on first use and cached on disk (``cache=True``, one directory per
version of this package's element sources: :func:`kernel_cache_dir`; see
docs/performance.md).

Implemented: the filters in :data:`FILTERS`; any other filter is evaluated by the NumPy
kernels (the assembler dispatches).  No PETSc, no MPI.

Layout (shared with the assembler):

* ``terms``: name -> (``start``, ``rest``, ``stiffness``) from :func:`element_arrays`:
  ``start`` (n,) int64 first vertex of each element (its vertices are
  ``start + 0..k-1``, nondecreasing), ``rest``, ``stiffness`` (n,) float64, validated
  once;
* ``x`` (nv, 3) local positions; ``g`` (nv, 3) vertex gradient, added to;
* ``values`` flat, with a :class:`BlockLayout`: entry (r, c) of block (i, i + d) at
  ``values[base[i, d + b] + r + 3 c]`` (column-major blocks, each block row's blocks
  contiguous), set (zeroed and summed in the same pass); with ``upper`` only d >= 0 is
  written (SBAIJ);
* ``band`` (nv, 3, 3 (2 b + 1)) (:func:`add_gradient_hessian`, for the tests):
  ``band[i, r, 3 (d + b) + c]`` is entry (3 i + r, 3 (i + d) + c) of the matrix.

All terms are evaluated in one pass over the vertices (:func:`_terms`): stretch
element by element (``_v_stretch``, inlined); bend and twist in batches of
:data:`BATCH` elements (:func:`_bend_batch`, :func:`_twist_batch`: loops over the batch
in structure-of-arrays form, which the compiler vectorises, 8 elements per AVX-512
instruction), whose gradients and upper blocks are then added element by element in the
pass's order (:func:`_v_put`): the same values as element by element, bit for bit
(strict IEEE arithmetic in each vector lane).  A row's blocks below the diagonal are
copied from the transposed upper ones once the row is complete (:func:`_vcopy_lower`),
and the mass term, if given, added to its diagonal then.  The loops vectorise only
without calls and branches: angles come from an atan2 in arithmetic (:func:`_vatan2`,
within 2 ulps of libm's), square roots from LLVM's intrinsic (:func:`_sqrt`), flags
from ``|`` and ``&``, alternatives from selects (:func:`_vselect`).  A non-finite
position or a zero-length edge (the rule of :func:`common.edge_lengths`) stops the pass;
the NumPy kernel of that term is then run to raise its documented
:class:`~lc_petsc.elements.common.ElementError`.
"""

from __future__ import annotations

import hashlib
import math
import os
import time
from pathlib import Path

import numpy as np

from lc_petsc.elements import bend, stretch, twist
from lc_petsc.elements.angle import STRAIGHT_TOL
from lc_petsc.elements.common import (_ZERO_EDGE_ULPS, check_finite, check_per_element)

try:
    import numba
    from llvmlite import ir as llvm_ir
    from numba.extending import intrinsic
except ImportError:                 # pragma: no cover - numba is a dependency
    numba = None                    # type: ignore[assignment]


def kernel_cache_dir(sources=None):
    """Numba's on-disk cache of this package's kernels: one directory per version of
    the sources of ``lc_petsc/elements`` (a hash of its modules; ``sources``: another
    folder, for the tests), under ``NUMBA_CACHE_DIR`` if set, else that folder's
    ``__pycache__``.  Numba keys a cached function on its own file only, while the
    helpers and constants it inlines come from the other modules here: without the
    version a change there (a code update) would keep running the stale machine code."""
    here = Path(sources or Path(__file__).resolve().parent)
    digest = hashlib.sha1()
    for path in sorted(here.glob("*.py")):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    base = os.environ.get("NUMBA_CACHE_DIR") or str(here / "__pycache__")
    return os.path.join(base, f"kernels-{digest.hexdigest()[:16]}")


if numba is not None:
    # read when a kernel is decorated (its cache locator is chosen then)
    numba.config.CACHE_DIR = kernel_cache_dir()  # type: ignore[attr-defined]

#: Filters the compiled kernels implement (others fall back to NumPy).
FILTERS = ("analytic", "none")

#: What each kernel computes: the energy only, the gradient, gradient + Hessian.
ENERGY, GRADIENT, HESSIAN = 0, 1, 2

_EDGE_TOL = _ZERO_EDGE_ULPS * np.finfo(np.float64).eps
_TWIST_TOL = twist.DEGENERATE_TOL
_SQRT_HALF = math.sqrt(0.5)
_PI = math.pi
_TWO_PI = 2.0 * math.pi


def available():
    """Whether Numba is importable (it is a dependency of lc_petsc)."""
    return numba is not None


def check_term(name, rest, stiffness):
    """The rest values and stiffnesses of a term, validated as the NumPy kernels do."""
    n = len(rest)
    if name == "stretch":
        rest = check_per_element(rest, n, name, "rest length", positive=True)
    else:
        rest = check_finite(rest, n, name, "rest angle")
    stiffness = check_per_element(stiffness, n, name, "stiffness")
    # copies: the checks return read-only broadcasts, a different Numba type
    return np.array(rest, np.float64), np.array(stiffness, np.float64)


def _jit(fn):
    """Numba-compile ``fn``, cached on disk; helpers (``_v*``) are inlined.  Strict IEEE
    arithmetic (no fastmath): the NaN checks stay valid, and near degenerate geometry
    (sin theta ~ 1e-6) the results stay within round-off of the NumPy kernels, which
    FMA contraction would not (measured: 1e-10 relative, for no measurable speed-up)."""
    if numba is None:               # pragma: no cover
        return fn
    options = dict(cache=True, error_model="numpy")
    if fn.__name__.startswith("_v"):
        options["inline"] = "always"
    return numba.njit(**options)(fn)


if numba is not None:
    @intrinsic
    def _sqrt(typingctx, x):
        """sqrt(x) as LLVM's intrinsic: IEEE's correctly rounded square root, the bits of
        libm's, NaN below 0.  Numba's ``math.sqrt`` calls libm's ``sqrt``, which may set
        errno: a loop with one whose argument the compiler cannot prove >= 0 is not
        vectorised (LLVM's remark: "call instruction cannot be vectorized")."""
        def codegen(context, builder, signature, args):
            value = context.cast(builder, args[0], signature.args[0], numba.float64)
            fn = builder.module.declare_intrinsic("llvm.sqrt", [llvm_ir.DoubleType()])
            return builder.call(fn, [value])
        return numba.float64(x), codegen
else:                               # pragma: no cover
    _sqrt = math.sqrt


# ---------------------------------------------------------------- 3-vectors as tuples
@_jit
def _vsub(u, v):
    return (u[0] - v[0], u[1] - v[1], u[2] - v[2])


@_jit
def _vadd(u, v):
    return (u[0] + v[0], u[1] + v[1], u[2] + v[2])


@_jit
def _vscale(u, s):
    return (u[0] * s, u[1] * s, u[2] * s)


@_jit
def _vdiv(u, s):
    return (u[0] / s, u[1] / s, u[2] / s)


@_jit
def _vdot(u, v):
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


@_jit
def _vcross(u, v):
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


@_jit
def _vnorm(u):
    return _sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])


#: Cephes' atan(t) = t + t z P(z) / Q(z), z = t^2, |t| <= 0.66 (Q monic)
_ATAN_P = (-8.750608600031904122785e-1, -1.615753718733365076637e1, -7.500855792314704667340e1,
           -1.228866684490136173410e2, -6.485021904942025371773e1)
_ATAN_Q = (2.485846490142306297962e1, 1.650270098316988542046e2, 4.328810604912902668951e2,
           4.853903996359136964868e2, 1.945506571482613964425e2)
#: pi / 2, 3 pi / 4 and pi minus their float64 values: the bits those constants miss
_PIO2_LO = 6.123233995736766e-17
_3PIO4_LO = 9.184850993605148e-17
_PI_LO = 1.2246467991473532e-16
_TAN_3PI_8 = 2.41421356237309504880


@_jit
def _vatan2(y, x):
    """atan2(y, x) within 2 ulps of libm's (signed zeros, the axes, pi and NaN as libm)
    while |x| + |y| does not overflow (the kernels pass a cosine and a sine), in
    arithmetic and selects only, so a loop of them vectorises (libm's is a call: ~20 ns
    per element, the largest scalar piece of the bend and twist batches).  Cephes' atan
    with Cephes' reduction: |y| / |x| (or its inverse) as is up to 0.66, else through
    (r - 1) / (r + 1) or -1 / r; the quadrant folded into the reduction (x < 0 or -0:
    pi - atan(|y| / |x|)).  Between ratios 0.41 and 0.66 (the polynomial used beyond
    tan(pi / 8)) a few results in 10^5 are 2 ulps from libm's (a reviewer's scan: at most
    1.62 ulps from the exact value); elsewhere within 1."""
    ax, ay = abs(x), abs(y)
    neg = math.copysign(1.0, x) < 0.0
    high = ay > _TAN_3PI_8 * ax         # pi/2 -+ atan(|x| / |y|)
    mid = ay > 0.66 * ax                # pi/4 + atan((|y| - |x|) / (|y| + |x|)), or 3 pi/4 - it
    sx = -1.0 if neg else 1.0
    num = sx * -ax if high else (sx * (ay - ax) if mid else sx * ay)
    den = ay if high else (ay + ax if mid else ax)
    base = (0.5 * _PI if high else ((0.75 * _PI if neg else 0.25 * _PI) if mid
                                    else (_PI if neg else 0.0)))
    low = (_PIO2_LO if high else ((_3PIO4_LO if neg else 0.5 * _PIO2_LO) if mid
                                  else (_PI_LO if neg else 0.0)))
    t = num / den if ay != 0.0 else (0.0 if ax == ax else ax)    # atan2(0, NaN) is NaN
    z = t * t
    p = (((_ATAN_P[0] * z + _ATAN_P[1]) * z + _ATAN_P[2]) * z + _ATAN_P[3]) * z + _ATAN_P[4]
    q = ((((z + _ATAN_Q[0]) * z + _ATAN_Q[1]) * z + _ATAN_Q[2]) * z + _ATAN_Q[3]) * z + _ATAN_Q[4]
    return math.copysign(base + ((t * (z * p / q) + t) + low), y)


@_jit
def _vselect(cond, u, v):
    """u if cond else v, per component: a select, not a branch (the batch loops
    vectorise only without branches)."""
    return (u[0] if cond else v[0], u[1] if cond else v[1], u[2] if cond else v[2])


@_jit
def _vperp(v):
    """Unit vector perpendicular to v (as :func:`angle.any_perpendicular`)."""
    a0, a1, a2 = abs(v[0]), abs(v[1]), abs(v[2])
    # v x e0 where |v0| is smallest, else v x e1 where |v1| <= |v2|, else v x e2
    p = _vselect((a0 <= a1) & (a0 <= a2), (0.0, v[2], -v[1]),
                 _vselect(a1 <= a2, (-v[2], 0.0, v[0]), (v[1], -v[0], 0.0)))
    return _vdiv(p, _vnorm(p))


@_jit
def _vframe(u, lu, v, lv):
    """The angle frame of u, v (lengths lu, lv), as angle.AngleFrame: unit t0, t1,
    t0 x t1, cos and sin."""
    t0 = _vdiv(u, lu)
    t1 = _vdiv(v, lv)
    tx = _vcross(t0, t1)
    return t0, t1, tx, _vdot(t0, t1), _vnorm(tx)


@_jit
def _vpoint(x, i):
    return (x[i, 0], x[i, 1], x[i, 2])


@_jit
def _vadd_to(g, i, u):
    g[i, 0] += u[0]
    g[i, 1] += u[1]
    g[i, 2] += u[2]


@_jit
def _vput(vals, o, r, c, h):
    """Add h to entry (r, c) of the column-major block at offset o (BlockLayout:
    base[i, d + b], a stored block: o >= 0; the index is unsigned, no wrap-around
    test).  The kernels read the offsets of an element's blocks into locals first: a
    store into ``vals`` may alias ``base`` for the compiler."""
    vals[np.uint64(o + r + 3 * c)] += h


@_jit
def _vzero_row(vals, base, i, first):
    """Zero the stored blocks (i, i + d), d >= first - b, of block row i
    (BlockLayout.block_csr: one contiguous run)."""
    lo, hi = -1, -1
    for dd in range(first, base.shape[1]):
        o = base[i, dd]
        if o >= 0:
            hi = o + 9
            if lo < 0:
                lo = o
    if lo >= 0:
        vals[lo:hi] = 0.0


@_jit
def _vcopy_lower(vals, base, b, i):
    """Set the stored blocks (i + d, i), d = 1 .. b, to the transposes of blocks
    (i, i + d), complete once the elements starting at i are in (later ones do not touch
    row i): one store per entry instead of an add per element, and the same values bit
    for bit (each lower entry was the same sum, in the same order, as its upper one);
    zero where the upper block is not stored."""
    for d in range(1, b + 1):
        if i + d >= base.shape[0]:
            return
        lo = base[i + d, b - d]
        if lo < 0:
            continue
        up = base[i, b + d]
        for q in range(3):
            for r in range(3):
                vals[np.uint64(lo + r + 3 * q)] = vals[np.uint64(up + q + 3 * r)] if up >= 0 else 0.0


@_jit
def _visfinite(a):
    """math.isfinite(a) as a comparison (NaN and +-inf fail it).  The flags of the batch
    loops use these and ``|``, ``&`` instead of ``and``, ``or``: the short-circuit
    branches kept those loops from vectorising (measured at 2,000 wisps: the twist
    batches' energy pass 9.8 ms with them, 3.0 ms without)."""
    return abs(a) < math.inf


@_jit
def _vbad_edge(e, scale):
    """Zero-length edge at the round-off level of the coordinates (common.edge_lengths)."""
    length = _vnorm(e)
    return length, (length <= _EDGE_TOL * scale) | (length == 0.0)


@_jit
def _vscale_add(u, scale, total):
    """(scale, total) updated by the coordinates of u: the largest |coordinate| and the
    sum of the |coordinates| (in order)."""
    for a in (abs(u[0]), abs(u[1]), abs(u[2])):
        total += a
        scale = a if a > scale else scale
    return scale, total


@_jit
def _vscale_of(x, i0, k):
    """(largest |coordinate| of vertices i0..i0+k-1, whether all are finite)."""
    scale = total = 0.0
    for i in range(i0, i0 + k):
        scale, total = _vscale_add(_vpoint(x, i), scale, total)
    return scale, math.isfinite(total)


# ------------------------------------------------------------- batches of elements
#: Elements per batch of :func:`_bend_batch` and :func:`_twist_batch`: their loops over
#: the batch run in structure-of-arrays form, which the compiler vectorises.
BATCH = 64
#: Row stride of the batch scratch arrays: not a power of two (rows would share cache sets).
_STRIDE = BATCH + 8
#: The flag of a bad element (non-finite, zero-length edge): the pass stops there.
_BAD = 1.0
#: Rows 0 .. 10 of the bend and twist batch scratch: the angle frame (:func:`_vput_frame`).
_F_C, _F_S, _F_T0, _F_T1, _F_TX = 0, 1, 2, 5, 8


@_jit
def _vput_at(tw, r, j, h):
    """Row r of batch element j (a flat scratch array: entry r * _STRIDE + j) = h: one
    array with constant row offsets, so the compiler sees that rows do not overlap.  The
    index is unsigned: no test for a negative (wrap-around) index, which would make the
    compiler gather and scatter."""
    tw[np.uint64(r * _STRIDE + j)] = h


@_jit
def _vat(tw, r, j):
    """Row r of batch element j (:func:`_vput_at`)."""
    return tw[np.uint64(r * _STRIDE + j)]


@_jit
def _vrow3(tw, r, j):
    """Rows r .. r + 2 of batch element j."""
    return (_vat(tw, r, j), _vat(tw, r + 1, j), _vat(tw, r + 2, j))


@_jit
def _vput_row3(tw, r, j, u):
    _vput_at(tw, r, j, u[0])
    _vput_at(tw, r + 1, j, u[1])
    _vput_at(tw, r + 2, j, u[2])


@_jit
def _vput_frame(tw, j, t0, t1, tx, c, s):
    """Rows _F_* of batch element j = its angle frame (:func:`_vframe`)."""
    _vput_at(tw, _F_C, j, c)
    _vput_at(tw, _F_S, j, s)
    _vput_row3(tw, _F_T0, j, t0)
    _vput_row3(tw, _F_T1, j, t1)
    _vput_row3(tw, _F_TX, j, tx)


@_jit
def _v_gather(x, start, lo, m, tw, row, k):
    """Rows row .. row + 3 k - 1 of batch elements 0 .. m - 1 = the positions of their k
    vertices (element lo + j's first vertex: start[lo + j]); an indexed loop, not
    vectorised: the loops over the batch read these rows."""
    for j in range(m):
        i = start[lo + j]
        for a in range(k):
            _vput_row3(tw, row + 3 * a, j, _vpoint(x, i + a))


@_jit
def _v_put(g, vals, base, b, mode, i, j, tw, g_row, hh, k):
    """Add batch element j on vertices i .. i + k - 1 to the gradient g (its rows g_row
    .. g_row + 3 k - 1 of tw: vertex a, coordinate q in row g_row + 3 a + q) and,
    HESSIAN, its blocks to ``vals``: hh holds its upper blocks (a, c), a <= c, in
    order, block n's entry (r, q) in row 9 n + r + 3 q (the lower blocks, their
    transposes, are copied once a row is complete: :func:`_vcopy_lower`)."""
    for a in range(k):
        for q in range(3):
            g[i + a, q] += _vat(tw, g_row + 3 * a + q, j)
    if mode != HESSIAN:
        return
    blk = 0
    for a in range(k):
        for cc in range(a, k):
            o = base[i + a, cc - a + b]
            for t in range(9):
                vals[np.uint64(o + t)] += _vat(hh, 9 * blk + t, j)
            blk += 1


# ---------------------------------------------------------------------- stretch
@_jit
def _v_stretch(x, i, Lbar, k, mode, g, vals, base, b, exact):
    """One stretch element on vertices i, i+1: (energy, bad); ``exact``: the exact
    Hessian (filter "none"), else the analytic filter."""
    scale, finite = _vscale_of(x, i, 2)
    ev = _vsub(_vpoint(x, i + 1), _vpoint(x, i))
    L, zero = _vbad_edge(ev, scale)
    if not finite or zero:
        return 0.0, True
    if mode == ENERGY:
        return 0.5 * k * (L - Lbar) ** 2, False
    ge = _vscale(ev, k * (L - Lbar) / L)
    _vadd_to(g, i, _vscale(ge, -1.0))
    _vadd_to(g, i + 1, ge)
    if mode != HESSIAN:
        return 0.0, False
    o00, o11, o01 = base[i, b], base[i + 1, b], base[i, b + 1]
    eh = _vdiv(ev, L)
    perp = k * (1.0 - Lbar / L)
    if not exact:
        perp = max(perp, 0.0)
    kp = k - perp
    for c in range(3):              # column-major blocks: r runs along memory
        for r in range(3):
            h = kp * (eh[r] * eh[c])
            if r == c:
                h += perp
            _vput(vals, o00, r, c, h)
            _vput(vals, o11, r, c, h)
            _vput(vals, o01, r, c, -h)
    return 0.0, False


# ------------------------------------------------------------------------- bend
@_jit
def _vstore(a, j, vec, f):
    a[j, 0] = vec[0] * f
    a[j, 1] = vec[1] * f
    a[j, 2] = vec[2] * f


@_jit
def _v_eigenpairs(u, v, w, t0, t1, b0, b1, n, c, s, s_safe, d, k, fu, fv, first):
    """The eigenpairs ``first`` .. 5 of the unit-column Hessian of Psi(theta)
    (angle.AngleFrame.eigensystem, away from its degenerate points) into rows 0.. of
    u, v (times fu, fv: the column scaling) and w (their eigenvalues)."""
    if c > 0.0:
        one_plus, one_minus = 1.0 + c, s * s / (1.0 + c)
    elif c < 0.0:
        one_plus, one_minus = s * s / (1.0 - c), 1.0 - c
    else:
        one_plus, one_minus = 1.0, 1.0
    lam2 = k + _sqrt(k * k + d * d)
    rr = d / lam2 if lam2 > 0.0 else 0.0
    scn = 1.0 / _sqrt(2.0 * (1.0 + rr * rr))
    lams = (-d * one_minus / s_safe, d * one_plus / s_safe, lam2, -d * rr, -d, d)
    for j in range(first, 6):
        if j == 0:
            top, bot, f = n, n, _SQRT_HALF
        elif j == 1:
            top, bot, f = n, _vscale(n, -1.0), _SQRT_HALF
        elif j == 2:
            top, bot, f = _vsub(_vscale(t0, rr), b0), _vadd(_vscale(t1, rr), b1), scn
        elif j == 3:
            top, bot, f = _vadd(t0, _vscale(b0, rr)), _vsub(t1, _vscale(b1, rr)), scn
        elif j == 4:
            top, bot, f = _vadd(t0, b0), _vsub(b1, t1), 0.5
        else:
            top, bot, f = _vsub(t0, b0), _vsub(_vscale(t1, -1.0), b1), 0.5
        _vstore(u, j - first, _vscale(top, f), fu)
        _vstore(v, j - first, _vscale(bot, f), fv)
        w[j - first] = lams[j]


# Rows of the bend batch scratch (:func:`_bend_batch`): the element's angle frame (rows
# _F_*), edge lengths, d = k (theta - rest), energy, flag (0, _BAD), its three vertices
# (9 rows from _B_X), its gradient on them (9 from _B_G), its column weights (6 from
# _B_W) and Hessian columns [u; -u - v; v] (column c: u in rows _B_U + 6 c .. + 2, v in
# the next three); ``hb`` (54 rows): its six upper 3x3 blocks (:func:`_v_put`).
_B_L0, _B_L1, _B_D, _B_EN, _B_FLAG = 11, 12, 13, 14, 15
_B_X, _B_G, _B_W, _B_U = 16, 25, 34, 40
_B_ROWS = _B_U + 36


@_jit
def _v_bend_frame(tb, j):
    """Bend batch element j's unit t0, t1, normal n (any perpendicular to t0 where the
    bend is straight), b0 = t0 x n, b1 = t1 x n, sin theta (1 where straight) and
    whether it is straight (sin theta < STRAIGHT_TOL)."""
    t0, t1 = _vrow3(tb, _F_T0, j), _vrow3(tb, _F_T1, j)
    s = _vat(tb, _F_S, j)
    degenerate = s < STRAIGHT_TOL
    n = _vselect(degenerate, _vperp(t0), _vdiv(_vrow3(tb, _F_TX, j), s))
    s_safe = 1.0 if degenerate else s
    return t0, t1, n, _vcross(t0, n), _vcross(t1, n), s_safe, degenerate


@_jit
def _v_bend_exact(u, v, w, t0, t1, n, b0, b1, c, s, s_safe, d, k, l0, l1, degenerate):
    """All six eigenpairs of a bend's Hessian (angle.AngleFrame.eigensystem; the cone
    rule where it is straight) into u, v (6, 3) (scaled by 1 / |e|) and w (6,)."""
    if degenerate:
        # the cone rule (angle.AngleFrame._cone_eigensystem)
        cs = 1.0 if c > 0.0 else (-1.0 if c < 0.0 else 0.0)
        zero3 = (0.0, 0.0, 0.0)
        _vstore(u, 0, _vscale(n, _SQRT_HALF), 1.0 / l0)
        _vstore(v, 0, _vscale(n, -cs * _SQRT_HALF), 1.0 / l1)
        _vstore(u, 1, _vscale(b0, _SQRT_HALF), 1.0 / l0)
        _vstore(v, 1, _vscale(b0, -cs * _SQRT_HALF), 1.0 / l1)
        _vstore(u, 2, _vscale(n, _SQRT_HALF), 1.0 / l0)
        _vstore(v, 2, _vscale(n, cs * _SQRT_HALF), 1.0 / l1)
        _vstore(u, 3, _vscale(b0, _SQRT_HALF), 1.0 / l0)
        _vstore(v, 3, _vscale(b0, cs * _SQRT_HALF), 1.0 / l1)
        _vstore(u, 4, t0, 1.0 / l0)
        _vstore(v, 4, zero3, 1.0 / l1)
        _vstore(u, 5, zero3, 1.0 / l0)
        _vstore(v, 5, t0, 1.0 / l1)
        w[0] = w[1] = 2.0 * k
        w[2] = w[3] = w[4] = w[5] = 0.0
    else:
        _v_eigenpairs(u, v, w, t0, t1, b0, b1, n, c, s, s_safe, d, k, 1.0 / l0, 1.0 / l1, 0)


@_jit
def _v_bend_analytic(t0, t1, n, b0, b1, c, s, s_safe, d, k, l0, l1, degenerate):
    """The analytic filter's three kept eigenpairs of a bend (angle.AngleFrame.positive_part;
    the cone rule where it is straight), times the square roots of their eigenvalues,
    on the unit edges [top; bottom], / |e|: (u0, v0, u1, v1, u2, v2)."""
    if degenerate:
        cs = 1.0 if c > 0.0 else (-1.0 if c < 0.0 else 0.0)
        r0 = _sqrt(2.0 * k)
        return (_vscale(_vscale(n, _SQRT_HALF), r0 / l0), _vscale(_vscale(n, -cs * _SQRT_HALF), r0 / l1),
                _vscale(_vscale(b0, _SQRT_HALF), r0 / l0), _vscale(_vscale(b0, -cs * _SQRT_HALF), r0 / l1),
                _vscale(n, 0.0), _vscale(n, 0.0))
    sd = 1.0 if d >= 0.0 else -1.0
    ad = abs(d)
    lam2 = k + _sqrt(k * k + d * d)
    rr = d / lam2 if lam2 > 0.0 else 0.0
    sc = sd * c
    one_plus = s * s / (1.0 + abs(sc)) if sc < 0.0 else 1.0 + sc
    scn = 1.0 / _sqrt(2.0 * (1.0 + rr * rr))
    rs = rr * scn
    hsd = 0.5 * sd
    root0, root1, root2 = _sqrt(lam2), _sqrt(ad * one_plus / s_safe), _sqrt(ad)
    return (_vscale(_vsub(_vscale(t0, rs), _vscale(b0, scn)), root0 / l0),
            _vscale(_vadd(_vscale(t1, rs), _vscale(b1, scn)), root0 / l1),
            _vscale(_vscale(n, _SQRT_HALF), root1 / l0),
            _vscale(_vscale(n, -_SQRT_HALF * sd), root1 / l1),
            _vscale(_vsub(_vscale(t0, 0.5), _vscale(b0, hsd)), root2 / l0),
            _vscale(_vadd(_vscale(t1, -0.5), _vscale(b1, -hsd)), root2 / l1))


@_jit
def _v_bend_blocks(hb, j, r, q, uu, uv, vu, vv):
    """Entry (r, q) of bend element j's six upper blocks from the products
    uu = sum_c w_c u_c[r] u_c[q], uv, vu, vv (H = sum_c w_c c_c c_c^T, c_c = [u_c;
    -u_c - v_c; v_c])."""
    t = r + 3 * q
    _vput_at(hb, t, j, uu)
    _vput_at(hb, 9 + t, j, -uu - uv)
    _vput_at(hb, 18 + t, j, uv)
    _vput_at(hb, 27 + t, j, uu + uv + vu + vv)
    _vput_at(hb, 36 + t, j, -uv - vv)
    _vput_at(hb, 45 + t, j, vv)


@_jit
def _bend_batch(x, start, rest, stiff, lo, hi, mode, exact, tb, hb, u, v, w):
    """Bend elements lo .. hi - 1 (at most BATCH), element lo + j in column j of the
    flat scratch ``tb`` (_B_ROWS * _STRIDE,) (rows _B_*: :func:`_vput_at`): its flag
    and energy; with GRADIENT its gradient (rows _B_G; zero where it is straight); with
    HESSIAN its six upper blocks in ``hb`` (54 * _STRIDE,) (:func:`_v_put`), from its
    columns (analytic: three, weights 1; ``exact``: six with their eigenvalues).  u, v
    (6, 3), w (6,): scratch for the exact filter.  The loops over the batch are
    branch-free (selects), so the compiler vectorises them, except the gather and the
    exact filter's."""
    m = hi - lo
    _v_gather(x, start, lo, m, tb, _B_X, 3)
    for j in range(m):
        x0, x1, x2 = _vrow3(tb, _B_X, j), _vrow3(tb, _B_X + 3, j), _vrow3(tb, _B_X + 6, j)
        scale, total = _vscale_add(x0, 0.0, 0.0)
        scale, total = _vscale_add(x1, scale, total)
        scale, total = _vscale_add(x2, scale, total)
        e0 = _vsub(x0, x1)
        e1 = _vsub(x2, x1)
        l0, zero0 = _vbad_edge(e0, scale)
        l1, zero1 = _vbad_edge(e1, scale)
        bad = (not _visfinite(total)) | zero0 | zero1
        t0, t1, tx, c, s = _vframe(e0, l0, e1, l1)
        _vput_at(tb, _B_FLAG, j, _BAD if bad else 0.0)
        _vput_at(tb, _B_L0, j, l0)
        _vput_at(tb, _B_L1, j, l1)
        _vput_frame(tb, j, t0, t1, tx, c, s)
    for j in range(m):
        theta = _vatan2(_vat(tb, _F_S, j), _vat(tb, _F_C, j))
        k = stiff[lo + j]
        _vput_at(tb, _B_EN, j, 0.5 * k * (theta - rest[lo + j]) ** 2)
        _vput_at(tb, _B_D, j, k * (theta - rest[lo + j]))
    if mode == ENERGY:
        return
    for j in range(m):
        t0, t1, n, b0, b1, s_safe, degenerate = _v_bend_frame(tb, j)
        d = _vat(tb, _B_D, j)
        gu = _vscale(_vdiv(b0, _vat(tb, _B_L0, j)), d)
        gv = _vscale(_vdiv(b1, -_vat(tb, _B_L1, j)), d)
        if degenerate:
            gu = gv = (0.0, 0.0, 0.0)
        _vput_row3(tb, _B_G, j, gu)
        _vput_row3(tb, _B_G + 3, j, (-gu[0] - gv[0], -gu[1] - gv[1], -gu[2] - gv[2]))
        _vput_row3(tb, _B_G + 6, j, gv)
    if mode != HESSIAN:
        return
    if exact:
        for j in range(m):
            t0, t1, n, b0, b1, s_safe, degenerate = _v_bend_frame(tb, j)
            _v_bend_exact(u, v, w, t0, t1, n, b0, b1, _vat(tb, _F_C, j), _vat(tb, _F_S, j),
                          s_safe, _vat(tb, _B_D, j), stiff[lo + j], _vat(tb, _B_L0, j),
                          _vat(tb, _B_L1, j), degenerate)
            for c in range(6):
                _vput_row3(tb, _B_U + 6 * c, j, (u[c, 0], u[c, 1], u[c, 2]))
                _vput_row3(tb, _B_U + 6 * c + 3, j, (v[c, 0], v[c, 1], v[c, 2]))
                _vput_at(tb, _B_W + c, j, w[c])
        for r in range(3):
            for q in range(3):
                for j in range(m):
                    uu = uv = vu = vv = 0.0
                    for c in range(6):
                        wu = _vat(tb, _B_W + c, j) * _vat(tb, _B_U + 6 * c + r, j)
                        wv = _vat(tb, _B_W + c, j) * _vat(tb, _B_U + 6 * c + 3 + r, j)
                        uu += wu * _vat(tb, _B_U + 6 * c + q, j)
                        uv += wu * _vat(tb, _B_U + 6 * c + 3 + q, j)
                        vu += wv * _vat(tb, _B_U + 6 * c + q, j)
                        vv += wv * _vat(tb, _B_U + 6 * c + 3 + q, j)
                    _v_bend_blocks(hb, j, r, q, uu, uv, vu, vv)
        return
    for j in range(m):
        t0, t1, n, b0, b1, s_safe, degenerate = _v_bend_frame(tb, j)
        cols = _v_bend_analytic(t0, t1, n, b0, b1, _vat(tb, _F_C, j), _vat(tb, _F_S, j), s_safe,
                                _vat(tb, _B_D, j), stiff[lo + j], _vat(tb, _B_L0, j),
                                _vat(tb, _B_L1, j), degenerate)
        _vput_row3(tb, _B_U, j, cols[0])
        _vput_row3(tb, _B_U + 3, j, cols[1])
        _vput_row3(tb, _B_U + 6, j, cols[2])
        _vput_row3(tb, _B_U + 9, j, cols[3])
        _vput_row3(tb, _B_U + 12, j, cols[4])
        _vput_row3(tb, _B_U + 15, j, cols[5])
    for r in range(3):
        for q in range(3):
            for j in range(m):      # three columns, weights 1: unrolled
                u0, u1, u2 = _vat(tb, _B_U + r, j), _vat(tb, _B_U + 6 + r, j), _vat(tb, _B_U + 12 + r, j)
                v0, v1, v2 = _vat(tb, _B_U + 3 + r, j), _vat(tb, _B_U + 9 + r, j), _vat(tb, _B_U + 15 + r, j)
                p0, p1, p2 = _vat(tb, _B_U + q, j), _vat(tb, _B_U + 6 + q, j), _vat(tb, _B_U + 12 + q, j)
                s0, s1, s2 = _vat(tb, _B_U + 3 + q, j), _vat(tb, _B_U + 9 + q, j), _vat(tb, _B_U + 15 + q, j)
                _v_bend_blocks(hb, j, r, q, u0 * p0 + u1 * p1 + u2 * p2, u0 * s0 + u1 * s1 + u2 * s2,
                               v0 * p0 + v1 * p1 + v2 * p2, v0 * s0 + v1 * s1 + v2 * s2)


# ------------------------------------------------------------------------ twist
# Rows of the twist batch scratch (:func:`_twist_batch`): the angle frame of the
# element's projected outer edges (rows _F_*), its geometry (e1: three rows), its angle
# error dphi, energy and flag (0, _BAD, _T_DROPPED: collinear outer edge, dropped), its
# four vertices (12 rows from _T_X), its gradient on them (12 rows from _T_G), its
# column weights (8 from _T_W) and Hessian columns (column c entry q in row
# _T_COLS + 12 c + q); ``hh`` (90 rows): its ten upper 3x3 blocks (:func:`_v_put`).
_T_AL, _T_BE, _T_SIG, _T_IL1SQ, _T_LA, _T_LB, _T_DPHI, _T_EN = range(11, 19)
_T_E1, _T_FLAG = 19, 22
_T_X, _T_G, _T_W, _T_COLS = 23, 35, 47, 55
_T_ROWS = _T_COLS + 96
_T_DROPPED = 2.0


@_jit
def _v_in_plane(tw, c, j, top, bot, fu, fv, al, be):
    """Column c of twist element j's Hessian: P^T [top fu; bot fv]
    (twist.simplified_transpose), into the twist batch scratch tw."""
    uq = _vscale(top, fu)
    vq = _vscale(bot, fv)
    _v_column(tw, c, j, uq, _vadd(_vscale(uq, al - 1.0), _vscale(vq, be)),
              _vsub(_vscale(uq, -al), _vscale(vq, 1.0 + be)), vq)


@_jit
def _v_column(tw, c, j, p0, p1, p2, p3):
    """Column c of twist element j's Hessian, its parts on the four vertices p0 .. p3,
    into the twist batch scratch tw."""
    r = _T_COLS + 12 * c
    _vput_row3(tw, r, j, p0)
    _vput_row3(tw, r + 3, j, p1)
    _vput_row3(tw, r + 6, j, p2)
    _vput_row3(tw, r + 9, j, p3)


@_jit
def _v_balanced(tw, c, j, sign, pl, mg):
    """Column c of twist element j's Hessian: 1/2 ([0; pl; -pl; 0] + sign mg), mg the
    four parts of a balanced out-of-plane column."""
    _v_column(tw, c, j, _vscale(_vscale(mg[0], sign), 0.5),
              _vscale(_vadd(pl, _vscale(mg[1], sign)), 0.5),
              _vscale(_vadd(_vscale(pl, -1.0), _vscale(mg[2], sign)), 0.5),
              _vscale(_vscale(mg[3], sign), 0.5))


@_jit
def _v_out_of_plane(tw, j, p, plus, eps, t0, t1, b0, st0, e1h, al, be, c, d, osc, mu, inv_lb,
                    inv_l1):
    """Out-of-plane pair p (eps = +-1) of twist element j: the plus column into column
    plus + p, the minus column into column 6 + p of the twist batch scratch tw."""
    nu = eps * osc * inv_lb
    w = _vscale(_vadd(t0, _vscale(t1, eps)), osc * inv_l1)
    m0 = _vscale(e1h, 2.0 * mu)
    m1 = _vsub(_vscale(e1h, 2.0 * ((al - 1.0) * mu + be * nu)), w)
    m2 = _vadd(_vscale(e1h, -2.0 * (al * mu + (1.0 + be) * nu)), w)
    m3 = _vscale(e1h, 2.0 * nu)
    cs = (1.0 - c) if eps > 0.0 else (1.0 + c)
    lw = _vscale(_vsub(_vscale(b0, cs), _vscale(st0, eps)), d * osc * inv_l1)
    # gs = sqrt(|p| / |m|) from the squared norms: two square roots, one division
    sq_p = 2.0 * _vdot(lw, lw)
    sq_m = _vdot(m0, m0) + _vdot(m1, m1) + _vdot(m2, m2) + _vdot(m3, m3)
    ok = sq_p > 0.0 and sq_m > 0.0
    gs = _sqrt(_sqrt(sq_p / sq_m)) if ok else 0.0
    inv_gs = 1.0 / gs if ok else 0.0
    # 1/2 (lw inv_gs [0; 1; -1; 0] +- gs m), lw the nonzero parts of p
    pl = _vscale(lw, inv_gs)
    mg = (_vscale(m0, gs), _vscale(m1, gs), _vscale(m2, gs), _vscale(m3, gs))
    _v_balanced(tw, plus + p, j, 1.0, pl, mg)
    _v_balanced(tw, 6 + p, j, -1.0, pl, mg)


@_jit
def _v_twist_frame(tw, j, k):
    """The twist element j's unit t0, t1, normal n, binormals b0 = t0 x n, b1 = t1 x n,
    d = sigma k dphi, 1 / la and 1 / lb, from the batch scratch ``tw``."""
    t0 = _vrow3(tw, _F_T0, j)
    t1 = _vrow3(tw, _F_T1, j)
    s = _vat(tw, _F_S, j)
    sigma = _vat(tw, _T_SIG, j)
    # a, b parallel: the frame turns about e1; a select, not a branch (the compiler left
    # a reference count in the branch, which kept the loops calling this scalar)
    straight = s < STRAIGHT_TOL
    n_e1 = _vscale(_vrow3(tw, _T_E1, j), sigma * _sqrt(_vat(tw, _T_IL1SQ, j)))
    n_tx = _vdiv(_vrow3(tw, _F_TX, j), s)
    n = _vselect(straight, n_e1, n_tx)
    d = sigma * k * _vat(tw, _T_DPHI, j)
    return t0, t1, n, _vcross(t0, n), _vcross(t1, n), d, 1.0 / _vat(tw, _T_LA, j), 1.0 / _vat(tw, _T_LB, j)


@_jit
def _twist_batch(x, start, rest, stiff, lo, hi, mode, exact, tw, hh, u, v, w):
    """Twist elements lo .. hi - 1 (at most BATCH), element lo + j in column j of the
    flat scratch ``tw`` (_T_ROWS * _STRIDE,) (rows _T_*: :func:`_vput_at`): its flag
    and energy; with GRADIENT its gradient (rows _T_G); with HESSIAN its ten upper
    blocks in ``hh`` (90 * _STRIDE,) (:func:`_v_put`), from its columns and weights
    (analytic: four columns, weights 1; ``exact``: eight, twist._exact_columns).  u, v
    (6, 3), w (8,): scratch for the exact filter's eigenpairs.  The loops over the
    batch are branch-free (selects), so the compiler vectorises them, except the
    gather, the fallback of the angle's modulo and the exact filter's."""
    m = hi - lo
    _v_gather(x, start, lo, m, tw, _T_X, 4)
    for j in range(m):
        x0, x1 = _vrow3(tw, _T_X, j), _vrow3(tw, _T_X + 3, j)
        x2, x3 = _vrow3(tw, _T_X + 6, j), _vrow3(tw, _T_X + 9, j)
        scale, total = _vscale_add(x0, 0.0, 0.0)
        scale, total = _vscale_add(x1, scale, total)
        scale, total = _vscale_add(x2, scale, total)
        scale, total = _vscale_add(x3, scale, total)
        finite = _visfinite(total)
        e0 = _vsub(x0, x1)
        e1 = _vsub(x2, x1)
        e2 = _vsub(x3, x2)
        l0, zero0 = _vbad_edge(e0, scale)
        l1, zero1 = _vbad_edge(e1, scale)
        l2, zero2 = _vbad_edge(e2, scale)
        inv_l1_sq = 1.0 / (l1 * l1)
        al = _vdot(e0, e1) * inv_l1_sq
        be = _vdot(e2, e1) * inv_l1_sq
        av = _vsub(e0, _vscale(e1, al))
        bv = _vsub(e2, _vscale(e1, be))
        la, lb = _vnorm(av), _vnorm(bv)
        dropped = not ((la >= _TWIST_TOL * l0) & (lb >= _TWIST_TOL * l2))
        bad = (not finite) | zero0 | zero1 | zero2
        _vput_at(tw, _T_FLAG, j, _BAD if bad else (_T_DROPPED if dropped else 0.0))
        t0, t1, tx, c, s = _vframe(av, la, bv, lb)
        _vput_at(tw, _T_AL, j, al)
        _vput_at(tw, _T_BE, j, be)
        _vput_at(tw, _T_SIG, j, -1.0 if _vdot(_vcross(av, bv), e1) < 0.0 else 1.0)
        _vput_at(tw, _T_IL1SQ, j, inv_l1_sq)
        _vput_at(tw, _T_LA, j, la)
        _vput_at(tw, _T_LB, j, lb)
        _vput_frame(tw, j, t0, t1, tx, c, s)
        _vput_row3(tw, _T_E1, j, e1)
    n_out = 0
    for j in range(m):
        # wrap(phi - phibar) = pi - ((pi - (phi - phibar)) mod 2 pi), the modulo's result
        # to the bit (Python's: fmod, then + 2 pi if negative) where wr lies in
        # (-2 pi, 4 pi) (the adds are exact there: Sterbenz), in selects
        wr = _PI - (_vat(tw, _T_SIG, j) * _vatan2(_vat(tw, _F_S, j), _vat(tw, _F_C, j)) - rest[lo + j])
        inside = -_TWO_PI < wr < 2.0 * _TWO_PI
        n_out += 0 if inside else 1
        dphi = _PI - (wr + _TWO_PI if wr < 0.0 else (wr - _TWO_PI if wr >= _TWO_PI else wr))
        _vput_at(tw, _T_DPHI, j, dphi if inside else wr)
    if n_out:                       # rows _T_DPHI hold wr where it left that range: fmod
        # (a loop apart, run only then: the compiler would call fmod for every element)
        for j in range(m):
            wr = _vat(tw, _T_DPHI, j)
            if not -_TWO_PI < wr < 2.0 * _TWO_PI and math.isfinite(wr):
                _vput_at(tw, _T_DPHI, j, _PI - (wr % _TWO_PI))
    for j in range(m):
        dphi = _vat(tw, _T_DPHI, j)
        _vput_at(tw, _T_EN, j, 0.5 * stiff[lo + j] * dphi * dphi)
    if mode == ENERGY:
        return
    for j in range(m):
        t0, t1, n, b0, b1, d, inv_la, inv_lb = _v_twist_frame(tw, j, stiff[lo + j])
        al, be = _vat(tw, _T_AL, j), _vat(tw, _T_BE, j)
        ga = _vscale(b0, d * inv_la)
        gb = _vscale(b1, -d * inv_lb)
        _vput_row3(tw, _T_G, j, ga)
        _vput_row3(tw, _T_G + 3, j, _vadd(_vscale(ga, al - 1.0), _vscale(gb, be)))
        _vput_row3(tw, _T_G + 6, j, _vsub(_vscale(ga, -al), _vscale(gb, 1.0 + be)))
        _vput_row3(tw, _T_G + 9, j, gb)
    if mode != HESSIAN:
        return
    if exact:
        # the four in-plane eigenpairs with their eigenvalues, mapped by P^T
        for j in range(m):
            k = stiff[lo + j]
            t0, t1, n, b0, b1, d, inv_la, inv_lb = _v_twist_frame(tw, j, k)
            _v_eigenpairs(u, v, w, t0, t1, b0, b1, n, _vat(tw, _F_C, j), _vat(tw, _F_S, j), 1.0, d,
                          k, inv_la, inv_lb, 2)
            for c in range(4):
                _v_in_plane(tw, c, j, (u[c, 0], u[c, 1], u[c, 2]), (v[c, 0], v[c, 1], v[c, 2]),
                            1.0, 1.0, _vat(tw, _T_AL, j), _vat(tw, _T_BE, j))
            for c in range(8):
                _vput_at(tw, _T_W + c, j, w[c] if c < 4 else (1.0 if c < 6 else -1.0))
    else:
        # in-plane pairs 0 and 2 of angle.AngleFrame.positive_part, mapped by P^T
        for j in range(m):
            k = stiff[lo + j]
            t0, t1, n, b0, b1, d, inv_la, inv_lb = _v_twist_frame(tw, j, k)
            sd = 1.0 if d >= 0.0 else -1.0
            ad = abs(d)
            lam2 = k + _sqrt(k * k + d * d)
            rr = d / lam2 if lam2 > 0.0 else 0.0
            scn = 1.0 / _sqrt(2.0 * (1.0 + rr * rr))
            rs = rr * scn
            hsd = 0.5 * sd
            root0, root2 = _sqrt(lam2), _sqrt(ad)
            al, be = _vat(tw, _T_AL, j), _vat(tw, _T_BE, j)
            _v_in_plane(tw, 0, j, _vsub(_vscale(t0, rs), _vscale(b0, scn)),
                        _vadd(_vscale(t1, rs), _vscale(b1, scn)), root0 * inv_la,
                        root0 * inv_lb, al, be)
            _v_in_plane(tw, 1, j, _vsub(_vscale(t0, 0.5), _vscale(b0, hsd)),
                        _vadd(_vscale(t1, -0.5), _vscale(b1, -hsd)), root2 * inv_la,
                        root2 * inv_lb, al, be)
    # out-of-plane pairs: PSD part of 1/2 (p m^T + m p^T) (twist._out_of_plane and
    # twist._balanced_columns): the plus columns (both filters) in rows ``plus``, the
    # minus ones (used by the exact filter only) in rows 6, 7
    plus = 4 if exact else 2
    for j in range(m):
        t0, t1, n, b0, b1, d, inv_la, inv_lb = _v_twist_frame(tw, j, stiff[lo + j])
        al, be, sigma = _vat(tw, _T_AL, j), _vat(tw, _T_BE, j), _vat(tw, _T_SIG, j)
        c, s = _vat(tw, _F_C, j), _vat(tw, _F_S, j)
        inv_l1 = _sqrt(_vat(tw, _T_IL1SQ, j))
        e1h = _vscale(_vrow3(tw, _T_E1, j), inv_l1)
        osc = sigma * _SQRT_HALF
        mu = osc * inv_la
        st0 = _vscale(t0, s)
        _v_out_of_plane(tw, j, 0, plus, 1.0, t0, t1, b0, st0, e1h, al, be, c, d, osc, mu,
                        inv_lb, inv_l1)
        _v_out_of_plane(tw, j, 1, plus, -1.0, t0, t1, b0, st0, e1h, al, be, c, d, osc, mu,
                        inv_lb, inv_l1)
    # H = sum_c wts_c cols_c cols_c^T, the upper blocks
    blk = 0
    for a in range(4):
        for cc in range(a, 4):
            for q in range(3):
                qc = 3 * cc + q
                for r in range(3):
                    ra = 3 * a + r
                    row = 9 * blk + r + 3 * q
                    if exact:
                        for j in range(m):
                            hv = 0.0
                            for c in range(8):
                                hv += (_vat(tw, _T_W + c, j) * _vat(tw, _T_COLS + 12 * c + ra, j)
                                       * _vat(tw, _T_COLS + 12 * c + qc, j))
                            _vput_at(hh, row, j, hv)
                    else:       # four columns, weights 1
                        for j in range(m):
                            _vput_at(hh, row, j, _vat(tw, _T_COLS + ra, j) * _vat(tw, _T_COLS + qc, j)
                                     + _vat(tw, _T_COLS + 12 + ra, j) * _vat(tw, _T_COLS + 12 + qc, j)
                                     + _vat(tw, _T_COLS + 24 + ra, j) * _vat(tw, _T_COLS + 24 + qc, j)
                                     + _vat(tw, _T_COLS + 36 + ra, j) * _vat(tw, _T_COLS + 36 + qc, j))
            blk += 1


@_jit
def _terms(x, s_start, s_rest, s_k, b_start, b_rest, b_k, t_start, t_rest, t_k,
           mode, g, vals, base, b, upper, exact, diag, per_vertex):
    """All terms in one pass over the vertices (elements in order of their first
    vertex), so each block row is written while it is in cache; with ENERGY and a
    ``per_vertex`` (nv,) (or empty) each element's energy is also added to its first
    vertex's entry there (:func:`vertex_energy`); with HESSIAN the
    stored blocks of each row are zeroed on the way (row v + b just before the elements
    starting at v, the first to touch it), and without ``upper`` its blocks below the
    diagonal copied from the transposed upper ones once the row is complete, and
    ``diag`` (nv,) (or empty) added on its diagonal then (the mass term).  The matrix goes to ``vals`` as
    :class:`BlockLayout` ``base`` places it (column-major blocks).  Returns (energy, term, element):
    term 0, 1, 2 and the first bad element of that term, or -1, -1."""
    energy = 0.0
    u, v, w = np.empty((6, 3)), np.empty((6, 3)), np.empty(8)
    # the batches' scratch (_bend_batch, _twist_batch): elements b_lo .. b_hi - 1, t_lo .. t_hi - 1
    tb, hb = np.empty(_B_ROWS * _STRIDE), np.empty(54 * _STRIDE)
    tw, hh = np.empty(_T_ROWS * _STRIDE), np.empty(90 * _STRIDE)
    b_lo = b_hi = 0
    t_lo = t_hi = 0
    nv = x.shape[0]
    zero = mode == HESSIAN
    # without ``upper`` the blocks below the diagonal are set by _vcopy_lower, not summed;
    # the first b rows' whole rows are zeroed: a layout of the full band also stores
    # blocks (i, i + d) with i + d < 0, which no upper block copies over
    first = 0 if upper else b
    if zero:
        for r in range(min(b, nv)):
            _vzero_row(vals, base, r, 0)
    ps = pb = pt = 0
    for vtx in range(nv):
        if zero and vtx + b < nv:
            _vzero_row(vals, base, vtx + b, first)
        while ps < s_start.shape[0] and s_start[ps] == vtx:
            en, bad = _v_stretch(x, vtx, s_rest[ps], s_k[ps], mode, g, vals, base, b, exact)
            if bad:
                return energy, 0, ps
            energy += en
            if len(per_vertex):
                per_vertex[vtx] += en
            ps += 1
        while pb < b_start.shape[0] and b_start[pb] == vtx:
            if pb == b_hi:
                b_lo, b_hi = pb, min(pb + BATCH, b_start.shape[0])
                _bend_batch(x, b_start, b_rest, b_k, b_lo, b_hi, mode, exact, tb, hb, u, v, w)
            j = pb - b_lo
            if _vat(tb, _B_FLAG, j) == _BAD:
                return energy, 1, pb
            if mode == ENERGY:
                energy += _vat(tb, _B_EN, j)
                if len(per_vertex):
                    per_vertex[vtx] += _vat(tb, _B_EN, j)
            else:
                _v_put(g, vals, base, b, mode, vtx, j, tb, _B_G, hb, 3)
            pb += 1
        while pt < t_start.shape[0] and t_start[pt] == vtx:
            if pt == t_hi:
                t_lo, t_hi = pt, min(pt + BATCH, t_start.shape[0])
                _twist_batch(x, t_start, t_rest, t_k, t_lo, t_hi, mode, exact, tw, hh, u, v, w)
            j = pt - t_lo
            flag = _vat(tw, _T_FLAG, j)
            if flag == _BAD:
                return energy, 2, pt
            if flag == 0.0:
                if mode == ENERGY:
                    energy += _vat(tw, _T_EN, j)
                    if len(per_vertex):
                        per_vertex[vtx] += _vat(tw, _T_EN, j)
                else:
                    _v_put(g, vals, base, b, mode, vtx, j, tw, _T_G, hh, 4)
            pt += 1
        if zero and len(diag):      # block (vtx, vtx) is complete: + diag[vtx] I
            o = base[vtx, b]
            for r in range(3):
                vals[np.uint64(o + 4 * r)] += diag[vtx]
        if zero and not upper:
            _vcopy_lower(vals, base, b, vtx)
    return energy, -1, -1


TERMS = ("stretch", "bend", "twist")
_REFERENCE = {"stretch": stretch, "bend": bend, "twist": twist}
_K = {"stretch": 2, "bend": 3, "twist": 4}
_NO_ELEMENTS = (np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
_NO_G = np.zeros((0, 3))
_NO_VALUES = np.zeros(0)


def element_arrays(name, start, rest, stiffness):
    """(start, rest, stiffness) of a term as the kernels take them: validated as the
    NumPy kernels do, contiguous, ``start`` (n,) int64 nondecreasing."""
    if name not in _K:
        raise ValueError(f"unknown term {name!r}: use one of {', '.join(TERMS)}")
    start = np.ascontiguousarray(start, np.int64)
    if start.ndim != 1 or len(start) != len(rest) or (len(start) and np.any(np.diff(start) < 0)):
        raise ValueError(f"{name}: element first vertices must be a nondecreasing (n,) array "
                         f"matching the {len(rest)} rest values")
    return (start, *check_term(name, rest, stiffness))


class BlockLayout:
    """Where the matrix's 3x3 blocks live in a flat value array: entry (r, c) of block
    (i, i + d), |d| <= b, is ``values[base[i, d + b] + r * row_stride + c * col_stride]``
    (``base`` (nv, 2 b + 1) int64, -1 where the block is not stored: outside the wisp,
    or below the diagonal for SBAIJ).  Blocks not stored must never be written: the
    elements stay inside their wisp.  The kernels take :meth:`block_csr` layouts
    (column-major blocks, a row's blocks contiguous)."""

    def __init__(self, base, row_stride, col_stride, b):
        self.base = np.ascontiguousarray(base, np.int64)
        self.row_stride, self.col_stride, self.b = int(row_stride), int(col_stride), int(b)
        if self.base.ndim != 2 or self.base.shape[1] != 2 * self.b + 1:
            raise ValueError(f"BlockLayout: base must be (nv, {2 * self.b + 1}), got {self.base.shape}")

    @classmethod
    def block_csr(cls, stored, b):
        """A block-CSR value array (PETSc SeqBAIJ: block rows in order, each row's
        blocks by column, each block column-major) holding the blocks ``stored``
        (nv, 2 b + 1) bool: block (i, i + d) at ``stored[i, d + b]``."""
        stored = np.asarray(stored, bool)
        base = np.full(stored.shape, -1, np.int64)
        base[stored] = 9 * np.arange(int(stored.sum()))
        return cls(base, 1, 3, b)

    def size(self):
        """The smallest value array the layout fits."""
        last = int(self.base.max(initial=-1))
        return 0 if last < 0 else last + 2 * self.row_stride + 2 * self.col_stride + 1


_NO_LAYOUT = BlockLayout(np.zeros((0, 1), np.int64), 0, 0, 0)


def _run(terms, x, mode, g, values, layout, upper, exact=False, diag=_NO_VALUES, per_vertex=_NO_VALUES):
    """Run the fused pass over ``terms`` (name -> :func:`element_arrays`)."""
    x = np.ascontiguousarray(x, np.float64)
    for name, (start, _, _) in terms.items():
        k = _K[name]
        if len(start) and (start[0] < 0 or start[-1] + k > len(x)):
            raise ValueError(f"{name}: elements reach vertex {int(start[-1]) + k - 1} of {len(x)}")
        if mode == HESSIAN and k - 1 > layout.b:
            raise ValueError(f"{name}: a half bandwidth of {layout.b} cannot hold {k}-vertex elements")
    arrays = [terms.get(name, _NO_ELEMENTS) for name in TERMS]
    energy, term, bad = _terms(x, *arrays[0], *arrays[1], *arrays[2], mode, g, values,
                               layout.base, layout.b, upper, exact, diag, per_vertex)
    if bad >= 0:
        # The NumPy kernel names the problem (ElementError); it must raise here.
        name = TERMS[term]
        start, rest, stiffness = arrays[term]
        _REFERENCE[name].energy(x[start[:, None] + np.arange(_K[name])], rest, stiffness)
        raise RuntimeError(f"{name}: the compiled kernel rejected element {bad} but the "
                           f"NumPy kernel accepted it")
    return energy


def energy(terms, x):
    """Summed energy of ``terms`` (name -> :func:`element_arrays`) at positions x (nv, 3)."""
    return _run(terms, x, ENERGY, _NO_G, _NO_VALUES, _NO_LAYOUT, False)


def vertex_energy(terms, x):
    """Per vertex (nv,) the energy of the elements of ``terms`` starting there (a wisp's
    sum of it is its elastic energy): :meth:`lc_petsc.assembly.Assembler.vertex_energy`
    in one compiled pass, each element's energy that of :func:`energy` (within round-off
    of the NumPy kernels')."""
    out = np.zeros(len(x))
    _run(terms, x, ENERGY, _NO_G, _NO_VALUES, _NO_LAYOUT, False, per_vertex=out)
    return out


def add_gradient(terms, x, g):
    """Add the gradient of ``terms`` to g (nv, 3)."""
    _run(terms, x, GRADIENT, g, _NO_VALUES, _NO_LAYOUT, False)


def add_gradient_hessian(terms, x, g, band, b, upper, filter="analytic"):
    """Add the gradient to g (nv, 3) and set ``band`` (nv, 3, 3 (2 b + 1)) to the
    ``filter``-ed Hessian of ``terms`` (module doc; ``upper``: only d >= 0), through
    a block array of the whole band (:func:`add_gradient_hessian_into`)."""
    nv, width = len(x), 2 * b + 1
    if band.shape != (nv, 3, 3 * width):
        raise ValueError(f"band must have shape {(nv, 3, 3 * width)}, got {band.shape}")
    values = np.zeros(9 * nv * width)
    add_gradient_hessian_into(terms, x, g, values, BlockLayout.block_csr(np.ones((nv, width)), b),
                              upper, filter)
    # values[9 (i width + d + b) + r + 3 c] -> band[i, r, 3 (d + b) + c]
    band.reshape(nv, 3, width, 3)[...] = values.reshape(nv, width, 3, 3).transpose(0, 3, 1, 2)


def add_gradient_hessian_into(terms, x, g, values, layout, upper, filter="analytic", diag=None):
    """Add the gradient to g (nv, 3) and set the blocks of the flat ``values`` that
    ``layout`` (:class:`BlockLayout`, column-major blocks: :meth:`BlockLayout.block_csr`)
    stores to the ``filter``-ed Hessian of ``terms`` (``upper``: only blocks with
    d >= 0 are written): e.g. straight into PETSc's SeqBAIJ value array, with no band
    or per-element buffer in between.  ``diag`` (nv,): diag[i] I added to block (i, i)
    once its elements are in, while the row is in cache (the values of adding it
    after, bit for bit)."""
    if filter not in FILTERS:
        raise ValueError(f"compiled kernels implement the filters {FILTERS}, not {filter!r}")
    if (layout.row_stride, layout.col_stride) != (1, 3):
        raise ValueError("the compiled kernels write column-major 3x3 blocks: use "
                         "BlockLayout.block_csr")
    if layout.base.shape[0] != len(x) or values.ndim != 1 or len(values) < layout.size():
        raise ValueError(f"values ({values.shape}) and layout ({layout.base.shape} blocks) do "
                         f"not fit {len(x)} vertices: build the layout for these values")
    if diag is None:
        diag = _NO_VALUES
    else:
        diag = np.ascontiguousarray(diag, np.float64)
        if diag.shape != (len(x),):
            raise ValueError(f"diag must have shape ({len(x)},) (one value per vertex), got {diag.shape}")
    _run(terms, x, HESSIAN, g, values, layout, bool(upper), filter == "none", diag)


@_jit
def _gather_blocks(band, rows, diags, out, column_major):
    """out[9 j:9 j + 9] = block (rows[j], rows[j] + diags[j] - b) of ``band`` (module
    doc; ``diags`` counts from the band's first diagonal), row-major or column-major."""
    for j in range(rows.shape[0]):
        i, d = rows[j], diags[j]
        o = 9 * j
        for r in range(3):
            for c in range(3):
                if column_major:
                    out[o + 3 * c + r] = band[i, r, 3 * d + c]
                else:
                    out[o + 3 * r + c] = band[i, r, 3 * d + c]


def gather_blocks(band, rows, diags, out, column_major):
    """Copy the band's blocks (rows[j], diagonal diags[j]) into the flat ``out``
    (9 per block), as a PETSc BAIJ value array stores them (``column_major``) or as
    ``MatSetValuesBlocked`` takes them."""
    _gather_blocks(band, rows, diags, out, bool(column_major))


@_jit
def _add_diagonal(values, index, diag):
    """values[index[j, c]] += diag[j] for c = 0, 1, 2."""
    for j in range(index.shape[0]):
        for c in range(3):
            values[index[j, c]] += diag[j]


def add_diagonal(values, index, diag):
    """Add diag (nv,) to the entries index (nv, 3) of the flat ``values`` (the
    diagonals of the diagonal blocks: M / dt^2): one compiled loop (a NumPy fancy-index
    add costs 15-25 ms at 2,000 wisps)."""
    _add_diagonal(values, np.ascontiguousarray(index, np.int64), np.ascontiguousarray(diag, np.float64))


@_jit
def _add_segment_blocks(values, block_index, idx, b, h00, h01, h11):
    # four passes in add_segment_blocks' order: a block that two of them reach (the
    # (v + 1, v + 1) block of consecutive segments) gets its sums in NumPy's order
    for p in range(4):
        H = h00 if p == 0 else (h11 if p == 1 else h01)
        row = 1 if p == 1 or p == 3 else 0                  # block row v or v + 1
        diag = b if p < 2 else (b + 1 if p == 2 else b - 1)
        for k in range(idx.shape[0]):
            blk = block_index[idx[k] + row, diag]
            if blk < 0:         # not stored (SBAIJ keeps the upper triangle only)
                continue
            for r in range(3):
                for c in range(3):                          # blocks stored column-major
                    values[9 * blk + 3 * c + r] += H[k, c, r] if p == 3 else H[k, r, c]


def add_segment_blocks(values, block_index, idx, b, h00, h01, h11):
    """Add the 2x2 blocks of segments (v, v + 1), v = idx (m,) unique local first
    vertices, to the flat BAIJ ``values`` (column-major 3x3 blocks; block (i, i + d - b)
    is block_index[i, d], a band of half width b >= 1): h00 to (v, v), h11 to (v + 1,
    v + 1), h01 to (v, v + 1) and its transpose to (v + 1, v), all (m, 3, 3); blocks not
    stored (block_index -1: the lower triangle of an SBAIJ matrix) are skipped.  The sums
    of four NumPy fancy-index adds (the same bits), in one compiled loop (those took 64
    ms per Newton iteration at 8K)."""
    idx = np.ascontiguousarray(idx, np.int64)
    m = len(idx)
    if any(np.shape(h) != (m, 3, 3) for h in (h00, h01, h11)) or not 1 <= b < block_index.shape[1] - 1:
        raise ValueError(f"add_segment_blocks: h00, h01, h11 must be ({m}, 3, 3) and 1 <= b < "
                         f"{block_index.shape[1] - 1}, got {[np.shape(h) for h in (h00, h01, h11)]}, b = {b}")
    if m and (idx.min() < 0 or idx.max() + 1 >= block_index.shape[0]):   # no bounds checks inside
        raise ValueError(f"add_segment_blocks: first vertices must lie in [0, {block_index.shape[0] - 1}), "
                         f"got [{idx.min()}, {idx.max()}]")
    _add_segment_blocks(values, np.ascontiguousarray(block_index, np.int64), idx, int(b),
                        *(np.ascontiguousarray(h, np.float64) for h in (h00, h01, h11)))


# ------------------------------------------------ edge lengths (the Newton update)
@_jit
def _onto_head(q0, q1, q2, y0, y1, y2, L, R):
    """The point z at distance L from q (|z - q| = L) on the sphere |z| = R closest to y
    (positions relative to the sphere's centre; y at distance L from q, inside it): on
    the circle where the two spheres meet, in the direction of y's part across q's axis;
    q + L q / |q| when that circle does not exist (q too deep to reach the surface)."""
    a = _sqrt(q0 * q0 + q1 * q1 + q2 * q2)
    if not a > 0.0:
        return y0, y1, y2
    u0, u1, u2 = q0 / a, q1 / a, q2 / a
    if a + L <= R:
        return q0 + L * u0, q1 + L * u1, q2 + L * u2
    h = (a * a + R * R - L * L) / (2.0 * a)
    rho = _sqrt(max(R * R - h * h, 0.0))
    yu = y0 * u0 + y1 * u1 + y2 * u2
    w0, w1, w2 = y0 - yu * u0, y1 - yu * u1, y2 - yu * u2
    nw = _sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    if not nw > 1e-12 * L:
        # y on q's axis (the edge points straight into the head): any side will do; the
        # axis of q's smallest component, made perpendicular to q
        k0 = 1.0 if abs(u0) <= abs(u1) and abs(u0) <= abs(u2) else 0.0
        k1 = 1.0 if k0 == 0.0 and abs(u1) <= abs(u2) else 0.0
        k2 = 1.0 - k0 - k1
        ku = k0 * u0 + k1 * u1 + k2 * u2
        w0, w1, w2 = k0 - ku * u0, k1 - ku * u1, k2 - ku * u2
        nw = _sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    return h * u0 + rho * w0 / nw, h * u1 + rho * w1 / nw, h * u2 + rho * w2 / nw


@_jit
def _edge_lengths(x, dx, length, free, offsets, mass, retract, out, center, surface, allow):
    """out = the positions of lc_petsc.predictors._set_edge_lengths, wisp by wisp.

    ``retract``: the positions are x + dx and the lengths |e| + eh . de of the edges e
    of x (predictors.retract_edge_lengths; ``length`` unused), else the positions are x
    and the lengths ``length`` (nv - 1,) (dx unused).  Walking each wisp from its root,
    the correction of vertex v is the sum of (length / |edge| - 1) edge over the edges
    (u - 1, u) since the last pinned vertex (edges of zero length or with a length <= 0
    add nothing); on a wisp without a pinned vertex, with ``mass`` (nv,) non-empty, the
    mass-weighted mean correction is removed.

    ``surface`` > 0 (with ``center`` (3,) and ``allow`` (nv,)): on a wisp with a pinned
    vertex, a vertex whose new position lies deeper in the sphere of radius ``surface``
    about ``center`` than ``allow`` is put on the sphere instead, at its edge's length
    from its (new) predecessor (:func:`_onto_head`); the vertices after it follow."""
    for w in range(offsets.shape[0] - 1):
        lo, hi = offsets[w], offsets[w + 1]
        c0 = c1 = c2 = 0.0
        pinned = False
        head = False
        if surface > 0.0:
            for v in range(lo, hi):
                head = head or not free[v]
        for v in range(lo, hi):
            p0 = x[v, 0]
            p1 = x[v, 1]
            p2 = x[v, 2]
            if retract:
                p0 += dx[v, 0]
                p1 += dx[v, 1]
                p2 += dx[v, 2]
            if v == lo or not free[v]:
                pinned = pinned or not free[v]
                c0 = c1 = c2 = 0.0
            else:
                e0, e1, e2 = out[v - 1, 3], out[v - 1, 4], out[v - 1, 5]   # x + dx at v - 1
                d0, d1, d2 = p0 - e0, p1 - e1, p2 - e2
                n = _sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                if retract:
                    f0, f1, f2 = x[v, 0] - x[v - 1, 0], x[v, 1] - x[v - 1, 1], x[v, 2] - x[v - 1, 2]
                    L = _sqrt(f0 * f0 + f1 * f1 + f2 * f2)
                    if L > 0.0:
                        target = L + (f0 * (d0 - f0) + f1 * (d1 - f1) + f2 * (d2 - f2)) / L
                    else:
                        target = 0.0
                else:
                    target = length[v - 1]
                if n > 0.0 and target > 0.0:
                    f = target / n - 1.0
                    # relative to the centre: q the predecessor's new position, y this one's
                    q0, q1, q2 = e0 + c0 - center[0], e1 + c1 - center[1], e2 + c2 - center[2]
                    c0 += d0 * f
                    c1 += d1 * f
                    c2 += d2 * f
                    if head:
                        y0, y1, y2 = p0 + c0 - center[0], p1 + c1 - center[1], p2 + c2 - center[2]
                        if _sqrt(y0 * y0 + y1 * y1 + y2 * y2) < surface - allow[v]:
                            z0, z1, z2 = _onto_head(q0, q1, q2, y0, y1, y2, target, surface)
                            c0, c1, c2 = z0 + center[0] - p0, z1 + center[1] - p1, z2 + center[2] - p2
            out[v, 0], out[v, 1], out[v, 2] = c0, c1, c2
            out[v, 3], out[v, 4], out[v, 5] = p0, p1, p2
        if not pinned and mass.shape[0] > 0:
            m = s0 = s1 = s2 = 0.0
            for v in range(lo, hi):
                m += mass[v]
                s0 += mass[v] * out[v, 0]
                s1 += mass[v] * out[v, 1]
                s2 += mass[v] * out[v, 2]
            if not m > 0.0:
                m = 1.0
            s0, s1, s2 = s0 / m, s1 / m, s2 / m
            for v in range(lo, hi):
                out[v, 0] -= s0
                out[v, 1] -= s1
                out[v, 2] -= s2
    for v in range(x.shape[0]):
        out[v, 0] += out[v, 3]
        out[v, 1] += out[v, 4]
        out[v, 2] += out[v, 5]


def _chain_arrays(name, x, dx, offsets):
    """x, dx (nv, 3) float64 and offsets (n_wisps + 1,) int64, contiguous, checked
    (ValueError naming ``name`` and what is wrong)."""
    x = np.ascontiguousarray(x, np.float64)
    dx = np.ascontiguousarray(dx, np.float64)
    offsets = np.ascontiguousarray(offsets, np.int64)
    nv = len(x)
    if dx.shape != x.shape or x.ndim != 2 or x.shape[1:] != (3,):
        raise ValueError(f"{name}: x and dx must be (nv, 3), got {x.shape} and {dx.shape}")
    if len(offsets) < 1 or offsets[0] != 0 or offsets[-1] != nv or np.any(np.diff(offsets) < 0):
        raise ValueError(f"{name}: wisp offsets must rise from 0 to {nv}")
    return x, dx, offsets


def edge_lengths(x, dx, length, free, offsets, mass, head=None):
    """The positions of :func:`lc_petsc.predictors._set_edge_lengths` (``dx`` None: x
    with edge lengths ``length`` (nv - 1,)) or of
    :func:`lc_petsc.predictors.retract_edge_lengths` (``length`` None: x + dx with the
    linearised lengths), in one compiled pass over each wisp.  x, dx (nv, 3), free (nv,)
    bool, offsets (n_wisps + 1,) covering 0..nv, mass (nv,) or None; ``head``: None or
    (centre (3,), radius > 0, allowed depth (nv,)), a sphere the lengths are set
    around (:func:`_edge_lengths`).  Returns (nv, 3)."""
    retract = dx is not None
    x, dx, offsets = _chain_arrays("edge lengths", x, dx if retract else x, offsets)
    nv = len(x)
    length = np.zeros(0) if retract else np.ascontiguousarray(length, np.float64)
    if not retract and len(length) != max(nv - 1, 0):
        raise ValueError(f"edge lengths: {len(length)} lengths for {nv} vertices, need {nv - 1}")
    mass = np.zeros(0) if mass is None else np.ascontiguousarray(mass, np.float64)
    center, surface, allow = np.zeros(3), 0.0, np.zeros(0)
    if head is not None:
        center, surface, allow = (np.ascontiguousarray(head[0], np.float64), float(head[1]),
                                  np.ascontiguousarray(head[2], np.float64))
        if center.shape != (3,) or not surface > 0.0 or allow.shape != (nv,):
            raise ValueError(f"edge lengths: the head must be (centre (3,), radius > 0, allowed depth "
                             f"({nv},)), got {center.shape}, {surface!r}, {allow.shape}")
    out = np.empty((nv, 6))     # (correction, x (+ dx)) per vertex, then the result
    _edge_lengths(x, dx, length, np.ascontiguousarray(free, np.bool_), offsets, mass, retract, out,
                  center, surface, allow)
    return out[:, :3].copy()


#: corotate: the rotation fit's regularisation, relative to the trace of its normal matrix
#: (only a neighbourhood of collinear edges needs it: the rotation about their common
#: line is then free, and it does not move them)
COROTATE_EPS = 1e-10


@_jit
def _corotate(x, dx, free, offsets, mass, y, length):
    """y = x + dx with every edge e ending at a free vertex turned by the rotation w fitted
    to the increments de of the edges around it, and ``length`` (nv - 1,) = |e| + eh . de,
    the first-order lengths (predictors.corotational_update; the lengths are set by
    :func:`_edge_lengths` afterwards).

    Edge j = (v - 1, v): w minimises sum_k |w x e_k - de_k|^2 over the edges k = j - 1,
    j, j + 1 of the same wisp, i.e. (sum_k |e_k|^2 I - e_k e_k^T) w = sum_k e_k x de_k
    (+ COROTATE_EPS trace I); the new edge is R(w) e + (de - w x e) (Rodrigues), equal to
    e + de to first order and exactly R(w) e for a rigid rotation (de_k = w x e_k).  The
    positions are accumulated from the root (or the last pinned vertex), whose x + dx is
    kept; on a wisp with no pinned vertex (``mass`` non-empty) y is shifted so that its
    mass-weighted mean is that of x + dx."""
    for w in range(offsets.shape[0] - 1):
        lo, hi = offsets[w], offsets[w + 1]
        pinned = False
        for v in range(lo, hi):
            if v == lo or not free[v]:
                pinned = pinned or not free[v]
                for c in range(3):
                    y[v, c] = x[v, c] + dx[v, c]
                if v > lo:
                    length[v - 1] = 0.0
                continue
            a00 = a01 = a02 = a11 = a12 = a22 = 0.0
            b0 = b1 = b2 = 0.0
            for k in range(max(v - 2, lo), min(v + 1, hi - 1)):     # edges (k, k + 1)
                e0, e1, e2 = x[k + 1, 0] - x[k, 0], x[k + 1, 1] - x[k, 1], x[k + 1, 2] - x[k, 2]
                d0, d1, d2 = dx[k + 1, 0] - dx[k, 0], dx[k + 1, 1] - dx[k, 1], dx[k + 1, 2] - dx[k, 2]
                ee = e0 * e0 + e1 * e1 + e2 * e2
                a00 += ee - e0 * e0
                a11 += ee - e1 * e1
                a22 += ee - e2 * e2
                a01 -= e0 * e1
                a02 -= e0 * e2
                a12 -= e1 * e2
                b0 += e1 * d2 - e2 * d1
                b1 += e2 * d0 - e0 * d2
                b2 += e0 * d1 - e1 * d0
            reg = COROTATE_EPS * (a00 + a11 + a22)
            a00 += reg
            a11 += reg
            a22 += reg
            c00 = a11 * a22 - a12 * a12
            c01 = a02 * a12 - a01 * a22
            c02 = a01 * a12 - a02 * a11
            c11 = a00 * a22 - a02 * a02
            c12 = a01 * a02 - a00 * a12
            c22 = a00 * a11 - a01 * a01
            det = a00 * c00 + a01 * c01 + a02 * c02
            w0 = w1 = w2 = 0.0
            if det > 0.0:
                w0 = (c00 * b0 + c01 * b1 + c02 * b2) / det
                w1 = (c01 * b0 + c11 * b1 + c12 * b2) / det
                w2 = (c02 * b0 + c12 * b1 + c22 * b2) / det
            e0, e1, e2 = x[v, 0] - x[v - 1, 0], x[v, 1] - x[v - 1, 1], x[v, 2] - x[v - 1, 2]
            d0, d1, d2 = dx[v, 0] - dx[v - 1, 0], dx[v, 1] - dx[v - 1, 1], dx[v, 2] - dx[v - 1, 2]
            L = _sqrt(e0 * e0 + e1 * e1 + e2 * e2)
            length[v - 1] = L + (e0 * d0 + e1 * d1 + e2 * d2) / L if L > 0.0 else 0.0
            # w x e, and R(w) e = e + s (k x e) + (1 - c) k x (k x e), k = w / |w|
            x0, x1, x2 = w1 * e2 - w2 * e1, w2 * e0 - w0 * e2, w0 * e1 - w1 * e0
            xx0, xx1, xx2 = w1 * x2 - w2 * x1, w2 * x0 - w0 * x2, w0 * x1 - w1 * x0
            th2 = w0 * w0 + w1 * w1 + w2 * w2
            if th2 > 1e-16:
                th = _sqrt(th2)
                fs, fc = math.sin(th) / th, (1.0 - math.cos(th)) / th2
            else:
                fs, fc = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
            y[v, 0] = y[v - 1, 0] + e0 + (fs - 1.0) * x0 + fc * xx0 + d0
            y[v, 1] = y[v - 1, 1] + e1 + (fs - 1.0) * x1 + fc * xx1 + d1
            y[v, 2] = y[v - 1, 2] + e2 + (fs - 1.0) * x2 + fc * xx2 + d2
        if not pinned and mass.shape[0] > 0:
            m = s0 = s1 = s2 = 0.0
            for v in range(lo, hi):
                m += mass[v]
                s0 += mass[v] * (x[v, 0] + dx[v, 0] - y[v, 0])
                s1 += mass[v] * (x[v, 1] + dx[v, 1] - y[v, 1])
                s2 += mass[v] * (x[v, 2] + dx[v, 2] - y[v, 2])
            if not m > 0.0:
                m = 1.0
            for v in range(lo, hi):
                y[v, 0] += s0 / m
                y[v, 1] += s1 / m
                y[v, 2] += s2 / m


def corotate(x, dx, free, offsets, mass):
    """The positions of :func:`lc_petsc.predictors.corotational_update`: x + dx with each
    free edge turned by the rotation fitted to its neighbourhood's increments and given
    its first-order length (:func:`_corotate`, then :func:`_edge_lengths`), in two
    compiled passes over each wisp.  x, dx (nv, 3), free (nv,) bool, offsets
    (n_wisps + 1,) covering 0..nv, mass (nv,) or None.  Returns (nv, 3)."""
    x, dx, offsets = _chain_arrays("corotate", x, dx, offsets)
    nv = len(x)
    free = np.ascontiguousarray(free, np.bool_)
    mass = np.zeros(0) if mass is None else np.ascontiguousarray(mass, np.float64)
    y = np.empty((nv, 3))
    length = np.zeros(max(nv - 1, 0))
    _corotate(x, dx, free, offsets, mass, y, length)
    out = np.empty((nv, 6))
    _edge_lengths(y, y, length, free, offsets, mass, False, out, np.zeros(3), 0.0, np.zeros(0))
    return out[:, :3].copy()


def warm_up():
    """Compile (or load from the cache) every kernel, the root turn's too
    (:mod:`compiled_turn`); returns the seconds it took."""
    t0 = time.perf_counter()
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [1.0, 1.0, 1.0]])
    one = (np.zeros(1, np.int64), np.ones(1), np.ones(1))
    g = np.zeros((4, 3))
    band = np.zeros((4, 3, 21))
    layout = BlockLayout.block_csr(np.ones((4, 7)), 3)
    for mode in (ENERGY, GRADIENT, HESSIAN):
        for exact in (False, True):
            _terms(x, *one, *one, *one, mode, g, np.zeros(9 * 28), layout.base, 3, False, exact, _NO_VALUES,
                   _NO_VALUES)
    _gather_blocks(band, one[0], one[0], np.zeros(9), True)
    add_diagonal(np.zeros(9), np.zeros((1, 3), np.int64), np.ones(1))
    add_segment_blocks(np.zeros(54), np.arange(6, dtype=np.int64).reshape(2, 3), np.zeros(1, np.int64), 1,
                       *np.zeros((3, 1, 3, 3)))
    off = np.array([0, 4])
    edge_lengths(x, g, None, np.ones(4, bool), off, np.ones(4))
    edge_lengths(x, None, np.ones(3), np.ones(4, bool), off, None)
    corotate(x, g, np.ones(4, bool), off, np.ones(4))
    from lc_petsc.elements import compiled_turn     # it imports _jit from here
    compiled_turn.warm_up()
    return time.perf_counter() - t0
