"""Newton convergence histories: per frame and iteration, the largest vertex increment
relative to its wisp's length, the relative residual force and the decrease of the
incremental potential G, for variants of one scene side by side (filter, terms, line
search, head contact, initial guess).  Used by ``scripts/newton_history.py``; findings
in docs/newton.md.
"""

from __future__ import annotations

import copy
import time
from typing import Any, Callable
from pathlib import Path

import numpy as np

from lc_petsc.config import without_tolerance_defaults
from lc_petsc.simulator import build_simulator
from lc_petsc.studies import report

_TRUE, _FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


def _flag(value):
    """A variant's on/off value (a word that is neither was read as off)."""
    if value not in _TRUE + _FALSE:
        raise ValueError(f"variant value {value!r}: use one of {', '.join(_TRUE + _FALSE)}")
    return value in _TRUE


#: Variant keys (``key=value`` pairs joined by commas) and the config fields they set.
VARIANT_KEYS: dict[str, tuple[str, str, Callable[[str], Any]]] = {
    "filter": ("solver", "filter", str),
    "fallback": ("solver", "exact_fallback", str),
    "stay": ("solver", "exact_stay", _flag),
    "trust": ("solver", "wisp_trust", _flag),
    "stop": ("time", "newton_stop", str),
    "guess": ("time", "initial_guess", str),
    "carry": ("time", "carry_with_head", _flag),
    "jolt": ("time", "jolt_first_iterate", _flag),
    "update": ("time", "newton_update", str),
    "newton": ("time", "newton", str),
    "ls": ("time", "line_search", _flag),
    "terms": ("physics", "terms", lambda v: tuple(v.split("+"))),
    "options": ("solver", "options", str),
}


def parse_variant(text):
    """``"filter=none,ls=1,terms=stretch+gravity"`` -> {key: value}.  ``head=0`` drops
    head contact, ``strands=0`` strand contact (shortcuts for ``terms``)."""
    out = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, sep, value = part.partition("=")
        if not sep or key not in (*VARIANT_KEYS, "head", "strands"):
            raise ValueError(f"variant part {part!r}: use key=value with key one of "
                             f"{', '.join((*VARIANT_KEYS, 'head', 'strands'))}")
        out[key] = value
    return out


def configure(base_cfg, variant: dict, iterations, frames):
    """A copy of ``base_cfg`` with the variant applied, ``iterations`` Newton iterations
    and no tolerance (every iteration is recorded): a file's tolerance's defaults are
    dropped with it (:func:`without_tolerance_defaults`)."""
    cfg = without_tolerance_defaults(copy.deepcopy(base_cfg))
    cfg.time.frames = frames
    cfg.time.newton_iterations = iterations
    cfg.time.newton_tol = None
    cfg.time.newton_increment_tol = None
    for key, value in variant.items():
        if key in ("head", "strands"):
            term = "head_collision" if key == "head" else "strand_collision"
            if not _flag(value):
                cfg.physics.terms = tuple(t for t in cfg.physics.terms if t != term)
            continue
        section, name, conv = VARIANT_KEYS[key]
        setattr(getattr(cfg, section), name, conv(value))
    return cfg.validate()


def run_history(cfg, comm, log=None):
    """Run ``cfg`` recording every Newton iteration; returns (history rows, wall s)."""
    sim = build_simulator(cfg, comm)
    sim.integrator.history = rows = []
    t0 = time.perf_counter()
    try:
        for f in range(cfg.time.frames):
            sim.step()
            if log is not None:
                last = [r for r in rows if r["frame"] == f]
                log(f"    frame {f}: increment {last[-1]['increment']:.2e} after "
                    f"{len(last)} iterations")
    finally:
        wall = time.perf_counter() - t0
        sim.close()
    return rows, wall


def iterations_to(rows, tol):
    """Per frame, the first iteration (1-based) whose relative increment is below
    ``tol`` (None: never within the recorded iterations).  A trust-region step that was
    rejected or ended on the region's boundary does not count (the integrator's rule)."""
    frames = sorted({r["frame"] for r in rows})
    out = []
    for f in frames:
        its = [r for r in rows if r["frame"] == f]
        hit = [r["iteration"] + 1 for r in its if r["increment"] < tol
               and r.get("exact_rejected") != "rejected" and not r.get("boundary", False)]
        out.append(hit[0] if hit else None)
    return out


def summarize(name, rows, tol, wall):
    """One table row: iterations to ``tol`` (median, worst, frames never reaching it)
    and frame 0's first increments."""
    its = iterations_to(rows, tol)
    reached = [i for i in its if i is not None]
    cap = max(r["iteration"] for r in rows) + 1
    # a frame that never reached tol counts as more than the cap
    full = sorted(i if i is not None else cap + 1 for i in its)
    f0 = [r["increment"] for r in rows if r["frame"] == 0]
    res0 = [r["residual"] for r in rows if r["frame"] == 0]
    return {"variant": name, "frames": len(its), "reached": len(reached),
            "median_iterations": float(np.median(full)) if full else None,
            "worst_iterations": max(full) if full else None,
            "never": len(its) - len(reached), "cap": cap, "wall_s": wall,
            "frame0_increments": [float(v) for v in f0[:12]],
            "frame0_residuals": [float(v) for v in res0[:12]],
            # G went up by more than its round-off
            "energy_increases": int(sum(r["energy_decrease"] < -1e-10 * abs(r["energy"])
                                        for r in rows))}


def plot_histories(histories, path, title, tol):
    """Left: frame 0's relative increment per iteration; right: the median over frames."""
    plt = report._plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for name, rows in histories.items():
        f0 = [r["increment"] for r in rows if r["frame"] == 0]
        axes[0].semilogy(np.arange(1, len(f0) + 1), np.maximum(f0, 1e-17), marker=".", label=name)
        n = max(r["iteration"] for r in rows) + 1
        med = [np.median([r["increment"] for r in rows if r["iteration"] == i]) for i in range(n)]
        axes[1].semilogy(np.arange(1, n + 1), np.maximum(med, 1e-17), marker=".", label=name)
    for ax, t in zip(axes, ("frame 0", "median over frames")):
        ax.axhline(tol, color="k", lw=0.8, ls="--")
        ax.set_xlabel("Newton iteration")
        ax.set_ylabel("largest increment / wisp length")
        ax.set_title(t)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_study(scenes, variants, comm, out_dir, iterations=30, frames=10, tol=1e-6, log=print):
    """For each (scene name, config) and (variant name, spec): record the histories;
    write newton.csv (every iteration), newton.json, newton.md and one plot per scene
    (rank 0).  Returns the summary rows (rank 0; None elsewhere)."""
    out = Path(out_dir)
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    summary, all_rows = [], []
    for scene, base in scenes:
        histories = {}
        for name, spec in variants:
            log(f"{scene}: {name}")
            rows, wall = run_history(configure(base, parse_variant(spec), iterations, frames),
                                     comm, log)
            histories[name] = rows
            s = summarize(name, rows, tol, wall)
            s["scene"] = scene
            s["spec"] = spec
            summary.append(s)
            all_rows += [dict(r, scene=scene, variant=name) for r in rows]
            log(f"  {name}: median {s['median_iterations']}, worst {s['worst_iterations']} "
                f"iterations to {tol:g} ({s['never']} of {s['frames']} frames never), {wall:.1f} s")
        if comm.rank == 0:
            plot_histories(histories, out / f"newton_{scene}.png",
                           f"{scene}: Newton increments ({frames} frames)", tol)
    if comm.rank != 0:
        return None
    report.write_csv(all_rows, out / "newton.csv",
                     ["scene", "variant", "frame", "iteration", "increment", "residual",
                      "energy", "energy_decrease", "alpha", "exact", "ksp_reason", "ksp_iterations"])
    report.write_json({"tol": tol, "iterations": iterations, "frames": frames,
                       "summary": summary}, out / "newton.json")
    (out / "newton.md").write_text(markdown(summary, tol))
    return summary


def markdown(summary, tol):
    """Markdown table of the Newton study's summary rows."""
    head = ["scene", "variant", "median its", "worst its", "frames never", "frame 0 increments 1..6",
            "frame 0 residuals 1..6", "G increased", "wall s"]
    body = [[s["scene"], s["variant"], report.fmt(s["median_iterations"]),
             report.fmt(s["worst_iterations"]), f"{s['never']}/{s['frames']}",
             " ".join(f"{v:.1e}" for v in s["frame0_increments"][:6]),
             " ".join(f"{v:.1e}" for v in s["frame0_residuals"][:6]),
             str(s["energy_increases"]), f"{s['wall_s']:.1f}"] for s in summary]
    return (f"# Newton iterations to a largest increment of {tol:g} wisp lengths\n\n"
            f"(a frame that never gets there counts as cap + 1)\n\n"
            + report.markdown_table(head, body) + "\n")


# ------------------------------------------------------------------ filter rates
class _TermFilter:
    """An element module whose ``gradient_hessian`` uses a fixed filter, whatever the
    assembler asks for."""

    def __init__(self, module, filter):
        self.module, self.filter = module, filter

    def gradient_hessian(self, *args, filter=None, out=None):
        return self.module.gradient_hessian(*args, filter=self.filter, out=out)

    def __getattr__(self, name):
        return getattr(self.module, name)


def dense_newton_matrix(sim, filters):
    """The Newton matrix (M/dt^2 + Hessians) of the integrator's current frame at its
    current positions, dense over the free DoFs (one rank, small scenes), with
    ``filters`` {term: filter} (terms not named: exact).  Needs a simulator built with
    ``-lc_element_kernels numpy``.  Returns (n_free_dofs,)^2."""
    if sim.assembler.kernels != "numpy":
        raise ValueError("dense_newton_matrix swaps the NumPy element kernels: build the "
                         "simulator with -lc_element_kernels numpy")
    from lc_petsc import assembly
    it = sim.integrator
    saved = dict(assembly.KERNELS)
    try:
        for term, module in saved.items():
            assembly.KERNELS[term] = _TermFilter(module, filters.get(term, "none"))
        it._assemble_system(it.x, 0, filter="none")
    finally:
        assembly.KERNELS.clear()
        assembly.KERNELS.update(saved)
    A = it.asm.mat
    rows = np.arange(A.getSize()[0], dtype=np.int32)
    free = np.repeat(it.free, 3)
    return A.getValues(rows, rows)[np.ix_(free, free)]


def iteration_rate(H, Hf):
    """Spectral radius of I - Hf^{-1} H (the linear rate of Newton steps with the matrix
    Hf on a problem with Hessian H; Hf may be indefinite): ARPACK's largest-magnitude
    eigenvalue with one LU of Hf.  H, Hf dense (n, n)."""
    import scipy.linalg
    import scipy.sparse.linalg
    lu = scipy.linalg.lu_factor(Hf)
    n = H.shape[0]
    op = scipy.sparse.linalg.LinearOperator(
        (n, n), matvec=lambda v: v - scipy.linalg.lu_solve(lu, H @ v), dtype=float)
    lam = scipy.sparse.linalg.eigs(op, k=2, which="LM", tol=1e-8, return_eigenvectors=False,
                                   maxiter=20 * n)
    return float(np.abs(lam).max())


def filter_rates(cfg, comm, combos, frames=3, log=print):
    """Per frame (converged with ``exact_or_analytic`` to 1e-12 wisp lengths, cap 60):
    the smallest eigenvalue of the exact Newton matrix and, per combination (name,
    {term: filter}), the linear rate of the filtered Newton iteration at the frame's
    solution: the spectral radius of I - H_f^{-1} H (generalised eigenvalues of
    (H, H_f), :func:`iteration_rate`; H_f may be indefinite when only some terms are
    filtered).  Serial only; rows (dicts)."""
    if comm.size != 1:
        raise ValueError("filter_rates runs on one rank (dense matrices)")
    cfg = copy.deepcopy(cfg)
    cfg.time.frames = frames
    cfg.time.newton_iterations = 60
    cfg.time.newton_increment_tol = 1e-12
    cfg.solver.filter = "exact_or_analytic"
    # dense_newton_matrix swaps the NumPy kernels' filters; the compiled ones would not see it
    cfg.solver.options = (cfg.solver.options + " -lc_element_kernels numpy").strip()
    sim = build_simulator(cfg.validate(), comm)
    rows = []
    try:
        for f in range(frames):
            sim.step()
            it = sim.integrator
            H = dense_newton_matrix(sim, {})
            row = {"frame": f, "iterations": it.newton_iterations[-1],
                   "increment": it.newton_increment[-1],
                   "exact_min_eigenvalue": float(np.linalg.eigvalsh(H)[0]),
                   "mass_dt2_min": float((sim.scene.mass[it.free] / cfg.time.dt ** 2).min())}
            for name, filters in combos:
                row[name] = iteration_rate(H, dense_newton_matrix(sim, filters))
            log(f"  frame {f}: " + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                             for k, v in row.items() if k != "frame"))
            rows.append(row)
    finally:
        sim.close()
    return rows


def degenerate_margins(cfg, comm, frames=10):
    """Over every Newton iterate of ``frames`` frames: the smallest sin(theta) of the bend
    elements and the smallest |a| / |e0| (and |b| / |e2|) of the twist elements that
    have a free vertex, leaving out the twist elements that are exactly degenerate
    (|a| <= 1e-12 |e0|, e.g. on a straight pinned root; ``twist_exactly_degenerate``:
    the most of them in one iterate).  How close the iterates come to the bend cone at
    theta = pi (STRAIGHT_TOL) and the twist element's collinear threshold
    (DEGENERATE_TOL), where the elements' rules switch."""
    from lc_petsc.elements import bend
    sim = build_simulator(configure(cfg, {}, cfg.time.newton_iterations, frames), comm)
    it = sim.integrator
    out = {"bend_min_sin": np.inf, "twist_min_ratio": np.inf, "twist_exactly_degenerate": 0}
    update = it.update

    def measured(x, step, exact=False):
        y = update(x, step, exact)
        for name, t in sim.assembler.padded.items():
            X = t.positions(y)
            keep = (t.stiffness > 0) & it.free[t.index].any(axis=1)
            if name == "bend":
                out["bend_min_sin"] = min(out["bend_min_sin"], float(np.sin(bend.angle(X[keep])).min(initial=np.inf)))
            elif name == "twist":
                X = X[keep]
                e1 = X[:, 2] - X[:, 1]
                ratio = np.full(len(X), np.inf)
                for e in (X[:, 0] - X[:, 1], X[:, 3] - X[:, 2]):
                    a = e - (np.einsum("ij,ij->i", e, e1) / np.einsum("ij,ij->i", e1, e1))[:, None] * e1
                    ratio = np.minimum(ratio, np.linalg.norm(a, axis=1) / np.linalg.norm(e, axis=1))
                zero = ratio <= 1e-12
                out["twist_exactly_degenerate"] = max(out["twist_exactly_degenerate"], int(zero.sum()))
                out["twist_min_ratio"] = min(out["twist_min_ratio"], float(ratio[~zero].min(initial=np.inf)))
        return y

    it.update = measured
    try:
        for _ in range(frames):
            sim.step()
    finally:
        sim.close()
    return out


# ------------------------------------------------------------------ error to the solution
def watch_iterates(it, fn):
    """Call ``fn(x)`` on each frame's first iterate and on every Newton iterate after it:
    wraps the integrator's per-iteration record (``it.history`` must be a list, or the
    record is not called)."""
    record = it._record_iteration

    def keep(k, x_old, x_new, *args):
        out = record(k, x_old, x_new, *args)
        if k == 0:
            fn(x_old)
        fn(x_new)
        return out

    it._record_iteration = keep


def error_history(cfg, comm, frames, iterations=40, wisp=None):
    """Per frame and Newton iteration (``iterations``, no tolerance): the largest distance
    of the iterate to the frame's last iterate (the converged solution when the frame
    converges within ``iterations``: check that the last rows' increments are at
    round-off) relative to the wisp length, and where it sits: the vertex's wisp, its
    index along the wisp and its distance to the head sphere (cm).  With ``wisp`` (a
    wisp index of this rank), also that wisp's per-vertex distances in cm (``profile``).
    Serial only (the iterates are compared vertex by vertex on one rank).  Rows (dicts),
    frame and iteration 0-based; iteration -1 is the first iterate."""
    if comm.size != 1:
        raise ValueError("error_history runs on one rank")
    sim = build_simulator(configure(cfg, {}, iterations, frames), comm)
    it = sim.integrator
    it.history = hist = []
    iterates: list = []
    watch_iterates(it, lambda x: iterates.append(x.copy()))
    off = np.asarray(sim.scene.offsets)
    owner = np.searchsorted(off, np.arange(sim.scene.nv), side="right") - 1
    rows = []
    try:
        for f in range(frames):
            iterates.clear()
            sim.step()
            c, R = sim.head.sphere_center(it.t), sim.head.radius
            x_end = iterates[-1]
            incs = [r["increment"] for r in hist if r["frame"] == f]
            for k, x in enumerate(iterates):
                d = np.linalg.norm(x - x_end, axis=1)
                v = int(np.argmax(d / it.wisp_length))
                row = {"frame": f, "iteration": k - 1, "error": float(d[v] / it.wisp_length[v]),
                       "increment": incs[k - 1] if k > 0 else None, "wisp": int(owner[v]),
                       "vertex": int(v - off[owner[v]]), "head_distance": float(np.linalg.norm(x[v] - c) - R)}
                if wisp is not None:
                    row["profile"] = d[off[wisp]:off[wisp + 1]].tolist()
                rows.append(row)
    finally:
        sim.close()
    return rows
