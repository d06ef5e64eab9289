"""One run per output folder: an exclusive ``flock`` on ``<out>/.lc_petsc.lock``.

Rank 0 of a run takes the lock before it reads or changes anything in the folder and
holds it for the whole run; the lock file records who holds it (PID, host, start time,
command), so a second run into the same folder is refused with a message naming the
running one.  ``flock`` locks belong to the open file and are released by the kernel
when the holder dies, however it dies (SIGKILL, a crash, a lost node's process), so a
killed run never blocks the folder.  A clean exit removes the lock file; a lock file
that is present, unlocked and not empty was left by a run that did not finish, which
the next run reports (:attr:`OutputLock.stale`).  A run refused before it changed
anything puts the lock file back as it found it (a killed run's record, its times) or
removes the one it created, so the folder is as it was and the next run still warns.
A lock file that is unlocked but records another host (and no ``ended``) is not taken
over: from here a run killed there cannot be told from one still going on a filesystem
that does not pass flocks between hosts (a ``local_lock`` NFS mount), so the run is
refused, the file left as it was, until the user removes it (tests/io/test_lock_other_host.py).
A run whose final summary.json could not be written (a full disk) leaves its lock file
with ``ended`` (why) in the record (:meth:`OutputLock.leave`), so its ``running``
summary is not taken for a killed run's.  :func:`probe` looks at a folder's lock
without taking it (``scripts/check_outputs.py``, ``scripts/join_summaries.py``).

The file is removed only while it is locked, and a lock is only trusted if the locked
file is still the one at the path (the inode check in :meth:`acquire`): otherwise a run
that opened the old file just before it was removed could lock a deleted file while a
third run locks the new one.  Another process of the same job may remove the file for
its holder (:func:`remove_for_holder`, a job stopped during its set-up): both put back
only the inode locked, so a file that came after it is left alone.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import sys
import time
from pathlib import Path

from lc_petsc.errors import FolderBusy

LOCK_NAME = ".lc_petsc.lock"


def read_record(text):
    """The record of a lock file's text (a dict: ``pid``, ``host``, ``started``,
    ``command``, and ``ended`` when its run noted why it ended), or None."""
    try:
        d = json.loads(text)
    except ValueError:
        return None
    return d if isinstance(d, dict) else None


def describe_holder(text):
    """'pid 123 on host h, started 2026-12-01 10:00:00 UTC (python ...)' from a lock file's
    text (and '; it ended: WHY' when its run noted that: :meth:`OutputLock.leave`)."""
    d = read_record(text)
    try:
        return (f"pid {d['pid']} on host {d['host']}, started {d['started']}"
                + (f" ({d['command']})" if d.get("command") else "")
                + (f"; it ended: {d['ended']}" if d.get("ended") else ""))
    except (KeyError, TypeError):
        return f"unknown holder (lock file text {text[:80]!r})"


class OutputLock:
    """Exclusive lock of one output folder (used on one process, rank 0)."""

    def __init__(self, folder):
        self.folder = Path(folder)
        self.path = self.folder / LOCK_NAME
        self.fd = None
        self.inode = None           # of the file locked
        self.created_folder = False
        self.created = []           # the folders acquire made, the deepest first
        self.stale = None           # holder description of a lock left by a killed run
        self.ended = None           # why that run ended, when it noted it (leave)
        self.before = None          # the lock file as it was (bytes, atime_ns, mtime_ns), or None

    def acquire(self):
        """Create the folder if needed and lock it.  Raises :class:`FolderBusy` when a
        live run holds it, OSError when the folder cannot be created or written."""
        if not self.folder.exists():
            # the parents too: a refused run removes every folder it made (--out new/run
            # left new behind)
            p = self.folder
            while not p.exists():
                self.created.append(p)
                p = p.parent
            self.folder.mkdir(parents=True)
            self.created_folder = True
        elif not self.folder.is_dir():
            raise NotADirectoryError(f"{self.folder} exists and is not a folder")
        try:
            return self._take()
        except BaseException:
            # a refused run leaves no trace: a full volume (no block for the record) used to
            # leave the folder it created, with an empty lock file in it
            _remove_empty(self.created)
            raise

    def _take(self):
        try:
            st = os.stat(self.path)
            before = (st.st_atime_ns, st.st_mtime_ns)
        except FileNotFoundError:
            before = None
        for _ in range(100):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                _lock_past_probes(fd)
            except BlockingIOError:
                text = _read(fd)
                os.close(fd)
                raise FolderBusy(f"output folder {str(self.folder)!r} is in use by another run: "
                                 f"{describe_holder(text)}; lock file {self.path}. Wait for it to "
                                 "finish, stop it, or choose another --out") from None
            except BaseException:
                os.close(fd)
                raise
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if not same:                  # removed by its previous holder meanwhile: retry
                os.close(fd)
                continue
            self.fd, self.inode = fd, os.fstat(fd).st_ino
            break
        else:  # pragma: no cover - would need 100 lost races in a row
            raise OSError(f"{self.path}: could not take the lock (the file keeps changing)")
        old = _read(self.fd, raw=True)
        held = read_record(old.decode(errors="replace")) or {}      # the last run's record
        if old.strip():
            self.stale = describe_holder(old.decode(errors="replace"))
            self.ended = held.get("ended")
        if before is not None:
            self.before = (old, *before)
        here = socket.gethostname()
        if held.get("host") not in (None, here) and not held.get("ended"):
            self._give_back()
            raise FolderBusy(f"output folder {str(self.folder)!r} holds the lock of a run on another host, "
                             f"{self.stale}: no process holds it as seen from {here}, but this filesystem may "
                             f"not pass locks between hosts, so that run may still be going (it cannot be "
                             f"probed from here); if it is not running there, remove {self.path} and run again")
        record = {"pid": os.getpid(), "host": here,
                  "started": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
                  "command": " ".join(os.path.basename(a) if i == 0 else a
                                      for i, a in enumerate(sys.argv))[:300]}
        try:
            os.ftruncate(self.fd, 0)
            os.pwrite(self.fd, (json.dumps(record) + "\n").encode(), 0)
            os.fsync(self.fd)
        except BaseException:
            self._give_back()
            raise
        return self

    def _give_back(self):
        """Undo the lock (its record not written: ENOSPC; or the run refused): the lock
        file as it was, text and times (a killed run's record kept for the next run's
        warning) or, if this run created it, removed; then unlock."""
        try:
            put_back(self.path, self.inode, self.before)
        finally:
            os.close(self.fd)
            self.fd = None

    def taken(self):
        """What another process of the same job needs for :func:`remove_for_holder`."""
        return {"stale": self.stale, "ended": self.ended, "inode": self.inode, "created_folder": self.created_folder,
                "created": [str(p) for p in self.created], "before": self.before}

    def release(self, remove_created_folder=False):
        """Remove the lock file and unlock.  ``remove_created_folder`` (a run refused
        before it wrote anything, which leaves no trace): a lock file that was there
        (a killed run's) is put back as it was instead, so the next run still warns
        about it, and the folder is removed if this lock created it and nothing else is
        in it."""
        if self.fd is None:
            return
        if remove_created_folder:
            self._give_back()
            _remove_empty(self.created)
            return
        try:
            # not a file that came after another rank removed ours (remove_for_holder)
            if os.stat(self.path).st_ino == self.inode:
                self.path.unlink()
        except FileNotFoundError:
            pass
        finally:
            os.close(self.fd)       # releases the flock
            self.fd = None

    def leave(self, ended):
        """Unlock and keep the lock file, its record with ``ended`` (why the run ended
        without its final summary.json: a full disk), instead of removing it: an unlocked
        lock file that is not empty is a run that did not finish (:attr:`stale`), and
        ``ended`` tells the next run and the scripts (:func:`probe`) that it was not
        killed.  The record is rewritten in place (the file's block is already there, so
        a full disk does not refuse it).  Returns whether the file is left: not when it is
        gone (the folder removed or renamed during the run: nothing to tell).  Raises the
        OSError of a failed write (the lock file then holds its earlier record: a killed
        run's)."""
        if self.fd is None:
            return False
        try:
            try:
                if os.stat(self.path).st_ino != self.inode:
                    return False
            except FileNotFoundError:
                return False
            data = (json.dumps({**(read_record(_read(self.fd)) or {}), "ended": ended}) + "\n").encode()
            os.pwrite(self.fd, data, 0)
            os.ftruncate(self.fd, len(data))
            os.fsync(self.fd)
        finally:
            os.close(self.fd)       # releases the flock
            self.fd = None
        return True

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()


#: how long a run waits for :func:`probe`s (shared flocks, held for microseconds) to let go
#: before it takes the folder for busy (a run holds the lock exclusively)
PROBE_WAIT_S = 2.0


def _lock_past_probes(fd):
    """Lock ``fd`` exclusively, waiting up to :data:`PROBE_WAIT_S` while only shared
    locks (:func:`probe`s of scripts/check_outputs.py, join_summaries.py) are in the
    way; raises BlockingIOError at once when an exclusive holder (a run) has it."""
    deadline = time.monotonic() + PROBE_WAIT_S
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            # a shared lock granted now means no run holds the file: a probe's is in the way
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                raise BlockingIOError("held by a run") from None
            fcntl.flock(fd, fcntl.LOCK_UN)
            if time.monotonic() > deadline:
                raise BlockingIOError("held by probes") from None
            time.sleep(0.005)


def probe(folder):
    """A look at the lock of ``folder`` that changes nothing: (state, record).  state:
    ``absent`` (no lock file), ``held`` (a live process holds the flock: a run is going)
    or ``free`` (the file is there and unlocked: its run ended without removing it,
    killed unless its record says ``ended``; the test :meth:`OutputLock.acquire` makes
    for :attr:`OutputLock.stale`).  record: :func:`read_record` of the file's text.
    The flock is tried shared and dropped at once; a run starting in that instant waits
    for it (:func:`_lock_past_probes`).  Whether a run on another host
    shows as ``held`` depends on the filesystem (NFS passes flocks between hosts, a
    ``local_lock`` mount does not): the caller compares ``record["host"]``."""
    try:
        fd = os.open(Path(folder) / LOCK_NAME, os.O_RDONLY)
    except FileNotFoundError:
        return "absent", None
    try:
        text = _read(fd)
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            state = "free"
        except BlockingIOError:
            state = "held"
    finally:
        os.close(fd)            # releases the probe's flock
    return state, read_record(text)


def remove_for_holder(folder, taken):
    """Put the lock file of ``folder`` back as it was (:func:`put_back`) and, when the
    run created the folder and nothing else is in it, remove the folder, for the holder (``taken``: its
    :meth:`OutputLock.taken`), a process of the same job that may not get to do it (a job
    stopped during its set-up: the holder may wait for the caller in a collective call
    until it is killed).  It still holds the lock, so the file at the path is the one it
    locked, unless it is gone: only that inode is put back."""
    folder = Path(folder)
    put_back(folder / LOCK_NAME, taken["inode"], taken.get("before"))
    _remove_empty([Path(p) for p in taken.get("created", [])])


def put_back(path, inode, before):
    """The lock file ``path`` (if it is still the one locked, ``inode``) as it was before
    the lock was taken: ``before`` = (bytes, atime_ns, mtime_ns) of a file that was there,
    else None (removed).  A refused run leaves the folder as it was: removing a killed
    run's lock file lost the warning about it for the next run."""
    try:
        if os.stat(path).st_ino != inode:
            return
        if before is None:
            os.unlink(path)
            return
        data, atime, mtime = before
        with open(path, "r+b") as f:
            f.truncate(0)
            f.write(data)               # fits: truncating freed its blocks
        os.utime(path, ns=(atime, mtime))
    except OSError:
        pass


def _remove_empty(folders):
    """Remove ``folders`` (the deepest first) while they are empty."""
    for p in folders:
        try:
            p.rmdir()
        except OSError:
            return


def _read(fd, raw=False):
    """The lock file's text (its first 64 kB; ``raw``: as bytes)."""
    try:
        data = os.pread(fd, 1 << 16, 0)
    except OSError:
        data = b""
    return data if raw else data.decode(errors="replace")
