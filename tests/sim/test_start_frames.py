"""``time.start_increment_tol`` / ``time.start_frames`` / ``time.start_iterations``: the
first frames of a fixed count solved to a relative increment tolerance on the recommended
converging path, the later frames at the count (docs/newton.md "Twenty-second round").
The collective test (marked ``mpi``) also runs on 2 and 3 ranks through
tests/test_mpi_launch.py."""

import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.config import TimeConfig
from lc_petsc.errors import ConfigError
from sim_helpers import assert_follows_serial, jolt_hairball_config, run_positions

comm = MPI.COMM_WORLD
TOL = 1e-6


def _config(frames=4, **time):
    """3 wisps under a stronger shake (:func:`jolt_hairball_config`)."""
    return jolt_hairball_config(frames=frames, **time)


@pytest.mark.mpi
@pytest.mark.parametrize("turn", [False, True])
def test_start_frames_converge_then_the_count_resumes(turn):
    """The plain count leaves frame 0's last increment above 1e-6 of a wisp length; with
    ``start_increment_tol = 1e-6`` and ``start_frames = 2`` frames 0 and 1 converge below
    it (``newton_converged`` True, ``newton_start`` True) in more iterations, and frames
    2 and 3 take the count of 3 (``newton_converged`` None, the root turn on them only);
    every rank count takes the same iterations and follows the serial run within
    test_mpi_sim's 1e-10."""
    plain = run_positions(_config(root_rotation=turn), comm=comm)[1]
    cfg = _config(root_rotation=turn, start_increment_tol=TOL, start_frames=2)
    X, summ = run_positions(cfg, comm=comm)
    its, inc = summ["newton_iterations"], summ["newton_increment"]
    ok = plain["newton_iterations"] == [3, 3, 3, 3] and plain["newton_increment"][0] > 100 * TOL
    msg = f"plain run: iterations {plain['newton_iterations']}, increments {plain['newton_increment']}"
    if ok:
        ok = (summ["newton_start"] == [True, True, False, False]
              and summ["newton_converged"] == [True, True, None, None]
              and max(inc[:2]) < TOL and min(its[:2]) > 3 and its[2:] == [3, 3]
              and summ["root_turns_reduced"] == [0, 0] + plain["root_turns_reduced"][2:])
        msg = (f"{comm.size} ranks: start {summ['newton_start']}, converged {summ['newton_converged']}, "
               f"iterations {its}, last increments {inc}, turns cut {summ['root_turns_reduced']}")
    assert_follows_serial(cfg, X, its, ok, msg, comm)


def test_a_start_frame_is_the_converging_path_bit_for_bit():
    """Frame 0 with the start option is the frame of a run configured by
    :meth:`SimConfig.start_config` (the recommended path to that tolerance): the same
    positions to the bit and the same iterations; the frame after it differs from that
    run's (the count of 3, not the tolerance)."""
    cfg = _config(frames=2, start_increment_tol=TOL, start_frames=1)
    X, summ = run_positions(cfg, comm=MPI.COMM_SELF, frames=1)
    conv, conv_summ = run_positions(cfg.start_config().validate(), comm=MPI.COMM_SELF, frames=1)
    assert np.array_equal(X, conv)
    assert summ["newton_iterations"] == conv_summ["newton_iterations"]
    assert summ["newton_converged"] == conv_summ["newton_converged"] == [True]
    two = run_positions(cfg, comm=MPI.COMM_SELF)[1]
    assert two["newton_iterations"][1] == 3 and two["newton_converged"] == [True, None]


@pytest.mark.parametrize("fields, words", [
    (dict(start_increment_tol=-1e-3), "time.start_increment_tol must be a finite positive number"),
    (dict(start_increment_tol="1e-3"), "time.start_increment_tol must be a number"),
    (dict(start_increment_tol=float("inf")), "time.start_increment_tol must be a finite positive"),
    (dict(start_frames=0), "time.start_frames must be an integer >= 1"),
    (dict(start_frames=1.5), "time.start_frames must be an integer >= 1"),
    (dict(start_iterations=0), "time.start_iterations must be an integer >= 1"),
    (dict(start_iterations=20000), "time.start_iterations = 20000 is more than"),
    (dict(start_increment_tol=1e-3, newton_increment_tol=1e-4), "drop one of them"),
    (dict(start_increment_tol=1e-3, newton_tol=1e-3), "drop one of them"),
    (dict(start_increment_tol=1e-3, newton="trust_region"), "set time.newton = \"filtered\""),
])
def test_bad_start_settings_are_refused(fields, words):
    with pytest.raises(ConfigError, match=words.replace("(", r"\(").replace(".", r"\.")):
        TimeConfig(**fields).validate()


def test_the_wisp_shares_take_the_compiled_energy_pass(monkeypatch):
    """The per-wisp line searches' energies (Assembler.vertex_energy, 45% of frame 0's
    Newton time on the converging path when it ran the NumPy kernels, docs/newton.md
    "Twenty-second round") are one compiled pass with the compiled kernels: no NumPy
    kernel call, within round-off of the NumPy kernels' per-vertex energies and summing
    to the elastic energy."""
    from lc_petsc import assembly
    from lc_petsc.simulator import build_simulator
    cfg = _config(frames=1)
    sims = [build_simulator(cfg, comm=MPI.COMM_SELF)]
    cfg_numpy = _config(frames=1)
    cfg_numpy.solver.options += " -lc_element_kernels numpy"
    sims.append(build_simulator(cfg_numpy, comm=MPI.COMM_SELF))
    try:
        sims[0].step()
        x = sims[0].integrator.x
        calls = []
        for name, module in assembly.KERNELS.items():
            real = module.energy
            monkeypatch.setattr(module, "energy", lambda *a, real=real: calls.append(1) or real(*a))
        fast = sims[0].assembler.vertex_energy(x)
        assert calls == []
        ref = sims[1].assembler.vertex_energy(x)
        assert len(calls) == 3 and sims[1].assembler.kernels == "numpy"
        assert np.abs(fast - ref).max() <= 1e-12 * np.abs(ref).max()
        assert abs(fast.sum() - sims[0].assembler.energy(x)) <= 1e-12 * abs(fast.sum())
    finally:
        for s in sims:
            s.close()


def test_the_start_keys_without_a_tolerance_are_warned():
    """``time.start_frames`` / ``start_iterations`` without ``time.start_increment_tol``
    change nothing: the configuration says so, naming the key; with it, no warning."""
    from lc_petsc.config import config_from_dict
    cfg = config_from_dict({"time": {"start_frames": 3, "start_iterations": 10}})
    assert [w.split(" is set")[0] for w in cfg.key_warnings] == ["time.start_frames", "time.start_iterations"]
    assert all("time.start_increment_tol set" in w for w in cfg.key_warnings)
    cfg = config_from_dict({"time": {"start_frames": 3, "start_increment_tol": 1e-3}})
    assert cfg.key_warnings == [] and cfg.time.start_frames == 3
