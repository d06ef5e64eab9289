"""A restart of a scene read from a groom file: the groom's content is compared with the
checkpoint's, not its path (a moved copy restarts, a changed file is refused naming what
differs, even with --force); the free-text scene.description may change; time.dt, which every row of
frames.h5 and frames.usdc shares, may not, even with --force."""

import hashlib
import shutil
from pathlib import Path

import h5py
import numpy as np

from lc_petsc.batch import main
from lc_petsc.io.checkpoint import GLOBAL_DATASETS, VERTEX_DATASETS, _meta_digest
from lc_petsc.io.checkpoint_seal import seal

ROOT = Path(__file__).resolve().parents[2]
FRINGE = ROOT / "configs" / "data" / "fringe.h5"

SCENE = """[scene]
kind = "file"
path = "{path}"
description = "{description}"
[material]
youngs_modulus = 1.0e10
[physics]
terms = ["stretch", "bend", "twist", "gravity"]
[time]
dt = {dt}
frames = 3
newton_iterations = 2
[output]
previews = false
xdmf = false
usd = false
checkpoint_every = 1
"""


def _config(folder, groom, name="g.toml", dt="0.03333333333333333", description="a fringe"):
    p = Path(folder) / name
    p.write_text(SCENE.format(path=groom, dt=dt, description=description))
    return str(p)


def _positions(out):
    with h5py.File(Path(out) / "frames.h5", "r") as f:
        return f["positions"][...]


def _digest(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _snapshot(folder):
    """{relative path: sha256} of every file under ``folder``."""
    return {str(p.relative_to(folder)): _digest(p) for p in sorted(Path(folder).rglob("*")) if p.is_file()}


def test_a_moved_groom_restarts_and_a_changed_one_is_refused(tmp_path, capsys):
    first = tmp_path / "a" / "fringe.h5"
    first.parent.mkdir()
    shutil.copy(FRINGE, first)
    straight = tmp_path / "straight"
    assert main([_config(tmp_path, first, "s.toml"), "--out", str(straight), "--quiet"]) == 0
    out = tmp_path / "out"
    assert main([_config(tmp_path, first), "--out", str(out), "--quiet", "--frames", "1"]) == 0

    # the same file moved, with another description: it restarts, bit for bit the straight run
    moved = tmp_path / "b" / "moved.h5"
    moved.parent.mkdir()
    shutil.move(first, moved)
    cfg = _config(tmp_path, moved, "m.toml", description="the fringe, moved")
    capsys.readouterr()
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest", "--frames", "2"]) == 0
    assert capsys.readouterr().err == ""
    assert np.array_equal(_positions(out), _positions(straight)[:3])

    # a checkpoint from before the radius digest: its groom is still compared by path
    old = tmp_path / "old.h5"
    shutil.copy(out / "checkpoints" / "checkpoint_000001.h5", old)
    with h5py.File(old, "r+") as f:
        del f.attrs["radius_sha256"]
        f.attrs["meta_sha256"] = _meta_digest(dict(f.attrs))      # as its writer had
    seal(old, h5py, VERTEX_DATASETS + GLOBAL_DATASETS)
    assert main([cfg, "--out", str(tmp_path / "o2"), "--quiet", "--restart", str(old)]) == 2
    assert (f"the config differs from the checkpoint's in scene.path (checkpoint: '{first}', config: '{moved}'); "
            "the checkpoint predates radius_sha256 (2026-12-07), so its groom is compared by path (a link at "
            "the checkpoint's path to a moved file will do)") in capsys.readouterr().err

    # a changed copy: refused, naming what differs and both paths, also with --force
    # (frames.h5 holds one groom: main went on and kept the old /rest_positions and
    # /radius under the new rows, for the USD export's rest pose and widths)
    held = _snapshot(out)
    changed = tmp_path / "b" / "changed.h5"
    shutil.copy(moved, changed)
    with h5py.File(changed, "r+") as f:
        f["positions"][45, 1] += 0.01           # a vertex of wisp w (below)
        offsets = f["wisp_offsets"][...]
    w = int(np.searchsorted(offsets, 45, side="right")) - 1
    cfg = _config(tmp_path, changed, "c.toml")
    for force in ([], ["--force"]):
        assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest", "--frames", "3"] + force) == 2
        e = capsys.readouterr().err
        assert (f"the scene's groom ({changed}; the checkpoint's run read {moved}) differs from the checkpoint's "
                f"in its rest positions at 1 vertex (first: vertex 45, wisp {w}'s vertex {45 - offsets[w]}: ") in e, e
        assert ("; the groom cannot change in a restart, not even with --force: the run's frames.h5 "
                "(/rest_positions, /pinned, /radius) and frames.usdc (widths, pinned, the rest pose) hold one "
                "groom for all its rows; restart with the groom the checkpoint ran with, or start a new run "
                "(without --restart) with this one") in e, e
        assert _snapshot(out) == held

    # radii only (not in the checkpoint's datasets, compared by their digest)
    shutil.copy(moved, changed)
    with h5py.File(changed, "r+") as f:
        f["radius"][7] *= 1.1
    for force in ([], ["--force"]):
        assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest", "--frames", "3"] + force) == 2
        e = capsys.readouterr().err
        assert "differs from the checkpoint's in its radii; the groom cannot change in a restart" in e, e
        assert _snapshot(out) == held


def test_a_new_time_step_is_refused_even_with_force(tmp_path, capsys):
    """--force let a restart change time.dt: frames.h5's dt attribute then said 0.02 over
    rows written 1/30 s apart, and frames.usdc played them at the new rate."""
    out = tmp_path / "out"
    assert main([_config(tmp_path, FRINGE), "--out", str(out), "--quiet", "--frames", "1"]) == 0
    held = _digest(out / "frames.h5")
    capsys.readouterr()
    cfg = _config(tmp_path, FRINGE, "dt.toml", dt="0.02")
    for force in ([], ["--force"]):
        assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest"] + force) == 2
        e = capsys.readouterr().err
        assert ("the config differs from the checkpoint's in time.dt (checkpoint: 0.03333333333333333, "
                "config: 0.02); time.dt cannot change in a restart, not even with --force: the run's "
                "frames.h5 (its dt and every attributes) and frames.usdc (timeCodesPerSecond = 1 / "
                "(dt * every)) give all its rows one time step") in e, e
        assert _digest(out / "frames.h5") == held
    with h5py.File(out / "frames.h5", "r") as f:
        assert f.attrs["dt"] == 1 / 30 and f["time"].shape == (2,)
    # scene.description is free text: another one restarts (main: refused, naming it)
    cfg = _config(tmp_path, FRINGE, "d.toml", description="the fringe, take 2")
    assert main([cfg, "--out", str(out), "--quiet", "--restart", "latest", "--frames", "2"]) == 0
    assert capsys.readouterr().err == ""
