"""Newton convergence histories on the demo hairball (10 wisps, no strand contact) and
smash, variants side by side (docs/newton.md).

  .venv/bin/python scripts/newton_history.py [--scenes hairball10 smash] [--frames 10]
      [--iterations 30] [--tol 1e-6] [--variant NAME=SPEC ...] [--wisps 10] [--dt DT]
      [--out out/newton]

SPEC: comma-separated key=value: filter=analytic|numerical|none|abs|exact_or_analytic,
update=linear|edge_retraction|corotational, guess=inertial|follow_the_leader, ls=0|1 (line search),
terms=stretch+gravity, head=0 (no head contact), strands=0, options=-ksp_type gmres,
fallback=analytic|shifted, stay=0|1 (solver.exact_stay), trust=0|1 (solver.wisp_trust),
stop=quadratic_estimate|chord_estimate
(time.newton_stop; needs a tolerance: scripts/newton_frames.py only).
hairball10 is configs/hairball_demo.toml cut to 10 wisps (--wisps) without strand
contact (head contact and the shaking head kept; the inertial first iterate), demo10 the
same with strand contact (the demo's ccd mode and follow-the-leader first iterate);
smash is configs/smash.toml.
Outputs in --out: newton.csv (every iteration), newton.json, newton.md (table),
newton_<scene>.png (increment per iteration: frame 0 and the median over frames).
"""

import argparse
import sys
from pathlib import Path

import petsc4py

petsc4py.init(sys.argv[:1])
from mpi4py import MPI  # noqa: E402

from lc_petsc.config import load_config  # noqa: E402
from lc_petsc.errors import ConfigError  # noqa: E402
from lc_petsc.studies.command_line import bad_input, integer_at_least, positive_number  # noqa: E402
from lc_petsc.studies.newton import configure, parse_variant, run_study  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent

DEFAULT_VARIANTS = [
    "paper (analytic, linear)=filter=analytic,update=linear",
    "analytic, linear, LS=filter=analytic,update=linear,ls=1",
    "stretch+gravity only=filter=analytic,update=linear,terms=stretch+gravity",
    "no twist=filter=analytic,update=linear,terms=stretch+bend+gravity+head_collision",
    "no head contact=filter=analytic,update=linear,head=0",
    "numerical, linear=filter=numerical,update=linear",
    "abs, linear=filter=abs,update=linear",
    "exact + LS (GMRES), linear=filter=none,update=linear,ls=1,options=-ksp_type gmres",
    "analytic, linear, FTL guess=filter=analytic,update=linear,guess=follow_the_leader",
    "exact_or_analytic, linear=filter=exact_or_analytic,update=linear",
    "analytic, retraction (default)=filter=analytic,update=edge_retraction",
    "abs, retraction=filter=abs,update=edge_retraction",
    "exact_or_analytic, retraction=filter=exact_or_analytic,update=edge_retraction",
]


#: the scenes :func:`scene` knows by name (anything else is a config file)
SCENES = ("hairball10", "demo10", "smash")


def scene(name, wisps=10):
    """The base config of ``name``: one of :data:`SCENES` or a config file (a ConfigError
    names a name that is neither)."""
    if name in ("hairball10", "demo10"):
        cfg = load_config(ROOT / "configs" / "hairball_demo.toml")
        cfg.scene.n_wisps = wisps
        # the demo projects onto the rest lengths for its ccd contact; the studies
        # (docs/newton.md) measured Newton's own iterate
        cfg.time.length_projection = False
        if name == "hairball10":
            cfg.physics.terms = tuple(t for t in cfg.physics.terms if t != "strand_collision")
            # the demo sets follow_the_leader for its ccd contact; without strand contact
            # the studies (docs/newton.md) measured the inertial first iterate
            cfg.time.initial_guess = "inertial"
        return cfg
    if name == "smash":
        return load_config(ROOT / "configs" / "smash.toml")
    if not Path(name).exists():
        raise ConfigError(f"{name!r}: not a built-in scene ({', '.join(SCENES)}) and no such config file")
    return load_config(name)


def named_variants(texts):
    """``--variant NAME=SPEC`` arguments as (name, spec) pairs; a ValueError names a
    malformed one."""
    out = []
    for text in texts:
        name, sep, spec = text.partition("=")
        if not sep or not name:
            raise ValueError(f"--variant {text!r}: use NAME=SPEC, e.g. 'mine=filter=analytic,ls=1'")
        out.append((name, spec))
    return out


def check_variants(scenes, variants, iterations, frames):
    """Apply every (name, spec) of ``variants`` to every config of ``scenes`` (cheap: no
    simulator) so that a bad spec is reported before anything runs; a ValueError names
    the variant and what is wrong."""
    for name, spec in variants:
        for _, cfg in scenes:
            try:
                configure(cfg, parse_variant(spec), iterations, frames)
            except ValueError as e:
                raise type(e)(f"--variant {name}={spec}: {e}") from None


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", default=["hairball10", "smash"])
    p.add_argument("--frames", type=integer_at_least(1), default=10)
    p.add_argument("--iterations", type=integer_at_least(1), default=30)
    p.add_argument("--tol", type=positive_number, default=1e-6)
    p.add_argument("--variant", action="append", help="NAME=SPEC (repeatable)")
    p.add_argument("--wisps", type=integer_at_least(1), default=10, help="wisps of hairball10 (default 10)")
    p.add_argument("--dt", type=positive_number, help="time step (s) instead of the scenes' own")
    p.add_argument("--out", default="out/newton")
    a = p.parse_args(argv)
    comm = MPI.COMM_WORLD
    try:
        variants = named_variants(a.variant or DEFAULT_VARIANTS)
        scenes = [(Path(s).stem, scene(s, a.wisps)) for s in a.scenes]
        if a.dt is not None:
            for _, cfg in scenes:
                cfg.time.dt = a.dt
        check_variants(scenes, variants, a.iterations, a.frames)
    except (ValueError, OSError) as e:          # ConfigError is a ValueError
        return bad_input(comm, "newton_history.py", e)
    log = print if comm.rank == 0 else (lambda *_: None)
    run_study(scenes, variants, comm, a.out, a.iterations, a.frames, a.tol, log)
    if comm.rank == 0:
        print((Path(a.out) / "newton.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
