"""Gains judged case by case: every case a tuning problem flies (the envelope's cases,
or its scenarios), on held-out draws, over each case's full horizon, with each
switching law (:func:`evaluate_cases`).

One compiled rollout per law serves every case: the cases' union
(:func:`fojax.scenarios.union`), draw ``j`` of case ``c`` the held-out draw ``c n +
j`` (``n`` draws per case), each draw run to its own case's horizon. Per draw the
requirement metrics (:class:`fojax.requirements.RequirementMetrics`): position RMSE,
largest tilt, torque chattering (the total variation of the three torque commands per
second); per case and set of gains their summaries over the draws kept, and the diverged
draws. :func:`losses` names where one set of gains does worse than another.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from fojax import scenarios, simulator
from fojax.blocks import EvaluatorCache, evaluate_in_blocks
from fojax.optimize.spec import ProblemSpec, draw_keys

__all__ = ["LAWS", "evaluate_cases", "losses", "table"]

LAWS = ("sat", "sign")
"""The switching laws every case is judged with (the tuner's boundary layer and the
paper's sign); a controller without switching is judged once."""

_PROGRAMS = EvaluatorCache(4)


def _cases(spec: ProblemSpec) -> tuple:
    """``((name, scenario), ...)`` of ``spec``: its envelope's cases, or its scenarios."""
    if spec.envelope is not None:  # a sign case is its twin judged with sign below
        laws = spec.envelope.laws()
        cases = spec.envelope.cases(spec.vehicle)
        return tuple(c for c, law in zip(cases, laws, strict=True) if law != "sign")
    ids = spec.scenario if isinstance(spec.scenario, tuple) else (spec.scenario,)
    union = spec.scenario_object()
    members = union.members or (union,)
    return tuple((f"scenario {i}", m) for i, m in zip(ids, members, strict=True))


def _program(controller, union, config, observer, dtype, model):
    def build():
        def run(gains, batch):
            keys, members = batch
            result = simulator.rollout_from_keys(
                controller, gains, model, union, keys, config, observer, dtype, members
            )
            return result.outputs, result.status

        return jax.jit(run)

    return _PROGRAMS.get((controller, union, config, observer, str(dtype)), build)


def evaluate_cases(spec: ProblemSpec, gains: dict[str, Any], draws: int,
                   rotor_speed_limit: float | None = None, laws: tuple[str, ...] = LAWS,
                   block: int = 32) -> dict:  # fmt: skip
    """Each set of ``gains`` (label -> the controller's gains) on ``draws`` held-out draws
    of every case of ``spec``, at every law of ``laws`` the controller has, each case
    over its own horizon, with rotors limited to ``rotor_speed_limit`` (rad/s; ``None``:
    ideal).

    Returns ``{"draws", "cases": [names], "laws": {law: {case: {label: summary}}}}``,
    a summary ``{"diverged", "position_rmse", "max_tilt_deg", "torque_chattering"}``:
    diverged draws, then the mean position RMSE (m), the largest tilt (deg) and the
    median torque chattering (N m/s) over the draws kept (``None`` where none is)."""
    from fojax.controllers import registry
    from fojax.requirements import RequirementMetrics, draw_metrics

    cases = _cases(spec)
    union = scenarios.union(*(c for _, c in cases)) if len(cases) > 1 else cases[0][1]
    dtype = jnp.dtype(spec.dtype)
    model = union.plant_params(dtype)
    horizon = union.horizon
    steps = int(round(horizon / spec.dt))
    config = simulator.SimulationConfig(
        dt=spec.dt, horizon=horizon, save_every=simulator.divisor_near(steps, 1000.0),
        rotor_speed_limit=rotor_speed_limit,
    )  # fmt: skip
    observer = RequirementMetrics(spec.dt, steps, rotor_speed_limit)
    keys = draw_keys(spec.seed, "heldout", draws * len(cases))
    members = (np.arange(draws * len(cases)) // draws).astype(np.int32)
    has_switching = "switching" in registry.controller_options(spec.controller)
    out: dict = {"draws": draws, "cases": [n for n, _ in cases], "laws": {}}
    for law in laws if has_switching else laws[:1]:
        controller = spec.make_controller(law, horizon)
        run = _program(controller, union, config, observer, dtype, model)
        table: dict = {name: {} for name, _ in cases}
        for label, values in gains.items():
            values = type(values)(*(jnp.asarray(g, dtype) for g in values))
            outputs, status = evaluate_in_blocks(run, values, (keys, members), block=block)
            metrics = draw_metrics(outputs, status)
            for c, (name, _) in enumerate(cases):
                mine = members == c
                kept = mine & np.isfinite(metrics["position_rmse"])
                table[name][label] = _summary(metrics, mine, kept)
        out["laws"][law if has_switching else "none"] = table
    return out


def _summary(metrics: dict, mine: np.ndarray, kept: np.ndarray) -> dict:
    def over(name, reduce):
        return float(reduce(metrics[name][kept])) if np.any(kept) else None

    tilt = over("max_tilt", np.max)
    return {
        "diverged": int(np.sum(mine & ~kept)),
        "position_rmse": over("position_rmse", np.mean),
        "max_tilt_deg": None if tilt is None else math.degrees(tilt),
        "torque_chattering": over("torque_chattering", np.median),
    }


def losses(evaluation: dict, worse: str, better: str) -> list[str]:
    """Where the gains ``worse`` do worse than ``better`` in an :func:`evaluate_cases`
    result: more diverged draws, a larger position RMSE or more chattering, one line
    each (law, case, what)."""
    out = []
    for law, table in evaluation["laws"].items():
        for case, row in table.items():
            a, b = row[worse], row[better]
            if a["diverged"] > b["diverged"]:
                out.append(f"{law}, {case}: {a['diverged']} diverged draws against "
                           f"{b['diverged']}")  # fmt: skip
            if a["position_rmse"] is None:
                continue  # every draw diverged: said above
            for key, what in (("position_rmse", "position RMSE"),
                              ("torque_chattering", "torque chattering")):  # fmt: skip
                if b[key] is not None and a[key] > b[key]:
                    out.append(f"{law}, {case}: {what} {a[key]:.3g} against {b[key]:.3g}")
    return out


def table(evaluation: dict, labels: tuple[str, ...]) -> str:
    """The evaluation as lines of text: per law and case, each label's diverged draws,
    position RMSE, largest tilt and torque chattering."""
    lines = []
    for law, rows in evaluation["laws"].items():
        for case, row in rows.items():
            cells = []
            for label in labels:
                s = row[label]
                if s["position_rmse"] is None:
                    cells.append(f"{label}: all {s['diverged']} diverged")
                    continue
                cells.append(
                    f"{label}: RMSE {s['position_rmse']:.3g} m, tilt {s['max_tilt_deg']:.3g} "
                    f"deg, chattering {s['torque_chattering']:.3g} N m/s"
                    + (f", {s['diverged']} diverged" if s["diverged"] else "")
                )
            lines.append(f"  {law:>4}  {case}: " + "; ".join(cells))
    return "\n".join(lines)

