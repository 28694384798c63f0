"""``--requirements FILE`` and ``--rotor-limit T`` of ``fojax simulate`` and ``fojax tune``
(docs/requirements.md, "Commands").

``fojax simulate --requirements FILE`` measures every metric of
:data:`fojax.requirements.METRICS` on the study's own draws, controllers, gains and
actuators (:func:`fojax.requirements.measure`) and reports per controller the yield
(draws meeting every requirement) with its 95 % Clopper-Pearson interval, the failures
per requirement and the one failing most often: printed, in ``summary.json``
(``summary["requirements"]``: the set, once; ``summary["controllers"][NAME]
["requirements"]``: :meth:`fojax.requirements.YieldResult.to_dict`), the per-draw metrics
in ``requirements.npz`` and the figure ``requirements.png``. ``fojax tune`` shares the
option types and :func:`resolve_requirements`.

Actuators are rotor-limited (squared rotor speeds clipped to ``[0, w_max^2]``) when the
file's ``[settings]`` ask for it, or with ``--rotor-limit T`` (thrust-to-weight ratio at
``w_max``; it replaces the file's limit). A file that cannot be used is an error (exit
status 2) before anything compiles.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path

from fojax.cli import arguments

__all__ = [
    "actuators_record", "add_simulate_options", "configure_study", "limit_source",
    "report_simulate",
    "requirements_file", "resolve_requirements", "thrust_to_weight",
]  # fmt: skip


def requirements_file(text: str):
    """argparse type: a requirement file (TOML or JSON), loaded and checked
    (:func:`fojax.requirements.load`); every problem in one message."""
    from fojax import requirements as rq

    try:
        path = arguments.check_input_file(text, "requirement file")
        return rq.load(path)
    except ValueError as error:  # RequirementError is a ValueError
        raise argparse.ArgumentTypeError(str(error)) from None


def thrust_to_weight(text: str) -> float:
    """argparse type: a thrust-to-weight ratio > 1 (a vehicle that can hover)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or value <= 1:
        raise argparse.ArgumentTypeError(
            f"expected the thrust-to-weight ratio at full rotor speed, a number > 1 (2 is a "
            f"typical minimum; 1 or less cannot hover), got {text!r}"
        )
    return value


def add_simulate_options(parser: argparse.ArgumentParser) -> None:
    """``--requirements FILE`` and ``--rotor-limit T`` of ``fojax simulate``."""
    parser.add_argument(
        "--requirements",
        type=requirements_file,
        metavar="FILE",
        help="requirement file (TOML or JSON, docs/requirements.md; e.g. "
        "examples/requirements/small_quadrotor.toml); checked before anything compiles",
    )
    parser.add_argument(
        "--rotor-limit",
        type=thrust_to_weight,
        metavar="T",
        help="rotor-limited actuators: squared rotor speeds clipped to [0, w_max^2], "
        "w_max giving T times the weight (e.g. 2); replaces the requirement file's limit",
    )


def resolve_requirements(args):
    """``(requirement set or None, w_max or None)``: the file's set with ``--rotor-limit``
    applied, and the rotor speed limit the simulation uses (None: ideal actuators)."""
    from fojax import requirements as rq

    reqs, ratio = args.requirements, args.rotor_limit
    vehicle = getattr(args, "vehicle", None)  # a thrust-to-weight ratio is the vehicle's
    if ratio is None:
        if reqs is not None and reqs.settings.speed_limit() is not None:
            return reqs, reqs.settings.simulation_limit(vehicle)
        return reqs, None if vehicle is None else vehicle.speed_limit()
    if reqs is not None:
        settings = dataclasses.replace(
            reqs.settings, thrust_to_weight=ratio, rotor_speed_limit=None, rotor_limited=True
        )
        reqs = dataclasses.replace(reqs, settings=settings)
    return reqs, rq.rotor_speed_limit(ratio, vehicle)


def limit_source(args) -> str:
    """Where the run's rotor speed limit comes from (:func:`resolve_requirements`)."""
    reqs = args.requirements
    if args.rotor_limit is not None:
        return f"--rotor-limit {args.rotor_limit:g}"
    if reqs is not None and reqs.settings.speed_limit() is not None:
        return "the requirement file's rotor limit"
    return "vehicle.rotor_speed_limit"


def actuators_record(limit: float | None, args) -> dict:
    """The actuators of ``limit`` (``w_max``, ``None``: ideal) and where it comes from."""
    from fojax import requirements as rq

    if limit is None:
        return {"rotor_limited": False}
    ratio, source = args.rotor_limit, "--rotor-limit"
    vehicle = getattr(args, "vehicle", None)
    reqs = args.requirements
    if ratio is None and reqs is not None and reqs.settings.speed_limit() is not None:
        source = "the requirement file's settings"
        ratio = reqs.settings.thrust_to_weight
    elif ratio is None:
        source = "the vehicle file"
        ratio = vehicle.thrust_to_weight
    if ratio is None:
        ratio = (limit / rq.rotor_speed_limit(1.0, vehicle)) ** 2
    return {"rotor_limited": True, "rotor_speed_limit_rad_s": limit, "source": source,
            "thrust_to_weight": ratio}  # fmt: skip


def configure_study(parser, args, study):
    """The study on the actuators asked for (rotor-limited by ``--rotor-limit`` or the
    requirement file); keeps the resolved set in ``args.requirement_set``."""
    reqs, limit = resolve_requirements(args)
    args.requirement_set, args.rotor_speed_limit = reqs, limit
    arguments.check_flight(parser, args, limit, limit_source(args))
    if limit is None:
        return study
    return dataclasses.replace(study, rotor_speed_limit=limit)


def report_simulate(study, args, out: Path, summary: dict, figures: bool = True) -> dict:
    """After ``write_outputs``: the actuators in ``summary.json`` and, with
    ``--requirements``, the yield per controller (printed, in ``summary.json``,
    ``requirements.npz``, ``requirements.png``). Returns the updated summary."""
    from fojax.cli import style
    from fojax.cli.figures import plot_yield
    from fojax.cli.output import write_json, write_npz

    reqs = getattr(args, "requirement_set", None)
    limit = getattr(args, "rotor_speed_limit", None)
    if reqs is None and limit is None:
        return summary
    out = Path(out)
    summary["actuators"] = actuators_record(limit, args)
    if limit is not None:
        print(
            f"rotor-limited actuators: w_max {limit:.4g} rad/s (thrust-to-weight "
            f"{summary['actuators']['thrust_to_weight']:.3g}, {summary['actuators']['source']})"
        )
    if reqs is None:
        write_json(out / "summary.json", summary)
        return summary
    start = time.perf_counter()
    results, arrays = _yields(study, reqs, summary)
    summary["requirements"] = {
        **reqs.to_dict(),
        "names": list(reqs.names),
        "bounds": {r.name: r.describe() for r in reqs},
        "per_draw": "requirements.npz: <controller>.<metric> (canonical units, NaN for "
        "diverged draws), <controller>.status, <controller>.passed",
        "measured_on": "the study's draws (same seed, gains, actuators); diverged draws "
        "fail every requirement",
        "interval": "Clopper-Pearson, 95 %",
        "wall_time_s": round(time.perf_counter() - start, 2),
    }
    write_npz(out / "requirements.npz", arrays)
    files = summary.setdefault("files", [])
    if "requirements.npz" not in files:
        files.append("requirements.npz")
    write_json(out / "summary.json", summary)
    _print_yields(reqs, results)
    if figures:
        drawn = style.attempt(
            "requirements.png",
            plot_yield,
            results,
            out / "requirements.png",
            f"Requirements: scenario {study.scenario_id}, {study.draws} draws x "
            f"{study.horizon:g} s"
            + (f", rotor-limited (w_max {limit:.3g} rad/s)" if limit else ", ideal actuators"),
        )
        if drawn is not None:
            summary.setdefault("figures", []).append(drawn.name)
            write_json(out / "summary.json", summary)
    return summary


def _yields(study, reqs, summary: dict) -> tuple[dict, dict]:
    """``({name: YieldResult}, per-draw arrays)`` of every requirement metric measured on
    the study's draws (same keys, controllers, gains and actuators); each result in
    ``summary["controllers"][name]["requirements"]``."""
    import numpy as np

    from fojax import requirements as rq
    from fojax import scenarios
    from fojax.cli import study as study_layer

    _, scenario, config, dtype, runs = study_layer.prepare_runs(study)
    keys = np.asarray(scenarios.draw_keys(study.seed, np.arange(study.draws)))
    results, arrays = {}, {}
    for name, (controller, gains) in runs.items():
        metrics, status = rq.measure(controller, gains, scenario, reqs, keys, config, dtype=dtype)
        valid = (status & rq.DIVERGED) == 0
        result = rq.evaluate(reqs, metrics, valid=valid)
        results[name] = result
        entry = result.to_dict()
        entry["diverged"] = int(np.sum(~valid))
        summary["controllers"].setdefault(name, {})["requirements"] = entry
        for metric, values in metrics.items():
            arrays[f"{name}.{metric}"] = values
        arrays[f"{name}.status"] = status
        arrays[f"{name}.passed"] = np.all(result.matrix, axis=0)
    return results, arrays


def _print_yields(reqs, results: dict) -> None:
    print(f"requirements ({len(reqs)}: {', '.join(reqs.names)}):")
    width = max(len(n) for n in results)
    for name, result in results.items():
        print(f"  {name:<{width}} {result.describe()}")
        failing = [(n, f) for n, f in zip(result.names, result.failures, strict=True) if f]
        if failing:
            print(
                f"  {'':<{width}} failures: "
                + ", ".join(f"{n} {f}/{result.draws}" for n, f in failing)
            )
