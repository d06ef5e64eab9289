"""The partition with a groom whose wisps come in any order: ghost fraction, contact and
frame time, for the scene in its generated (spatially ordered) order and as a groom
file with its wisps shuffled, with the wisps partitioned in the file's order
(``-lc_wisp_order input``, the partition before the spatial order existed) and along a
Hilbert curve of their roots (``spatial``, the default).

  mpiexec -n 2 .venv/bin/python scripts/bench_partition.py [--config configs/hairball_demo.toml]
      [--wisps N] [--frames 3] [--out out/bench_partition]

The scene of ``--config`` (default: the 300-wisp demo hairball, strand contact on) is
written as a strands file twice, in its own order and shuffled (seeded); each case runs
``--frames`` frames after a first one (dropped).  Ghost fraction: segments received
from other ranks by the contact broad phase over the segments owned, summed over ranks
(median over the contact passes).  Prints a table (medians; phase times are maxima over
ranks) and writes it with a bar plot to ``--out``.
"""

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

import petsc4py

petsc4py.init(sys.argv)
from mpi4py import MPI  # noqa: E402
import numpy as np  # noqa: E402

from lc_petsc.config import load_config  # noqa: E402
from lc_petsc.scene.sources import source_from_config  # noqa: E402
from lc_petsc.simulator import build_simulator  # noqa: E402
from lc_petsc.studies.command_line import bad_input, check_wisps_flag, integer_at_least, parse_args  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def write_groom(path, batch, perm):
    """Strands file of ``batch``'s wisps in the order ``perm``."""
    import h5py
    off = batch.offsets
    rows = np.concatenate([np.arange(off[w], off[w + 1]) for w in perm])
    sizes = np.diff(off)[perm]
    with h5py.File(path, "w") as f:
        f["positions"] = batch.positions[rows]
        f["radius"] = batch.radius[rows]
        f["pinned"] = batch.pinned[rows]
        f["wisp_offsets"] = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)


def run_case(cfg, frames, comm):
    sim = build_simulator(cfg, comm=comm)
    try:
        sim.step()                                   # first frame: dropped
        walls, coll = [], []
        for _ in range(frames):
            before = sim.timers.as_dict()["collision"]
            comm.Barrier()
            t0 = time.perf_counter()
            sim.step()
            comm.Barrier()
            walls.append(time.perf_counter() - t0)
            coll.append(comm.allreduce(sim.timers.as_dict()["collision"] - before, op=MPI.MAX))
        # ghost segments received per exchange, all ranks: the measured frames' means
        ghosts = np.array(comm.allreduce(np.array(sim.strand.ghosts_received.means()[-frames:])))
        owned = comm.allreduce(len(sim.strand.seg))
        s = sim.summary()
        return {"frame_s": statistics.median(walls), "collision_s": statistics.median(coll),
                "ghost_fraction": float(np.median(ghosts)) / owned,
                "pairs": statistics.median(s["contact"]["pairs_per_frame"][1:]),
                "cross_rank_pairs": int(statistics.median(sim.strand.cross_pairs.means()[-frames:]))}
    finally:
        sim.close()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=str(ROOT / "configs" / "hairball_demo.toml"))
    ap.add_argument("--wisps", type=integer_at_least(1))
    ap.add_argument("--frames", type=integer_at_least(1), default=3)
    ap.add_argument("--out", default="out/bench_partition")
    args = parse_args(ap)
    comm = MPI.COMM_WORLD
    try:
        cfg = load_config(args.config)
        if args.wisps:
            check_wisps_flag(cfg, args.config)
            cfg.scene.n_wisps = args.wisps
        if "strand_collision" not in cfg.physics.terms:
            cfg.physics.terms = tuple(cfg.physics.terms) + ("strand_collision",)
        cfg.validate()
        src = source_from_config(cfg.scene, cfg.material, cfg.physics)
    except (ValueError, OSError) as e:          # ConfigError, SceneError are ValueErrors
        return bad_input(comm, "bench_partition.py", e)
    out = Path(args.out)
    perm = np.random.default_rng(0).permutation(src.n_wisps)
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        batch = src.load(0, src.n_wisps)
        write_groom(out / "ordered.h5", batch, np.arange(src.n_wisps))
        write_groom(out / "shuffled.h5", batch, perm)
    comm.Barrier()
    cases = [("ordered", "input"), ("shuffled", "input"), ("shuffled", "spatial"), ("ordered", "spatial")]
    rows = []
    for groom, order in cases:
        c = dataclasses.replace(cfg, scene=dataclasses.replace(cfg.scene, kind="file",
                                                                path=str(out / f"{groom}.h5")),
                                solver=dataclasses.replace(cfg.solver, options=(
                                    cfg.solver.options + f" -lc_wisp_order {order}").strip()))
        r = run_case(c, args.frames, comm)
        r.update(groom=groom, order=order)
        rows.append(r)
        if comm.rank == 0:
            print(f"{groom:9} {order:8} frame {r['frame_s']:.3f} s, collision {r['collision_s']:.3f} s, "
                  f"ghost fraction {r['ghost_fraction']:.3f}", flush=True)
    if comm.rank != 0:
        return 0
    head = ("| groom | -lc_wisp_order | frame s | collision s | ghost fraction | pairs | "
            "cross-rank pairs |\n|---|---|---|---|---|---|---|")
    lines = [head] + [f"| {r['groom']} | {r['order']} | {r['frame_s']:.3f} | {r['collision_s']:.3f} | "
                      f"{r['ghost_fraction']:.3f} | {r['pairs']:.0f} | {r['cross_rank_pairs']} |"
                      for r in rows]
    table = (f"{src.n_wisps} wisps, {comm.size} ranks, {args.frames} frames after the first "
             f"(medians)\n\n" + "\n".join(lines))
    print("\n" + table)
    (out / "partition.md").write_text(table + "\n")
    (out / "partition.json").write_text(json.dumps(rows, indent=2))
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.2))
    labels = [f"{r['groom']}\n{r['order']}" for r in rows]
    for ax, key, title in zip(axes, ("ghost_fraction", "collision_s", "frame_s"),
                              ("ghost fraction", "collision s / frame", "frame s")):
        ax.bar(labels, [r[key] for r in rows], color=["C0", "C3", "C2", "C1"])
        ax.set_title(title)
        ax.tick_params(axis="x", labelsize=8)
    fig.suptitle(f"partition of a shuffled groom, {src.n_wisps} wisps, {comm.size} ranks")
    fig.tight_layout()
    fig.savefig(out / "partition.png", dpi=120)
    print(f"wrote {out / 'partition.md'}, {out / 'partition.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
