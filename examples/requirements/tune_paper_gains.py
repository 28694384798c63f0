"""Tune the AFONFTSMC from the paper's gains to the example requirement set on
rotor-limited actuators (scenario 2, 10 s, thrust-to-weight 2), minimising effort, and
report the held-out yield before and after (docs/requirements.md).

    python examples/requirements/tune_paper_gains.py [outer_steps inner_steps]

About 10 minutes on 2 busy cores (3 of them compiling). What ``fojax tune
--requirements FILE`` will run.
"""

import json
import sys
import time
from pathlib import Path

import fojax
from fojax import requirements as rq
from fojax.optimize import constrained as co
from fojax.optimize.problem import ProblemSpec

HERE = Path(__file__).resolve().parent


def main(outer: int = 10, inner: int = 10) -> None:
    reqs = rq.load(HERE / "small_quadrotor.toml")
    spec = ProblemSpec(controller="afonftsmc", scenario=2, horizon=10.0, draws=8)
    problem = co.RequirementProblem(spec, fojax.paper_gains(), reqs, objective="effort")
    start = problem.evaluate(problem.initial_params(), problem.heldout_keys(64))
    print("paper's gains, held-out:", start["yield"].describe(), flush=True)
    config = co.ConstrainedConfig(
        formulation="mean", outer_steps=outer, inner_steps=inner, learning_rate=0.1
    )
    t0 = time.perf_counter()
    result = co.tune_to_requirements(problem, config, progress=True)
    print(f"tuned in {time.perf_counter() - t0:.0f} s; selected:", json.dumps(result.selected))
    tuned = problem.evaluate(result.params, problem.heldout_keys(64))
    print("tuned gains, held-out:", tuned["yield"].describe(), f"effort {tuned['objective']:.4g}")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:3]))
