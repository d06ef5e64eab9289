"""Stability at the extremes (scripts/extremes.py): stated expectations, pass/fail with
figures, a failing case reported as a result."""

import csv
import json

from mpi4py import MPI

from lc_petsc.studies.extremes import catalogue, run_cases

comm = MPI.COMM_WORLD


def test_catalogue_has_the_issue_cases(tmp_path):
    names = [c.name for c in catalogue(quick=True, tmpdir=tmp_path)]
    for n in ("smash60", "compress30_analytic", "compress30_numerical", "compress30_none",
              "compress40_analytic", "compress40_none", "jitter", "straighten", "curl_radius_1mm",
              "dt_1_10", "stiffness_ratio_1e+08", "wisp_1000_vertices"):
        assert n in names, n
    assert (tmp_path / "helix1mm.h5").exists()


def test_extremes_run_and_report(tmp_path):
    cases = {c.name: c for c in catalogue(quick=True, tmpdir=tmp_path)}
    pick = [cases["compress40_none_cg_pbjacobi"], cases["dt_1_10"], cases["compress30_analytic"]]
    rows = run_cases(pick, comm, tmp_path / "out", log=lambda *a: None)
    by = {r["case"]: r for r in rows}
    u = by["compress40_none_cg_pbjacobi"]
    assert u["expect"] == "fails_cleanly"
    assert u["status"] == "unstable" and u["failure"] == "SolverError" and u["passed"] is True
    assert u["outcome"].startswith("failed (SolverError at frame 0")
    d = by["dt_1_10"]
    assert d["passed"] and d["status"] == "ok" and d["frames_run"] == 3
    assert d["max_stretch_strain"] < 0.5 and abs(d["curl_retention"] - 1) < 0.2
    c = by["compress30_analytic"]
    assert c["status"] == "ok" and c["expect"] == "recovers" and c["frames_run"] == 10
    assert c["final_rms_from_rest"] > 0
    out = tmp_path / "out"
    rows_csv = list(csv.DictReader(open(out / "extremes.csv")))
    assert [r["case"] for r in rows_csv] == [p.name for p in pick]
    assert rows_csv[0]["passed"] == "True" and rows_csv[0]["failure"] == "SolverError"
    assert len(json.loads((out / "extremes.json").read_text())) == 3
    md = (out / "extremes.md").read_text()
    assert "| compress40_none_cg_pbjacobi |" in md and "PASS" in md


def test_every_judged_expectation_can_fail_and_info_is_not_a_pass(tmp_path):
    """fails_cleanly fails when the run finishes (an indefinite system solved silently),
    recovers / finite fail on a failed run; an info case is neither PASS nor FAIL (it used
    to count as a pass whatever happened)."""
    import numpy as np
    from lc_petsc.studies.extremes import judge, verdict
    cases = {c.name: c for c in catalogue(quick=True, tmpdir=tmp_path)}
    rest = np.array([[0.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, -2.0, 0.0]])
    geo = (rest, np.array([0, 3]), np.zeros(3, bool))
    traj = {"positions": [rest, rest]}
    ok = {"status": "ok", "failure": "", "failed_frame": None, "message": ""}
    failed = {"status": "unstable", "failure": "SolverError", "failed_frame": 0, "message": "DIVERGED"}
    blown = dict(failed, failure="blow-up")
    clean = cases["compress40_none_cg_pbjacobi"]
    assert judge(clean, failed, traj, geo)["passed"] is True
    assert judge(clean, ok, traj, geo)["passed"] is False
    assert judge(clean, blown, traj, geo)["passed"] is False
    for name in ("dt_1_10", "compress30_analytic"):
        assert judge(cases[name], failed, traj, geo)["passed"] is False, name
    info = cases["compress40_none"]
    assert info.expect == "info"
    for res in (ok, failed):
        row = judge(info, res, traj, geo)
        assert row["passed"] is None and verdict(row) == "INFO"



def test_a_tolerance_resolves_the_path_a_config_file_of_the_case_gets(tmp_path):
    """``at_tolerance`` (``scripts/extremes.py --tolerance``): smash60 runs the path the TOML
    loader resolves for a file of its scene naming only the tolerance and the cap (the
    seven keys of ``solver_path_defaulted``, every [time] and [solver] value the same, the
    code's Krylov tolerance); a case about its filter (compress30_numerical) names it, so,
    as for such a file, nothing is resolved and the filter stays."""
    from lc_petsc.config import config_from_dict
    from lc_petsc.studies.extremes import at_tolerance
    from lc_petsc.studies.tradeoff import configure
    cases = {c.name: c for c in catalogue(quick=True, tmpdir=tmp_path)}
    scene = {"kind": "wisp4c", "perturbation": "smash", "smash_factor": 0.4}
    time = {"newton_increment_tol": 1e-6, "newton_iterations": 30}
    resolved = {}
    for name, solver in (("smash60", {}), ("compress30_numerical", {"filter": "numerical"})):
        file_cfg = config_from_dict({"scene": scene, "physics": {"terms": ["stretch", "bend", "twist"]},
                                     "time": time, "solver": solver})
        case = at_tolerance(cases[name], 1e-6, 30)
        resolved[name] = case.meta["solver_path_defaulted"]
        assert resolved[name] == list(file_cfg.solver_path_defaulted)
        ran = configure(case.config, case.settings, case.frames * case.settings.dt)
        for table in ("time", "solver"):
            for key, value in vars(getattr(file_cfg, table)).items():
                if key not in ("frames", "options"):
                    assert getattr(getattr(ran, table), key) == value, (name, table, key)
        assert "-ksp_rtol" in cases[name].settings.options + configure(
            cases[name].config, cases[name].settings, 1.0).solver.options
        assert "-ksp_rtol" not in ran.solver.options
    assert resolved == {"smash60": ["solver.filter", "solver.exact_fallback", "solver.exact_stay",
                                    "time.newton_update", "solver.wisp_trust", "time.newton_stop",
                                    "time.jolt_first_iterate"],
                        "compress30_numerical": []}


def test_a_tolerance_runs_convergence_figures_are_the_runs_own(tmp_path):
    """smash60 (10 frames) to 1e-6: the row's frames converged, median and worst iterations
    (and its frame) and cut-back frames are those of the same run stepped frame by frame,
    and every frame it reports converged ends within the tolerance of the step solved to
    1e-10 from the same start state (and not on it: a stop, not the reference).  Capped at
    3 iterations without cutback, frame 0 (the release from 60% compression) is reported
    not converged, as the stepped run finds."""
    import statistics
    from dataclasses import replace

    from lc_petsc.studies.extremes import at_tolerance
    from lc_petsc.studies.iteration_targets import REFERENCE, run_path, stop_distances, tolerance_config
    from lc_petsc.studies.tradeoff import configure
    case = at_tolerance({c.name: c for c in catalogue(quick=True, tmpdir=tmp_path)}["smash60"], 1e-6, 30)
    capped = replace(case, name="capped", settings=replace(case.settings, newton_iterations=3, max_substeps=1))
    rows = {r["case"]: r for r in run_cases([case, capped], comm, log=lambda *a: None)}
    for c in (case, capped):
        row = rows[c.name]
        stepped, states = run_path(configure(c.config, c.settings, c.frames * c.settings.dt), comm)
        its = [s["iterations"] for s in stepped]
        assert row["frames_run"] == len(its) == 10
        assert row["frames_converged"] == sum(s["converged"] for s in stepped)
        assert (row["newton_median"], row["newton_worst"], row["newton_worst_frame"]) == \
            (statistics.median(its), max(its), its.index(max(its)))
        assert row["cut_back_frames"] == sum(s["substeps"] > 1 for s in stepped)
        converged = {f for f, s in enumerate(stepped) if s["converged"]}
        if c is case:
            assert converged == set(range(10)) and row["newton_worst"] > 3
            ref = tolerance_config(c.config, REFERENCE, 1e-6, 80, 10, 1)
            dist = stop_distances(ref, comm, states, converged)
            assert all(d["reference_converged"] and 0 < d["distance"] < 1e-6 for d in dist.values()), dist
        else:
            assert 0 not in converged and row["frames_converged"] < 10
