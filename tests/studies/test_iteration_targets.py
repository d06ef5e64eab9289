"""scripts/iteration_targets.py: issue 14's table on whole runs, and the check of every
sampled stop against the step solved to 1e-10 from the same start state."""

import json

from mpi4py import MPI

from test_scripts_small_inputs import _script

from lc_petsc.studies.iteration_targets import RECOMMENDED, run_path, stop_distances, summarize, tolerance_config


def test_smash_table_and_every_stop_within_the_tolerance(tmp_path, capsys):
    """Smash's first three frames to 1e-6 on the recommended path: the printed table's
    figures are the rows', every frame converged at full dt, and every stop is within the
    tolerance of the same step solved to 1e-10 (the stop's distance is not zero: it is a
    stop, not the reference's own iterate)."""
    out = tmp_path / "t.json"
    assert _script("iteration_targets").main(
        ["--scenes", "smash", "--frames", "3", "--path", f"rec={RECOMMENDED}", "--check-every", "1",
         "--out", str(out)]) == 0
    res = json.loads(out.read_text())["scenes"]["smash"]["rec"]
    its = [r["iterations"] for r in res["rows"]]
    assert all(r["converged"] and r["substeps"] == 1 for r in res["rows"])
    assert res["summary"]["total"] == sum(its) and res["summary"]["worst"] == max(its) >= 3
    assert sorted(res["distances"]) == ["0", "1", "2"]
    assert all(0 < d["distance"] < 1e-6 and d["reference_converged"] for d in res["distances"].values())
    printed = capsys.readouterr().out
    assert f"iterations {' '.join(map(str, its))}" in printed and "stops checked 3" in printed


def test_a_stop_far_from_the_solution_is_measured_so():
    """The distance is that of the run's own end: frame 0 of the smashed coil (its jolt)
    capped at 3 iterations without cutback ends unconverged, measured far above the
    tolerance from the step's solution; the summary counts a cut-back frame and the
    first 30 frames' median."""
    base = _script("newton_history").scene("smash")
    capped = tolerance_config(base, RECOMMENDED, 1e-6, 3, 1, 1)
    rows, states = run_path(capped, MPI.COMM_WORLD)
    assert rows[0]["iterations"] == 3 and not rows[0]["converged"]
    ref = tolerance_config(base, RECOMMENDED, 1e-6, 80, 1, 1)
    dist = stop_distances(ref, MPI.COMM_WORLD, states, {0})
    assert dist[0]["reference_converged"] and dist[0]["distance"] > 1e-4
    s = summarize([dict(rows[0], substeps=2)] + [dict(rows[0], iterations=1)] * 31)
    assert (s["cut_back"], s["median_first30"], s["frames"]) == (1, 1, 32)


def test_the_empty_path_of_a_tolerance_file_runs_the_path_the_file_runs():
    """``--path NAME=`` (an empty SPEC) keeps the config's own solver settings: for a file
    with a tolerance and no solver.filter those its tolerance resolved
    (``solver_path_defaulted``), as drivers/simulate.py runs it.  On main the study's
    ``configure`` dropped them (without_tolerance_defaults) and the empty path ran the
    analytic filter: a 6-wisp shaking hairball took 450 iterations a frame (cut back, never
    converged) where the file runs 15-29.  A named path and a fixed-count file are as before."""
    from lc_petsc.config import SimConfig, config_from_dict
    data = {"scene": {"kind": "hairball", "n_wisps": 2}, "physics": {"head_motion": "shake"},
            "time": {"newton_increment_tol": 1e-4, "newton_iterations": 30}}
    base = config_from_dict(data)
    own = tolerance_config(base, "", 1e-6, 30, 2, 8)
    keys = [k.split(".") for k in base.solver_path_defaulted]
    assert len(keys) == 7
    assert [getattr(getattr(own, t), k) for t, k in keys] == [getattr(getattr(base, t), k) for t, k in keys]
    assert (own.time.newton_increment_tol, own.time.frames, own.time.newton_iterations) == (1e-6, 2, 30)
    # a named path is the study's, the stop its key's
    named = tolerance_config(base, RECOMMENDED, 1e-6, 30, 2, 8)
    assert (named.solver.wisp_trust, named.time.newton_stop, named.time.jolt_first_iterate) == \
        (False, "increment", False)
    # a file without a tolerance resolves nothing: its own (the paper's) path, as before
    plain = tolerance_config(config_from_dict({**data, "time": {}}), "", 1e-6, 30, 2, 8)
    assert (plain.solver.filter, plain.solver.exact_fallback) == (SimConfig().solver.filter, "analytic")
    rows, _ = run_path(own, MPI.COMM_WORLD)
    assert all(r["converged"] for r in rows) and max(r["iterations"] for r in rows) <= 30, rows
