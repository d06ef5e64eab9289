"""A generated scene too large for the memory of the job's nodes is refused before it is
built, with the strands files' estimate."""

import subprocess
import sys
import time
from pathlib import Path

import pytest

from lc_petsc.batch import EXIT_USAGE
from lc_petsc.errors import ConfigError
from lc_petsc.scene import sources

ROOT = Path(__file__).resolve().parents[2]
DRIVER = str(ROOT / "drivers" / "simulate.py")

HAIRBALL = """
[scene]
kind = "hairball"
n_wisps = {n_wisps}
[physics]
terms = ["stretch", "bend", "twist", "gravity"]
[time]
frames = 3
[output]
previews = false
usd = false
"""


def _config(tmp_path, n_wisps=4):
    p = tmp_path / "h.toml"
    p.write_text(HAIRBALL.format(n_wisps=n_wisps))
    return str(p)



# ------------------------------------------------------------------- size check
def test_absurd_n_wisps_is_refused_before_building(tmp_path):
    """n_wisps = 1e8 used to build for many minutes (1.8 GB and growing, no message):
    the memory estimate of strands files refuses it at once, naming the key."""
    out = tmp_path / "out"
    cmd = [sys.executable, DRIVER, _config(tmp_path, n_wisps=100_000_000), "--out", str(out), "--quiet"]
    t0 = time.monotonic()
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=30, stdin=subprocess.DEVNULL)
    assert r.returncode == EXIT_USAGE, r.stderr[-2000:]
    assert time.monotonic() - t0 < 15
    assert ("scene.n_wisps = 100000000: 100,000,000 wisps of 101 vertices (10,100,000,000 "
            "vertices); a run needs at least 4096 bytes per vertex, 4.14e+04 GB, and this machine "
            "has ") in r.stderr, r.stderr
    assert "GB of memory; use fewer wisps or run on more nodes" in r.stderr
    assert r.stderr.count("error:") == 1 and "Traceback" not in r.stderr
    assert not out.exists()


def test_generated_scene_memory_estimate(monkeypatch):
    """The strands files' estimate (4 kB per vertex against the memory of the job's
    nodes) on a machine of 1 GiB: 2,000 hairball wisps fit, 3,000 do not on one node but
    do on two; a straight strand names scene.n_vertices."""
    monkeypatch.setattr(sources, "machine_memory", lambda: 1 << 30)
    monkeypatch.setattr(sources, "job_nodes", lambda: 1)
    assert sources.GeneratedSource("hairball", n_wisps=2000).n_wisps == 2000
    with pytest.raises(ConfigError) as e:
        sources.GeneratedSource("hairball", n_wisps=3000)
    assert str(e.value) == ("scene.n_wisps = 3000: 3,000 wisps of 101 vertices (303,000 vertices); "
                            "a run needs at least 4096 bytes per vertex, 1.24 GB, and this machine has "
                            "1.07 GB of memory; use fewer wisps or run on more nodes")
    with pytest.raises(ConfigError, match=r"^scene.n_vertices = 300000: .* 1.07 GB of memory; use fewer"):
        sources.GeneratedSource("straight", n_vertices=300_000)
    monkeypatch.setattr(sources, "job_nodes", lambda: 2)
    assert sources.GeneratedSource("hairball", n_wisps=3000).n_wisps == 3000
