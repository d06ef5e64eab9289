"""TOML configs and the main job's command line: every class of bad input is reported
once, names key, value and what is allowed, exits non-zero, dumps no traceback and
writes nothing."""

import json
import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.batch import main
from lc_petsc.errors import UsageError
from lc_petsc.config import ConfigError, SimConfig, load_config

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = sorted((ROOT / "configs").glob("*.toml"))
CATALOGUE = {"hairball_2k", "hairball_4k", "hairball_8k", "hairball_demo", "smash", "jitter",
             "straighten", "compression_30", "compression_40", "cantilever", "from_file", "from_usd"}
SELF = MPI.COMM_SELF
from sim_helpers import MPI_ENV  # noqa: E402

GOOD = """
[scene]
kind = "wisp4c"
n_vertices = 12
[physics]
terms = ["stretch", "bend", "twist", "gravity"]
[time]
frames = 2
"""


def test_catalogue_complete_documented_and_valid():
    assert {p.stem for p in CONFIGS} == CATALOGUE
    for p in CONFIGS:
        text = p.read_text()
        assert text.startswith(f"# {p.stem}: "), f"{p.name} must open with a comment on what it shows"
        assert "What it shows" in text or "what it shows" in text.lower(), p.name
        cfg = load_config(p)
        assert isinstance(cfg, SimConfig)
        assert cfg.scene.description, p.name


def test_scene_terms_only_what_is_needed():
    cfg = {p.stem: load_config(p) for p in CONFIGS}
    for name in ("smash", "jitter", "compression_30", "compression_40"):
        assert set(cfg[name].physics.terms) == {"stretch", "bend", "twist"}, name   # no gravity, no contact
    assert "twist" not in cfg["cantilever"].physics.terms
    assert "head_collision" not in cfg["from_file"].physics.terms
    for n in ("2k", "4k", "8k"):
        c = cfg[f"hairball_{n}"]
        assert c.scene.n_wisps == int(n[0]) * 1000 and c.time.frames == 540
        assert c.physics.head_motion == "shake" and "head_collision" in c.physics.terms


def test_paths_relative_to_the_config_file(tmp_path):
    cfg = load_config(ROOT / "configs" / "from_file.toml")
    assert cfg.scene.path == str(ROOT / "configs" / "data" / "fringe.h5")
    demo = load_config(ROOT / "configs" / "hairball_demo.toml")
    assert demo.solver.options_file == str(ROOT / "configs" / "solvers" / "default.opts")
    assert "-pc_type bjacobi" in demo.solver.effective_options()
    # the options string comes after the file, so it wins
    (tmp_path / "x.opts").write_text("-ksp_rtol 1e-3  # comment\n-pc_type none\n")
    (tmp_path / "c.toml").write_text('[solver]\noptions_file = "x.opts"\noptions = "-ksp_rtol 1e-9"\n')
    c = load_config(tmp_path / "c.toml")
    from lc_petsc.solver_plan import parse_options
    assert dict(parse_options(c.solver.effective_options()))["ksp_rtol"] == "1e-9"


# (class of bad input, TOML text or None for a missing file, the message's parts)
BAD = [
    ("unknown table", GOOD + "[physic]\nterms = []\n", ["unknown table [physic]", "[physics]"]),
    ("unknown key", GOOD.replace("frames = 2", "frames = 2\nnewton_iters = 3"),
     ["unknown key time.newton_iters", "newton_iterations"]),
    ("wrong type", GOOD.replace("frames = 2", 'frames = "2"'), ["time.frames = '2'", "expected an integer"]),
    ("wrong type (vector)", GOOD.replace('"gravity"]', '"gravity"]\ngravity = [0, -981]'),
     ["physics.gravity = [0, -981]", "an array of 3 numbers"]),
    ("negative dt", GOOD.replace("frames = 2", "frames = 2\ndt = -0.01"),
     ["time.dt", "-0.01", "positive"]),
    ("zero density", GOOD + "[material]\ndensity = 0\n", ["material.density", "got 0", "positive"]),
    ("twist rest sine of 1", GOOD + "[material]\ntwist_rest_sine = 1.0\n",
     ["material.twist_rest_sine", "[0, 1)", "got 1.0"]),
    ("Newton count < 1", GOOD.replace("frames = 2", "frames = 2\nnewton_iterations = 0"),
     ["time.newton_iterations", ">= 1", "got 0"]),
    ("unknown term", GOOD.replace('"gravity"]', '"gravity", "bending"]'),
     ["physics.terms", "'bending'", "stretch"]),
    ("missing strands file", '[scene]\nkind = "file"\npath = "nowhere.h5"\n',
     ["scene.path", "nowhere.h5", "no such file"]),
    ("missing options file", GOOD + '[solver]\noptions_file = "none.opts"\n',
     ["solver.options_file", "none.opts", "no such file"]),
    ("bad enum", GOOD + '[output]\nview = "iso"\n', ["output.view", "'iso'", "front"]),
    ("TOML syntax", GOOD + "[time\n", ["invalid TOML"]),
    ("missing config file", None, ["no such config file"]),
    # a zero-length file (a failed copy) ran the defaults' 1-wisp scene, exit 0, and
    # replaced a finished run's outputs in --out
    ("empty file", "", ["the config file is empty (0 bytes, no key)", "[scene]"]),
    ("comments only", "# cut here\n\n", ["the config file is empty (12 bytes, no key)"]),
    # the frame times k dt overflowed: an OverflowError traceback in the head's motion, exit 1
    ("dt times frames overflows", GOOD.replace("frames = 2", "frames = 2\ndt = 1e308"),
     ["time.dt = 1e+308 s times time.frames = 2 is beyond the largest float"]),
    # a fixed count of 1e18 iterations per frame ran until killed
    ("Newton count 1e18", GOOD.replace("frames = 2", "frames = 2\nnewton_iterations = 1000000000000000000"),
     ["time.newton_iterations = 1000000000000000000 is more than 10,000 Newton iterations per frame"]),
    # numpy's uniform(-jitter, jitter) raised OverflowError: a traceback, exit 1
    ("jitter beyond half the largest float",
     GOOD.replace("n_vertices = 12", 'n_vertices = 12\nperturbation = "jitter"\njitter = 1e308'),
     ["scene.jitter = 1e+308 cm is beyond half the largest float"]),
    # these three passed the config and failed in frame 0 (exit 3), after writing it
    ("head radius beyond double precision", GOOD.replace("[physics]\n", "[physics]\nhead_radius = 1e308\n"),
     ["physics.head_radius + head_margin = 1e+308 cm is beyond 4.5e+07 cm"]),
    ("head margin beyond double precision", GOOD.replace("[physics]\n", "[physics]\nhead_margin = 1e308\n"),
     ["physics.head_radius + head_margin = 1e+308 cm is beyond 4.5e+07 cm"]),
    ("radius below an atom", GOOD.replace("[physics]\n", "[material]\ntip_radius = 1e-300\n[physics]\n"),
     ["material.tip_radius = 1e-300 cm is below 1e-08 cm"]),
]


def _run_main(capsys, argv, comm=SELF):
    code = main(argv, comm=comm)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("case, text, parts", BAD, ids=[b[0] for b in BAD])
def test_bad_config_is_reported_once_without_traceback_or_output(tmp_path, capsys, case, text, parts):
    cfg = tmp_path / "bad.toml"
    if text is not None:
        cfg.write_text(text)
    out_dir = tmp_path / "out"
    code, out, err = _run_main(capsys, [str(cfg), "--out", str(out_dir), "--quiet"])
    assert code == 2
    assert err.count("error:") == 1 and "Traceback" not in err + out, err
    assert str(cfg) in err or case == "missing config file"
    for p in parts or []:
        assert p in err, (p, err)
    assert not out_dir.exists(), "no partial output"
    if text is not None and case not in ("TOML syntax",):
        with pytest.raises(ConfigError):
            load_config(cfg)


@pytest.mark.parametrize("argv, part", [
    (["--frames", "-1"], "--frames must be an integer >= 0"),
    (["--frames", "two"], "invalid int value: 'two'"),
    (["stray"], "unexpected argument 'stray'"),
    (["--restart", "latest"], "--restart latest: no valid checkpoint in"),
    # an unknown double-dash flag went to PETSc and was refused as its option -bogus
    (["--bogus"], "--bogus is not a flag of simulate.py (usage: mpiexec -n P python drivers/simulate.py "
                  "CONFIG.toml [--frames N]"),
    (["--fram", "3"], "--fram is not a flag of simulate.py (did you mean --frames?"),
    (["--ksp_rtol", "1e-3"], "a PETSc option takes one dash: -ksp_rtol"),
])
def test_bad_command_line(tmp_path, capsys, argv, part):
    (tmp_path / "c.toml").write_text(GOOD)
    code, out, err = _run_main(capsys, [str(tmp_path / "c.toml")] + argv + ["--out", str(tmp_path / "o")])
    assert code == 2 and part in err and "Traceback" not in err and not (tmp_path / "o").exists(), err


@pytest.mark.parametrize("argv", [
    ["c.toml", "--frames", "3", "--", "-ksp_rtol", "1e-3"],
    ["c.toml", "--", "-ksp_rtol", "1e-3"],
    ["c.toml", "-ksp_rtol", "1e-3", "--frames", "3"],
])
def test_double_dash_before_petsc_options_is_not_an_option(argv):
    """``simulate.py CONFIG -- -ksp_rtol 1e-3`` (the usage DESIGN.md gives): the ``--``
    was passed on to PETSc as an option named "-", which it reported as never used."""
    from lc_petsc.batch import parse_command_line
    args, petsc_argv = parse_command_line(argv)
    assert args.config == "c.toml" and petsc_argv == ["-ksp_rtol", "1e-3"]


def test_options_file_on_the_command_line_is_read_like_the_configs(tmp_path):
    """``-options_file FILE`` is replaced in place by the file's options, read as
    ``solver.options_file`` is (several per line, comments): PETSc 3.18's reader takes
    one option per line and refused the shipped configs/solvers/*.opts."""
    from lc_petsc.batch import expand_options_files
    (tmp_path / "x.opts").write_text("# two per line\n-ksp_type cg -ksp_rtol 1e-6  # tight\n-pc_type jacobi\n")
    assert expand_options_files(["-ksp_rtol", "1e-3", "-options_file", str(tmp_path / "x.opts"),
                                 "-ksp_max_it", "7"]) == \
        ["-ksp_rtol", "1e-3", "-ksp_type", "cg", "-ksp_rtol", "1e-6", "-pc_type", "jacobi", "-ksp_max_it", "7"]
    with pytest.raises(UsageError, match="-options_file needs a file name"):
        expand_options_files(["-options_file", "-ksp_rtol", "1e-3"])
    (tmp_path / "b.opts").write_bytes(b"-ksp_type \xff\n")
    with pytest.raises(UsageError, match="b.opts.*not a text file"):
        expand_options_files(["-options_file", str(tmp_path / "b.opts")])


def test_shipped_options_file_on_the_command_line_under_mpiexec(tmp_path):
    """The real CLI on 2 ranks with ``-options_file configs/solvers/bjacobi_rank.opts``:
    PETSc's own reader failed on one rank ("extra token") and mpiexec hung."""
    (tmp_path / "c.toml").write_text('[scene]\nkind = "hairball"\nn_wisps = 3\nseed = 5\n[physics]\n'
                                     'terms = ["stretch", "bend", "twist", "gravity"]\n[time]\nframes = 2\n'
                                     '[output]\npreviews = false\nusd = false\n')
    cmd = ["mpiexec", "--oversubscribe", "-n", "2", sys.executable, str(ROOT / "drivers" / "simulate.py"),
           str(tmp_path / "c.toml"), "--out", str(tmp_path / "o"), "--quiet", "--frames", "1",
           "-options_file", str(ROOT / "configs" / "solvers" / "bjacobi_rank.opts")]
    p = subprocess.run(cmd, capture_output=True, text=True, env=MPI_ENV, timeout=120, cwd=tmp_path,
                       stdin=subprocess.DEVNULL)
    assert p.returncode == 0, p.stderr
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["petsc_options_command_line"]["pc_type"] == "bjacobi", s["petsc_options_command_line"]


def test_problems_found_while_building_are_reported_once(tmp_path, capsys):
    """A strands file without /wisp_offsets and a solver that refuses the matrix type
    are found after the TOML checks, still before any output."""
    with h5py.File(tmp_path / "s.h5", "w") as f:
        f["positions"] = np.zeros((8, 3))
    (tmp_path / "a.toml").write_text('[scene]\nkind = "file"\npath = "s.h5"\n')
    code, out, err = _run_main(capsys, [str(tmp_path / "a.toml"), "--out", str(tmp_path / "o")])
    assert code == 2 and "missing dataset /wisp_offsets" in err and "Traceback" not in err
    (tmp_path / "b.toml").write_text(GOOD + '[solver]\noptions = "-pc_type cholesky '
                                     '-pc_factor_mat_solver_type mumps -mat_type baij"\n')
    code, out, err = _run_main(capsys, [str(tmp_path / "b.toml"), "--out", str(tmp_path / "o")])
    assert code == 2 and "MUMPS does not accept BAIJ" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_command_line_exit_status_under_mpiexec(tmp_path):
    """The real CLI on 2 ranks: one message, non-zero exit, no traceback, no output."""
    (tmp_path / "bad.toml").write_text(GOOD.replace("frames = 2", "frames = 2\ndt = 0"))
    cmd = ["mpiexec", "--oversubscribe", "-n", "2", sys.executable, str(ROOT / "drivers" / "simulate.py"),
           str(tmp_path / "bad.toml"), "--out", str(tmp_path / "o")]
    p = subprocess.run(cmd, capture_output=True, text=True, env=MPI_ENV, timeout=120, cwd=tmp_path)
    assert p.returncode != 0
    assert p.stderr.count("simulate.py: error:") == 1, p.stderr
    assert "time.dt must be a finite positive number, got 0.0" in p.stderr
    assert "Traceback" not in p.stderr + p.stdout
    assert not (tmp_path / "o").exists()


def test_help(capsys):
    code, out, err = _run_main(capsys, ["--help"])
    assert code == 0 and "CONFIG.toml" in out and "PETSc" in out


def test_every_config_key_is_documented_in_the_readme():
    from dataclasses import fields
    from lc_petsc.config import TABLES
    readme = (ROOT / "README.md").read_text()
    table = readme[readme.index("## Config reference"):]
    for name, cls in TABLES.items():
        for f in fields(cls):
            assert f"`{name}.{f.name}`" in table, f"{name}.{f.name} is not in the README's config table"
    for p in CONFIGS:
        assert f"`{p.stem}`" in readme or p.stem.startswith("compression"), p.stem


@pytest.mark.parametrize("key, value, physics, warned", [
    ("strand_contact_mode", "ccd", {}, True),
    ("strand_rest_overlap", "exempt", {}, True),
    ("strand_min_separation", 0.3, {}, True),
    ("strand_min_separation", 0.3, {"terms": ["stretch", "strand_collision"]}, True),     # penalty mode
    ("strand_min_separation", 0.3, {"terms": ["stretch", "strand_collision"], "strand_contact_mode": "ccd"}, False),
    ("strand_contact_mode", "ccd", {"terms": ["stretch", "strand_collision"]}, False),
])
def test_strand_contact_keys_without_strand_contact_are_warned_about(key, value, physics, warned):
    from lc_petsc.config import config_from_dict, keys_without_effect
    data = {"physics": {"terms": ["stretch"], **physics, key: value}}
    warn = [w for w in keys_without_effect(config_from_dict(data), data) if w.startswith(f"physics.{key} ")]
    assert len(warn) == int(warned), warn


@pytest.mark.parametrize("table, key, value, expect", [
    ("material", "youngs_modulus", 4.0, "material.youngs_modulus = 4 dyn/cm^2 is outside the plausible "
     "range for hair, 1e+06 to 1e+12 dyn/cm^2: it looks like MPa or GPa"),
    ("material", "shear_modulus", 5e13, "material.shear_modulus = 5e+13 dyn/cm^2 is outside the plausible "
     "range for hair, 1e+06 to 1e+12 dyn/cm^2: stiffer than any hair"),
    ("material", "root_radius", 3.5, "material.root_radius = 3.5 cm is outside the plausible range for "
     "hair, 0.0005 to 2 cm: it looks like millimetres or micrometres"),
    ("material", "tip_radius", 4e-5, "material.tip_radius = 4e-05 cm is outside the plausible range for "
     "hair, 0.0005 to 2 cm: thinner than any hair; it looks like metres"),
    ("time", "dt", 33.0, "time.dt = 33 s is outside the plausible range for hair, 1e-06 to 1 s: it "
     "looks like milliseconds"),
    ("physics", "gravity", [0.0, -9.81, 0.0], "|physics.gravity| = 9.81 cm/s^2 is outside the plausible "
     "range for hair, 100 to 5000 cm/s^2: it looks like m/s^2 (9.81 m/s^2 = 981 cm/s^2)"),
    ("physics", "head_radius", 0.15, "physics.head_radius = 0.15 cm is outside the plausible range for "
     "hair, 1 to 100 cm: it looks like metres (0.15 m = 15 cm)"),
])
def test_implausible_values_are_warned_about_with_the_likely_unit(table, key, value, expect):
    """Valid but absurd values (a unit mistake) run, with a warning naming key, value,
    range and the likely mistake; the same table's plausible values do not warn."""
    from lc_petsc.config import config_from_dict
    data = {"physics": {"terms": ["stretch", "bend", "gravity", "head_collision"]}}
    data.setdefault(table, {})[key] = value
    warn = config_from_dict(data).key_warnings
    assert len(warn) == 1 and warn[0].startswith(expect), warn
    plausible = {"youngs_modulus": 4e10, "shear_modulus": 1e10, "root_radius": 0.35,
                 "tip_radius": 0.004, "dt": 1.0, "gravity": [0.0, -981.0, 0.0], "head_radius": 15.25}
    data[table][key] = plausible[key]
    assert config_from_dict(data).key_warnings == []


def test_implausible_value_is_reported_by_the_main_job(tmp_path, capsys):
    """The warning reaches stderr and summary.json and the run goes ahead; a head radius
    in metres without head_collision (nothing uses it) is not warned about."""
    import json
    cfg = tmp_path / "w.toml"
    cfg.write_text(GOOD.replace('"gravity"]', '"gravity"]\nhead_radius = 0.15')
                   + "[material]\nroot_radius = 3.5\n[output]\npreviews = false\nusd = false\n")
    assert main([str(cfg), "--out", str(tmp_path / "o"), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "warning: material.root_radius = 3.5 cm is outside the plausible range for hair" in err
    warnings = json.loads((tmp_path / "o" / "summary.json").read_text())["warnings"]
    assert len(warnings) == 1 and warnings[0].startswith("material.root_radius = 3.5 cm")


@pytest.mark.parametrize("value, likely", [
    (1300.0, "it looks like kg/m^3 (hair: 1300 kg/m^3 = 1.3 g/cm^3)"),
    (0.0013, "it looks like kg/cm^3 or g/mm^3 (hair: 1.3 g/cm^3 = 0.0013 g/mm^3)"),
    (1e308, "it looks like kg/m^3 (hair: 1300 kg/m^3 = 1.3 g/cm^3)"),
])
def test_a_density_in_another_unit_is_refused(value, likely):
    """material.density 1000 times off (kg/m^3, g/mm^3) ran with a warning, as if the hair
    were 1000 times softer or stiffer (docs/design_notes.md "Densities: refused outside
    0.1-10 g/cm^3": hairball10 at 1300 stretched its edges by up to 100%, smash at 1300
    looked like a slow recovery); now a ConfigError naming key, value, range, unit and the
    likely mistake.  The range's ends and hair's 1.3 run."""
    from lc_petsc.config import config_from_dict
    with pytest.raises(ConfigError) as e:
        config_from_dict({"material": {"density": value}})
    assert str(e.value) == (f"material.density = {value:g} g/cm^3 is outside 0.1 to 10 g/cm^3: {likely}; a "
                            "density 1000 times off runs the scene as if 1000 times softer or stiffer, without "
                            "an error; give it in g/cm^3 (stiffness is set by the Young's modulus)")
    for ok in (0.1, 1.3, 10.0):
        cfg = config_from_dict({"material": {"density": ok}})
        assert cfg.material.density == ok and cfg.key_warnings == []


def test_a_binary_options_file_is_named(tmp_path, capsys):
    """solver.options_file naming a file that is not UTF-8 text ended simulate.py in a
    UnicodeDecodeError traceback; now exit 2 naming the key and the file, nothing written."""
    (tmp_path / "x.opts").write_bytes(b"-ksp_rtol 1e-6\n\x80\n")
    cfg = tmp_path / "c.toml"
    cfg.write_text(GOOD + '[solver]\noptions_file = "x.opts"\n')
    code, out, err = _run_main(capsys, [str(cfg), "--out", str(tmp_path / "out"), "--quiet"])
    assert code == 2 and "Traceback" not in err + out
    assert err.strip() == (f"simulate.py: error: {cfg}: solver.options_file = '{tmp_path / 'x.opts'}': not a "
                           "text file of PETSc options (invalid start byte at byte 15)"), err
    assert not (tmp_path / "out").exists()


def test_a_smash_factor_that_overflows_the_positions_is_refused_before_anything_is_written(tmp_path, capsys):
    """smash_factor = 1e308 ran, wrote frame 0 and failed there (non-finite positions, exit 3)."""
    from sim_helpers import hairball_toml
    text = hairball_toml(n_wisps=3, frames=2).replace(
        "[material]", 'perturbation = "smash"\nsmash_factor = 1e308\n[material]')
    (tmp_path / "s.toml").write_text(text)
    code, out, err = _run_main(capsys, [str(tmp_path / "s.toml"), "--out", str(tmp_path / "o"), "--quiet"])
    assert code == 2, err
    assert err.count("error:") == 1 and "Traceback" not in err, err
    assert re.search(r"scene\.perturbation = 'smash' \(scene\.smash_factor = 1e\+308\) moves wisp \d, vertex 4 "
                     r"to \[-?inf, ", err), err
    assert "not a finite number" in err and not (tmp_path / "o").exists()
