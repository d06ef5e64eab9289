"""PETSc option tokens -> (key, value) pairs, and which options only report, without
importing PETSc.

The main job parses its command line before ``petsc4py.init`` has seen it, so this must
not import ``petsc4py.PETSc``.
"""

import re


def option_pairs(tokens, what="PETSc options"):
    """['-a', '1', '-flag', '-b', 'x'] -> [('a', '1'), ('flag', ''), ('b', 'x')].

    A token that does not start with '-' (and is not the value of the option before it)
    is a ``ValueError`` naming ``what``. Negative numbers are values, not options.
    """
    out, i = [], 0
    while i < len(tokens):
        tok = tokens[i]
        if not tok.startswith("-") or len(tok) < 2:
            raise ValueError(f"{what}: expected an option starting with '-', got {tok!r}")
        value = ""
        if i + 1 < len(tokens) and not _is_option(tokens[i + 1]):
            value = tokens[i + 1]
            i += 1
        out.append((tok.lstrip("-"), value))
        i += 1
    return out


def diagnostic_option(key):
    """Whether PETSc option ``key`` (no dash) only reports (monitors, views, logs): it
    does not change the run's numbers (docs/newton.md: -lc_newton_monitor is bit for bit)."""
    return bool(re.search(r"(^|_)(monitor|view|log)(_|$)|converged_reason|^options_left$|^malloc", key))


def _is_option(tok):
    if not tok.startswith("-"):
        return False
    try:
        float(tok)
        return False
    except ValueError:
        return True
