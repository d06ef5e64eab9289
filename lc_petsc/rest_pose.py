"""Rest-pose check of strand contact: pairs of segments of different wisps (with
``physics.strand_self_contact`` also non-neighbouring segments of one wisp) that are
already closer than the contact thickness d0 in the groom.

Such pairs are interlocked or touching coils: the penalty cannot tell which side is
out, and the intersection-free mode (``physics.strand_contact_mode = "ccd"``) needs a
start in which every pair is at least d0 apart.  :func:`check_rest_pose` finds them
with the contact's own ghost exchange and broad phase (collective), and the simulator
builder stops with :class:`RestPoseOverlapError` unless ``physics.strand_rest_overlap =
"exempt"`` (those pairs then never interact, as in penalty mode; docs/contact.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lc_petsc.elements import segment_contact
from lc_petsc.errors import RestPoseOverlapError  # noqa: F401 - re-exported: the check's error type


@dataclass
class RestPoseReport:
    """What the rest-pose check found: pairs of segments of different wisps (and, with
    self-contact, of one wisp) closer than the contact thickness, and the closest pair."""

    thickness: float
    pairs: int                       # pairs closer than the thickness, over all ranks
    min_distance: float              # inf when no pair is within the search radius
    worst: tuple = ()                # (wisp A, vertex A, wisp B, vertex B): first vertices
                                     # (global indices) of the closest pair's segments
    self_contact: bool = False       # pairs of one wisp were checked too
    thickness_default: bool = False  # the thickness was not set: twice the smallest radius

    def message(self) -> str:
        """The report for a person: count, closest pair (wisps, vertices), distance."""
        wa, va, wb, vb = self.worst
        which, fold = ("of different wisps or of one wisp (not neighbours along it)",
                       " or physics.strand_self_contact = false (for a wisp folded onto itself)") \
            if self.self_contact else ("of different wisps", "")
        why = (" (physics.strand_thickness is not set: twice the scene's smallest vertex "
               "radius)") if self.thickness_default else ""
        return (f"rest pose: {self.pairs} pair(s) of segments {which} are closer than "
                f"the contact thickness {self.thickness:g} cm{why}; the closest: wisp {wa} segment "
                f"(vertices {va}, {va + 1}) and wisp {wb} segment (vertices {vb}, {vb + 1}), "
                f"{self.min_distance:.3g} cm apart (global vertex indices).  Untangle the groom "
                f"(e.g. give neighbouring coils the same phase), lower physics.strand_thickness "
                f"below that distance, or set physics.strand_rest_overlap = \"exempt\" to let "
                f"these pairs pass through each other{fold}")


def check_rest_pose(strand) -> RestPoseReport:
    """Pairs closer than the thickness in the rest pose of a
    :class:`lc_petsc.contact.StrandContact`'s scene, over all ranks.  Collective."""
    comm, d0 = strand.comm, strand.d0
    (P,), _, gv, wisp, _, _, n_local = strand._gather_segments(strand.scene.x_rest)
    ij = strand.candidates(P, wisp, n_local, d0, **strand.self_pairs(len(P)))
    i, j = ij[:, 0], ij[:, 1]
    d = segment_contact.distance(np.concatenate([P[i], P[j]], axis=1)) if len(ij) else np.zeros(0)
    close = d < d0
    n = comm.allreduce(int(close.sum()))
    k = int(np.argmin(d)) if len(d) else -1
    mine = (float(d[k]), int(min(gv[i[k]], gv[j[k]])), int(max(gv[i[k]], gv[j[k]]))) if k >= 0 \
        else (np.inf, -1, -1)
    local_worst = (mine[0], mine[1], mine[2],
                   int(wisp[i[k]] if gv[i[k]] < gv[j[k]] else wisp[j[k]]) if k >= 0 else -1,
                   int(wisp[j[k]] if gv[i[k]] < gv[j[k]] else wisp[i[k]]) if k >= 0 else -1)
    best = min(comm.allgather(local_worst))          # the same on every rank
    dmin, va, vb, wa, wb = best
    return RestPoseReport(thickness=d0, pairs=n, min_distance=float(dmin),
                          worst=(wa, va, wb, vb) if np.isfinite(dmin) else (),
                          self_contact=strand.self_contact)
