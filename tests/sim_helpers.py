"""Shared builders for the simulator tests (tests/sim/, tests/contact/ and the test_mpi_*.py files)."""

import contextlib
import os
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np
from mpi4py import MPI

from lc_petsc.config import (MaterialConfig, PhysicsConfig, SceneConfig, SimConfig,
                             SolverConfig, TimeConfig, load_config)
from lc_petsc.scene import geometry
from lc_petsc.scene.sources import ArraySource
from lc_petsc.simulator import build_simulator

CONFIGS = Path(__file__).resolve().parents[1] / "configs"

#: Environment for mpiexec launched by tests: root allowed, more ranks than cores allowed.
# the environment of a test's own mpiexec: without the launcher variables of an outer
# mpiexec (a test tree run under mpiexec -n 2 would otherwise make the child a part of it)
MPI_ENV = dict({k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_", "PRTE_"))},
               OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_rmaps_base_oversubscribe="1")


def small_hairball_config(n_wisps=4, options="", terms=("stretch", "bend", "twist", "gravity",
                                                         "head_collision"), frames=10, **time):
    return SimConfig(
        scene=SceneConfig(kind="hairball", n_wisps=n_wisps, seed=7),
        material=MaterialConfig(youngs_modulus=1.0e9),
        physics=PhysicsConfig(terms=terms, head_motion="shake", head_amplitude=0.3, head_period=0.5),
        time=TimeConfig(frames=frames, **time),
        solver=SolverConfig(options=options))


def jolt_hairball_config(frames=3, **time):
    """3 wisps under a stronger shake (0.5 rad, 1 s), the linear solves tight (comparisons
    to 1e-10 must not depend on where CG stops): the plain count's last increments are
    1.8e-3, 6.1e-3, 5.3e-3 wisp lengths in frames 0-2."""
    cfg = small_hairball_config(n_wisps=3, frames=frames, options="-ksp_rtol 1e-12", **time)
    cfg.scene.seed = 3
    cfg.physics.head_amplitude, cfg.physics.head_period = 0.5, 1.0
    return cfg.validate()


def assert_follows_serial(cfg, X, iterations, ok, msg, comm):
    """On every rank of ``comm``: unless ``ok`` is already False (``msg`` says why), rank 0
    checks that positions X follow the serial run of ``cfg`` within test_mpi_sim's 1e-10
    with the same Newton ``iterations`` per frame; the verdict is broadcast and asserted."""
    ref, ref_summ = serial_reference(cfg)
    if comm.rank == 0 and ok:
        err = rel_diff(X, ref)
        ok = err <= 1e-10 and ref_summ["newton_iterations"] == iterations
        msg = f"{comm.size} ranks: relative difference to 1 rank {err:.3e}, iterations {iterations}"
        print("\n" + msg)
    ok, msg = comm.bcast((ok, msg))
    assert ok, msg


def touching_wisps_source(n_wisps=6, n_vertices=30, spin_step=1.3, n_pinned=4):
    """Six short 4C wisps hanging from a row of roots 0.9 cm apart (coil diameter 1 cm):
    neighbours touch and interleave, so contact pairs form between wisps 1-2 and 3-4,
    which sit on different ranks with 3 ranks (and 2-3 with 2 ranks).  ``spin_step`` 0:
    all coils in phase, translated copies of each other that do not touch at rest.  Used with
    ``touching_wisps_config`` by monkeypatching ``lc_petsc.simulator.source_from_config``."""
    wisps = [geometry.wisp4c(n_vertices, root=(0.9 * w, 16.0, 0.0), spin=spin_step * w)
             for w in range(n_wisps)]
    pos = np.concatenate(wisps)
    off = np.arange(n_wisps + 1) * n_vertices
    pin = np.zeros(len(pos), bool)
    for w in range(n_wisps):
        pin[w * n_vertices: w * n_vertices + n_pinned] = True
    return ArraySource(pos, off, pinned=pin, root_radius=0.08, tip_radius=0.05)


def touching_wisps_config(frames, options="-ksp_rtol 1e-14 -ksp_max_it 5000"):
    """Strand contact on the ``touching_wisps_source`` scene, head shaking.  The default
    tight tolerance: with contact CG takes several iterations, and comparisons to 1e-10
    must not depend on where round-off stops it."""
    return SimConfig(
        scene=SceneConfig(kind="straight"),
        material=MaterialConfig(youngs_modulus=2.0e7),
        physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity", "strand_collision"),
                              head_motion="shake", head_amplitude=0.3, head_period=0.5,
                              strand_thickness=0.12, strand_stiffness=1.0e4),
        time=TimeConfig(frames=frames),
        solver=SolverConfig(options=options))


def run_positions(config, comm=None, frames=None):
    """Run ``config``; positions gathered to rank 0 of ``comm`` (None elsewhere)."""
    sim = build_simulator(config, comm=comm)
    try:
        sim.run(frames)
        X = sim.gather_positions()
        summary = sim.summary()
    finally:
        sim.close()
    return X, summary


def frames_run(sim, frames):
    """Gathered positions (rank 0) at the start and after each of ``frames`` frames, and
    the summary; closes ``sim``."""
    try:
        X = [sim.gather_positions()]
        for _ in range(frames):
            sim.step()
            X.append(sim.gather_positions())
        return X, sim.summary()
    finally:
        sim.close()


def serial_reference(config, frames=None):
    """The same run on COMM_SELF, on rank 0 of COMM_WORLD only (None elsewhere)."""
    if MPI.COMM_WORLD.rank != 0:
        return None, None
    return run_positions(config, comm=MPI.COMM_SELF, frames=frames)


def run_alone(config):
    """(positions, summary, per-vertex rest wisp length) of ``config`` run on this rank
    alone (COMM_SELF)."""
    sim = build_simulator(config, MPI.COMM_SELF)
    try:
        sim.run()
        return sim.integrator.x.copy(), sim.summary(), sim.integrator.wisp_length
    finally:
        sim.close()


def stiff_smash_config(tol, cap=30, fallback="analytic", n_vertices=31):
    """configs/smash.toml cut to ``n_vertices`` vertices with E = 1e12: a stiff coil
    crushed to 40% of its length; one frame of dt 0.2 with exact_or_analytic steps to
    the relative increment ``tol`` within ``cap`` iterations, no cutback (its Newton
    wanders: docs/newton.md "Tight tolerances")."""
    cfg = load_config(CONFIGS / "smash.toml")
    cfg.scene.n_vertices, cfg.material.youngs_modulus = n_vertices, 1e12
    cfg.time.frames, cfg.time.dt, cfg.time.max_substeps = 1, 0.2, 1
    cfg.time.newton_increment_tol, cfg.time.newton_iterations = tol, cap
    cfg.solver.filter, cfg.solver.exact_fallback = "exact_or_analytic", fallback
    return cfg.validate()


def smashed_wisps_config(youngs_modulus, sizes=(51, 41, 31), frames=3, cap=12, tol=1e-3):
    """(source, config): 4C wisps of ``sizes`` vertices (4 pinned) hanging 5 cm apart (no
    contact), smashed to 40% of their length as configs/smash.toml's; stiffness
    ``youngs_modulus``, ``frames`` of dt 0.2 with the analytic filter alone to the relative
    increment ``tol`` within ``cap`` iterations, no cutback: stops after filtered steps,
    checked by an exact step (docs/newton.md "Verifying a stop after filtered steps").
    Use the source by monkeypatching ``lc_petsc.simulator.source_from_config``."""
    wisps = [geometry.wisp4c(n, root=(5.0 * w, 0.0, 0.0)) for w, n in enumerate(sizes)]
    off = np.concatenate([[0], np.cumsum([len(w) for w in wisps])])
    pin = np.zeros(off[-1], bool)
    for w in range(len(wisps)):
        pin[off[w]:off[w] + 4] = True
    source = ArraySource(np.concatenate(wisps), off, pinned=pin, root_radius=0.35, tip_radius=0.07)
    cfg = load_config(CONFIGS / "smash.toml")
    cfg.scene.kind = "straight"             # the source replaces the scene's wisps
    cfg.material.youngs_modulus = youngs_modulus
    cfg.time.frames, cfg.time.dt, cfg.time.max_substeps = frames, 0.2, 1
    cfg.time.newton_increment_tol, cfg.time.newton_iterations = tol, cap
    cfg.solver.filter = "analytic"
    return source, cfg.validate()


def rel_diff(a, b):
    return float(np.abs(a - b).max() / np.abs(b).max())


def hairball_toml(n_wisps=5, seed=3, frames=5, output=""):
    """A small shaking-head hairball scene file (TOML text) for driver tests.

    ``output``: the lines of its ``[output]`` table.
    """
    return f"""
[scene]
kind = "hairball"
n_wisps = {n_wisps}
seed = {seed}
[material]
youngs_modulus = 2.5e8
[physics]
terms = ["stretch", "bend", "twist", "gravity", "head_collision"]
head_motion = "shake"
head_period = 0.4
[time]
frames = {frames}
[output]
{output}
"""


@contextlib.contextmanager
def shared_scene_dir(comm, prefix, scene_text):
    """A temporary folder made by rank 0 with the config ``s.toml`` = ``scene_text``,
    the same on every rank of ``comm``; yields (folder, config path), removed after."""
    d = comm.bcast(tempfile.mkdtemp(prefix=prefix) if comm.rank == 0 else None)
    cfg = os.path.join(d, "s.toml")
    if comm.rank == 0:
        with open(cfg, "w") as f:
            f.write(scene_text)
    comm.Barrier()
    try:
        yield d, cfg
    finally:
        comm.Barrier()
        if comm.rank == 0:
            shutil.rmtree(d, ignore_errors=True)


def chains(rng):
    """Three random polylines (18 vertices, offsets 0 6 11 18) with pinned roots and a
    pinned vertex inside the last one: (x, offsets, free), for the Newton updates' tests."""
    off = np.array([0, 6, 11, 18])
    x = np.cumsum(rng.normal(size=(18, 3)), axis=0)
    free = np.ones(18, bool)
    free[[0, 1, 6, 11, 14]] = False          # roots, and a pinned vertex inside wisp 2
    return x, off, free


def rotate(w, e):
    """e (3,) rotated by the rotation vector w (3,) (Rodrigues)."""
    th = np.linalg.norm(w)
    if th == 0.0:
        return e.copy()
    k = w / th
    return e * np.cos(th) + np.cross(k, e) * np.sin(th) + k * (k @ e) * (1.0 - np.cos(th))


def falling_strand(physics, time, n_pinned=2):
    """A 30-vertex strand (radius 0.05 cm, 0.5 cm edges) falling onto a 5 cm head below
    it, at 3 Newton iterations, 30 frames (``physics``, ``time``: more keys)."""
    return SimConfig(scene=SceneConfig(kind="straight", n_vertices=30, n_pinned=n_pinned, direction=(1, 0, 0),
                                       segment_length=0.5),
                     material=MaterialConfig(youngs_modulus=1e7, root_radius=0.05, tip_radius=0.05),
                     physics=PhysicsConfig(terms=("stretch", "bend", "gravity", "head_collision"),
                                           head_radius=5.0, head_center=(8.0, -5.05, 0.0), head_stiffness=1e5,
                                           **physics),
                     time=TimeConfig(**dict(dict(frames=30, newton_iterations=3), **time)))


def head_figures(sim):
    """Runs ``sim`` (a :func:`falling_strand`) and returns its head figures per frame
    step: (largest depth over strand radius of each frame written, vertex paths through
    the head between frames in all, kinetic energy of the free vertices of each step,
    the last frame's positions)."""
    from lc_petsc.head_check import frame_depths, path_depths
    X, T = [sim.x.copy()], [0.0]
    sim.run(callback=lambda s: (X.append(s.x.copy()), T.append(s.integrator.t)))
    head, sc, dt = sim.integrator.head, sim.scene, sim.config.time.dt
    free = ~sc.pinned
    ratio, through, ke = [], 0, []
    for k in range(len(X) - 1):
        c0, c1 = head.sphere_center(T[k]), head.sphere_center(T[k + 1])
        ratio.append(frame_depths(X[k + 1], c1, head.radius, sc.offsets, sc.pinned, sc.radius)["ratio"])
        through += path_depths(X[k], X[k + 1], c0, c1, head.radius, sc.pinned, sc.radius)["through"]
        v = (X[k + 1] - X[k])[free] / dt
        ke.append(0.5 * float(np.sum(sc.mass[free, None] * v * v)))
    return np.array(ratio), through, np.array(ke), X[-1]


def break_header(path, dataset):
    """Break the object header of ``dataset`` in the HDF5 file at ``path`` (its version
    byte): h5py then raises a KeyError ("bad object header version number") opening it."""
    import h5py
    with h5py.File(path, "r") as f:
        addr = f.userblock_size + h5py.h5o.get_info(f[dataset].id).addr
    with open(path, "r+b") as fh:
        fh.seek(addr)
        fh.write(b"\x07")


#: summary.json's entries whose keys are not figures of their own (the resolved config, the
#: phases, PETSc's option names): README names them as a whole
OPAQUE_SUMMARY_ENTRIES = ("config", "timings_s", "cpu_timings_s", "petsc_options_used",
                          "petsc_options_command_line")


def _summary_keys(value, path=""):
    """Every (key, dotted path) of a summary.json's ``value``, into its records (dicts, and
    the dicts of a list: its items' keys are named like the list's own), the entries of
    :data:`OPAQUE_SUMMARY_ENTRIES` not entered."""
    if isinstance(value, list):
        for v in value:
            yield from _summary_keys(v, path)
    elif isinstance(value, dict) and path not in OPAQUE_SUMMARY_ENTRIES:
        for k, v in value.items():
            dotted = f"{path}.{k}" if path else k
            yield k, dotted
            yield from _summary_keys(v, dotted)


def _outputs_table():
    """The rows of the README's table of the files in an output folder."""
    readme = (CONFIGS.parent / "README.md").read_text()
    rows = readme[readme.index("Outputs in the output folder:"):].split("\n\n")[1]
    return rows.splitlines()


def undocumented_summary_keys(summary):
    """The keys of ``summary`` (a summary.json, parsed) that the README's ``summary.json``
    row of its outputs table does not name in backticks, by name or dotted path (sorted)."""
    row = next(line for line in _outputs_table() if line.startswith("| `summary.json` |"))
    named = set(re.findall(r"`([^`]+)`", row))
    return sorted({dotted for k, dotted in _summary_keys(summary) if k not in named and dotted not in named})


def undocumented_outputs(folder):
    """The names in the output folder ``folder`` (files and folders) that no row of the
    README's outputs table names first (a folder's row names it with its content,
    ``previews/frame_NNNNN.png``)."""
    named = [re.match(r"\| `([^`/]+)", line) for line in _outputs_table()]
    named = {m.group(1) for m in named if m}
    return sorted(q.name for q in Path(folder).iterdir() if q.name not in named)
