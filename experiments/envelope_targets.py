"""The flight-envelope targets of tuned gains: each gains file and the controller's
default (the paper's) gains on held-out draws of every case of an envelope, with ``sat``
and ``sign`` (:func:`fojax.optimize.cases.evaluate_cases`), and per file whether it
diverges nowhere, tracks no worse than the defaults in every case and at most
``RATIO`` of them on average, and chatters (``sat``) no more than them in every case.

    python -m experiments.envelope_targets ENVELOPE GAINS.json [GAINS.json ...] [--draws 64]
"""

from __future__ import annotations

import argparse
import json
import sys

import jax.numpy as jnp
import numpy as np

from fojax import envelope as envelope_lib
from fojax import optimize
from fojax.controllers import gains_io, registry
from fojax.optimize import cases as cases_lib

RATIO = 0.7
"""The largest mean ratio of position RMSE to the defaults' over the cases."""


def targets(evaluation: dict, label: str, reference: str = "paper") -> dict:
    """The targets of ``label`` against ``reference`` in an :func:`evaluate_cases` result."""
    ratios, chatter, diverged, worse = [], [], 0, []
    for law, rows in evaluation["laws"].items():
        for case, row in rows.items():
            mine, ref = row[label], row[reference]
            diverged += mine["diverged"]
            if mine["position_rmse"] is None or ref["position_rmse"] is None:
                ratios.append(float("inf"))
                continue
            r = mine["position_rmse"] / ref["position_rmse"]
            ratios.append(r)
            if r > 1:
                worse.append(f"{law} {case}: RMSE x{r:.2f}")
            if law == "sat":
                c = mine["torque_chattering"] / ref["torque_chattering"]
                chatter.append(c)
                if c > 1:
                    worse.append(f"{law} {case}: chattering x{c:.2f}")
    return {
        "diverged": diverged,
        "largest_rmse_ratio": max(ratios),
        "mean_rmse_ratio": float(np.mean(ratios)),
        "largest_chattering_ratio": max(chatter) if chatter else None,
        "met": diverged == 0 and max(ratios) <= 1 and np.mean(ratios) <= RATIO
        and (not chatter or max(chatter) <= 1),
        "worse": worse,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("envelope")
    parser.add_argument("gains", nargs="+")
    parser.add_argument("--draws", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json")
    args = parser.parse_args(argv)
    env = envelope_lib.load(args.envelope)
    loaded = [gains_io.load_gains(g, jnp.float32) for g in args.gains]
    controller = loaded[0][0]
    spec = optimize.ProblemSpec(controller=controller, scenario=None, envelope=env,
                                seed=args.seed)  # fmt: skip
    gains = {"paper": registry.get_controller_class(controller).default_gains(jnp.float32)}
    gains.update({f"run{i}": g for i, (_, g, _) in enumerate(loaded)})
    evaluation = cases_lib.evaluate_cases(spec, gains, args.draws)
    print(cases_lib.table(evaluation, tuple(gains)))
    out = {"evaluation": evaluation, "targets": {}}
    for i, path in enumerate(args.gains):
        t = targets(evaluation, f"run{i}")
        out["targets"][path] = t
        print(f"{path}: met {t['met']}; diverged {t['diverged']}, RMSE ratio largest "
              f"{t['largest_rmse_ratio']:.3f} mean {t['mean_rmse_ratio']:.3f}, chattering "
              f"ratio largest {t['largest_chattering_ratio']:.3f}; "
              + "; ".join(t["worse"]))  # fmt: skip
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
