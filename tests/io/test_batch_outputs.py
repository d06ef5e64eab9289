"""The main job end to end: the demo scene under mpiexec -n 2 at a reduced frame count,
frames.h5 layout (identical on 1 and 2 ranks up to round-off), frames.xdmf read back by
VTK's XDMF reader (the reader ParaView uses), previews, summary.json, report, a run
that fails part-way."""

import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.batch import main
from lc_petsc.io.frames_read import FramesReader

ROOT = Path(__file__).resolve().parents[2]
from sim_helpers import MPI_ENV, hairball_toml, undocumented_outputs, undocumented_summary_keys  # noqa: E402
DEMO_FRAMES = 4

SMALL = hairball_toml(frames=8, output="every = 2\npreview_frames = [0, -1]\ncontact_sheet = 4")


def _mpiexec(n, args, cwd):
    cmd = ["mpiexec", "--oversubscribe", "-n", str(n), sys.executable,
           str(ROOT / "drivers" / "simulate.py")] + args
    return subprocess.run(cmd, capture_output=True, text=True, env=MPI_ENV, timeout=150, cwd=cwd)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """configs/hairball_demo.toml on 2 ranks, DEMO_FRAMES frames, a PETSc override."""
    d = tmp_path_factory.mktemp("demo")
    p = _mpiexec(2, [str(ROOT / "configs" / "hairball_demo.toml"), "--frames", str(DEMO_FRAMES),
                     "--out", str(d / "out"), "-ksp_rtol", "1e-8"], cwd=d)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return d / "out", p


def test_every_summary_key_and_output_is_documented_in_the_readme(demo):
    """Every key of the demo's summary.json (and of its records: output, shape, contact,
    crossings and its head check, ...) is named in the README's summary.json row, and
    every file of its output folder in the outputs table; before, 54 of its keys were not
    (element_kernels, jit_compile_s, config_file, the contact's and the head check's
    figures, ...).  A key added to the summary without its documentation fails here (as
    does a restart's, tests/io/test_checkpoint_restart.py)."""
    out, _ = demo
    s = json.loads((out / "summary.json").read_text())
    assert undocumented_summary_keys(s) == [] and undocumented_outputs(out) == []
    assert {"element_kernels", "contact", "crossings"} <= set(s) and "head" in s["crossings"]
    s["newton_bogus"] = 1
    s["output"]["bogus_s"] = 0.0
    s["checkpoints"] = [{"frame": 1, "bogus": 2}]
    s["config"]["bogus"] = 3                 # the resolved config: README's config table names its keys
    assert undocumented_summary_keys(s) == ["checkpoints.bogus", "newton_bogus", "output.bogus_s"]


def test_demo_end_to_end(demo):
    out, p = demo
    names = {"frames.h5", "frames.xdmf", "summary.json", "contact_sheet.png", "previews"}
    assert names <= {q.name for q in out.iterdir()}
    s = json.loads((out / "summary.json").read_text())
    for key in ("dofs", "wisps", "ranks", "frames", "wall_time_s", "timings_s", "newton_iterations",
                "ksp_iterations", "ksp_reasons", "converged", "petsc_options", "config"):
        assert key in s, key
    assert set(s["timings_s"]) >= {"elements", "filter", "assembly", "solve", "collision", "io"}
    assert s["wisps"] == 300 and s["dofs"] == 300 * 101 * 3 and s["ranks"] == 2
    assert s["frames"] == DEMO_FRAMES and s["converged"] and s["error"] is None
    assert s["newton_iterations"] == [3] * DEMO_FRAMES
    assert s["terms"] == ["stretch", "bend", "twist", "gravity", "head_collision", "strand_collision"]
    c = s["contact"]
    assert len(c["pairs_per_frame"]) == DEMO_FRAMES and c["thickness"] == pytest.approx(0.14)
    # config options file < command line; the options actually used are recorded
    assert s["petsc_options_used"]["ksp_rtol"] == "1e-8"
    assert s["petsc_options_used"]["pc_type"] == "bjacobi"
    assert "-ksp_rtol 1e-8" in s["petsc_options"]
    assert s["config"]["scene"]["n_wisps"] == 300 and s["config"]["time"]["frames"] == DEMO_FRAMES
    assert s["timings_s"]["io"] > 0 and s["timings_s"]["collision"] > 0
    # the CPU time of the frame loop, summed over ranks, holds each rank's phases' CPU time
    assert set(s["cpu_timings_s"]) == set(s["timings_s"]) and s["cpu_timings_s"]["solve"] > 0
    assert s["cpu_time_s"] >= max(s["cpu_timings_s"].values()) > 0
    assert f" over {s['ranks']} rank(s))" in p.stdout
    # each rank's peak resident set: a Python process with PETSc and the demo holds 100 MiB to 4 GiB
    peak = s["peak_memory_mib"]
    assert 100 < peak["max_rank"] < 4096 and peak["max_rank"] < peak["sum_ranks"] <= 2 * peak["max_rank"]
    assert f"peak memory {peak['max_rank'] / 1024:.2f} GiB on the largest rank" in p.stdout
    # report on stdout, once
    assert p.stdout.count("lc_petsc: ") == 1 and "converged: yes" in p.stdout
    assert "per frame" in p.stdout and "phases" in p.stdout
    assert "Traceback" not in p.stderr
    # a batch log (stderr not a terminal) shows progress as plain lines, rank 0 only
    lines = [ln for ln in p.stderr.splitlines() if " per frame, " in ln]
    assert lines[0].startswith(f"hairball_demo: frame 1/{DEMO_FRAMES} (25%), ")
    assert lines[-1].startswith(f"hairball_demo: frame {DEMO_FRAMES}/{DEMO_FRAMES} (100%), ")
    assert lines[-1].endswith("0 s left, Newton 3, KSP " + lines[-1].rsplit("KSP ", 1)[1])


def test_log_progress_lines_at_most_every_interval():
    import io

    from lc_petsc.job import LogProgress
    now = [0.0]
    out = io.StringIO()
    bar = LogProgress(100, "scene", interval=30.0, stream=out, clock=lambda: now[0])
    for k in range(100):
        now[0] += 2.0                       # 2 s per frame: a line every 15 frames
        bar.set_postfix_str(f"Newton 3, KSP {k}")
        bar.update(1)
    lines = out.getvalue().splitlines()
    assert lines[0] == "scene: frame 1/100 (1%), 2 s per frame, 3 min 18 s left, Newton 3, KSP 0"
    assert [int(ln.split()[2].split("/")[0]) for ln in lines] == [1, 16, 31, 46, 61, 76, 91, 100]
    assert lines[-1] == "scene: frame 100/100 (100%), 2 s per frame, 0 s left, Newton 3, KSP 99"
    slow = LogProgress(3, "s", interval=30.0, stream=out, clock=lambda: now[0])
    now[0] += 4000.0
    slow.update(1)
    assert out.getvalue().splitlines()[-1] == "s: frame 1/3 (33%), 1 h 06 min per frame, 2 h 13 min left"


def test_frames_file_layout(demo):
    out, _ = demo
    with h5py.File(out / "frames.h5", "r") as f:
        nv = 300 * 101
        assert f["positions"].shape == (DEMO_FRAMES + 1, nv, 3) and f["positions"].dtype == np.float64
        assert f["time"].shape == (DEMO_FRAMES + 1,) and f["time"].dtype == np.float64
        assert np.allclose(f["time"][...], np.arange(DEMO_FRAMES + 1) / 30.0)
        off = f["wisp_offsets"][...]
        assert off.dtype == np.int64 and np.array_equal(off, 101 * np.arange(301))
        assert f["rest_positions"].shape == (nv, 3) and f["pinned"].dtype == np.bool_
        assert f["pinned"][...].sum() == 4 * 300
        assert np.array_equal(f["positions"][0], f["rest_positions"][...])
        X = f["positions"][-1]
        pin = f["pinned"][...]
        assert np.all(np.isfinite(X)) and np.abs(X[~pin] - f["rest_positions"][...][~pin]).max() > 0.01
        cfg = json.loads(f.attrs["config"])
        assert cfg["scene"]["kind"] == "hairball" and f.attrs["every"] == 1


def test_xdmf_read_back_by_vtk(demo):
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline as SDDP
    from vtkmodules.vtkIOXdmf2 import vtkXdmfReader
    out, _ = demo
    with h5py.File(out / "frames.h5", "r") as f:
        X, T = f["positions"][...], f["time"][...]
    r = vtkXdmfReader()
    r.SetFileName(str(out / "frames.xdmf"))
    r.UpdateInformation()
    steps = r.GetOutputInformation(0).Get(SDDP.TIME_STEPS())
    assert np.allclose(steps, T)
    for k in [len(T) - 1, 0, 2]:        # out of order: no cached frame comes back
        r.UpdateTimeStep(T[k])
        g = r.GetOutputDataObject(0)
        assert g.GetNumberOfCells() == 300
        assert all(g.GetCellType(c) == 4 and g.GetCell(c).GetNumberOfPoints() == 101   # VTK_POLY_LINE
                   for c in (0, 150, 299))
        P = vtk_to_numpy(g.GetPoints().GetData())
        assert np.array_equal(P, X[k]), k


def test_previews_written(demo):
    import matplotlib.image as mpimg
    out, _ = demo
    files = sorted((out / "previews").glob("frame_*.png"))
    assert [q.name for q in files] == [f"frame_{i:05d}.png" for i in sorted({0, DEMO_FRAMES})]
    for q in files + [out / "contact_sheet.png"]:
        img = mpimg.imread(q)
        assert q.stat().st_size > 10_000 and img.shape[0] > 300 and img.shape[1] > 300
        assert img[..., :3].std() > 0.05, f"{q.name} is blank"


def test_frames_identical_on_1_and_2_ranks(tmp_path):
    (tmp_path / "s.toml").write_text(SMALL)
    p = _mpiexec(2, ["s.toml", "--out", "two", "--quiet"], cwd=tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    cwd = os.getcwd()
    try:
        os.chdir(tmp_path)
        assert main(["s.toml", "--out", "one", "--quiet"], comm=MPI.COMM_SELF) == 0
    finally:
        os.chdir(cwd)
    with h5py.File(tmp_path / "one" / "frames.h5") as a, h5py.File(tmp_path / "two" / "frames.h5") as b:
        assert set(a) == set(b) == {"positions", "time", "wisp_offsets", "rest_positions", "pinned",
                                    "radius", "polylines", "row_digest"}
        for k in a:
            assert a[k].shape == b[k].shape and a[k].dtype == b[k].dtype, k
            if k == "row_digest":       # of positions equal to 1e-10: each file's its own rows'
                for f in (a, b):
                    with FramesReader(f.filename) as fr:
                        assert all(fr.digest_problem(r, f["positions"][r]) is None for r in range(f[k].shape[0]))
            elif k == "positions":
                scale = np.abs(a[k][...]).max()
                assert np.abs(a[k][...] - b[k][...]).max() <= 1e-10 * scale
            else:
                assert np.array_equal(a[k][...], b[k][...]), k
        assert a["positions"].shape[0] == 1 + 8 // 2
        assert {k: v for k, v in a.attrs.items() if k != "ranks"} == \
            {k: v for k, v in b.attrs.items() if k != "ranks"}
        assert (a.attrs["ranks"], b.attrs["ranks"]) == (1, 2)


@pytest.mark.parametrize("error_flag", [[], ["-ksp_error_if_not_converged"]])
def test_run_failing_part_way_keeps_frames_and_says_so(tmp_path, capsys, error_flag):
    """A diverged solve ends the run with exit 3, its message and readable outputs; with
    -ksp_error_if_not_converged (PETSc raises instead of returning the reason) the same,
    not an internal error that aborts and leaves frames.h5 unreadable."""
    (tmp_path / "s.toml").write_text(SMALL)
    out = tmp_path / "o"
    code = main([str(tmp_path / "s.toml"), "--out", str(out), "--quiet",
                 "-pc_type", "none", "-ksp_max_it", "2"] + error_flag, comm=MPI.COMM_SELF)
    o, err = capsys.readouterr()
    assert code == 3
    assert "DIVERGED_MAX_IT" in err and "Traceback" not in err
    s = json.loads((out / "summary.json").read_text())
    assert not s["converged"] and "DIVERGED_MAX_IT" in s["error"]
    with h5py.File(out / "frames.h5") as f:
        assert f["positions"].shape[0] == f["time"].shape[0] == 1    # the initial state only
    assert (out / "frames.xdmf").exists()


def test_report_after_a_restart_divides_by_this_runs_frames():
    """A run restarted at frame 30 of 40 times 10 frames: the report's per-frame figure
    is its wall time over those 10, not over all 40 (it said 3.15 s for 12.6 s)."""
    from lc_petsc.io.summary import format_report
    s = {"frames": 40, "frames_this_run": 10, "wall_time_s": 126.0, "wisps": 2, "dofs": 6, "ranks": 2,
         "config": {"time": {"dt": 1.0 / 30.0}}}
    line = format_report(s).splitlines()[2]
    assert "frames: 40, 1.33 s simulated (10 in this run); wall time 126.00 s (12.60 s per frame)" in line
    del s["frames_this_run"]
    assert "(3.15 s per frame)" in format_report(s).splitlines()[2]


def test_report_of_a_restart_that_only_wrote_the_outputs_has_no_phase_shares():
    """A restart after the last frame's checkpoint runs no frame: the set-up's assembly
    over a 0.2 ms wall time read as 517%; the phases line says no frame ran."""
    from lc_petsc.io.summary import format_report
    s = {"frames": 6, "frames_this_run": 0, "wall_time_s": 2e-4, "wisps": 2, "dofs": 6, "ranks": 1,
         "config": {"time": {"dt": 1.0 / 30.0}}, "timings_s": {"assembly": 8e-4}}
    report = format_report(s)
    assert "phases: no frame ran in this run (the outputs only)" in report and "%)" not in report
    s["frames_this_run"] = 1
    assert "assembly 0.8 ms (400%)" in format_report(s)


def test_report_of_a_run_whose_first_step_failed_says_so():
    """A run that failed in its first step (frame 0 -> 1, exit 3) was reported as "no
    frame ran in this run (the outputs only)", as if it had nothing to do."""
    from lc_petsc.io.summary import format_report
    s = {"frames": 0, "frames_this_run": 0, "wall_time_s": 0.0, "wisps": 2, "dofs": 6, "ranks": 2,
         "config": {"time": {"dt": 1.0 / 30.0}}, "timings_s": {"solve": 1.3e-3, "filter": 0.0},
         "error": "linear solve failed at frame 0, Newton iteration 0: DIVERGED_NANORINF"}
    report = format_report(s)
    assert ("phases: no frame completed in this run: its first step failed (the error below); the failed "
            "step's phases (max over ranks): solve 1.3 ms\n") in report
    assert "the outputs only" not in report and "%)" not in report


def test_report_counts_chord_checks_only_when_there_are_some():
    """The report says how many chord checks (time.newton_stop = "chord_estimate") the run
    solved and in how many frames; a run without any says nothing about them."""
    from lc_petsc.io.summary import format_report
    s = {"frames": 3, "wall_time_s": 3.0, "wisps": 2, "dofs": 6, "ranks": 1,
         "config": {"time": {"dt": 1.0 / 30.0}}, "newton_chord_checks": [0, 2, 1]}
    assert "chord checks (time.newton_stop = \"chord_estimate\"): 3 solves in 2 frames" in format_report(s)
    s["newton_chord_checks"] = [0, 0, 0]
    assert "chord checks" not in format_report(s)


def test_report_counts_the_stop_checks_only_when_there_are_some():
    """The report says how many stops after filtered steps an exact step verified (and
    refused), and how many stops' coupled curvature stayed unknown; a run without any
    says nothing about them (summary.json counts them per frame)."""
    from lc_petsc.io.summary import format_report
    s = {"frames": 3, "wall_time_s": 3.0, "wisps": 2, "dofs": 6, "ranks": 1,
         "config": {"time": {"dt": 1.0 / 30.0}}, "newton_verified": [1, 0, 2],
         "newton_verify_refused": [1, 0, 0], "newton_coupled_unknown": [0, 1, 0]}
    report = format_report(s)
    assert "stops after filtered steps verified by an exact step: 3 (1 refused) in 2 frames" in report
    assert "contact-coupled wisps is unknown (Lanczos unconverged, kept): 1 in 1 frames" in report
    s["newton_verified"], s["newton_coupled_unknown"] = [0, 0, 0], [0, 0, 0]
    assert "verified by an exact step" not in format_report(s)
    assert "is unknown" not in format_report(s)


def test_preview_frames_outside_the_run_are_named(tmp_path):
    """A scene's preview_frames kept when the run is cut (--frames 3): frames 5 and 20 and
    -9 were drawn as the last and the first frame without a word."""
    (tmp_path / "w.toml").write_text('[scene]\nkind = "wisp4c"\nn_vertices = 12\n[time]\nframes = 30\n'
                                     '[output]\npreview_frames = [0, 2, 5, 20, -1, -9]\ncontact_sheet = 0\n'
                                     'usd = false\n')
    assert main([str(tmp_path / "w.toml"), "--frames", "3", "--out", str(tmp_path / "o"), "--quiet"],
                comm=MPI.COMM_SELF) == 0
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["warnings"] == [
        "output.preview_frames = [0, 2, 5, 20, -1, -9]: the run has frames 0 to 3 (time.frames / "
        "--frames), and [5, 20] lie after its last frame (3), drawn as frame 3; [-9] lie before "
        "frame 0, drawn as frame 0; ask for frames in 0..3 (or -1 .. -4 from the end)"]
    assert sorted(q.name for q in (tmp_path / "o" / "previews").glob("*.png")) == \
        ["frame_00000.png", "frame_00002.png", "frame_00003.png"]


def test_phase_times_lie_within_the_frame_loops_wall_time(tmp_path, capsys):
    """The phases of summary.json (and the report's shares of the wall time) cover the
    frame loop's span, frames.h5's creation and frame 0 included: main timed them as io
    outside ``wall_time_s``, and counted the set-up's phase times too, so a 1-frame run
    reported io 72.2 ms of a 5.1 ms wall time (1421%)."""
    import re
    (tmp_path / "w.toml").write_text('[scene]\nkind = "wisp4c"\nn_vertices = 12\n[time]\nframes = 1\n'
                                     '[output]\npreviews = false\ncontact_sheet = 0\nusd = false\n')
    capsys.readouterr()
    assert main([str(tmp_path / "w.toml"), "--out", str(tmp_path / "o"), "--quiet"], comm=MPI.COMM_SELF) == 0
    report = capsys.readouterr().out
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["timings_s"]["io"] > 0
    assert all(v <= s["wall_time_s"] for v in s["timings_s"].values()), (s["timings_s"], s["wall_time_s"])
    assert all(v <= s["cpu_time_s"] for v in s["cpu_timings_s"].values()), (s["cpu_timings_s"], s["cpu_time_s"])
    [line] = [x for x in report.splitlines() if x.startswith("  phases (max over ranks): ")]
    assert all(int(p) <= 100 for p in re.findall(r"\((\d+)%\)", line)), line


def test_preview_frames_with_every_name_the_frames_drawn(tmp_path):
    """With output.every = 2 and 5 frames, frames.h5 holds frames 0, 2, 4: the warning
    named frame 5 as the one drawn for a frame after the run (it drew frame 4), and a frame
    between two written ones (3) was drawn as frame 2 without a word."""
    (tmp_path / "w.toml").write_text('[scene]\nkind = "wisp4c"\nn_vertices = 12\n[time]\nframes = 5\n'
                                     '[output]\nevery = 2\npreview_frames = [0, 3, 9, -1]\ncontact_sheet = 0\n'
                                     'usd = false\n')
    assert main([str(tmp_path / "w.toml"), "--out", str(tmp_path / "o"), "--quiet"], comm=MPI.COMM_SELF) == 0
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["warnings"][1:] == [
        "output.preview_frames = [0, 3, 9, -1]: the run has frames 0 to 5 (time.frames / --frames), and "
        "[9] lie after its last frame (5), drawn as frame 4; [3] are not written (output.every = 2), each "
        "drawn as the frame written before it; ask for frames in 0, 2, ... 4 (the frames written) (or "
        "-1 .. -6 from the end)"]
    assert sorted(q.name for q in (tmp_path / "o" / "previews").glob("*.png")) == \
        ["frame_00000.png", "frame_00002.png", "frame_00004.png"]


def test_report_names_the_compile_time_in_the_setup():
    """A first run compiles the kernels (minutes, then cached): the report said "setup
    349.18 s" without a word of the 347 s (elements 131.9 s, contact 215.3 s) it spent
    compiling; loading them from the cache (about a second) is not named."""
    from lc_petsc.io.summary import format_report
    s = {"frames": 2, "wall_time_s": 4.2, "wisps": 300, "dofs": 90900, "ranks": 1, "setup_time_s": 349.18,
         "config": {"time": {"dt": 1.0 / 30.0}}, "jit_compile_s": 131.9, "contact": {"jit_compile_s": 215.3}}
    assert "setup 349.18 s (of which compiling the kernels 347.20 s: once, cached for later runs)" \
        in format_report(s).splitlines()[2]
    s.update(setup_time_s=3.1, jit_compile_s=0.4, contact={"jit_compile_s": 0.6})
    assert format_report(s).splitlines()[2].endswith("setup 3.10 s")


@pytest.mark.parametrize("frames, every, checkpoint_every, expected", [
    (3, 5, 0, "frames 1 to 3 are simulated but not written (frames.h5 ends at frame 0; no file keeps its "
              "final state); run 5 frames to have the run's end written"),
    (7, 3, 7, "frame 7 is simulated but not written (frames.h5 ends at frame 6; the checkpoint of frame 7 "
              "keeps its final state); run 9 frames (or 6) to have the run's end written"),
    (6, 3, 0, None)])
def test_frames_simulated_after_the_last_written_are_named(tmp_path, frames, every, checkpoint_every, expected):
    """time.frames not a multiple of output.every: the run's last frames (its end state)
    are simulated and not written, which main did without a word (every = 5 with 3 frames
    wrote frame 0 alone)."""
    (tmp_path / "w.toml").write_text(f'[scene]\nkind = "wisp4c"\nn_vertices = 12\n[time]\nframes = {frames}\n'
                                     f'[output]\nevery = {every}\ncheckpoint_every = {checkpoint_every}\n'
                                     'previews = false\ncontact_sheet = 0\nusd = false\n')
    assert main([str(tmp_path / "w.toml"), "--out", str(tmp_path / "o"), "--quiet"], comm=MPI.COMM_SELF) == 0
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    with h5py.File(tmp_path / "o" / "frames.h5") as f:
        assert f["positions"].shape[0] == frames // every + 1
    lead = f"time.frames = {frames} (time.frames / --frames) is not a multiple of output.every = {every}: "
    assert s["warnings"] == ([] if expected is None else [lead + expected]), s["warnings"]


def test_log_view_on_the_command_line_prints_petsc_log(tmp_path):
    """``drivers/simulate.py ... -log_view`` prints PETSc's performance summary: PETSc is
    initialised with the command line (an import of PETSc by lc_petsc.batch's modules
    before ``petsc4py.init`` skipped that, and -log_view was dropped and reported as an
    option never used)."""
    cfg = tmp_path / "s.toml"
    cfg.write_text(hairball_toml(n_wisps=2, frames=1, output="previews = false\nxdmf = false"))
    proc = subprocess.run([sys.executable, str(ROOT / "drivers" / "simulate.py"), str(cfg), "--out",
                           str(tmp_path / "out"), "--quiet", "-log_view"], capture_output=True, text=True,
                          timeout=300, env=MPI_ENV, cwd=tmp_path, stdin=subprocess.DEVNULL)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "PETSc Performance Summary" in proc.stdout, proc.stdout[-3000:]
    assert "-log_view was given but never used" not in proc.stdout + proc.stderr
