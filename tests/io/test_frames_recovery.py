"""A restart whose frames.h5 cannot be appended to (missing, truncated, corrupt):
refused without --force, saying what --force keeps; with --force the run continues
from the checkpoint into a new frames.h5, the old file renamed aside byte for byte,
the rows recovered from it and from the checkpoints equal to the first run's, the
others NaN and marked in /frame_valid (not made up), the continuation bit for bit the
straight run's, the exports and summary.json consistent with it, and a later restart
appending to it."""

import hashlib
import json
import os
import re
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from lc_petsc.batch import main
from lc_petsc.crossings import count_frames
from lc_petsc.io import read_frames

from sim_helpers import break_header, hairball_toml  # noqa: E402

SCENE = hairball_toml(frames="{frames}",
                      output="checkpoint_every = 2\ncheckpoints_kept = {kept}\ncontact_sheet = 4")


def _config(folder, frames=6, kept=5):
    p = Path(folder) / "s.toml"
    p.write_text(SCENE.format(frames=frames, kept=kept))
    return str(p)


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """The reference: 10 frames straight, serial (positions and times of frames.h5)."""
    d = tmp_path_factory.mktemp("straight")
    assert main([_config(d, frames=10), "--out", str(d / "out"), "--quiet"]) == 0
    with h5py.File(d / "out" / "frames.h5", "r") as f:
        return f["positions"][...], f["time"][...]


def _run(cfg, out, *extra):
    return main([cfg, "--out", str(out), "--quiet", *extra])


def _sha(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _snapshot(folder):
    return {str(p.relative_to(folder)): (_sha(p), p.stat().st_mtime_ns)
            for p in sorted(Path(folder).rglob("*")) if p.is_file()}


def _check_rows(out, ref, recovered, lost, upto):
    """Rows ``recovered`` and those after the checkpoint up to ``upto`` equal the straight
    run's bit for bit (times too); rows ``lost`` are NaN and marked invalid."""
    got = read_frames(Path(out) / "frames.h5")
    pos, t, valid = got["positions"], got["time"], got["frame_valid"]
    assert pos.shape == (upto + 1,) + ref[0].shape[1:]
    kept = sorted(set(range(upto + 1)) - set(lost))
    assert valid.tolist() == [k not in lost for k in range(upto + 1)]
    assert np.array_equal(pos[kept], ref[0][kept]) and np.array_equal(t[kept], ref[1][kept])
    assert np.isnan(pos[lost]).all() and np.isnan(t[lost]).all()
    assert set(recovered) <= set(kept)
    return got


def test_deleted_frames_file_continues_with_force(tmp_path, straight, capsys):
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    assert _run(cfg, out, "--frames", "4") == 0              # checkpoints at 2 and 4
    os.unlink(out / "frames.h5")
    before = _snapshot(out)
    capsys.readouterr()
    assert _run(cfg, out, "--frames", "6", "--restart", "latest") == 2
    err = capsys.readouterr().err
    assert "frames file is missing" in err and "With --force the run continues from" in err, err
    assert "frame(s) 2, 4 recovered" in err and "frame(s) 0-1, 3 lost" in err, err
    assert _snapshot(out) == before, "a refused restart changed the folder"

    assert _run(cfg, out, "--frames", "6", "--restart", "latest", "--force") == 0
    err = capsys.readouterr().err
    assert "--force" in err and "frame(s) 2, 4 recovered (frame(s) 2, 4 from checkpoints)" in err, err
    assert "frame(s) 0-1, 3 lost" in err and "hold NaN" in err, err
    _check_rows(out, straight, recovered=[2, 4], lost=[0, 1, 3], upto=6)
    summary = json.loads((out / "summary.json").read_text())
    rec = summary["frames_recovery"]
    assert rec["recovered_frames"] == [[2, 2], [4, 4]] and rec["missing_frames"] == [[0, 1], [3, 3]]
    assert rec["from_checkpoints"] == [2, 4] and rec["from_frames_file"] == [] and rec["renamed_to"] is None
    assert any("frame(s) 0-1, 3 lost" in w for w in summary["warnings"])
    # the exports show the rows that hold a frame, and only those
    xdmf = (out / "frames.xdmf").read_text()
    assert [f'Name="frame_{k}"' in xdmf for k in range(7)] == [False, False, True, False, True, True, True]
    from pxr import Usd, UsdGeom
    stage = Usd.Stage.Open(str(out / "frames.usdc"))
    samples = UsdGeom.BasisCurves(stage.GetPrimAtPath("/Groom/wisps")).GetPointsAttr().GetTimeSamples()
    assert samples == [2.0, 4.0, 5.0, 6.0]
    # preview frame 0 was lost: the nearest frame that holds one is drawn instead
    assert sorted(p.name for p in (out / "previews").iterdir()) == ["frame_00002.png", "frame_00006.png"]
    steps, _ = count_frames(out / "frames.h5")
    assert [s["step"] for s in steps] == [4, 5]          # 4 -> 5 and 5 -> 6 only

    # a later restart of the recovered run appends to it like any other
    assert _run(cfg, out, "--frames", "9", "--restart", "latest") == 0
    got = _check_rows(out, straight, recovered=[], lost=[0, 1, 3], upto=9)
    assert got["frame_valid"][4:].all()
    assert json.loads((out / "summary.json").read_text())["frames_recovery"] is None


def _corrupt_last_row(path):
    """Random bytes over the last frame row's positions (frames.h5 has no checksums:
    only the checkpoint of that frame can tell)."""
    with h5py.File(path, "r") as f:
        d = f["positions"]
        at = d.id.get_chunk_info(d.shape[0] - 1).byte_offset
    with open(path, "r+b") as fh:
        fh.seek(at + 240)
        fh.write(np.random.default_rng(3).bytes(2400))


def _truncate(path):
    os.truncate(path, os.path.getsize(path) // 2)


def _garbage_in_the_metadata(path):
    with open(path, "r+b") as fh:
        fh.seek(800)
        fh.write(np.random.default_rng(4).bytes(1024))


def _damaged_time_index(path):
    """The chunk index (a version-1 B-tree node, "TREE") of /time claims more children
    than a node holds: /time cannot be read ("Can't read data"), /positions can.  The
    check before the restart looked at the shapes only; the restart then failed in its
    frame loop (exit 3) after removing the outputs, and again on every try."""
    data = Path(path).read_bytes()
    for at in [m.start() for m in re.finditer(b"TREE", data)]:
        Path(path).write_bytes(data[:at + 6] + b"\xff\xff" + data[at + 8:])
        with h5py.File(path, "r") as f:
            try:
                f["time"][...]
            except KeyError:        # the root group's index: nothing opens
                continue
            except OSError:
                f["positions"][...]
                return
    raise AssertionError("no chunk index of /time found")


@pytest.mark.parametrize("damage, from_file, lost", [
    (_corrupt_last_row, [[0, 1], [3, 3], [5, 5]], []),     # row 6 replaced by its checkpoint
    (_truncate, [], [0, 1, 3, 5]),
    (_garbage_in_the_metadata, [], [0, 1, 3, 5]),
    (_damaged_time_index, [], [0, 1, 3, 5]),
])
def test_damaged_frames_file_is_set_aside_and_the_run_continues(tmp_path, straight, capsys, damage,
                                                                 from_file, lost):
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    assert _run(cfg, out) == 0                       # 6 frames, checkpoints 2, 4, 6
    damage(out / "frames.h5")
    damaged = _sha(out / "frames.h5")
    copy = tmp_path / "damaged.h5"
    shutil.copy(out / "frames.h5", copy)
    capsys.readouterr()
    assert _run(cfg, out, "--frames", "8", "--restart", "latest") == 2
    err = capsys.readouterr().err
    assert "--force" in err and "frames.unusable-1.h5 (kept, never removed)" in err, err
    assert _sha(out / "frames.h5") == damaged
    assert _run(cfg, out, "--frames", "8", "--restart", "latest", "--force") == 0
    err = capsys.readouterr().err
    aside = out / "frames.unusable-1.h5"
    assert f"renamed to {aside}" in err, err
    assert _sha(aside) == damaged, "the damaged frames.h5 was not kept byte for byte"
    _check_rows(out, straight, recovered=[2, 4, 6], lost=lost, upto=8)
    rec = json.loads((out / "summary.json").read_text())["frames_recovery"]
    assert rec["renamed_to"] == str(aside) and rec["from_checkpoints"] == [2, 4, 6]
    assert rec["from_frames_file"] == from_file
    assert rec["missing_frames"] == ([] if from_file else [[0, 1], [3, 3], [5, 5]])
    # a new run into the folder keeps the file set aside (it removes only its own outputs)
    assert _run(cfg, out, "--frames", "2") == 0
    assert _sha(aside) == damaged


def test_old_file_gone_between_plan_and_write_loses_its_rows_only(tmp_path, straight, monkeypatch):
    """The set-aside file disappears after the plan was made (another program): its rows
    are lost, the checkpoints' rows are still written and the run goes on (the read on
    rank 0 used to raise there while the other ranks waited in the row writes)."""
    from lc_petsc.io import recovery
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    assert _run(cfg, out) == 0
    _corrupt_last_row(out / "frames.h5")
    write = recovery.write_recovered

    def old_file_gone(writer, plan, old_path, offsets, comm):
        assert plan.from_file                      # the plan would take rows from it
        os.rename(old_path, tmp_path / "elsewhere.h5")
        return write(writer, plan, old_path, offsets, comm)
    monkeypatch.setattr(recovery, "write_recovered", old_file_gone)
    assert _run(cfg, out, "--frames", "8", "--restart", "latest", "--force") == 0
    _check_rows(out, straight, recovered=[2, 4, 6], lost=[0, 1, 3, 5], upto=8)


def test_every_two_recovers_only_the_rows_of_written_frames(tmp_path, capsys):
    """output.every = 2, checkpoint at frame 3 (not a row): rows 0 and 1 lost, nothing
    from the checkpoint, whose frame is no row."""
    cfg = _config(tmp_path, frames=3)
    text = Path(cfg).read_text().replace("checkpoint_every = 2", "checkpoint_every = 3\nevery = 2")
    Path(cfg).write_text(text)
    out = tmp_path / "out"
    assert _run(cfg, out) == 0
    os.unlink(out / "frames.h5")
    capsys.readouterr()
    assert _run(cfg, out, "--frames", "5", "--restart", "latest", "--force") == 0
    err = capsys.readouterr().err
    assert "(output.every = 2), no frame recovered (none), frame(s) 0-2 lost" in err, err
    got = read_frames(out / "frames.h5")
    assert got["frame_valid"].tolist() == [False, False, True]
    assert np.isnan(got["positions"][:2]).all() and np.isfinite(got["positions"][2]).all()


def _flip_a_bit(path, row, at=240):
    """One bit of /positions row ``row`` flipped (a bit error of a disk or a copy)."""
    with h5py.File(path, "r") as f:
        start = f["positions"].id.get_chunk_info(row).byte_offset
    with open(path, "r+b") as fh:
        fh.seek(start + at)
        b = fh.read(1)[0]
        fh.seek(start + at)
        fh.write(bytes([b ^ 0x10]))


def test_a_bit_flipped_in_a_kept_row_is_refused_before_the_restart_changes_anything(tmp_path, straight, capsys):
    """frames.h5 had no checksums: a bit flipped in row 3 was kept by the restart, which
    appended to the file (exit 0), and a reader got a wrong number.  Now every dataset
    has Fletcher-32 checksums: the reader gets an error, the restart is refused before
    it changes anything, and --force recovers every other row."""
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    assert _run(cfg, out) == 0                       # 6 frames, checkpoints 2, 4, 6
    with h5py.File(out / "frames.h5", "r") as f:
        assert all(d.fletcher32 for d in f.values()), {k: d.fletcher32 for k, d in f.items()}
    _flip_a_bit(out / "frames.h5", 3)
    with h5py.File(out / "frames.h5", "r") as f:
        assert np.array_equal(f["positions"][2], straight[0][2])
        with pytest.raises(OSError, match="Fletcher32 checksum"):
            f["positions"][3]
    before = _snapshot(out)
    capsys.readouterr()
    assert _run(cfg, out, "--frames", "8", "--restart", "latest") == 2
    err = capsys.readouterr().err
    assert (f"{out / 'frames.h5'}: /positions row 3 (frame 3) cannot be read (data error detected by "
            f"Fletcher32 checksum): the file is damaged. With --force") in err, err
    assert "frames.unusable-1.h5 (kept, never removed)" in err, err
    assert _snapshot(out) == before, "a refused restart changed the folder"
    assert _run(cfg, out, "--frames", "8", "--restart", "latest", "--force") == 0
    _check_rows(out, straight, recovered=[0, 1, 2, 4, 5, 6], lost=[3], upto=8)
    rec = json.loads((out / "summary.json").read_text())["frames_recovery"]
    assert rec["from_frames_file"] == [[0, 1], [5, 5]] and rec["from_checkpoints"] == [2, 4, 6]
    assert rec["missing_frames"] == [[3, 3]]


def test_damaged_wisp_offsets_are_named(tmp_path, capsys):
    """A damaged /wisp_offsets (here with a valid checksum, as in a file from before
    them) passed the restart's check and showed up only as a MemoryError in the
    crossing check's warning."""
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    assert _run(cfg, out) == 0
    with h5py.File(out / "frames.h5", "r+") as f:
        f["wisp_offsets"][1] = 1 << 60
    capsys.readouterr()
    assert _run(cfg, out, "--frames", "8", "--restart", "latest") == 2
    err = capsys.readouterr().err
    assert (f"{out / 'frames.h5'}: /wisp_offsets is not 0, increasing, ..., 505 (the vertex count of "
            "/positions): entry 2 is 202 after 1152921504606846976; the file is damaged. With --force") in err, err
    with pytest.raises(ValueError, match=r"/wisp_offsets is not 0, increasing, \.\.\., 505"):
        count_frames(out / "frames.h5")
    with h5py.File(out / "frames.h5", "r+") as f:     # increasing, but not the wisps of /polylines
        f["wisp_offsets"][1] = 100
    assert _run(cfg, out, "--frames", "8", "--restart", "latest") == 2
    assert (f"{out / 'frames.h5'}: /wisp_offsets gives wisp 0 vertices 0-99, /polylines (the wisps written "
            "with it) does not: the file is damaged") in capsys.readouterr().err
    with h5py.File(out / "frames.h5", "r+") as f:     # both valid, but not the scene's wisps
        off = f["wisp_offsets"][...]
        f["polylines"][...] = np.concatenate([[2, b - a, *range(a, b)] for a, b in zip(off[:-1], off[1:])])
    assert _run(cfg, out, "--frames", "8", "--restart", "latest") == 2
    assert "/wisp_offsets differs from the scene's wisp sizes" in capsys.readouterr().err


def _without_checksums(path):
    """``path`` rewritten as frames.h5 was before the checksums: the same datasets,
    chunks and attributes, no Fletcher-32."""
    old = Path(path).with_suffix(".old.h5")
    with h5py.File(path, "r") as f, h5py.File(old, "w") as g:
        g.attrs.update(dict(f.attrs))
        for k, d in f.items():
            grows = d.maxshape[0] is None
            g.create_dataset(k, data=d[...], chunks=d.chunks if grows else None, maxshape=d.maxshape)
            g[k].attrs.update(dict(d.attrs))
    os.replace(old, path)


def test_a_frames_file_from_before_the_checksums_still_restarts(tmp_path, straight, capsys):
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    assert _run(cfg, out) == 0
    _without_checksums(out / "frames.h5")
    capsys.readouterr()
    assert _run(cfg, out, "--frames", "8", "--restart", "latest") == 0
    err = capsys.readouterr().err
    assert "was written before frames.h5 had checksums: its kept rows could be read but not verified" in err
    _check_rows(out, straight, recovered=[], lost=[], upto=8)
    with h5py.File(out / "frames.h5", "r") as f:
        assert not f["positions"].fletcher32


def _positions_key(data, path, row):
    """Where the key of /positions row ``row`` starts in ``data`` (the bytes of the file
    at ``path``): the key before the child pointer to the row's chunk in a version-1
    B-tree node ("TREE"): chunk size (4 bytes), filter mask (4), 4 offsets of 8 (row first)."""
    with h5py.File(path, "r") as f:
        addr = f["positions"].id.get_chunk_info(row).byte_offset
    node = data.find(b"TREE")
    while node >= 0 and data.find(addr.to_bytes(8, "little"), node, node + 4096) < 0:
        node = data.find(b"TREE", node + 4)
    return data.find(addr.to_bytes(8, "little"), node) - 40


def _lose_a_chunk(path, row):
    """The key of /positions row ``row`` in its chunk index (a version-1 B-tree node,
    which has no checksum) given a huge row coordinate, as one flipped bit does (found
    by a random-corruption sweep): libhdf5 no longer finds the chunk and reads the fill
    value without an error."""
    data = bytearray(Path(path).read_bytes())
    data[_positions_key(data, path, row) + 15] ^= 0x80
    Path(path).write_bytes(bytes(data))


def test_a_chunk_lost_from_the_index_reads_as_nan_and_is_refused(tmp_path, straight, capsys):
    """One flipped bit in the chunk index made row 4 read as zeros (the fill value), no
    error: the restart kept it, the crossing check then ran out of memory on 2,020
    vertices at the origin.  Now the fill value is NaN, which no frame holds."""
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    assert _run(cfg, out) == 0
    _lose_a_chunk(out / "frames.h5", 4)
    with h5py.File(out / "frames.h5", "r") as f:
        assert np.isnan(f["positions"][4]).all() and np.array_equal(f["positions"][3], straight[0][3])
    capsys.readouterr()
    assert _run(cfg, out, "--frames", "8", "--restart", "latest") == 2
    err = capsys.readouterr().err
    assert (f"{out / 'frames.h5'}: /positions row 4 (frame 4): its chunk is missing from the chunk index (a "
            "read returns the fill value, NaN): the file's chunk index (which has no checksum in the HDF5 1.8 "
            "format) is damaged. With --force") in err, err


def test_a_chunk_index_key_naming_another_row_is_found_before_any_read(tmp_path):
    """The key of row 4's chunk (its row coordinate, in the chunk index, which has no
    checksum) changed to 2: libhdf5 reads row 4's chunk for row 2, whose Fletcher-32
    checksum passes (it covers the chunk's bytes, not its row), and rows 3-4 as NaN.  A
    restart keeping rows 0-2 kept the wrong row 2, and a reader of row 2 alone (a
    preview) drew frame 4 there, without a word.  And a damaged chunk size crashed every
    reader (a segfault in libhdf5).  Now the index is looked up for every chunk before
    any read (frames.index_problem), by the restart and by every reader."""
    from lc_petsc.io.frames import resumable_problem
    cfg, out = _config(tmp_path), tmp_path / "out"
    assert _run(cfg, out) == 0
    path = out / "frames.h5"
    with h5py.File(path, "r") as f:
        n_wisps, n_vertices = f["wisp_offsets"].shape[0] - 1, f["positions"].shape[1]
        rows = f["positions"][...]
    good = Path(path).read_bytes()
    data = bytearray(good)
    key = _positions_key(data, path, 4)
    data[key + 8:key + 16] = (2).to_bytes(8, "little")
    Path(path).write_bytes(bytes(data))
    with h5py.File(path, "r") as f:      # what libhdf5 does with it
        got = f["positions"][2]
        assert [k for k in range(7) if np.array_equal(got, rows[k])] == [4], "row 2 reads row 4"
        assert np.isnan(f["positions"][3]).all() and np.array_equal(f["positions"][5], rows[5])
    assert resumable_problem(path, n_wisps, n_vertices, 3) == (
        f"{path}: /positions row 4 (frame 4): its chunk is missing from the chunk index (a read returns the fill "
        "value, NaN): the file's chunk index (which has no checksum in the HDF5 1.8 format) is damaged")
    with pytest.raises(ValueError, match=r"/positions row 4 \(frame 4\): its chunk is missing from the chunk "
                                         r"index .*; the rows before it may still be read, or rerun from"):
        read_frames(path, frames=[2])
    # a chunk's stored size 1 (not its 3 x 8 bytes per vertex + 4 for the checksum)
    data = bytearray(good)
    data[key:key + 4] = (1).to_bytes(4, "little")
    Path(path).write_bytes(bytes(data))
    assert f"/positions row 4 (frame 4): its chunk index entry is damaged (stored size 1 bytes, not " \
           f"{24 * n_vertices + 4};" in resumable_problem(path, n_wisps, n_vertices, 3)
    with pytest.raises(ValueError, match="its chunk index entry is damaged"):
        read_frames(path, frames=[2])


def test_recovery_names_damaged_wisp_offsets(tmp_path):
    """What --force can recover from a file whose /wisp_offsets is damaged (not 0,
    increasing, ..., the vertex count) says so, where one of another scene says that; on
    main both read "it has other wisps than the scene"."""
    from lc_petsc.io.recovery import _file_rows
    offsets = np.array([0, 2, 5])
    p = tmp_path / "frames.h5"

    def write(stored):
        with h5py.File(p, "w") as f:
            f.create_dataset("positions", data=np.zeros((3, 5, 3)))
            f.create_dataset("time", data=np.arange(3) / 30.0)
            f.create_dataset("wisp_offsets", data=np.asarray(stored, np.int64))
            f.attrs["dt"], f.attrs["every"] = 1 / 30.0, 1
        return _file_rows(p, offsets, 3, 1 / 30.0, 1, {})

    assert write([0, 2, 5]) == ([0, 1, 2], "")
    rows, why = write([0, 2 + 2 ** 40, 5])             # a flipped bit
    assert rows == [] and "/wisp_offsets is not 0, increasing" in why and "damaged" in why
    assert write([0, 3, 5]) == ([], "it has other wisps than the scene")


def _swap_chunks(path, a, b, at):
    """The chunk index entries of /positions rows ``a`` and ``b`` exchanged, in the
    version-1 B-tree node, which has no checksum: their child addresses (``at`` 40, after
    the key) or the row offsets of their keys (``at`` 8)."""
    data = bytearray(Path(path).read_bytes())
    ka, kb = _positions_key(data, path, a) + at, _positions_key(data, path, b) + at
    data[ka:ka + 8], data[kb:kb + 8] = data[kb:kb + 8], data[ka:ka + 8]
    Path(path).write_bytes(bytes(data))


@pytest.mark.parametrize("at, row_4", [(40, "row 2"), (8, "NaN")], ids=["children", "keys"])
def test_two_rows_exchanged_in_the_chunk_index_fail_their_digests(tmp_path, straight, capsys, at, row_4):
    """Rows 2 and 4 exchanged in /positions' chunk index (their chunk addresses, or their
    keys' row offsets): every read of row 2 returned row 4's positions without an error,
    and the index check passed (each row found, of its size, at a chunk no other row
    has); a restart keeping rows 0-2 kept the wrong row.  Now every row has a digest in
    /row_digest (over its values, its row number and its time), checked by every read of
    a row and by the restart."""
    from lc_petsc.io.frames import index_problem, resumable_problem
    from lc_petsc.io.frames_read import FramesReader
    cfg, out = _config(tmp_path), tmp_path / "out"
    assert _run(cfg, out) == 0
    path = out / "frames.h5"
    with h5py.File(path, "r") as f:
        n_wisps, n_vertices = f["wisp_offsets"].shape[0] - 1, f["positions"].shape[1]
    _swap_chunks(path, 2, 4, at)
    with h5py.File(path, "r") as f:      # what libhdf5 does with it
        assert np.array_equal(f["positions"][2], straight[0][4])
        if row_4 == "row 2":
            assert np.array_equal(f["positions"][4], straight[0][2])
        else:                            # (the keys out of order: rows 3 and 4 are not found)
            assert np.isnan(f["positions"][4]).all() and np.isnan(f["positions"][3]).all()
        assert index_problem(f) is None
    with FramesReader(path) as r:
        with pytest.raises(ValueError, match=r"^/positions row 2 \(frame 2\) does not match its "
                                             r"/row_digest: another row's values \(a damaged chunk index\)"):
            r.row(2)
        with pytest.raises(ValueError, match=r"/positions row 4 \(frame 4\) " + (
                "does not match its /row_digest" if row_4 == "row 2" else "reads as NaN")):
            r.row(4)
        assert np.array_equal(r.row(1), straight[0][1])
    assert resumable_problem(path, n_wisps, n_vertices, 3) == (
        f"{path}: /positions row 2 (frame 2) does not match its /row_digest: another row's values (a damaged "
        "chunk index), or its time in /time is another row's; the file is damaged")
    assert resumable_problem(path, n_wisps, n_vertices, 2) is None
    with pytest.raises(ValueError, match="row 2 .frame 2. does not match its /row_digest"):
        read_frames(path, frames=[2])
    with pytest.raises(ValueError, match="row 2 .frame 2. does not match its /row_digest"):
        read_frames(path)
    with pytest.raises(ValueError, match="row 2 .frame 2. does not match its /row_digest"):
        count_frames(path)
    # the restart from frame 4's checkpoint keeps rows 0-4: refused, nothing changed
    damaged = _sha(path)
    capsys.readouterr()
    assert _run(cfg, out, "--frames", "8", "--restart", str(out / "checkpoints" / "checkpoint_000004.h5")) == 2
    assert "/positions row 2 (frame 2) does not match its /row_digest" in capsys.readouterr().err
    assert _sha(path) == damaged


def test_a_frames_file_from_before_the_row_digests_still_reads_and_restarts(tmp_path, straight):
    """A frames.h5 without /row_digest (written before 2026-12-07) is read and continued
    unchecked; the continued file has no digests either (its kept rows have none)."""
    cfg, out = _config(tmp_path), tmp_path / "out"
    assert _run(cfg, out) == 0
    with h5py.File(out / "frames.h5", "r+") as f:
        assert f["row_digest"].shape == (7,) and f["row_digest"].dtype == np.uint64
        del f["row_digest"]
    got = read_frames(out / "frames.h5")
    assert np.array_equal(got["positions"], straight[0][:7])
    assert _run(cfg, out, "--frames", "8", "--restart", "latest") == 0
    _check_rows(out, straight, recovered=[], lost=[], upto=8)
    with h5py.File(out / "frames.h5", "r") as f:
        assert "row_digest" not in f
    assert [r["step"] for r in count_frames(out / "frames.h5")[0]] == list(range(8))


def _damage_chunk(path, name, row):
    """One byte of the chunk of /``name`` holding row ``row`` flipped (its Fletcher-32
    checksum then fails)."""
    with h5py.File(path, "r") as f:
        at = f[name].id.get_chunk_info_by_coord((row,)).byte_offset
    with open(path, "r+b") as fh:
        fh.seek(at + 3)
        b = fh.read(1)[0]
        fh.seek(at + 3)
        fh.write(bytes([b ^ 0xFF]))


def _restarted_from_checkpoint_4(cfg, out, tmp_path, straight, capsys):
    """A copy of the run folder ``out`` (returned as it was), then ``out`` restarted from
    checkpoint 4 to frame 8: it keeps rows 0-4 and rewrites the others (the straight run's)."""
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    capsys.readouterr()
    assert _run(cfg, out, "--frames", "8", "--restart", str(out / "checkpoints" / "checkpoint_000004.h5")) == 0, \
        capsys.readouterr().err
    _check_rows(out, straight, recovered=[], lost=[], upto=8)
    return copy


@pytest.mark.parametrize("name", ["time", "row_digest"])
def test_a_damaged_chunk_after_the_kept_rows_leaves_the_restart_and_the_recovery_alone(tmp_path, straight,
                                                                                     capsys, name):
    """A run continued by a restart keeps its first run's chunks of /time and /row_digest
    (5 rows here: run to frame 4, then to 8), so a damaged chunk can hold only rows after
    a checkpoint.  Each row's digest check had read the whole of /time and /row_digest
    (fault56's once-per-file table): the restart from checkpoint 4, which keeps the
    intact rows 0-4 only, was refused (exit 2), and --force recovered no row of the file
    (frames 0-4 lost besides the damaged chunk's; so were they with a damaged /row_digest
    chunk before).  A row's check now reads that row's entries when the whole table cannot be
    read, and the recovery leaves out a row whose digest cannot be read, not the file."""
    cfg = _config(tmp_path, kept=10)
    out = tmp_path / "out"
    assert _run(cfg, out, "--frames", "4") == 0                             # rows 0-4
    assert _run(cfg, out, "--frames", "8", "--restart", "latest") == 0      # rows 5-8: a second chunk
    with h5py.File(out / "frames.h5", "r") as f:
        assert f[name].chunks == (5,) and f[name].shape == (9,)
    _damage_chunk(out / "frames.h5", name, 5)
    copy = _restarted_from_checkpoint_4(cfg, out, tmp_path, straight, capsys)
    # from checkpoint 8 the damaged rows are kept rows: refused, then --force recovers the others
    assert _run(cfg, copy, "--frames", "9", "--restart", "latest") == 2
    # (the damaged chunk's rows, not every kept row: rows 0-8 before)
    assert f"/{name} rows 5-8 (frames 5-8) cannot be read (data error detected by Fletcher32" in \
        capsys.readouterr().err
    assert _run(cfg, copy, "--frames", "9", "--restart", "latest", "--force") == 0
    _check_rows(copy, straight, recovered=[0, 1, 2, 3, 4, 6, 8], lost=[5, 7], upto=9)
    rec = json.loads((copy / "summary.json").read_text())["frames_recovery"]
    # (checkpoints 2 and 4 are of the first run's config, --frames 4: not used)
    assert rec["from_frames_file"] == [[0, 4]] and rec["from_checkpoints"] == [6, 8]
    assert rec["missing_frames"] == [[5, 5], [7, 7]]


def _unopenable(dataset):
    return lambda path: break_header(path, dataset)


def _pinned_of_another_shape(path):
    with h5py.File(path, "r+") as f:
        n = len(f["pinned"])
        del f["pinned"]
        f.create_dataset("pinned", data=np.zeros(n + 3, bool))


@pytest.mark.parametrize("damage", [_unopenable("pinned"), _unopenable("radius"), _pinned_of_another_shape])
def test_a_damaged_dataset_the_rows_do_not_need_leaves_them_recovered(tmp_path, straight, capsys, damage):
    """--force recovers the rows of a frames.h5 whose /pinned or /radius is damaged (the
    new file takes them from the scene): the recovery read them before io57, which then
    checked every dataset's shape when the file was opened and recovered no row
    ("unreadable (/pinned has shape ...)"; fault51's damaged headers, /tmp/s51/f51/sw_metaa)."""
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    assert _run(cfg, out) == 0                       # 6 frames, checkpoints 2, 4, 6
    damage(out / "frames.h5")
    capsys.readouterr()
    assert _run(cfg, out, "--frames", "8", "--restart", "latest") == 2      # cannot be appended to
    err = capsys.readouterr().err
    assert "frame(s) 0-1, 3, 5 from the old frames.h5" in err and "no frame lost" in err, err
    assert _run(cfg, out, "--frames", "8", "--restart", "latest", "--force") == 0
    _check_rows(out, straight, recovered=[0, 1, 2, 3, 4, 5, 6], lost=[], upto=8)
    rec = json.loads((out / "summary.json").read_text())["frames_recovery"]
    assert rec["from_frames_file"] == [[0, 1], [3, 3], [5, 5]] and rec["from_checkpoints"] == [2, 4, 6]


def _short_last_time(path):
    with h5py.File(path, "r+") as f:
        f["time"].resize(f["time"].shape[0] - 1, axis=0)


def test_a_frame_dataset_short_after_the_kept_rows_leaves_the_restart_and_the_recovery_alone(tmp_path, straight,
                                                                                           capsys):
    """/time one row shorter than /positions (its last row, frame 6, has no time): the
    restart from checkpoint 4 keeps rows 0-4 and rewrites the others, as it did before
    io57, which refused it ("unreadable, truncated or damaged HDF5 file (/time has shape
    (6,) ...)") although its own check asks only the kept rows to be in every frame
    dataset; from checkpoint 6 the rows kept need row 6's time (refused) and --force
    recovers rows 0-5 of the file (io57: none)."""
    cfg = _config(tmp_path)
    out = tmp_path / "out"
    assert _run(cfg, out) == 0                       # 6 frames, checkpoints 2, 4, 6
    # a /row_digest short of the last row: the recovery takes the rows it holds (it ended
    # in an IndexError traceback before io57, and took none after)
    from lc_petsc.io.recovery import _file_rows
    short = tmp_path / "short_digest.h5"
    shutil.copy(out / "frames.h5", short)
    with h5py.File(short, "r+") as f:
        f["row_digest"].resize(6, axis=0)
        offsets, dt = f["wisp_offsets"][...], float(f.attrs["dt"])
    assert _file_rows(short, offsets, 7, dt, 1, {}) == (list(range(6)), "")
    _short_last_time(out / "frames.h5")
    copy = _restarted_from_checkpoint_4(cfg, out, tmp_path, straight, capsys)
    assert _run(cfg, copy, "--frames", "8", "--restart", "latest") == 2
    assert "/time has shape (6,), /positions 7 rows: row 6 (frame 6) has no /time entry" in capsys.readouterr().err
    assert _run(cfg, copy, "--frames", "8", "--restart", "latest", "--force") == 0
    _check_rows(copy, straight, recovered=list(range(7)), lost=[], upto=8)
    rec = json.loads((copy / "summary.json").read_text())["frames_recovery"]
    assert rec["from_frames_file"] == [[0, 1], [3, 3], [5, 5]] and rec["from_checkpoints"] == [2, 4, 6]
