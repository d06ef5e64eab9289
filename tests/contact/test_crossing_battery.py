"""The crossing counter never hangs and never misses: a pair that coincides along its
length mid-path is decided within seconds (it kept Tight-Inclusion busy for minutes),
and on adversarial categories of pairs every crossing that an independent brute force
finds is counted (``crossing_pairs`` and the whole ``count_crossings``)."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ccd_reference import classify
from crossing_cases import CATEGORIES, cases
from lc_petsc.crossings import count_crossings, crossing_pairs

# the pair of /tmp/c56/hang.py: B = A shifted by ~1e-3, moving by -2 shifts, so the two
# coincide exactly at t = 1/2; and B's end also moving 1e-4 aside
_CHILD = """
import sys, time
import numpy as np
from lc_petsc.crossings import count_crossings, crossing_pairs
rng = np.random.default_rng(1)
a0 = rng.normal(size=3); a1 = a0 + rng.normal(size=3)
pairs = []
for noise in (0.0, 1e-4):
    off = rng.normal(size=3) * 1e-3
    S = np.array([a0, a1, a0 + off, a1 + off]); E = S.copy(); E[2:] -= 2 * off; E[2:] += rng.normal(size=3) * noise
    pairs.append((S, E))
crossing_pairs(pairs[0][0][None] + 5.0, pairs[0][0][None] + 5.0)    # imports and compiles first
print("ready", flush=True)
for S, E in pairs:
    print(int(crossing_pairs(S[None], E[None])[0]), count_crossings(S, E, [0, 2, 4])["crossings"], flush=True)
"""

#: seconds the two pairs may take (each took over 120 s)
HANG_BOUND = 10.0


def test_coincident_parallel_pair_is_decided_in_bounded_time():
    """Both pairs are decided within HANG_BOUND s (a subprocess, so that a hang fails the
    test instead of stalling the suite): the coincident one is a crossing, the one 1e-4
    aside is none (the brute force: 1.9e-5 apart at t = 0.4955)."""
    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]))
    child = subprocess.Popen([sys.executable, "-c", _CHILD], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert child.stdout.readline().strip() == "ready"
        try:
            out, _ = child.communicate(timeout=HANG_BOUND)
        except subprocess.TimeoutExpired:
            pytest.fail(f"crossing_pairs took more than {HANG_BOUND} s on a coincident parallel pair")
    finally:
        child.kill()
        child.wait()
    assert child.returncode == 0
    assert out.split() == ["1", "1", "0", "0"]


#: pairs per category
N_PAIRS = 40
#: per category, the pairs the brute force sees meet and stay apart (the rest are in
#: between, where the counter may answer either way)
BRUTE_FORCE = {"near_parallel": (15, 9), "parallel": (22, 18), "coincident": (20, 20), "parallel_sliding": (0, 34),
               "endpoint_touch": (40, 0), "collinear": (19, 9), "cross_at_instant": (40, 0), "long_step": (19, 21),
               "rotate_through": (40, 0), "far_small": (15, 0), "random_pairs": (4, 36)}


@pytest.mark.parametrize("name", list(CATEGORIES))
def test_every_brute_force_crossing_is_counted(name):
    """Per category: every pair the brute force sees meet (distance <= 1e-12 x scale) is
    a crossing of crossing_pairs and of count_crossings, and no pair it sees stay
    1e-7 x scale apart is.  On main: count_crossings missed 2 of endpoint_touch's
    (a vertex arriving head-on at the other's at t = 1: the screen's proof lost to
    round-off), near_parallel ran out of memory in ipctk, parallel_sliding did not end."""
    S, E = cases(name, N_PAIRS)
    meets, apart, d = classify(S, E)
    got = crossing_pairs(S, E)
    full = np.array([count_crossings(s, e, [0, 2, 4])["crossings"] == 1 for s, e in zip(S, E)])
    assert not np.any(meets & ~got), d[meets & ~got]
    assert not np.any(meets & ~full), d[meets & ~full]
    assert not np.any(apart & (got | full)), d[apart & (got | full)]
    # the battery is not vacuous: at least the brute force's verdicts as counted, less one
    # pair on a band's edge, which moves with the platform's round-off (near_parallel: 16
    # meet on an AMD EPYC without AVX-512, 17 on a Xeon whose OpenBLAS runs its generic
    # kernels, 15 where the counts were taken); more decided pairs only check more
    expect_meets, expect_apart = BRUTE_FORCE[name]
    assert int(meets.sum()) >= expect_meets - 1 and int(apart.sum()) >= expect_apart - 1, \
        (int(meets.sum()), int(apart.sum()))
