"""Test configuration: float64 available, persistent compilation cache, two tiers.

The default tier runs in minutes; ``--slow`` adds the slow tier (tests marked
``@pytest.mark.slow``: end-to-end studies, multi-process runs, full horizons and the
optimised-compile layout check) and the cases of ``SLOW_CASES``; an entry there that
matches no test of a file collected whole stops the run (a rename would otherwise move
its case into the default tier unnoticed)."""

import os
import pathlib

# The tests run short horizons, so compilation dominates their time: skip LLVM's
# optimisation passes (compiles about 1.6x faster; the arithmetic is still IEEE, and
# every comparison of two runs is within one build). Set before JAX starts.
_flags = os.environ.get("XLA_FLAGS", "")
if "xla_backend_optimization_level" not in _flags:
    os.environ["XLA_FLAGS"] = f"{_flags} --xla_backend_optimization_level=0".strip()

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
_cache = os.environ.get(
    "FOJAX_TEST_CACHE", str(pathlib.Path(__file__).resolve().parent.parent / ".jax_cache")
)
jax.config.update("jax_compilation_cache_dir", _cache)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def pytest_addoption(parser):
    parser.addoption(
        "--slow",
        action="store_true",
        help="also run the slow tier (end-to-end studies, multi-process runs)",
    )


# Cases of the slow tier besides the tests marked in their files: each checks again,
# on another controller, scenario, method or precision, what a case of the default
# tier checks (the default keeps one golden forward per controller, the AFONFTSMC's
# golden gradient, the tuner's finite-difference gradient, the driver's resume; the
# augmented Lagrangian on the toy problem), compiles a program of its own for one
# property (cache reuse, device split, batch independence, chunked benches, a union's
# members), or runs a command or a tuner whole.
SLOW_CASES = (
    "test_golden.py::test_forward_matches_saved[f/afonftsmc/s1",
    "test_golden.py::test_forward_matches_saved[f/afonftsmc/s3",
    "test_golden.py::test_forward_matches_saved[f/afonftsmc/s2/sat/gl]",
    "test_golden.py::test_forward_matches_saved[f/afonftsmc/s2/sat/oustaloup]",
    "test_golden.py::test_forward_matches_saved[f/anftsmc/s1",
    "test_golden.py::test_forward_matches_saved[f/anftsmc/s3",
    "test_golden.py::test_forward_matches_saved[f/bsmc/s1",
    "test_golden.py::test_forward_matches_saved[f/bsmc/s3",
    "test_golden.py::test_forward_matches_saved[f/fl/s1",
    "test_golden.py::test_forward_matches_saved[f/fl/s3",
    "test_golden.py::test_forward_matches_saved[f/fobsmc/s1",
    "test_golden.py::test_forward_matches_saved[f/fobsmc/s3",
    "test_golden.py::test_forward_matches_saved[f/fobsmc/s2/sat/oustaloup]",
    "test_golden.py::test_gradient_matches_saved[g/anftsmc",
    "test_golden.py::test_gradient_matches_saved[g/bsmc",
    "test_golden.py::test_gradient_matches_saved[g/fl",
    "test_golden.py::test_gradient_matches_saved[g/fobsmc",
    "test_golden.py::test_gradient_matches_saved[g/afonftsmc/s3",
    "test_controllers.py::test_gradient_with_respect_to_gains_matches_finite_differences",
    "test_simulator.py::test_gradient_with_respect_to_gains_matches_finite_differences",
    "test_simulator.py::test_vmap_equals_loop_and_draws_do_not_depend_on_batch",
    "test_scenarios.py::test_a_union_runs_each_member_as_it_runs_alone[float64]",
    "test_montecarlo.py::test_a_union_member_runs_as_its_scenario_alone",
    "test_study_union.py::test_studies_of_three_scenarios_compile_one_program_per_controller",
    "test_study_union.py::test_float32_and_a_horizon_dependent_operator_stay_within_rounding",
    "test_sensitivity.py::test_union_runner_equals_study_run_float64",
    "test_runtime_options.py::test_a_second_run_reads_its_programs_from_the_cache",
    "test_tune_cli.py::test_tuning_study_smoke",
    "test_requirements_tuner.py::test_a_union_objective_alternates_members",
    "test_requirements_tuner.py::test_lagrangian_gradient_matches_finite_differences",
    "test_requirements_cli.py::test_tune_to_requirements_resumes_to_the_uninterrupted_gains",
    "test_performance.py::test_sharded_run_is_identical_to_single_device_run",
    "test_performance.py::test_bench_forward_runs_big_batches_in_chunks",
    "test_performance.py::test_bench_smoke",
    "test_performance.py::test_numpy_reference_agrees_with_jax_rollout[tanh]",
    "test_evaluate_in_blocks.py::test_blocks_give_a_direct_calls_numbers_in_float64",
    # Whole runs of a command or of a tuner on the simulator (each compiles its forward
    # and gradient programs); their parts are checked in the default tier.
    "test_tune_cli.py::test_tune_end_to_end_resume_and_refusals",
    "test_requirements_cli.py::test_tune_to_requirements_writes_gains_and_heldout_yield",
    "test_requirements_cli.py::test_simulate_requirements_yield_matches_per_draw_metrics",
    "test_requirements_tuner.py::test_tuning_raises_the_heldout_yield_from_a_failing_start",
    "test_requirements_tuner.py::test_the_run_returns_its_best_validated_iterate",
    "test_requirements_tuner.py::test_an_interrupted_lagrangian_run_resumes_to_the_uninterrupted_result",
    "test_simulate_cli.py::test_simulate_end_to_end_tiny",
    "test_reproduce.py::test_a_controller_compared_with_itself_is_equivalent_end_to_end",
    "test_scenarios.py::test_a_union_runs_each_member_as_it_runs_alone[float32]",
)


# The files whose slow tier takes longest (the tuning studies' end-to-end runs, the
# Ctrl-C and resume runs, the envelope's tune, multi-process runs, the wheel), longest
# first: with --slow they are collected first, so that pytest-xdist (--dist loadfile
# hands out files in collection order) starts them first and the short files fill in
# behind them, rather than a long file starting last on one worker while the other idles.
LONG_FILES = (
    "test_tuning_studies.py",
    "test_tune_cli.py",
    "test_envelope.py",
    "test_distributed.py",
    "test_packaging.py",
    "test_fair_comparison.py",
)


def _is_slow(item) -> bool:
    return "slow" in item.keywords or item.nodeid.removeprefix("tests/").startswith(SLOW_CASES)


def dead_slow_cases(nodeids, partial_files=()) -> list[str]:
    """The :data:`SLOW_CASES` entries that start no collected test id of ``nodeids``
    (``tests/``-relative or not), judged only for test files that were collected whole
    (a file of ``partial_files``, selected by test id, is not)."""
    ids = [nodeid.removeprefix("tests/") for nodeid in nodeids]
    whole = {nodeid.split("::", 1)[0] for nodeid in ids} - set(partial_files)
    return [
        entry
        for entry in SLOW_CASES
        if entry.split("::", 1)[0] in whole and not any(i.startswith(entry) for i in ids)
    ]


@pytest.hookimpl(tryfirst=True)  # before -k and -m deselect: judge every collected test
def pytest_collection_modifyitems(session, config, items):
    partial = {pathlib.Path(arg.split("::", 1)[0]).name for arg in config.args if "::" in str(arg)}
    dead = dead_slow_cases([item.nodeid for item in items], partial)
    if dead:
        message = (
            "tests/conftest.py: SLOW_CASES entries that match no collected test (renamed or "
            "removed? a case would run in the default tier unnoticed): " + ", ".join(dead)
        )
        if hasattr(config, "workerinput"):  # an xdist worker: the controller stops the run
            session.shouldfail = message
            items[:] = []
            return
        raise pytest.UsageError(message)
    if config.getoption("--slow"):
        rank = {name: i for i, name in enumerate(LONG_FILES)}
        items.sort(key=lambda item: rank.get(item.path.name, len(LONG_FILES)))  # stable
        return
    slow = [item for item in items if _is_slow(item)]
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = [item for item in items if not _is_slow(item)]


def close_normwise(got, want, err_msg=""):
    """float32 comparison of two programs that may fuse and round apart: non-finite
    values equal, the largest difference within 1e-4 of the array's largest magnitude
    (a few 1e-5 of a signal's scale were measured on CPUs of different vector widths).
    Import it: ``from conftest import close_normwise``."""
    import numpy as np

    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    finite = np.isfinite(want)
    np.testing.assert_array_equal(got[~finite], want[~finite], err_msg=err_msg)
    got, want = got[finite], want[finite]
    scale = max(float(np.max(np.abs(want), initial=0.0)), 1e-6)
    worst = float(np.max(np.abs(got - want), initial=0.0))
    assert worst <= 1e-4 * scale, f"{err_msg}: max difference {worst:.3g} against scale {scale:.3g}"


def drive(evaluate, strategy, x0, requests: int):
    """A strategy's state after ``requests`` requests evaluated by ``evaluate(request) ->
    Evaluation`` (no driver): the strategies' tests on analytic functions. Import it:
    ``from conftest import drive``."""
    import numpy as np

    state = strategy.init(np.asarray(x0, np.float64))
    for _ in range(requests):
        request = strategy.ask(state)
        state = strategy.tell(state, request, evaluate(request))
    return state


def usage_error(capsys, main, argv) -> str:
    """stderr of ``main(argv)``, which must exit with argparse's status 2 and no traceback.
    Import it: ``from conftest import usage_error``."""
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


def run_python(*args: str, env=None, timeout: float = 600) -> str:
    """stdout of ``python *args`` (e.g. ``"-c", script``) in a fresh process, which must
    exit with status 0 (its stderr's end is the failure's message). Import it:
    ``from conftest import run_python``."""
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, *args], env=env, capture_output=True, text=True, timeout=timeout
    )
    assert done.returncode == 0, done.stderr[-4000:]
    return done.stdout


def vehicle_table(**changes) -> dict:
    """The paper's vehicle as a vehicle file's content, with ``changes`` to its [vehicle]
    table (a value of None removes the field)."""
    from fojax import vehicle

    paper = vehicle.Vehicle.paper()
    table = {
        name: {"value": list(v) if isinstance(v, tuple) else v, "unit": field.unit}
        for name, field in vehicle.FIELDS.items()
        for v in [getattr(paper, name)]
    }
    for name, value in changes.items():
        if value is None:
            table.pop(name)
        else:
            table[name] = value
    return {"description": "test", "vehicle": table}
