"""The contact preconditioner's greedy clustering (:func:`lc_petsc.contact_pc.cluster_labels`),
compiled (Numba).

Every rank computes the same clusters from the global contact graph (``-lc_cluster_span
global``, lc_petsc/contact_pc.py), so this set-up is not divided by the ranks.  As a
Python loop over the coupled wisp pairs, with a dict of the cross blocks between
clusters, it took 22 ms per preconditioner set-up of a late 2K ccd frame, the same on
each of 2 ranks (docs/performance.md, "What the second rank repeats").

Here the blocks between two clusters are summed when a merge asks for them, over the
pairs at the members of the smaller cluster (a cluster holds at most ``max_wisps``
wisps), instead of being kept up to date by every merge: integer sums, the same
clusters as the dict version.
"""

from __future__ import annotations

import numpy as np

from lc_petsc.elements.compiled import _jit


@_jit
def _find(parent, w):
    while parent[w] != w:
        parent[w] = parent[parent[w]]
        w = parent[w]
    return w


@_jit
def _blocks_between(parent, head, nxt, adj_ptr, adj_wisp, adj_count, s, t, limit):
    """Cross blocks of the pairs between the clusters of roots s and t, over the pairs at
    the members of s (its member list: ``head``, ``nxt``); any value above ``limit`` once
    the sum passes it (the merge is refused then whatever the rest)."""
    total = 0
    w = head[s]
    while w >= 0:
        for e in range(adj_ptr[w], adj_ptr[w + 1]):
            if _find(parent, adj_wisp[e]) == t:
                total += adj_count[e]
                if total > limit:
                    return total
        w = nxt[w]
    return total


@_jit
def cluster_roots(n, pairs, counts, order, max_wisps, max_blocks, inner):
    """The root of every wisp's cluster (n,), the smallest wisp of the cluster: the merge
    of :func:`lc_petsc.contact_pc.cluster_labels` over ``pairs`` (m, 2, each wisp pair
    once) in the order ``order`` (m,), with ``counts`` (m,) their cross blocks and
    ``inner`` (n,) each wisp's own blocks (changed: the clusters' blocks at their roots)."""
    m = len(order)
    # the pairs at each wisp (both ends), for the blocks between two clusters
    deg = np.zeros(n + 1, np.int64)
    for e in range(m):
        deg[pairs[e, 0] + 1] += 1
        deg[pairs[e, 1] + 1] += 1
    adj_ptr = np.cumsum(deg)
    fill = adj_ptr[:-1].copy()
    adj_wisp = np.empty(2 * m, np.int64)
    adj_count = np.empty(2 * m, np.int64)
    for e in range(m):
        a, b = pairs[e, 0], pairs[e, 1]
        adj_wisp[fill[a]] = b
        adj_count[fill[a]] = counts[e]
        fill[a] += 1
        adj_wisp[fill[b]] = a
        adj_count[fill[b]] = counts[e]
        fill[b] += 1
    parent = np.arange(n)
    size = np.ones(n, np.int64)
    pairs_at = np.diff(adj_ptr)         # pairs at a cluster's members (inside ones twice)
    head = np.arange(n)                 # members of a root's cluster: a linked list
    tail = np.arange(n)
    nxt = np.full(n, -1, np.int64)
    for k in range(m):
        e = order[k]
        ra = _find(parent, pairs[e, 0])
        rb = _find(parent, pairs[e, 1])
        if ra == rb or size[ra] + size[rb] > max_wisps:
            continue
        room = max_blocks - inner[ra] - inner[rb]
        if room < 0:
            continue
        # over the cluster with fewer pairs at its members
        if pairs_at[ra] <= pairs_at[rb]:
            between = _blocks_between(parent, head, nxt, adj_ptr, adj_wisp, adj_count, ra, rb, room)
        else:
            between = _blocks_between(parent, head, nxt, adj_ptr, adj_wisp, adj_count, rb, ra, room)
        if between > room:
            continue
        joined = inner[ra] + inner[rb] + between
        if rb < ra:
            ra, rb = rb, ra
        parent[rb] = ra
        size[ra] += size[rb]
        pairs_at[ra] += pairs_at[rb]
        inner[ra] = joined
        nxt[tail[ra]] = head[rb]
        tail[ra] = tail[rb]
    roots = np.empty(n, np.int64)
    for w in range(n):
        roots[w] = _find(parent, w)
    return roots


@_jit
def point_csr(indptr, cols, blocks, point_indptr, point_cols, values):
    """Fill the point (AIJ) CSR (``point_indptr`` (3 n + 1,), ``point_cols`` and
    ``values`` (9 k,)) of the block CSR (``indptr`` (n + 1,), ``cols`` (k,): 3x3
    ``blocks`` (k, 3, 3) row-major): each block row's three point rows hold its blocks'
    rows in column order, explicit zeros kept, as PETSc's ``MatConvert`` of the BAIJ
    matrix gives them (lc_petsc/contact_pc.py, ``factor_cluster_matrix``)."""
    point_indptr[0] = 0
    for i in range(len(indptr) - 1):
        a, b = indptr[i], indptr[i + 1]
        width = 3 * (b - a)
        for r in range(3):
            base = 9 * a + r * width
            point_indptr[3 * i + r + 1] = base + width
            for e in range(a, b):
                p = base + 3 * (e - a)
                for j in range(3):
                    point_cols[p + j] = 3 * cols[e] + j
                    values[p + j] = blocks[e, r, j]


def warm_up():
    """Compile (or load from the cache) the kernels."""
    cluster_roots(2, np.array([[0, 1]], np.int64), np.ones(1, np.int64), np.zeros(1, np.int64),
                  2, 10, np.zeros(2, np.int64))
    for index in (np.int32, np.int64):          # PETSc's IntType, either build
        point_csr(np.array([0, 1], index), np.zeros(1, index), np.zeros((1, 3, 3)),
                  np.zeros(4, index), np.zeros(9, index), np.zeros(9))
