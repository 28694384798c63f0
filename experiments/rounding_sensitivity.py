"""How much a tuner's result moves when float32 rounding moves: the reason a study's
gradient row is reproduced only by the same code on the same kind of CPU.

    python -m experiments.rounding_sensitivity [--methods adam,lbfgs] [--ulps 0,1,2]
                                               [--steps 50] [--draws 16]
                                               [--out results/rounding_sensitivity]

Runs the gradient tuner from the naive start on the study's problem (scenario 2, 10 s,
the default cost, seed 0, float32; ``experiments.tune_paper_gains``'s settings) with
every tuned gain of the start moved up by ``k`` float32 ulps (``numpy.nextafter`` ``k``
times: a relative change of about ``6e-8 k``, the size of the rounding differences
between two builds or two CPUs), and compares the returned gains
and their held-out cost (64 held-out draws, 10 s, ``sat``) with the unperturbed run's.
For comparison, CMA-ES (batched, 10 generations) from the same perturbed starts.

Writes ``results.json`` and ``table.md``; ``--update-doc FILE`` replaces the block
between ``<!-- rounding:begin -->`` and ``<!-- rounding:end -->``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from experiments import arguments

__all__ = ["main"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m experiments.rounding_sensitivity")
    parser.add_argument("--methods", default="adam,lbfgs,cma-es")
    parser.add_argument("--ulps", default="0,1,2")
    parser.add_argument("--steps", type=arguments.positive_int, default=50)
    parser.add_argument("--draws", type=arguments.positive_int, default=16)
    parser.add_argument("--cma-generations", type=arguments.positive_int, default=10)
    parser.add_argument("--heldout-draws", type=arguments.positive_int, default=64)
    parser.add_argument("--out", type=Path, default=Path("results/rounding_sensitivity"))
    parser.add_argument("--update-doc", type=Path)
    parser.add_argument("--quiet", action="store_true")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    ulps = tuple(int(k) for k in args.ulps.split(","))
    import jax.numpy as jnp

    from experiments.tuning_study import run_context
    from optimize import derivative_free
    from optimize import params as params_lib
    from optimize import problem as problem_lib
    from optimize import tuner as tuner_lib

    context = run_context(["python", "-m", "experiments.rounding_sensitivity", *(argv or [])])
    start_all = time.perf_counter()
    spec = problem_lib.ProblemSpec(horizon=10.0, draws=args.draws, seed=0)
    naive = params_lib.naive_gains("afonftsmc", jnp.float32)
    problem = problem_lib.TuningProblem(spec, naive)
    heldout = problem.heldout_keys(args.heldout_draws)
    tuned = problem.param_map.names

    def perturbed(k):
        """The naive gains, each tuned value moved up by ``k`` float32 ulps."""
        values = {}
        for name in tuned:
            value = np.asarray(getattr(naive, name), np.float32)
            for _ in range(k):
                value = np.nextafter(value, np.float32(np.inf))
            values[name] = jnp.asarray(value)
        return naive._replace(**values)

    runs = []
    for method in methods:
        for k in ulps:
            gains_start = perturbed(k)
            t0 = time.perf_counter()
            if method == "cma-es":
                per_generation = 14 * args.draws * spec.steps
                result = derivative_free.cma_es(
                    problem,
                    args.cma_generations * per_generation,
                    x0=problem.params_of(gains_start),
                )
                gains, step, last = result.gains, None, None
            else:
                config = tuner_lib.TunerConfig(
                    steps=args.steps, method=method, learning_rate=0.1, checkpoint_every=10**6
                )
                run = tuner_lib.prepare(spec, config, gains_start, f"naive+{k}ulp", None)
                result = tuner_lib.tune(run, progress=False, problem=problem)
                gains, step = result.gains, result.best_step
                last = problem_lib.evaluate(spec, problem.gains(result.final_params), heldout).cost
                last = float(np.mean(np.asarray(last, np.float64)))
            cost = problem_lib.evaluate(spec, gains, heldout).cost
            runs.append(
                {
                    "method": method,
                    "ulps": k,
                    "heldout": float(np.mean(np.asarray(cost, np.float64))),
                    "returned_step": step,
                    "heldout_last_iterate": last,
                    "gains": {
                        f: np.asarray(v, np.float64).tolist() for f, v in gains._asdict().items()
                    },
                    "seconds": round(time.perf_counter() - t0, 1),
                }
            )
            if not args.quiet:
                print(f"{method} +{k} ulp: held-out {runs[-1]['heldout']:.5g}", file=sys.stderr)
    for r in runs:
        base = next(b for b in runs if b["method"] == r["method"] and b["ulps"] == ulps[0])
        r["max_abs_log_ratio_to_unperturbed"] = max(
            float(np.max(np.abs(np.log(np.asarray(r["gains"][f]) / np.asarray(base["gains"][f])))))
            for f in r["gains"]
        )
    results = {
        "runs": runs,
        "provenance": context,
        "total_wall_time_s": round(time.perf_counter() - start_all, 1),
    }
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    text = table(results)
    (out / "table.md").write_text(text + "\n")
    if args.update_doc is not None:
        from experiments.remark3 import replace_block

        replace_block(args.update_doc, "rounding", text)
    print(text)
    return 0


def table(results: dict) -> str:
    from experiments.tuning_study import commit_label

    lines = [
        "| tuner | start moved by | held-out cost of the returned gains (10 s, 64 draws) "
        "| returned step | held-out cost of the last iterate | largest change of a gain "
        "against the unmoved start's run (abs. log ratio) |",
        "|---|---|---|---|---|---|",
    ]
    for r in results["runs"]:
        step = "-" if r["returned_step"] is None else str(r["returned_step"])
        last = r.get("heldout_last_iterate")
        last = "-" if last is None else f"{last:.5g}"
        lines.append(
            f"| {r['method']} | {r['ulps']} ulp | {r['heldout']:.5g} | {step} | {last} | "
            f"{r['max_abs_log_ratio_to_unperturbed']:.2g} |"
        )
    p = results["provenance"]
    lines += [
        "",
        f"(`{p['command']}`, commit {commit_label(p)}, {p.get('cpu_model')}; "
        f"{results['total_wall_time_s']:.0f} s.)",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
