"""Speed versus accuracy: what fewer Newton iterations, looser Krylov
tolerances, bigger steps, a cheaper filter or a line search cost in accuracy.

  mpiexec -n P python drivers/tradeoff.py [--scene hairball|smash|jitter|CONFIG.toml]
      [--wisps 10] [--duration 1.0] [--axes newton ksp_rtol dt filter line_search newton_update
      cutback trust_region corotational carry_with_head root_rotation newton_extend wisp_trust]
      [--ref-dt 0.008333] [--ref-tol 1e-9] [--ref converged|base]
      [--ref-method exact_or_analytic|unfiltered] [--rtols 1e-2 1e-4 ...]
      [--set NAME] [--cost wall_per_sim_s|cpu_per_sim_s] [--no-ref-check] [--out out/tradeoff]
      [PETSc options ...]

A reference trajectory (Newton to max|dx| < --ref-tol cm, at most 100 iterations, with
the exact Hessian near the solution, the analytic filter otherwise and the edge
retraction (--ref-method exact_or_analytic, docs/newton.md), or the unfiltered Hessian
with the line search and GMRES (--ref-method unfiltered); falling back to the analytic
filter if that fails; Krylov rtol 1e-12; dt = --ref-dt, default 1/120) and variants
along each axis (Newton iterations 1, 2, 3, 6, 12; ksp rtol 1e-2 .. 1e-10; dt 1/30,
1/60, 1/120; filter analytic, numerical, none; line search on; newton_update: linear
and edge retraction at 2, 3, 4, 6 iterations, the follow-the-leader guess, the
retraction with the final positions projected onto the rest lengths at 2 and 3, and
exact_or_analytic to increments of 1e-3, 1e-4, 1e-6 wisp lengths with a cap of 30;
cutback: exact_or_analytic to 1e-3 and 1e-6 with a cap of 30 without step cutback
(time.max_substeps = 1), 30 and 10 with it (8); trust_region: time.newton =
"trust_region" against exact_or_analytic to 1e-3 and 1e-6 with a cap of 30, and the
trust region at 2, 3, 4 iterations; root_rotation: 2, 3, 4 iterations with and without
the root turn (time.root_rotation), inertial and follow-the-leader first iterates, and
the paper's setting (linear update, uncarried) with each; newton_extend: the fixed count
extended on frames whose last increment is above 3e-2, 1e-2, 3e-3 wisp lengths
(time.newton_extend_above, cap 12) with and without the root turn; wisp_trust: the recommended
path (exact_or_analytic, corotational, shifted fallback, exact_stay, cap 30) to 1e-3 and
1e-6 with and without solver.wisp_trust),
all from the base setting dt 1/30, 3 Newton iterations, rtol 1e-6, analytic filter, no
line search, the config's default Newton update.  Positions and energies are
compared at the common output times (every 1/30 s).  ``--set NAME`` runs every
variant with the solver set configs/solvers/NAME.opts (the reference keeps the default
exact per-wisp solver).  ``--ref base`` replaces the reference with the base setting
with Krylov rtol 1e-10, for scenes too large for a converged reference (e.g.
configs/hairball_2k.toml with strand contact): errors then measure only the Krylov
tolerance's share (use with ``--axes ksp_rtol``; ``--rtols`` picks its values).
The reference is checked against a tighter one (a converged reference at half its dt,
``--ref base`` at a 100x tighter Krylov tolerance; ``--no-ref-check`` skips it): their
distance, the reference's own error, is reported, drawn in the plot, and targets at or
below it are not judged ("below the reference's own error").

Outputs in --out: tradeoff.csv, tradeoff.json, pareto.png (cost vs RMS error, front
highlighted, unstable variants listed), recommendations.md.  Each run (the reference
too) reports its frames cut back into substeps (``newton_cut_back_frames``): those are
not solutions of the run's own dt.  Unstable variants (NaN,
failed solves, blow-up) are rows with status "unstable", the failure kind, frame and
message: the study never stops for them.  A variant the scene refuses (its config's
ConfigError, e.g. the trust region with strand contact) is a row of status
"unsupported", never run; a setting listed on several axes runs once (``same_as``).
With ``--scene CONFIG.toml`` the file's own [time] and [solver] choices are a row of their
own ("as configured"; the base runs the code's defaults).
The recommendations take the cheapest by a modelled cost, the same in every run: Newton
plus Krylov iterations per simulated second priced per group of settings (filter, Newton
method, line search, solver set) by the group's median measured cost; modelled costs
within 25% of the lowest go to the lower error (lc_petsc/studies/cost_model.py).
A variant whose edges stretch by more than ``--max-strain`` (10%) is listed but not
recommended, whatever its error: drawn-out curls, a wrong stretch energy.  A Newton
tolerance that saves less than 10% of the Newton iterations of the same setting at a
tighter tolerance reaching the same target is not recommended either: the tighter one is
(since loose stops must agree with their model, 1e-3 can cost what 1e-6 costs).
A variant converged in every frame at the reference's dt is named when its error is not
Newton's: frames split into other substeps than the reference's (its error there is the
time step's; the demo cut to 10 wisps, uncarried, to 1e-6: frame 0 in 3 substeps against
2, 1.7e-3 away), or farther than its tolerance with the same splits (a step reached
another of its solutions); column "not_newtons_error" (docs/newton.md).
"""

import argparse
import shlex
import sys
from dataclasses import replace
from pathlib import Path

import petsc4py

petsc4py.init(sys.argv)
from mpi4py import MPI  # noqa: E402

from lc_petsc.config import (MaterialConfig, PhysicsConfig, SceneConfig, SimConfig,  # noqa: E402
                             load_config)
from lc_petsc.studies.command_line import (bad_input, check_wisps_flag, integer_at_least,  # noqa: E402
                                           parse_args, positive_number)
from lc_petsc.studies.systems import option_sets  # noqa: E402
from lc_petsc.studies.tradeoff import (BASE, KSP_RTOLS, MAX_STRAIN, base_reference,  # noqa: E402
                                       configured_settings, default_variants, reference_settings, run_study)

ROOT = Path(__file__).resolve().parent.parent


def scene_config(scene, wisps=20):
    """Built-in study scenes: a small shaking hairball, the Smash and Jitter wisps."""
    if scene == "hairball":
        return SimConfig(scene=SceneConfig(kind="hairball", n_wisps=wisps, seed=3),
                         material=MaterialConfig(youngs_modulus=1.0e9),
                         physics=PhysicsConfig(terms=("stretch", "bend", "twist", "gravity", "head_collision"),
                                               head_motion="shake", head_amplitude=0.5, head_period=1.0))
    if scene in ("smash", "jitter"):
        if wisps is not None:           # one wisp: --wisps used to be ignored silently
            raise ValueError(f"--wisps sets the hairball's wisp count; --scene {scene} is one wisp: "
                             "leave out --wisps")
        return SimConfig(scene=SceneConfig(kind="wisp4c", perturbation=scene, smash_factor=0.4),
                         material=MaterialConfig(youngs_modulus=3.9e9),
                         physics=PhysicsConfig(terms=("stretch", "bend", "twist")))
    if not Path(scene).exists():
        raise ValueError(f"--scene {scene!r}: not a built-in scene (hairball, smash, jitter) and "
                         "no such config file")
    cfg = load_config(scene)
    if wisps is not None:
        check_wisps_flag(cfg, scene)    # a groom or single-wisp config: it was ignored silently
        cfg.scene.n_wisps = wisps       # e.g. the demo hairball cut to a study size
    return cfg


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="hairball")
    ap.add_argument("--wisps", type=integer_at_least(1), default=None,
                    help="wisps of the built-in hairball (default 10) or of a hairball CONFIG.toml "
                         "(default: its own count)")
    ap.add_argument("--duration", type=positive_number, default=1.0, help="simulated seconds")
    ap.add_argument("--axes", nargs="+", default=None,
                    choices=["newton", "ksp_rtol", "dt", "filter", "line_search", "newton_update", "cutback",
                             "trust_region", "corotational", "carry_with_head", "root_rotation",
                             "newton_extend", "wisp_trust"])
    ap.add_argument("--ref-dt", type=positive_number, default=1.0 / 120.0)
    ap.add_argument("--ref-tol", type=positive_number, default=1e-9)
    ap.add_argument("--ref", default="converged", choices=["converged", "base"],
                    help="converged: Newton to --ref-tol at --ref-dt; base: the base setting "
                         "with Krylov rtol 1e-10")
    ap.add_argument("--ref-method", default="exact_or_analytic",
                    choices=["exact_or_analytic", "unfiltered"],
                    help="converged reference: the exact-or-analytic Hessian with the edge "
                         "retraction (docs/newton.md), or the unfiltered Hessian with the line "
                         "search and GMRES (the reference before)")
    ap.add_argument("--no-ref-check", action="store_true",
                    help="skip the reference's check (a converged reference at half its dt, a base "
                         "one at a 100x tighter Krylov tolerance), which measures the reference's own "
                         "error and leaves the targets below it unjudged")
    ap.add_argument("--rtols", type=positive_number, nargs="+", default=list(KSP_RTOLS),
                    help="Krylov tolerances of the ksp_rtol axis")
    ap.add_argument("--set", default=None, help="solver set of configs/solvers for every run")
    ap.add_argument("--blowup", type=positive_number, default=5.0)
    ap.add_argument("--cost", default="wall_per_sim_s", choices=["wall_per_sim_s", "cpu_per_sim_s"],
                    help="cost axis of the Pareto plot and the recommendations")
    ap.add_argument("--max-strain", type=positive_number, default=MAX_STRAIN,
                    help="largest edge strain of a recommended variant (default %(default)g: 10%%; "
                         "a variant stretched more is listed, not recommended)")
    ap.add_argument("--out", default="out/tradeoff")
    args = parse_args(ap, argv)
    comm = MPI.COMM_WORLD
    if args.wisps is None and args.scene == "hairball":
        args.wisps = 10
    try:
        cfg = scene_config(args.scene, args.wisps)
        opts = option_sets(ROOT / "configs" / "solvers", [args.set])[args.set] if args.set else ""
    except (ValueError, OSError) as e:          # ConfigError is a ValueError
        return bad_input(comm, "tradeoff.py", e)
    base = replace(BASE, options=opts)
    # the default exact solver, whatever --set
    ref = (reference_settings(args.ref_dt, args.ref_tol, method=args.ref_method)
           if args.ref == "converged" else base_reference())
    log = print if comm.rank == 0 else (lambda *a, **k: None)
    cmd = f"mpiexec -n {comm.size} python " + " ".join(shlex.quote(a) for a in sys.argv)
    # a config file's own settings are a row ("as configured"); the built-in scenes run the defaults
    configured = configured_settings(cfg, opts) if Path(args.scene).exists() else None
    run_study(cfg, default_variants(base, args.axes, args.rtols, configured), comm, args.out,
              duration=args.duration,
              ref=ref, blowup=args.blowup, cost=args.cost, ref_check=not args.no_ref_check,
              max_strain=args.max_strain,
              log=lambda *a: (log(*a), sys.stdout.flush()),
              meta={"command": cmd, "scene": args.scene if args.scene != "hairball"
                    else f"hairball {args.wisps} wisps", "solver_set": args.set})
    if comm.rank == 0:
        print((Path(args.out) / "recommendations.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
