"""Solver comparison: record a scene's Newton systems once, replay them with
every named option set, summarise per set and scene size, write CSV/JSON/markdown/PNG.

Used by ``drivers/compare_solvers.py``; see docs/studies.md.
"""

from __future__ import annotations

import copy
import time
from pathlib import Path

import numpy as np

from lc_petsc.simulator import build_simulator
from lc_petsc.studies import report
from lc_petsc.studies.systems import SystemRecorder, destroy_systems, direct_solutions, replay
from lc_petsc.timing import peak_rss_mib

ROW_COLUMNS = ["wisps", "dofs", "ranks", "set", "repeat", "system", "frame", "newton_it", "status",
               "setup_s", "solve_s", "total_s", "solve_cpu_s", "iterations", "reason", "true_rel_residual",
               "rel_error_vs_direct", "rss_delta_mib", "peak_rss_mib", "set_peak_mib", "memory_window",
               "cluster_fallback", "cluster_captured", "cluster_couplings", "cluster_rows",
               "mat_type", "message",
               "options"]
SUMMARY_COLUMNS = ["wisps", "dofs", "ranks", "set", "status", "n_systems", "n_ok", "repeats",
                   "setup_s", "solve_s", "total_s", "total_s_repeats", "ratio_vs_default",
                   "iterations_first",
                   "iterations_mean", "max_true_rel_residual", "max_rel_error_vs_direct",
                   "rss_delta_mib", "set_peak_mib", "budget_s", "message"]


def record(config, comm, frames=1, max_systems=None, skip_frames=0, restart=None):
    """Run ``skip_frames`` + ``frames`` frames of ``config`` with the simulator's own
    solver, recording every Newton system of the last ``frames``; with ``restart`` (a
    checkpoint of drivers/simulate.py written with ``config``) from that checkpoint's
    state instead of frame 0.  Returns (systems, wisp_rows, info)."""
    sim = build_simulator(config, comm, check_start=restart is None)
    try:
        start = 0 if restart is None else restore_checkpoint(sim, config, restart)
        rec = SystemRecorder(sim, max_systems=max_systems, first_frame=start + skip_frames)
        t0 = time.perf_counter()
        sim.run(skip_frames + frames)
        info = {"wisps": sim.n_wisps, "dofs": 3 * sim.n_vertices, "ranks": comm.size,
                "start_frame": start, "record_wall_s": time.perf_counter() - t0,
                "sim_ksp_iterations": list(sim.solver.iterations),
                "strand_contact_pairs": list(getattr(sim.integrator, "contact_pairs", [])),
                "sim_solver": sim.solver.describe()}
        rec.detach()
        systems, rows = rec.systems, rec.wisp_rows
    finally:
        sim.close()
    return systems, rows, info


def restore_checkpoint(sim, config, path):
    """Continue ``sim`` from the checkpoint ``path`` as a restart of drivers/simulate.py
    does; returns its frame.  A checkpoint of another scene, or written with a config that
    differs from ``config`` in a key that changes the trajectory, is refused
    (:class:`CheckpointError`, a ValueError, on every rank) naming what differs."""
    from lc_petsc.config import SimConfig
    from lc_petsc.errors import CheckpointError
    from lc_petsc.io.checkpoint import config_differences, load_checkpoint
    from lc_petsc.job import RESTART_FREE_KEYS, _differences_text
    ck = load_checkpoint(path, sim.comm, sim.user, sim.n_wisps, sim.n_vertices, sim.head)
    saved, now = ck["attrs"]["config"], config.to_dict()
    diff = config_differences(saved, now, ignore=RESTART_FREE_KEYS, defaults=SimConfig().to_dict())
    if diff:
        raise CheckpointError(f"{path}: the checkpoint's config differs from the study's in "
                              f"{_differences_text(diff, saved, now)}; give --config the config the "
                              f"checkpoint ran with (its attribute config_toml)")
    sim.restore(dict(ck, x=sim.user.from_user(ck["x"]), v=sim.user.from_user(ck["v"])))
    return ck["frame"]


def summarise(rows, budget_s):
    """One summary row per (wisps, set) from the per-system rows; ratios vs ``default``.

    With several repeats (``repeat`` column) the times are those of the median repeat
    by total time among the repeats in which every system was solved (the mean of the two
    middle ones for an even count, so setup + solve = total; ``total_s_repeats`` lists
    them; a set stopped in its first repeat: the systems it solved); the status is the
    worst over all repeats (a set over the budget in a later repeat is not ``ok`` on
    its fast repeats alone); iterations, residuals and errors come from the first repeat."""
    out = []
    keys = list(dict.fromkeys((r["wisps"], r["set"]) for r in rows))
    for wisps, name in keys:
        every = [r for r in rows if r["wisps"] == wisps and r["set"] == name]
        rs = [r for r in every if r.get("repeat", 0) == 0]
        ok = [r for r in rs if r["status"] == "ok"]
        statuses = {r["status"] for r in every}
        status = "ok" if statuses == {"ok"} else next(
            s for s in ("error", "diverged", "inaccurate", "budget") if s in statuses)
        its = [r["iterations"] for r in ok]
        s = {"wisps": wisps, "dofs": rs[0].get("dofs"), "ranks": rs[0].get("ranks"),
             "set": name, "status": status, "n_systems": len(rs), "n_ok": len(ok),
             "budget_s": budget_s,
             "message": next((r.get("message") for r in rs if r.get("message")), "")}
        if ok:
            per_repeat = {}
            for r in every:
                per_repeat.setdefault(r.get("repeat", 0), []).append(r)
            complete = [g for g in per_repeat.values()
                        if len(g) == len(rs) and all(r["status"] == "ok" for r in g)] or [ok]
            sums = sorted(({k: sum(r[k] for r in g) for k in ("setup_s", "solve_s", "total_s")}
                           for g in complete), key=lambda t: t["total_s"])
            middle = sums[(len(sums) - 1) // 2: len(sums) // 2 + 1]
            med = {k: float(np.mean([t[k] for t in middle])) for k in ("setup_s", "solve_s", "total_s")}
            s.update(med, repeats=len(complete),
                     total_s_repeats=[sum(r["total_s"] for r in g) for g in complete],
                     iterations_first=its[0], iterations_mean=float(np.mean(its)),
                     max_true_rel_residual=max(r["true_rel_residual"] for r in ok),
                     max_rel_error_vs_direct=max((r.get("rel_error_vs_direct") or 0.0) for r in ok),
                     rss_delta_mib=max(r["rss_delta_mib"] for r in every if r["status"] == "ok"),
                     set_peak_mib=max(r["set_peak_mib"] for r in every if r["status"] == "ok"))
        if status == "budget":
            s["time_spent_s"] = budget_s
        out.append(s)
    for s in out:
        d = next((x for x in out if x["wisps"] == s["wisps"] and x["set"] == "default"), None)
        if d and d.get("total_s") and s.get("total_s") and s["status"] == "ok":
            s["ratio_vs_default"] = s["total_s"] / d["total_s"]
        elif d and d.get("total_s") and s["status"] == "budget":
            s["ratio_vs_default"] = f">{budget_s / d['total_s']:.3g}"
    return out


def table3(summary):
    """Markdown in the layout of the paper's Table 3: one row per solver set, per wisp
    count the time of the recorded systems, the ratio against ``default`` and the Krylov
    iterations of the first system."""
    sizes = sorted({s["wisps"] for s in summary})
    sets = list(dict.fromkeys(s["set"] for s in summary))
    header = ["solver set"] + [f"{n} wisps: time (s), x default, its" for n in sizes]
    body = []
    for name in sets:
        cells = [name]
        for n in sizes:
            s = next((x for x in summary if x["set"] == name and x["wisps"] == n), None)
            if s is None:
                cells.append("-")
            elif s["status"] == "ok":
                r = s.get("ratio_vs_default")
                cells.append(f"{report.fmt(s['total_s'])}, {report.fmt(r)}x, {s['iterations_first']}")
            elif s["status"] == "budget":
                cells.append(f"> {s['budget_s']:g} (budget), {s.get('ratio_vs_default', '-')}x")
            else:
                cells.append(f"{s['status']}: {s.get('message', '')[:60]}")
        body.append(cells)
    return report.markdown_table(header, body)


def details_table(summary):
    """Markdown table of every set's figures per wisp count."""
    header = ["wisps", "set", "status", "setup (s)", "solve (s)", "total (s)", "x default",
              "its (first/mean)", "true rel. residual", "error vs direct", "RSS delta (MiB)",
              "peak over start (MiB)"]
    body = []
    for s in summary:
        body.append([s["wisps"], s["set"], s["status"], report.fmt(s.get("setup_s")),
                     report.fmt(s.get("solve_s")), report.fmt(s.get("total_s")),
                     report.fmt(s.get("ratio_vs_default")),
                     f"{s.get('iterations_first', '-')}/{report.fmt(s.get('iterations_mean'))}",
                     report.fmt(s.get("max_true_rel_residual")),
                     report.fmt(s.get("max_rel_error_vs_direct")),
                     report.fmt(s.get("rss_delta_mib")), report.fmt(s.get("set_peak_mib"))])
    return report.markdown_table(header, body)


def run_comparison(make_config, sizes, sets, comm, out_dir, budget_s=60.0, frames=1,
                   max_systems=None, reference=True, log=print, meta=None,
                   skip_after_budget=False, repeats=1, skip_frames=0, restart=None):
    """The whole study: for each size, record once, replay with each set (``repeats``
    times, the sets interleaved; summaries report median times; the first
    ``skip_frames`` frames run unrecorded, from the checkpoint ``restart`` if given); write
    ``rows.csv``, ``summary.csv``, ``results.json``, ``table.md`` and (with more than
    one size) ``time_vs_wisps.png`` into ``out_dir`` (rank 0).  Returns the summary."""
    out = Path(out_dir)
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    rows, infos = [], []
    for n in sizes:
        cfg = make_config(n)
        systems, wisp_rows, info = record(cfg, comm, frames=frames, max_systems=max_systems,
                                          skip_frames=skip_frames, restart=restart)
        infos.append(info)
        log(f"[{n} wisps] {info['dofs']} DoFs: recorded {len(systems)} Newton systems in "
            f"{info['record_wall_s']:.2f} s (simulator's KSP iterations {info['sim_ksp_iterations']}"
            + (f", strand contact pairs {info['strand_contact_pairs']})" if info["strand_contact_pairs"] else ")"))
        refs = direct_solutions(systems, comm) if reference else None
        for rep in range(repeats):
            for name, opts in sets.items():
                here = [r for r in rows if r["set"] == name and r["wisps"] == info["wisps"]]
                if rep > 0 and any(r["status"] != "ok" for r in here):
                    continue        # stopped or failed in the first repeat: once is enough
                over = next((r["wisps"] for r in rows if r["set"] == name and r["status"] == "budget"), None)
                if skip_after_budget and over is not None:
                    rs = [{"set": name, "options": opts, "system": i, "status": "budget",
                           "message": f"skipped: over the budget at {over} wisps"}
                          for i in range(len(systems))]
                else:
                    rs = replay(systems, wisp_rows, name, opts, comm, budget_s=budget_s,
                                references=refs)
                for r in rs:
                    r.update(wisps=info["wisps"], dofs=info["dofs"], ranks=comm.size, repeat=rep)
                rows += rs
                tot = sum(r.get("total_s", 0.0) for r in rs)
                log(f"  {name:18s} {','.join(sorted({r['status'] for r in rs})):8s} "
                    f"{tot:8.3f} s  its {[r.get('iterations') for r in rs]}  "
                    f"err {max((r.get('rel_error_vs_direct') or 0.0) for r in rs):.1e}"
                    + (f"  (repeat {rep + 1}/{repeats})" if repeats > 1 else ""))
        for x in refs or []:
            x.destroy()
        destroy_systems(systems)
    summary = summarise(rows, budget_s)
    if comm.rank == 0:
        report.write_csv(rows, out / "rows.csv", ROW_COLUMNS)
        report.write_csv(summary, out / "summary.csv", SUMMARY_COLUMNS)
        report.write_json({"meta": dict(meta or {}, budget_s=budget_s, frames=frames,
                                        skip_frames=skip_frames, restart=restart,
                                        peak_rss_mib_rank0=peak_rss_mib()),
                           "scenes": infos, "summary": summary, "rows": rows},
                          out / "results.json")
        md = ["# Solver comparison\n",
              "Same recorded Newton systems for every set; time = setup + solve summed over "
              "them (max over ranks)" + (f", median of {repeats} replays" if repeats > 1 else "")
              + ". Layout of the paper's Table 3.\n",
              table3(summary), "\n## Details\n", details_table(summary)]
        if meta and meta.get("command"):
            md.insert(1, f"Command: `{meta['command']}`\n")
        (out / "table.md").write_text("\n".join(md))
        if len(set(sizes)) > 1:
            report.plot_time_vs_size(summary, out / "time_vs_wisps.png")
    return summary


def hairball_config(base, n_wisps):
    """A copy of the config ``base`` with ``n_wisps`` wisps."""
    cfg = copy.deepcopy(base)
    cfg.scene.n_wisps = int(n_wisps)
    return cfg
