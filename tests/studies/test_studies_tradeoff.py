"""Speed versus accuracy (drivers/tradeoff.py, lc_petsc/studies/tradeoff.py): errors
against a reference, outputs, and an unstable variant reported instead of crashing."""

import csv
import json
from dataclasses import asdict, replace

import numpy as np
from mpi4py import MPI

from lc_petsc.config import MaterialConfig, PhysicsConfig, SceneConfig, SimConfig
from lc_petsc.studies.measures import compare_trajectories, curl_radius, stretch_strain
from lc_petsc.studies.report import pareto_front
from lc_petsc.solver_plan import KSP_RTOL_CONVERGING, KSP_RTOL_FIXED_COUNT
from lc_petsc.studies.tradeoff import (BASE, configure, default_variants, markdown, not_newtons_error,
                                      recommend, reference_settings, run_study, run_trajectory,
                                      tighter_reference)
from sim_helpers import jolt_hairball_config, small_hairball_config

comm = MPI.COMM_WORLD


def smash(factor=0.6):
    return SimConfig(scene=SceneConfig(kind="wisp4c", perturbation="smash", smash_factor=factor),
                     material=MaterialConfig(youngs_modulus=3.9e9),
                     physics=PhysicsConfig(terms=("stretch", "bend", "twist")))


def test_measures_on_known_geometry():
    from lc_petsc.scene.geometry import wisp4c
    x = wisp4c(101)
    off = np.array([0, 101])
    assert stretch_strain(x, x, off) == 0.0
    assert abs(stretch_strain(1.1 * x, x, off) - 0.1) < 1e-12
    r = curl_radius(x, off)
    # circumradius of 3 helix vertices (72 deg apart, rise 0.1) is a bit above 0.5 cm
    assert 0.5 < r < 0.6
    assert abs(curl_radius(2 * x, off) / r - 2) < 1e-12
    ref = {"times": [0.0, 0.1, 0.2], "positions": [x, x, x], "energies": [1.0, 2.0, 2.0]}
    var = {"times": [0.0, 0.1, 0.2], "positions": [x, x + [0.3, 0.0, 0.4], x], "energies": [1.0, 1.5, 2.0]}
    e = compare_trajectories(var, ref, x, off, np.zeros(101, bool))
    L = np.linalg.norm(np.diff(x, axis=0), axis=1).sum()
    assert abs(e["max_rel_error"] - 0.5 / L) < 1e-12
    # the shared initial state is not counted (it diluted the RMS: sqrt(0.25 / 3) / L)
    assert abs(e["rms_rel_error"] - np.sqrt(0.25 / 2) / L) < 1e-12
    assert abs(e["energy_rel_error"] - 0.25) < 1e-12 and e["n_common_times"] == 2
    assert compare_trajectories(var | {"times": [0.0]}, ref, x, off, np.zeros(101, bool)) == {"n_common_times": 0}
    assert pareto_front([(1, 5), (2, 3), (3, 4), (0.5, 9), (4, 1)]) == [3, 0, 1, 4]


def test_base_runs_the_shipped_krylov_default():
    """The study's base is what a user runs: no -ksp_rtol of its own, so the code default
    for its stopping rule applies (and is what its label and rows report); an explicit
    tolerance (the ksp_rtol axis) is passed on."""
    assert BASE.ksp_rtol is None and BASE.effective_rtol() == float(KSP_RTOL_FIXED_COUNT)
    assert "rtol=1e-04" in BASE.label()
    converging = replace(BASE, newton_increment_tol=1e-6)
    assert converging.effective_rtol() == float(KSP_RTOL_CONVERGING)
    assert "-ksp_rtol" not in configure(smash(), BASE, 0.1).solver.options
    assert "-ksp_rtol 0.01" in configure(smash(), replace(BASE, ksp_rtol=1e-2), 0.1).solver.options


def test_variants_cover_the_axes():
    v = default_variants()
    names = [n for _, n, _ in v]
    assert names[0] == "base" and len(names) == len(set(names))
    for n in ("newton 1", "newton 12", "rtol 1e-02", "rtol 1e-10", "dt 1/120", "filter none",
              "filter numerical", "line search", "inc<1e-06 cap 30 no cutback",
              "inc<1e-06 cap 10 cutback 8", "corotational N=3",
              "exact_or_analytic corotational inc<1e-06", "root turn N=3", "paper setting ftl"):
        assert n in names
    assert sum(s == BASE for _, _, s in v) == 1


def test_a_config_file_runs_as_configured(tmp_path):
    """A study of a scene's config file has a row of that file's own settings: the
    shipped demo's follow-the-leader first iterate and length projection, which the
    study's base replaces with the code's defaults, were in no row (on main the driver's
    rows were the base's axes only).  A file that sets the defaults adds no row."""
    import subprocess
    import sys
    from pathlib import Path
    from lc_petsc.config import load_config
    from lc_petsc.studies.tradeoff import configured_settings
    root = Path(__file__).resolve().parents[2]
    demo = configured_settings(load_config(str(root / "configs" / "hairball_demo.toml")))
    assert (demo.initial_guess, demo.length_projection, demo.newton_iterations) == \
        ("follow_the_leader", True, 3)
    v = default_variants(BASE, ["newton"], configured=demo)
    assert v[1] == ("configured", "as configured", demo)
    assert [n for _, n, _ in default_variants(BASE, ["newton"], configured=BASE)] == \
        [n for _, n, _ in default_variants(BASE, ["newton"])]
    cmd = [sys.executable, str(root / "drivers" / "tradeoff.py"), "--scene",
           str(root / "configs" / "hairball_demo.toml"), "--wisps", "2", "--duration", str(2 / 30),
           "--axes", "newton", "--ref", "base", "--no-ref-check", "--out", str(tmp_path)]
    proc = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    by = {r["variant"]: r for r in json.loads((tmp_path / "tradeoff.json").read_text())["variants"]}
    row = by["as configured"]
    assert row["status"] == "ok" and row["initial_guess"] == "follow_the_leader" and row["length_projection"]
    assert "follow_the_leader" in row["label"] and "projected" in row["label"]
    assert "| as configured | ok |" in (tmp_path / "recommendations.md").read_text()


def test_the_study_sweeps_wisp_trust():
    """``solver.wisp_trust`` is a field of the study's Settings (main had none: the
    driver could not sweep it, and a config file's "as configured" row ran without it):
    its axis against the recommended path without it, its label, the run's config, the
    config file's own row, and the reference's fallback (whose analytic fallback refuses
    it).  Run on the 60% smash for 3 frames to 1e-6: 23 Newton iterations with it, 24
    without (the same figures as the config option's)."""
    from lc_petsc.studies.tradeoff import configured_settings, reference_fallback
    on = replace(BASE, filter="exact_or_analytic", newton_update="corotational", exact_fallback="shifted",
                 exact_stay=True, wisp_trust=True, newton_iterations=30, newton_increment_tol=1e-6)
    off = replace(on, wisp_trust=False)
    assert on.label().endswith("shifted fallback exact_stay wisp_trust") and "wisp_trust" not in off.label()
    variants = default_variants(BASE, ["wisp_trust"])
    assert [n for _, n, _ in variants] == ["base", "wisp trust inc<0.001", "shifted inc<0.001",
                                           "wisp trust inc<1e-06", "shifted inc<1e-06"]
    assert variants[3][2] == on and variants[4][2] == off
    cfg = configure(smash(), on, 0.1).validate()
    assert cfg.solver.wisp_trust and configured_settings(cfg) == on
    assert not configure(smash(), off, 0.1).validate().solver.wisp_trust
    fallback = reference_fallback(on)
    assert not fallback.wisp_trust and configure(smash(), fallback, 0.1).validate().solver.exact_fallback == "analytic"
    runs = {s.wisp_trust: run_trajectory(smash(0.6), s, 3 / 30, 1 / 30, comm)[0] for s in (on, off)}
    assert [(runs[w]["status"], runs[w]["newton_total"], runs[w]["newton_substeps"]) for w in (True, False)] == \
        [("ok", 23, [1, 1, 1]), ("ok", 24, [1, 1, 1])]


def test_the_study_sets_jolt_first_iterate():
    """``time.jolt_first_iterate`` is a field of the study's Settings (main had none:
    scripts/fixed_count_errors.py could not measure it on fixed-count runs): its label,
    the run's config, the config file's own row.  3 wisps shaken with a period of 0.1 s
    (the axis changes at t = 0.1 s, frame 3) at the fixed count: the steps of frames 0
    and 3 start from the jolt's first iterate, the count stays 3 a frame, and frame 0
    ends 0.26 cm (largest vertex) from where it ends without the option."""
    from lc_petsc.simulator import build_simulator
    from lc_petsc.studies.tradeoff import configured_settings
    on = replace(BASE, jolt_first_iterate=True)
    assert on.label().endswith(" jolt first iterate") and "jolt" not in BASE.label()
    shaken = jolt_hairball_config(frames=4)
    shaken.physics.head_period = 0.1
    cfg = configure(shaken, on, 4 / 30).validate()
    assert cfg.time.jolt_first_iterate and configured_settings(cfg) == on
    summaries, firsts = {}, {}
    for s in (on, BASE):
        sim = build_simulator(configure(shaken, s, 4 / 30), comm)
        sim.step()
        firsts[s.jolt_first_iterate] = comm.bcast(sim.gather_positions())
        sim.run(3)
        summaries[s.jolt_first_iterate] = sim.summary()
        sim.close()
    assert summaries[True]["newton_jolt_starts"] == [1, 0, 0, 1] and summaries[False]["newton_jolt_starts"] == [0] * 4
    assert summaries[True]["newton_iterations"] == summaries[False]["newton_iterations"] == [3] * 4
    assert np.abs(firsts[True] - firsts[False]).max() > 0.1      # 0.26 cm


def test_study_outputs_and_unstable_variant(tmp_path):
    # filter none on a 40% compression: the unfiltered Hessian is indefinite, CG with a
    # point-block Jacobi preconditioner detects it (DIVERGED_INDEFINITE_MAT): unstable
    unstable = replace(BASE, filter="none", options="-pc_type pbjacobi -ksp_max_it 5000")
    variants = [("base", "base", BASE),
                ("newton", "newton 1", replace(BASE, newton_iterations=1)),
                ("dt", "dt 1/60", replace(BASE, dt=1 / 60)),
                ("filter", "none+pbjacobi", unstable)]
    rows = run_study(smash(0.6), variants, comm, tmp_path, duration=4 / 30,
                     ref=reference_settings(dt=1 / 60), log=lambda *a: None,
                     meta={"command": "pytest", "scene": "smash 40%"})
    by = {r["variant"]: r for r in rows}
    assert [r["variant"] for r in rows] == ["base", "newton 1", "dt 1/60", "none+pbjacobi"]
    bad = by["none+pbjacobi"]
    assert bad["status"] == "unstable" and not bad["stable"]
    assert bad["failure"] == "SolverError" and bad["failed_frame"] == 0
    assert "DIVERGED_INDEFINITE" in bad["message"]
    for k in ("base", "newton 1", "dt 1/60"):
        r = by[k]
        assert r["stable"] and r["n_common_times"] == 4
        assert 0 < r["rms_rel_error"] <= r["max_rel_error"] < 1
        assert r["wall_per_sim_s"] > 0 and r["wall_per_frame_s"] > 0
        assert 0.5 < r["curl_retention"] < 1.5
    assert by["newton 1"]["rms_rel_error"] > by["base"]["rms_rel_error"]
    assert by["dt 1/60"]["rms_rel_error"] < by["base"]["rms_rel_error"]
    csv_rows = list(csv.DictReader(open(tmp_path / "tradeoff.csv")))
    assert [r["variant"] for r in csv_rows] == [r["variant"] for r in rows]
    for col in ("status", "wall_per_sim_s", "wall_per_frame_s", "rms_rel_error", "max_rel_error",
                "energy_rel_error", "max_stretch_strain", "curl_retention", "failure",
                "failed_frame", "message", "dt", "newton_iterations", "ksp_rtol", "filter", "line_search"):
        assert col in csv_rows[0], col
    assert csv_rows[3]["status"] == "unstable" and csv_rows[3]["rms_rel_error"] == ""
    data = json.loads((tmp_path / "tradeoff.json").read_text())
    assert data["reference"]["filter"] == "exact_or_analytic" and data["reference"]["status"] == "ok"
    rec = {r["target"]: r for r in data["recommendations"]}
    assert rec[0.1]["variant"] in ("base", "newton 1", "dt 1/60")
    assert rec[0.1]["variant"] != "none+pbjacobi"
    md = (tmp_path / "recommendations.md").read_text()
    assert "| target RMS error |" in md and "SolverError at frame 0" in md
    # the reference says whether it solved its own steps (cutback splits a frame)
    ref = data["reference"]
    assert ref["newton_cut_back_frames"] == 0 and ref["newton_unconverged_frames"] == 0
    assert f"(0 of {ref['frames_run']} frames cut back into substeps, 0 not converged)" in md
    assert all(r["newton_cut_back_frames"] == 0 for r in rows if r["stable"])
    png = tmp_path / "pareto.png"
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    # the reference's own error: its distance to the same reference at half its dt
    own = ref["own_error"]
    assert own["status"] == "ok" and "dt=1/120" in own["against"] and own["n_common_times"] == 4
    assert 0 < own["rms_rel_error"] < by["dt 1/60"]["rms_rel_error"]
    floor = own["rms_rel_error"]
    assert [r["below_reference"] for r in data["recommendations"]] == \
        [t <= floor for t in (0.1, 0.03, 0.01, 0.003, 0.001)]
    assert f"Reference's own error (its distance to {own['against']}): RMS" in md


def test_targets_below_the_reference_own_error_are_not_judged():
    """A variant 1e-4 from a reference that is itself 3e-3 from a tighter one (dt/2: the
    10-wisp shaking hairball at dt 1/120 is that far from dt 1/240) does not reach a
    1e-3 target; on main it was recommended for it."""
    rows = [{"variant": "a", "label": "a", "status": "ok", "stable": True, "rms_rel_error": 1e-4,
             "wall_per_sim_s": 2.0},
            {"variant": "b", "label": "b", "status": "ok", "stable": True, "rms_rel_error": 8e-3,
             "wall_per_sim_s": 1.0}]
    recs = recommend(rows, (0.01, 0.003, 0.001), floor=3e-3)
    assert [r["variant"] for r in recs] == ["b", None, None]
    assert [r["below_reference"] for r in recs] == [False, True, True]
    md = markdown(rows, recs, BASE, own={"against": "x", "status": "ok", "rms_rel_error": 3e-3,
                                         "max_rel_error": 1e-2, "energy_rel_error": 0.1})
    assert md.count("below the reference's own error") == 2 and "RMS 0.003" in md
    assert [r["variant"] for r in recommend(rows, (0.01, 0.003, 0.001))] == ["b", "a", "a"]
    assert tighter_reference(reference_settings(dt=1 / 120)).dt == 1 / 240
    assert tighter_reference(replace(BASE, ksp_rtol=1e-10)).ksp_rtol == 1e-12


def test_stretched_variants_are_not_recommended():
    """A variant whose edges stretch beyond the limit (smash unfiltered: RMS 0.23 with edges
    101x long; the uncarried 2-iteration hairball: 6%, energy error 172x) is listed, not
    recommended, whatever its error; the cheaper ones passed over are named.  On main
    the cheapest variant under the target was recommended, stretched or not."""
    rows = [{"variant": "stretched", "label": "s", "status": "ok", "stable": True,
             "rms_rel_error": 0.02, "max_stretch_strain": 0.06, "energy_rel_error": 172.0,
             "wall_per_sim_s": 1.0},
            {"variant": "sound", "label": "t", "status": "ok", "stable": True,
             "rms_rel_error": 0.025, "max_stretch_strain": 7e-5, "energy_rel_error": 0.2,
             "wall_per_sim_s": 1.5},
            {"variant": "torn", "label": "u", "status": "ok", "stable": True,
             "rms_rel_error": 0.005, "max_stretch_strain": 101.0, "energy_rel_error": 2771.0,
             "wall_per_sim_s": 0.5}]
    recs = recommend(rows, (0.03, 0.01), max_strain=0.05)
    assert [r["variant"] for r in recs] == ["sound", None]
    assert recs[0]["stretched"] == ["torn", "stretched"] and recs[1]["stretched"] == ["torn"]
    assert recs[0]["max_stretch_strain"] == 7e-5 and recs[0]["energy_rel_error"] == 0.2
    assert [r["variant"] for r in recommend(rows, (0.03, 0.01), max_strain=None)] == ["torn", "torn"]
    # under the default limit (10%) the 6% variant is recommended, the torn one passed over
    assert [r["variant"] for r in recommend(rows, (0.03,))] == ["stretched"]
    md = markdown(rows, recs, BASE, max_strain=0.05)
    assert "edges within 5% of their length" in md and "| torn, stretched |" in md
    assert md.count("edges stretched beyond the limit: not recommended") == 2


def test_driver_base_reference_on_the_krylov_axis(tmp_path):
    """--ref base (for scenes too large for a converged reference): the reference is the
    base setting with Krylov rtol 1e-10, and --rtols picks the axis's values.  (The
    variants use point-block Jacobi, with which CG's tolerance matters; the default
    per-wisp blocks are exact without contact.)"""
    import subprocess
    import sys
    from pathlib import Path
    root = Path(__file__).resolve().parents[2]
    cmd = [sys.executable, str(root / "drivers" / "tradeoff.py"), "--scene", "hairball",
           "--wisps", "3", "--duration", str(4 / 30), "--axes", "ksp_rtol", "--rtols", "1e-2",
           "1e-4", "--ref", "base", "--set", "pbjacobi", "--out", str(tmp_path)]
    proc = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    data = json.loads((tmp_path / "tradeoff.json").read_text())
    ref = data["reference"]
    assert ref["ksp_rtol"] == 1e-10 and ref["newton_iterations"] == 3 and ref["filter"] == "analytic"
    assert ref["dt"] == BASE.dt and ref["status"] == "ok"
    by = {r["variant"]: r for r in data["variants"]}
    assert list(by) == ["base", "rtol 1e-02", "rtol 1e-04"]
    assert all(r["stable"] and r["n_common_times"] == 4 for r in by.values())
    # looser Krylov solves move the trajectory further from the reference
    assert 0 < by["base"]["rms_rel_error"] < by["rtol 1e-02"]["rms_rel_error"] < 0.1


def test_a_run_reports_its_frames_cut_back():
    """Two shaking-head wisps to 1e-6 with a cap of 8 (tests/sim/test_step_cutback.py: no
    frame converges at the full step, every one does in 2-5 substeps): the record counts
    every frame as cut back; without cutback none."""
    cfg = small_hairball_config(n_wisps=2, frames=4)
    cut = replace(BASE, newton_iterations=8, newton_increment_tol=1e-6, filter="exact_or_analytic")
    res, _, _ = run_trajectory(cfg, cut, 4 / 30, 1 / 30, comm)
    assert res["status"] == "ok" and res["newton_cut_back_frames"] == 4, res
    res, _, _ = run_trajectory(cfg, replace(cut, max_substeps=1), 4 / 30, 1 / 30, comm)
    assert res["newton_cut_back_frames"] == 0 and res["newton_unconverged_frames"] == 4, res


def test_pareto_plot_tells_every_axis_apart_and_covers_no_point(tmp_path, monkeypatch):
    """The full study has 11 axes (base + 10): with 10 markers and 10 colours the 11th
    (carry_with_head) was drawn exactly like the first (base), two identical legend
    entries; and the legend sat inside the axes, over points (Smash: dt 1/120)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import to_hex
    from lc_petsc.studies import report
    figs = []
    monkeypatch.setattr(plt, "close", figs.append)      # keep the figure to look at it
    rows = [{"variant": f"v{k}", "axis": f"axis{k}", "stable": True, "rms_rel_error": 0.01 * (k + 1),
             "wall_per_sim_s": 1.0 + k} for k in range(11)]
    report.plot_pareto(rows, tmp_path / "pareto.png", floor=0.005)
    (fig,) = figs
    ax = fig.axes[0]
    styles = [(line.get_marker(), to_hex(line.get_color())) for line in ax.get_lines()
              if line.get_label().startswith("axis")]
    assert len(styles) == 11 and len(set(styles)) == 11, styles
    fig.canvas.draw()
    legend = ax.get_legend().get_window_extent()
    assert legend.x0 >= ax.get_window_extent().x1       # right of the axes, over nothing


def test_a_setting_on_two_axes_runs_once(tmp_path, monkeypatch):
    """The full study lists 59 variants of 45 distinct settings (newton 2 = edge_retraction
    N=2 = carried N=2, ...): each ran again, and the copies showed different costs for
    one setting (0.75-0.85 CPU s/sim-s on the 10-wisp hairball).  Now a repeated
    setting copies the first run's figures and names it."""
    from lc_petsc.studies import tradeoff
    calls = []
    real = tradeoff.run_trajectory
    monkeypatch.setattr(tradeoff, "run_trajectory", lambda cfg, s, *a: calls.append(s) or real(cfg, s, *a))
    two = replace(BASE, newton_iterations=2)
    variants = [("base", "base", BASE), ("newton", "newton 2", two),
                ("carry_with_head", "carried N=2", replace(two, carry_with_head=True))]
    rows = run_study(smash(0.6), variants, comm, tmp_path, duration=2 / 30,
                     ref=reference_settings(dt=1 / 60), log=lambda *a: None)
    assert len(calls) == 4                      # reference, its check, base, newton 2
    by = {r["variant"]: r for r in rows}
    copy, orig = by["carried N=2"], by["newton 2"]
    assert copy["same_as"] == "newton 2" and copy["axis"] == "carry_with_head"
    assert orig["same_as"] is None and by["base"]["same_as"] is None
    for k in ("rms_rel_error", "cpu_per_sim_s", "newton_total", "status"):
        assert copy[k] == orig[k]
    assert 0 < orig["rms_rel_error"] < 1 and orig["newton_total"] == 2 * 2
    assert "| carried N=2 (= newton 2) | ok |" in (tmp_path / "recommendations.md").read_text()
    assert [r["same_as"] for r in csv.DictReader(open(tmp_path / "tradeoff.csv"))] == ["", "", "newton 2"]


def test_a_variant_the_scene_refuses_is_a_row_not_a_crash(tmp_path):
    """The default axes on a scene with strand contact (configs/hairball_demo.toml
    --wisps 10): the trust region refuses strand contact (ConfigError), and on main the
    study stopped there, after its first 34 variants, with nothing written.  Now the
    variant is a row of status "unsupported" carrying the refusal; the others run."""
    terms = ("stretch", "bend", "twist", "gravity", "head_collision", "strand_collision")
    variants = [("base", "base", BASE), ("trust_region", "trust_region N=3", replace(BASE, newton="trust_region"))]
    rows = run_study(small_hairball_config(n_wisps=2, terms=terms), variants, comm, tmp_path,
                     duration=2 / 30, ref=reference_settings(dt=1 / 60), log=lambda *a: None)
    by = {r["variant"]: r for r in rows}
    assert by["base"]["status"] == "ok" and 0 < by["base"]["rms_rel_error"] < 1
    tr = by["trust_region N=3"]
    assert tr["status"] == "unsupported" and not tr["stable"] and tr["failure"] == "ConfigError"
    assert "does not support strand contact" in tr["message"] and "rms_rel_error" not in tr
    md = (tmp_path / "recommendations.md").read_text()
    assert "| trust_region N=3 | unsupported |" in md and "not run: time.newton" in md
    assert [r["status"] for r in csv.DictReader(open(tmp_path / "tradeoff.csv"))] == ["ok", "unsupported"]


def test_the_table_counts_frames_that_missed_their_tolerance():
    """recommendations.md's variant table says how many frames a variant run to a
    tolerance left unconverged ("-" for a fixed Newton count, which has none to miss);
    on main the count was only in tradeoff.csv."""
    rows = [{"variant": "to 1e-6", "label": "a", "status": "ok", "stable": True, "rms_rel_error": 1e-3,
             "wall_per_sim_s": 2.0, "newton_increment_tol": 1e-6, "newton_unconverged_frames": 2,
             "newton_cut_back_frames": 0},
            {"variant": "fixed 3", "label": "b", "status": "ok", "stable": True, "rms_rel_error": 1e-2,
             "wall_per_sim_s": 1.0, "newton_increment_tol": None, "newton_unconverged_frames": 0,
             "newton_cut_back_frames": 0}]
    md = markdown(rows, recommend(rows, (0.1,)), BASE)
    header = next(line for line in md.splitlines() if line.startswith("| variant | status"))
    col = [c.strip() for c in header.split("|")].index("frames not converged")
    cells = {line.split("|")[1].strip(): line.split("|")[col].strip()
             for line in md.splitlines() if line.startswith(("| to 1e-6", "| fixed 3"))}
    assert cells == {"to 1e-6": "2", "fixed 3": "-"}


def test_a_looser_tolerance_that_saves_little_is_not_recommended():
    """Since a loose stop must agree with its quadratic model (docs/newton.md, twelfth
    round) Newton to 1e-3 takes about the iterations of 1e-6.  On the demo cut to 10
    wisps (drivers/tradeoff.py, 2026-12-07) the corotational update to 1e-3 took 283
    iterations and 1.09 CPU s/sim-s, to 1e-6 290 and 1.19 s, both 7.59e-3 from the
    reference: main recommended "inc<0.001" for 0.01 on the cost's noise.  A looser
    tolerance that saves less than 10% of the tighter one's iterations gives way to it;
    one that saves more (the retraction: 390 against 440 on hairball10) is kept."""
    def row(name, tol, its, cpu, err, update="corotational"):
        s = replace(BASE, filter="exact_or_analytic", newton_update=update, newton_iterations=30,
                    newton_increment_tol=tol)
        return {"variant": name, "label": s.label(), **asdict(s), "ksp_rtol": s.effective_rtol(),
                "status": "ok", "stable": True, "newton_total": its, "cpu_per_sim_s": cpu,
                "rms_rel_error": err, "max_stretch_strain": 2.2e-4}
    rows = [row("corot 1e-3", 1e-3, 283, 1.09, 7.594787991e-3),
            row("corot 1e-6", 1e-6, 290, 1.19, 7.594787694e-3),
            {"variant": "newton 12", "label": "n12", **asdict(replace(BASE, newton_iterations=12)),
             "status": "ok", "stable": True, "newton_total": 360, "cpu_per_sim_s": 1.39,
             "rms_rel_error": 1.02e-2, "max_stretch_strain": 5.7e-4}]
    # tie=0: the cheapest alone (these rows have no work counts: their measured cost), so
    # the rule is seen on its own; the cost model's tie would already take 1e-6 on its
    # lower error (7.594787694e-3 against 7.594787991e-3)
    recs = recommend(rows, (0.03, 0.01), cost="cpu_per_sim_s", tie=0)
    assert [r["variant"] for r in recs] == ["corot 1e-6", "corot 1e-6"]
    assert recs[1]["looser"] == ["corot 1e-3"] and recs[1]["cost"] == 1.19
    # without the rule: main's pick, the cheapest
    assert [r["variant"] for r in recommend(rows, (0.01,), cost="cpu_per_sim_s", min_saving=None, tie=0)] \
        == ["corot 1e-3"]
    md = markdown(rows, recs, BASE, cost="cpu_per_sim_s")
    assert "saves more than 10% of the Newton iterations" in md
    assert "| looser tolerance, passed over (saves too little) |" in md and "| corot 1e-3 |" in md
    # a tighter tolerance that misses the target, or another setting, is no replacement;
    # a saving above 10% keeps the looser one
    retr = [row("retr 1e-3", 1e-3, 390, 0.72, 3.03e-3, "edge_retraction"),
            row("retr 1e-6", 1e-6, 440, 1.14, 3.02e-3, "edge_retraction")]
    assert [(r["variant"], r["looser"]) for r in recommend(retr + rows[:1], (0.01,), cost="cpu_per_sim_s", tie=0)] \
        == [("retr 1e-3", [])]
    assert recommend([rows[0], dict(rows[1], rms_rel_error=0.02)], (0.01,),
                     cost="cpu_per_sim_s", tie=0)[0]["variant"] == "corot 1e-3"


def test_a_converged_variant_split_unlike_the_reference_is_not_called_newtons_error(tmp_path):
    """The demo cut to 10 wisps (basin53, 2026-12-07): the uncarried first iterate to
    1e-6 with a cap of 30 sat 1.7e-3 from the carried reference, though every frame
    converged, because it split frame 0 into 3 substeps where the reference took 2 (its
    dt/2 step needed 39 iterations).  The study now says so per variant.  Here the
    shaking two-wisp hairball to 1e-6 (every frame cut back with a cap of 8, fewer with
    16): the reference at cap 16 splits its 4 frames [3, 2, 1, 1]; cap 8 splits them
    [5, 4, 2, 3], the uncarried iterate at cap 16 as the reference."""
    cfg = small_hairball_config(n_wisps=2, frames=4)
    ref = replace(BASE, newton_iterations=16, newton_increment_tol=1e-6, filter="exact_or_analytic")
    variants = [("newton", "cap 8", replace(ref, newton_iterations=8)),
                ("carry_with_head", "uncarried", replace(ref, carry_with_head=False)),
                ("newton", "newton 3", BASE)]
    rows = run_study(cfg, variants, comm, tmp_path, duration=4 / 30, ref=ref, ref_check=False,
                     log=lambda *a: None)
    if comm.rank != 0:
        return
    by = {r["variant"]: r for r in rows}
    assert by["cap 8"]["newton_substeps"] == [5, 4, 2, 3] and by["cap 8"]["newton_unconverged_frames"] == 0
    assert by["cap 8"]["rms_rel_error"] > 1e-4
    assert by["cap 8"]["not_newtons_error"] == (
        "frames split into other substeps than the reference's (frame 0: 5 against 3, frame 1: 4 "
        "against 2, frame 2: 2 against 1 and 1 more): its error is the time step's there, not Newton's")
    # the same splits: its error is Newton's (within the tolerance); a fixed count has none
    assert by["uncarried"]["newton_substeps"] == [3, 2, 1, 1] and by["uncarried"]["rms_rel_error"] < 1e-6
    assert by["uncarried"]["not_newtons_error"] == "" and by["newton 3"]["not_newtons_error"] == ""
    md = (tmp_path / "recommendations.md").read_text()
    assert "Converged at the reference's time step, yet not Newton's error (table below, last column): cap 8." in md
    line = next(x for x in md.splitlines() if x.startswith("| cap 8 |"))
    assert line.endswith("its error is the time step's there, not Newton's |")
    in_csv = {r["variant"]: r["not_newtons_error"] for r in csv.DictReader(open(tmp_path / "tradeoff.csv"))}
    assert in_csv == {k: r["not_newtons_error"] for k, r in by.items()}


def test_a_converged_variant_far_from_the_reference_with_its_splits_reached_another_solution():
    """Same substeps as the reference and every frame converged, yet farther from it than
    the tolerance: a frame's step reached another of its solutions (the demo's frame 0 at
    the full step has several, docs/newton.md "Two converged runs that disagree").  Not
    said of a variant at another time step, one with unconverged frames, or within its
    tolerance."""
    s = replace(BASE, filter="exact_or_analytic", newton_iterations=30, newton_increment_tol=1e-6)
    row = {"variant": "uncarried", **asdict(s), "status": "ok", "stable": True, "rms_rel_error": 1.7e-3,
           "newton_unconverged_frames": 0, "newton_substeps": [2] + [1] * 29}
    ref = replace(s, newton_iterations=100)
    assert not_newtons_error(row, ref, [2] + [1] * 29) == (
        "converged to 1e-06 with the reference's substeps yet 0.0017 from it: some frame reached "
        "another solution of its step (bistable, the first iterate decides), not Newton's error")
    assert not_newtons_error(dict(row, rms_rel_error=9e-7), ref, [2] + [1] * 29) == ""
    assert not_newtons_error(dict(row, newton_unconverged_frames=1), ref, [2] + [1] * 29) == ""
    assert not_newtons_error(row, replace(ref, dt=1 / 120), [1] * 120) == ""
    assert not_newtons_error(dict(row, newton_substeps=[3] + [1] * 29), ref, [2] + [1] * 29).startswith(
        "frames split into other substeps than the reference's (frame 0: 3 against 2): its error")


# The 10-wisp hairball's study run twice on the same code (drivers/tradeoff.py --scene
# hairball --wisps 10 --duration 1.0 --cost cpu_per_sim_s, 2026-12-07, trade53): Newton
# and Krylov counts, errors and strains equal to the digit, CPU s/sim-s (first, second run)
# as measured.  variant: (filter, Newton method, dt, Newton its, Krylov its, RMS error,
# max strain, CPU first run, CPU second run)
HAIRBALL10_TWICE = {
    "base": ("analytic", "filtered", 1 / 30, 90, 90, 0.01322, 7.32e-05, 0.1627, 0.1102),
    "newton 1": ("analytic", "filtered", 1 / 30, 30, 30, 0.04377, 0.0117, 0.07952, 0.05125),
    "newton 2": ("analytic", "filtered", 1 / 30, 60, 60, 0.01646, 0.00119, 0.1491, 0.0955),
    "newton 6": ("analytic", "filtered", 1 / 30, 180, 180, 0.008914, 7.27e-05, 0.2968, 0.2006),
    "dt 1/60": ("analytic", "filtered", 1 / 60, 180, 180, 0.008696, 4.69e-05, 0.2598, 0.2626),
    "linear N=2": ("analytic", "filtered", 1 / 30, 60, 60, 0.01651, 0.00696, 0.07545, 0.08686),
    "uncarried N=2": ("analytic", "filtered", 1 / 30, 60, 60, 0.02965, 0.0594, 0.0831, 0.07568),
    "trust_region N=2": ("analytic", "trust_region", 1 / 30, 60, 60, 0.01646, 0.00119, 0.1255, 0.1162),
    "trust_region N=3": ("analytic", "trust_region", 1 / 30, 90, 90, 0.009938, 0.000236, 0.246, 0.1947),
    "trust_region N=4": ("analytic", "trust_region", 1 / 30, 120, 120, 0.007909, 0.000132, 0.3413, 0.2819),
    "trust_region inc<1e-06": ("analytic", "trust_region", 1 / 30, 449, 449, 0.003024, 5.61e-05, 1.283, 1.332),
}


def test_two_runs_of_a_study_recommend_the_same():
    """Main picked the cheapest measured CPU time, and the two runs of the hairball10
    study above recommended different settings for 0.03: `linear N=2` (0.0755 against
    0.0831) and `uncarried N=2` (0.0757 against 0.0869), the same 60 Newton iterations,
    the second with a 1.8x larger error and 5.9% edge strain.  Now the modelled cost (counts
    times a price per group of settings, cost_model) ties the 60-iteration rows exactly
    and the lowest error wins (`newton 2`); 0.1 goes to `newton 1` in both."""
    from lc_petsc.studies.cost_model import modelled_costs
    def rows(run):
        out = []
        for name, (filt, method, dt, its, ksp, err, strain, *cpu) in HAIRBALL10_TWICE.items():
            out.append({"variant": name, "label": name, "status": "ok", "stable": True, "filter": filt,
                        "newton": method, "line_search": False, "options": "", "dt": dt,
                        "frames_run": round(1 / dt), "newton_total": its, "ksp_total": ksp,
                        "rms_rel_error": err, "max_stretch_strain": strain, "cpu_per_sim_s": cpu[run]})
        return out
    first, second = ([r["variant"] for r in recommend(rows(k), (0.1, 0.03), cost="cpu_per_sim_s")]
                     for k in (0, 1))
    assert first == second == ["newton 1", "newton 2"]
    # main's rule, the cheapest measured: the two runs disagree
    assert [min((r for r in rows(k) if r["rms_rel_error"] <= 0.03), key=lambda r: r["cpu_per_sim_s"])["variant"]
            for k in (0, 1)] == ["linear N=2", "uncarried N=2"]
    # the model: one price per group (the median CPU s per unit of work: newton 6's
    # 0.2968 / 360 in the first run), the counts decide within it
    m = dict(zip(HAIRBALL10_TWICE, modelled_costs(rows(0), "cpu_per_sim_s")))
    assert m["newton 2"] == m["linear N=2"] == m["uncarried N=2"] == 2 * m["newton 1"]
    assert m["newton 6"] == 0.2968 and abs(m["base"] - 0.2968 / 2) < 1e-15
    # the trust region's group: median of 0.246 / 180 and 0.3413 / 240
    assert abs(m["trust_region N=3"] - 180 * (0.246 / 180 + 0.3413 / 240) / 2) < 1e-15
    rec = recommend(rows(1), (0.03,), cost="cpu_per_sim_s")[0]
    # measured 0.0955; modelled at the second run's median price, linear N=2's 0.08686 / 120
    assert rec["cost"] == 0.0955 and abs(rec["modelled_cost"] - 0.08686) < 1e-15
    assert "within 25% of the lowest go to the lower error" in markdown(rows(1), [rec], BASE, cost="cpu_per_sim_s")


def test_the_reference_solves_every_frame_whole():
    """The study's reference must solve the variants' problem, one backward-Euler step of
    its dt per frame: on main it took the edge retraction with the analytic fallback and
    step cutback, which on the 10-wisp hairball missed 1e-9 cm in frame 0 within 100
    iterations and split it into 2 x dt/2 (docs/newton.md, "Fifteenth round").  Here the
    shaking two-wisp hairball at dt 1/30: main's reference cut frame 0 into 2 substeps (on one machine);
    the recommended path (shifted fallback, exact_stay, corotational) solves every frame
    whole to the tolerance, on every machine."""
    cfg = small_hairball_config(n_wisps=2, frames=4)
    ref = reference_settings(dt=1 / 30)
    res, _, _ = run_trajectory(cfg, ref, 4 / 30, 1 / 30, comm)
    # on main: [2, 1, 1, 1]
    assert res["status"] == "ok" and res["newton_substeps"] == [1, 1, 1, 1], res
    from lc_petsc.studies.tradeoff import reference_warning
    assert res["newton_unconverged_frames"] == 0 and reference_warning(res) == ""
    assert (ref.exact_fallback, ref.exact_stay, ref.newton_update, ref.max_substeps) == \
        ("shifted", True, "corotational", 1)
    built = configure(cfg, ref, 4 / 30)
    assert (built.solver.exact_fallback, built.solver.exact_stay, built.time.max_substeps) == ("shifted", True, 1)
    # main's reference (analytic fallback, edge retraction, cutback) cut frame 0 into 2
    # substeps on one machine and solved it whole on another (an AMD EPYC without
    # AVX-512): a round-off decision, so not pinned


def test_a_reference_cut_back_or_unconverged_is_reported_loudly(tmp_path):
    """A reference whose frames were cut into substeps (another discretisation) or missed
    its tolerance was compared against silently (only a count in one sentence of the
    report); now the log, tradeoff.json and recommendations.md carry a warning naming
    the frames.  The two-wisp hairball to 1e-6 with a cap of 8 cuts every frame (as in
    test_a_run_reports_its_frames_cut_back)."""
    cfg = small_hairball_config(n_wisps=2, frames=2)
    ref = replace(BASE, newton_iterations=8, newton_increment_tol=1e-6, filter="exact_or_analytic")
    logged = []
    run_study(cfg, [("newton", "newton 2", replace(BASE, newton_iterations=2))], comm, tmp_path,
              duration=2 / 30, ref=ref, ref_check=False, log=logged.append)
    if comm.rank != 0:
        return
    want = ("the reference is not the converged solution of every step: 2 frame(s) cut into "
            "substeps (frames 0, 1): another discretisation than the variants'. Errors against it "
            "include its own deviation there; raise --ref-tol or use a smaller --ref-dt")
    assert f"WARNING: {want}" in logged
    assert json.loads((tmp_path / "tradeoff.json").read_text())["reference"]["warning"] == want
    assert f"**WARNING: {want}.**" in (tmp_path / "recommendations.md").read_text()
    from lc_petsc.studies.tradeoff import reference_warning
    assert reference_warning({"newton_substeps": [1, 1, 1], "newton_unconverged_frames": 2}) == (
        "the reference is not the converged solution of every step: 2 frame(s) not converged to "
        "its tolerance. Errors against it include its own deviation there; raise --ref-tol or use "
        "a smaller --ref-dt")


def test_a_scene_file_with_the_extension_gets_a_converged_reference():
    """A scene file that sets time.newton_extend_above: the study reads it as configured
    and the reference (a tolerance) runs without it; the extension's settings would
    otherwise stay in the copied config and be refused with the reference's tolerance
    (ConfigError).  The newton_extend axis has the three bounds with and without the turn."""
    from lc_petsc.studies.tradeoff import configured_settings
    cfg = small_hairball_config(n_wisps=2, newton_extend_above=3e-3, newton_extend_cap=8)
    mine = configured_settings(cfg)
    assert (mine.newton_extend_above, mine.newton_extend_cap) == (3e-3, 8)
    assert "extend>0.003 cap 8" in mine.label()
    ref = configure(cfg, reference_settings(dt=1 / 30), 0.1)
    ref.validate()
    assert ref.time.newton_extend_above is None and ref.time.newton_tol == 1e-9
    again = configure(small_hairball_config(n_wisps=2), mine, 0.1)
    assert (again.time.newton_extend_above, again.time.newton_extend_cap) == (3e-3, 8)
    rows = {n: s for a, n, s in default_variants(BASE, ["newton_extend"]) if a == "newton_extend"}
    assert {(s.root_rotation, s.newton_extend_above) for s in rows.values()} == \
        {(t, b) for t in (False, True) for b in (3e-2, 1e-2, 3e-3)} | {(True, None)}


def test_a_scene_file_with_start_and_jolt_frames_runs_them_as_configured():
    """The "as configured" row of a file that sets time.start_increment_tol and
    time.jolt_above (Settings fields since they were added) keeps them: on main a83e279
    configured_settings did not read them and the row ran the plain count."""
    from lc_petsc.studies.tradeoff import configured_settings
    cfg = small_hairball_config(n_wisps=2, start_increment_tol=1e-3, start_frames=3, start_iterations=20,
                                jolt_above=50.0, jolt_frames=2)
    mine = configured_settings(cfg)
    assert (mine.start_increment_tol, mine.start_frames, mine.start_iterations, mine.jolt_above,
            mine.jolt_frames) == (1e-3, 3, 20, 50.0, 2)
    assert "start 3 to 0.001 cap 20" in mine.label() and "jolts>50 x2" in mine.label()
    t = configure(small_hairball_config(n_wisps=2), mine, 0.1).validate().time
    assert (t.start_increment_tol, t.start_frames, t.start_iterations, t.jolt_above, t.jolt_frames) == \
        (1e-3, 3, 20, 50.0, 2)


def test_the_configured_row_of_a_tolerance_file_runs_the_stop_the_file_runs():
    """A file with a tolerance and no solver.filter runs ``time.newton_stop =
    "chord_estimate"`` (its tolerance's default, lc_petsc.config.tolerance_defaults); its
    study's "as configured" row ran ``"increment"`` (on main: ``configure`` drops the
    file's defaults and Settings held no stop), so that row was not what
    drivers/simulate.py runs of the file.  The other rows keep the file's named stop or
    the dataclass default; a file that names its stop or sets none adds nothing."""
    from lc_petsc.config import config_from_dict
    from lc_petsc.studies.tradeoff import configured_settings
    data = {"scene": {"kind": "hairball", "n_wisps": 2}, "physics": {"head_motion": "shake"},
            "time": {"newton_increment_tol": 1e-4, "newton_iterations": 30}}
    cfg = config_from_dict(data)
    keys = [("time", "newton_stop"), ("time", "newton_update"), ("time", "jolt_first_iterate"),
            ("solver", "filter"), ("solver", "exact_fallback"), ("solver", "exact_stay"), ("solver", "wisp_trust")]
    mine = configured_settings(cfg)
    run = configure(cfg, mine, 0.1).validate()
    assert [getattr(getattr(run, t), k) for t, k in keys] == [getattr(getattr(cfg, t), k) for t, k in keys]
    assert run.time.newton_stop == "chord_estimate" and "stop chord_estimate" in mine.label()
    # the other rows: the study's own path with the dataclass stop, as before
    assert configure(cfg, BASE, 0.1).validate().time.newton_stop == "increment"
    assert configure(cfg, replace(BASE, filter="exact_or_analytic", newton_increment_tol=1e-4),
                     0.1).validate().time.newton_stop == "increment"
    named = config_from_dict({**data, "time": {**data["time"], "newton_stop": "quadratic_estimate"}})
    assert configured_settings(named).newton_stop is None
    assert configure(named, configured_settings(named), 0.1).validate().time.newton_stop == "quadratic_estimate"
    assert configured_settings(config_from_dict({**data, "time": {}})) == BASE
