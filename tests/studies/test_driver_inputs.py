"""The study drivers and scripts given bad input (drivers/compare_solvers.py,
drivers/tradeoff.py, scripts/extremes.py, scripts/count_crossings.py,
scripts/bench_usd.py, the benchmarks and studies of scripts/): a missing or wrong file,
an unknown option set, an out-of-range or misspelt flag is one error line and exit
status 2, no traceback, nothing run."""

import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


def _strands(path, rest=False):
    """A strands file (a groom, not a run); with ``rest`` also the datasets a frames.h5
    has besides (rest positions, radius, pinned)."""
    with h5py.File(path, "w") as f:
        f["positions"] = np.arange(24.0).reshape(8, 3)
        f["wisp_offsets"] = np.array([0, 4, 8])
        if rest:
            f["rest_positions"] = np.arange(24.0).reshape(8, 3)
            f["radius"] = np.ones(8)
            f["pinned"] = np.zeros(8, bool)
    return str(path)


def _wisps_refused(prog):
    """The error of ``--wisps`` on a groom file's config (one helper behind every script)."""
    return (f"{prog}.py: error: --wisps sets scene.n_wisps, which only a hairball scene has; "
            "configs/from_file.toml is scene.kind = 'file': leave out --wisps")


CASES = [
    ("drivers/tradeoff.py", ["--scene", "nope.toml"],
     "tradeoff.py: error: --scene 'nope.toml': not a built-in scene (hairball, smash, jitter) and no "
     "such config file"),
    ("drivers/tradeoff.py", ["--set", "nope"], "tradeoff.py: error: no option set(s) ['nope'] in "),
    ("drivers/tradeoff.py", ["--duration", "-1"],
     "tradeoff.py: error: argument --duration: must be a positive number, got -1"),
    ("drivers/tradeoff.py", ["--wispz", "3"],
     "tradeoff.py: error: unrecognized arguments: --wispz (see --help; PETSc options take one dash)"),
    # --wisps on a config without a hairball, or on the one-wisp built-ins, was ignored
    # silently by tradeoff.py: the study ran the one-wisp scene
    ("drivers/tradeoff.py", ["--scene", "configs/from_file.toml", "--wisps", "3"], _wisps_refused("tradeoff")),
    ("drivers/tradeoff.py", ["--scene", "smash", "--wisps", "3"],
     "tradeoff.py: error: --wisps sets the hairball's wisp count; --scene smash is one wisp: leave out --wisps"),
    ("drivers/compare_solvers.py", ["--config", "nope.toml"],
     "compare_solvers.py: error: nope.toml: no such config file"),
    ("drivers/compare_solvers.py", ["--config", "configs/from_file.toml", "--wisps", "3"],
     _wisps_refused("compare_solvers")),
    # a figure type matplotlib cannot write used to be a traceback after the whole count
    ("scripts/edge_strain.py", ["STRANDS", "--plot", "SCRATCH/s.txt"],
     "edge_strain.py: error: argument --plot: SCRATCH/s.txt: not a figure format matplotlib writes; "
     "end the name in one of "),
    ("scripts/newton_frames.py", ["--plot", "SCRATCH/f.nope"],
     "newton_frames.py: error: argument --plot: SCRATCH/f.nope: not a figure format matplotlib writes"),
    # --wisps on a groom file's config used to be ignored silently by these two
    ("scripts/bench_contact.py", ["--config", "configs/from_file.toml", "--wisps", "3"],
     _wisps_refused("bench_contact")),
    ("scripts/bench_partition.py", ["--config", "configs/from_file.toml", "--wisps", "3"],
     _wisps_refused("bench_partition")),
    ("drivers/compare_solvers.py", ["--sets-dir", "SCRATCH"],
     "compare_solvers.py: error: no option sets (*.opts files) in "),
    ("drivers/compare_solvers.py", ["--restart", "SCRATCH/ck.h5"],
     "compare_solvers.py: error: --restart needs --config (the config its checkpoint ran with)"),
    ("drivers/compare_solvers.py", ["--config", "configs/hairball_demo.toml", "--restart", "SCRATCH/ck.h5"],
     "compare_solvers.py: error: --restart SCRATCH/ck.h5: no such checkpoint file"),
    ("drivers/compare_solvers.py", ["--repeats", "0"],
     "compare_solvers.py: error: argument --repeats: must be an integer >= 1, got 0"),
    ("drivers/compare_solvers.py", ["--wisps", "0"],
     "compare_solvers.py: error: argument --wisps: must be an integer >= 1, got 0"),
    ("scripts/extremes.py", ["--only", "nope"],
     "extremes.py: error: --only nope: no case name starts with that; the cases: smash60, "),
    ("scripts/extremes.py", ["--cap", "20"],
     "extremes.py: error: --cap 20 caps the iterations of a run to --tolerance; add --tolerance TOL"),
    ("scripts/extremes.py", ["--tolerance", "1e-6", "--start-increment-tol", "1e-3"],
     "extremes.py: error: --start-increment-tol converges the first frames of a fixed count; with "
     "--tolerance every frame runs to the tolerance: give one of the two"),
    ("scripts/extremes.py", ["--tolerance", "0"],
     "extremes.py: error: argument --tolerance: must be a positive number, got 0"),
    ("scripts/count_crossings.py", ["STRANDS"],
     "/positions has shape (8, 3), a frames.h5 has (frames, 8 vertices, 3) (a strands file is a "
     "groom, not a run)"),
    ("scripts/bench_usd.py", ["SCRATCH/nope.h5"],
     "bench_usd.py: error: SCRATCH/nope.h5: not a readable frames.h5 of lc_petsc"),
    ("scripts/bench_usd.py", ["STRANDS"], "not a readable frames.h5 of lc_petsc (\"no 'dt' attribute\")"),
    # a misspelt flag used to be dropped (parse_known_args) and the 2,000-wisp default run
    ("scripts/bench_step.py", ["--wispz", "10"],
     "bench_step.py: error: unrecognized arguments: --wispz (see --help; PETSc options take one dash)"),
    ("scripts/bench_product.py", ["--repeats", "0"],
     "bench_product.py: error: argument --repeats: must be an integer >= 1, got 0"),
    ("scripts/bench_contact.py", ["--config", "nope.toml"], "bench_contact.py: error: nope.toml: no such config file"),
    ("scripts/bench_contact.py", ["--framez", "2"],
     "bench_contact.py: error: unrecognized arguments: --framez (see --help; PETSc options take one dash)"),
    ("scripts/bench_partition.py", ["--config", "STRANDS"],
     "bench_partition.py: error: SCRATCH/groom.h5: not a UTF-8 text file"),
    ("scripts/bench_ccd.py", ["configs/smash.toml", "--modes", "ccd+selff"],
     "bench_ccd.py: error: --modes ccd+selff: physics.strand_contact_potential must be one of"),
    ("scripts/bench_ccd.py", ["--compare", "STRANDS"], "bench_ccd.py: error: SCRATCH/groom.h5: not a --json file of "
     "bench_ccd.py ("),
    ("scripts/bench_checkpoint.py", ["--config", "nope.toml"],
     "bench_checkpoint.py: error: nope.toml: no such config file"),
    ("scripts/bench_checkpoint.py", ["--config", "configs/smash.toml", "--dir", "SCRATCH/nope"],
     "bench_checkpoint.py: error: --dir SCRATCH/nope: no such folder"),
    ("scripts/newton_history.py", ["--scenes", "hairball10", "smash", "--variant", "x=filter=nah"],
     "newton_history.py: error: --variant x=filter=nah: solver.filter must be one of"),
    # an on/off word that is neither was read as off
    ("scripts/newton_history.py", ["--scenes", "smash", "--variant", "x=ls=maybe"],
     "newton_history.py: error: --variant x=ls=maybe: variant value 'maybe': use one of 1, true, yes, on, "
     "0, false, no, off"),
    ("scripts/newton_history.py", ["--scenes", "smash", "--variant", "x=head=maybe"],
     "newton_history.py: error: --variant x=head=maybe: variant value 'maybe': use one of"),
    ("scripts/newton_history.py", ["--variant", "analytic"],
     "newton_history.py: error: --variant 'analytic': use NAME=SPEC, e.g."),
    ("scripts/newton_errors.py", ["--scene", "smash", "--variant", "colour=red", "--out", "SCRATCH/out/e.json"],
     "newton_errors.py: error: --variant colour=red: variant part 'colour=red': use key=value with key one of"),
    ("scripts/fixed_count_errors.py", ["--scene", "smash", "x=colour=red"],
     "fixed_count_errors.py: error: variant part 'colour=red': use key=value with key one of"),
    ("scripts/fixed_count_errors.py", ["--scene", "smash", "x=root_rotation=maybe"],
     "fixed_count_errors.py: error: variant part 'root_rotation=maybe': root_rotation is true or false"),
    ("scripts/fixed_count_errors.py", ["--scene", "smash", "x=default@default"],
     "fixed_count_errors.py: error: 'x=default@default': @SPEC2 sets the first frames of --from K: give --from"),
    ("scripts/fixed_count_errors.py", ["--frames", "1", "--from", "1", "--out", "SCRATCH/out/e.json", "x=default"],
     "fixed_count_errors.py: error: --from 1 is not below --frames 1: no frame would run from the reference's "
     "state; give --from 0 to 0"),
    ("scripts/fixed_count_errors.py", ["--scene", "nope", "x=default"],
     "fixed_count_errors.py: error: --scene 'nope': use one of hairball10, demo10, smash"),
    ("scripts/newton_frames.py", ["--scene", "nope", "--out", "SCRATCH/out/f.json"],
     "newton_frames.py: error: 'nope': not a built-in scene (hairball10, demo10, smash) and no such config file"),
    ("scripts/newton_rates.py", ["--scene", "STRANDS"], "newton_rates.py: error: SCRATCH/groom.h5: not a UTF-8"),
    ("scripts/bench_cutback.py", ["--scenes", "smash", "--setting", "x=a,b"],
     "bench_cutback.py: error: --setting 'x=a,b': use NAME=CAP,SUBSTEPS[,DT"),
    ("scripts/bench_cutback.py", ["--scenes", "smash", "--setting", "x=6,2,,bogus"],
     "bench_cutback.py: error: --setting x on smash: time.newton must be one of"),
    # a groom with a frames.h5's other datasets used to end in an IndexError / ValueError
    ("scripts/edge_strain.py", ["GROOM2"], "edge_strain.py: error: SCRATCH/groom2.h5: not a readable frames.h5 "
     "of lc_petsc (/positions has shape (8, 3), a frames.h5 has (frames, 8 vertices, 3)"),
    ("scripts/pair_census.py", ["GROOM2"], "pair_census.py: error: SCRATCH/groom2.h5: not a readable frames.h5 "
     "of lc_petsc (/positions has shape (8, 3)"),
    ("scripts/pair_census.py", ["STRANDS", "--every", "0"],
     "pair_census.py: error: argument --every: must be an integer >= 1, got 0"),
    ("scripts/pair_census.py", ["STRANDS", "--thickness", "-1"],
     "pair_census.py: error: argument --thickness: must be a positive number, got -1"),
    # an output in a missing folder: refused before the count, not a traceback after it
    ("scripts/count_crossings.py", ["STRANDS", "--json", "SCRATCH/nope/c.json"],
     "count_crossings.py: error: argument --json: SCRATCH/nope/c.json: no such folder SCRATCH/nope"),
    # counts of 0 used to end in a traceback (median or min of nothing) after the set-up
    ("scripts/bench_elements.py", ["--repeats", "0"],
     "bench_elements.py: error: argument --repeats: must be an integer >= 1, got 0"),
    ("scripts/profile_compiled.py", ["--repeats", "0"],
     "profile_compiled.py: error: argument --repeats: must be an integer >= 1, got 0"),
    ("scripts/count_compiled.py", ["twist", "1", "--wisps", "0"],
     "count_compiled.py: error: argument --wisps: must be an integer >= 1, got 0"),
    ("scripts/weak_scaling.py", ["--per-rank", "0"],
     "weak_scaling.py: error: argument --per-rank: must be an integer >= 1, got 0"),
    ("scripts/report_contact.py", ["STRANDS"], "report_contact.py: error: cannot read SCRATCH/groom.h5: "),
]

#: the scripts that write into an ``--out`` folder (given one in SCRATCH/out, which must stay absent)
TAKES_OUT = ("drivers/tradeoff.py", "drivers/compare_solvers.py", "scripts/extremes.py",
             "scripts/bench_partition.py", "scripts/newton_history.py", "scripts/newton_rates.py",
             "scripts/bench_cutback.py", "scripts/weak_scaling.py", "scripts/report_contact.py")


@pytest.mark.parametrize("script, args, message", CASES, ids=[f"{c[0]} {' '.join(c[1])}" for c in CASES])
def test_bad_input_is_one_line_and_exit_2(tmp_path, script, args, message):
    strands, groom2 = _strands(tmp_path / "groom.h5"), _strands(tmp_path / "groom2.h5", rest=True)
    args = [a.replace("SCRATCH", str(tmp_path)).replace("STRANDS", strands).replace("GROOM2", groom2)
            for a in args]
    message = message.replace("SCRATCH", str(tmp_path))
    out = tmp_path / "out"
    # the temporary folder the script sees: scripts/extremes.py left one in /tmp on every
    # run (lc_extremes_*, its groom file), even on bad input
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    proc = subprocess.run([sys.executable, str(ROOT / script), *args]
                          + (["--out", str(out)] if script in TAKES_OUT else []),
                          cwd=ROOT, capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL,
                          env=dict(os.environ, TMPDIR=str(tmp)))
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    error_lines = [line for line in proc.stderr.splitlines() if "error:" in line]
    assert len(error_lines) == 1 and message in error_lines[0], proc.stderr
    assert not out.exists()
    assert sorted(p.name for p in tmp.iterdir()) == []


@pytest.mark.parametrize("args, message", [
    (["--wisps", "0"], "tradeoff.py: error: argument --wisps: must be an integer >= 1, got 0"),
    (["--scene", "nope.toml"], "tradeoff.py: error: --scene 'nope.toml': not a built-in scene")])
def test_bad_input_under_mpiexec_is_reported_once(tmp_path, args, message):
    """argparse's error and the driver's own: printed by rank 0 only, on 2 ranks."""
    from sim_helpers import MPI_ENV
    proc = subprocess.run(["mpiexec", "-n", "2", sys.executable, str(ROOT / "drivers/tradeoff.py"), *args,
                           "--out", str(tmp_path / "out")], cwd=ROOT, env=MPI_ENV, capture_output=True,
                          text=True, timeout=120, stdin=subprocess.DEVNULL)
    assert proc.returncode == 2, proc.stderr[-2000:]
    error_lines = [line for line in proc.stderr.splitlines() if "error:" in line]
    assert len(error_lines) == 1 and message in error_lines[0], proc.stderr
    assert proc.stderr.count("usage:") <= 1 and "Traceback" not in proc.stderr


def test_a_binary_option_set_is_named(tmp_path):
    """An option set that is not UTF-8 text (a binary file named *.opts) ended
    compare_solvers.py in a UnicodeDecodeError traceback naming no file; now one error
    line names it (exit 2), and so does a folder named *.opts."""
    sets = tmp_path / "sets"
    sets.mkdir()
    (sets / "default.opts").write_text("-ksp_type cg\n")
    (sets / "bin.opts").write_bytes(b"-ksp_type \xff\xfe\n")
    for bad, why in [("bin", "not a text file of PETSc options (invalid start byte at byte 10)"),
                     ("dir", "cannot read the options file: Is a directory")]:
        if bad == "dir":
            (sets / "bin.opts").unlink()
            (sets / "dir.opts").mkdir()
        proc = subprocess.run([sys.executable, str(ROOT / "drivers" / "compare_solvers.py"), "--sets-dir",
                               str(sets), "--out", str(tmp_path / "out")], cwd=ROOT, capture_output=True,
                              text=True, timeout=120, stdin=subprocess.DEVNULL)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
        assert proc.stderr.strip() == f"compare_solvers.py: error: option set '{sets / (bad + '.opts')}': {why}"
        assert not (tmp_path / "out").exists()
