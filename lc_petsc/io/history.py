"""One per-frame history of a run over its restarts (``scripts/join_summaries.py``).

A restarted run's per-frame records are split: each restart set the earlier run's
``summary.json`` aside in ``summaries/`` (:func:`lc_petsc.io.summary.set_summary_aside`)
and the folder's ``summary.json`` lists them in ``restart.earlier_summaries`` with the
frames no later run re-ran (``frames_kept``).  :func:`join_history` takes, for every
frame 1 .. the last, the record of the last segment that ran it (the one whose
``frames_kept`` holds it; ``summary.json``'s own frames are all kept), and checks that
the segments tile the frames once each; a missing, damaged or inconsistent file is a
``ValueError`` naming it.  A ``running`` summary.json is told apart by the folder's lock
(:func:`running_state`): a run going, killed, or failed to write its final summary.
"""

from __future__ import annotations

import hashlib
import json
import socket
from pathlib import Path

from lc_petsc.config import RESTART_FREE_KEYS
from lc_petsc.io.summary import RUNNING, frames_covered, run_status

#: the history's columns that say where a frame's record is from (before the summaries' keys)
SOURCE_COLUMNS = ("frame", "segment", "ranks", "config_sha256")


def _read(path, name):
    try:
        s = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ValueError(f"{name}: missing") from None
    except OSError as e:
        raise ValueError(f"{name}: unreadable ({e.strerror or e})") from None
    except (UnicodeDecodeError, ValueError) as e:
        raise ValueError(f"{name}: damaged (not JSON: {e})") from None
    if not isinstance(s, dict):
        raise ValueError(f"{name}: damaged (not a JSON object but {type(s).__name__})")
    return s


def running_state(out, summary):
    """What the ``running`` summary.json of the output folder ``out`` (``summary``, as
    read) means now, from the folder's lock (:func:`lc_petsc.io.lock.probe`, which
    changes nothing; the test a run makes when it finds the lock, ``OutputLock.stale``):
    (state, text).  ``running``: a live process holds the lock; ``failed``: the lock
    file says why its run ended (its final summary.json could not be written:
    ``OutputLock.leave``); ``killed``: the lock file is there and no process holds it
    (stale), or there is none; ``unknown``: the lock is free but its holder was on another
    host, whose lock this filesystem may not show here (not guessed); ``ended``: the run
    ended while being looked at (summary.json no longer says running: read it again)."""
    from lc_petsc.io.lock import LOCK_NAME, describe_holder, probe
    frames = summary.get("frames")
    state, record = probe(out)
    who = f"pid {record.get('pid')} on host {record.get('host')}" if record else "its holder not recorded yet"
    if state == "held":
        return "running", (f"running ({who}, alive: it holds the folder's lock {LOCK_NAME}), {frames} frames "
                           "recorded so far")
    try:
        now = json.loads((Path(out) / "summary.json").read_text())
    except (OSError, ValueError):
        now = None
    if isinstance(now, dict) and now.get("status") != RUNNING:
        return "ended", f"ended while being looked at: summary.json now says {run_status(now)}"
    if record and record.get("ended"):
        return "failed", (f"failed after frame {frames}: {record['ended']} (its lock file {LOCK_NAME} says so; "
                          f"summary.json is the one kept while it ran)")
    here = socket.gethostname()
    if record and record.get("host") and record["host"] != here:
        return "unknown", (f"not known after frame {frames}: {who}, another host than {here}: no process holds "
                           f"its lock {LOCK_NAME} as seen from here, but this filesystem may not share locks "
                           f"between hosts; it cannot be probed from here (killed, or still running: look on "
                           f"{record.get('host')})")
    if state == "free":
        # no record: empty (killed before it wrote one) or damaged; it said "empty" for both
        held = describe_holder(json.dumps(record)) if record else \
            "a lock file without a run's record (empty or damaged)"
        return "killed", f"killed after frame {frames} (its lock {LOCK_NAME} is stale: {held}; no process holds it)"
    return "killed", f"killed after frame {frames} (no lock file {LOCK_NAME}: no run holds the folder)"


def config_digest(config):
    """SHA-256 of a resolved config (summary.json's ``config``) without the keys a restart
    may change (``RESTART_FREE_KEYS``: frame count, outputs): equal for segments that ran
    the same trajectory-defining config, different after a ``--force`` restart with another."""
    kept = {t: {k: v for k, v in (keys or {}).items() if f"{t}.{k}" not in RESTART_FREE_KEYS}
            for t, keys in (config or {}).items()}
    return hashlib.sha256(json.dumps(kept, sort_keys=True).encode()).hexdigest()


def _value(summary, key):
    where = summary
    for part in key.split("."):
        where = where.get(part) if isinstance(where, dict) else None
    return where


def _per_frame_keys(summary, n):
    """The keys of ``summary`` with one entry per frame of its run (``n``): its
    ``per_frame_keys``; a summary written before that key (2026-12-07): its Newton lists
    and contact's ``*_per_frame`` lists of that length."""
    if isinstance(summary.get("per_frame_keys"), list):
        return list(summary["per_frame_keys"])
    keys = [k for k, v in summary.items() if isinstance(v, list) and len(v) == n
            and (k.startswith("newton_") or k == "length_projection_move")]
    return keys + [f"contact.{k}" for k, v in (summary.get("contact") or {}).items()
                   if k.endswith("_per_frame") and isinstance(v, list) and len(v) == n]


def _segments(out):
    """[(name, summary, [first, last] frames, [first, last] kept or None)], oldest first."""
    now = _read(Path(out) / "summary.json", "summary.json")
    frames = frames_covered(now)
    if frames is None:
        raise ValueError("summary.json: no frame count (a run aborted in its set-up?): "
                         f"{'error: ' + str(now['error']) if now.get('error') else 'nothing to join'}")
    listed = (now.get("restart") or {}).get("earlier_summaries") or []
    segments = []
    for entry in listed:
        name = entry.get("file")
        kept = entry.get("frames_kept")
        if entry.get("frames") is None:
            if kept is not None:
                raise ValueError(f"{name}: damaged, yet summary.json says its frames {kept} are kept")
            continue            # nothing of it is kept: its frames were run again later
        s = _read(Path(out) / name, name)
        if list(frames_covered(s) or []) != list(entry["frames"]):
            raise ValueError(f"{name}: covers frames {frames_covered(s)}, summary.json's "
                             f"restart.earlier_summaries says {entry['frames']}")
        if kept is not None:
            segments.append((name, s, list(entry["frames"]), list(kept)))
    segments.append(("summary.json", now, list(frames), list(frames)))
    return segments


def join_history(out, retries=1):
    """The per-frame history of the run in the output folder ``out`` (a dict, what
    ``history.json`` holds): ``segments`` (each summary with kept frames, oldest first:
    ``file``, ``status``, ``ranks``, ``config_sha256``, ``frames`` [first, last] covered,
    ``frames_kept``), ``keys`` (the per-frame keys joined) and ``per_frame``: for frames
    1 .. ``frames`` one entry each of ``frame``, ``segment`` (index into ``segments``),
    ``ranks``, ``config_sha256`` and every key (null where a segment lacks it;
    ``ksp_iterations``: the frame's solves, split by ``ksp_solves``).  ``ValueError``
    naming the file when one is missing or damaged, or the segments do not tile the
    frames once each.  ``running``: summary.json says running, and ``running_state``
    then (:func:`running_state`: ``state``, ``text``), else null; a run that ended while
    being joined is joined again (``retries`` times)."""
    segments = _segments(out)
    now = running_state(out, segments[-1][1]) if segments[-1][1].get("status") == RUNNING else None
    if now is not None and now[0] == "ended" and retries > 0:
        return join_history(out, retries - 1)
    keys: list = []
    per_frame: dict = {c: [] for c in SOURCE_COLUMNS}
    columns = []
    described = []
    expected = 1
    for i, (name, s, frames, kept) in enumerate(segments):
        first, n = frames[0], frames[1] - frames[0]
        if kept[0] + 1 != expected and kept[1] > kept[0]:
            what = (f"frames {expected}-{kept[0]} have no record" if kept[0] + 1 > expected
                    else f"frames {kept[0] + 1}-{expected - 1} are recorded twice")
            raise ValueError(f"{name}: its kept frames start at {kept[0] + 1}; {what} (a summary missing "
                             f"or damaged before it in restart.earlier_summaries)")
        own = _per_frame_keys(s, n)
        lists = {}
        for k in own:
            v = _value(s, k)
            if not isinstance(v, list) or len(v) != n:
                raise ValueError(f"{name}: {k} has {len(v) if isinstance(v, list) else 'no'} entries for "
                                 f"its {n} frames ({first + 1}-{frames[1]})")
            lists[k] = v
        if "ksp_solves" in lists:
            its, counts = s.get("ksp_iterations") or [], lists["ksp_solves"]
            if sum(counts) != len(its):
                raise ValueError(f"{name}: ksp_solves sum to {sum(counts)}, ksp_iterations has {len(its)} solves")
            at = [sum(counts[:j]) for j in range(n + 1)]
            lists["ksp_iterations"] = [its[at[j]:at[j + 1]] for j in range(n)]
        keys += [k for k in lists if k not in keys]
        columns.append(lists)
        digest = config_digest(s.get("config"))
        described.append({"file": name, "status": run_status(s), "ended": s.get("ended"), "ranks": s.get("ranks"),
                          "config_sha256": digest, "frames": frames, "frames_kept": kept})
        for f in range(kept[0] + 1, kept[1] + 1):
            per_frame["frame"].append(f)
            per_frame["segment"].append(i)
            per_frame["ranks"].append(s.get("ranks"))
            per_frame["config_sha256"].append(digest)
        expected = max(expected, kept[1] + 1)
    for k in keys:
        per_frame[k] = [v for (_, _, frames, kept), lists in zip(segments, columns)
                        for v in (lists[k][kept[0] - frames[0]:kept[1] - frames[0]] if k in lists
                                  else [None] * (kept[1] - kept[0]))]
    last = segments[-1][2][1]
    return {"out": str(out), "frames": last, "running": now is not None,
            "running_state": None if now is None else {"state": now[0], "text": now[1]},
            "segments": described, "keys": keys, "per_frame": per_frame}


def history_table(history, columns=("newton_iterations", "newton_converged", "newton_capped", "newton_increment",
                                    "ksp_iterations", "contact.pairs_per_frame")):
    """Lines for a person: the segments, then a row per frame of ``columns`` (those present;
    ``newton_capped`` only where a frame was capped: a start/jolt frame ended by
    ``time.start_iterations`` shows False under ``newton_converged``, and this says why)."""
    lines = [f"{history['out']}: frames 1-{history['frames']} from {len(history['segments'])} summar"
             f"{'y' if len(history['segments']) == 1 else 'ies'}"
             + (f" (the last says running: {history['running_state']['text']})" if history["running"] else "")]
    last = len(history["segments"]) - 1
    for i, seg in enumerate(history["segments"]):
        a, b = seg["frames_kept"]
        # an earlier segment that says running was killed, or failed when the restart that
        # set it aside found its lock saying why (set_summary_aside); the last one is what
        # its lock says
        status = seg["status"] if seg["status"] != RUNNING else \
            f"{(seg.get('ended') or 'killed').split(':')[0]} (running)" if i < last \
            else RUNNING if history["running_state"]["state"] == RUNNING \
            else f"{history['running_state']['state']} (running)"
        # a restart at the run's last checkpoint runs no frame: it writes the skipped outputs
        span = (f"frames {a + 1}-{b} kept of {seg['frames'][0] + 1}-{seg['frames'][1]}"
                if seg["frames"][1] > seg["frames"][0]
                else f"no frame run (the end-of-run outputs after frame {seg['frames'][1]})")
        lines.append(f"  segment {i}: {seg['file']}, {status}, {seg['ranks']} rank(s), config "
                     f"{seg['config_sha256'][:12]}, {span}")
    pf = history["per_frame"]
    shown = ["frame", "segment", "ranks", *(c for c in columns if c in pf and (c != "newton_capped" or any(pf[c])))]
    # a list (the frame's KSP solves) is shown as its sum
    names = {c: c.split(".")[-1] + (" (sum)" if c == "ksp_iterations" else "") for c in shown}
    lines.append("  " + "  ".join(names[c].rjust(8) for c in shown))

    def cell(v):
        if isinstance(v, list):
            v = sum(v)
        return f"{v:.3g}" if isinstance(v, float) else str(v)
    for j in range(len(pf["frame"])):
        lines.append("  " + "  ".join(cell(pf[c][j]).rjust(max(8, len(names[c]))) for c in shown))
    return lines
