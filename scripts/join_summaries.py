"""One per-frame history over all segments of a (restarted) run of drivers/simulate.py.

    .venv/bin/python scripts/join_summaries.py OUT [--json FILE] [--quiet]

Each restart sets the earlier run's ``summary.json`` aside in ``OUT/summaries/`` (its
``restart.earlier_summaries`` lists them with ``frames_kept``): the per-frame records
(Newton iterations and increments, ``newton_converged``, KSP iterations, contact pairs,
...) are split over those files, and a frame re-run after a restart is in two of them.
This joins them into one list per key over frames 1 .. the last, taking for each frame
the record of the last segment that ran it (the one whose ``frames_kept`` holds it;
``lc_petsc.io.history``), with the segment, its rank count and a config digest per frame.
Prints a table (the segments, then a row per frame) and writes ``OUT/history.json``
(``--json FILE`` elsewhere; the next run into OUT removes ``OUT/history.json``, which
would be stale).  A summary missing, damaged, or disagreeing with the others (frames
without a record, or recorded twice) is refused naming the file: exit status 2.
Works on a run in progress or killed too (its ``summary.json`` says ``running``): the
first line then says what the folder's lock says (``lc_petsc.io.history.running_state``):
running (pid, host, alive), killed (lock stale or absent), failed (its final summary
could not be written) or not known (a holder on another host cannot be probed).
"""

import argparse
import os
import sys
from pathlib import Path

from lc_petsc.io.history import history_table, join_history
from lc_petsc.io.summary import write_summary


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", help="the output folder of drivers/simulate.py")
    ap.add_argument("--json", help="where to write the history (default OUT/history.json)")
    ap.add_argument("--quiet", action="store_true", help="print the segments only, no row per frame")
    a = ap.parse_args(argv)
    try:
        history = join_history(a.out)
    except ValueError as e:
        print(f"join_summaries.py: error: {a.out}: {e}; nothing written", file=sys.stderr)
        return 2
    lines = history_table(history)
    _say("\n".join(lines[:1 + len(history["segments"])] if a.quiet else lines))
    target = Path(a.json) if a.json else Path(a.out) / "history.json"
    try:
        write_summary(target, history)
    except OSError as e:
        print(f"join_summaries.py: error: {target}: {e.strerror or e}", file=sys.stderr)
        return 2
    _say(f"written: {target}")
    return 0


def _say(text):
    """Print ``text``; read by ``| head``, the reader may have left (before the table's end, or
    after it and before the last line): it has what it wanted, and the rest goes nowhere."""
    try:
        print(text, flush=True)
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


if __name__ == "__main__":
    sys.exit(main())
