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
