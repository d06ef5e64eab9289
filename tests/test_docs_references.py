"""The docs' references checked against the code (README.md, docs/*.md, configs/*.toml,
configs/solvers/*.opts): every file of the repository and every ``tests/X.py::test`` they
name exists, every ``-lc_*`` option they name is one the solver plan reads (and the
README's table lists each one), every backquoted config key ``table.key`` is a field of
the config, and every ``--flag`` they give a script or driver is one that script's
command line (or the lc_petsc modules it imports) spells out; and a /tmp path (a
session's scratch file) is said to be one.  A rename in the code that the docs miss fails
here."""

import dataclasses
import functools
import re
from pathlib import Path

from lc_petsc.config import TABLES
from lc_petsc.solver_plan import LC_OPTIONS

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md"), *(ROOT / "configs").glob("*.toml"),
               *(ROOT / "configs" / "solvers").glob("*.opts")])
FILE = re.compile(r"\b(?:scripts|drivers|lc_petsc|tests|configs)/[\w./-]+\.(?:py|sh|toml|opts|h5|usda)\b")
TEST = re.compile(r"\b(tests/[\w/]+\.py)::(\w+)")
LC_OPTION = re.compile(r"(?<![\w-])-(lc_[a-z0-9_]+)")
CONFIG_KEY = re.compile(r"`((?:scene|material|physics|time|solver|output)\.[a-z_][a-z_0-9]*)(?: = [^`]*)?`")
COMMAND = re.compile(r"\b((?:scripts|drivers)/\w+\.py)\b")
FLAG = re.compile(r"(?<![\w-])(--[a-z][a-z0-9-]*)")
#: a /tmp path a reader can use as it stands: the benchmarks' lock, a Numba cache folder
TMP = re.compile(r"/tmp/(?!lc_bench\.lock)(?<!NUMBA_CACHE_DIR=/tmp/)[\w.{*-]")
SAID_SCRATCH = re.compile(r"scratch|not kept|throwaway", re.I)
#: the README's example of a misspelt option that the run refuses
REFUSED_EXAMPLES = {"lc_wisp_blockz"}
#: backquoted names that look like config keys and are not: summary.json's ``output``
#: record, Python's ``time`` module, a module file, and keys of patches that were not kept
NOT_CONFIG_KEYS = {"output.skipped", "output.not_written", "output.progress_summaries", "output.usd_error",
                   "output.usd_s", "time.process_time", "time.thread_time", "solver.py",
                   "time.root_turn_hinges", "solver.exact_contact"}


def _lines():
    for path in DOCS:
        for number, line in enumerate(path.read_text().splitlines(), 1):
            yield f"{path.relative_to(ROOT)}:{number}", line


@functools.cache
def _script_flags(path: Path) -> frozenset:
    """The ``--flags`` spelt in ``path`` and in the lc_petsc modules it imports (recursively)."""
    flags: set = set()
    todo, seen = [path], set()
    while todo:
        current = todo.pop()
        if current in seen or not current.is_file():
            continue
        seen.add(current)
        text = current.read_text()
        flags |= set(re.findall(r"[\"'](--[a-z][a-z0-9-]*)", text))
        for module in re.findall(r"^\s*(?:from|import) (lc_petsc[\w.]*)", text, re.M):
            stem = ROOT / module.replace(".", "/")
            todo += [stem.with_suffix(".py"), stem / "__init__.py"]
    return frozenset(flags)


def test_named_files_exist():
    named = [(where, name) for where, line in _lines() for name in FILE.findall(line)]
    assert len(named) > 300, "the pattern finds the docs' file names"
    missing = [f"{where}: {name}" for where, name in named if not (ROOT / name).exists()]
    assert not missing, "files named in the docs that do not exist:\n" + "\n".join(missing)


def test_named_tests_exist():
    named = [(where, path, name) for where, line in _lines() for path, name in TEST.findall(line)]
    assert len(named) > 50
    missing = [f"{where}: {path}::{name}" for where, path, name in named
               if not (ROOT / path).is_file() or not re.search(rf"^\s*(?:async )?(?:def|class) {name}\b",
                                                                (ROOT / path).read_text(), re.M)]
    assert not missing, "tests named in the docs that do not exist:\n" + "\n".join(missing)


def test_lc_options_are_the_ones_the_plan_reads():
    named = [(where, name) for where, line in _lines() for name in LC_OPTION.findall(line)]
    assert len(named) > 100
    unknown = [f"{where}: -{name}" for where, name in named if name not in LC_OPTIONS and name not in REFUSED_EXAMPLES]
    assert not unknown, "-lc_ options named in the docs that lc_petsc does not read:\n" + "\n".join(unknown)
    readme = (ROOT / "README.md").read_text()
    assert not [o for o in LC_OPTIONS if f"`-{o}`" not in readme], "the README names every -lc_ option"


def test_config_keys_are_fields_of_the_config():
    keys = {f"{table}.{field.name}" for table, cls in TABLES.items() for field in dataclasses.fields(cls)}
    named = [(where, key) for where, line in _lines() for key in CONFIG_KEY.findall(line)]
    assert len(named) > 400
    unknown = [f"{where}: {key}" for where, key in named if key not in keys and key not in NOT_CONFIG_KEYS]
    assert not unknown, "config keys named in the docs that the config does not have:\n" + "\n".join(unknown)


def test_script_flags_are_on_their_command_lines():
    lines = list(_lines())
    checked, unknown = 0, []
    for i, (where, line) in enumerate(lines):
        for match in COMMAND.finditer(line):
            # the command's words up to the next script or driver it wraps, a pipe, ; or a comment,
            # with the backslash-continued lines after it
            rest = re.split(r"[;|#`]|\b(?:scripts|drivers)/\w+\.py", line[match.end():])[0]
            j = i
            while line[match.end():].rstrip().endswith("\\") and rest.rstrip().endswith("\\") and \
                    j + 1 < len(lines) and lines[j + 1][0].split(":")[0] == where.split(":")[0]:
                j += 1
                rest = rest.rstrip()[:-1] + " " + re.split(r"[;|#`]|\b(?:scripts|drivers)/\w+\.py", lines[j][1])[0]
                if not lines[j][1].rstrip().endswith("\\"):
                    break
            script = ROOT / match.group(1)
            if not script.is_file():
                continue          # test_named_files_exist reports it
            accepted = _script_flags(script) | {"--help", "--"}
            for flag in FLAG.findall(rest):
                checked += 1
                if flag not in accepted:
                    unknown.append(f"{where}: {match.group(1)} {flag}")
    assert checked > 300
    assert not unknown, "flags the docs give scripts that their command lines do not have:\n" + "\n".join(unknown)


def test_tmp_paths_are_said_to_be_scratch():
    """A /tmp path in the docs is a session's scratch file (docs/architecture.md, "Commands
    in the docs"): each paragraph or command block naming one says so, so that no reader
    takes it for a command to run."""
    unsaid, named = [], 0
    for path in DOCS:
        blocks = re.split(r"\n\s*\n", path.read_text())
        for block in blocks:
            if TMP.search(block):
                named += 1
                if not SAID_SCRATCH.search(block):
                    line = next(text for text in block.splitlines() if TMP.search(text))
                    unsaid.append(f"{path.relative_to(ROOT)}: {line.strip()[:160]}")
    assert named > 100
    assert not unsaid, ("/tmp paths in paragraphs that do not say 'scratch, not kept' (write the "
                        "command with scripts/ and out/, or mark it):\n" + "\n".join(unsaid))
