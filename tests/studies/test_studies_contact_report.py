"""Strand-contact benchmark report (lc_petsc/studies/contact_report.py,
scripts/bench_contact.py --json, scripts/report_contact.py): figures, targets, plot."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from lc_petsc.studies.contact_report import plot_runs, summarize, summary_table

ROOT = Path(__file__).resolve().parents[2]


def synthetic_run(ranks, walls, collision, deep=None, dmin=0.08, d0=0.14):
    deep = deep or [0] * len(walls)
    return {"ranks": ranks, "d0": d0, "build": 1.0, "frames": [
        {"frame": f, "wall": w, "phases": {"solve": 0.5 * w, "collision": c, "elements": 0.1,
                                           "assembly": 0.1},
         "ksp": [3 + f, 60, 100 + f], "pairs": 1000 * (f + 1), "dmin": dmin + 0.001 * f,
         "deep": dp, "separated": [10 * f, 5, 0], "ghosts": 50 + f}
        for f, (w, c, dp) in enumerate(zip(walls, collision, deep))]}


def test_summary_figures():
    run = synthetic_run(2, walls=[9.0, 4.0, 6.0, 5.0, 7.0], collision=[1.0, 1.0, 2.0, 1.0, 2.0])
    s = summarize(run)
    assert s["first_frame_s"] == 9.0
    assert s["wall_median_s"] == 5.5                  # frames after the first: 4, 5, 6, 7
    assert s["wall_max_s"] == 7.0
    assert s["collision_share"] == pytest.approx(7.0 / 31.0)
    assert s["phase_median_s"]["solve"] == pytest.approx(2.75)
    assert s["cg_first_frame"] == [3, 60, 100]
    assert s["cg_max"] == 104 and s["cg_median"] == 60
    assert s["cg_per_frame_median"] == 167             # 163 + 2 f, f = 0..4
    assert (s["pairs_first"], s["pairs_median"], s["pairs_max"]) == (1000, 3000, 5000)
    assert s["dmin_cm"] == pytest.approx(0.08) and s["dmin_over_d0"] == pytest.approx(0.08 / 0.14)
    assert s["frames_with_deep_pairs"] == 0 and s["separated_max"] == 40


def test_targets_are_judged_on_two_ranks_and_said_plainly():
    fast = summarize(synthetic_run(2, walls=[5.0, 6.0, 7.0], collision=[1.0, 1.0, 1.0]))
    slow1 = summarize(synthetic_run(1, walls=[9.0, 12.0, 11.0], collision=[4.0, 5.0, 5.0]))
    table = summary_table([fast, slow1])
    assert table.index("| 1 rank |") < table.index("| 2 ranks |")      # sorted by ranks
    assert "judged on the first run on 2 rank(s)" in table
    assert "6.50 s, met" in table and "not met" not in table
    slow2 = summarize(synthetic_run(2, walls=[9.0, 9.0, 10.0], collision=[5.0, 5.0, 5.0],
                                    deep=[0, 3, 0], dmin=0.06))
    table = summary_table([slow2])
    assert "9.50 s, **not met**" in table                     # 8 s per frame
    assert "53.6%, **not met**" in table                      # contact share 15 / 28
    assert "1 frame(s) ending below, **not met**" in table    # a pair closer than d0/2
    one = summary_table([slow1])                # no 2-rank run: the time target cannot be met
    assert "judged on the first run on 1 rank(s)" in one and "11.50 s, **not met**" in one


def test_bad_runs_are_refused_with_what_is_wrong():
    with pytest.raises(ValueError, match="no frames"):
        summarize({"ranks": 1, "d0": 0.1, "frames": []})
    with pytest.raises(ValueError, match="JSON object, got list"):
        summarize([1, 2])
    with pytest.raises(ValueError, match=r"lacks \['d0', 'ranks'\]"):
        summarize({"frames": [{}]})
    run = synthetic_run(2, [5.0, 6.0], [1.0, 1.0])
    del run["frames"][1]["ksp"]
    with pytest.raises(ValueError, match="frame row 1 lacks"):
        summarize(run)
    run = synthetic_run(2, [5.0, 6.0], [1.0, 1.0], d0=0.14)
    run["d0"] = 0
    with pytest.raises(ValueError, match="d0 must be a positive number"):
        summarize(run)


def test_frames_without_pairs_in_range_and_scene_label(tmp_path):
    run = synthetic_run(2, [5.0, 6.0, 7.0], [1.0, 1.0, 1.0])
    run["frames"][0]["dmin"] = None              # bench_contact writes None for no pair in range
    run.update(wisps=2000, dofs=606000)
    s = summarize(run)
    assert s["dmin_cm"] == pytest.approx(0.081) and s["scene"] == "2,000-wisp hairball (606,000 DoFs)"
    assert summary_table([s]).startswith("| 2,000-wisp hairball (606,000 DoFs) with contact | 2 ranks |")
    for f in run["frames"]:
        f["dmin"] = None
    s = summarize(run)
    assert s["dmin_cm"] == float("inf") and "0 frame(s) ending below, met" in summary_table([s])
    plot_runs([run], tmp_path / "none.png")
    assert (tmp_path / "none.png").stat().st_size > 20_000


def test_plot_writes_a_png(tmp_path):
    runs = [synthetic_run(1, [9.0, 10.0], [3.0, 3.0]), synthetic_run(2, [5.0, 6.0], [1.0, 2.0])]
    path = tmp_path / "contact.png"
    plot_runs(runs, path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 20_000


@pytest.mark.slow
def test_bench_contact_json_feeds_the_report(tmp_path):
    """bench_contact.py on a 12-wisp hairball (2 frames) writes a JSON that
    report_contact.py turns into a table and a plot."""
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1")
    js = tmp_path / "run.json"
    bench = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_contact.py"),
                            "--config", str(ROOT / "configs" / "hairball_demo.toml"),
                            "--wisps", "12", "--frames", "2", "--json", str(js)],
                           cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert bench.returncode == 0, bench.stdout + bench.stderr
    run = json.loads(js.read_text())
    assert run["ranks"] == 1 and len(run["frames"]) == 2
    assert all(len(r["ksp"]) == 3 for r in run["frames"])        # 3 Newton solves per frame
    assert "collision share of the run" in bench.stdout
    assert run["wisps"] == 12 and run["dofs"] == 12 * 101 * 3
    rep = subprocess.run([sys.executable, str(ROOT / "scripts" / "report_contact.py"), str(js),
                          "--out", str(tmp_path / "rep_1.5")], capture_output=True, text=True,
                         timeout=120)
    assert rep.returncode == 0, rep.stdout + rep.stderr
    assert (tmp_path / "rep_1.5.png").stat().st_size > 20_000
    md = (tmp_path / "rep_1.5.md").read_text()
    assert "| 12-wisp hairball (3,636 DoFs) with contact | 1 rank |" in md and "Targets, judged on" in md
    bad = tmp_path / "bad.json"
    bad.write_text('{"frames": []}')
    rep = subprocess.run([sys.executable, str(ROOT / "scripts" / "report_contact.py"), str(bad)],
                         capture_output=True, text=True, timeout=120)
    assert rep.returncode == 2 and "lacks ['d0', 'ranks']" in rep.stderr and "bad.json" in rep.stderr
