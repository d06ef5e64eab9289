"""``summary.json`` (DESIGN section 3) and the short human-readable report on stdout."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from lc_petsc.io.disk import written_aside


def _jsonable(o):
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return o


def write_summary(path, summary):
    """Write ``summary`` as JSON atomically: through ``<path>.tmp``, synced to the disk,
    then renamed over ``path``, so a reader (or a run killed at any moment, a crash)
    never leaves or sees half a file: the old one or the new one whole."""
    text = json.dumps(_jsonable(summary), indent=1) + "\n"     # one write: json.dump's many took 8x longer
    with written_aside(path, fsync=True) as tmp, open(tmp, "w") as fh:
        fh.write(text)


#: ``status`` of the summary.json a running job keeps up to date (rank 0, at each
#: checkpoint and frames.h5 flush): a run killed (SIGKILL) leaves it so
RUNNING = "running"


def run_status(summary):
    """A summary's ``status``: ``running`` (written while the run went: it is going, or it
    was killed), ``finished``, ``preempted`` (stopped by a signal) or ``error``; a summary
    written before the key (2026-12-07) by its ``error`` and ``preempted``."""
    if isinstance(summary.get("status"), str):
        return summary["status"]
    return "error" if summary.get("error") else "preempted" if summary.get("preempted") else "finished"


#: the folder (in the output folder) of the summaries a restart set aside
SUMMARIES = "summaries"


def frames_covered(summary):
    """(first, last) frame of a run's summary (its per-frame lists are frames first + 1 ..
    last), or None when it says no frame count (a run aborted in its set-up)."""
    if not isinstance(summary, dict) or not isinstance(summary.get("frames"), int):
        return None
    first = (summary.get("restart") or {}).get("frame", 0)
    return (first, summary["frames"]) if isinstance(first, int) else None


def set_summary_aside(out, failed=None):
    """Rank 0, at a restart that was accepted (before anything is replaced): rename
    ``out/summary.json`` (the earlier run's) into ``out/summaries/`` under a name saying
    which frames it covers, ``summary_frames_AAAAAA-BBBBBB.json`` (``.2``, ``.3``, ... when
    that name is taken), or ``summary_damaged.json`` when it is not a JSON object; a rename,
    so it is whole under one name or the other.  A summary that says ``running`` then gets
    ``ended``, what the restart found of its run: ``killed``, or ``failed: WHY`` when its
    lock file said why (``failed``: :attr:`OutputLock.ended`); rewritten atomically after
    the rename, so a crash in between leaves it unannotated, never half.  Returns (its new
    path or None when there was none, the reason it is damaged or None)."""
    path = Path(out) / "summary.json"
    if not os.path.lexists(path):
        return None, None
    damaged = None
    try:
        summary = json.loads(path.read_text())
        if not isinstance(summary, dict):
            damaged = f"not a JSON object but {type(summary).__name__}"
    except OSError as e:
        summary, damaged = None, f"unreadable: {e.strerror or e}"
    except (UnicodeDecodeError, ValueError) as e:
        summary, damaged = None, f"not JSON: {e}"
    frames = None if damaged else frames_covered(summary)
    stem = "summary_damaged" if damaged else "summary_no_frames" if frames is None else \
        f"summary_frames_{frames[0]:06d}-{frames[1]:06d}"
    folder = Path(out) / SUMMARIES
    folder.mkdir(exist_ok=True)
    target, n = folder / f"{stem}.json", 1
    while os.path.lexists(target):
        n += 1
        target = folder / f"{stem}.{n}.json"
    os.rename(path, target)
    if not damaged and run_status(summary) == RUNNING:
        write_summary(target, {**summary, "ended": f"failed: {failed}" if failed else "killed"})
    return target, damaged


def earlier_summaries(out, restart_frame):
    """Rank 0: the summaries set aside in ``out/summaries/``, oldest first (their files'
    times: a rename keeps them), each with the frames it covers (``frames``: [first, last],
    null for a damaged one) and those of its frames no later run replaced (``frames_kept``:
    [first, last], null when none: a restart from frame k re-runs the frames after k, whose
    records are then the later summary's, never two for one frame)."""
    folder = Path(out) / SUMMARIES
    files = sorted(folder.glob("summary_*.json"), key=lambda p: (p.stat().st_mtime_ns, p.name)) \
        if folder.is_dir() else []
    found = []
    for p in files:
        try:
            frames = frames_covered(json.loads(p.read_text()))
        except (OSError, UnicodeDecodeError, ValueError):
            frames = None
        found.append({"file": f"{SUMMARIES}/{p.name}", "frames": None if frames is None else list(frames)})
    start = restart_frame           # the first frame a later run (this one included) re-ran from
    for entry in reversed(found):
        frames = entry["frames"]
        kept = None if frames is None or min(frames[1], start) <= frames[0] else [frames[0], min(frames[1], start)]
        entry["frames_kept"] = kept
        if frames is not None:
            start = min(start, frames[0])
    return found


def remove_summaries(out):
    """Rank 0, at a new run (not a restart): the summaries an earlier run's restarts set
    aside belong to the run it replaces (like its frames.h5 and checkpoints): removed."""
    folder = Path(out) / SUMMARIES
    if not folder.is_dir():
        return
    for p in folder.glob("summary_*.json"):
        p.unlink()
    if not any(folder.iterdir()):
        folder.rmdir()


#: the report names the kernels' compile time in the set-up from this many seconds on
#: (loading them from Numba's cache takes about a second)
JIT_REPORTED_S = 5.0


def missed_frames(summary):
    """The indices of ``summary``'s frames whose Newton missed its tolerance: those with
    ``newton_converged`` false, except the start/jolt frames ``newton_capped`` marks (ended
    by ``time.start_iterations`` with ``time.max_substeps = 1``: the cap asked for there;
    a summary from before the key has none)."""
    capped = summary.get("newton_capped") or []
    return [i for i, c in enumerate(summary.get("newton_converged", []))
            if c is False and not (i < len(capped) and capped[i])]


def capped_frames(summary):
    """The indices of ``summary``'s start/jolt frames ended by their cap (``newton_capped``)."""
    return [i for i, c in enumerate(summary.get("newton_capped") or []) if c]


def _fmt_s(s):
    return f"{s * 1e3:.1f} ms" if s < 1.0 else f"{s:.2f} s"


def format_report(s) -> str:
    """A few lines for a person: what ran, how long, where the time went, did it converge."""
    frames = s["frames"]
    wall = s["wall_time_s"]
    # after a restart the wall time covers this run's frames only
    run_frames = s.get("frames_this_run", frames)
    per = wall / run_frames if run_frames else 0.0
    cfg = s.get("config", {})
    name = s.get("config_file", "")
    lines = [f"lc_petsc: {name}  ({s['wisps']} wisps, {s['dofs']} DoFs, {s['ranks']} rank(s), "
             f"matrix {s.get('mat_type', '?')})",
             f"  terms: {', '.join(s.get('terms', []))}"]
    dt = cfg.get("time", {}).get("dt")
    sim_t = f", {frames * dt:.3g} s simulated" if dt else ""
    this_run = f" ({run_frames} in this run)" if run_frames != frames else ""
    cpu = s.get("cpu_time_s")
    cpu_t = f", CPU {_fmt_s(cpu)} over {s['ranks']} rank(s)" if cpu is not None else ""
    peak = s.get("peak_memory_mib")
    mem_t = (f"; peak memory {peak['max_rank'] / 1024:.2f} GiB on the largest rank, "
             f"{peak['sum_ranks'] / 1024:.2f} GiB summed") if peak else ""
    # the compiled kernels' JIT (the first run on a machine: minutes, then cached) is set-up
    # time: main's report said "setup 349.18 s" with no word of the 347 s it compiled
    jit = (s.get("jit_compile_s") or 0.0) + ((s.get("contact") or {}).get("jit_compile_s") or 0.0)
    jit_t = f" (of which compiling the kernels {_fmt_s(jit)}: once, cached for later runs)" \
        if jit >= JIT_REPORTED_S else ""
    lines.append(f"  frames: {frames}{sim_t}{this_run}; wall time {_fmt_s(wall)} "
                 f"({_fmt_s(per)} per frame{cpu_t}); setup {_fmt_s(s.get('setup_time_s', 0.0))}{jit_t}{mem_t}")
    tim = s.get("timings_s", {})
    if run_frames:
        lines.append("  phases (max over ranks): " + ", ".join(
            f"{k} {_fmt_s(v)} ({100 * v / max(wall, 1e-300):.0f}%)" for k, v in tim.items() if v > 0))
    elif s.get("error"):    # its first step failed: "the outputs only" read as if none was due
        spent = ", ".join(f"{k} {_fmt_s(v)}" for k, v in tim.items() if v > 0)
        lines.append("  phases: no frame completed in this run: its first step failed (the error below)"
                     + (f"; the failed step's phases (max over ranks): {spent}" if spent else ""))
    else:       # a restart that only wrote the outputs: the set-up's work over no frame time
        lines.append("  phases: no frame ran in this run (the outputs only)")
    newton = s.get("newton_iterations", [])
    ksp = s.get("ksp_iterations", [])
    if newton:
        lines.append(f"  Newton iterations per frame: min {min(newton)}, mean {np.mean(newton):.2f}, "
                     f"max {max(newton)} ({len(ksp)} solves)")
    conv_frames = [c for c in s.get("newton_converged", []) if c is not None]
    incs = [v for v in s.get("newton_increment", []) if v is not None]
    if conv_frames:
        which = ("the start and jolt frames' time.start_increment_tol" if any(s.get("newton_jolt", []))
                 else "the start frames' time.start_increment_tol" if any(s.get("newton_start", []))
                 else "time.newton_increment_tol / newton_tol")
        lines.append(f"  Newton converged ({which}) in {sum(conv_frames)} of {len(conv_frames)} frames")
    capped = capped_frames(s)
    if capped:
        cap = cfg.get("time", {}).get("start_iterations")
        worst = max(s["newton_increment"][i] or 0.0 for i in capped)
        lines.append(f"  start/jolt frames capped at {cap} (start/jolt cap, time.start_iterations with "
                     f"time.max_substeps = 1): {len(capped)} of them, measure up to {worst:.3g} "
                     f"(not counted as missed: newton_capped in summary.json)")
    refused = sum(s.get("newton_verify_refused", []))
    # per-frame counts: a line where any frame has some
    for key, what in (("newton_chord_checks", "chord checks (time.newton_stop = \"chord_estimate\"): {} solves"),
                      ("newton_verified", "stops after filtered steps verified by an exact step: {} "
                                          f"({refused} refused)"),
                      ("newton_coupled_unknown", "stops whose curvature over contact-coupled wisps is unknown "
                                                 "(Lanczos unconverged, kept): {}"),
                      ("root_turns_reduced", "root turns halved or dropped (they raised a wisp's share of "
                                             "G, time.root_rotation): {} wisp turns"),
                      ("newton_extend_capped", "extended counts ended by time.newton_extend_cap above "
                                               "time.newton_extend_above: {} solves")):
        counts = s.get(key, [])
        if sum(counts):
            lines.append(f"  {what.format(sum(counts))} in {sum(n > 0 for n in counts)} frames")
    subs = s.get("newton_substeps", [])
    if any(n > 1 for n in subs):
        lines.append(f"  step cutback (time.max_substeps) in {sum(n > 1 for n in subs)} of {len(subs)} "
                     f"frames, at most {max(subs)} substeps")
    if incs:
        lines.append(f"  last Newton increment / wisp length: median {np.median(incs):.2e}, "
                     f"max {max(incs):.2e}")
    if ksp:
        lines.append(f"  KSP iterations per solve: min {min(ksp)}, mean {np.mean(ksp):.1f}, max {max(ksp)}")
    reasons = s.get("ksp_reasons", [])
    counts = {r: reasons.count(r) for r in sorted(set(reasons))}
    conv = "yes" if s.get("converged") else "NO"
    why = []
    missed = missed_frames(s)
    if missed:      # the frames the run kept although Newton missed its tolerance
        why.append(f"Newton missed the tolerance in {len(missed)} of {len(s['newton_converged'])} frames")
    if counts:
        why.append("linear solves " + ", ".join(f"{k} x{v}" for k, v in counts.items()))
    lines.append(f"  converged: {conv}" + (f" ({'; '.join(why)})" if why else ""))
    if s.get("error"):
        lines.append(f"  error: {s['error']}")
    shape = s.get("shape") or {}
    parts = []
    if shape.get("curl_radius_ratio") is not None:
        parts.append(f"curl radius {shape['curl_radius_ratio']:.3f}")
    if shape.get("wisp_length_ratio") is not None:
        parts.append(f"wisp length (root to tip) {shape['wisp_length_ratio']:.3f}")
    if parts:
        lines.append("  shape at the end / rest (mean over wisps): " + ", ".join(parts))
    check = s.get("crossings")
    if check and "error" in check:
        lines.append(f"  crossings between the frames written: not checked ({check['error']})")
    elif check:
        def exempt(kind):       # crossings of pairs the contact exempts at rest
            n = check.get(f"{kind}_exempt")
            return f" ({n} of pairs exempt at rest)" if n else ""
        within = "" if check["within_wisps"] is None else \
            f", within wisps {check['within_wisps']}{exempt('within')}"
        strain = ("" if check.get("largest_strain") is None else
                  f"; largest edge strain {100 * check['largest_strain']:.2f}%")
        lines.append(f"  crossings between the frames written: between wisps {check['between_wisps']}"
                     f"{exempt('between')}{within} over {check['steps']} steps{strain} "
                     f"(checked in {_fmt_s(check['seconds'])})")
    head = (check or {}).get("head")
    if head:
        lines.append(f"  hair inside the head: deepest free vertex {head['vertex_depth']:.3g} cm, edge point "
                     f"{head['edge_depth']:.3g} cm ({head['ratio']:.3g} strand radii); frames with a strand "
                     f"entirely inside {head['rows_sunk']} ({head.get('rows_sunk_by_chords', 0)} only along edges "
                     f"between vertices resting on it); vertex paths through it {head['paths_through']}")
    earlier = (s.get("restart") or {}).get("earlier_summaries")
    if earlier:     # this summary's per-frame figures are this run's frames only
        lines.append("  the earlier runs' summaries (set aside by the restarts): " + ", ".join(
            e["file"] + ("" if e["frames"] is None else f" (frames {e['frames'][0] + 1}-{e['frames'][1]})")
            for e in earlier))
    for w in s.get("warnings", []):
        lines.append(f"  warning: {w}")
    out = s.get("output", {})
    if out:
        files, n = out.get("files", []), out.get("frames_written")
        # frames.h5 missing from the files written: its folder was removed during the run
        every = out.get("every")
        held = f"{n} frames in frames.h5, every {every}" if "frames.h5" in files or not n else \
            f"{n} frames (every {every}) had been written to frames.h5, which is gone"
        lines.append(f"  output: {out.get('dir')}  ({held}; " + (", ".join(files) or "no file") + ")")
    return "\n".join(lines)
