"""Remark 3 redone: is the paper's gain set a local optimum of the objective its
authors would have set, and where does gradient tuning from a naive start land?

    python -m experiments.remark3 [--out results/remark3] [--steps 40]
                                  [--horizon 80] [--tiny]

The paper (Remark 3) chose its AFONFTSMC gains "using MATLAB optimization toolbox"
without giving the objective. The one such a user would have set: the integral of the
squared position and attitude errors (ISE, ``J = P + A`` of :mod:`fojax.optimize.cost` with
``w_effort = w_chattering = 0``) on the nominal run of scenario 1: the reference
(54)-(55) and the deterministic disturbances (53) with the nominal drag (no random
variation: one deterministic run), over the scenario's 80 s, float64. Parameters: the
tuner's 33 (``share="paper"``: x = y, z, phi = theta = psi; ``p/q``, ``phi``, the orders
and the adaptation rates included), unconstrained as in :mod:`fojax.optimize.params` (log
or logit of each gain). One :class:`fojax.optimize.Objective` on that run (one draw: the
run is deterministic).

Switching. ``J`` is scored with the boundary layer ``sat`` (the evaluation law; the
paper's ``sgn`` has no useful gradient, its cost is reported beside). The engine takes
gradients through its tuning law only, ``tanh(S / (w b))`` at the gains' boundary layers
``b``, not through ``sat``: the gradient, its finite-difference check and the L-BFGS
steps are of ``J`` at ``tanh`` with ``w = 1`` (:data:`WIDTH`: the same slope as ``sat``
at ``S = 0``, the closest smooth law), and ``J`` at ``sat`` is reported beside it.

1. At the paper's gains: ``J`` (``sat`` and ``tanh``), the gradient with respect to the
   unconstrained parameters (per field; a unit step in a log-mapped parameter is a
   relative change of the gain), its norm, a central finite difference along it (a
   check of the reverse pass), and ``J`` along the negative gradient at several step
   lengths.
2. L-BFGS (:class:`fojax.optimize.strategies.LBFGS` on the run, through the driver
   :func:`fojax.optimize.run`: ``--steps`` gradient evaluations, each trial step capped
   at 1 in every parameter) from the naive start (:func:`fojax.optimize.params.naive_gains`)
   and from the paper's gains; every answer is validated on the run at ``sat`` and the
   best returned (the start on a tie).
3. Field by field: naive, paper, tuned-from-naive, tuned-from-paper gains, with
   ``J``, ``P``, ``A`` and the effort and chattering terms of :mod:`fojax.optimize.cost`.

Writes ``results.json`` and ``table.md`` to ``--out``; ``--update-doc FILE`` replaces
the block between ``<!-- remark3:begin -->`` and ``<!-- remark3:end -->`` in FILE.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np

from experiments import _common
from fojax.cli import output

__all__ = ["main"]

STEPS_ALONG = (1e-3, 3e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0)
"""Step lengths (in the unconstrained parameters) along the negative unit gradient."""
WIDTH = 1.0
"""The tuning law's width scale of the gradient (module docstring)."""
TERMS = ("position", "attitude", "effort", "chattering")


def build_parser() -> argparse.ArgumentParser:
    parser = _common.parser("remark3")
    _common.add_numbers(parser, horizon=80.0, steps=(40, "L-BFGS's gradient evaluations"))
    _common.add_outputs(parser, "remark3")
    return parser


def nominal_scenario(number: int = 1):
    """Scenario ``number`` without its random drag variation: one deterministic run."""
    from fojax import scenarios

    return dataclasses.replace(scenarios.get_scenario(number), drag_variation=0.0)


def timed(function, *args):
    """``(function(*args), its wall time (s))``."""
    began = time.perf_counter()
    return function(*args), time.perf_counter() - began


class _Study:
    """``J = P + A`` of the nominal run of scenario 1 (:class:`fojax.optimize.Objective`,
    ``sat`` its evaluation law) and the same run at ``sign``."""

    def __init__(self, args):
        import jax.numpy as jnp

        from fojax import optimize
        from fojax.controllers.afonftsmc import paper_gains

        cost = optimize.CostConfig(effort_weight=0.0, chattering_weight=0.0)
        spec = optimize.ProblemSpec(
            "afonftsmc", 1, args.horizon, draws=1, cost=cost, dtype="float64"
        )
        self.paper = paper_gains(jnp.float64)
        self.objective = optimize.Objective(spec, self.paper, scenario=nominal_scenario())
        self.sign = optimize.Objective(
            spec, self.paper, scenario=self.objective.scenario, switching="sign"
        )
        self.keys = self.objective.sample(0)  # the run is deterministic: no random process
        self.starts = {
            "naive": self.objective.vector(optimize.naive_gains("afonftsmc", jnp.float64)),
            "paper": self.objective.x0,
        }

    def J(self, points, width=None):
        """``(J (P,), diverged (P,))`` of ``points`` at ``tanh`` (``width``) or ``sat``."""
        out = self.objective.forward(points, self.keys, width)
        return out.values[:, 0, 0], ~out.valid[:, 0]

    def gradient(self, x):
        from fojax.optimize import Request

        evaluation = self.objective(Request(np.asarray(x)[None], True, 0, WIDTH))
        return float(evaluation.values[0]), np.asarray(evaluation.gradient)

    def describe(self, x) -> dict:
        """``J`` and each term of the cost of ``x`` under ``sat`` and ``sign``."""
        out = {}
        for switching, objective in (("sat", self.objective), ("sign", self.sign)):
            _, _, outputs = objective.evaluate(x, self.keys)
            terms = dict(zip(TERMS, outputs.terms[0].tolist(), strict=True))
            total = terms["position"] + terms["attitude"]
            out[switching] = {"J": total, **terms, "diverged": not bool(outputs.valid[0])}
        return out


def paper_point(study: _Study, quiet: bool):
    """``J`` and its gradient at the paper's gains, a central finite difference along
    it, and ``J`` along the negative gradient; with the compile and gradient times."""
    x_paper = study.starts["paper"]
    (j_paper, grad), compile_s = timed(study.gradient, x_paper)
    gradient_s = timed(study.gradient, x_paper)[1]
    norm = float(np.linalg.norm(grad))
    direction = -grad / norm
    output.log(quiet, f"paper: J = {j_paper:.6g}, |grad| = {norm:.4g} ({gradient_s:.1f} s)")
    h = 1e-5
    (plus, minus), _ = study.J(x_paper + np.outer([h, -h], direction), WIDTH)
    points = x_paper + np.outer(STEPS_ALONG, direction)
    (tanh, bad), (sat, bad_sat) = study.J(points, WIDTH), study.J(points)
    along = [
        {"step": t, "J": float(j), "J_sat": float(js), "diverged": bool(b or bs)}
        for t, j, js, b, bs in zip(STEPS_ALONG, tanh, sat, bad, bad_sat, strict=True)
    ]
    labels = study.objective.param_map.labels()
    per_field = sorted(
        ({"parameter": label, "dJ_du": float(g)} for label, g in zip(labels, grad, strict=True)),
        key=lambda entry: -abs(entry["dJ_du"]),
    )
    point = {
        "J": j_paper,
        "J_sat": float(study.J(x_paper[None])[0][0]),
        "gradient_norm": norm,
        "directional_derivative": -norm,
        "finite_difference": float(plus - minus) / (2 * h),
        "along_negative_gradient": along,
        "gradient_by_parameter": per_field,
    }
    return point, compile_s, gradient_s


def lbfgs(study: _Study, start: str, args):
    """L-BFGS from ``start`` for ``--steps`` gradient evaluations (validated at ``sat``
    every step): the returned answer and the trace per step."""
    from fojax import optimize
    from fojax.optimize import strategies

    output.log(args.quiet, f"L-BFGS from {start} ({args.steps} gradient evaluations)")
    result = optimize.run(
        study.objective, strategies.LBFGS(width=WIDTH), optimize.Budget(steps=args.steps),
        study.starts[start], validation_draws=1, validate_every=1, progress=not args.quiet,
    )  # fmt: skip
    keys = ("step", "J", "accepted", "J_sat", "wall_time_s")
    fields = ("step", "loss", "accepted", "validation", "wall_time_s")  # the driver's history
    trace = [{k: row[f] for k, f in zip(keys, fields, strict=True)} for row in result.history]
    accepted = sum(row["accepted"] for row in trace[1:])  # the first: the start
    return result.x, {"trace": trace, "returned_step": result.returned_step, "accepted": accepted}


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.tiny:
        args.horizon, args.steps = 0.3, 4
    _common.enable_float64()
    from fojax.controllers import gains_io

    start_all = time.perf_counter()
    study = _Study(args)
    point, compile_s, gradient_s = paper_point(study, args.quiet)
    points, traces = dict(study.starts), {}
    for start in ("naive", "paper"):
        points[f"tuned from {start}"], traces[f"from {start}"] = lbfgs(study, start, args)
    results = {
        "objective": {
            "J": "P + A: ISE of position (m^2 s) and attitude (rad^2 s) errors",
            "scenario": "1, nominal drag (no random variation), disturbances (53)",
            "horizon_s": args.horizon,
            "switching": "sat (scored); tanh at width 1 (differentiated)",
            "dtype": "float64",
            "parameters": study.objective.size,
        },
        "paper_point": point,
        "lbfgs": traces,
        "costs": {name: study.describe(x) for name, x in points.items()},
        "gains": {
            name: gains_io.gains_to_dict(study.objective.gains(x)) for name, x in points.items()
        },
        "compile_time_s": round(compile_s, 1),
        "gradient_time_s": round(gradient_s, 2),
        "total_wall_time_s": round(time.perf_counter() - start_all, 1),
        "git_commit": output.git_commit().get("commit"),
    }
    wrote = f" ({results['total_wall_time_s']:.0f} s in all)"
    text = table(results)
    return _common.finish(args.out, results, text, args.update_doc, "remark3", None, wrote)


FIELD_ROWS = {
    "surface_c1": "c1", "surface_c2": "c2", "reaching_h1": "hbar1", "reaching_h2": "hbar2",
    "power": "phi", "ratio": "p/q", "gamma1": "gamma1", "gamma2": "gamma2",
}  # fmt: skip
"""Gain field -> its symbol: one table row per group of shared axes (:data:`AXIS_GROUPS`)."""
AXIS_GROUPS = (("x = y", 0), ("z", 2), ("phi = theta = psi", 3))
ADAPTATION = ("eta0", "eta1", "eta2")


def table_row(*cells) -> str:
    """A Markdown table's row of ``cells``."""
    return "| " + " | ".join(cells) + " |"


def parameters(gains: dict) -> dict:
    """``{(symbol, axes): value}`` of a gain set (:func:`fojax.controllers.gains_io.gains_to_dict`):
    its 33 tuned parameters, one per group of shared axes, the fields of :data:`FIELD_ROWS`
    then the adaptation rates."""
    out = {}
    for field, symbol in [*FIELD_ROWS.items(), ("adaptation", None)]:
        for axes, index in AXIS_GROUPS:
            values = np.atleast_1d(np.asarray(gains[field])[index])
            symbols = ADAPTATION if symbol is None else (symbol,)
            out |= {(name, axes): float(v) for name, v in zip(symbols, values, strict=True)}
    return out


def table(results: dict) -> str:
    """Markdown: the paper's point (gradient, cost along it), and the gains field by
    field with their costs."""
    point = results["paper_point"]
    objective = results["objective"]
    along = point["along_negative_gradient"]
    lines = [
        f"Objective: `J = P + A` on the nominal run of scenario 1 ({objective['horizon_s']:g} s, "
        f"float64, {objective['parameters']} parameters), scored at `sat`; its gradient is "
        f"taken at `tanh` with the width of `sat`'s boundary layer (the engine's tuning law).",
        "",
        f"At the paper's gains: `J` = {point['J_sat']:.5g} at `sat`, {point['J']:.5g} at `tanh`; "
        f"gradient norm {point['gradient_norm']:.3g} (directional derivative along the negative "
        f"gradient {point['directional_derivative']:.4g}, central finite difference "
        f"{point['finite_difference']:.4g}). Largest components `dJ/du` (u: log of the gain, or "
        "logit for bounded ones): "
        + ", ".join(
            f"`{e['parameter']}` {e['dJ_du']:+.3g}" for e in point["gradient_by_parameter"][:5]
        )
        + ".",
        "",
        table_row("step along -grad/|grad|", *(f"{e['step']:g}" for e in along)),
        "|---|" + "---|" * len(along),
        *(
            table_row(f"J (`{law}`)", *(f"{e[key]:.4g}" + " (div.)" * e["diverged"] for e in along))
            for law, key in (("tanh", "J"), ("sat", "J_sat"))
        ),
        "",
    ]
    names = list(results["gains"])
    columns = [parameters(results["gains"][n]) for n in names]
    lines += _common.table_head("field | axes | " + " | ".join(names))
    for symbol, axes in columns[0]:
        digits = ".3g" if symbol in ADAPTATION else ".4g"
        lines.append(table_row(symbol, axes, *(f"{c[symbol, axes]:{digits}}" for c in columns)))
    costs = results["costs"]
    labels = dict(zip(("J", *TERMS), ("J = P + A", *"PAEC"), strict=True))
    for switching in ("sat", "sign"):
        for term, label in labels.items():
            entries = [costs[n][switching] for n in names]
            cells = ["diverged" if e["diverged"] else f"{e[term]:.4g}" for e in entries]
            lines.append(table_row(f"**{label}**", f"`{switching}`", *cells))
    lines += [
        "",
        "L-BFGS: "
        + "; ".join(
            f"{name}: {len(t['trace'])} gradient evaluations, {t['accepted']} steps accepted, "
            f"returned step {t['returned_step']}, {t['trace'][-1]['wall_time_s']:.0f} s"
            for name, t in results["lbfgs"].items()
            if t["trace"]
        )
        + f" (a gradient of the {objective['horizon_s']:g} s run: {results['gradient_time_s']:.1f}"
        f" s; compile {results['compile_time_s']:.0f} s).",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
