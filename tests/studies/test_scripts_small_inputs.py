"""Scripts of scripts/ on the smallest inputs they allow (the study logic itself is tested
with lc_petsc.studies): what used to crash on them."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _script(name):
    """scripts/<name>.py as a module (its main() not run)."""
    spec = importlib.util.spec_from_file_location(f"script_{name}", ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_newton_frames_plots_fewer_than_four_frames(tmp_path):
    """The right panel (the median over frames 3..) has no frame to draw: it stays empty
    instead of min() of an empty sequence."""
    rows = [{"iterations": 3, "converged": True, "true": 2, "first_error": 1e-2,
             "errors": [1e-3, 1e-5, 1e-7]}]
    _script("newton_frames").plot({"a": rows}, ["a"], 1e-6, 5, tmp_path / "f.png", "one frame")
    assert (tmp_path / "f.png").stat().st_size > 0
