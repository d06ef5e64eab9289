"""A tolerance run whose config file does not name ``solver.filter`` takes the converging
path (lc_petsc.config.tolerance_defaults, docs/newton.md "The default for tolerance
runs"); a file that names its filter, a fixed count and the trust region keep the
defaults; a checkpoint that ran the old default is not continued on the new path."""

import json
from dataclasses import replace

import h5py
import numpy as np
import pytest

from lc_petsc.batch import main
from lc_petsc.config import TOLERANCE_PATH, TOLERANCE_PATH_WITHOUT_STRAND_CONTACT, SimConfig, config_from_dict
from sim_helpers import hairball_toml

#: the converging path's keys, dotted: with strand contact the first four
PATH_KEYS = ["solver.filter", "solver.exact_fallback", "solver.exact_stay", "time.newton_update",
             "solver.wisp_trust", "time.newton_stop", "time.jolt_first_iterate"]
CONTACT_KEYS = PATH_KEYS[:4]


def resolved(cfg):
    return {k: getattr(getattr(cfg, k.split(".")[0]), k.split(".")[1]) for k in PATH_KEYS}


OLD = resolved(SimConfig())
NEW = {"solver.filter": "exact_or_analytic", "solver.exact_fallback": "shifted", "solver.exact_stay": True,
       "time.newton_update": "corotational", "solver.wisp_trust": True, "time.newton_stop": "chord_estimate",
       "time.jolt_first_iterate": True}


def test_a_tolerance_without_a_filter_resolves_to_the_converging_path():
    cfg = config_from_dict({"time": {"newton_increment_tol": 1e-6}})
    assert resolved(cfg) == NEW and list(cfg.solver_path_defaulted) == PATH_KEYS
    assert {f"{t}.{k}": v for (t, k), v in {**TOLERANCE_PATH, **TOLERANCE_PATH_WITHOUT_STRAND_CONTACT}.items()} == NEW
    # the chord stop estimates the relative increment: not with newton_tol
    cfg = config_from_dict({"time": {"newton_tol": 1e-5}})
    assert resolved(cfg) == {**NEW, "time.newton_stop": "increment"}
    assert list(cfg.solver_path_defaulted) == PATH_KEYS[:5] + PATH_KEYS[6:]
    # strand contact: the first four (it refuses wisp_trust and chord_estimate; the jolt's
    # first iterate bought nothing measurable with it, docs/newton.md)
    cfg = config_from_dict({"time": {"newton_increment_tol": 1e-4},
                            "physics": {"terms": ["stretch", "bend", "gravity", "strand_collision"]}})
    assert resolved(cfg) == {**NEW, "solver.wisp_trust": False, "time.newton_stop": "increment",
                             "time.jolt_first_iterate": False}
    assert list(cfg.solver_path_defaulted) == CONTACT_KEYS


def test_keys_the_file_sets_keep_their_values():
    # the filter named: nothing resolves, whatever else is set (the old path, bit for bit)
    for filt in ("analytic", "exact_or_analytic", "none"):
        cfg = config_from_dict({"time": {"newton_increment_tol": 1e-6}, "solver": {"filter": filt}})
        assert resolved(cfg) == {**OLD, "solver.filter": filt} and cfg.solver_path_defaulted == ()
    # other keys named: they keep their values, the rest resolves
    cfg = config_from_dict({"time": {"newton_increment_tol": 1e-6, "newton_update": "edge_retraction"},
                            "solver": {"exact_fallback": "analytic"}})
    # (wisp_trust carries the shifted fallback's shifts: not with the analytic one)
    assert resolved(cfg) == {**NEW, "time.newton_update": "edge_retraction", "solver.exact_fallback": "analytic",
                             "solver.wisp_trust": False}
    assert cfg.solver_path_defaulted == ("solver.filter", "solver.exact_stay", "time.newton_stop",
                                         "time.jolt_first_iterate")
    cfg = config_from_dict({"time": {"newton_increment_tol": 1e-6, "newton_stop": "increment"},
                            "solver": {"wisp_trust": False}})
    assert resolved(cfg) == {**NEW, "time.newton_stop": "increment", "solver.wisp_trust": False}


@pytest.mark.parametrize("data", [{}, {"time": {"newton_iterations": 5}},
                                  {"time": {"newton_increment_tol": 1e-6, "newton": "trust_region"}}])
def test_a_fixed_count_and_the_trust_region_keep_the_defaults(data):
    cfg = config_from_dict(data)
    assert resolved(cfg) == OLD and cfg.solver_path_defaulted == ()


#: the outputs the tests do not read, off
QUIET = "previews = false\nxdmf = false\nusd = false\ncheck_crossings = false\n"


def run(folder, name, solver="", frames=3, output="", args=()):
    """The 2-wisp shaking hairball to 1e-6 (cap 40, no cutback) in ``folder`` from the config
    ``name``.toml (``solver``: its [solver] lines): the exit code and summary.json."""
    folder.mkdir(exist_ok=True)
    cfg = folder / f"{name}.toml"
    cfg.write_text(hairball_toml(n_wisps=2, frames=frames, output=QUIET + output).replace(
        "[time]\n", "[time]\nnewton_increment_tol = 1e-6\nnewton_iterations = 40\nmax_substeps = 1\n")
        + (f"[solver]\n{solver}\n" if solver else ""))
    out = folder / "out"
    code = main([str(cfg), "--out", str(out), "--quiet", *args])
    return code, (json.loads((out / "summary.json").read_text()) if code == 0 else None)


def test_the_default_converges_where_the_named_analytic_filter_crawls(tmp_path):
    """2 wisps of the shaking hairball, 3 frames to 1e-6 (cap 40, no cutback): the default
    converges every frame (16, 9, 18 iterations; without wisp_trust and the chord stop 24, 11,
    25); the analytic filter named in the file keeps the old path (main's default), which
    misses the tolerance in every frame at the cap of 40, and says so."""
    _, new = run(tmp_path / "new", "s")
    _, old = run(tmp_path / "old", "s", solver='filter = "analytic"')
    assert new["solver_path_defaulted"] == PATH_KEYS and old["solver_path_defaulted"] == []
    assert {k: new["config"][k.split(".")[0]][k.split(".")[1]] for k in PATH_KEYS} == NEW
    assert {k: old["config"][k.split(".")[0]][k.split(".")[1]] for k in PATH_KEYS} == OLD
    assert new["newton_converged"] == [True] * 3 and max(new["newton_iterations"]) <= 20, new["newton_iterations"]
    assert old["newton_converged"] == [False] * 3 and old["newton_iterations"] == [40] * 3
    assert not any("converges linearly" in w for w in new["warnings"])
    assert any("converges linearly" in w and "leave solver.filter unset" in w for w in old["warnings"])


def test_a_checkpoint_of_the_old_default_is_not_continued_on_the_new_path(tmp_path):
    """A checkpoint written before this default (a tolerance, no filter: the analytic path,
    as its config records) restarted with the same file is refused, naming the keys and
    the values it ran with; the file with them set continues it bit for bit."""
    out = "checkpoint_every = 2"
    old_path = 'filter = "analytic"'          # what such a checkpoint's config records
    code, ref = run(tmp_path / "ref", "s", solver=old_path, frames=4, output=out)
    assert code == 0
    run_dir = tmp_path / "run"
    assert run(run_dir, "s", solver=old_path, frames=3, output=out)[0] == 0      # checkpoint at frame 2
    code, _ = run(run_dir, "s", frames=4, output=out, args=("--restart", "latest"))
    assert code != 0
    code, s = run(run_dir, "s", solver=old_path, frames=4, output=out, args=("--restart", "latest"))
    assert code == 0 and s["restart"]["frame"] == 2 and s["solver_path_defaulted"] == []
    with h5py.File(tmp_path / "ref" / "out" / "frames.h5") as a, h5py.File(run_dir / "out" / "frames.h5") as b:
        assert np.array_equal(a["positions"][...], b["positions"][...])


def test_the_refusal_names_the_keys_and_the_values_the_checkpoint_ran_with(tmp_path, capsys):
    out = "checkpoint_every = 1"
    assert run(tmp_path, "s", solver='filter = "analytic"', frames=1, output=out)[0] == 0
    capsys.readouterr()
    code, _ = run(tmp_path, "s", frames=2, output=out, args=("--restart", "latest"))
    err = capsys.readouterr().err
    assert code != 0
    assert ("this config leaves solver.filter, solver.exact_fallback, solver.exact_stay, time.newton_update, "
            "solver.wisp_trust, time.newton_stop, time.jolt_first_iterate unset, which with a tolerance now selects "
            "the converging path") \
        in err, err
    assert ('the checkpoint ran with solver.filter = "analytic", solver.exact_fallback = "analytic", '
            'solver.exact_stay = false, time.newton_update = "edge_retraction", solver.wisp_trust = false, '
            'time.newton_stop = "increment", time.jolt_first_iterate = false: set that in the config') in err, err
    assert "solver_path_defaulted" not in err       # a record, not a key of the config


def test_the_studies_that_set_their_own_path_drop_the_files_tolerance_defaults():
    """scripts/newton_history.py (a fixed count) and drivers/tradeoff.py (the settings'
    path) on a config file with a tolerance and no filter: the file's resolved
    ``time.newton_stop = "chord_estimate"`` stayed in every variant and refused it (on
    main: a ConfigError for each, the study stopped before running)."""
    from lc_petsc.studies import newton, tradeoff
    data = {"scene": {"kind": "hairball", "n_wisps": 2}, "time": {"newton_increment_tol": 1e-6},
            "physics": {"head_motion": "shake"}}
    cfg = config_from_dict(data)
    assert resolved(cfg) == NEW
    # the newton study's base is the paper's path at a fixed count, as without the tolerance
    plain = config_from_dict({**data, "time": {}})
    for spec in ("", "filter=analytic,update=linear"):
        variant = newton.parse_variant(spec)
        assert newton.configure(cfg, variant, 30, 3).to_dict() == newton.configure(plain, variant, 30, 3).to_dict()
    assert resolved(newton.configure(cfg, {}, 30, 3)) == OLD
    # the trade-off study runs its settings' path; the file keeps its resolved config
    for settings in (tradeoff.BASE, replace(tradeoff.BASE, newton_increment_tol=1e-6)):
        run = tradeoff.configure(cfg, settings, 0.1).validate()
        assert (run.solver.filter, run.time.newton_stop, run.solver_path_defaulted) == ("analytic", "increment", ())
    assert resolved(cfg) == NEW and list(cfg.solver_path_defaulted) == PATH_KEYS
    # a newton_stop the file names stays
    named = config_from_dict({**data, "time": {"newton_increment_tol": 1e-6, "newton_stop": "quadratic_estimate"}})
    assert tradeoff.configure(named, replace(tradeoff.BASE, filter="exact_or_analytic",
                                                       newton_increment_tol=1e-6), 0.1).validate().time.newton_stop \
        == "quadratic_estimate"


def test_a_file_naming_the_filter_is_told_the_checkpoint_ran_the_tolerance_defaults(tmp_path, capsys):
    """The reverse of the refusal above: a checkpoint of the converging path (a tolerance,
    no filter in the file) restarted with a file that names the very filter it ran
    (``exact_or_analytic``) is refused over the six keys that file leaves at their
    defaults; the refusal says why and which values continue it (on main it listed them
    only); the file with them set continues it."""
    out = "checkpoint_every = 1"
    assert run(tmp_path, "s", frames=1, output=out)[0] == 0
    capsys.readouterr()
    named = 'filter = "exact_or_analytic"'
    code, _ = run(tmp_path, "s", solver=named, frames=2, output=out, args=("--restart", "latest"))
    err = capsys.readouterr().err
    assert code != 0
    assert ("this config names solver.filter, which keeps the keys it leaves unset at their defaults" in err
            and 'set solver.exact_fallback = "shifted", solver.exact_stay = true, time.newton_update = '
                '"corotational", solver.wisp_trust = true, time.newton_stop = "chord_estimate", '
                'time.jolt_first_iterate = true in the config to continue it as it ran' in err), err
    # the values the message names set in the file: continued
    cfg = tmp_path / "s.toml"
    cfg.write_text(cfg.read_text().replace("[time]\n", '[time]\nnewton_update = "corotational"\nnewton_stop = '
                                            '"chord_estimate"\njolt_first_iterate = true\n').replace(
        named, named + '\nexact_fallback = "shifted"\nexact_stay = true\nwisp_trust = true'))
    assert main([str(cfg), "--out", str(tmp_path / "out"), "--quiet", "--restart", "latest", "--frames", "2"]) == 0
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert s["restart"]["frame"] == 1 and s["solver_path_defaulted"] == [] and s["newton_converged"] == [True]
