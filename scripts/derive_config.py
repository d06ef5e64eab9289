r"""Write a variant of a scene config: a shipped ``configs/*.toml`` with some keys changed.

    .venv/bin/python scripts/derive_config.py BASE.toml OUT.toml [--set TABLE.KEY=VALUE ...]

The docs' benchmarks run the shipped scenes with a key or two changed, e.g. the 2K
hairball written every frame (the crossing count between written frames, and what a
viewer interpolates, are of every step then) or in penalty mode::

    .venv/bin/python scripts/derive_config.py configs/hairball_2k.toml out/ccd100.toml --set output.every=1
    .venv/bin/python scripts/derive_config.py configs/hairball_2k.toml out/pen.toml \
        --set output.every=1 --set physics.strand_contact_mode='"penalty"' --set time.initial_guess='"inertial"'

``VALUE`` is a TOML value (strings in double quotes, arrays in brackets).  The file
paths of BASE (``scene.path``, ``solver.options_file``) are written absolute, so OUT may
live in any folder (``out/`` is ignored by git; configs/ holds the catalogue only).
Comments are not copied.  The written config is loaded once
(``lc_petsc.config.load_config``): a key the config does not know or a bad value stops
here with the config's own message (exit 2), and OUT is not left behind.
"""

import argparse
import json
import sys
import tomllib
from pathlib import Path

from lc_petsc.config import PATH_KEYS, load_config
from lc_petsc.errors import ConfigError


def derive(base: Path, changes: list[str]) -> dict:
    """BASE's tables with ``changes`` (``TABLE.KEY=VALUE``) applied and paths made absolute."""
    data = tomllib.loads(base.read_text())
    for table, key in PATH_KEYS:
        if key in data.get(table, {}):
            data[table][key] = str((base.parent / data[table][key]).resolve())
    for item in changes:
        name, _, value = item.partition("=")
        table, _, key = name.partition(".")
        if not value or not key or "." in key:
            raise ValueError(f"--set wants TABLE.KEY=VALUE (e.g. output.every=1), got {item!r}")
        try:
            data.setdefault(table, {})[key] = tomllib.loads(f"v = {value}")["v"]
        except tomllib.TOMLDecodeError:
            raise ValueError(f"--set {name}: {value!r} is not a TOML value (a string needs "
                             f"double quotes: --set {name}='\"{value}\"')") from None
    return data


def to_toml(data: dict) -> str:
    """Tables of scalars and arrays as TOML (JSON's spelling of them is TOML's too)."""
    return "".join(f"[{table}]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in keys.items()) + "\n"
                   for table, keys in data.items())


def cli(argv=None) -> int:
    """Write OUT from BASE and the ``--set`` changes; print OUT."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("base", type=Path, help="the config to start from, e.g. configs/hairball_2k.toml")
    ap.add_argument("out", type=Path, help="the config file to write")
    ap.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE")
    a = ap.parse_args(argv)
    try:
        text = to_toml(derive(a.base, a.set))
    except (OSError, ValueError, tomllib.TOMLDecodeError) as e:
        ap.error(str(e))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(text)
    try:
        load_config(a.out)
    except ConfigError as e:
        a.out.unlink()
        ap.error(f"{a.out} not written: {e}")
    print(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(cli())
