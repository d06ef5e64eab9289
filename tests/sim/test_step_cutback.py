"""Step cutback (``time.max_substeps``, docs/newton.md fourth round): a frame whose
Newton misses the tolerance within the cap is redone as steps of dt / 2, dt / 4, ...;
the substeps are backward-Euler steps of their own dt (equal to a run at dt / 2 when
every frame is cut once), restarts stay equivalent, the rank count changes nothing,
and bad settings are clear errors."""

import json

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from lc_petsc.batch import main
from lc_petsc.config import ConfigError, SimConfig, TimeConfig
from lc_petsc.errors import SimulationError
from sim_helpers import hairball_toml, rel_diff, run_positions, serial_reference, small_hairball_config

COMM = MPI.COMM_WORLD
TOL = 1e-6


def _cfg(cap=8, max_substeps=8, frames=4, **time):
    """Two shaking-head wisps, exact_or_analytic + retraction, tolerance 1e-6 wisp
    lengths: with a cap of 8 no frame converges at dt 1/30 (measured final increments
    2e-3 to 6e-3), with cutback every frame does in 3-5 substeps of 4-8 iterations."""
    cfg = small_hairball_config(n_wisps=2, frames=frames, newton_iterations=cap,
                                newton_increment_tol=TOL, max_substeps=max_substeps, **time)
    cfg.solver.filter = "exact_or_analytic"
    return cfg.validate()


def test_cutback_converges_where_the_cap_alone_does_not():
    _, off = run_positions(_cfg(max_substeps=1))
    assert off["newton_converged"] == [False] * 4
    assert all(v > 100 * TOL for v in off["newton_increment"])
    assert off["newton_substeps"] == [1] * 4 and off["newton_iterations"] == [8] * 4
    _, on = run_positions(_cfg())
    assert on["newton_converged"] == [True] * 4
    assert all(v < TOL for v in on["newton_increment"])
    assert all(2 <= n <= 8 for n in on["newton_substeps"])
    for total, kept, n in zip(on["newton_iterations"], on["newton_substep_iterations"],
                              on["newton_substeps"]):
        assert len(kept) == n and max(kept) <= 8
        assert total >= sum(kept) + 8          # the discarded full step counts
    assert len(on["ksp_iterations"]) == sum(on["newton_iterations"])


def test_every_frame_cut_once_equals_the_run_at_half_dt():
    """max_substeps 2 and a cap no full step meets: every frame is two steps of dt / 2,
    the run at dt / 2 to round-off (the substep times t + dt / 2 against accumulated
    ones)."""
    X, s = run_positions(_cfg(max_substeps=2, frames=3))
    assert s["newton_substeps"] == [2] * 3
    half = _cfg(max_substeps=1, frames=6, dt=1.0 / 60.0)
    Y, h = run_positions(half)
    assert [i for row in s["newton_substep_iterations"] for i in row] == h["newton_iterations"]
    assert rel_diff(X, Y) < 1e-12
    # the control: not cutting differs by far more than round-off
    Z, _ = run_positions(_cfg(max_substeps=1, frames=3))
    assert rel_diff(Z, Y) > 1e-6


def test_no_tolerance_means_no_cutback():
    """The fixed-count default: max_substeps has no effect without a tolerance."""
    cfg = _cfg(cap=3)
    cfg.time.newton_increment_tol = None
    X, s = run_positions(cfg)
    cfg.time.max_substeps = 1
    Y, _ = run_positions(cfg)
    assert s["newton_substeps"] == [1] * 4 and s["newton_converged"] == [None] * 4
    assert np.array_equal(X, Y)


def test_deepest_level_unconverged_accept_or_error():
    _, s = run_positions(_cfg(cap=2, max_substeps=2, frames=1))
    assert s["newton_converged"] == [False] and s["newton_substeps"] == [2]
    with pytest.raises(SimulationError, match=r"frame 0: Newton did not reach the tolerance.*"
                                              r"2 substep\(s\).*time.max_substeps"):
        run_positions(_cfg(cap=2, max_substeps=2, frames=1, unconverged="error"))


@pytest.mark.parametrize("value,match", [
    (0, "integer >= 1"), (3, "power of 2"), (2048, "power of 2"), ("4", "integer"),
    (True, "integer"), (1.5, "integer")])
def test_bad_max_substeps_is_config_error(value, match):
    with pytest.raises(ConfigError, match="time.max_substeps.*" + match):
        SimConfig(time=TimeConfig(max_substeps=value)).validate()


def test_bad_unconverged_and_too_small_substep_are_config_errors():
    with pytest.raises(ConfigError, match="time.unconverged must be one of"):
        SimConfig(time=TimeConfig(unconverged="stop")).validate()
    with pytest.raises(ConfigError, match=r"time.max_substeps = 1024 .* below 1e-06 s"):
        SimConfig(time=TimeConfig(dt=1e-4, max_substeps=1024)).validate()


def test_restart_with_cutbacks_is_bitwise_equal(tmp_path):
    """A checkpoint is at a frame time (cutback starts every frame at full dt again), so
    a restart continues the uninterrupted trajectory bit for bit."""
    text = hairball_toml(n_wisps=2, frames=4, output="previews = false\nxdmf = false\n"
                                                     "checkpoint_every = 2") \
        .replace("[time]\n", "[time]\nnewton_iterations = 8\nnewton_increment_tol = 1e-6\n"
                             "max_substeps = 8\n") \
        .replace("[output]", '[solver]\nfilter = "exact_or_analytic"\n[output]')
    cfg = tmp_path / "s.toml"
    cfg.write_text(text)
    ref, out = tmp_path / "ref", tmp_path / "out"
    assert main([str(cfg), "--out", str(ref), "--quiet"]) == 0
    assert main([str(cfg), "--out", str(out), "--quiet", "--frames", "3"]) == 0   # checkpoint at 2
    assert main([str(cfg), "--out", str(out), "--quiet", "--restart", "latest"]) == 0
    s = json.loads((ref / "summary.json").read_text())
    assert all(n > 1 for n in s["newton_substeps"])       # frames 2 and 3 too
    with h5py.File(ref / "frames.h5") as a, h5py.File(out / "frames.h5") as b:
        assert np.array_equal(a["time"][...], b["time"][...])
        assert np.array_equal(a["positions"][...], b["positions"][...])


@pytest.mark.mpi
def test_cutback_rank_invariance():
    """The cutback decision is collective: the parallel run cuts the serial run's frames
    into the same substeps and reaches its positions."""
    cfg = small_hairball_config(n_wisps=4, frames=3, newton_iterations=8,
                                newton_increment_tol=TOL, max_substeps=8)
    cfg.solver.filter = "exact_or_analytic"
    X, s = run_positions(cfg.validate())
    ref, r = serial_reference(cfg)
    ok = True
    if COMM.rank == 0:
        ok = (s["newton_substep_iterations"] == r["newton_substep_iterations"]
              and s["newton_iterations"] == r["newton_iterations"]
              and all(s["newton_converged"]) and max(s["newton_substeps"]) > 1
              and rel_diff(X, ref) < 1e-9)
        msg = (f"{COMM.size} ranks: {s['newton_substep_iterations']} against "
               f"{r['newton_substep_iterations']}, difference {rel_diff(X, ref):.2e}")
    if not COMM.bcast(ok):
        pytest.fail(msg if COMM.rank == 0 else "see rank 0")


def test_cutback_with_strand_contact_ccd(monkeypatch):
    """Six touching wisps, ccd mode (rest-pose pairs exempt), cap 20: no frame converges
    without cutback (measured 0 of 10), with it frames 0 and 1 do (3 substeps each,
    measured); the contact figures stay one entry per frame."""
    import lc_petsc.simulator as simmod
    from sim_helpers import touching_wisps_config, touching_wisps_source
    monkeypatch.setattr(simmod, "source_from_config", lambda *a: touching_wisps_source())

    def run(max_substeps):
        cfg = touching_wisps_config(2, options="")
        cfg.physics.strand_contact_mode, cfg.physics.strand_rest_overlap = "ccd", "exempt"
        cfg.solver.filter = "exact_or_analytic"
        cfg.time.newton_iterations, cfg.time.newton_increment_tol = 20, TOL
        cfg.time.max_substeps = max_substeps
        return run_positions(cfg.validate(), comm=MPI.COMM_SELF)[1]
    off = run(1)
    assert off["newton_converged"] == [False, False]
    on = run(8)
    assert on["newton_converged"] == [True, True] and min(on["newton_substeps"]) >= 2
    c = on["contact"]
    for key in ("pairs_per_frame", "min_distance_per_frame", "frame_path_held_vertices_per_frame",
                "limited_vertices_per_frame"):
        assert len(c[key]) == 2, key
    assert max(c["pairs_per_frame"]) > 0
