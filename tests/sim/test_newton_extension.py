"""``time.newton_extend_above`` / ``time.newton_extend_cap``: a fixed count of Newton
iterations that extends itself on a frame whose last increment is still above the bound
(docs/newton.md "Eighteenth round").  The collective tests (marked ``mpi``) also run on 2
and 3 ranks through tests/test_mpi_launch.py."""

import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.config import TimeConfig
from lc_petsc.errors import ConfigError
from sim_helpers import assert_follows_serial, jolt_hairball_config, run_positions

comm = MPI.COMM_WORLD


def _jolt_config(**time):
    """3 wisps, 3 frames under a stronger shake (:func:`jolt_hairball_config`)."""
    return jolt_hairball_config(**time)


@pytest.mark.mpi
@pytest.mark.parametrize("turn", [False, True])
def test_a_jolt_frame_is_extended_until_below_the_bound(turn):
    """Frame 0's last increment after the count is above 1e-3 (asserted on the plain
    run); with the extension it takes more iterations, and every frame ends at or below
    1e-3 unless at the cap; every rank count takes the same iterations and follows the
    serial run within test_mpi_sim's 1e-10.  With the root turn the turn runs once per
    frame, after the frame's last iteration (``root_turns_reduced`` has one entry per
    frame; the turn's own move is part of the last increment, so that is not bounded)."""
    plain = run_positions(_jolt_config(root_rotation=turn), comm=comm)[1]
    cfg = _jolt_config(root_rotation=turn, newton_extend_above=1e-3, newton_extend_cap=12)
    X, summ = run_positions(cfg, comm=comm)
    its, inc = summ["newton_iterations"], summ["newton_increment"]
    ok = plain["newton_iterations"] == [3, 3, 3] and plain["newton_increment"][0] > 1e-3
    msg = f"plain run: iterations {plain['newton_iterations']}, increments {plain['newton_increment']}"
    if ok and not turn:
        ok = 3 < its[0] and all(3 <= n < 12 and d <= 1e-3 or n == 12 for n, d in zip(its, inc))
        msg = f"{comm.size} ranks: iterations {its}, last increments {inc}"
    if ok and turn:
        ok = 3 < its[0] <= 12 and len(summ["root_turns_reduced"]) == 3
        msg = f"{comm.size} ranks, turned: iterations {its}, turns cut {summ['root_turns_reduced']}"
    assert_follows_serial(cfg, X, its, ok, msg, comm)


@pytest.mark.parametrize("turn", [False, True])
def test_calm_frames_are_unchanged_bit_for_bit(turn):
    """A bound that no frame's third increment exceeds (0.1 wisp lengths on the same
    scene): the same positions to the bit and the same 3 iterations per frame as the
    plain fixed count, with and without the root turn."""
    cfg = _jolt_config(root_rotation=turn)
    X0, s0 = run_positions(cfg, comm=MPI.COMM_SELF)
    assert max(s0["newton_increment"]) < 0.1
    X1, s1 = run_positions(_jolt_config(root_rotation=turn, newton_extend_above=0.1), comm=MPI.COMM_SELF)
    assert s1["newton_iterations"] == s0["newton_iterations"] == [3, 3, 3]
    assert np.array_equal(X1, X0)
    assert s1["newton_increment"] == s0["newton_increment"]


def test_the_cap_ends_an_extended_frame():
    """A bound no iteration reaches (1e-12): every frame takes exactly the cap, each is
    counted as ended by it (``newton_extend_capped``), and the run's warning names the
    frames and the keys; a bound every frame reaches counts none."""
    from lc_petsc.job import outcome_warnings
    cfg = _jolt_config(newton_extend_above=1e-12, newton_extend_cap=5)
    summ = run_positions(cfg, comm=MPI.COMM_SELF)[1]
    assert summ["newton_iterations"] == [5, 5, 5]
    assert min(summ["newton_increment"]) > 1e-12
    assert summ["newton_extend_capped"] == [1, 1, 1]
    warned = [w for w in outcome_warnings(summ, 0, cfg.time) if "newton_extend_cap = 5" in w]
    assert len(warned) == 1 and "in 3 frame(s)" in warned[0] and "newton_extend_above = 1e-12" in warned[0]
    calm = run_positions(_jolt_config(newton_extend_above=1e-1, newton_extend_cap=5), comm=MPI.COMM_SELF)[1]
    assert calm["newton_extend_capped"] == [0, 0, 0]
    assert not [w for w in outcome_warnings(calm, 0, cfg.time) if "newton_extend_cap" in w]


@pytest.mark.parametrize("fields, words", [
    (dict(newton_extend_above=-1e-2), "time.newton_extend_above must be a finite positive number"),
    (dict(newton_extend_above="1e-2"), "time.newton_extend_above must be a number"),
    (dict(newton_extend_above=True), "time.newton_extend_above must be a number"),
    (dict(newton_extend_above=float("nan")), "time.newton_extend_above must be a finite positive"),
    (dict(newton_extend_cap=0), "time.newton_extend_cap must be an integer >= 1"),
    (dict(newton_extend_cap=12.5), "time.newton_extend_cap must be an integer >= 1"),
    (dict(newton_extend_above=1e-2, newton_extend_cap=3), "must be above time.newton_iterations = 3"),
    (dict(newton_extend_above=1e-2, newton_iterations=20), "must be above time.newton_iterations = 20"),
    (dict(newton_extend_above=1e-2, newton_increment_tol=1e-4), "drop one of them"),
    (dict(newton_extend_above=1e-2, newton_tol=1e-3), "drop one of them"),
])
def test_bad_extension_settings_are_refused(fields, words):
    with pytest.raises(ConfigError, match=words.replace("(", r"\(").replace(".", r"\.")):
        TimeConfig(**fields).validate()
