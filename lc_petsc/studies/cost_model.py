"""The trade-off study's cost model: deterministic work counts priced by the measured times.

A study's measured costs are noisy: on this shared 2-core machine one setting's CPU
seconds spread by up to 1.6x between two copies in one run (docs/studies.md), so picking
the cheapest measured row picked by the noise (hairball10, target 0.03: ``linear N=2`` in
one run, ``uncarried N=2`` in the next, the same 60 Newton iterations).  Here a row's
cost is its work (Newton iterations plus Krylov iterations per simulated second, counts
that are the same in every run) times the price of one unit of work, one price per
group of settings that changes what an iteration costs (:data:`PRICE_KEYS`), calibrated
as the median of the group's measured cost per unit of work.  Rows of one group are
then ordered by their counts alone; groups by a median over their rows.  Used by
:func:`lc_petsc.studies.tradeoff.recommend`.
"""

from __future__ import annotations

import statistics

#: the settings that change the price of one Newton or Krylov iteration: the element
#: Hessians' filter (the numerical one costs ~10x per iteration), the trust region (its
#: own solves), the line search (energy evaluations), the solver set (the preconditioner)
PRICE_KEYS = ("filter", "newton", "line_search", "options")
#: modelled costs within this fraction of the lowest are a tie, won by the lower error.
#: Within a price group costs are exact ratios of counts; between groups they are ratios
#: of medians of noisy times: replayed on the ten recorded studies of 2026-12-07 (two runs
#: each), 10% still swapped a pick between groups (hairball10 0.01: trust_region N=3 /
#: dt 1/60, 0.256 / 0.263 in one run, 0.211 / 0.245 in the other), 20% another (Smash's
#: 0.1 and 0.03 in the fourth-to-tenth-round axes), 25% none
COST_TIE = 0.25


def work_per_sim_s(row):
    """Newton plus Krylov iterations per simulated second of ``row`` (None when the
    row lacks the counts): one Newton iteration assembles and factorises, one Krylov
    iteration is a product and a preconditioner application."""
    n, k, frames, dt = (row.get(x) for x in ("newton_total", "ksp_total", "frames_run", "dt"))
    if n is None or k is None or not frames or not dt:
        return None
    return (n + k) / (frames * dt)


def price_group(row):
    """The settings of ``row`` that set the price of its work (:data:`PRICE_KEYS`)."""
    return tuple(row.get(k) for k in PRICE_KEYS)


def modelled_costs(rows, cost):
    """[modelled cost per row of ``rows``]: work per simulated second times its group's
    price, the median of measured ``cost`` per unit of work over the group's stable rows
    (copies of another row, ``same_as``, counted once).  A row without the counts, or
    in a group with no priced row, keeps its measured cost."""
    ratios: dict[tuple, list[float]] = {}
    for r in rows:
        w = work_per_sim_s(r)
        if r.get("stable") and not r.get("same_as") and w and r.get(cost):
            ratios.setdefault(price_group(r), []).append(r[cost] / w)
    price = {g: statistics.median(v) for g, v in ratios.items()}
    out = []
    for r in rows:
        w = work_per_sim_s(r)
        g = price_group(r)
        out.append(price[g] * w if w is not None and g in price else r.get(cost))
    return out


def cheapest(candidates, error, tie=COST_TIE):
    """The pick among ``candidates`` [(modelled cost, row)]: of those within ``tie`` of
    the lowest modelled cost, the lowest ``error``, then the lowest modelled cost, then
    the variant's name (a total order: the same rows give the same pick)."""
    low = min(c for c, _ in candidates)
    tied = [(c, r) for c, r in candidates if c <= (1 + tie) * low]
    return min(tied, key=lambda cr: (cr[1][error], cr[0], cr[1]["variant"]))
