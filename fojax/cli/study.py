"""The study layer shared by the commands: the study engine of :mod:`fojax.study` (a
study's declaration, its unions of scenarios, compile threads and runs) with the
commands' names for the settings a store was written with, and what every output
records to be rerun exactly.

* :class:`Study`, :func:`run_study`, :func:`run_studies`: :mod:`fojax.study`'s, with
  a store's differences named by the option that sets each field and the advice to
  add ``--overwrite`` (``fojax simulate``; ``fojax reproduce`` runs one per scenario);
  its files: :func:`fojax.cli.study_files.write_outputs`.
* :func:`provenance` (:mod:`fojax.cli.output`): the command line, versions (fojax and
  its git commit, Python, JAX, jaxlib, NumPy), backend and device and process counts;
  :func:`gains_record`: the gains' values and where they came from. ``fojax
  simulate``, ``tune`` and ``bench`` store both with their results.
* :func:`write_json` (:mod:`fojax.records`): atomic JSON files.
"""

from __future__ import annotations

import os
from pathlib import Path

from fojax.cli.output import provenance, write_json
from fojax.controllers import gains_io
from fojax.study import (
    StoreMismatch,
    Study,
    UnionMember,
    compile_threads,
    options_applied_to,
    plan_unions,
    prepare_runs,
    snapshot_interval,
    union_enabled,
)
from fojax.study import run_studies as _run_studies
from fojax.study import run_study as _run_study

__all__ = [
    "Study",
    "StoreMismatch",
    "UnionMember",
    "compile_threads",
    "gains_record",
    "options_applied_to",
    "plan_unions",
    "prepare_runs",
    "provenance",
    "run_studies",
    "run_study",
    "snapshot_interval",
    "union_enabled",
    "write_json",
]

ADVICE = "to start afresh, add --overwrite (discards those draws), or choose another --out"
"""The last line of a command's :class:`StoreMismatch`."""


# ------------------------------------------------------------------------- provenance


def gains_record(gains, source: str | os.PathLike | None) -> dict:
    """``{"source": absolute file path or "defaults", "values": {field: value}}``: the
    values as the run used them (after the cast to its dtype)."""
    return {
        "source": str(Path(source).resolve()) if source is not None else "defaults",
        "values": gains_io.gains_to_dict(gains),
    }


# ---------------------------------------------------------------------- the chunk store


_FLAGS = {
    "seed": "--seed",
    "dtype": "--dtype",
    "device_batch": "--device-batch",
    "xla_flags": "XLA_FLAGS",
    "backend": "the platform: cpu or gpu draws round differently",
    "store_format": "stored by an earlier fojax",
    "gains": "--gains",
    "controller_config.law.switching": "--switching",
    "controller_config.law.fractional_method": "--fractional",
    "controller_config.law.dt": "--dt",
    "controller_config.law.horizon": "--horizon",
    "scenario.horizon": "--horizon",
    "simulation.horizon": "--horizon",
    "simulation.dt": "--dt",
    "simulation.rotor_speed_limit": "--rotor-limit or the requirement file's rotor limit",
    "simulation.save_every": "snapshot interval (follows --horizon and --dt)",
    "metrics": "metric settings (follow --horizon and --dt)",
}


def _flag(field: str) -> str:
    matches = [prefix for prefix in _FLAGS if field == prefix or field.startswith(prefix + ".")]
    return _FLAGS[max(matches, key=len)] if matches else ""


def run_studies(
    studies: list[tuple[Study, Path]],
    progress: bool = True,
    overwrite: bool = False,
    threads: int | None = None,
    announce=None,
    settings=None,
):
    """:func:`fojax.study.run_studies`, each field of a store of other
    settings named by the option that sets it, with :data:`ADVICE`."""
    return _run_studies(
        studies, progress, overwrite, threads, announce, settings, hint=_flag, advice=ADVICE
    )


def run_study(
    study: Study, out: Path, progress: bool = True, overwrite: bool = False, settings=None
) -> dict:
    """:func:`fojax.study.run_study`, each field of a store of other
    settings named by the option that sets it, with :data:`ADVICE`."""
    return _run_study(study, out, progress, overwrite, settings, hint=_flag, advice=ADVICE)
