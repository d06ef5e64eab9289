"""Every reader of frames.h5 (count_crossings, edge_strain, head_depth, to_usd,
read_frames, a restart) names the dataset and the rows of a chunk failing its checksum,
reads /time and /row_digest once per file, not once per row, and /positions in blocks of
consecutive rows, one read per block."""

import collections
import shutil
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from lc_petsc.batch import main
from lc_petsc.crossings import count_frames
from lc_petsc.io import read_frames
from lc_petsc.io.frames import resumable_problem
from lc_petsc.io.frames_read import FramesReader

from sim_helpers import break_header, hairball_toml  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "scripts"))
sys.path.insert(0, str(ROOT / "drivers"))

import count_crossings  # noqa: E402
import edge_strain  # noqa: E402
import head_depth  # noqa: E402
import to_usd  # noqa: E402


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A 6-frame run of a 5-wisp hairball (checkpoint at frame 3): its folder."""
    d = tmp_path_factory.mktemp("readers")
    cfg = d / "s.toml"
    cfg.write_text(hairball_toml(frames=6, output="checkpoint_every = 3\npreviews = false\nusd = false"))
    assert main([str(cfg), "--out", str(d / "out"), "--quiet"]) == 0
    return d


def _damaged_copy(run, tmp_path, name, row=0):
    """A copy of the run's frames.h5 with one byte of the chunk of /``name`` holding row
    ``row`` flipped (its Fletcher-32 checksum then fails)."""
    path = tmp_path / "frames.h5"
    shutil.copy(run / "out" / "frames.h5", path)
    with h5py.File(path, "r") as f:
        d = f[name]
        info = d.id.get_chunk_info_by_coord((row,) + (0,) * (d.ndim - 1))
    with open(path, "r+b") as fh:
        fh.seek(info.byte_offset + 3)
        b = fh.read(1)[0]
        fh.seek(info.byte_offset + 3)
        fh.write(bytes([b ^ 0xFF]))
    return path


WHY = "cannot be read (data error detected by Fletcher32 checksum): the file is damaged"


@pytest.mark.parametrize("name, row, what", [
    ("row_digest", 0, "/row_digest rows 0-6 (frames 0-6) "),
    ("time", 0, "/time rows 0-6 (frames 0-6) "),
    ("positions", 4, "/positions row 4 (frame 4) ")])
def test_a_damaged_chunk_is_named_by_every_reader(run, tmp_path, capsys, name, row, what):
    """A chunk of /row_digest, /time or /positions failing its checksum: every reader said
    only "Can't read data (data error detected by Fletcher32 checksum)" (to_usd without
    even the file's name).  Now each names the file, the dataset and its rows."""
    path = _damaged_copy(run, tmp_path, name, row)
    want = what + WHY
    for tool in (count_crossings, edge_strain, head_depth):
        capsys.readouterr()
        assert tool.main([str(path)]) == 2
        err = capsys.readouterr().err
        assert f"error: {path}: not a readable frames.h5 of lc_petsc" in err and want in err, (tool, err)
    capsys.readouterr()
    assert to_usd.main([str(path), "--out", str(tmp_path / "x.usdc"), "--quiet"]) == 2
    assert f"to_usd.py: error: {path}: {want}" in capsys.readouterr().err
    assert not (tmp_path / "x.usdc").exists()
    with pytest.raises(ValueError) as e:
        read_frames(path, frames=[row])
    assert str(e.value).startswith(f"{path}: {want}"), e.value
    # a restart keeping the damaged row names it too, before it changes anything
    with h5py.File(path, "r") as f:
        n_wisps, n_vertices = f["wisp_offsets"].shape[0] - 1, f["positions"].shape[1]
    # (the damaged chunk's rows, as the other readers: "rows 0-5", every kept row, before)
    kept = "row 4 (frame 4)" if name == "positions" else "rows 0-6 (frames 0-6)"
    assert resumable_problem(path, n_wisps, n_vertices, 6) == f"{path}: /{name} {kept} {WHY}"


@pytest.fixture
def reads(monkeypatch):
    """h5py's dataset reads, counted per dataset."""
    counter = collections.Counter()
    real = h5py.Dataset.__getitem__

    def counted(self, sel):
        counter[self.name] += 1
        return real(self, sel)
    monkeypatch.setattr(h5py.Dataset, "__getitem__", counted)
    return counter


def test_rows_are_read_in_blocks_with_one_read_each(run, tmp_path, reads):
    """Reading every row of a 7-row file read /positions row by row, one read per row
    (fault56 had cut the reads of /time and /row_digest to one per open file; before,
    every row read all three).  Now consecutive rows are one read: read_frames, the
    end-of-run check (count_frames), to_usd, the restart's read-back and a reader
    object's rows take one read of /positions for the whole file, and the digests of
    every row are checked from the block."""
    path = run / "out" / "frames.h5"
    with FramesReader(path) as r:
        n = len(r.valid)
        reads.clear()
        rows = dict(r.rows(range(n)))
        assert n == 7 and sorted(rows) == list(range(7))
        assert dict(reads) == {"/positions": 1, "/time": 1, "/row_digest": 1}
        reads.clear()
        assert np.array_equal(r.row(3), rows[3])        # the table is kept: one read of the row
        assert dict(reads) == {"/positions": 1}
    with FramesReader(path) as r:       # a new reader reads the table again
        reads.clear()
        r.row(3)
        assert dict(reads) == {"/positions": 1, "/time": 1, "/row_digest": 1}
    reads.clear()
    got = read_frames(path)
    assert got["positions"].shape[0] == 7 and reads["/positions"] == 1, reads
    assert np.array_equal(got["positions"][3], rows[3])
    reads.clear()
    assert len(count_frames(path)[0]) == 6 and reads["/positions"] == 1 and reads["/time"] == 1, reads
    reads.clear()
    assert to_usd.main([str(path), "--out", str(tmp_path / "x.usdc"), "--quiet"]) == 0
    assert reads["/positions"] == 1 and reads["/time"] == 1 and reads["/row_digest"] == 1, reads
    reads.clear()
    with h5py.File(path, "r") as f:
        n_wisps, n_vertices = f["wisp_offsets"].shape[0] - 1, f["positions"].shape[1]
    assert resumable_problem(path, n_wisps, n_vertices, 7) is None
    assert reads["/positions"] == 1 and reads["/row_digest"] == 2, reads     # (read back, then the table)


def test_blocks_of_rows_are_bounded_and_a_damaged_row_in_one_is_named(run, tmp_path, reads, monkeypatch):
    """Blocks hold at most READ_BLOCK_BYTES of /positions (the USD export and the
    crossing check stream a run of any length), rows given out of order, twice or with
    gaps are read once each in ascending order, and a row failing its checksum inside a
    block is named (the block read again row by row)."""
    from lc_petsc.io import frames_read
    path = run / "out" / "frames.h5"
    with FramesReader(path) as r:
        row_bytes = 24 * r.f["positions"].shape[1]
        monkeypatch.setattr(frames_read, "READ_BLOCK_BYTES", 3 * row_bytes)
        reads.clear()
        got = list(r.rows([6, 0, 1, 2, 3, 4, 5, 1]))
        assert [k for k, _ in got] == list(range(7))
        assert reads["/positions"] == 3, reads          # rows 0-2, 3-5, 6
        reads.clear()
        assert [k for k, _ in r.rows([5, 0, 2, 1])] == [0, 1, 2, 5] and reads["/positions"] == 2
        with pytest.raises(IndexError, match="row 7 of /positions: the file has rows 0-6"):
            list(r.rows([7]))
    damaged = _damaged_copy(run, tmp_path, "positions", 4)
    with FramesReader(damaged) as r, pytest.raises(ValueError) as e:
        dict(r.rows(range(7)))
    assert str(e.value) == ("/positions row 4 (frame 4) cannot be read (data error detected by Fletcher32 "
                            "checksum): the file is damaged; the rows before it may still be read, or rerun "
                            "from a checkpoint")


def test_a_run_folder_given_for_its_frames_file_says_which_file(run, tmp_path, capsys):
    """count_crossings.py OUT (the run's folder, a common slip) printed libhdf5's
    multi-line dump ending in 'Is a directory'; now each reader says it is a folder and
    names the frames.h5 inside it."""
    out = run / "out"
    want = f"a folder, not a frames.h5 file; give {out / 'frames.h5'})"
    for tool in (count_crossings, edge_strain, head_depth):
        capsys.readouterr()
        assert tool.main([str(out)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"error: {out}: not a readable frames.h5 of lc_petsc" in err \
            and err.rstrip().endswith(want), (tool, err)
    assert to_usd.main([str(out), "--out", str(tmp_path / "x.usdc"), "--quiet"]) == 2
    assert capsys.readouterr().err == f"to_usd.py: error: {out}: cannot open the frames file ({want}\n"
    assert count_crossings.main([str(tmp_path)]) == 2      # a folder without one: no hint
    assert capsys.readouterr().err.rstrip().endswith("(a folder, not a frames.h5 file)")


def test_read_frames_reads_one_row_given_as_a_number(run):
    """``read_frames(path, frames=2)`` read row 2 (positions (1, n, 3), its time and
    validity as numbers) until fault56 moved the row reads into a loop over the rows
    asked for, which ended in "TypeError: 'int' object is not iterable"."""
    path = run / "out" / "frames.h5"
    every = read_frames(path)
    one = read_frames(path, frames=2)
    assert one["positions"].shape == (1,) + every["positions"].shape[1:]
    assert np.array_equal(one["positions"][0], every["positions"][2])
    assert one["time"] == every["time"][2] and np.ndim(one["time"]) == 0 and one["frame_valid"] == True  # noqa: E712
    assert np.array_equal(read_frames(path, frames=[2, 4])["positions"], every["positions"][[2, 4]])


def _shortened(name):
    def cut(f):
        f[name].resize(f[name].shape[0] - 1, axis=0)
    return cut


def _time_not_increasing(f):
    """Row 5's time set to row 3's, its digest recomputed (so only the order is wrong)."""
    from lc_petsc.io.frames import row_digest, vertex_digest
    t = f["time"][...]
    t[5] = t[3]
    f["time"][...] = t
    f["row_digest"][5] = row_digest([vertex_digest(f["positions"][5], 0)], 5, float(t[5]))


def _rest_short(f):
    x = f["rest_positions"][...]
    del f["rest_positions"]
    f["rest_positions"] = x[:-3]


def _positions_flat(f):
    x = f["positions"][...]
    del f["positions"]
    f["positions"] = x.reshape(x.shape[0], -1)


@pytest.mark.parametrize("damage, want", [
    (_shortened("row_digest"), "/row_digest has shape (6,), /positions 7 rows: row 6 (frame 6) has no /row_digest "
                               "entry: the file is damaged"),
    (_shortened("time"), "/time has shape (6,), /positions 7 rows: row 6 (frame 6) has no /time entry: the file "
                         "is damaged"),
    (_time_not_increasing, "/time rows 4 and 5 (frames 4, 5) are not increasing ("),
    (_rest_short, "/rest_positions has shape (N-3, 3), a frames.h5 of N vertices has (N, 3): the file is damaged"),
    (_positions_flat, "/positions has shape (7, 3N), a frames.h5 has (frames, N vertices, 3)"),
    (lambda f: f.attrs.__setitem__("every", 0), "the attribute every = 0 is not an integer >= 1 (row k is frame "
                                               "k * every): the file is damaged"),
    (lambda f: f.attrs.__setitem__("dt", -1.0 / 30), "the attribute dt = -0.03333333333333333 is not a finite "
                                                     "number > 0 (the time step, s): the file is damaged")],
    ids=["digest_short", "time_short", "time_not_increasing", "rest_short", "positions_flat", "every_0", "dt_negative"])
def test_a_frames_file_of_other_shapes_or_times_is_refused_naming_dataset_and_rows(run, tmp_path, capsys, damage,
                                                                                     want):
    """A /row_digest or /time one row shorter than /positions ended every reader in an
    IndexError traceback (to_usd.py with a short /time wrote the export without the last
    row, exit 0; the restart's message said the file had too few rows); /time not
    increasing (digests consistent) was read by every reader and kept by a restart; a
    /rest_positions of another length was read by all but edge_strain (the USD's rest
    pose and the restart kept it); a flat /positions ended to_usd in a TypeError; an
    attribute every = 0 ended to_usd in a ZeroDivisionError traceback (and numbered every
    row frame 0 elsewhere), a negative dt wrote a USD of negative frame rate.  Now each
    reader and the restart refuse, naming the file, the dataset (attribute) and the rows."""
    path = tmp_path / "frames.h5"
    shutil.copy(run / "out" / "frames.h5", path)
    with h5py.File(path, "r") as f:
        n_wisps, nv = f["wisp_offsets"].shape[0] - 1, f["positions"].shape[1]
    with h5py.File(path, "r+") as f:
        damage(f)
    want = want.replace("3N", str(3 * nv)).replace("N-3", str(nv - 3)).replace("N", str(nv))
    for tool in (count_crossings, edge_strain, head_depth):
        capsys.readouterr()
        assert tool.main([str(path)]) == 2
        err = capsys.readouterr().err
        assert f"error: {path}: not a readable frames.h5 of lc_petsc" in err and want in err and \
            err.count("\n") == 1, (tool, err)
    assert to_usd.main([str(path), "--out", str(tmp_path / "x.usdc"), "--quiet"]) == 2
    assert capsys.readouterr().err.startswith(f"to_usd.py: error: {path}: {want}")
    assert not (tmp_path / "x.usdc").exists()
    with pytest.raises(ValueError) as e:
        read_frames(path)
    assert str(e.value).startswith(f"{path}: {want}"), e.value
    problem = resumable_problem(path, n_wisps, nv, 7)
    if damage is _positions_flat:   # (the restart's own shape check says it first)
        assert problem == f"{path}: has {n_wisps} wisps and /positions (7, {3 * nv}), the scene {n_wisps} wisps " \
                          f"and {nv} vertices"
    else:
        assert problem.startswith(f"{path}: {want}"), problem


def _offset_moved(f):
    """The offset between wisps 1 and 2 moved by one vertex (still 0, increasing, ..., n)."""
    f["wisp_offsets"][2] += 1


def _offsets_not_increasing(f):
    f["wisp_offsets"][2] = f["wisp_offsets"][1] - 1


@pytest.mark.parametrize("damage, want", [
    (_offset_moved, "/wisp_offsets gives wisp 1 vertices 101-202, /polylines (the wisps written with it) does not: "
                    "the file is damaged"),
    (_offsets_not_increasing, "/wisp_offsets is not 0, increasing, ..., N (the vertex count of /positions): entry "
                              "2 is 100 after 101; the file is damaged")], ids=["moved", "not_increasing"])
def test_damaged_wisp_offsets_are_refused_by_every_reader(run, tmp_path, capsys, damage, want):
    """/wisp_offsets with a valid checksum but wrong values (a file written before the
    checksums, or edited): read_frames and the previews returned and drew them as they
    were, and one moved between its neighbours (still 0, increasing, ..., n) was read by
    every reader: the crossing check, the strains and the USD curves split the wisps one
    vertex off.  Now every reader and the restart refuse, naming the dataset and the entry
    or wisp."""
    from lc_petsc.io.previews import render_previews
    path = tmp_path / "frames.h5"
    shutil.copy(run / "out" / "frames.h5", path)
    with h5py.File(path, "r+") as f:
        n_wisps, nv = f["wisp_offsets"].shape[0] - 1, f["positions"].shape[1]
        assert f["wisp_offsets"][1] == 101 and f["wisp_offsets"][2] == 202       # (the messages' numbers)
        damage(f)
    want = want.replace("N", str(nv))
    with pytest.raises(ValueError) as e:
        read_frames(path)
    assert str(e.value) == f"{path}: {want}", e.value
    for tool in (count_crossings, edge_strain, head_depth):
        capsys.readouterr()
        assert tool.main([str(path)]) == 2
        err = capsys.readouterr().err
        assert f"error: {path}: not a readable frames.h5 of lc_petsc" in err and want in err, (tool, err)
    assert to_usd.main([str(path), "--out", str(tmp_path / "x.usdc"), "--quiet"]) == 2
    assert capsys.readouterr().err.startswith(f"to_usd.py: error: {path}: {want}")
    with pytest.raises(ValueError) as e:
        render_previews(path, tmp_path / "previews", [0])
    assert str(e.value) == want
    assert not (tmp_path / "x.usdc").exists() and not (tmp_path / "previews").exists()
    assert resumable_problem(path, n_wisps, nv, 7) == f"{path}: {want}"


def _unopenable_copy(run, tmp_path, name):
    """A copy of the run's frames.h5 whose /``name`` cannot be opened (a broken header)."""
    path = tmp_path / "frames.h5"
    shutil.copy(run / "out" / "frames.h5", path)
    break_header(path, name)
    return path


def test_a_dataset_that_cannot_be_opened_is_named_and_only_its_readers_refuse(run, tmp_path, capsys):
    """A broken /radius header (fault51's damaged metadata, /tmp/s51/f51/sw_metaa/s104)
    ended read_frames in a bare KeyError without the file or the dataset (read_frames
    needs no /radius and read the file before io57's shape check), and count_crossings
    and edge_strain refused it; a broken /pinned, which read_frames returns, was the same
    KeyError.  Now the readers that do not need the dataset read the file, and one that
    does names the file and the dataset."""
    path = _unopenable_copy(run, tmp_path, "radius")
    whole = read_frames(run / "out" / "frames.h5")
    got = read_frames(path)
    assert np.array_equal(got["positions"], whole["positions"]) and np.array_equal(got["pinned"], whole["pinned"])
    for tool in (count_crossings, edge_strain):
        assert tool.main([str(path)]) == 0
    capsys.readouterr()
    assert head_depth.main([str(path)]) == 2        # (the strand radius: /radius)
    assert "/radius cannot be opened (bad object header version number): the file is damaged" in \
        capsys.readouterr().err
    path = _unopenable_copy(run, tmp_path, "pinned")
    with pytest.raises(ValueError) as e:
        read_frames(path)
    assert str(e.value).startswith(f"{path}: /pinned cannot be opened (bad object header version number): the "
                                   "file is damaged"), e.value
