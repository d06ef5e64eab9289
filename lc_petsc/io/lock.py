"""One run per output folder: an exclusive ``flock`` on ``<out>/.lc_petsc.lock``.

Rank 0 of a run takes the lock before it reads or changes anything in the folder and
holds it for the whole run; the lock file records who holds it (PID, host, start time,
command), so a second run into the same folder is refused with a message naming the
running one.  ``flock`` locks belong to the open file and are released by the kernel
when the holder dies, however it dies (SIGKILL, a crash, a lost node's process), so a
killed run never blocks the folder.  A clean exit removes the lock file; a lock file
that is present, unlocked and not empty was left by a run that did not finish, which
the next run reports (:attr:`OutputLock.stale`).

The file is removed only while it is locked, and a lock is only trusted if the locked
file is still the one at the path (the inode check in :meth:`acquire`): otherwise a run
that opened the old file just before it was removed could lock a deleted file while a
third run locks the new one.  Another process of the same job may remove the file for
its holder (:func:`remove_for_holder`, a job stopped during its set-up): the holder then
leaves alone whatever file is at the path when it releases the lock.
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


def describe_holder(text):
    """'pid 123 on host h, started 2026-12-01 10:00:00 UTC (python ...)' from a lock file's text."""
    try:
        d = json.loads(text)
        return (f"pid {d['pid']} on host {d['host']}, started {d['started']}"
                + (f" ({d['command']})" if d.get("command") else ""))
    except (ValueError, KeyError, TypeError):
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
        existed = self.path.exists()
        for _ in range(100):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
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
        old = _read(self.fd)
        if old.strip():
            self.stale = describe_holder(old)
        record = {"pid": os.getpid(), "host": socket.gethostname(),
                  "started": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
                  "command": " ".join(os.path.basename(a) if i == 0 else a
                                      for i, a in enumerate(sys.argv))[:300]}
        try:
            os.ftruncate(self.fd, 0)
            os.pwrite(self.fd, (json.dumps(record) + "\n").encode(), 0)
            os.fsync(self.fd)
        except BaseException:
            self._give_back(old, existed)
            raise
        return self

    def _give_back(self, old, existed):
        """Undo a lock whose record could not be written (ENOSPC): the lock file as it
        was (a killed run's record kept for the next run's warning) or, if this run
        created it, removed; then unlock."""
        try:
            if existed:
                os.ftruncate(self.fd, 0)
                os.pwrite(self.fd, old.encode(), 0)     # fits: truncating freed its blocks
            elif os.stat(self.path).st_ino == self.inode:
                self.path.unlink()
        except OSError:
            pass
        finally:
            os.close(self.fd)
            self.fd = None

    def taken(self):
        """What another process of the same job needs for :func:`remove_for_holder`."""
        return {"stale": self.stale, "inode": self.inode, "created_folder": self.created_folder,
                "created": [str(p) for p in self.created]}

    def release(self, remove_created_folder=False):
        """Remove the lock file and unlock.  ``remove_created_folder``: also remove the
        folder if this lock created it and nothing else is in it (a run refused before
        it wrote anything leaves no trace)."""
        if self.fd is None:
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
        if remove_created_folder:
            _remove_empty(self.created)

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()


def remove_for_holder(folder, taken):
    """Remove the lock file of ``folder`` and, when the run created the folder and
    nothing else is in it, the folder, for the holder (``taken``: its
    :meth:`OutputLock.taken`), a process of the same job that may not get to do it (a job
    stopped during its set-up: the holder may wait for the caller in a collective call
    until it is killed).  It still holds the lock, so the file at the path is the one it
    locked, unless it is gone: only that inode is removed."""
    folder = Path(folder)
    try:
        if os.stat(folder / LOCK_NAME).st_ino == taken["inode"]:
            (folder / LOCK_NAME).unlink()
    except OSError:
        pass
    _remove_empty([Path(p) for p in taken.get("created", [])])


def _remove_empty(folders):
    """Remove ``folders`` (the deepest first) while they are empty."""
    for p in folders:
        try:
            p.rmdir()
        except OSError:
            return


def _read(fd):
    try:
        return os.pread(fd, 4096, 0).decode(errors="replace")
    except OSError:
        return ""
