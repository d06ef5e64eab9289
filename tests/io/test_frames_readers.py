"""Every reader of frames.h5 (count_crossings, edge_strain, head_depth, to_usd,
read_frames, a restart) names the dataset and the rows of a chunk failing its checksum,
and reads /time and /row_digest once per file, not once per row."""

import collections
import shutil
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from lc_petsc.batch import main
from lc_petsc.io.frames import frame_row, read_frames, resumable_problem, valid_rows

from sim_helpers import hairball_toml  # noqa: E402

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
    kept = "row 4 (frame 4)" if name == "positions" else "rows 0-5"
    assert resumable_problem(path, n_wisps, n_vertices, 6) == f"{path}: /{name} {kept} {WHY}"


def test_rows_are_read_with_one_read_each(run, monkeypatch):
    """Reading every row of a 7-row file read /positions, /time and /row_digest once per
    row (each row's digest check read its time and digest): 21 reads.  Now /time and
    /row_digest are read once per open file: 7 + 2; the end-of-run check (count_frames)
    and to_usd likewise."""
    reads = collections.Counter()
    real = h5py.Dataset.__getitem__

    def counted(self, sel):
        reads[self.name] += 1
        return real(self, sel)
    monkeypatch.setattr(h5py.Dataset, "__getitem__", counted)
    with h5py.File(run / "out" / "frames.h5", "r") as f:
        n = len(valid_rows(f))
        reads.clear()
        rows = [frame_row(f, k) for k in range(n)]
        assert n == 7 and len(rows) == 7
        assert dict(reads) == {"/positions": 7, "/time": 1, "/row_digest": 1}
    with h5py.File(run / "out" / "frames.h5", "r") as f:     # a new file object reads them again
        reads.clear()
        frame_row(f, 3)
        assert dict(reads) == {"/positions": 1, "/time": 1, "/row_digest": 1}


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
