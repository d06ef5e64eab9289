"""PETSc option tokens -> (key, value) pairs, without importing PETSc.

The main job parses its command line before ``petsc4py.init`` has seen it, so this must
not import ``petsc4py.PETSc``.
"""


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


def _is_option(tok):
    if not tok.startswith("-"):
        return False
    try:
        float(tok)
        return False
    except ValueError:
        return True
