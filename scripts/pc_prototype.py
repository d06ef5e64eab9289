"""Preconditioner prototypes for the contact Newton systems, in SciPy, on a system dumped
by scripts/dump_system.py (docs/contact_solver.md, "Preconditioner prototypes on a dumped
system").

  python scripts/pc_prototype.py SYSTEM.npz [SYSTEM.npz ...] --variants blocks adef2:chunk@16x1 ...
      [--rtol 1e-4] [--max-it 1000] [--chunk 16] [--agg-cap 8] [--theta 0]
      [--cluster-wisps 64] [--ilu-drop 1e-3] [--ilu-fill 4] [--json OUT.json]

K = A + C.  PCG from x0 = 0 with PETSc's test for CG (the preconditioned residual norm
below ``--rtol`` times its start).  Variants (``NAME``, ``NAME:COARSE``, ``NAME:COARSE@LxM``):

* ``blocks``: B^-1, B the per-wisp blocks as the default's fallback builds them: each
  wisp's band of A, plus its own self-contact blocks of C (a one-wisp cluster); it must
  take the run's CG count (the file's ``iterations``).
* ``add:COARSE``, ``adef2:COARSE``, ``bnn:COARSE``: two levels, B as the first, the
  coarse space Z of COARSE, E = Z^T K Z (LU), Q = Z E^-1 Z^T: additive B^-1 + Q;
  A-DEF2 (I - Q K) B^-1 + Q, applied as y = B^-1 r, y + Q (r - K y) (one K product more);
  balanced (I - Q K) B^-1 (I - K Q) + Q (two).  COARSE: ``agg``: every wisp cut into
  chunks of L (``--chunk``) vertices, chunks joined by contact (C's blocks between them,
  summed Frobenius norms at least ``--theta`` times the strongest) merged strongest first
  into aggregates of at most M (``--agg-cap``) chunks; translations as the near-null
  space; ``aggrot`` the same with rotations about each aggregate's centre; ``chunk`` the
  chunks alone (M = 1); a trailing ``s`` (``aggs``) smooths Z once with the point-block
  Jacobi of K (smoothed aggregation).  ``@LxM`` overrides L and M for this variant.
* ``ilu``: the wisps grouped into clusters (connected components of the wisp contact
  graph, merged strongest first up to ``--cluster-wisps`` wisps), each cluster's block of
  A + C (inside it) factored incompletely (SuperLU's ILUTP without pivoting, ``--ilu-drop``,
  ``--ilu-fill``), the other wisps by B; ``exact``: the same clusters factored exactly
  (the cluster PC with ``-lc_cluster_min_captured 0``, this wisp cap and no block cap,
  but clustered by this script's greedy merge, not ``contact_pc.cluster_labels``).

Per variant it prints: iterations; the smallest and largest Ritz values of the
preconditioned operator (from CG's coefficients); extra (coarse) unknowns; set-up work
(the extra factor's entries and flops, the Galerkin product's flops); the bytes read per CG
iteration (operator product, preconditioner and vectors) relative to ``blocks``; and a
predicted time per system: ``T = T_setup + its * t_it * bytes / bytes_blocks + work /
FLOPS`` with the default's measured set-up ``--t-setup`` and time per CG iteration
``--t-it`` (2 ranks) and a factorisation rate ``--flops`` (see the docs section).
"""

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.sparse import linalg as spla

#: bytes of one stored double entry with its column index (CSR/BSR values and indices)
ENTRY = 12
#: vectors of n doubles read or written per CG iteration beside the products (x, r, z, p,
#: K p and the dot products: about 10 streams)
CG_VECTORS = 10


def load_system(path):
    """scripts/dump_system.py's reader (the .npz of one Newton system)."""
    spec = importlib.util.spec_from_file_location("dump_system", Path(__file__).with_name("dump_system.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.load_system(path)


def row_wisps(wisp_rows):
    """The wisp of every row."""
    return np.repeat(np.arange(len(wisp_rows)), wisp_rows)


def pcg(K, b, apply, rtol=1e-4, max_it=1000, coeffs=None):
    """PCG from x0 = 0 with PETSc's KSPCG test (preconditioned norm): stops at the first
    iteration k with ||z_k|| <= rtol ||z_0||.  Returns (x, k, ||z_k|| / ||z_0||); CG's
    (alpha, beta) of every iteration are appended to the list ``coeffs`` if given."""
    x = np.zeros_like(b)
    r = b.copy()
    z = apply(r)
    z0 = np.linalg.norm(z)
    p = z.copy()
    rz = r @ z
    for k in range(max_it + 1):
        zn = np.linalg.norm(z)
        if zn <= rtol * z0 or k == max_it:
            return x, k, zn / z0
        q = K @ p
        pq = p @ q
        if pq <= 0:
            raise ValueError(f"CG: p^T K p = {pq:g} <= 0 at iteration {k} (K or the "
                             "preconditioner is not positive definite)")
        a = rz / pq
        x += a * p
        r -= a * q
        z = apply(r)
        rz_new = r @ z
        if coeffs is not None:
            coeffs.append((a, rz_new / rz))
        p = z + (rz_new / rz) * p
        rz = rz_new
    raise AssertionError("unreachable")


def ritz_values(coeffs):
    """The Ritz values of the preconditioned operator from CG's (alpha, beta): the
    eigenvalues of the Lanczos tridiagonal matrix."""
    if not coeffs:
        return np.zeros(0)
    a, b = np.array(coeffs).T
    diag = 1.0 / a + np.r_[0.0, b[:-1] / a[:-1]]
    off = np.sqrt(b[:-1]) / a[:-1]
    return np.linalg.eigvalsh(np.diag(diag) + np.diag(off, 1) + np.diag(off, -1))


def lu_work(lu):
    """(factor entries, flops) of a SuperLU factor: flops ~ 2 sum_j |L_:j| |U_j:|."""
    L, U = lu.L.tocsc(), lu.U.tocsr()
    entries = L.nnz + U.nnz
    return entries, 2.0 * float(np.diff(L.indptr).astype(float) @ np.diff(U.indptr).astype(float))


def block_jacobi(A, C, wisp_rows):
    """B = A + C's blocks within a wisp (self-contact) and its LU (SuperLU, its own
    ordering: a wisp's band, or band + self-contact blocks, factors with little fill)."""
    w = row_wisps(wisp_rows)
    Cc = C.tocoo()
    inside = w[Cc.row] == w[Cc.col]
    B = (A.tocsr() + sparse.csr_matrix((Cc.data[inside], (Cc.row[inside], Cc.col[inside])),
                                       shape=A.shape)).tocsc()
    return B, spla.splu(B, permc_spec="MMD_AT_PLUS_A")


def block_norms(M):
    """(block row, block column, Frobenius norm) of the 3x3 blocks of the BSR ``M``."""
    M = M.tobsr(blocksize=(3, 3))
    rows = np.repeat(np.arange(M.shape[0] // 3), np.diff(M.indptr))
    return rows, M.indices.copy(), np.sqrt((M.data ** 2).sum(axis=(1, 2)))


def greedy_groups(n, i, j, weight, cap):
    """Union-find over n items joining (i, j) in order of decreasing weight, a join refused
    when the group would exceed ``cap`` items: the group label of every item."""
    parent = np.arange(n)
    size = np.ones(n, np.int64)

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a
    for e in np.argsort(-weight, kind="stable"):
        a, b = find(i[e]), find(j[e])
        if a != b and size[a] + size[b] <= cap:
            if size[a] < size[b]:
                a, b = b, a
            parent[b] = a
            size[a] += size[b]
    return np.array([find(a) for a in range(n)])


def aggregates(C, wisp_rows, chunk, cap, theta=0.0):
    """Vertex aggregates: every wisp cut into chunks of ``chunk`` consecutive vertices,
    then chunks joined by contact (the summed Frobenius norms of C's blocks between them,
    at least ``theta`` times the largest) merged strongest first into aggregates of at
    most ``cap`` chunks (``cap`` 1: the chunks alone).  Returns the aggregate of every
    vertex (0..n-1) and the number of chunks in aggregates of several."""
    vw = row_wisps(np.asarray(wisp_rows) // 3)
    first = np.r_[0, np.cumsum(np.asarray(wisp_rows) // 3)][vw]
    pos = np.arange(len(vw)) - first
    per_wisp = -(-(np.asarray(wisp_rows) // 3) // chunk)
    chunk_of = np.r_[0, np.cumsum(per_wisp)][vw] + pos // chunk
    n_chunks = int(per_wisp.sum())
    if cap <= 1:
        return chunk_of, 0
    r, c, nrm = block_norms(C)
    a, b = chunk_of[r], chunk_of[c]
    keep = (a < b) & (nrm > 0)
    pairs, inv = np.unique(np.stack([a[keep], b[keep]], axis=1), axis=0, return_inverse=True)
    weight = np.bincount(inv.ravel(), nrm[keep])
    strong = weight >= theta * weight.max()
    labels = greedy_groups(n_chunks, pairs[strong, 0], pairs[strong, 1], weight[strong], cap)
    labels = np.unique(labels, return_inverse=True)[1]
    merged = int((np.bincount(labels)[labels] > 1).sum())
    return labels[chunk_of], merged


def coarse_space(labels, x=None, rotations=False):
    """Z (3 nv x coarse) of the aggregates ``labels``: the 3 translations of each, and with
    ``rotations`` the 3 rotations about its centre (positions ``x``), orthonormalised per
    aggregate (dependent columns dropped)."""
    nv = len(labels)
    if not rotations:
        rows = np.arange(3 * nv)
        return sparse.csr_matrix((np.ones(3 * nv), (rows, 3 * labels.repeat(3) + np.tile([0, 1, 2], nv))),
                                 shape=(3 * nv, 3 * (labels.max() + 1)))
    order = np.argsort(labels, kind="stable")
    bounds = np.flatnonzero(np.r_[True, np.diff(labels[order]) != 0, True])
    R, Cl, V = [], [], []
    col = 0
    for s, e in zip(bounds[:-1], bounds[1:]):
        v = order[s:e]
        d = x[v] - x[v].mean(axis=0)
        cols = [np.tile(np.eye(3)[k], len(v)) for k in range(3)]
        if len(v) > 1:
            cols += [np.cross(np.eye(3)[k], d).ravel() for k in range(3)]
        q, rr = np.linalg.qr(np.array(cols).T)
        keep = np.abs(np.diag(rr)) > 1e-8 * np.abs(rr).max()
        q = q[:, keep]
        dofs = (3 * v[:, None] + np.arange(3)).ravel()
        R.append(np.repeat(dofs, q.shape[1]))
        Cl.append(np.tile(col + np.arange(q.shape[1]), len(dofs)))
        V.append(q.ravel())
        col += q.shape[1]
    return sparse.csr_matrix((np.concatenate(V), (np.concatenate(R), np.concatenate(Cl))),
                             shape=(3 * nv, col))


def smooth(Z, K, omega_scale=4.0 / 3.0):
    """One point-block Jacobi step on the columns of Z: (I - w D^-1 K) Z, D K's 3x3
    diagonal blocks, w = omega_scale / lambda_max(D^-1 K) (power iterations)."""
    nv = K.shape[0] // 3
    Kb = K.tobsr(blocksize=(3, 3))
    D = np.zeros((nv, 3, 3))
    rows = np.repeat(np.arange(nv), np.diff(Kb.indptr))
    on = rows == Kb.indices
    D[rows[on]] = Kb.data[on]
    Dinv = sparse.block_diag(np.linalg.inv(D), format="csr")
    DK = Dinv @ K
    v = np.random.default_rng(0).standard_normal(K.shape[0])
    for _ in range(20):
        v = DK @ v
        lam = np.linalg.norm(v)
        v /= lam
    return (Z - (omega_scale / lam) * (DK @ Z)).tocsr()


def wisp_clusters(C, wisp_rows, cap):
    """Wisp labels of clusters: coupled wisps joined strongest first (summed Frobenius
    norms of their cross blocks) up to ``cap`` wisps."""
    vw = row_wisps(np.asarray(wisp_rows) // 3)
    r, c, nrm = block_norms(C)
    a, b = vw[r], vw[c]
    keep = a < b
    pairs, inv = np.unique(np.stack([a[keep], b[keep]], axis=1), axis=0, return_inverse=True)
    weight = np.bincount(inv.ravel(), nrm[keep])
    return greedy_groups(len(wisp_rows), pairs[:, 0], pairs[:, 1], weight, cap)


KINDS = ("blocks", "add", "adef2", "bnn", "ilu", "exact")
COARSE = ("agg", "aggrot", "chunk")


def parse_variant(name):
    """(kind, coarse space, smoothed, chunk, cap) of a variant name (module doc); chunk and
    cap are None unless the name gives them (``@CHUNKxCAP``)."""
    base, _, size = name.partition("@")
    kind, _, coarse = base.partition(":")
    two_level = kind in ("add", "adef2", "bnn")
    chunk = cap = None
    try:
        if size:
            chunk, cap = (int(v) for v in size.split("x"))
    except ValueError:
        chunk = -1
    if (kind not in KINDS or two_level != (coarse.removesuffix("s") in COARSE) or (coarse and not two_level)
            or (size and (not two_level or chunk is None or chunk < 1 or cap < 1))):
        raise ValueError(f"unknown variant {name!r}: blocks, ilu, exact, or add:/adef2:/bnn: with a "
                         "coarse space agg, aggrot or chunk (a trailing s: smoothed) and optionally "
                         "@CHUNKxCAP, e.g. adef2:aggs@16x8")
    return kind, coarse.removesuffix("s"), coarse.endswith("s"), chunk, cap


class Variant:
    """One preconditioner: ``apply(r)``, ``extra`` unknowns, set-up ``entries``/``flops``
    beyond the per-wisp blocks, ``bytes`` read per CG iteration (product, PC, vectors)."""

    def __init__(self, name, apply, bytes_it, extra=0, entries=0, flops=0.0, note=""):
        self.name, self.apply, self.bytes = name, apply, bytes_it
        self.extra, self.entries, self.flops, self.note = extra, entries, flops, note


def product_bytes(K):
    """Bytes of one symmetric product by K (the upper triangle's entries, as the run's
    compiled product reads them)."""
    return ENTRY * (sparse.triu(K).nnz)


def build_variants(names, sys_, opts):
    A, C, wisp_rows = sys_["A"].tocsr(), sys_["C"].tocsr(), sys_["wisp_rows"]
    K = (A + C).tocsr()
    n = K.shape[0]
    B, Blu = block_jacobi(A, C, wisp_rows)
    # the default's per-iteration bytes: the product, the per-wisp Cholesky (its lower
    # triangle: the compiled factor stores 3 blocks left of the diagonal and the diagonal
    # block's inverse per vertex) and the CG vectors
    b_prod = product_bytes(K)
    b_blocks = ENTRY * sparse.tril(B).nnz
    b_vec = 8 * CG_VECTORS * n
    base = b_prod + b_blocks + b_vec
    out = []
    for name in names:
        kind, cs, smoothed, chunk, cap = parse_variant(name)
        if kind == "blocks":
            out.append(Variant(name, Blu.solve, base))
        elif kind in ("add", "adef2", "bnn"):
            labels, n_agg = aggregates(C, wisp_rows, chunk or opts.chunk,
                                       1 if cs == "chunk" else cap or opts.agg_cap, opts.theta)
            Z = coarse_space(labels, sys_["x"], rotations=cs == "aggrot")
            if smoothed:
                Z = smooth(Z, K)
            KZ = K @ Z
            E = (Z.T @ KZ).tocsc()
            z_rows = np.diff(Z.indptr).astype(float)
            galerkin = 2.0 * (float(K.astype(bool).astype(float) @ z_rows @ np.ones(n))
                              + float(z_rows @ np.diff(KZ.indptr)))
            Elu = spla.splu(E, permc_spec="MMD_AT_PLUS_A")
            entries, flops = lu_work(Elu)
            Zt = Z.T.tocsr()

            def q(r, Z=Z, Zt=Zt, Elu=Elu):
                return Z @ Elu.solve(Zt @ r)
            coarse_bytes = 2 * ENTRY * Z.nnz + ENTRY * entries
            if kind == "add":
                def apply(r, q=q):
                    return Blu.solve(r) + q(r)
                extra_bytes = coarse_bytes
            elif kind == "adef2":
                def apply(r, q=q):
                    y = Blu.solve(r)
                    return y + q(r - K @ y)
                extra_bytes = coarse_bytes + b_prod
            else:
                def apply(r, q=q):
                    qr = q(r)
                    y = Blu.solve(r - K @ qr)
                    return y - q(K @ y) + qr
                extra_bytes = 2 * coarse_bytes + 2 * b_prod
            out.append(Variant(name, apply, base + extra_bytes, Z.shape[1], entries, flops + galerkin,
                               f"{labels.max() + 1} aggregates, {n_agg} chunks merged by contact, "
                               f"Z {Z.nnz} entries, E {E.nnz} entries"))
        else:
            labels = wisp_clusters(C, wisp_rows, opts.cluster_wisps)
            sizes = np.bincount(labels, minlength=len(wisp_rows))
            wl = row_wisps(wisp_rows)
            rows = np.flatnonzero(sizes[labels[wl]] > 1)
            rows = rows[np.argsort(labels[wl[rows]], kind="stable")]
            Cc = C.tocoo()
            keep = labels[wl[Cc.row]] == labels[wl[Cc.col]]
            P = (A + sparse.csr_matrix((Cc.data[keep], (Cc.row[keep], Cc.col[keep])), shape=A.shape)).tocsr()
            Pc = P[rows][:, rows].tocsc()
            if kind == "ilu":
                lu = spla.spilu(Pc, drop_tol=opts.ilu_drop, fill_factor=opts.ilu_fill,
                                permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0)
            else:
                lu = spla.splu(Pc, permc_spec="MMD_AT_PLUS_A")
            entries, flops = lu_work(lu)
            # the clusters' rows' band factor is not read (the compiled Cholesky skips them)
            band_rows = ENTRY * sparse.tril(B[rows][:, rows]).nnz

            def apply(r, lu=lu, rows=rows):
                z = Blu.solve(r)
                z[rows] = lu.solve(r[rows])
                return z
            out.append(Variant(name, apply, base - band_rows + ENTRY * entries, 0, entries, flops,
                               f"{int((sizes > 1).sum())} clusters, {len(rows)} rows, largest "
                               f"{sizes.max()} wisps, P's cluster block {Pc.nnz} entries"))
    return out, {"n": n, "bytes_blocks": base, "bytes_product": b_prod, "bytes_pc": b_blocks,
                 "bytes_vectors": b_vec, "B_entries": B.nnz}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("systems", nargs="+")
    ap.add_argument("--variants", nargs="+", default=["blocks"])
    ap.add_argument("--rtol", type=float, default=1e-4)
    ap.add_argument("--max-it", type=int, default=1000)
    ap.add_argument("--theta", type=float, default=0.0,
                    help="contact couplings joined: at least theta times the strongest (agg)")
    ap.add_argument("--agg-cap", type=int, default=8, help="chunks per contact aggregate (agg)")
    ap.add_argument("--chunk", type=int, default=16, help="vertices per along-wisp chunk")
    ap.add_argument("--cluster-wisps", type=int, default=64, help="wisps per cluster (ilu, exact)")
    ap.add_argument("--ilu-drop", type=float, default=1e-3)
    ap.add_argument("--ilu-fill", type=float, default=4.0)
    ap.add_argument("--t-setup", type=float, default=0.17,
                    help="the default's set-up per system, s (measured: 0.51 s / 3 systems)")
    ap.add_argument("--t-it", type=float, default=2.41 / 135,
                    help="the default's time per CG iteration, s (measured: 2.41 s / 135)")
    ap.add_argument("--flops", type=float, default=1e9, help="factorisation rate, flop/s")
    ap.add_argument("--json", default=None)
    opts = ap.parse_args(argv)
    for name in opts.variants:
        parse_variant(name)
    results = []
    for path in opts.systems:
        sys_ = load_system(path)
        t0 = time.perf_counter()
        variants, info = build_variants(opts.variants, sys_, opts)
        print(f"{path}: {info['n']} rows, {len(sys_['wisp_rows'])} wisps, run's CG {sys_['iterations']}; "
              f"bytes per iteration (blocks) {info['bytes_blocks'] / 1e6:.1f} MB (product "
              f"{info['bytes_product'] / 1e6:.1f}, PC {info['bytes_pc'] / 1e6:.1f}, vectors "
              f"{info['bytes_vectors'] / 1e6:.1f}); set-up {time.perf_counter() - t0:.1f} s", flush=True)
        K = (sys_["A"] + sys_["C"]).tocsr()
        for v in variants:
            coeffs: list = []
            x, its, _ = pcg(K, sys_["b"], v.apply, opts.rtol, opts.max_it, coeffs)
            ritz = ritz_values(coeffs)
            res = np.linalg.norm(sys_["b"] - K @ x) / np.linalg.norm(sys_["b"])
            rel = v.bytes / info["bytes_blocks"]
            t = opts.t_setup + v.flops / opts.flops + its * opts.t_it * rel
            row = {"system": str(path), "variant": v.name, "iterations": its, "run_iterations": sys_["iterations"],
                   "extra_unknowns": v.extra, "factor_entries": v.entries, "setup_flops": v.flops,
                   "bytes_rel": rel, "predicted_s": t, "true_rel_residual": res, "note": v.note,
                   "ritz_smallest": ritz[:5].tolist(), "ritz_largest": ritz[-3:].tolist()}
            results.append(row)
            print(f"  {v.name:12s} its {its:4d}  extra {v.extra:7d}  factor {v.entries / 1e6:7.2f} M  "
                  f"flops {v.flops / 1e9:7.2f} G  bytes/it {rel:5.2f}x  predicted {t:6.3f} s  "
                  f"|r|/|b| {res:.1e}  Ritz {ritz[0]:.2e} .. {ritz[-1]:.2f}  {v.note}", flush=True)
    if opts.json:
        Path(opts.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
