"""Tune the AFONFTSMC from the paper's gains to the example requirement set on
rotor-limited actuators (scenario 2, 10 s, thrust-to-weight 2), minimising effort, and
report the held-out yield before and after (docs/requirements.md).

    python examples/requirements/tune_paper_gains.py [outer_steps inner_steps]

About 10 minutes on 2 busy cores. What ``fojax tune --requirements FILE --method adam``
runs, on the engine (:mod:`fojax.optimize`): the objective, Adam inside the augmented
Lagrangian, the driver.
"""

import sys
import time
from pathlib import Path

import fojax
from fojax import optimize
from fojax import requirements as rq
from fojax.optimize import strategies

HERE = Path(__file__).resolve().parent


def main(outer: int = 10, inner: int = 10) -> None:
    reqs = rq.load(HERE / "small_quadrotor.toml")
    spec = optimize.ProblemSpec(controller="afonftsmc", scenario=2, horizon=10.0, draws=8)
    limit = reqs.settings.simulation_limit()
    objective = optimize.Objective(
        spec, fojax.paper_gains(), reqs, "effort", rotor_speed_limit=limit
    )
    keys = objective.keys("heldout", 64)
    print("paper's gains, held-out:", objective.evaluate(objective.x0, keys)[1], flush=True)
    adam = strategies.adam(outer * inner, 0.1, 1.0, anneal=(1.0, 1.0), sample="fixed")
    strategy = strategies.AugmentedLagrangian(adam, len(reqs), outer, inner)
    t0 = time.perf_counter()
    result = optimize.run(
        objective, strategy, optimize.Budget(steps=strategy.requests), validate_every=inner + 1
    )
    print(f"tuned in {time.perf_counter() - t0:.0f} s; selected step {result.returned_step}:")
    print(result.validation["best"])
    print("tuned gains, held-out:", objective.evaluate(result.x, keys)[1])


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:3]))
