"""Monte Carlo studies: chunked, vmapped rollouts of many draws, stored and summarised.

* :func:`run` (``fojax.run_monte_carlo``): draws ``0 ... n - 1`` of a scenario under
  one controller, in compiled chunks, over the devices of a mesh, resumable through a
  chunk store; :func:`make_chunk_runner` its compiled function, to share;
* :class:`ChunkStore`: one file per finished chunk, keyed by the run's settings;
* :func:`summarize`, :func:`metric_table`, :func:`status_counts`: per-metric means and
  95 % intervals over the valid draws (:mod:`fojax.statistics`).
"""

from fojax.study._run import DIVERGED, MonteCarloResult, fingerprint, make_chunk_runner, run
from fojax.study._store import ChunkStore
from fojax.study._summary import metric_table, status_counts, summarize

__all__ = [
    "DIVERGED",
    "ChunkStore",
    "MonteCarloResult",
    "fingerprint",
    "make_chunk_runner",
    "metric_table",
    "run",
    "status_counts",
    "summarize",
]
