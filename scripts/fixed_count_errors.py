"""Where a fixed Newton count's error lives: per frame, one step of each variant from the
converged reference's state against the reference's next state (the local error), split
by position along the wisp and by the coarse rigid motion that explains it best; and each
variant's trajectory started from the reference's state after K frames (docs/newton.md,
"Twenty-first round").  One rank; the scenes and the reference of drivers/tradeoff.py.

  .venv/bin/python scripts/fixed_count_errors.py [--scene hairball10|demo10|smash]
      [--frames 30] [--from K] [--out out/fixed_count_errors.json] NAME=SPEC ...

SPEC: ``default`` (the study's base: the code's defaults, demo10 its config's), or
key=value pairs joined by ``+`` of the study's settings (lc_petsc.studies.tradeoff.Settings,
e.g. ``root_rotation=true+newton_iterations=2``); with ``--from K`` a ``@SPEC2`` after it
runs the first K frames with SPEC2 instead of the reference (e.g. a converging setting).
Errors are relative to the mean wisp length, as the study's ``rms_rel_error``.
"""

import argparse
import importlib.util
import json
import sys
from dataclasses import fields, replace
from pathlib import Path

import petsc4py

petsc4py.init(sys.argv[:1])
import numpy as np  # noqa: E402
from mpi4py import MPI  # noqa: E402

from lc_petsc.studies.coarse_fit import MOTIONS, explained  # noqa: E402
from lc_petsc.studies.command_line import bad_input, integer_at_least  # noqa: E402
from lc_petsc.studies.measures import wisp_lengths  # noqa: E402
from lc_petsc.studies.tradeoff import BASE, Settings, configure, configured_settings, reference_settings  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SCENES = ("hairball10", "demo10", "smash")


def scene(name):
    """(config, the study's base settings) of a scene of :data:`SCENES`."""
    spec = importlib.util.spec_from_file_location("tradeoff_driver", ROOT / "drivers" / "tradeoff.py")
    driver = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(driver)
    if name == "hairball10":
        return driver.scene_config("hairball", 10), BASE
    if name == "demo10":
        cfg = driver.scene_config(str(ROOT / "configs" / "hairball_demo.toml"), 10)
        return cfg, configured_settings(cfg)
    if name == "smash":
        return driver.scene_config("smash", None), BASE
    raise ValueError(f"--scene {name!r}: use one of {', '.join(SCENES)}")


def settings(base, spec):
    """The :class:`Settings` of a SPEC (see the module's doc)."""
    if spec == "default":
        return base
    known = [f.name for f in fields(Settings)]
    changes = {}
    for part in spec.split("+"):
        key, eq, value = part.partition("=")
        if not eq or key not in known:
            raise ValueError(f"variant part {part!r}: use key=value with key one of {', '.join(known)}")
        default = getattr(BASE, key)
        if isinstance(default, bool):
            if value.lower() not in ("true", "false"):
                raise ValueError(f"variant part {part!r}: {key} is true or false")
            changes[key] = value.lower() == "true"
        elif value.lower() == "none":
            changes[key] = None
        else:
            kind = float if default is None else type(default)
            try:
                changes[key] = kind(value)
            except ValueError:
                raise ValueError(f"variant part {part!r}: {value!r} is not a {kind.__name__}") from None
    return replace(base, **changes)


def scene_variants(name, specs):
    """(config, {NAME: Settings}) of a ``--scene`` and NAME=SPEC arguments (scripts/setting_cost.py,
    scripts/setting_frames.py); ValueError naming a bad one."""
    if name not in SCENES:
        raise ValueError(f"--scene {name!r}: use one of {', '.join(SCENES)}")
    cfg, base = scene(name)
    variants = {}
    for v in specs:
        label, eq, spec = v.partition("=")
        if not eq:
            raise ValueError(f"{v!r}: give NAME=SPEC")
        variants[label] = settings(base, spec)
    return cfg, variants


def simulator(cfg, s, frames):
    from lc_petsc.simulator import build_simulator
    c = configure(cfg, s, frames * s.dt)
    return build_simulator(c, MPI.COMM_SELF)


def study(name, variants, frames, start=None):
    """{label: {"local": per frame local RMS, "split": the local errors' summed squares
    (:func:`explained`, summed over frames), "frame0_share"; with ``start`` (K):
    "from_K": the trajectory RMS over frames 1..frames started from the reference (or
    its first-frames variant) after K frames}."""
    cfg, base = scene(name)
    ref = simulator(cfg, reference_settings(dt=base.dt), frames)
    sc = ref.integrator.scene
    L = float(np.mean(wisp_lengths(sc.x_rest, sc.offsets)))
    runs = {}
    for label, (spec, first) in variants.items():
        runs[label] = [simulator(cfg, settings(base, spec), frames),          # local steps
                       simulator(cfg, settings(base, spec), frames) if start is not None else None,
                       simulator(cfg, settings(base, first), frames) if first else None]
    out = {label: {"local": [], "split": None, "from": []} for label in variants}
    for f in range(frames):
        it = ref.integrator
        x0, v0, t0 = it.x.copy(), it.v.copy(), it.t
        if f == start:
            for label, (_, traj, first) in runs.items():
                src = first.integrator if first is not None else it
                traj.integrator.x, traj.integrator.v = src.x.copy(), src.v.copy()
                traj.integrator.t, traj.integrator.frame = src.t, f
        ref.step()
        for label, (local, traj, first) in runs.items():
            li = local.integrator
            li.x, li.v, li.t, li.frame = x0.copy(), v0.copy(), t0, f
            local.step()
            split = explained(li.x, it.x, sc.offsets, sc.pinned)
            o = out[label]
            o["local"].append(float(np.sqrt(np.mean(np.sum((li.x - it.x) ** 2, axis=1)))) / L)
            o["split"] = split if o["split"] is None else {k: o["split"][k] + v for k, v in split.items()}
            if f == 0:
                o["frame0"] = split["total"]
            if start is None:
                continue
            stepped = traj if f >= start else first
            if stepped is not None:
                stepped.step()
            o["from"].append(0.0 if stepped is None else float(np.mean(np.sum((stepped.x - it.x) ** 2, axis=1))))
    for o in out.values():
        o["frame0_share"] = o.pop("frame0") / o["split"]["total"]
        o["local_rms"] = float(np.sqrt(np.mean(np.square(o["local"]))))
        o["from_rms"] = float(np.sqrt(np.mean(o.pop("from")))) / L if start is not None else None
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="hairball10")
    p.add_argument("--frames", type=integer_at_least(1), default=30)
    p.add_argument("--from", dest="start", type=integer_at_least(0),
                   help="trajectories from the reference after K frames")
    p.add_argument("--out", default="out/fixed_count_errors.json")
    p.add_argument("variants", nargs="+", metavar="NAME=SPEC")
    a = p.parse_args(argv)
    try:
        if a.scene not in SCENES:
            raise ValueError(f"--scene {a.scene!r}: use one of {', '.join(SCENES)}")
        if a.start is not None and a.start >= a.frames:
            # no trajectory would start: its RMS came out 0.0, a perfect setting
            raise ValueError(f"--from {a.start} is not below --frames {a.frames}: no frame would run from the "
                             f"reference's state; give --from 0 to {a.frames - 1}")
        variants = {}
        for v in a.variants:
            label, eq, spec = v.partition("=")
            if not eq:
                raise ValueError(f"{v!r}: give NAME=SPEC")
            spec, _, first = spec.partition("@")
            if first and a.start is None:
                raise ValueError(f"{v!r}: @SPEC2 sets the first frames of --from K: give --from")
            _, base = scene(a.scene)
            settings(base, spec), first and settings(base, first)          # checked before running
            variants[label] = (spec, first)
    except ValueError as e:                     # ConfigError is a ValueError
        return bad_input(MPI.COMM_WORLD, "fixed_count_errors.py", e)
    out = study(a.scene, variants, a.frames, a.start)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out))
    for label, o in out.items():
        s = o["split"]
        print(f"{label}: local RMS {o['local_rms']:.3e} (frame 0: {o['frame0_share']:.2f} of its square)"
              + ("" if o["from_rms"] is None else f"; trajectory from frame {a.start}: RMS {o['from_rms']:.3e}"))
        print("   thirds root/middle/tip " + " ".join(f"{s[k] / s['total']:.2f}" for k in
                                                     ("root third", "middle third", "tip third"))
              + "; left after the best " + ", ".join(f"{m[0]} {s[m[0]] / s['total']:.3f}" for m in MOTIONS))
        print("   per frame " + " ".join(f"{e:.1e}" for e in o["local"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
