"""The --help of every script and driver that describes itself from its docstring: the
whole first paragraph, never its first line cut mid-sentence (newton_history.py's --help
read "... on the demo hairball (10 wisps, no strand contact) and"; 12 scripts did so on
main 26a1516)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _descriptions():
    """(file, description) for each ArgumentParser(description=<expression of __doc__>)."""
    for path in sorted([*ROOT.glob("scripts/*.py"), *ROOT.glob("drivers/*.py")]):
        tree = ast.parse(path.read_text())
        doc = ast.get_docstring(tree, clean=False)
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "ArgumentParser":
                for kw in node.keywords:
                    if kw.arg == "description" and "__doc__" in ast.unparse(kw.value):
                        yield path.relative_to(ROOT), eval(ast.unparse(kw.value), {"__doc__": doc})


def test_help_descriptions_are_whole_sentences():
    found = list(_descriptions())
    assert len(found) >= 20
    cut = [f"{path}: ...{text[-60:]!r}" for path, text in found if not text.rstrip().endswith((".", ":", ")"))]
    assert not cut, "\n".join(cut)
