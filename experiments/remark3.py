"""Remark 3 redone: is the paper's gain set a local optimum of the objective its
authors would have set, and where does gradient tuning from a naive start land?

    python -m experiments.remark3 [--out results/remark3] [--iterations 40]
                                  [--horizon 80] [--tiny]

The paper (Remark 3) chose its AFONFTSMC gains "using MATLAB optimization toolbox"
without giving the objective. The one such a user would have set: the integral of the
squared position and attitude errors (ISE, ``J = P + A`` of :mod:`fojax.optimize.cost` with
``w_effort = w_chattering = 0``) on the nominal run of scenario 1: the reference
(54)-(55) and the deterministic disturbances (53) with the nominal drag (no random
variation: one deterministic run), over the scenario's 80 s, float64. Switching: the
boundary layer ``sat`` of the evaluation (the paper's ``sgn`` has no useful gradient;
its cost is reported beside). Parameters: the tuner's 33 (``share="paper"``: x = y,
z, phi = theta = psi; ``p/q``, ``phi``, the orders and the adaptation rates
included), unconstrained as in :mod:`fojax.optimize.params` (log or logit of each gain).

1. At the paper's gains: ``J``, the gradient with respect to the unconstrained
   parameters (per field; a unit step in a log-mapped parameter is a relative change
   of the gain), its norm, a central finite difference along it (a check of the
   reverse pass), and ``J`` along the negative gradient at several step lengths.
2. L-BFGS (SciPy ``L-BFGS-B`` with the reverse-mode gradient, ``u`` in
   ``[-U_MAX, U_MAX]``) for ``--iterations`` iterations from the naive start
   (:func:`fojax.optimize.params.naive_gains`) and from the paper's gains.
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


def build_parser() -> argparse.ArgumentParser:
    parser = _common.parser("remark3")
    _common.add_numbers(parser, horizon=80.0, iterations=40)
    parser.add_argument("--switching", choices=("sat", "tanh"), default="sat")
    _common.add_outputs(parser, "remark3")
    return parser


def nominal_scenario_1():
    """Scenario 1 without its random drag variation: one deterministic run."""
    from fojax import scenarios

    return dataclasses.replace(scenarios.get_scenario(1), drag_variation=0.0)


class _Objective:
    """``J = P + A`` of the nominal run of scenario 1 against the tuner's unconstrained
    parameters (compiled, with its gradient), and every cost term of a gain set."""

    def __init__(self, args):
        import jax
        import jax.numpy as jnp

        from fojax import scenarios, simulator
        from fojax.controllers import registry
        from fojax.controllers.afonftsmc import paper_gains
        from fojax.optimize import cost as cost_lib
        from fojax.optimize import params as params_lib
        from fojax.optimize import problem as problem_lib

        scenario = nominal_scenario_1()
        steps = int(round(args.horizon / 1e-3))
        config = simulator.SimulationConfig(
            dt=1e-3, horizon=args.horizon, save_every=problem_lib.checkpoint_interval(steps)
        )
        tracking = cost_lib.CostConfig(effort_weight=0.0, chattering_weight=0.0)
        self.param_map = params_lib.make_parameter_map("afonftsmc", None, "paper")
        self.paper = paper_gains(jnp.float64)
        self.naive = params_lib.naive_gains("afonftsmc", jnp.float64)
        self.key = scenarios.draw_keys(0, [0])[0]  # the run is deterministic: no random process

        def draw_cost(switching, weights):
            law = registry.make_controller(
                "afonftsmc", dt=1e-3, horizon=args.horizon, switching=switching
            )
            return cost_lib.make_draw_cost(law, scenario, config, weights)

        tracking_cost = draw_cost(args.switching, tracking)
        _, self.unravel = self.param_map.ravel(self.param_map.to_params(self.paper, jnp.float64))

        def objective(vector):
            gains = self.param_map.to_gains(self.unravel(vector), self.paper)
            j, terms, status = tracking_cost(gains, self.key)
            bad = ((status & cost_lib.DIVERGED) != 0) | ~jnp.isfinite(j)
            return j, bad

        self.value_and_grad = jax.jit(jax.value_and_grad(objective, has_aux=True))
        self.value = jax.jit(objective)
        every_term = cost_lib.CostConfig()
        self.term_costs = {s: jax.jit(draw_cost(s, every_term)) for s in ("sat", "sign")}

    def vector_of(self, gains):
        import jax.numpy as jnp

        return np.asarray(self.param_map.ravel(self.param_map.to_params(gains, jnp.float64))[0])

    def gains_of(self, vector):
        import jax.numpy as jnp

        return self.param_map.to_gains(self.unravel(jnp.asarray(vector)), self.paper)

    def describe(self, gains) -> dict:
        """``J`` and each term of the cost of ``gains`` under ``sat`` and ``sign``."""
        from fojax.optimize import cost as cost_lib

        out = {}
        for switching, fn in self.term_costs.items():
            _, terms, status = fn(gains, self.key)
            terms = np.asarray(terms, np.float64).tolist()
            named = dict(zip(("position", "attitude", "effort", "chattering"), terms, strict=True))
            diverged = bool(int(status) & cost_lib.DIVERGED)
            out[switching] = {"J": terms[0] + terms[1], **named, "diverged": diverged}
        return out


def paper_point(obj: _Objective, quiet: bool):
    """``J`` and its gradient at the paper's gains, a central finite difference along
    it, and ``J`` along the negative gradient; with the compile and gradient times."""
    import jax.numpy as jnp

    t0 = time.perf_counter()
    x_paper = obj.vector_of(obj.paper)
    (j_paper, _), grad = obj.value_and_grad(jnp.asarray(x_paper))
    grad = np.asarray(grad)
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    obj.value_and_grad(jnp.asarray(x_paper))[1].block_until_ready()
    gradient_s = time.perf_counter() - t0
    norm = float(np.linalg.norm(grad))
    direction = -grad / norm
    output.log(quiet, f"paper: J = {float(j_paper):.6g}, |grad| = {norm:.4g} ({gradient_s:.1f} s)")
    h = 1e-5
    plus = float(obj.value(jnp.asarray(x_paper + h * direction))[0])
    minus = float(obj.value(jnp.asarray(x_paper - h * direction))[0])
    along = []
    for t in STEPS_ALONG:
        j, bad = obj.value(jnp.asarray(x_paper + t * direction))
        along.append({"step": t, "J": float(j), "diverged": bool(bad)})
    labels = obj.param_map.labels()
    per_field = sorted(
        ({"parameter": label, "dJ_du": float(g)} for label, g in zip(labels, grad, strict=True)),
        key=lambda entry: -abs(entry["dJ_du"]),
    )
    point = {
        "J": float(j_paper),
        "gradient_norm": norm,
        "directional_derivative": -norm,
        "finite_difference": (plus - minus) / (2 * h),
        "along_negative_gradient": along,
        "gradient_by_parameter": per_field,
    }
    return point, compile_s, gradient_s


def lbfgs(obj: _Objective, start_vector, label: str, args):
    """SciPy's L-BFGS-B from ``start_vector`` for ``--iterations`` iterations: the
    answer, the trace of ``J`` per iteration and SciPy's message."""
    import jax.numpy as jnp
    from scipy import optimize as scipy_optimize

    from fojax.optimize import params as params_lib

    trace = []
    calls = {"n": 0}
    t_start = time.perf_counter()

    def fun(x):
        (j, bad), g = obj.value_and_grad(jnp.asarray(x))
        calls["n"] += 1
        if bool(bad) or not np.all(np.isfinite(np.asarray(g))):
            return 1e6, np.zeros_like(x)
        return float(j), np.asarray(g, np.float64)

    def callback(xk):
        j = float(obj.value(jnp.asarray(xk))[0])
        wall = round(time.perf_counter() - t_start, 1)
        trace.append(
            {"iteration": len(trace) + 1, "evaluations": calls["n"], "J": j, "wall_time_s": wall}
        )
        output.log(args.quiet, f"  {label}: iteration {len(trace)}, J = {j:.6g}")

    bound = params_lib.U_MAX
    result = scipy_optimize.minimize(
        fun,
        start_vector,
        jac=True,
        method="L-BFGS-B",
        bounds=[(-bound, bound)] * len(start_vector),
        callback=callback,
        options={"maxiter": args.iterations, "maxfun": 3 * args.iterations},
    )
    return np.asarray(result.x), trace, str(result.message)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.tiny:
        args.horizon, args.iterations = 0.3, 3
    _common.enable_float64()
    from fojax.controllers import gains_io

    start_all = time.perf_counter()
    obj = _Objective(args)
    point, compile_s, gradient_s = paper_point(obj, args.quiet)
    gain_sets, traces = {"naive": obj.naive, "paper": obj.paper}, {}
    for start, origin in (("naive", "the naive start"), ("paper", "the paper's gains")):
        output.log(args.quiet, f"L-BFGS from {origin} ({args.iterations} iterations)")
        x, trace, message = lbfgs(obj, obj.vector_of(gain_sets[start]), start, args)
        traces[f"from {start}"] = {"trace": trace, "message": message}
        gain_sets[f"tuned from {start}"] = obj.gains_of(x)
    results = {
        "objective": {
            "J": "P + A: ISE of position (m^2 s) and attitude (rad^2 s) errors",
            "scenario": "1, nominal drag (no random variation), disturbances (53)",
            "horizon_s": args.horizon,
            "switching": args.switching,
            "dtype": "float64",
            "parameters": obj.param_map.size,
        },
        "paper_point": point,
        "lbfgs": traces,
        "costs": {name: obj.describe(g) for name, g in gain_sets.items()},
        "gains": {name: gains_io.gains_to_dict(g) for name, g in gain_sets.items()},
        "compile_time_s": round(compile_s, 1),
        "gradient_time_s": round(gradient_s, 2),
        "total_wall_time_s": round(time.perf_counter() - start_all, 1),
        "git_commit": output.git_commit().get("commit"),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    wrote = f" ({results['total_wall_time_s']:.0f} s in all)"
    text = table(results)
    return _common.finish(args.out, results, text, args.update_doc, "remark3", None, wrote)


FIELD_ROWS = (
    ("surface_c1", "c1", True),
    ("surface_c2", "c2", True),
    ("reaching_h1", "hbar1", True),
    ("reaching_h2", "hbar2", True),
    ("power", "phi", True),
    ("ratio", "p/q", True),
    ("gamma1", "gamma1", True),
    ("gamma2", "gamma2", True),
)
AXIS_GROUPS = (("x = y", 0), ("z", 2), ("phi = theta = psi", 3))
ADAPTATION = ("eta0", "eta1", "eta2")


def table(results: dict) -> str:
    """Markdown: the paper's point (gradient, cost along it), and the gains field by
    field with their costs."""
    point = results["paper_point"]
    objective = results["objective"]
    lines = [
        f"Objective: `J = P + A` on the nominal run of scenario 1 ({objective['horizon_s']:g} s, "
        f"`{objective['switching']}` switching, float64, {objective['parameters']} parameters).",
        "",
        f"At the paper's gains: `J` = {point['J']:.5g}; gradient norm "
        f"{point['gradient_norm']:.3g} (directional derivative along the negative gradient "
        f"{point['directional_derivative']:.4g}, central finite difference "
        f"{point['finite_difference']:.4g}). Largest components `dJ/du` (u: log of the "
        "gain, or logit for bounded ones): "
        + ", ".join(
            f"`{e['parameter']}` {e['dJ_du']:+.3g}" for e in point["gradient_by_parameter"][:5]
        )
        + ".",
        "",
        "| step along -grad/|grad| | "
        + " | ".join(f"{e['step']:g}" for e in point["along_negative_gradient"])
        + " |",
        "|---|" + "---|" * len(point["along_negative_gradient"]),
        "| J | "
        + " | ".join(
            f"{e['J']:.4g}" + (" (div.)" if e["diverged"] else "")
            for e in point["along_negative_gradient"]
        )
        + " |",
        "",
    ]
    gains = results["gains"]
    names = list(gains)
    lines += _common.table_head("field | axes | " + " | ".join(names))
    for field, symbol, per_axis in FIELD_ROWS:
        for axes, index in AXIS_GROUPS if per_axis else (("all", 0),):
            cells = [f"{np.asarray(gains[n][field])[index]:.4g}" for n in names]
            lines.append(f"| {symbol} | {axes} | " + " | ".join(cells) + " |")
    for axes, index in AXIS_GROUPS:
        for k, symbol in enumerate(ADAPTATION):
            cells = [f"{np.asarray(gains[n]['adaptation'])[index][k]:.3g}" for n in names]
            lines.append(f"| {symbol} | {axes} | " + " | ".join(cells) + " |")
    costs = results["costs"]
    terms = ("J", "position", "attitude", "effort", "chattering")
    labels = dict(zip(terms, ("J = P + A", *"PAEC"), strict=True))
    for switching in ("sat", "sign"):
        for term, label in labels.items():
            cells = []
            for n in names:
                entry = costs[n][switching]
                cells.append("diverged" if entry["diverged"] else f"{entry[term]:.4g}")
            lines.append(f"| **{label}** | `{switching}` | " + " | ".join(cells) + " |")
    traces = results["lbfgs"]
    lines += [
        "",
        "L-BFGS: "
        + "; ".join(
            f"{name}: {len(t['trace'])} iterations, {t['trace'][-1]['evaluations']} "
            f"gradient evaluations, {t['trace'][-1]['wall_time_s']:.0f} s"
            for name, t in traces.items()
            if t["trace"]
        )
        + f" (a gradient of the {objective['horizon_s']:g} s run: "
        f"{results['gradient_time_s']:.1f} s; compile "
        f"{results['compile_time_s']:.0f} s).",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
