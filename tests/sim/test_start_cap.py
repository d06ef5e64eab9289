"""A start/jolt frame ended by ``time.start_iterations`` with ``time.max_substeps = 1`` is
the cap the user asked for there (a larger fixed count on the converging path), reported
as "capped at N (start/jolt cap), measure X" and counted apart from a frame that missed a
tolerance (docs/newton.md "A capped start/jolt frame", 2026-12-07)."""

import json

from mpi4py import MPI

from lc_petsc.batch import main
from lc_petsc.io.history import history_table, join_history
from lc_petsc.job import outcome_warnings
from sim_helpers import hairball_toml, jolt_hairball_config, run_positions

#: far below what 4 iterations reach on these frames (1e-3 .. 2e-2 wisp lengths)
TOL, CAP = 1e-9, 4


def test_a_capped_start_frame_is_no_missed_tolerance(tmp_path, capsys):
    """Frames 0-1 (start) end at the cap of 4 above the tolerance: ``newton_capped`` true on
    them (``newton_converged`` stays false), the monitor says "capped at 4 (start/jolt
    cap, ...), measure X", the report counts them apart, no missed-tolerance warning, the
    run converged, and ``time.unconverged = "error"`` does not end the run on them."""
    cfg = tmp_path / "s.toml"
    cfg.write_text(hairball_toml(n_wisps=2, frames=3, output="previews = false\nxdmf = false").replace(
        "[time]\n", f"[time]\nstart_increment_tol = {TOL}\nstart_iterations = {CAP}\nmax_substeps = 1\n"
                    "unconverged = \"error\"\n")
        + '[solver]\noptions = "-lc_newton_monitor"\n')
    capsys.readouterr()
    assert main([str(cfg), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    out = capsys.readouterr().out
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert s["newton_iterations"] == [CAP, CAP, 3] and s["newton_start"] == [True, True, False]
    assert s["newton_converged"] == [False, False, None] and s["newton_capped"] == [True, True, False]
    assert min(s["newton_increment"][:2]) > 1e3 * TOL
    assert "newton_capped" in s["per_frame_keys"]
    assert s["converged"] is True and s["error"] is None
    assert not [w for w in s["warnings"] if "missed the tolerance" in w], s["warnings"]
    ends = [line for line in out.splitlines() if line.startswith("  frame ") and "measure" in line]
    assert ends == [f"  frame {k} (dt 0.03333): capped at {CAP} (start/jolt cap, time.start_iterations), "
                    f"measure {s['newton_increment'][k]:.3e}" for k in (0, 1)], ends
    assert (f"  start/jolt frames capped at {CAP} (start/jolt cap, time.start_iterations with "
            f"time.max_substeps = 1): 2 of them, measure up to {max(s['newton_increment'][:2]):.3g}") in out
    assert "  converged: yes" in out and "Newton converged (the start frames' time.start_increment_tol) " \
        "in 0 of 2 frames" in out
    # join_summaries' table says why those frames show False under newton_converged (the
    # column only where a frame was capped: a run without a cap shows none)
    table = history_table(join_history(tmp_path / "out"))
    assert table[2].split() == ["frame", "segment", "ranks", "newton_iterations", "newton_converged",
                                "newton_capped", "newton_increment", "ksp_iterations", "(sum)"], table[2]
    assert [line.split()[3:6] for line in table[3:6]] == [[str(CAP), "False", "True"], [str(CAP), "False", "True"],
                                                          ["3", "None", "False"]], table[3:6]


def test_with_cutback_a_start_frame_above_the_tolerance_missed_it():
    """The same frames with ``time.max_substeps = 2``: cut back, still above the tolerance:
    missed (``newton_capped`` false), warned naming ``time.start_iterations``."""
    cfg = jolt_hairball_config(frames=2, start_increment_tol=TOL, start_iterations=CAP, max_substeps=2)
    s = run_positions(cfg, comm=MPI.COMM_SELF)[1]
    assert s["newton_substeps"] == [2, 2] and s["newton_converged"] == [False, False]
    assert s["newton_capped"] == [False, False]
    [w] = [w for w in outcome_warnings(s, 0, cfg.time) if "missed the tolerance" in w]
    assert w.startswith("Newton missed the tolerance in 2 of 2 frame(s) (0, 1;") and \
        f"Raise time.start_iterations (now {CAP}) or time.max_substeps (now 2)" in w, w
