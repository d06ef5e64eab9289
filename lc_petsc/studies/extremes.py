"""Stability at the extremes: the catalogue's hard cases, each with a stated
expectation, run and judged pass/fail with figures.  Used by ``scripts/extremes.py``.

Expectations:
* ``recovers``: the run finishes and ends near its rest shape (no gravity, so the rest
  shape is the equilibrium): RMS distance from rest <= ``rms_tol`` x wisp length and
  curl-radius retention within ``1 +- retention_tol``;
* ``finite``: the run finishes (no NaN, no failed linear solve, no blow-up) and the
  largest stretch strain stays below ``strain_tol``;
* ``fails_cleanly``: the run must stop with a named solver error (``SolverError``: a
  diverged or indefinite linear solve is an error, never silent);
* ``info``: no expectation of ours (e.g. the paper's "unfiltered Newton diverges"): the
  outcome is reported and not judged (``passed`` None, "INFO"): it cannot fail, so it
  is not counted as a pass either.

The catalogue runs fixed counts; :func:`at_tolerance` runs a case to a tolerance on the
path a user's config file gets (:func:`lc_petsc.config.tolerance_defaults`), judged by
the same expectation and reported with its convergence (frames converged, iterations per
frame, frames cut back).
"""

from __future__ import annotations

import copy
import statistics
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from lc_petsc.config import (ELASTIC_TERMS, MaterialConfig, PhysicsConfig, SceneConfig, SimConfig,
                             tolerance_defaults)
from lc_petsc.studies import report
from lc_petsc.studies.measures import curl_radius, stretch_strain, wisp_lengths
from lc_petsc.studies.tradeoff import Settings, configure, run_trajectory


@dataclass
class Case:
    """One hard case: its config, the settings it runs with, and what it is expected to do."""

    name: str
    what: str
    config: SimConfig
    settings: Settings
    frames: int
    expect: str = "recovers"          # recovers | finite | fails_cleanly | info
    rms_tol: float = 0.05
    retention_tol: float = 0.1
    strain_tol: float = 0.5
    meta: dict = field(default_factory=dict)
    #: the Newton path's keys the case is about (dotted, as its config file names them,
    #: e.g. its filter): kept when it runs to a tolerance (:func:`at_tolerance`)
    names: tuple = ()


def wisp(perturbation="none", factor=0.4, gravity=False, n_vertices=101, E=3.9e9, radius=None,
         jitter=0.5):
    """Config of one 4C wisp with the given perturbation and material."""
    terms = ELASTIC_TERMS + (("gravity",) if gravity else ())
    mat = MaterialConfig(youngs_modulus=E)
    if radius is not None:
        mat.root_radius = mat.tip_radius = radius
    return SimConfig(scene=SceneConfig(kind="wisp4c", n_vertices=n_vertices, perturbation=perturbation,
                                       smash_factor=factor, jitter=jitter),
                     material=mat, physics=PhysicsConfig(terms=terms))


def helix_file(path, helix_radius=0.1, n_vertices=101, per_turn=5, rise=0.1, stem=3, stem_len=0.6):
    """A 4C-like wisp with a helix of ``helix_radius`` cm, hanging along -y, as an
    HDF5 strands file (DESIGN 3)."""
    import h5py
    x = np.zeros((n_vertices, 3))
    x[:stem, 1] = -stem_len * np.arange(stem)
    k = np.arange(n_vertices - stem)
    th = 2 * np.pi / per_turn * k
    x[stem:, 0] = helix_radius * (np.cos(th) - 1.0)
    x[stem:, 2] = helix_radius * np.sin(th)
    x[stem:, 1] = -stem_len * stem - rise * k
    with h5py.File(path, "w") as f:
        f["positions"] = x
        f["wisp_offsets"] = np.array([0, n_vertices], np.int64)
    return str(path)


def catalogue(*, tmpdir, quick=False):
    """The catalogue's hard cases; ``tmpdir``: an existing folder the cases' groom files
    are written to, which must outlive the runs and which the caller removes (a folder
    made here was left in /tmp by every run and test).  ``quick`` shortens every run
    (for tests)."""
    q = (lambda n: max(3, n // 10)) if quick else (lambda n: n)
    tmpdir = Path(tmpdir)
    # the Krylov tolerance the catalogue's figures were set with (its one iterating case,
    # pbjacobi at dt = 1, would otherwise take the fixed count's looser code default)
    dt30 = Settings(ksp_rtol=1e-6)
    cases = [Case("smash60", "Smash: free x scaled by 0.4 (60% compression), no gravity",
                  wisp("smash", 0.4), dt30, q(100))]
    for pct in (30, 40):
        for f in ("analytic", "numerical", "none"):
            cases.append(Case(f"compress{pct}_{f}", f"{pct}% compression, filter {f}",
                              wisp("smash", 1 - pct / 100), replace(dt30, filter=f), q(100),
                              expect="recovers" if f != "none" else "info", names=("solver.filter",)))
    cases.append(Case("compress40_none_cg_pbjacobi",
                      "40% compression, filter none, dt 1 s, CG + point-block Jacobi "
                      "(CG needs an SPD matrix: the filters guarantee one)",
                      wisp("smash", 0.6), replace(dt30, dt=1.0, filter="none",
                                                  options="-pc_type pbjacobi -ksp_max_it 5000"),
                      3, expect="fails_cleanly", names=("solver.filter",)))
    cases.append(Case("jitter", "Jitter: uniform offsets in [-0.5, 0.5] cm, no gravity",
                      wisp("jitter"), dt30, q(200)))
    cases.append(Case("straighten", "Straighten: 20-vertex curl on a vertical line (bends = pi), "
                      "gravity on", wisp("straighten", gravity=True, n_vertices=20), dt30, q(40),
                      expect="finite"))
    cases.append(Case("curl_radius_1mm", "helix radius 1 mm (0.1 cm) instead of 5 mm, gravity on",
                      SimConfig(scene=SceneConfig(kind="file", path=helix_file(tmpdir / "helix1mm.h5")),
                                material=MaterialConfig(youngs_modulus=3.9e9, root_radius=0.35,
                                                        tip_radius=0.07),
                                physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity"))),
                      dt30, q(60), expect="finite"))
    cases.append(Case("dt_1_10", "dt = 1/10 s, gravity on", wisp(gravity=True),
                      replace(dt30, dt=0.1), q(30), expect="finite"))
    for ratio in (1e4, 1e6, 1e8):
        r = 2.0 / np.sqrt(ratio)         # k_s / k_b = 4 / r^2 (equal edge and Voronoi lengths)
        cases.append(Case(f"stiffness_ratio_{ratio:.0e}",
                          f"stretch/bend stiffness ratio ~{ratio:.0e} (uniform radius {r:.2e} cm), "
                          "gravity on", wisp(gravity=True, radius=r), dt30, q(30), expect="finite",
                          meta={"radius_cm": r}))
    cases.append(Case("stiffness_ratio_1e+08_line_search",
                      "stiffness ratio ~1e8 as above, with the Armijo line search on G",
                      wisp(gravity=True, radius=2e-4), replace(dt30, line_search=True), q(30),
                      expect="finite", meta={"radius_cm": 2e-4}))
    cases.append(Case("wisp_1000_vertices", "a 4C wisp of 1,000 vertices, gravity on",
                      wisp(gravity=True, n_vertices=1000), dt30, q(10), expect="finite"))
    return cases


def at_tolerance(case: Case, tol: float, cap: int) -> Case:
    """``case`` run to the relative increment tolerance ``tol`` (``time.newton_increment_tol``)
    with at most ``cap`` iterations per step and the step cutback's default, as a user's
    config file of the case that names the tolerance, the cap and ``case.names`` runs it:
    the Newton path :func:`lc_petsc.config.tolerance_defaults` resolves for that file (listed
    in ``meta["solver_path_defaulted"]``; nothing where the case names its filter) and the
    code's Krylov tolerance for a tolerance (the catalogue's ``-ksp_rtol`` dropped)."""
    s = replace(case.settings, newton_increment_tol=tol, newton_iterations=cap, ksp_rtol=None)
    cfg = configure(case.config, s, case.frames * s.dt)
    given = {("time", "newton_increment_tol"), ("time", "newton_iterations")} | \
        {tuple(name.split(".")) for name in case.names}
    resolved = tolerance_defaults(cfg, given)
    keys = [name.split(".") for name in resolved]
    s = replace(s, **{key: getattr(getattr(cfg, table), key) for table, key in keys})
    return replace(case, settings=s, meta=dict(case.meta, solver_path_defaulted=list(resolved)))


def convergence(res) -> dict:
    """A tolerance run's convergence figures from :func:`run_trajectory`'s result: frames
    converged of those run, Newton iterations per frame (median, worst and its frame; a
    frame's substeps and discarded attempts included) and frames cut back into substeps."""
    its = res.get("frame_iterations") or []
    worst = max(its, default=None)
    return {"frames_converged": res.get("newton_converged_frames"),
            "newton_median": statistics.median(its) if its else None, "newton_worst": worst,
            "newton_worst_frame": None if worst is None else its.index(worst),
            "cut_back_frames": res.get("newton_cut_back_frames")}


def judge(case: Case, res, traj, geo):
    """Figures and pass/fail of one case (rank 0)."""
    rest, offsets, pinned = geo
    L = float(np.mean(wisp_lengths(rest, offsets)))
    fig = {"frames_run": res.get("frames_run"), "wall_s": res.get("wall_s"),
           "newton_total": res.get("newton_total"), "ksp_iterations_max": res.get("ksp_iterations_max"),
           "status": res["status"], "failure": res["failure"], "failed_frame": res["failed_frame"],
           "message": res["message"]}
    if case.settings.newton_increment_tol is not None:
        fig.update(convergence(res))
    if traj and traj["positions"]:
        x = traj["positions"][-1]
        fig["final_rms_from_rest"] = float(np.sqrt(np.mean(np.sum((x - rest) ** 2, axis=1)))) / L
        later = traj["positions"][1:] or traj["positions"]     # not the perturbed start
        fig["max_stretch_strain"] = max(stretch_strain(p, rest, offsets) for p in later)
        r0, r1 = curl_radius(rest, offsets, ~pinned), curl_radius(x, offsets, ~pinned)
        fig["curl_retention"] = (r1 / r0) if (r0 and r1) else None
    ok = res["status"] == "ok"
    ret = fig.get("curl_retention")
    if not ok:
        fig["outcome"] = f"failed ({res['failure']} at frame {res['failed_frame']})"
    elif fig.get("final_rms_from_rest", np.inf) <= case.rms_tol and ret is not None \
            and abs(ret - 1.0) <= case.retention_tol:
        fig["outcome"] = "recovered"
    else:
        fig["outcome"] = (f"finite, not recovered (strain up to {report.fmt(fig.get('max_stretch_strain'))}, "
                          f"curl retention {report.fmt(ret)})")
    if case.expect == "recovers":
        passed = ok and fig.get("final_rms_from_rest", np.inf) <= case.rms_tol and \
            ret is not None and abs(ret - 1.0) <= case.retention_tol
        expectation = (f"recovers: RMS distance from rest <= {case.rms_tol:g} L and curl "
                       f"retention 1 +- {case.retention_tol:g} after {case.frames} frames")
    elif case.expect == "finite":
        passed = ok and fig.get("max_stretch_strain", np.inf) <= case.strain_tol
        expectation = f"stays finite (no failure) with stretch strain <= {case.strain_tol:g}"
    elif case.expect == "fails_cleanly":
        passed = res["status"] == "unstable" and res["failure"] == "SolverError"
        expectation = "stops with a named solver error (SolverError), never silently"
    else:
        passed = None
        expectation = "reported, not judged (no expectation; the paper: unfiltered Newton diverges)"
    return dict(case=case.name, what=case.what, expect=case.expect, expectation=expectation,
                passed=None if passed is None else bool(passed), settings=case.settings.label(),
                **case.meta, **fig)


def verdict(row) -> str:
    """PASS, FAIL or INFO (an ``info`` case: reported, not judged)."""
    return "INFO" if row["passed"] is None else "PASS" if row["passed"] else "FAIL"


def convergence_text(row) -> str:
    """A tolerance run's convergence in a few words ("" for a fixed count)."""
    if "frames_converged" not in row:
        return ""
    return (f"{row['frames_converged']}/{row['frames_run']} converged, iterations median "
            f"{report.fmt(row['newton_median'])} worst {report.fmt(row['newton_worst'])} (frame "
            f"{report.fmt(row['newton_worst_frame'])}), {row['cut_back_frames']} cut back")


def run_cases(cases, comm, out_dir=None, log=print):
    """Run every case; one row (dict) per case on rank 0, optional trajectories in ``out_dir``."""
    rows = []
    for c in cases:
        cfg = copy.deepcopy(c.config)
        duration = c.frames * c.settings.dt
        res, traj, geo = run_trajectory(cfg, c.settings, duration, c.settings.dt, comm)
        if comm.rank != 0:
            continue
        row = judge(c, res, traj, geo)
        rows.append(row)
        converged = convergence_text(row)
        log(f"{verdict(row)} {c.name:28s} {row['outcome'][:40]:40s} "
            f"rms-from-rest {report.fmt(row.get('final_rms_from_rest'))}  "
            f"curl {report.fmt(row.get('curl_retention'))}  strain {report.fmt(row.get('max_stretch_strain'))}  "
            f"{row['wall_s'] or 0:.2f} s  {converged + '  ' if converged else ''}{row['failure']} "
            f"{row['message'][:90]}")
    if comm.rank == 0 and out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        cols = ["case", "passed", "expect", "outcome", "status", "failure", "failed_frame", "frames_run",
                "final_rms_from_rest", "curl_retention", "max_stretch_strain", "newton_total",
                "ksp_iterations_max", "wall_s", "settings", "what", "expectation", "message"]
        report.write_csv(rows, out / "extremes.csv", cols)
        report.write_json(rows, out / "extremes.json")
        tolerance = any("frames_converged" in r for r in rows)
        (out / "extremes.md").write_text("# Stability at the extremes\n\n" + report.markdown_table(
            ["case", "expectation", "result", "outcome", "RMS from rest (L)", "curl retention",
             "max strain", "wall (s)"] + ["to the tolerance"] * tolerance + ["failure"],
            [[r["case"], r["expectation"], verdict(r), r["outcome"],
              report.fmt(r.get("final_rms_from_rest")), report.fmt(r.get("curl_retention")),
              report.fmt(r.get("max_stretch_strain")), report.fmt(r.get("wall_s"))]
             + [convergence_text(r)] * tolerance
             + [f"{r['failure']} at frame {r['failed_frame']}: {r['message'][:80]}" if r["failure"] else ""]
             for r in rows]))
    return rows
