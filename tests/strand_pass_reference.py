"""NumPy references of the compiled passes along strands (tests only): the Jacobi
sweeps that :func:`lc_petsc.elements.compiled_ccd.smooth_fractions` and
:func:`~lc_petsc.elements.compiled_ccd.bound_edge_lengths` replaced (they were the
limiter's and the separation's code until 2026-12-04; 40% of a 2K ccd frame)."""

import numpy as np


def smooth_fractions_reference(beta, F, seg, rest_length, free, strain):
    """Jacobi sweeps of b_i = min(beta_i, b_j + c_ij) until nothing changes."""
    a, b = seg, seg + 1
    fn = np.linalg.norm(F, axis=1)
    fmax = np.maximum(fn[a], fn[b])
    c = np.full(len(seg), np.inf)
    moving = fmax > 0.0
    c[moving] = strain * rest_length[moving] / fmax[moving]
    out = np.asarray(beta, float).copy()
    while True:
        new = out.copy()
        np.minimum.at(new, a, out[b] + c)
        np.minimum.at(new, b, out[a] + c)
        new[~free] = out[~free]
        if np.array_equal(new, out):
            return out
        out = new


def bound_edge_lengths_reference(x, seg, colour, lo, hi, inverse_mass, check, max_sweeps):
    """Red-black sweeps, each half sweep one vectorised projection of a colour."""
    x = np.array(x, float)
    m = len(seg)
    movable = inverse_mass[seg] + inverse_mass[seg + 1] > 0.0
    check = movable.copy() if check is None else check & movable
    joined = np.flatnonzero(seg[1:] == seg[:-1] + 1)
    sweeps = 0
    while sweeps < max_sweeps and check.any():
        for c in (0, 1):
            k = np.flatnonzero(check & (colour == c))
            check[k] = False
            d = x[seg[k] + 1] - x[seg[k]]
            length = np.sqrt(np.einsum("ij,ij->i", d, d))
            out = ((length > hi[k] * (1.0 + 1e-12)) | (length < lo[k] * (1.0 - 1e-12))) & (length > 0.0)
            e, d, length = k[out], d[out], length[out]
            wa, wb = inverse_mass[seg[e]], inverse_mass[seg[e] + 1]
            push = d * ((length - np.clip(length, lo[e], hi[e])) / (length * (wa + wb)))[:, None]
            x[seg[e]] += wa[:, None] * push
            x[seg[e] + 1] -= wb[:, None] * push
            moved = np.zeros(m + 1, bool)
            moved[e] = True
            near = np.zeros(m, bool)
            near[joined] = moved[joined + 1]
            near[joined + 1] |= moved[joined]
            check |= near & movable
        sweeps += 1
    return x, sweeps
