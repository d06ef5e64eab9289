"""The seal of a checkpoint file: a SHA-256 of its HDF5 metadata, checked before
libhdf5 opens the file.

libhdf5 does not survive every damaged metadata byte: one bit in the global-heap index
of the ``format`` attribute's string made it segfault on open (measured with Debian's
HDF5 1.10, ``tests/io/test_checkpoint_restart.py``), which no ``except`` can catch and
which ended ``--restart latest`` before it could fall back to an older checkpoint.  The
dataset checksums cannot help: they are read through libhdf5.

So the file is created with a 512-byte HDF5 *user block* (bytes libhdf5 leaves alone;
the HDF5 file starts after it) and, once complete, rank 0 writes into it: :data:`MAGIC`,
then JSON with the file's size, the byte ranges of the datasets' values (their own
``sha256`` attributes check those, naming the dataset) and the SHA-256 of every other
byte after the user block (superblock, object headers, attributes, heaps).  A reader
hashes those bytes with plain file reads; a mismatch is a :class:`CheckpointError`
without libhdf5 ever parsing the file.  A file without the seal (written before it)
is opened as before.
"""

from __future__ import annotations

import hashlib
import json
import os

from lc_petsc.errors import CheckpointError

USERBLOCK = 512
MAGIC = b"lc_petsc checkpoint seal 1\n"


def _outside_digest(path, ranges, size):
    """SHA-256 of the bytes of ``path`` from USERBLOCK to ``size`` outside ``ranges``."""
    h = hashlib.sha256()
    at = USERBLOCK
    with open(path, "rb") as fh:
        for start, n in sorted(ranges) + [(size, 0)]:
            if start > at:
                fh.seek(at)
                h.update(fh.read(start - at))
            at = max(at, start + n)
    return h.hexdigest()


def seal(path, h5py, datasets):
    """Rank 0, serial, on the closed complete file: write the seal into its user block."""
    with h5py.File(str(path), "r") as f:
        ranges = [(int(f[k].id.get_offset()), int(f[k].id.get_storage_size())) for k in datasets]
    size = os.path.getsize(path)
    text = MAGIC + json.dumps({"size": size, "values": ranges,
                               "sha256": _outside_digest(path, ranges, size)}).encode()
    if len(text) > USERBLOCK:
        raise ValueError(f"checkpoint seal of {len(text)} bytes does not fit the {USERBLOCK}-byte user block")
    with open(path, "r+b") as fh:
        fh.write(text.ljust(USERBLOCK, b"\0"))


def check_seal(name):
    """Raise CheckpointError when the file ``name`` has a seal its bytes do not match
    (serial, plain reads: nothing is parsed by libhdf5)."""
    try:
        with open(name, "rb") as fh:
            head = fh.read(USERBLOCK)
    except OSError as e:
        raise CheckpointError(f"{name}: cannot read the checkpoint ({e.strerror or e})") from None
    if not head.startswith(MAGIC):
        return                        # no seal: written before it (or not a checkpoint)
    try:
        rec = json.loads(head[len(MAGIC):].rstrip(b"\0"))
        size, ranges, digest = int(rec["size"]), [tuple(r) for r in rec["values"]], rec["sha256"]
    except (ValueError, KeyError, TypeError):
        raise CheckpointError(f"{name}: corrupt checkpoint: its seal (the user block's checksum "
                              "record) is damaged") from None
    have = os.path.getsize(name)
    if have != size:
        raise CheckpointError(f"{name}: corrupt checkpoint: truncated or extended ({have} bytes, "
                              f"written as {size})")
    if _outside_digest(name, ranges, size) != digest:
        raise CheckpointError(f"{name}: corrupt checkpoint: its HDF5 metadata (all but the datasets' "
                              "values) fails its checksum (sha256 in the user block); not opened")
