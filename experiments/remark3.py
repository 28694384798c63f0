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
from pathlib import Path

import numpy as np

from fojax.cli import output

__all__ = ["main"]

STEPS_ALONG = (1e-3, 3e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0)
"""Step lengths (in the unconstrained parameters) along the negative unit gradient."""


def build_parser() -> argparse.ArgumentParser:
    from fojax.cli import arguments

    parser = argparse.ArgumentParser(prog="python -m experiments.remark3")
    parser.add_argument("--horizon", type=arguments.positive_float, default=80.0)
    parser.add_argument("--iterations", type=arguments.positive_int, default=40)
    parser.add_argument("--switching", choices=("sat", "tanh"), default="sat")
    parser.add_argument("--out", type=Path, default=Path("results/remark3"))
    parser.add_argument("--update-doc", type=Path, help="markdown file to update")
    parser.add_argument("--tiny", action="store_true", help="a seconds-long smoke run")
    parser.add_argument("--quiet", action="store_true")
    return parser


def nominal_scenario_1():
    """Scenario 1 without its random drag variation: one deterministic run."""
    from fojax import scenarios

    return dataclasses.replace(scenarios.get_scenario(1), drag_variation=0.0)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.tiny:
        args.horizon, args.iterations = 0.3, 3
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    from scipy import optimize as scipy_optimize

    from fojax import plant, scenarios, simulator
    from fojax.controllers import gains_io, registry
    from fojax.controllers.afonftsmc import paper_gains
    from fojax.optimize import cost as cost_lib
    from fojax.optimize import params as params_lib
    from fojax.optimize import problem as problem_lib

    start_all = time.perf_counter()
    dtype = jnp.float64
    scenario = nominal_scenario_1()
    steps = int(round(args.horizon / 1e-3))
    config = simulator.SimulationConfig(
        dt=1e-3, horizon=args.horizon, save_every=problem_lib.checkpoint_interval(steps)
    )
    tracking = cost_lib.CostConfig(effort_weight=0.0, chattering_weight=0.0)
    every_term = cost_lib.CostConfig()
    param_map = params_lib.make_parameter_map("afonftsmc", None, "paper")
    paper = paper_gains(dtype)
    naive = params_lib.naive_gains("afonftsmc", dtype)
    key = scenarios.draw_keys(0, [0])[0]  # the run is deterministic: no random process
    del plant

    def controller(switching):
        return registry.make_controller(
            "afonftsmc", dt=1e-3, horizon=args.horizon, switching=switching
        )

    draw_cost = cost_lib.make_draw_cost(controller(args.switching), scenario, config, tracking)
    _, unravel = param_map.ravel(param_map.to_params(paper, dtype))

    def objective(vector):
        gains = param_map.to_gains(unravel(vector), paper)
        j, terms, status = draw_cost(gains, key)
        bad = ((status & cost_lib.DIVERGED) != 0) | ~jnp.isfinite(j)
        return j, bad

    value_and_grad = jax.jit(jax.value_and_grad(objective, has_aux=True))
    value = jax.jit(objective)
    term_costs = {
        switching: jax.jit(
            cost_lib.make_draw_cost(controller(switching), scenario, config, every_term)
        )
        for switching in ("sat", "sign")
    }

    def vector_of(gains):
        return np.asarray(param_map.ravel(param_map.to_params(gains, dtype))[0])

    def gains_of(vector):
        return param_map.to_gains(unravel(jnp.asarray(vector)), paper)

    def describe(gains) -> dict:
        out = {}
        for switching, fn in term_costs.items():
            _, terms, status = fn(gains, key)
            terms = np.asarray(terms, np.float64).tolist()
            out[switching] = {
                "J": terms[0] + terms[1],
                "position": terms[0],
                "attitude": terms[1],
                "effort": terms[2],
                "chattering": terms[3],
                "diverged": bool(int(status) & cost_lib.DIVERGED),
            }
        return out

    # -- 1. the paper's gains -----------------------------------------------------------
    t0 = time.perf_counter()
    x_paper = vector_of(paper)
    (j_paper, _), grad = value_and_grad(jnp.asarray(x_paper))
    grad = np.asarray(grad)
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    value_and_grad(jnp.asarray(x_paper))[1].block_until_ready()
    gradient_s = time.perf_counter() - t0
    norm = float(np.linalg.norm(grad))
    direction = -grad / norm
    output.log(
        args.quiet, f"paper: J = {float(j_paper):.6g}, |grad| = {norm:.4g} ({gradient_s:.1f} s)"
    )
    h = 1e-5
    plus = float(value(jnp.asarray(x_paper + h * direction))[0])
    minus = float(value(jnp.asarray(x_paper - h * direction))[0])
    along = []
    for t in STEPS_ALONG:
        j, bad = value(jnp.asarray(x_paper + t * direction))
        along.append({"step": t, "J": float(j), "diverged": bool(bad)})
    labels = param_map.labels()
    per_field = sorted(
        ({"parameter": label, "dJ_du": float(g)} for label, g in zip(labels, grad, strict=True)),
        key=lambda entry: -abs(entry["dJ_du"]),
    )

    # -- 2. L-BFGS from the naive start and from the paper's gains ------------------------
    def lbfgs(start_vector, label):
        trace = []
        calls = {"n": 0}
        t_start = time.perf_counter()

        def fun(x):
            (j, bad), g = value_and_grad(jnp.asarray(x))
            calls["n"] += 1
            if bool(bad) or not np.all(np.isfinite(np.asarray(g))):
                return 1e6, np.zeros_like(x)
            return float(j), np.asarray(g, np.float64)

        def callback(xk):
            j = float(value(jnp.asarray(xk))[0])
            trace.append(
                {
                    "iteration": len(trace) + 1,
                    "evaluations": calls["n"],
                    "J": j,
                    "wall_time_s": round(time.perf_counter() - t_start, 1),
                }
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

    output.log(args.quiet, f"L-BFGS from the naive start ({args.iterations} iterations)")
    x_from_naive, trace_naive, message_naive = lbfgs(vector_of(naive), "naive")
    output.log(args.quiet, f"L-BFGS from the paper's gains ({args.iterations} iterations)")
    x_from_paper, trace_paper, message_paper = lbfgs(x_paper, "paper")

    gain_sets = {
        "naive": naive,
        "paper": paper,
        "tuned from naive": gains_of(x_from_naive),
        "tuned from paper": gains_of(x_from_paper),
    }
    results = {
        "objective": {
            "J": "P + A: ISE of position (m^2 s) and attitude (rad^2 s) errors",
            "scenario": "1, nominal drag (no random variation), disturbances (53)",
            "horizon_s": args.horizon,
            "switching": args.switching,
            "dtype": "float64",
            "parameters": param_map.size,
        },
        "paper_point": {
            "J": float(j_paper),
            "gradient_norm": norm,
            "directional_derivative": -norm,
            "finite_difference": (plus - minus) / (2 * h),
            "along_negative_gradient": along,
            "gradient_by_parameter": per_field,
        },
        "lbfgs": {
            "from naive": {"trace": trace_naive, "message": message_naive},
            "from paper": {"trace": trace_paper, "message": message_paper},
        },
        "costs": {name: describe(g) for name, g in gain_sets.items()},
        "gains": {name: gains_io.gains_to_dict(g) for name, g in gain_sets.items()},
        "compile_time_s": round(compile_s, 1),
        "gradient_time_s": round(gradient_s, 2),
        "total_wall_time_s": round(time.perf_counter() - start_all, 1),
        "git_commit": output.git_commit().get("commit"),
    }
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    output.write_json(out / "results.json", results)
    text = table(results)
    (out / "table.md").write_text(text + "\n")
    if args.update_doc is not None:
        output.splice(args.update_doc, text, name="remark3")
    print(text)
    print(f"wrote {out}/results.json, table.md ({results['total_wall_time_s']:.0f} s in all)")
    return 0


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
    lines += ["| field | axes | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for field, symbol, per_axis in FIELD_ROWS:
        for axes, index in AXIS_GROUPS if per_axis else (("all", 0),):
            cells = [f"{np.asarray(gains[n][field])[index]:.4g}" for n in names]
            lines.append(f"| {symbol} | {axes} | " + " | ".join(cells) + " |")
    for axes, index in AXIS_GROUPS:
        for k, symbol in enumerate(ADAPTATION):
            cells = [f"{np.asarray(gains[n]['adaptation'])[index][k]:.3g}" for n in names]
            lines.append(f"| {symbol} | {axes} | " + " | ".join(cells) + " |")
    costs = results["costs"]
    for switching in ("sat", "sign"):
        for term, label in (
            ("J", "J = P + A"),
            ("position", "P"),
            ("attitude", "A"),
            ("effort", "E"),
            ("chattering", "C"),
        ):
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
