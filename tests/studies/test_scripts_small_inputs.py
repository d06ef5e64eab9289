"""Scripts of scripts/ on the smallest inputs they allow (the study logic itself is tested
with lc_petsc.studies): what used to crash on them."""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from lc_petsc.config import load_config
from lc_petsc.scene.sources import source_from_config
from sim_helpers import touching_wisps_config, touching_wisps_source

ROOT = Path(__file__).resolve().parents[2]


def _script(name):
    """scripts/<name>.py as a module (its main() not run)."""
    spec = importlib.util.spec_from_file_location(f"script_{name}", ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_newton_frames_plots_fewer_than_four_frames(tmp_path):
    """The right panel (the median over frames 3..) has no frame to draw: it stays empty
    instead of min() of an empty sequence."""
    rows = [{"iterations": 3, "converged": True, "true": 2, "first_error": 1e-2,
             "errors": [1e-3, 1e-5, 1e-7]}]
    _script("newton_frames").plot({"a": rows}, ["a"], 1e-6, 5, tmp_path / "f.png", "one frame")
    assert (tmp_path / "f.png").stat().st_size > 0


def _run(tmp_path, script, *args):
    import subprocess
    import sys
    return subprocess.run([sys.executable, str(ROOT / "scripts" / script), *args], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)


def test_make_groom_help_is_help_not_a_file_name(tmp_path):
    """``make_groom.py --help`` used to write a strands file named ``--help``."""
    proc = _run(tmp_path, "make_groom.py", "--help")
    assert proc.returncode == 0 and "usage:" in proc.stdout
    assert list(tmp_path.iterdir()) == []


def test_make_groom_usd_refuses_a_non_usd_name_and_keeps_that_file(tmp_path):
    """The script removes its output before writing it: a name that is not a USD layer (a
    strands file given by mistake) is refused first, one error line, exit 2, the file kept."""
    keep = tmp_path / "fringe.h5"
    keep.write_bytes(b"groom")
    proc = _run(tmp_path, "make_groom_usd.py", str(keep))
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert [line for line in proc.stderr.splitlines() if "error:" in line] == [
        f"make_groom_usd.py: error: {keep}: give a USD file name ending in .usda, .usdc or .usd"]
    assert keep.read_bytes() == b"groom"


def test_bench_bandwidth_prints_a_positive_rate_per_rank(capsys):
    """One rank: one rate, the total equal to it; bad sizes refused by argparse."""
    import pytest
    bench = _script("bench_bandwidth")
    assert bench.main(["--doubles", "2000", "--passes", "2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rates = [float(r) for r in lines[1].split(":")[1].split()]
    assert len(rates) == 1 and rates[0] > 0
    assert lines[2].startswith(f"total {rates[0]:.1f} GB/s")
    with pytest.raises(SystemExit) as exit_info:
        bench.main(["--doubles", "10"])
    assert exit_info.value.code == 2


def test_bench_checkpoint_removes_its_folder_when_a_write_fails(tmp_path, monkeypatch, capsys):
    """A checkpoint write that failed (here a full disk) ended bench_checkpoint.py in a
    traceback and left its bench_ckpt_* folder with the partial files; now: exit 3, the
    error printed, the folder removed (and removed after a run that succeeds)."""
    import errno
    import sys
    sys.path.insert(0, str(ROOT / "tests"))
    from sim_helpers import hairball_toml
    from lc_petsc.errors import OutputError
    bench = _script("bench_checkpoint")
    cfg = tmp_path / "s.toml"
    cfg.write_text(hairball_toml(n_wisps=2, frames=2))
    work = tmp_path / "work"
    work.mkdir()
    args = ["--config", str(cfg), "--repeat", "2", "--dir", str(work)]
    assert bench.main(args) == 0
    assert "checkpoint write: median" in capsys.readouterr().out
    assert list(work.iterdir()) == []
    real = bench.write_checkpoint
    calls = []

    def full_disk(d, *a, **kw):
        calls.append(d)
        if len(calls) == 2:         # the first written, the second runs out of space
            (Path(d) / "checkpoint_partial.h5").write_bytes(b"\0" * 10)
            raise OutputError(f"{d}/checkpoint_partial.h5: {errno.errorcode[errno.ENOSPC]} no space left")
        return real(d, *a, **kw)
    monkeypatch.setattr(bench, "write_checkpoint", full_disk)
    assert bench.main(args) == 3
    err = capsys.readouterr().err
    assert f"bench_checkpoint.py: error: {calls[1]}/checkpoint_partial.h5: ENOSPC no space left" in err, err
    assert len(calls) == 2 and list(work.iterdir()) == []


def test_check_outputs_passes_a_run_and_names_what_disagrees(tmp_path, capsys):
    """scripts/check_outputs.py on a small run: frames.h5, frames.usdc, frames.xdmf and the
    previews agree with summary.json (ok, exit 0); a summary.json whose frame count no longer
    matches frames.h5 is named (exit 1); a folder without the outputs is exit 2."""
    import json
    from mpi4py import MPI
    from lc_petsc.batch import main
    (tmp_path / "w.toml").write_text('[scene]\nkind = "wisp4c"\nn_vertices = 12\n[time]\nframes = 4\n'
                                     '[output]\nevery = 2\npreview_frames = [0, 3, -1]\ncontact_sheet = 0\n')
    out = tmp_path / "o"
    assert main([str(tmp_path / "w.toml"), "--out", str(out), "--quiet"], comm=MPI.COMM_SELF) == 0
    check = _script("check_outputs")
    capsys.readouterr()
    assert check.main([str(out), "--crossings"]) == 0
    assert capsys.readouterr().out == f"{out}: ok\n"
    s = json.loads((out / "summary.json").read_text())
    s["frames"] = 6
    (out / "summary.json").write_text(json.dumps(s))
    assert check.main([str(out)]) == 1
    assert "frames.h5 has 3 rows, summary.json's 6 frames every 2: 4" in capsys.readouterr().out
    assert check.main([str(tmp_path)]) == 2
    assert "not a readable output folder" in capsys.readouterr().err


def test_setting_frames_counts_iterations_strain_and_a_watched_function(capsys):
    """scripts/setting_frames.py on smash, 2 frames: the fixed count's 3 iterations a frame;
    the start frames capped at 3 without cutback (reported capped, not missed) and run to
    the tolerance (converged, more iterations, the shift searches watched in frame 0);
    a bad --watch and a --frame beyond the run refused naming the flag."""
    script = _script("setting_frames")
    assert script.main(["--scene", "smash", "--frames", "2", "--watch", "lc_petsc.curvature.least_definite_shifts",
                        "default=default", "cap=start_increment_tol=1e-3+start_iterations=3+max_substeps=1",
                        "start=start_increment_tol=1e-3"]) == 0
    out = capsys.readouterr().out
    assert "default: 6 Newton iterations in 2 frames; largest |edge strain| over frames 1-2 " in out, out
    assert "  start/jolt frames: 0 (start, 3 its, capped), 1 (start, 3 its, capped)\n" in out, out
    start = out[out.index("start: "):]
    its = [int(n) for n in start.split("iterations per frame: ")[1].split("\n")[0].split()]
    assert min(its) > 3 and f"0 (start, {its[0]} its, converged), 1 (start, {its[1]} its, converged)" in start
    calls = int(start.split("least_definite_shifts: ")[1].split(" calls")[0])
    assert calls >= 1, start
    for bad, words in ((["--watch", "lc_petsc.curvature.no_such"],
                        "--watch 'lc_petsc.curvature.no_such': no 'no_such' in 'lc_petsc.curvature'"),
                       (["--frame", "2"], "--frame 2 is not among the 2 frames")):
        assert script.main(["--scene", "smash", "--frames", "2", *bad, "default=default"]) == 2
        assert words in capsys.readouterr().err


def test_compare_trees_runs_each_tree_on_the_same_restart(tmp_path):
    """``compare_trees.py`` with this checkout as both trees: each run continues the same
    checkpoint (frame 2 -> 3 of a 3-wisp hairball) in its own folder, and the same code
    gives the same positions bit for bit and the same CG iterations; a B / A ratio per
    round of each CPU figure."""
    import json
    import subprocess
    import sys
    import h5py
    from lc_petsc.batch import main
    from sim_helpers import MPI_ENV, hairball_toml
    cfg = tmp_path / "s.toml"
    cfg.write_text(hairball_toml(n_wisps=3, frames=3, output="previews = false\nxdmf = false\ncheckpoint_every = 2"))
    assert main([str(cfg), "--out", str(tmp_path / "r"), "--quiet", "--frames", "2"]) == 0
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "compare_trees.py"), "--config", str(cfg),
                           "--checkpoint", str(tmp_path / "r" / "checkpoints" / "checkpoint_000002.h5"),
                           "--frames", "3", "--rounds", "1", "--out", str(tmp_path / "c"), str(ROOT), str(ROOT)],
                          capture_output=True, text=True, timeout=300, env=MPI_ENV, cwd=tmp_path,
                          stdin=subprocess.DEVNULL)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    result = json.loads((tmp_path / "c" / "compare.json").read_text())
    (a,), (b,) = result["runs"]
    assert a["dx"] == b["dx"] == 0.0 and a["ksp"] == b["ksp"] > 0
    assert sorted(result["ratios"]) == ["collision_cpu", "cpu", "solve_cpu", "step"]
    assert all(len(v) == 1 and v[0] > 0 for v in result["ratios"].values())
    for name in ("a0", "b0"):
        with h5py.File(tmp_path / "c" / name / "frames.h5", "r") as f:
            assert f["frame_valid"][:].tolist() == [False, False, True, True]


def test_the_file_scene_is_the_tests_scene_with_the_tolerance_default(tmp_path):
    """scripts/touching_wisps.py (the scene through the job, docs/newton.md "The
    tolerance default measured where contact is active"): the strands file
    holds six_wisps_ccd's vertices, radii and pins bit for bit; the config its physics,
    material and time keys, ccd mode, the tolerance and the cap, and (no [solver] key) the
    loader resolves the tolerance default with strand contact; ``--set`` adds a key, and
    one of a table the script writes is refused."""
    ts = _script("touching_wisps")
    cfg = load_config(ts.write(tmp_path, 10, 1e-4, 60, ["time.max_substeps=1"]))
    ref = touching_wisps_config(10)
    src, want = source_from_config(cfg.scene, cfg.material, cfg.physics), touching_wisps_source(spin_step=0.0,
                                                                                                 n_pinned=3)
    got, exp = src.load(0, 6), want.load(0, 6)
    for name in ("positions", "radius", "pinned", "offsets"):
        assert np.array_equal(getattr(got, name), getattr(exp, name)), name
    assert cfg.physics.strand_contact_mode == "ccd"
    for table, keys in (("physics", ("terms", "head_motion", "head_amplitude", "head_period", "strand_thickness",
                                     "strand_stiffness", "gravity", "head_radius")),
                        ("material", ("youngs_modulus", "density")), ("time", ("dt", "initial_guess"))):
        for key in keys:
            assert getattr(getattr(cfg, table), key) == getattr(getattr(ref, table), key), (table, key)
    assert (cfg.time.frames, cfg.time.newton_iterations, cfg.time.newton_increment_tol) == (10, 60, 1e-4)
    assert cfg.time.max_substeps == 1
    assert cfg.solver_path_defaulted == ("solver.filter", "solver.exact_fallback", "solver.exact_stay",
                                         "time.newton_update")
    with pytest.raises(ValueError, match="the script writes \\[physics\\] itself"):
        ts.write(tmp_path, 10, 1e-4, 30, ["physics.strand_stiffness=1.0"])


def test_the_table_lists_each_frame_and_the_totals(tmp_path, capsys):
    """scripts/newton_contact_table.py: per frame converged / iterations / substeps / pairs / closest pair, then the
    frames converged, iterations, frames cut back and crossings; a restart's frames are
    numbered from its checkpoint's; a folder without summary.json is an error naming it."""
    s = {"ranks": 2, "status": "finished", "newton_iterations": [5, 40, 12], "newton_converged": [True, False, True],
         "newton_substeps": [1, 8, 2], "contact": {"pairs_per_frame": [0, 31, 7],
                                                   "min_distance_per_frame": [0.2, 0.0035, 0.11]},
         "crossings": {"between_wisps": 0, "within_wisps": 0, "steps": 3},
         "solver_path_defaulted": ["solver.filter"], "restart": {"frame": 10}}
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "summary.json").write_text(json.dumps(s))
    table = _script("newton_contact_table")
    assert table.cli([str(tmp_path / "run")]) == 0
    out = capsys.readouterr().out
    assert "| 10 | y | 5 | 1 | 0 | 0.2 |" in out and "| 11 | n | 40 | 8 | 31 | 0.0035 |" in out
    assert "| 12 | y | 12 | 2 | 7 | 0.11 |" in out
    assert "frames converged 2/3, iterations 57, frames cut back 2, crossings between wisps 0 within 0 " \
           "over 3 steps, defaulted solver.filter" in out
    with pytest.raises(SystemExit):
        table.cli([str(tmp_path)])
    assert "has no summary.json" in capsys.readouterr().err


def test_derive_config_changes_only_the_keys_set_and_refuses_a_bad_one(tmp_path, capsys):
    """scripts/derive_config.py (the docs' benchmark configs, docs/architecture.md "Commands
    in the docs"): the 2K hairball with two keys changed, written outside configs/, loads
    to the shipped config's values but those two (its options file found from the new
    folder); a misspelt key or an unquoted string is refused with exit 2 and no file."""
    derive = _script("derive_config")
    base = ROOT / "configs" / "hairball_2k.toml"
    out = tmp_path / "sub" / "pen.toml"
    assert derive.cli([str(base), str(out), "--set", "output.every=1",
                       "--set", 'physics.strand_contact_mode="penalty"']) == 0
    got, want = load_config(out).to_dict(), load_config(base).to_dict()
    assert (got["output"]["every"], want["output"]["every"]) == (1, 3)
    assert (got["physics"]["strand_contact_mode"], want["physics"]["strand_contact_mode"]) == ("penalty", "ccd")
    got["output"]["every"], got["physics"]["strand_contact_mode"] = 3, "ccd"
    got["output"]["dir"] = want["output"]["dir"] = ""     # named after the file
    assert got == want
    for bad, message in ((["--set", "output.evry=1"], "unknown key output.evry"),
                         (["--set", "physics.strand_contact_mode=penalty"], "is not a TOML value")):
        with pytest.raises(SystemExit) as e:
            derive.cli([str(base), str(tmp_path / "bad.toml"), *bad])
        assert e.value.code == 2 and message in capsys.readouterr().err
        assert not (tmp_path / "bad.toml").exists()


def test_the_table_of_a_run_without_contact_or_with_capped_frames(tmp_path, capsys):
    """newton_contact_table.py on a run without strand contact (no ``contact`` in its summary: a
    KeyError traceback on main), a frame whose closest pair was not measured (``null``: a
    TypeError on main), capped start frames (``newton_capped``: shown as capped, not n), and
    a damaged summary.json (an error naming it, not json's traceback)."""
    s = {"ranks": 1, "status": "finished", "newton_iterations": [30, 30, 3], "newton_converged": [False, False, None],
         "newton_capped": [True, True, False], "newton_substeps": [1, 1, 1], "crossings": None,
         "solver_path_defaulted": []}
    for name, contact in (("plain", None), ("far", {"pairs_per_frame": [0, 0, 2],
                                                    "min_distance_per_frame": [None, None, 0.25]})):
        (tmp_path / name).mkdir()
        (tmp_path / name / "summary.json").write_text(json.dumps({**s, "contact": contact}
                                                                 if contact else s))
    table = _script("newton_contact_table")
    assert table.cli([str(tmp_path / "plain"), str(tmp_path / "far")]) == 0
    out = capsys.readouterr().out
    assert "| 0 | capped | 30 | 1 | - | - |" in out and "| 2 | - | 3 | 1 | - | - |" in out
    assert "| 1 | capped | 30 | 1 | 0 | - |" in out and "| 2 | - | 3 | 1 | 2 | 0.25 |" in out
    assert out.count("frames converged 0/3 (2 capped), iterations 63, frames cut back 0") == 2
    (tmp_path / "plain" / "summary.json").write_text('{"ranks": 1, "newton_it')
    with pytest.raises(SystemExit):
        table.cli([str(tmp_path / "plain")])
    assert "summary.json is not a readable summary of drivers/simulate.py (JSONDecodeError" in capsys.readouterr().err


def test_compare_trees_refuses_bad_input_and_names_a_failed_runs_log(tmp_path, capsys, monkeypatch):
    """compare_trees.py: a missing checkpoint, a TREE that is no checkout and a PETSc option
    (which the runs never got) are one error line, exit 2, nothing written (on main: a
    FileNotFoundError traceback after creating OUT/a0, a traceback from the first run's
    mpiexec, and the option silently dropped); a run that fails (a config the job refuses)
    is exit 3 naming its message and its log (on main: CalledProcessError's traceback)."""
    for name in ("OMPI_ALLOW_RUN_AS_ROOT", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM"):   # the runs' mpiexec as root (CI)
        monkeypatch.setenv(name, "1")
    ct = _script("compare_trees")
    cfg = tmp_path / "s.toml"
    cfg.write_text("[scene]\nkind = \"smash\"\n")
    ck = tmp_path / "ck.h5"
    ck.write_bytes(b"")
    out = tmp_path / "c"
    base = ["--config", str(cfg), "--frames", "3", "--out", str(out)]
    for args, words in (([*base, "--checkpoint", str(tmp_path / "none.h5"), str(ROOT), str(ROOT)],
                         f"--checkpoint {tmp_path / 'none.h5'}: no such file"),
                        ([*base, "--checkpoint", str(ck), str(ROOT), str(tmp_path)],
                         f"TREE {tmp_path}: not a checkout of lc_petsc (no drivers/simulate.py there)"),
                        ([*base, "--checkpoint", str(ck), str(ROOT), str(ROOT), "-ksp_rtol", "1e-3"],
                         "unrecognized arguments: -ksp_rtol 1e-3 (the runs get no PETSc options")):
        with pytest.raises(SystemExit) as stop:
            ct.main(args)
        assert stop.value.code == 2 and words in capsys.readouterr().err
        assert not out.exists()
    assert ct.main([*base, "--checkpoint", str(ck), "--rounds", "1", str(ROOT), str(ROOT)]) == 3
    err = capsys.readouterr().err
    assert f"compare_trees.py: error: the run of {ROOT} into {out / 'a0'} ended with exit status 2: " in err
    assert f"(all of it: {out / 'a0'}.log)" in err and "scene.kind must be one of" in err


def test_touching_wisps_refuses_a_set_that_would_write_a_broken_config(tmp_path, capsys):
    """touching_wisps.py --set of a key it writes from a flag (time.frames: a key set twice)
    or a value that is not TOML (an unquoted string) is refused naming the flag or the
    quoting, nothing written; main wrote a config simulate.py then refused as invalid TOML.
    --frames 0 is argparse's error (main wrote it)."""
    ts = _script("touching_wisps")
    for extra, words in ((["time.frames=5"], "--set time.frames: the script writes it from --frames"),
                         (["time.newton_iterations=9"], "from --cap; give that instead"),
                         (["solver.options=-ksp_rtol 1e-8"], "not TOML values or a key set twice")):
        with pytest.raises(ValueError, match=words):
            ts.write(tmp_path / "w", 10, 1e-4, 30, extra)
        assert not (tmp_path / "w").exists()
    cfg = load_config(ts.write(tmp_path / "w", 10, 1e-4, 30, ['solver.options="-ksp_rtol 1e-8"']))
    assert cfg.solver.options == "-ksp_rtol 1e-8"
    with pytest.raises(SystemExit):
        ts.cli([str(tmp_path / "z"), "--frames", "0"])
    assert "--frames: must be an integer >= 1" in capsys.readouterr().err and not (tmp_path / "z").exists()


def test_contact_work_stats_help_and_bad_input_write_nothing(tmp_path):
    """contact_work_stats.py --help prints its usage (exit 0); a prefix without a script is one
    error line (exit 2); neither writes a file: on main --help was taken as the PREFIX, the
    empty script list an IndexError traceback, and its exit hook wrote ``--help.0.json``."""
    proc = _run(tmp_path, "contact_work_stats.py", "--help")
    assert proc.returncode == 0 and "mpiexec -n 2 python scripts/contact_work_stats.py PREFIX" in proc.stdout
    proc = _run(tmp_path, "contact_work_stats.py", "stats")
    assert proc.returncode == 2 and "error: give PREFIX SCRIPT.py [its arguments], got stats" in proc.stderr
    assert "Traceback" not in proc.stderr and list(tmp_path.iterdir()) == []


def test_bench_cg_iteration_times_every_part_of_the_recorded_solves(tmp_path, monkeypatch, capsys):
    """``bench_cg_iteration.py``: the touching wisps' first frame recorded (A, C, b apart),
    loaded back and solved with the default cluster preconditioner in the run's CG
    iterations, the clusters' solve timed; without clusters (the contact left to CG) A's
    and C's products, the band solve and KSP's rest timed per iteration; each kernel alone
    with a positive rate."""
    import lc_petsc.simulator as simulator
    from mpi4py import MPI
    from lc_petsc.studies.compare import record
    from lc_petsc.studies.systems import destroy_systems
    from sim_helpers import touching_wisps_source
    monkeypatch.setattr(simulator, "source_from_config", lambda *a, **k: touching_wisps_source())
    bench = _script("bench_cg_iteration")
    systems, rows, info = record(touching_wisps_config(1, options=""), MPI.COMM_WORLD, frames=1)
    try:
        bench.write_systems(tmp_path / "sys", systems, rows, info, MPI.COMM_WORLD)
    finally:
        destroy_systems(systems)
    run = json.loads((tmp_path / "sys" / "layout.json").read_text())["run_ksp_iterations"]
    for options, parts in (([], ("cluster solve (CPU)",)),      # the contact in the clusters' exact solves
                           (["--options", "-lc_cluster_max_wisps 1"],    # no cluster: the contact left to CG
                            ("A product (CPU)", "C diagonal block (CPU)", "band solve (CPU)", "KSP rest (CPU)"))):
        assert bench.main(["solve", str(tmp_path / "sys"), "--repeats", "1", *options]) == 0
        out = capsys.readouterr().out
        its = [int(v) for v in out.split("CG per solve: [")[1].split("]")[0].split(",")]
        assert its == run if not options else (len(its) == len(run) and min(its) > 1)
        times = {line[:44].strip(): float(line.split()[-1]) for line in out.splitlines()
                 if line.startswith("  ") and line.split()[-1].replace(".", "").isdigit()}
        for part in parts + ("solve (CPU)",):
            assert times[part] > 0, part
    assert bench.main(["kernels", str(tmp_path / "sys"), "--repeats", "1"]) == 0
    out = capsys.readouterr().out
    for kernel in ("A product", "band solve", "C diagonal block", "clusters' factor", "PETSc's LU"):
        line = next(x for x in out.splitlines() if kernel in x and "GB/s" not in x[:20] and "|" in x)
        assert float(line.split("(")[-1].split(")")[0]) > 0, line
