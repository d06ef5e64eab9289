"""Figures of the strand-contact benchmark (scripts/bench_contact.py): one run's
summary, a markdown table of several runs side by side (e.g. 1 and 2 ranks) with the
benchmark's targets, and a plot of the runs frame by frame.

A *run* is the dict ``bench_contact.py --json`` writes: ``ranks``, ``d0`` (cm), ``build``
(s) and ``frames``, one row per frame with ``wall`` (s), ``phases`` (s per phase, max
over ranks), ``ksp`` (CG iterations per Newton solve), ``pairs`` (active pairs at the end
of the frame), ``deep`` (pairs closer than d0/2 at the end of the frame), ``dmin`` (cm;
None when no pair was in range), ``separated`` ((pairs found below d0/2, Jacobi rounds,
left)) and ``ghosts``; optionally ``wisps`` and ``dofs``.
"""

from __future__ import annotations

import statistics

import numpy as np

from lc_petsc.studies.report import _plt, markdown_table

# the benchmark's targets for the 2,000-wisp hairball
TARGET_FRAME_S = 8.0            # per frame on 2 ranks
TARGET_COLLISION_SHARE = 0.35   # of the frame
PHASES = ("solve", "collision", "elements", "assembly")


def summarize(run):
    """Summary figures of one run (dict above).  Wall-time and phase medians are over the
    frames after the first (the first frame starts at rest, with a 3-iteration first
    solve, and pays first-touch costs); counts (CG iterations, pairs, ghosts), shares and
    minima over the whole run.  Raises ValueError naming what is missing or wrong."""
    if not isinstance(run, dict):
        raise ValueError(f"a contact benchmark run is a JSON object, got {type(run).__name__}")
    missing = {"ranks", "d0", "frames"} - set(run)
    if missing:
        raise ValueError(f"contact benchmark run lacks {sorted(missing)}: give a file written by "
                         f"bench_contact.py --json")
    rows = run["frames"]
    if not isinstance(rows, list) or not rows:
        raise ValueError("contact benchmark run has no frames: run bench_contact.py with --frames >= 1")
    need = {"frame", "wall", "phases", "ksp", "pairs", "dmin", "deep", "separated"}
    bad = [i for i, r in enumerate(rows) if not isinstance(r, dict) or not need <= set(r)]
    if bad:
        raise ValueError(f"contact benchmark run: frame row {bad[0]} lacks some of {sorted(need)}")
    if not (isinstance(run["d0"], (int, float)) and run["d0"] > 0):
        raise ValueError(f"contact benchmark run: d0 must be a positive number, got {run['d0']!r}")
    steady = rows[1:] or rows
    walls = [r["wall"] for r in steady]
    its = [i for r in rows for i in r["ksp"]]
    wall_total = sum(r["wall"] for r in rows)
    phases = sorted({k for r in rows for k in r["phases"]})
    d0 = float(run["d0"])
    dmin = min((r["dmin"] for r in rows if r["dmin"] is not None), default=float("inf"))
    return {
        "ranks": int(run["ranks"]),
        "frames": len(rows),
        "first_frame_s": rows[0]["wall"],
        "wall_median_s": statistics.median(walls),
        "wall_p10_s": float(np.percentile(walls, 10)),
        "wall_p90_s": float(np.percentile(walls, 90)),
        "wall_max_s": max(walls),
        "phase_median_s": {k: statistics.median(r["phases"].get(k, 0.0) for r in steady) for k in phases},
        "collision_share": sum(r["phases"].get("collision", 0.0) for r in rows) / wall_total,
        "cg_first_frame": list(rows[0]["ksp"]),
        "cg_median": statistics.median(its) if its else 0,
        "cg_max": max(its, default=0),
        "cg_per_frame_median": statistics.median(sum(r["ksp"]) for r in rows),
        "pairs_first": rows[0]["pairs"],
        "pairs_median": statistics.median(r["pairs"] for r in rows),
        "pairs_max": max(r["pairs"] for r in rows),
        "frames_with_deep_pairs": sum(1 for r in rows if r["deep"] > 0),
        "separated_max": max((r["separated"][0] for r in rows), default=0),
        "d0": d0,
        "dmin_cm": dmin,
        "dmin_over_d0": dmin / d0,
        "ghosts_median": statistics.median(r.get("ghosts", 0) for r in rows),
        "scene": _scene(run),
    }


def _scene(run):
    """'N-wisp hairball (M DoFs)' when the run says, else 'hairball'."""
    if "wisps" in run and "dofs" in run:
        return f"{run['wisps']:,}-wisp hairball ({run['dofs']:,} DoFs)"
    return "hairball"


def _met(ok):
    return "met" if ok else "**not met**"


def summary_table(summaries):
    """Markdown: one column per run (sorted by rank count), one row per figure, then the
    benchmark's targets judged on the first 2-rank run (else the run on the most ranks)."""
    ss = sorted(summaries, key=lambda s: s["ranks"])
    scenes = list(dict.fromkeys(s["scene"] for s in ss))
    header = [" / ".join(scenes) + " with contact"] + [
        f"{s['ranks']} rank{'s' if s['ranks'] > 1 else ''}" for s in ss]

    def row(name, f):
        return [name] + [f(s) for s in ss]

    phases = [p for p in PHASES if any(p in s["phase_median_s"] for s in ss)]
    rows = [
        row("frames", lambda s: s["frames"]),
        row("wall per frame, median (10th-90th pct, max)",
            lambda s: f"{s['wall_median_s']:.2f} s ({s['wall_p10_s']:.2f}-{s['wall_p90_s']:.2f}, "
                      f"{s['wall_max_s']:.2f})"),
        row("first frame", lambda s: f"{s['first_frame_s']:.2f} s"),
        row("median phases per frame", lambda s: ", ".join(
            f"{p} {s['phase_median_s'].get(p, 0.0):.2f}" for p in phases) + " s"),
        row("collision share of the run", lambda s: f"{s['collision_share']:.1%}"),
        row("CG iterations per Newton solve: first frame; median, max",
            lambda s: f"{s['cg_first_frame']}; {s['cg_median']:.0f}, {s['cg_max']}"),
        row("CG iterations per frame, median", lambda s: f"{s['cg_per_frame_median']:.0f}"),
        row("active contact pairs per frame: first, median, max",
            lambda s: f"{s['pairs_first']}, {s['pairs_median']:.0f}, {s['pairs_max']}"),
        row("pairs below d0/2 found after Newton and separated, max per frame",
            lambda s: f"{s['separated_max']}"),
        row("frames ending with a pair closer than d0/2", lambda s: f"{s['frames_with_deep_pairs']}"),
        row("minimum segment distance over the run",
            lambda s: f"{s['dmin_cm']:.4f} cm = {s['dmin_over_d0']:.3f} d0"),
        row("ghost segments received per exchange, median", lambda s: f"{s['ghosts_median']:.0f}"),
    ]
    out = markdown_table(header, rows)
    judged = next((s for s in ss if s["ranks"] == 2), ss[-1])
    out += (f"\nTargets, judged on the first run on {judged['ranks']} rank(s): "
            f"at most {TARGET_FRAME_S:g} s per frame on 2 ranks: {judged['wall_median_s']:.2f} s, "
            f"{_met(judged['ranks'] == 2 and judged['wall_median_s'] <= TARGET_FRAME_S)}; "
            f"contact at most {TARGET_COLLISION_SHARE:.0%} of the frame: {judged['collision_share']:.1%}, "
            f"{_met(judged['collision_share'] <= TARGET_COLLISION_SHARE)}; "
            f"no pair closer than d0/2: minimum {judged['dmin_over_d0']:.3f} d0, "
            f"{judged['frames_with_deep_pairs']} frame(s) ending below, "
            f"{_met(judged['frames_with_deep_pairs'] == 0 and judged['dmin_over_d0'] >= 0.5)}.\n")
    return out


def plot_runs(runs, path, title=None):
    """Four panels over the frames, one line per run: wall time per frame (with the
    solve and collision phases dashed/dotted), CG iterations per frame, active pairs,
    minimum segment distance / d0 (with the d0/2 floor)."""
    plt = _plt()
    if title is None:
        title = " / ".join(dict.fromkeys(_scene(r) for r in runs)) + " with strand contact"
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5), sharex=True)
    (a_t, a_cg), (a_p, a_d) = axes
    for run in sorted(runs, key=lambda r: r["ranks"]):
        rows = run["frames"]
        f = [r["frame"] for r in rows]
        lab = f"{run['ranks']} rank{'s' if run['ranks'] > 1 else ''}"
        line, = a_t.plot(f, [r["wall"] for r in rows], "-", label=f"{lab}: frame")
        c = line.get_color()
        a_t.plot(f, [r["phases"].get("solve", 0.0) for r in rows], "--", color=c, lw=1,
                 label=f"{lab}: solve")
        a_t.plot(f, [r["phases"].get("collision", 0.0) for r in rows], ":", color=c, lw=1.5,
                 label=f"{lab}: collision")
        a_cg.plot(f, [sum(r["ksp"]) for r in rows], "-", color=c, label=lab)
        a_p.plot(f, [r["pairs"] for r in rows], "-", color=c, label=lab)
        a_d.plot(f, [np.nan if r["dmin"] is None else r["dmin"] / run["d0"] for r in rows], "-",
                 color=c, label=lab)
    a_t.axhline(TARGET_FRAME_S, color="k", lw=0.8, ls="-.", label=f"target {TARGET_FRAME_S:g} s (2 ranks)")
    a_t.set_ylabel("seconds per frame")
    a_t.set_ylim(bottom=0)
    a_cg.set_ylabel("CG iterations per frame (3 Newton solves)")
    a_cg.set_ylim(bottom=0)
    a_p.set_ylabel("active contact pairs (end of frame)")
    a_p.set_ylim(bottom=0)
    a_d.axhline(0.5, color="r", lw=0.8, ls="-.", label="d0/2 (floor)")
    a_d.set_ylabel("minimum segment distance / d0")
    a_d.set_ylim(0.0, 1.05)
    for ax in (a_p, a_d):
        ax.set_xlabel("frame")
    for ax in axes.ravel():
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
