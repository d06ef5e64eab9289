"""Outputs of the studies: CSV, JSON, markdown tables and PNG plots (matplotlib, Agg)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np


def _clean(v):
    if isinstance(v, (np.floating, np.integer)):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None if math.isnan(v) else ("inf" if v > 0 else "-inf")
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    return v


def write_csv(rows, path, columns=None):
    """Rows (dicts) to CSV; columns: ``columns`` first, then any other key in order seen."""
    cols = list(columns or [])
    for r in rows:
        for k in r:
            if k not in cols:
                cols.append(k)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: _fmt_csv(r.get(k)) for k in cols})
    return cols


def _fmt_csv(v):
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, (list, tuple, dict)):
        return json.dumps(_clean(v))
    return v


def write_json(obj, path):
    """Write ``obj`` as JSON to ``path``."""
    Path(path).write_text(json.dumps(_clean(obj), indent=1) + "\n")


def fmt(v, digits=3):
    """``v`` as a short table cell (``-`` for None, scientific notation for very small or large)."""
    if v is None:
        return "-"
    if isinstance(v, float):
        if not math.isfinite(v):
            return str(v)
        if v != 0 and (abs(v) < 1e-3 or abs(v) >= 1e5):
            return f"{v:.{digits - 1}e}"
        return f"{v:.{digits}g}"
    return str(v)


def markdown_table(header, rows):
    """A markdown table of ``header`` and ``rows``."""
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out) + "\n"


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def plot_time_vs_size(summary, path, key="total_s", title="Newton-system solve time"):
    """Log-log time (summed over the recorded systems) against wisp count, one line per
    set; sets stopped by the time budget are drawn as open markers at the budget (a
    lower bound)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 5))
    sets = list(dict.fromkeys(r["set"] for r in summary))
    for name in sets:
        rs = sorted((r for r in summary if r["set"] == name), key=lambda r: r["wisps"])
        ok = [(r["wisps"], r[key]) for r in rs if r["status"] == "ok" and r.get(key)]
        lb = [(r["wisps"], r.get("time_spent_s") or r.get("budget_s")) for r in rs
              if r["status"] == "budget" and (r.get("time_spent_s") or r.get("budget_s") or 0) > 0]
        line = None
        if ok:
            line, = ax.plot(*zip(*ok), "o-", label=name)
        if lb:
            color = line.get_color() if line is not None else None
            ax.plot(*zip(*lb), "o", mfc="none", color=color,
                    label=None if line is not None else f"{name} (budget)")
    if ax.lines:
        ax.set_xscale("log")
        ax.set_yscale("log")
    ax.set_xlabel("wisps")
    ax.set_ylabel("setup + solve time of the recorded Newton systems (s)")
    ax.set_title(title + " (open markers: stopped by the time budget)")
    ax.grid(True, which="both", alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no set finished within the budget", ha="center", transform=ax.transAxes)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def pareto_front(points):
    """Indices of the Pareto-optimal (cost, error) points (both minimised)."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


# 12 markers against matplotlib's 10 colours: the (marker, colour) pairs repeat only
# after 60 axes (with 10 markers the study's 11th axis looked exactly like its first)
MARKERS = "os^vD<>ph*XP"


def axis_styles(n):
    """``n`` distinct (marker, colour) pairs, one per axis of a Pareto plot."""
    return [(MARKERS[k % len(MARKERS)], f"C{k % 10}") for k in range(n)]


def plot_pareto(rows, path, cost="wall_per_sim_s", error="rms_rel_error", title="",
                cost_label="wall time per simulated second (s)", floor=None):
    """Cost against error, log-log, one marker per stable variant, the front joined and
    highlighted; unstable variants listed in the caption; ``floor``: the reference's own
    error, a dashed line (errors below it are not resolved).  The legend sits right of
    the axes, where it covers no point."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9.5, 5.5))
    # a setting repeated on another axis ("same_as") is drawn once, under its first name
    stable = [r for r in rows if r.get("stable") and r.get(error) is not None and r.get(cost)
              and not r.get("same_as")]
    pts = [(float(r[cost]), max(float(r[error]), 1e-16)) for r in stable]
    axes = list(dict.fromkeys(r.get("axis", "") for r in stable))
    for a, (marker, colour) in zip(axes, axis_styles(len(axes))):
        sel = [p for p, r in zip(pts, stable) if r.get("axis", "") == a]
        ax.plot(*zip(*sel), marker, color=colour, label=a, alpha=0.8)
    for p, r in zip(pts, stable):
        ax.annotate(r["variant"], p, fontsize=6, xytext=(3, 3), textcoords="offset points")
    if pts:
        front = pareto_front(pts)
        fp = [pts[i] for i in front]
        ax.plot(*zip(*fp), "-", color="red", lw=2, alpha=0.5, label="Pareto front")
        ax.plot(*zip(*fp), "o", mfc="none", mec="red", ms=12)
        ax.set_xscale("log")
        ax.set_yscale("log")
        _label_log_ticks(ax)
    if floor:
        ax.axhline(floor, ls="--", color="grey", label="reference's own error")
    caption = [f"{status}: " + ", ".join(r["variant"] for r in rows if r.get("status") == status)
               for status in ("unstable", "unsupported") if any(r.get("status") == status for r in rows)]
    ax.set_xlabel(cost_label)
    ax.set_ylabel(error.replace("_", " ") + " vs reference")
    ax.set_title("\n".join([title, *caption]), fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def _label_log_ticks(ax):
    """Ticks labelled at 1, 2 and 5 per decade: a study's cost often spans about one
    decade, where matplotlib labels a single power of ten."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(NullFormatter())
