"""Solver comparison (drivers/compare_solvers.py, lc_petsc/studies): recorded systems,
replay per option set, budget stop, output files."""

import csv
import json
from pathlib import Path

import pytest
import numpy as np
from mpi4py import MPI

from lc_petsc.config import MaterialConfig, PhysicsConfig, SceneConfig, SimConfig, TimeConfig
from lc_petsc.studies.compare import record, run_comparison
from lc_petsc.studies.systems import destroy_systems, option_sets, replay

ROOT = Path(__file__).resolve().parents[2]
comm = MPI.COMM_WORLD


def hairball(n):
    return SimConfig(scene=SceneConfig(kind="hairball", n_wisps=n, seed=7),
                     material=MaterialConfig(youngs_modulus=1.0e9),
                     physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity", "head_collision"),
                                           head_motion="shake", head_amplitude=0.3, head_period=0.5),
                     time=TimeConfig(frames=1))


def test_shipped_option_sets_parse_and_include_the_issue_sets():
    sets = option_sets(ROOT / "configs" / "solvers")
    assert list(sets)[0] == "default"
    for name in ("default", "bjacobi_rank", "pbjacobi", "cg_none", "mumps_cholesky",
                 "hypre_boomeramg", "gamg"):
        assert name in sets and sets[name].startswith("-"), name
    assert "#" not in sets["hypre_boomeramg"]
    with pytest.raises(ValueError, match="no option set"):
        option_sets(ROOT / "configs" / "solvers", ["default", "nonexistent"])


@pytest.mark.mpi
def test_replay_same_systems_every_set_agrees_and_budget_stops():
    systems, wisp_rows, info = record(hairball(3), comm)
    assert len(systems) == 3 and info["dofs"] == 3 * 303
    sets = option_sets(ROOT / "configs" / "solvers", ["default", "bjacobi_rank", "mumps_cholesky"])
    from lc_petsc.studies.systems import direct_solutions
    refs = direct_solutions(systems, comm)
    for name, opts in sets.items():
        rows = replay(systems, wisp_rows, name, opts, comm, budget_s=30, references=refs)
        assert [r["status"] for r in rows] == ["ok"] * 3, rows
        for r in rows:
            assert r["true_rel_residual"] < 1e-8 and r["rel_error_vs_direct"] < 1e-8, (name, r)
            assert r["setup_s"] >= 0 and r["solve_s"] > 0
        if name != "mumps_cholesky":   # exact per-wisp (or per-rank) blocks: one CG iteration
            assert all(r["iterations"] == 1 for r in rows)
    # a set over budget is stopped inside its Krylov loop and reported, not dropped
    slow = replay(systems, wisp_rows, "slow", "-pc_type none -ksp_rtol 1e-14 -ksp_max_it 1000000",
                  comm, budget_s=0.0)
    assert [r["status"] for r in slow] == ["budget"] * 3
    assert "budget" in slow[0]["message"] and slow[0]["iterations"] == 10
    destroy_systems(systems)


def test_comparison_outputs(tmp_path):
    sets = option_sets(ROOT / "configs" / "solvers", ["default", "mumps_cholesky", "pbjacobi"])
    summary = run_comparison(hairball, [2, 3], sets, comm, tmp_path, budget_s=30, log=lambda *a: None,
                             meta={"command": "pytest"})
    assert {(s["wisps"], s["set"]) for s in summary} == {(n, k) for n in (2, 3) for k in sets}
    rows = list(csv.DictReader(open(tmp_path / "rows.csv")))
    assert len(rows) == 2 * 3 * 3
    for col in ("wisps", "set", "system", "status", "setup_s", "solve_s", "iterations", "reason",
                "true_rel_residual", "rel_error_vs_direct", "rss_delta_mib", "peak_rss_mib",
                "set_peak_mib", "memory_window"):
        assert col in rows[0], col
    for r in rows:
        assert r["status"] == "ok" and r["reason"].startswith("CONVERGED")
        assert float(r["rel_error_vs_direct"]) < (1e-3 if r["set"] == "pbjacobi" else 1e-8)
    d = [r for r in rows if r["set"] == "default"]
    assert all(int(r["iterations"]) == 1 for r in d)
    p = [r for r in rows if r["set"] == "pbjacobi"]
    assert all(int(r["iterations"]) > 10 for r in p)
    summ = list(csv.DictReader(open(tmp_path / "summary.csv")))
    ratios = {(int(s["wisps"]), s["set"]): float(s["ratio_vs_default"]) for s in summ}
    assert ratios[(3, "default")] == 1.0 and ratios[(3, "pbjacobi")] > 1.0
    data = json.loads((tmp_path / "results.json").read_text())
    assert len(data["rows"]) == 18 and data["scenes"][1]["dofs"] == 3 * 303
    assert data["meta"]["budget_s"] == 30
    md = (tmp_path / "table.md").read_text()
    assert "| solver set | 2 wisps: time (s), x default, its | 3 wisps:" in md
    assert "| default | " in md and "| mumps_cholesky | " in md and "1x, 1 |" in md
    png = tmp_path / "time_vs_wisps.png"
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"


def test_budget_stops_are_reported_and_can_skip_larger_sizes(tmp_path):
    sets = {"slow": "-pc_type none -ksp_rtol 1e-14 -ksp_max_it 1000000"}
    summary = run_comparison(hairball, [2, 3], sets, comm, tmp_path, budget_s=0.0, reference=False,
                             log=lambda *a: None, skip_after_budget=True)
    assert [s["status"] for s in summary] == ["budget", "budget"]
    rows = list(csv.DictReader(open(tmp_path / "rows.csv")))
    assert rows[0]["message"].startswith("time budget 0 s used up at Krylov iteration 10")
    assert all(r["message"] == "skipped: over the budget at 2 wisps" for r in rows if r["wisps"] == "3")
    md = (tmp_path / "table.md").read_text()
    assert "> 0 (budget)" in md


def test_coupled_systems_record_the_assembled_contact_operator():
    """With strand contact the simulator's operator is the shell A + C; the recorder
    stores the assembled sum (here C is a stand-in coupling two wisps' root-free
    vertices), replays it with new operators per system, and the per-wisp block Jacobi
    is no longer exact (more than one CG iteration) while MUMPS still is.  The per-wisp
    blocks are built from the strand matrix without C, as in the simulator: fused and
    separate (both from the AIJ copy, as the simulator does with strand contact) give
    the same iterations and solutions."""
    from types import SimpleNamespace
    from petsc4py import PETSc
    from lc_petsc.simulator import build_simulator
    from lc_petsc.studies.systems import SystemRecorder, direct_solutions
    cfg = hairball(2)
    cfg.physics.terms = ("stretch", "bend", "twist", "gravity")
    # the systems measured: carried (time.carry_with_head), the first one's CG ends within
    # round-off of the tolerance, and the two equal preconditioners take 7 and 8 iterations
    cfg.time.carry_with_head = False
    sim = build_simulator(cfg, MPI.COMM_SELF)
    n = 3 * sim.n_vertices
    C = PETSc.Mat().createBAIJ(size=(n, n), bsize=3, nnz=2, comm=PETSc.COMM_SELF)
    k = -2.0e6
    for a, b in ((50, 101 + 50), (80, 101 + 80)):        # springs between wisps 0 and 1
        for i, j, v in ((a, b, k), (b, a, k), (a, a, -k), (b, b, -k)):
            C.setValuesBlocked([i], [j], (v * np.eye(3)).ravel(), addv=PETSc.InsertMode.ADD_VALUES)
    C.assemble()
    sim.strand = SimpleNamespace(C=C)
    rec = SystemRecorder(sim)
    sim.run(1)
    rec.detach()
    sim.strand = None
    sim.close()
    systems = rec.systems
    assert all(s.coupled for s in systems)
    assert systems[0].A.getValue(3 * 50, 3 * 151) == k
    refs = direct_solutions(systems, MPI.COMM_SELF)
    # the per-wisp blocks (the default with contact grows them into clusters)
    sets = option_sets(ROOT / "configs" / "solvers", ["strand_blocks", "mumps_cholesky"])
    d = replay(systems, rec.wisp_rows, "strand_blocks", sets["strand_blocks"], MPI.COMM_SELF,
               references=refs)
    m = replay(systems, rec.wisp_rows, "mumps", sets["mumps_cholesky"], MPI.COMM_SELF, references=refs)
    sep = replay(systems, rec.wisp_rows, "separate", "-lc_wisp_blocks separate -lc_pmat_type aij",
                 MPI.COMM_SELF, references=refs)
    assert all(s.wisp_local is not None and s.wisp_local.getValue(3 * 50, 3 * 151) == 0.0
               for s in systems)
    assert [r["iterations"] for r in sep] == [r["iterations"] for r in d]
    assert [r["rel_error_vs_direct"] for r in sep] == pytest.approx(
        [r["rel_error_vs_direct"] for r in d], rel=1e-9, abs=1e-14)
    assert all(r["status"] == "ok" for r in d + m), [(r["set"], r["status"], r.get("message")) for r in d + m]
    assert max(r["iterations"] for r in d) > 1
    assert all(r["rel_error_vs_direct"] < 1e-4 for r in d)
    assert all(r["rel_error_vs_direct"] < 1e-9 for r in m)
    C.destroy()
    rec.destroy()


def test_memory_window_reports_a_sets_own_peak_after_an_earlier_set_freed_memory():
    """The memory columns are per set: memory an earlier set freed is given back to the
    OS before the next one and the peak RSS is reset, so a later set's 100 MB show up
    (with ru_maxrss and plain RSS growth they would be hidden by the earlier 200 MB)."""
    import numpy as np
    from lc_petsc.studies.systems import current_rss_mib, start_memory_window, window_peak_rss_mib
    assert start_memory_window()
    first = np.ones(200 * 2 ** 20 // 8)     # an earlier set: 200 MiB, touched, freed
    del first
    assert start_memory_window()
    rss0 = current_rss_mib()
    assert window_peak_rss_mib() < rss0 + 10
    later = np.ones(100 * 2 ** 20 // 8)
    assert 95 < window_peak_rss_mib() - rss0 < 115
    del later


def test_repeats_give_median_times_and_a_stopped_set_runs_once(tmp_path):
    sets = {"default": option_sets(ROOT / "configs" / "solvers", ["default"])["default"],
            # never converges, never breaks down: stopped by the budget
            "slow": "-ksp_type richardson -ksp_richardson_scale 1e-12 -pc_type none "
                    "-ksp_max_it 100000000"}
    summary = run_comparison(hairball, [2], sets, comm, tmp_path, budget_s=0.5, reference=False,
                             log=lambda *a: None, repeats=3)
    d, slow = summary
    assert d["status"] == "ok" and d["repeats"] == 3 and len(d["total_s_repeats"]) == 3
    assert d["total_s"] == pytest.approx(sorted(d["total_s_repeats"])[1])
    assert slow["status"] == "budget"
    rows = list(csv.DictReader(open(tmp_path / "rows.csv")))
    assert sorted({r["repeat"] for r in rows if r["set"] == "default"}) == ["0", "1", "2"]
    assert {r["repeat"] for r in rows if r["set"] == "slow"} == {"0"}
    assert "median of 3 replays" in (tmp_path / "table.md").read_text()


def test_replay_with_strand_contact_mirrors_the_simulator_and_covers_clusters(monkeypatch):
    import lc_petsc.simulator as simmod
    from sim_helpers import touching_wisps_config, touching_wisps_source
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: touching_wisps_source())
    systems, wisp_rows, info = record(touching_wisps_config(1, options=""), comm, frames=1,
                                      skip_frames=1)
    try:
        assert [s.frame for s in systems] == [1, 1, 1] and all(s.coupled for s in systems)
        assert all(s.C is not None for s in systems)
        sets = option_sets(ROOT / "configs" / "solvers", ["default", "strand_blocks", "contact_clusters"])
        its = {}
        for name, opts in sets.items():
            rows = replay(systems, wisp_rows, name, opts, comm, budget_s=60)
            assert [r["status"] for r in rows] == ["ok"] * 3, rows
            assert all(r["true_rel_residual"] < 1e-5 for r in rows), rows
            its[name] = [r["iterations"] for r in rows]
            # the rows say what the contact preconditioner made of each system
            if name == "strand_blocks":
                assert all("cluster_rows" not in r for r in rows)
            else:
                assert all(r["cluster_couplings"] > 0 and not r["cluster_fallback"]
                           and r["cluster_captured"] >= 0.9 and r["cluster_rows"] > 0 for r in rows), rows
        # the simulator's own CG iterations are the default's replayed (same operators;
        # round-off in the copies moves a count by 2 of 46); the default with contact is
        # the cluster preconditioner, the per-wisp strand blocks need many more
        assert its["default"] == its["contact_clusters"]
        assert np.abs(np.subtract(its["default"], info["sim_ksp_iterations"][3:])).max() <= 3, \
            (its, info["sim_ksp_iterations"])
        assert min(its["strand_blocks"]) > 10 and max(its["default"]) <= (1 if comm.size == 1 else 30), its
    finally:
        destroy_systems(systems)


@pytest.mark.mpi
def test_record_from_a_checkpoint_equals_recording_after_the_frames_before_it(tmp_path, monkeypatch):
    """``record(restart=...)`` (compare_solvers.py --restart) continues from a checkpoint
    of the main job: the systems of frame 2 recorded from frame 2's checkpoint are those
    recorded after running frames 0-1 (bit for bit), so a late frame of a large scene is
    recorded without running the frames before it again; a checkpoint written with
    another config is refused naming the key."""
    import copy
    import lc_petsc.simulator as simmod
    from lc_petsc.errors import CheckpointError
    from lc_petsc.io.checkpoint import checkpoint_path, write_checkpoint
    from lc_petsc.simulator import build_simulator
    from sim_helpers import touching_wisps_config, touching_wisps_source
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: touching_wisps_source())
    cfg = touching_wisps_config(3, options="")
    out = Path(comm.bcast(str(tmp_path) if comm.rank == 0 else None))    # one folder for every rank
    sim = build_simulator(cfg, comm)
    try:
        sim.run(2)
        it = sim.integrator
        write_checkpoint(out, comm, frame=it.frame, t=it.t, x=sim.user.to_user(it.x),
                         v=sim.user.to_user(it.v), scene=sim.user, n_wisps=sim.n_wisps,
                         n_vertices=sim.n_vertices, head=sim.head, dt=cfg.time.dt, every=cfg.output.every,
                         config_dict=cfg.to_dict(), config_toml="", petsc_options={}, keep=1,
                         version="test")
    finally:
        sim.close()
    ck = checkpoint_path(out, 2)
    ran, _, ran_info = record(cfg, comm, frames=1, skip_frames=2)
    restarted, _, info = record(cfg, comm, frames=1, restart=ck)
    try:
        assert info["start_frame"] == 2 and ran_info["start_frame"] == 0
        assert [s.frame for s in restarted] == [s.frame for s in ran] == [2, 2, 2]
        assert all(s.coupled for s in restarted)
        for a, b in zip(ran, restarted):
            d = a.A.copy()
            d.axpy(-1.0, b.A, structure=d.Structure.DIFFERENT_NONZERO_PATTERN)
            e = a.b.copy()
            e.axpy(-1.0, b.b)
            assert (d.norm(), e.norm()) == (0.0, 0.0) and a.A.norm() > 0 and a.b.norm() > 0
            d.destroy()
            e.destroy()
        assert info["sim_ksp_iterations"] == ran_info["sim_ksp_iterations"][-3:]
        assert min(info["strand_contact_pairs"]) > 0
    finally:
        destroy_systems(ran)
        destroy_systems(restarted)
    other = copy.deepcopy(cfg)
    other.time.dt = cfg.time.dt / 2
    with pytest.raises(CheckpointError, match=r"differs from the study's in time\.dt \(checkpoint: "):
        record(other, comm, frames=1, restart=ck)


@pytest.mark.mpi
def test_a_solve_without_convergence_test_is_judged_by_its_true_residual():
    """preonly + point-block Jacobi reports CONVERGED_ITS after one application of an
    inexact preconditioner: on main it was 'ok' and ranked 4x faster than the default in
    Table 3 with a true residual of 1.0.  Its true residual decides (as in the simulator);
    MUMPS Cholesky, also preonly, solves the system and stays ok."""
    from lc_petsc.studies.compare import summarise, table3
    systems, wisp_rows, _ = record(hairball(3), comm)   # a wisp per rank on 3 ranks
    sets = option_sets(ROOT / "configs" / "solvers", ["default", "mumps_cholesky"])
    sets["preonly_pbjacobi"] = "-ksp_type preonly -pc_type pbjacobi"
    rows = []
    for name, opts in sets.items():
        rs = replay(systems, wisp_rows, name, opts, comm, budget_s=30)
        for r in rs:
            r.update(wisps=3, dofs=3 * 303, ranks=comm.size)
        rows += rs
    destroy_systems(systems)
    bad = [r for r in rows if r["set"] == "preonly_pbjacobi"]
    assert [r["status"] for r in bad] == ["inaccurate"] * 3
    assert all(r["reason"] == "CONVERGED_ITS" and r["true_rel_residual"] > 1e-2 for r in bad)
    assert "true relative residual" in bad[0]["message"] and "> rtol 0.0001" in bad[0]["message"]
    mumps = [r for r in rows if r["set"] == "mumps_cholesky"]
    assert [r["status"] for r in mumps] == ["ok"] * 3
    assert all(r["reason"] == "CONVERGED_ITS" and r["true_rel_residual"] < 1e-10 for r in mumps)
    summary = {s["set"]: s for s in summarise(rows, 30)}
    assert summary["preonly_pbjacobi"]["status"] == "inaccurate"
    assert "ratio_vs_default" not in summary["preonly_pbjacobi"]
    assert summary["mumps_cholesky"]["status"] == "ok" and summary["mumps_cholesky"]["ratio_vs_default"] > 0
    line = next(x for x in table3(list(summary.values())).splitlines() if "preonly_pbjacobi" in x)
    assert "inaccurate: CONVERGED_ITS" in line and "x," not in line


def test_a_failed_direct_reference_is_an_error_not_a_reference():
    """A singular recorded system (a zero pivot): MUMPS's LU fails or leaves a residual of
    order one; the study says so instead of measuring every set's error against it."""
    from petsc4py import PETSc
    from lc_petsc.studies.systems import RecordedSystem, direct_solutions
    n = 6
    A = PETSc.Mat().createAIJ([n, n], nnz=1, comm=MPI.COMM_SELF)
    for i in range(n):                      # the last pivot 0: singular
        A.setValue(i, i, 2.0 if i < n - 1 else 0.0)
    A.assemble()
    b = PETSc.Vec().createSeq(n)
    b.set(1.0)
    good = RecordedSystem(A=A, b=b, coords=np.zeros((2, 3)), frame=0, newton_it=0)
    with pytest.raises(RuntimeError, match="direct reference solve .* of recorded system 0 failed"):
        direct_solutions([good], MPI.COMM_SELF)
    A.setValue(n - 1, n - 1, 4.0)
    A.assemble()
    refs = direct_solutions([good], MPI.COMM_SELF)
    assert np.allclose(refs[0].getArray(), [0.5] * (n - 1) + [0.25])
    for v in (A, b, *refs):
        v.destroy()


def test_summary_repeats_keep_setup_plus_solve_and_a_later_budget_stop():
    """The times are those of the median repeat (setup + solve = total: separate medians
    of 1+9, 5+2, 3+3 gave 3 + 3 against a total of 7); a set over the budget in a later repeat is
    reported as such, not ok on its fast repeats."""
    from lc_petsc.studies.compare import summarise

    def row(name, rep, setup, solve, status="ok"):
        return dict(wisps=2, dofs=6, ranks=1, set=name, repeat=rep, status=status, iterations=3,
                    setup_s=setup, solve_s=solve, total_s=setup + solve, true_rel_residual=1e-6,
                    rel_error_vs_direct=1e-6, rss_delta_mib=1.0, set_peak_mib=1.0)
    rows = [row("default", 0, 1.0, 9.0), row("default", 1, 5.0, 2.0), row("default", 2, 3.0, 3.0),
            row("slow", 0, 1.0, 1.0), row("slow", 1, 0.0, 30.0, status="budget")]
    s = {x["set"]: x for x in summarise(rows, 30.0)}
    d = s["default"]
    assert (d["setup_s"], d["solve_s"], d["total_s"]) == (5.0, 2.0, 7.0) and d["repeats"] == 3
    even = summarise(rows[:2], 30.0)[0]
    assert (even["setup_s"], even["solve_s"], even["total_s"]) == (3.0, 5.5, 8.5)
    assert s["slow"]["status"] == "budget" and s["slow"]["total_s"] == 2.0
