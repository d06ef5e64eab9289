"""Rest-pose check of strand contact: pairs of segments of different wisps (with
``physics.strand_self_contact`` also non-neighbouring segments of one wisp) that are
already closer than the contact thickness d0 in the groom.

Such pairs are interlocked or touching coils: the penalty cannot tell which side is
out, and the intersection-free mode (``physics.strand_contact_mode = "ccd"``) needs a
start in which every pair is at least d0 apart.  :func:`check_rest_pose` finds them
with the contact's own ghost exchange and broad phase (collective), and the simulator
builder stops with :class:`RestPoseOverlapError` unless ``physics.strand_rest_overlap =
"exempt"`` (those pairs then never interact, as in penalty mode; docs/contact.md).

The initial state a ``scene.perturbation`` makes is checked too
(:func:`check_start_pose`, :class:`StartOverlapError`): pairs apart at rest that pass
through each other on the straight way from the rest pose to it are a tangle the ccd
limiter would then hold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lc_petsc.elements import segment_contact
from lc_petsc.errors import RestPoseOverlapError, StartOverlapError  # noqa: F401 - re-exported: the checks' error types


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
                       ", or physics.strand_self_contact = false for a wisp folded onto itself (its segments then "
                       "do not touch each other at all: it may pass through itself anywhere, not only there)") \
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


def _closest(comm, d, i, j, gv, wisp):
    """(distance, wisp A, first vertex A, wisp B, first vertex B) of the closest of the
    pairs (i, j) at distances ``d`` over all ranks (the segment with the smaller global
    vertex first; inf and -1 where no rank has one): the same on every rank."""
    if len(d):
        k = int(np.argmin(d))
        a, b = (i[k], j[k]) if gv[i[k]] < gv[j[k]] else (j[k], i[k])
        mine = (float(d[k]), int(gv[a]), int(gv[b]), int(wisp[a]), int(wisp[b]))
    else:
        mine = (np.inf, -1, -1, -1, -1)
    dmin, va, vb, wa, wb = min(comm.allgather(mine))
    return dmin, wa, va, wb, vb


def check_rest_pose(strand) -> RestPoseReport:
    """Pairs closer than the thickness in the rest pose of a
    :class:`lc_petsc.contact.StrandContact`'s scene, over all ranks.  Collective."""
    comm, d0 = strand.comm, strand.d0
    (P,), _, gv, wisp, _, _, n_local = strand._gather_segments(strand.scene.x_rest)
    ij = strand.candidates(P, wisp, n_local, d0, **strand.self_pairs(len(P)))
    i, j = ij[:, 0], ij[:, 1]
    d = segment_contact.distance(np.concatenate([P[i], P[j]], axis=1)) if len(ij) else np.zeros(0)
    n = comm.allreduce(int((d < d0).sum()))
    dmin, wa, va, wb, vb = _closest(comm, d, i, j, gv, wisp)
    return RestPoseReport(thickness=d0, pairs=n, min_distance=float(dmin),
                          worst=(wa, va, wb, vb) if np.isfinite(dmin) else (),
                          self_contact=strand.self_contact)


@dataclass
class StartReport:
    """What the start-state check found: pairs of segments (of different wisps, with
    self-contact also of one wisp) at least the thickness apart at rest that pass through
    each other (or touch) on the straight way from the rest pose to the initial state,
    and the closest of them in the initial state."""

    thickness: float
    pairs: int
    min_distance: float
    worst: tuple = ()                # as RestPoseReport.worst
    self_contact: bool = False
    made_by: str = ""                # what made the start: the perturbation and its size
    smaller: str = "make the perturbation smaller"

    def message(self, exempt=False) -> str:
        """The report for a person: count, the closest pair, what to change (``exempt``:
        the run goes on, with ``physics.strand_rest_overlap = "exempt"``)."""
        wa, va, wb, vb = self.worst
        fix = (f"{self.smaller}, run the scene without strand contact (remove \"strand_collision\" from "
               f"physics.terms, as the SPEC's smash, jitter and straighten scenes do), or set "
               f"physics.strand_rest_overlap = \"exempt\" to run it anyway (these pairs are not "
               f"exempt: the contact holds them where the initial state put them)")
        if exempt:
            fix = (f"run anyway, as physics.strand_rest_overlap = \"exempt\" asks (it exempts pairs closer than "
                   f"the contact thickness at rest, not these: the contact holds them where the initial state put "
                   f"them); {self.smaller}, or run the scene without strand contact, to avoid it")
        which = "of different wisps or of one wisp" if self.self_contact else "of different wisps"
        return (f"the initial state ({self.made_by}) is tangled: {self.pairs} pair(s) of segments {which}, "
                f"at least the contact thickness {self.thickness:g} cm apart in the rest pose, pass "
                f"through each other (or touch) on the straight way from the rest pose to the initial "
                f"state; the closest there: wisp {wa} segment (vertices {va}, {va + 1}) and wisp {wb} "
                f"segment (vertices {vb}, {vb + 1}), {self.min_distance:.3g} cm apart (global vertex "
                f"indices).  Strand contact in \"ccd\" mode lets no pair pass through another from the "
                f"start on, so such pairs stay on the side the initial state put them (a tangle held "
                f"over the run: strands through strands, edges stretched): {fix}")


def check_start_pose(strand, x0, made_by="", smaller=None) -> StartReport:
    """Pairs of segments of a :class:`lc_petsc.contact.StrandContact`'s scene that are at
    least the thickness d0 apart at rest (closer ones are the rest check's: refused or
    exempt) and meet on the straight way from the rest pose to this rank's initial
    positions ``x0`` (nv, 3) (Tight-Inclusion at distance 0,
    :func:`lc_petsc.crossings.crossing_pairs`; a pair touching in ``x0`` meets).
    Pairs merely closer than d0 in ``x0`` are no tangle: the contact pushes them apart
    towards the rest pose.  ``smaller``: what to change, or a callable of ``first``, the
    fraction of the way at which the first of those pairs meets (Tight-Inclusion's time,
    a lower bound; the smallest over the ranks), giving it (a jitter's and a smash's starts lie on the straight
    way to a larger one, so the way's first meeting gives the largest that passes).
    Collective: the contact's ghost exchange over both poses, each pair judged on one
    rank."""
    from lc_petsc.crossings import crossing_pairs
    from lc_petsc.elements.segment_ccd import tight_inclusion_toi
    from lc_petsc.parallel import global_min
    comm, d0 = strand.comm, strand.d0
    (R, S), _, gv, wisp, _, _, n_local = strand._gather_segments(strand.scene.x_rest, extra=(x0,))
    # the boxes swept from the rest pose to the start: every pair that meets on the way
    RS = np.concatenate([R, S], axis=1)
    ij = strand.candidates(np.stack([RS.min(axis=1), RS.max(axis=1)], axis=1), wisp, n_local, d0,
                           **strand.self_pairs(len(R)))
    i, j = ij[:, 0], ij[:, 1]
    XR, XS = np.concatenate([R[i], R[j]], axis=1), np.concatenate([S[i], S[j]], axis=1)
    judged = segment_contact.distance(XR) >= d0 if len(ij) else np.zeros(0, bool)
    i, j, XR, XS = i[judged], j[judged], XR[judged], XS[judged]
    crossed = crossing_pairs(XR, XS) if len(i) else np.zeros(0, bool)
    d = segment_contact.distance(XS[crossed]) if crossed.any() else np.zeros(0)
    n = comm.allreduce(int(crossed.sum()))
    dmin, wa, va, wb, vb = _closest(comm, d, i[crossed], j[crossed], gv, wisp)
    t = tight_inclusion_toi(XR[crossed], XS[crossed], 0.0)[1] if crossed.any() else np.ones(0)
    first = global_min(comm, float(t.min(initial=1.0)))
    if callable(smaller):
        smaller = smaller(first)
    return StartReport(thickness=d0, pairs=n, min_distance=float(dmin),
                       worst=(wa, va, wb, vb) if np.isfinite(dmin) else (),
                       self_contact=strand.self_contact, made_by=made_by,
                       **({"smaller": smaller} if smaller else {}))
