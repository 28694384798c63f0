"""``fojax reproduce``: the paper's Section V redone with Monte Carlo.

    fojax reproduce --out DIR [--draws N] [--seed S] [--switching sign|sat|tanh]
                    [--fractional soe|oustaloup|gl] [--scenarios 1,2,3] [--horizon T]
                    [--compare NAMES] [--device-batch N] [--keep N]
                    [--dtype float32|float64] [--quiet]

All three scenarios, the AFONFTSMC and the four it is compared with (ANFTSMC, FOBSMC,
BSMC, FL; ``--compare`` names others, a control law of your own included, as
``package.module:Class``), the same draws for every controller
(common random numbers: draw ``i`` of seed ``S`` is the same disturbance, drag and
mass/inertia sample for all of them). Writes to ``DIR``:

* ``report.md``: per scenario and controller each metric's mean and 95 % confidence
  interval, paired differences against the AFONFTSMC with their margins, and claim by
  claim whether the paper's Section V conclusions hold under this Monte Carlo (the
  verdict rule: :mod:`fojax.cli.reproduce.claims`);
* ``report.json``: the same numbers, with every comparison's p-values;
* ``figures/``: the paper's Figs. 5-16 redrawn from the data, Monte Carlo spread shaded;
* ``s1/``, ``s2/``, ``s3/``: each scenario's ``summary.json`` (every metric),
  ``draws.npz`` (per-draw metrics), ``trajectories.npz`` and ``chunks/`` (finished
  chunks: an interrupted run, started again with the same command, continues there).

The default size (``--draws``) is chosen to finish within 10 minutes on a 2-core CPU
(see ``DEFAULT_DRAWS``). Everything is validated before anything is compiled.

Modules: :mod:`.claims` (the claim map and the verdict rule), :mod:`.report` (Markdown
and JSON), :mod:`.command` (argparse and ``main``).
"""

from fojax.cli.reproduce.claims import (
    ALPHA,
    BASELINE,
    CHATTER_THRESHOLD,
    CLAIMS,
    MARGIN_FLOORS,
    REACHING_BAND_FACTOR,
    RELATIVE_MARGIN,
    claim_verdict,
    compare,
    decide,
    evaluate_claims,
    margin,
    paired_tables,
    reaching_band,
)
from fojax.cli.reproduce.command import DEFAULT_DRAWS, build_parser, main, parse_args
from fojax.cli.reproduce.report import TABLE_METRICS, write_report

__all__ = [
    "ALPHA",
    "BASELINE",
    "CHATTER_THRESHOLD",
    "CLAIMS",
    "DEFAULT_DRAWS",
    "MARGIN_FLOORS",
    "REACHING_BAND_FACTOR",
    "RELATIVE_MARGIN",
    "TABLE_METRICS",
    "build_parser",
    "claim_verdict",
    "compare",
    "decide",
    "evaluate_claims",
    "main",
    "margin",
    "paired_tables",
    "parse_args",
    "reaching_band",
    "write_report",
]
