"""Monte Carlo studies: chunked, vmapped rollouts of many draws, stored and summarised.

* :class:`Study` (a declaration: the scenario, the controllers run on the same draws,
  their gains, the draws, the seed and the settings), :func:`run_study`,
  :func:`run_studies`: the study engine the commands are a thin layer over
  (:mod:`fojax.cli.study`): each controller's draws in a store under the study's
  folder, checked before anything compiles (:func:`check_stores`), studies that differ
  only in their scenario run as members of one union (:func:`plan_unions`), programs
  compiled in worker threads while earlier runs compute (:func:`compile_threads`);

* :func:`run` (``fojax.run_monte_carlo``): draws ``0 ... n - 1`` of a scenario under
  one controller, in fixed blocks of draws, one per device and call, over the devices
  (and processes) of a mesh, resumable and extendable through a store; draw ``i``'s
  numbers do not depend on the draw count, the devices or the processes (only on the
  block size, :func:`default_device_batch`); :func:`make_chunk_runner` and
  :func:`compile_chunk_runner` its compiled function, to share (or compile ahead, in a
  thread); for a union of scenarios (:func:`fojax.scenarios.union`) one compiled
  function serves every member (``run(..., member=i)``);
* :class:`ChunkStore`: one file per finished range of draws, keyed by
  :func:`fingerprint`; :class:`StoreMismatch` names the settings that differ,
  :func:`manifest_differences` lists them before anything runs
  (:func:`fingerprint_differences`, :func:`describe_differences`: those of
  :mod:`fojax.records`);
* :func:`evaluate_in_blocks` (:mod:`fojax.blocks`): any per-draw function over many
  draws in blocks, one per device and call, the same numbers as a direct call;
  :class:`EvaluatorCache`: compiled evaluators, a bounded number;
* :func:`summarize`, :func:`metric_table`, :func:`status_counts`: per-metric means and
  95 % intervals over the valid draws (:mod:`fojax.statistics`).
"""

from fojax.blocks import EvaluatorCache, evaluate_in_blocks
from fojax.records import describe as describe_differences
from fojax.records import differences as fingerprint_differences
from fojax.study._declaration import (
    Study,
    UnionMember,
    check_stores,
    options_applied_to,
    prepare_runs,
    scenario_of,
    snapshot_interval,
    store_fingerprint,
)
from fojax.study._jobs import compile_threads, run_studies, run_study
from fojax.study._run import (
    DEVICE_BATCH,
    DIVERGED,
    MAX_DRAWS,
    MAX_SEED,
    OTHER_DEVICE_BATCH,
    MonteCarloResult,
    batch_layout,
    check_member,
    check_run_arguments,
    check_settings,
    compile_chunk_runner,
    default_device_batch,
    fingerprint,
    make_chunk_runner,
    numeric_xla_flags,
    run,
)
from fojax.study._store import ChunkStore, StoreMismatch, manifest_differences
from fojax.study._summary import metric_table, status_counts, summarize
from fojax.study._unions import plan_unions, union_enabled

__all__ = [
    "Study",
    "UnionMember",
    "check_stores",
    "compile_threads",
    "options_applied_to",
    "plan_unions",
    "prepare_runs",
    "run_studies",
    "run_study",
    "scenario_of",
    "snapshot_interval",
    "store_fingerprint",
    "union_enabled",
    "DIVERGED",
    "MAX_DRAWS",
    "MAX_SEED",
    "DEVICE_BATCH",
    "ChunkStore",
    "EvaluatorCache",
    "OTHER_DEVICE_BATCH",
    "MonteCarloResult",
    "StoreMismatch",
    "batch_layout",
    "check_member",
    "check_run_arguments",
    "check_settings",
    "compile_chunk_runner",
    "default_device_batch",
    "describe_differences",
    "evaluate_in_blocks",
    "fingerprint",
    "fingerprint_differences",
    "make_chunk_runner",
    "manifest_differences",
    "metric_table",
    "numeric_xla_flags",
    "run",
    "status_counts",
    "summarize",
]
