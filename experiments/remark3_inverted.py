"""Remark 3 inverted: which requirement set or effort weight makes the paper's AFONFTSMC
gains (near) stationary, and does tuning from the naive start to it land near them?

    python -m experiments.remark3_inverted [--out results/remark3_inverted]
        [--scenario 1] [--horizon 20] [--rotor-limited] [--outer-steps 10]
        [--inner-steps 10] [--learning-rate 0.1] [--update-doc] [--tiny]

Setting: the nominal run of scenario ``--scenario`` (random drag off: one deterministic
run), ``--horizon`` s, float64, ``tanh`` switching at the paper's boundary layers (the
tuners' law), ideal actuators unless ``--rotor-limited``; the tuner's 33 unconstrained
parameters ``u`` (log or logit of each gain, ``share="paper"``). Quantities: the cost
terms ``P``, ``A``, ``E``, ``C`` (:mod:`fojax.optimize.cost`) and every metric of
:data:`fojax.requirements.METRICS`, with their Jacobian in ``u`` (reverse mode, checked
against a central finite difference), all from :class:`fojax.optimize.Objective`: one
objective minimising ``E`` under a bound of 0 on every metric (its outputs: ``E`` and
each metric over its scale), one reverse pass per row; ``C``'s row from an objective of
the cost ``C`` alone; ``P = T position_rmse^2`` and ``A = T attitude_rmse^2`` (the same
sums in the cost's and the metrics' observers, ``T`` the horizon), so their rows are the
metrics'.

Stationarity. With bounds ``g_j <= b_j = g_j(x_p)`` (met with equality by the paper's
gains ``x_p``), ``x_p`` is a KKT point of ``min f s.t. g_j <= b_j, j in S`` exactly
when ``grad f + sum_j lam_j grad g_j = 0`` with ``lam_j >= 0`` (and the weighted sum
``f + sum_j w_j g_j`` is stationary with ``w = lam``). :func:`cone_residual`::

    r(S) = min_{lam >= 0} |grad f + sum_{j in S} lam_j grad g_j| / |grad f|

is 0 where ``x_p`` is stationary, 1 where no bound in ``S`` opposes ``grad f``.
Objectives: ``tracking`` (``P + A``; candidates ``E``, ``C`` and the metrics that are
not functions of ``P`` or ``A``) and ``effort`` (``E``; every metric a candidate): the
best set of each size up to 3 and all candidates together (its active set is the
requirement set found); ``P + A + w_E E`` over ``w_E``; the same at the naive start and
at the tuned gains (the reference of what a tuned point reaches).

Tuning to the requirements found for ``effort`` (:func:`requirements_found`), objective
effort, by the engine (:class:`fojax.optimize.strategies.AugmentedLagrangian` around Adam,
``--outer-steps`` x ``--inner-steps`` steps on the run, margin 0; its answer validated on
the run after every outer step, the best returned): from the naive start (does it land near the
paper's gains, field by field?) and from the paper's gains (does the tuner stay there:
a local minimum, or only a stationary point?).

The tunings are kept in ``--out/tuned`` (a run started again reuses them). Writes
``results.json``, ``table.md`` and ``remark3_inverted.png`` to ``--out``;
``--update-doc`` replaces the block ``remark3-inverted`` of docs/requirements.md and
copies the figure to docs/.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from experiments import _common
from experiments import remark3 as remark3_study
from experiments.remark3 import timed
from experiments.remark3_inverted_report import SURROGATES, figure, table
from fojax.cli import output

__all__ = ["best_subsets", "cone_residual", "main"]

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "requirements.md"
EXAMPLE = ROOT / "examples" / "requirements" / "small_quadrotor.toml"
COST_TERMS = ("P", "A", "E", "C")
TRACKING_FUNCTIONS = ("P", "A", "position_rmse", "attitude_rmse")
"""Quantities that are functions of ``P`` or ``A`` (not candidates for ``tracking``)."""
WEIGHTS = np.logspace(-9, -2, 43)
"""The effort weights ``w_E`` of the sweep."""
ACTIVE = 1e-9
"""A multiplier (on unit-norm gradients) above this counts as active."""
BOUND_TOLERANCE = 1e-6
"""Relative slack of a bound set at the paper's value: the evaluation program rounds
the metric differently in the last digits."""


# ------------------------------------------------------------------ the cone residual


def nnls(A, b) -> tuple[np.ndarray, float]:
    """``(x, |A x - b|)`` with ``x = argmin_{x >= 0} |A x - b|`` (``A`` ``(m, n)``):
    Lawson and Hanson's active-set method (Solving Least Squares Problems, 1974, ch. 23),
    as SciPy's ``nnls``: move the coordinate of the largest gradient ``A^T (b - A x)``
    into the passive set, solve the least squares on it, and step back to the boundary
    while a passive coordinate would turn non-positive."""
    A, b = np.asarray(A, np.float64), np.asarray(b, np.float64)
    n = A.shape[1]
    x, passive = np.zeros(n), np.zeros(n, bool)
    tolerance = 10 * max(A.shape) * np.finfo(np.float64).eps * max(np.abs(A).sum(0).max(), 1)
    for _ in range(3 * n):
        w = A.T @ (b - A @ x)
        if passive.all() or np.max(np.where(passive, -np.inf, w)) <= tolerance:
            break
        passive[np.argmax(np.where(passive, -np.inf, w))] = True
        while True:
            z = np.zeros(n)
            z[passive] = np.linalg.lstsq(A[:, passive], b, rcond=None)[0]
            if np.all(z[passive] > 0):
                x = z
                break
            blocking = passive & (z <= 0)
            alpha = np.min(x[blocking] / (x[blocking] - z[blocking]))
            x = x + alpha * (z - x)
            passive &= x > tolerance
            x[~passive] = 0.0
    return x, float(np.linalg.norm(A @ x - b))


def cone_residual(gradient, candidates) -> tuple[float, np.ndarray]:
    """``(r, lam)``: ``r = min_{lam >= 0} |gradient + candidates.T lam| / |gradient|``
    and the minimiser ``lam`` ``(k,)`` (``candidates`` ``(k, n)``: one gradient per
    row; ``r = 1`` without candidates). Solved by non-negative least squares on
    unit-norm rows; ``lam`` is scaled back to the rows as given."""
    gradient = np.asarray(gradient, np.float64)
    candidates = np.asarray(candidates, np.float64).reshape(-1, gradient.size)
    size = np.linalg.norm(gradient)
    if size == 0:
        return 0.0, np.zeros(len(candidates))
    if not (np.all(np.isfinite(gradient)) and np.all(np.isfinite(candidates))):
        raise ValueError("cone_residual: the gradients must be finite")
    norms = np.linalg.norm(candidates, axis=1)
    usable = norms > 0
    if not np.any(usable):  # no candidate, or only zero gradients
        return 1.0, np.zeros(len(candidates))
    unit = candidates[usable] / norms[usable, None]
    mu, residual = nnls(unit.T, -gradient / size)
    lam = np.zeros(len(candidates))
    lam[usable] = mu * size / norms[usable]
    return float(residual), lam


def best_subsets(gradient, candidates, names, max_size: int = 3) -> list[dict]:
    """For every size ``1..max_size``, the subset of ``candidates`` (rows, named by
    ``names``) with the smallest :func:`cone_residual`; then all candidates together
    (``size`` ``"all"``, its active set the multipliers > 0)."""
    rows = []
    for size in range(1, min(max_size, len(names)) + 1):
        tried = (
            (*cone_residual(gradient, np.asarray(candidates)[list(subset)]), subset)
            for subset in itertools.combinations(range(len(names)), size)
        )
        r, lam, subset = min(tried, key=lambda t: t[0])  # the first of the smallest
        named = {names[i]: float(w) for i, w in zip(subset, lam, strict=True)}
        rows.append({"size": size, "residual": r, "set": named})
    r, lam = cone_residual(gradient, candidates)
    norms = np.linalg.norm(np.asarray(candidates, np.float64).reshape(len(names), -1), axis=1)
    active = {n: float(w) for n, w, s in zip(names, lam, norms, strict=True) if w * s > ACTIVE}
    rows.append({"size": "all", "residual": r, "set": active})
    return rows


# ------------------------------------------------------------------ the simulator side


@dataclasses.dataclass(frozen=True)
class _Row:
    """A loss whose gradient is row ``index`` of the outputs' Jacobian (one draw)."""

    index: int

    def values(self, outputs):
        return outputs.values[..., 0, self.index]

    def cotangents(self, outputs):
        cotangent = np.zeros(outputs.values.shape)
        cotangent[..., self.index] = 1.0
        return cotangent


class _Quantities:
    """The cost terms and metrics of one deterministic run as functions of ``u``
    (values, Jacobian: module docstring), and the objectives the tuners use."""

    def __init__(self, args):
        import jax.numpy as jnp

        from fojax import optimize
        from fojax import requirements as rq
        from fojax.controllers.afonftsmc import paper_gains

        settings = rq.load(args.requirements).settings
        self.settings = settings = dataclasses.replace(settings, rotor_limited=args.rotor_limited)
        self.limit = settings.speed_limit() if args.rotor_limited else None
        self.spec = optimize.ProblemSpec(
            "afonftsmc", args.scenario, args.horizon, draws=1, seed=args.seed, dtype="float64"
        )
        self.scenario = remark3_study.nominal_scenario(args.scenario)
        self.paper = paper_gains(jnp.float64)
        self.naive = optimize.naive_gains("afonftsmc", jnp.float64)
        probes = tuple(
            rq.Requirement(m, m, "upper", 0.0, info.unit) for m, info in rq.METRICS.items()
        )
        self.scales = np.asarray([r.scale for r in probes])
        self.metrics = self.objective(rq.RequirementSet(probes, settings, "every metric"))
        chattering = optimize.CostConfig(
            position_weight=0.0, attitude_weight=0.0, effort_weight=0.0, chattering_weight=1.0
        )
        self.chattering = self.objective(cost=chattering)
        self.names = COST_TERMS + tuple(rq.METRICS)
        self.keys = self.metrics.sample(0)

    def objective(self, requirements=None, cost=None):
        """The run's objective: effort under ``requirements``, or the weighted sum
        ``cost``; the tuning law (``tanh`` at the boundary layers) throughout."""
        from fojax import optimize

        spec = self.spec if cost is None else dataclasses.replace(self.spec, cost=cost)
        return optimize.Objective(
            spec, self.paper, requirements, "cost" if requirements is None else "effort",
            scenario=self.scenario, rotor_speed_limit=self.limit, switching="tanh",
        )  # fmt: skip

    def values(self, points) -> tuple[np.ndarray, np.ndarray]:
        """``(values (P, q), status (P,))`` of ``points`` ``(P, 33)``."""
        out = self.metrics.forward(points, self.keys, width=1.0)
        metrics = np.stack([out.metrics[m][:, 0] for m in self.names[4:]], -1)
        return np.concatenate([out.terms[:, 0], metrics], -1), out.status[:, 0]

    def point(self, gains) -> dict:
        """Values ``(q,)`` and Jacobian ``(q, 33)`` at ``gains``, and its status."""
        from fojax.optimize import Request

        x = self.metrics.vector(gains)
        values, status = self.values(x[None])

        def row(objective, loss=None):
            return objective(Request(x[None], True, 0, 1.0, loss)).gradient

        rows = [row(self.metrics, _Row(k)) for k in range(1 + len(self.scales))]
        metrics = np.stack(rows[1:]) * self.scales[:, None]
        tracking = [  # P = T position_rmse^2, A = T attitude_rmse^2
            2 * self.spec.horizon * values[0, i] * metrics[i - 4]
            for i in map(self.names.index, ("position_rmse", "attitude_rmse"))
        ]
        jacobian = np.stack([*tracking, rows[0], row(self.chattering), *metrics])
        return {"x": x, "values": values[0], "jacobian": jacobian, "status": int(status[0])}

    def finite_difference_check(self, point: dict, h: float = 1e-6) -> dict:
        """Central differences of every quantity along a random unit direction against
        the Jacobian's product: the relative error per quantity."""
        direction = np.random.default_rng(0).standard_normal(point["x"].size)
        direction /= np.linalg.norm(direction)
        (plus, minus), _ = self.values(point["x"] + np.outer([h, -h], direction))
        fd = (plus - minus) / (2 * h)
        ad = point["jacobian"] @ direction
        scale = np.maximum(np.abs(ad), 1e-12 * np.maximum(np.abs(point["values"]), 1e-300))
        return {
            n: {"reverse": float(a), "central": float(f), "relative_error": float(abs(a - f) / s)}
            for n, a, f, s in zip(self.names, ad, fd, scale, strict=True)
            if n not in SURROGATES
        }


# ------------------------------------------------------------------ the analyses


def analyse(point: dict, names: tuple[str, ...]) -> dict:
    """Both objectives' subset residuals (``tracking``: candidates all but the functions
    of ``P`` or ``A``; ``effort``: all but the cost terms), the effort-weight sweep and
    fojax tune's default weights, at one point."""
    jacobian = dict(zip(names, point["jacobian"], strict=True))
    tracking = jacobian["P"] + jacobian["A"]
    out = {}
    for objective, gradient, excluded in (
        ("tracking", tracking, TRACKING_FUNCTIONS),
        ("effort", jacobian["E"], COST_TERMS),
    ):
        candidates = [n for n in names if n not in excluded]
        rows = np.stack([jacobian[n] for n in candidates])
        out[objective] = {
            "gradient_norm": float(np.linalg.norm(gradient)),
            "subsets": best_subsets(gradient, rows, candidates),
        }
    norm = np.linalg.norm(tracking)
    sweep = [float(np.linalg.norm(tracking + w * jacobian["E"]) / norm) for w in WEIGHTS]
    r_ec, (w_e, w_c) = cone_residual(tracking, np.stack([jacobian["E"], jacobian["C"]]))
    default = tracking + 1e-5 * (jacobian["E"] + jacobian["C"])
    out["weights"] = {
        "sweep_w_E": WEIGHTS.tolist(),
        "sweep_residual": sweep,
        "best": {"w_E": float(w_e), "w_C": float(w_c), "residual": r_ec},
        "fojax_tune_default": {
            "w_E": 1e-5, "w_C": 1e-5, "residual": float(np.linalg.norm(default) / norm)
        },
    }  # fmt: skip
    return out


def requirements_found(study: _Quantities, paper: dict, analysis: dict):
    """The requirement set of the ``effort`` objective's active bounds, each at the
    paper's value (its canonical unit)."""
    from fojax import requirements as rq

    values = dict(zip(study.names, paper["values"], strict=True))
    active = analysis["effort"]["subsets"][-1]["set"]
    made = []
    for metric in active:  # metrics are >= 0 (shares <= 1): the bound stays valid
        bound = min(
            float(values[metric]) * (1.0 + BOUND_TOLERANCE),
            1.0 if rq.METRICS[metric].share else np.inf,
        )
        made.append(rq.Requirement(metric, metric, "upper", bound, rq.METRICS[metric].unit))
    if not made:
        raise SystemExit("no bound opposes the effort's gradient at the paper's gains")
    return rq.RequirementSet(tuple(made), study.settings, "the paper's values, active bounds")


def tune_requirements(study: _Quantities, objective, start: str, args) -> dict:
    """The augmented Lagrangian from the gains ``start`` (``"naive"`` or ``"paper"``) on
    ``objective`` (:meth:`_Quantities.objective` of the requirement set: the starts
    share its compiled programs), objective effort: its record (cached in
    ``--out/tuned``) and gains."""
    from fojax.controllers import gains_io

    def run() -> dict:
        began = time.perf_counter()
        result = _common.to_requirements(
            objective, study.metrics.vector(getattr(study, start)), "adam", args.outer_steps,
            args.inner_steps, validation_draws=1, margin=0.0, progress=not args.quiet,
            learning_rate=args.learning_rate,
        )  # fmt: skip
        return {
            "gains": gains_io.gains_to_dict(objective.gains(result.x)),
            "selected": {"step": result.returned_step, **result.validation["best"]},
            "initial": result.validation["initial"],
            "paper": objective.evaluate(objective.x0, objective.keys("validation", 1))[1],
            "wall_time_s": round(time.perf_counter() - began, 1),
        }

    settings = _common.settings(args, ("out", "update_doc", "quiet", "requirements"))
    requirements = objective.requirements.to_dict()
    fingerprint = {"settings": settings, "requirements": requirements, "start": start}
    fingerprint["engine"] = "fojax.optimize"
    record = _common.cached(args.out / "tuned", start, fingerprint, run)
    return {"record": record, "gains": gains_io.gains_from_dict("afonftsmc", record["gains"])}


def distance(gains, paper) -> dict:
    """Field by field: each tuned parameter's value (one per group of shared axes) and
    ``log10(value / paper's)``, the median of its absolute value and how many lie
    within a factor 2."""
    from fojax.controllers import gains_io

    ours, theirs = (remark3_study.parameters(gains_io.gains_to_dict(g)) for g in (gains, paper))
    values = {f"{name} [{axes}]": value for (name, axes), value in ours.items()}
    logs = {
        f"{name} [{axes}]": float(np.log10(value / theirs[name, axes]))
        for (name, axes), value in ours.items()
    }
    size = np.abs(np.asarray(list(logs.values())))
    return {
        "values": values,
        "log10_ratio": logs,
        "median_abs_log10": float(np.median(size)),
        "within_factor_2": int(np.sum(size <= np.log10(2.0))),
        "parameters": len(logs),
    }


# ------------------------------------------------------------------ the command


def build_parser() -> argparse.ArgumentParser:
    parser = _common.parser("remark3_inverted")
    parser.add_argument("--scenario", type=int, choices=(1, 2, 3), default=1)
    _common.add_numbers(parser, horizon=20.0, outer_steps=10, inner_steps=10, learning_rate=0.1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--requirements", type=Path, default=EXAMPLE, help="its [settings]")
    parser.add_argument("--rotor-limited", action="store_true", help="default: ideal rotors")
    parser.add_argument("--out", type=Path, default=Path("results/remark3_inverted"))
    parser.add_argument("--update-doc", action="store_true", help="docs/requirements.md")
    _common.add_smoke(parser)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.tiny:
        args.horizon, args.outer_steps, args.inner_steps = 0.3, 1, 2
    _common.enable_float64()
    from fojax.controllers import gains_io

    start_all = time.perf_counter()
    study = _Quantities(args)
    points, first_s = timed(lambda: {"paper": study.point(study.paper)})
    points["naive"], jacobian_s = timed(study.point, study.naive)
    output.log(args.quiet, f"Jacobians: first {first_s:.0f} s (compile), then {jacobian_s:.1f} s")
    analysis = {k: analyse(p, study.names) for k, p in points.items()}
    reqs = requirements_found(study, points["paper"], analysis["paper"])
    output.log(args.quiet, "tuning from naive, then paper, to: " + ", ".join(reqs.names))
    objective = study.objective(reqs)
    tuned = {k: tune_requirements(study, objective, k, args) for k in ("naive", "paper")}
    gain_sets = {"naive": study.naive, "paper": study.paper}
    gain_sets |= {f"tuned from {k}": t["gains"] for k, t in tuned.items()}
    points |= {k: study.point(g) for k, g in list(gain_sets.items())[2:]}
    analysis |= {k: analyse(points[k], study.names) for k in list(points)[2:]}
    results = {
        "setting": {
            "scenario": args.scenario,
            "drag": "nominal (random variation off)",
            "horizon_s": args.horizon,
            "switching": "tanh at the paper's boundary layers",
            "actuators": "rotor-limited" if args.rotor_limited else "ideal",
            "dtype": "float64",
            "parameters": study.metrics.size,
        },
        "quantities": list(study.names),
        "values": {k: p["values"].tolist() for k, p in points.items()},
        "status": {k: p["status"] for k, p in points.items()},
        "finite_difference_check": study.finite_difference_check(points["paper"]),
        "analysis": analysis,
        "requirements_found": reqs.to_dict(),
        "requirement_tuning": {k: t["record"] for k, t in tuned.items()},
        "gains": {k: gains_io.gains_to_dict(g) for k, g in gain_sets.items()},
        "distance_to_paper": {k: distance(g, study.paper) for k, g in gain_sets.items()},
        "command": ["python", "-m", "experiments.remark3_inverted", *sys.argv[1:]],
        "load_average": output.load_average(),
        "git_commit": output.git_commit().get("commit"),
        "times_s": {
            "first_jacobian_with_compile": round(first_s, 1),
            "jacobian": round(jacobian_s, 1),
            "total": round(time.perf_counter() - start_all, 1),
        },
    }
    args.out.mkdir(parents=True, exist_ok=True)
    figure(results, args.out / "remark3_inverted.png")
    if args.update_doc:
        shutil.copyfile(args.out / "remark3_inverted.png", DOC.parent / "remark3_inverted.png")
    doc = DOC if args.update_doc else None
    wrote = f", remark3_inverted.png ({results['times_s']['total']:.0f} s in all)"
    return _common.finish(args.out, results, table(results), doc, "remark3-inverted", None, wrote)


if __name__ == "__main__":
    sys.exit(main())
