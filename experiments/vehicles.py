"""The paper's gains, and the five controllers tuned from the naive start, on the vehicles
of ``examples/vehicles/`` other than the paper's.

    python -m experiments.vehicles [--out results/vehicles] [--vehicles crazyflie,iris]
        [--controllers afonftsmc,anftsmc,fobsmc,bsmc,fl] [--draws 64] [--retune]
        [--update-doc]

Per vehicle ``V`` (``examples/vehicles/V.toml``, judged by ``examples/requirements/V.toml``),
every step a ``fojax`` command in a process of its own, as a user runs it:

1. **Tuning.** For each controller ``fojax tune --vehicle V --envelope
   examples/envelopes/paper_and_manoeuvres.toml --controller C --init naive`` with the
   default method and the envelope's defaults (its held-out evaluation: 32 draws of
   every case).
   A controller whose ``gains.json`` is in ``--out`` is not tuned again unless
   ``--retune``.
2. **Yields.** ``fojax simulate --vehicle V --scenario 2 --controller all --requirements
   examples/requirements/V.toml --horizon 10 --seed 1 --switching sat`` with the
   paper's gains, then with the tuned gains (each also with ``--switching sign``, the
   paper's): each controller's yield (Clopper-Pearson 95 % interval), the requirements
   failing, the diverged draws. Seed 1 draws are none of the tuner's; ``sat`` is the
   switching the tuner validates with.
3. **The full horizon.** The paper's and the tuned gains over scenario 2's 80 s (no
   requirements, ``sat``): diverged draws and position RMSE.

Writes ``results.json`` and ``table.md`` to ``--out``; ``--update-doc`` replaces the
``vehicles`` block of docs/vehicles.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from experiments import _common
from fojax import requirements
from fojax.cli import output

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "vehicles.md"
CONTROLLERS = ("afonftsmc", "anftsmc", "fobsmc", "bsmc", "fl")
ENVELOPE = "examples/envelopes/paper_and_manoeuvres.toml"
"""The flight envelope every controller is tuned over (``fojax tune``'s default mix)."""
SEED = 1
"""The seed of the yield and full-horizon draws (the tuner draws from seed 0)."""


def files(vehicle: str) -> tuple[str, str]:
    """The vehicle file and requirement file of ``vehicle`` (relative to the root)."""
    return f"examples/vehicles/{vehicle}.toml", f"examples/requirements/{vehicle}.toml"


def tune_command(vehicle: str, controller: str, out: Path) -> list[str]:
    return [
        *("fojax", "tune", "--vehicle", files(vehicle)[0], "--envelope", ENVELOPE),
        *("--controller", controller, "--init", "naive", "--quiet", "--out", str(out)),
    ]


def simulate_command(vehicle: str, controllers, draws: int, gains, out: Path, full: bool,
                     switching: str = "sat"):  # fmt: skip
    """``fojax simulate`` of ``controllers`` with ``gains`` (files; none: the paper's):
    the requirements over 10 s, or (``full``) scenario 2's own horizon without them."""
    words = ["fojax", "simulate", "--vehicle", files(vehicle)[0], "--scenario", "2"]
    words += ["--controller", ",".join(controllers), "--draws", str(draws), "--seed", str(SEED)]
    words += ["--switching", switching]
    words += [] if full else ["--horizon", "10", "--requirements", files(vehicle)[1]]
    for path in gains:
        words += ["--gains", str(path)]
    return [*words, "--keep", "0", "--no-figures", "--overwrite", "--quiet", "--out", str(out)]


def _run(words: list[str]) -> float:
    """Run a ``fojax`` command from the root; its wall time (s)."""
    start = time.perf_counter()
    argv = [sys.executable, "-m", "fojax.cli", *words[1:]]
    subprocess.run(argv, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def tune(vehicle: str, controller: str, out: Path, again: bool) -> dict:
    """Tune ``controller`` for ``vehicle`` (unless done and not ``again``); what it wrote."""
    seconds = None
    if again or not (out / "gains.json").is_file():
        if out.exists():
            shutil.rmtree(out)
        print(f"  {' '.join(tune_command(vehicle, controller, out))}", flush=True)
        load = output.load_average()
        seconds = round(_run(tune_command(vehicle, controller, out)), 1)
        print(f"    {seconds:.0f} s", flush=True)
    else:
        load = None
    metadata = json.loads((out / "gains.json").read_text())["metadata"]
    evaluation = json.loads((out / "evaluation.json").read_text())
    return {
        "command": " ".join(tune_command(vehicle, controller, Path("DIR"))),
        "command_s": seconds,
        "load_before": load,
        "tuning_s": metadata["wall_time_s"],
        "steps": metadata["steps"],
        "returned_step": metadata["returned_step"],
        "heldout": {k: evaluation[k] for k in ("draws", "horizon_s", "initial", "tuned")},
    }


def study(vehicle: str, controllers, draws: int, gains, out: Path, full: bool,
          switching: str = "sat") -> dict:  # fmt: skip
    """One ``fojax simulate`` run; per controller its diverged draws, position RMSE and
    (requirements) yield."""
    words = simulate_command(vehicle, controllers, draws, gains, out, full, switching)
    print(f"  {' '.join(words)}", flush=True)
    seconds = _run(words)
    summary = json.loads((out / "summary.json").read_text())
    per_draw = np.load(out / "requirements.npz") if (out / "requirements.npz").is_file() else {}
    rows = {}
    for name, entry in summary["controllers"].items():
        rmse = entry["metrics"]["position_rmse"]
        rows[name] = {
            "diverged": entry["diverged"],
            "draws": entry["draws"],
            "position_rmse": rmse["mean"],
            "position_rmse_ci95": rmse["ci95"],
            **({"requirements": entry["requirements"]} if "requirements" in entry else {}),
        }
        if f"{name}.torque_chattering" in per_draw:  # N m/s, NaN for diverged draws
            chatter = per_draw[f"{name}.torque_chattering"]
            rows[name]["torque_chattering_median"] = float(np.nanmedian(chatter))
    return {
        "command": " ".join(simulate_command(vehicle, controllers, draws, ["GAINS"] * bool(gains),
                                             Path("DIR"), full, switching)),
        "seconds": round(seconds, 1),
        "horizon_s": summary["horizon_s"],
        "actuators": summary.get("actuators"),
        "vehicle": summary.get("vehicle"),
        "controllers": rows,
    }  # fmt: skip


def run_vehicle(vehicle: str, controllers, draws: int, out: Path, again: bool) -> dict:
    print(f"{vehicle}:", flush=True)
    tuned = {c: tune(vehicle, c, out / "tune" / c, again) for c in controllers}
    gains = [out / "tune" / c / "gains.json" for c in controllers]
    return {
        "vehicle": files(vehicle)[0],
        "requirements": files(vehicle)[1],
        "tuning": tuned,
        "paper": study(vehicle, controllers, draws, [], out / "paper", False),
        "paper_sign": study(vehicle, controllers, draws, [], out / "paper_sign", False, "sign"),
        "tuned": study(vehicle, controllers, draws, gains, out / "tuned", False),
        "tuned_sign": study(vehicle, controllers, draws, gains, out / "tuned_sign", False, "sign"),
        "paper_full": study(vehicle, controllers, draws, [], out / "paper_full", True),
        "tuned_full": study(vehicle, controllers, draws, gains, out / "tuned_full", True),
    }


def _yield(row: dict) -> str:
    entry = row["requirements"]
    diverged = f"; {entry['diverged']} diverged" if entry["diverged"] else ""
    return _common.yield_cell(entry) + diverged


def _rmse(row: dict) -> str:
    if row["position_rmse"] is None:
        return f"none: {row['diverged']} diverged"
    diverged = f", {row['diverged']} diverged" if row["diverged"] else ""
    return f"{row['position_rmse']:.3g}{diverged}"


def _sign(run: dict, kind: str, name: str) -> str:
    """The ``sign`` yield of ``name`` (the FL has no switching)."""
    return _yield(run[f"{kind}_sign"]["controllers"][name]) if name != "fl" else "no switching"


def table(results: dict) -> str:
    parts = []
    for vehicle, run in results["vehicles"].items():
        draws = next(iter(run["tuned"]["controllers"].values()))["draws"]
        actuators = run["tuned"]["actuators"] or {}
        limit = (
            f"rotor-limited at {actuators['rotor_speed_limit_rad_s']:.4g} rad/s (thrust-to-weight "
            f"{actuators['thrust_to_weight']:.3g})"
            if actuators.get("rotor_limited")
            else "ideal actuators"
        )
        record = run["tuned"].get("vehicle") or {}
        if record.get("max_torque"):
            table = record["vehicle"]
            layout = (f"rotors {table['configuration']}" if "configuration" in table
                      else "rotors as listed" if "rotors" in table else "rotors '+'")  # fmt: skip
            lag = table.get("rotor_time_constant")
            roll, pitch, yaw = record["max_torque"]
            limit += (f"; {layout}{f', lagging {lag * 1e3:g} ms' if lag else ''}; largest "
                      f"torques {roll:.3g}, {pitch:.3g}, {yaw:.3g} N m")  # fmt: skip
        heldout = run["tuning"][next(iter(run["tuning"]))]["heldout"]
        reqs = requirements.load(ROOT / run["requirements"]).requirements
        bound = next(r for r in reqs if r.metric == "torque_chattering")
        parts.append(
            f"#### {vehicle} (`{run['vehicle']}`, `{run['requirements']}`; {limit})\n\n"
            f"Yields on {draws} draws x 10 s of scenario 2 (seed {SEED}, none of the tuner's), "
            f"Clopper-Pearson 95 %, with `sat` switching (the tuner's) and with `sign` (the "
            f"paper's); position RMSE (m) on the same draws over "
            f"{run['tuned_full']['horizon_s']:g} s with `sat`; the tuning's own held-out cost "
            f"({heldout['draws']} draws x {heldout['horizon_s']:g} s, `sat`) against the naive "
            "start's."
        )
        rows = [
            "| controller | paper's gains: yield | yield, `sign` | RMSE, 80 s |",
            "|---|---|---|---|",
        ]
        for name in run["tuning"]:
            rows.append(
                f"| {name} | {_yield(run['paper']['controllers'][name])} | "
                f"{_sign(run, 'paper', name)} | {_rmse(run['paper_full']['controllers'][name])} |"
            )
        parts.append("\n".join(rows))
        rows = [
            "| controller | tuned from naive: steps, time (s) | held-out cost (naive start) | "
            f"yield | yield, `sign` | RMSE, 80 s | torque chattering (N m/s), median: bound "
            f"{bound.value:g} {bound.unit} |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, tuning in run["tuning"].items():
            start, end = tuning["heldout"]["initial"], tuning["heldout"]["tuned"]
            cost = f"{end['score']:.4g}" + (f", {end['diverged']} diverged" if end["diverged"]
                                             else "")  # fmt: skip
            rows.append(
                f"| {name} | {tuning['steps']}, {tuning['tuning_s']:.0f} | {cost} "
                f"({start['score']:.3g}{f', {d} diverged' if (d := start['diverged']) else ''}) | "
                f"{_yield(run['tuned']['controllers'][name])} | {_sign(run, 'tuned', name)} | "
                f"{_rmse(run['tuned_full']['controllers'][name])} | "
                f"{run['tuned']['controllers'][name]['torque_chattering_median']:.3g} |"
            )
        parts.append("\n".join(rows))
    tune_words = " ".join(tune_command("V", "C", Path("DIR")))
    yield_words = " ".join(simulate_command("V", ["all"], draws, ["GAINS"], Path("DIR"), False))
    parts.append(
        f"Commands (V the vehicle, C the controller): `{tune_words}`, then `{yield_words}` "
        "with each tuned gains file (and with `--switching sign`), and without `--gains` for "
        "the paper's; the 80 s runs drop `--horizon` and `--requirements`. Time: the tuning's "
        "wall time as its gains file records it."
    )
    return "\n\n".join(parts)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m experiments.vehicles")
    parser.add_argument("--out", type=Path, default=Path("results/vehicles"))
    parser.add_argument("--vehicles", default="crazyflie,iris")
    parser.add_argument("--controllers", default=",".join(CONTROLLERS))
    parser.add_argument("--draws", type=int, default=64)
    parser.add_argument("--retune", action="store_true", help="tune again what is in --out")
    parser.add_argument("--update-doc", action="store_true")
    args = parser.parse_args(argv)
    vehicles, controllers = _common.listed(args.vehicles), _common.listed(args.controllers)
    missing = [p for v in vehicles for p in files(v) if not (ROOT / p).is_file()]
    if missing:
        parser.error(f"--vehicles: no {', '.join(missing)}")
    results = {
        "vehicles": {
            v: run_vehicle(v, controllers, args.draws, args.out / v, args.retune) for v in vehicles
        },
        "command": output.invocation(),
    }
    doc = DOC if args.update_doc else None
    return _common.finish(args.out, results, table(results), doc, "vehicles")


if __name__ == "__main__":
    sys.exit(main())
