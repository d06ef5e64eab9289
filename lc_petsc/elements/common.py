"""Shared pieces of the element kernels: input validation, filters, batched small algebra.

All arrays are batch-first: a leading axis of ``n`` elements. Nothing here loops over
elements in Python.
"""

import numpy as np

from lc_petsc.errors import ElementError

#: Hessian filters every kernel accepts.
FILTERS = ("analytic", "numerical", "none", "abs")

#: Elements per chunk: small enough that a chunk's temporaries stay in cache, large
#: enough that NumPy's per-call overhead is amortised (measured in bench_elements.py).
CHUNK = 4096

#: An edge shorter than this many ulps of its endpoint coordinates has no direction.
_ZERO_EDGE_ULPS = 64.0


def check_filter(filter):
    """``filter`` if it names a Hessian filter, else a ValueError listing them."""
    if filter not in FILTERS:
        raise ValueError(f"unknown Hessian filter {filter!r}: use one of {', '.join(FILTERS)}")
    return filter


def check_positions(x, k, term):
    """Validate element positions of shape (n, k, 3); return them as float64.

    Raises :class:`ElementError` naming the first bad element.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 3 or x.shape[1:] != (k, 3):
        raise ElementError(
            f"{term}: positions must have shape (n_elements, {k}, 3), got {x.shape}")
    bad = ~np.isfinite(x).all(axis=(1, 2))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ElementError(f"{term}: element {i} has a non-finite position {x[i].tolist()}; "
                           f"{int(bad.sum())} element(s) affected")
    return x


def check_per_element(value, n, term, name, positive=False):
    """Broadcast a scalar or (n,) parameter to (n,) float64 and check it.

    Stiffnesses must be finite and >= 0 (``positive=True``: > 0).
    """
    v = np.asarray(value, dtype=np.float64)
    if v.ndim > 1 or (v.ndim == 1 and v.shape[0] != n):
        raise ElementError(f"{term}: {name} must be a scalar or have shape ({n},), got {v.shape}")
    v = np.broadcast_to(v, (n,))
    bad = ~np.isfinite(v) | ((v <= 0) if positive else (v < 0))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        rule = "> 0" if positive else ">= 0"
        raise ElementError(f"{term}: {name} of element {i} is {v[i]!r}; it must be finite and {rule}")
    return v


def check_finite(v, n, term, name):
    """Broadcast a scalar or (n,) parameter to (n,) float64 and check it is finite."""
    v = np.asarray(v, dtype=np.float64)
    if v.ndim > 1 or (v.ndim == 1 and v.shape[0] != n):
        raise ElementError(f"{term}: {name} must be a scalar or have shape ({n},), got {v.shape}")
    v = np.broadcast_to(v, (n,))
    bad = ~np.isfinite(v)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ElementError(f"{term}: {name} of element {i} is {v[i]!r}; it must be finite")
    return v


def coordinate_scale(x):
    """Largest coordinate magnitude of each element of x (n, k, 3): round-off reference."""
    return np.abs(x.reshape(x.shape[0], x.shape[1] * x.shape[2])).max(axis=1, initial=0.0)


def edge_lengths(e, scale, term, edge_name, offset=0):
    """Lengths (n,) of component-major edges e (3, n); a zero-length edge is an :class:`ElementError`.

    "Zero" means at the round-off level of the element's coordinates (``scale`` (n,), from
    :func:`coordinate_scale`), so the rule does not depend on the unit of length.
    """
    length = np.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    zero = length <= _ZERO_EDGE_ULPS * np.finfo(np.float64).eps * scale
    zero |= length == 0.0
    if zero.any():
        i = int(np.flatnonzero(zero)[0])
        raise ElementError(
            f"{term}: edge {edge_name} of element {i + offset} has zero length (|e| = "
            f"{length[i]:.3g} at coordinates of size {scale[i]:.3g}); merge or remove the "
            f"coincident vertices")
    return length


def gram(v, w=None, out=None):
    """sum_j w_j v_j v_j^T for component-major columns v (m, r, n), weights w (n, r).

    Returns (n, m, m). Both matmul operands are made contiguous: NumPy's batched matmul is
    about 2x faster than on transposed views.
    """
    vw = v if w is None else v * w.T
    return np.matmul(np.ascontiguousarray(vw.transpose(2, 0, 1)),
                     np.ascontiguousarray(v.transpose(2, 1, 0)), out=out)


def run_chunked(kernel, n, k, inputs, want_gradient, want_hessian, out=None):
    """Evaluate an element kernel chunk by chunk into preallocated outputs.

    ``kernel(lo, inputs_chunk, g_chunk, h_chunk)`` fills the gradient chunk (m, k, 3) and/or
    the Hessian chunk (m, 3k, 3k) (either may be None). ``out`` optionally supplies the
    Hessian array (n, 3k, 3k), e.g. a buffer reused across Newton iterations.
    Returns (gradient or None, hessian or None).
    """
    g = np.empty((n, k, 3)) if want_gradient else None
    h = None
    if want_hessian:
        if out is None:
            h = np.empty((n, 3 * k, 3 * k))
        elif out.shape != (n, 3 * k, 3 * k) or out.dtype != np.float64:
            raise ValueError(f"out must be a float64 array of shape {(n, 3 * k, 3 * k)}, "
                             f"got {out.dtype} {out.shape}")
        else:
            h = out
    for lo in range(0, n, CHUNK):
        hi = min(n, lo + CHUNK)
        kernel(lo, [a[lo:hi] for a in inputs],
               None if g is None else g[lo:hi], None if h is None else h[lo:hi])
    return g, h
