"""What several studies share: their command lines (numeric options, the output and
smoke-run options, the gradient tuner's settings), float64, and the files every study
ends with (``results.json``, ``table.md``, a document's block). Held-out draws are
:func:`fojax.optimize.draw_keys`'s (``"heldout"``); a run kept under its fingerprint and
the studies' code is :func:`cached`'s."""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import shutil
import tempfile
from pathlib import Path
from typing import NamedTuple

import numpy as np

from fojax import records
from fojax import settings as process_settings
from fojax.cli import arguments, output


def parser(name: str, **kwargs) -> argparse.ArgumentParser:
    """The parser of ``python -m experiments.<name>``."""
    return argparse.ArgumentParser(prog=f"python -m experiments.{name}", **kwargs)


def add_numbers(
    parser, whole=arguments.positive_int, real=arguments.positive_float, **options
) -> None:
    """One option ``--name`` per ``name=default`` or ``name=(default, help)``, in that
    order (``_`` in the name becomes ``-``): of type ``whole`` where the default is an
    int, ``real`` otherwise (a float, or None: no default)."""
    for name, value in options.items():
        default, text = value if isinstance(value, tuple) else (value, None)
        kind = whole if isinstance(default, int) else real
        parser.add_argument(f"--{name.replace('_', '-')}", type=kind, default=default, help=text)


def add_outputs(parser, name: str, update_doc="markdown file to update", smoke=True) -> None:
    """``--out`` (default ``results/<name>``), ``--update-doc FILE`` and, with ``smoke``,
    ``--tiny`` and ``--quiet``."""
    parser.add_argument("--out", type=Path, default=Path(f"results/{name}"))
    parser.add_argument("--update-doc", type=Path, help=update_doc)
    if smoke:
        add_smoke(parser)


def add_smoke(parser) -> None:
    """``--tiny`` (a seconds-long smoke run) and ``--quiet``."""
    parser.add_argument("--tiny", action="store_true", help="a seconds-long smoke run")
    parser.add_argument("--quiet", action="store_true")


def listed(text: str) -> tuple[str, ...]:
    """The items of a comma-separated option, stripped, empty ones left out."""
    return tuple(s.strip() for s in text.split(",") if s.strip())


@contextlib.contextmanager
def cold_environment(prefix: str):
    """The environment of a child process that starts as on a fresh machine: a new,
    empty folder as ``HOME`` and its ``.cache`` as ``XDG_CACHE_HOME`` (no compiled
    program, no pip cache), without this process's compilation cache
    (``JAX_COMPILATION_CACHE_DIR``, ``FOJAX_COMPILE_CACHE``), ``XLA_FLAGS`` or virtual
    environment; the folder (named ``prefix...``) is removed after the ``with`` block."""
    home = Path(tempfile.mkdtemp(prefix=prefix))
    drop = ("JAX_COMPILATION_CACHE_DIR", process_settings.CACHE_VARIABLE, "XLA_FLAGS")
    env = {k: v for k, v in os.environ.items() if k not in drop + ("VIRTUAL_ENV",)}
    env.update(HOME=str(home), XDG_CACHE_HOME=str(home / ".cache"))
    try:
        yield env
    finally:
        shutil.rmtree(home, ignore_errors=True)


@functools.lru_cache(maxsize=1)
def code() -> str:
    """Digest of the code a study's numbers come from: fojax's source
    (:func:`fojax.records.source_roots`) and experiments/, once per process."""
    return records.source_digest(*records.source_roots(), Path(__file__).resolve().parent)


def cached(folder, stem: str, fingerprint, compute):
    """:func:`fojax.records.cached` keyed by the studies' :func:`code` too: a run kept
    by other code is run again."""
    return records.cached(folder, stem, fingerprint, compute, code=code())


def stored(folder, stem: str, fingerprint) -> dict | None:
    """The run :func:`cached` keeps for ``fingerprint`` and this code, or ``None``."""
    return records.stored(folder, stem, fingerprint, code=code())


def enable_float64(on: bool = True) -> None:
    """Turn on ``jax_enable_x64`` (before any array is made) where ``on``."""
    if on:
        process_settings.enable_float64()


def finish(out: Path, results: dict, text: str, doc=None, block=None, doc_text=None, wrote=None):
    """Write ``out/results.json`` and ``out/table.md`` (``text``); with ``doc``, replace
    its block ``block`` with ``doc_text`` (default ``text``); print ``text`` and, given
    ``wrote``, ``wrote <out>/results.json, table.md<wrote>``. Returns 0."""
    output.write_json(out / "results.json", results)
    (out / "table.md").write_text(text + "\n")
    if doc is not None:
        output.splice(doc, text if doc_text is None else doc_text, name=block)
    print(text)
    if wrote is not None:
        print(f"wrote {out}/results.json, table.md{wrote}")
    return 0


def yield_cell(summary: dict) -> str:
    """``passed/draws, yield % (interval %)`` of a requirement yield (its ``to_dict``),
    and its failing requirements, most failures first."""
    low, high = (100 * v for v in summary["interval"])
    failed = [(k, n) for k, n in summary["failures"].items() if n]
    failures = ", ".join(f"{n} on {k}" for k, n in sorted(failed, key=lambda kn: -kn[1]))
    return (
        f"{summary['passed']}/{summary['draws']}, {100 * summary['yield']:.1f} % "
        f"({low:.1f}-{high:.1f} %)" + (f", failures: {failures}" if failures else "")
    )


def mean_cell(entry: dict, diverged: str) -> str:
    """``mean ± half-width`` of ``entry["cost"]`` (:func:`fojax.statistics.mean_ci`), and
    ``(n <diverged>)`` where draws diverged; ``n/a`` without a mean."""
    cost = entry["cost"]
    if cost["mean"] is None:
        return "n/a"
    half = "" if not cost["ci95"] else f" ± {(cost['ci95'][1] - cost['ci95'][0]) / 2:.2g}"
    count = f" ({entry['diverged']} {diverged})" if entry["diverged"] else ""
    return f"{cost['mean']:.4g}{half}{count}"


def difference_cell(diff: dict, note=lambda low, high: "") -> str:
    """``mean [low, high]`` of a paired difference (:func:`fojax.statistics.paired_difference`),
    signed, then ``note(low, high)``; the mean alone without an interval, ``n/a`` without
    a mean."""
    if diff["mean"] is None:
        return "n/a"
    if not diff["ci95"]:
        return f"{diff['mean']:+.3g}"
    low, high = diff["ci95"]
    return f"{diff['mean']:+.3g} [{low:+.3g}, {high:+.3g}]{note(low, high)}"


def table_head(columns: str) -> list[str]:
    """A Markdown table's header row (``columns``: ``"a | b | c"``) and the line below."""
    return [f"| {columns} |", "|" + "---|" * (columns.count("|") + 1)]


def settings(args, leave_out=()) -> dict:
    """The arguments, JSON-ready (tuples as lists, paths as text), but ``leave_out``."""
    plain = {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(args).items()}
    return {
        k: (str(v) if isinstance(v, Path) else v) for k, v in plain.items() if k not in leave_out
    }


def recorded_run(objective, strategy, budget, x0, **options):
    """``(result, steps)``: :func:`fojax.optimize.run` of ``strategy`` on ``objective``
    from ``x0`` within ``budget`` (``options``: the driver's), and the driver's callback
    record of every step, ``(step, wall time (s), draw-steps, answer (d,))``. The
    answers are scored after the run (:func:`mean_costs`): nothing runs beside it."""
    from fojax import optimize

    steps = []

    def record(step, answer, row):
        steps.append((step, row["wall_time_s"], row["draw_steps"], np.array(answer)))

    result = optimize.run(objective, strategy, budget, x0, callback=record, **options)
    return result, steps


def mean_costs(objective, points, keys) -> np.ndarray:
    """The mean cost (a diverged draw at the cost's ``divergence_cost``) of each of
    ``points`` ``(P, d)`` on ``keys`` at the evaluation law; each distinct point is
    evaluated once, all in one batched call."""
    points = np.asarray(points, np.float64).reshape(-1, objective.size)
    distinct = {x.tobytes(): x for x in points}
    outputs = objective.forward(np.stack(list(distinct.values())), keys)
    means = dict(zip(distinct, objective.loss.values(outputs), strict=True))
    return np.asarray([means[x.tobytes()] for x in points], np.float64)


class DrawCosts(NamedTuple):
    """Per-draw costs of one point: cost ``(n,)`` (``J``, ``divergence_cost`` where the
    draw diverged), terms ``(n, 4)`` ``(P, A, E, C)``, status ``(n,)``, diverged ``(n,)``."""

    cost: np.ndarray
    terms: np.ndarray
    status: np.ndarray
    diverged: np.ndarray


def draw_costs(objective, x, keys, horizon=None, scenario=None):
    """Per-draw costs of the point ``x`` on ``keys`` at the evaluation law
    (:class:`DrawCosts`: a diverged draw at ``divergence_cost``); ``horizon``,
    ``scenario``: :meth:`fojax.optimize.Objective.forward`'s."""
    _, _, out = objective.evaluate(x, keys, horizon, scenario)
    cost = np.where(out.valid, out.values[:, 0], objective.spec.cost.divergence_cost)
    return DrawCosts(cost, out.terms, out.status, ~out.valid)


def to_requirements(objective, x0, method, outer_steps, inner_steps, *, validation_draws,
                    margin=0.05, progress=False, seed=0, **options):  # fmt: skip
    """Tune ``objective`` (with a requirement set) from ``x0`` as ``fojax tune
    --requirements`` does: ``method``'s strategy with its defaults under requirements
    (:data:`fojax.optimize.strategies.METHODS`; ``options``: those of them the method
    takes) inside the augmented Lagrangian (restarted after each of ``outer_steps``
    multiplier updates), ``inner_steps`` steps per outer step,
    validated on ``validation_draws`` draws after every outer step. Returns the
    driver's result."""
    from fojax import optimize
    from fojax.optimize import strategies

    taken = {k: v for k, v in options.items() if k in strategies.METHODS[method].options}
    problem = strategies.Problem(objective, x0, seed, constrained=True, outer_steps=outer_steps)
    inner = strategies.make(method, problem, inner_steps, **taken)  # restarted per outer step
    count = len(objective.requirements)
    strategy = strategies.AugmentedLagrangian(inner, count, outer_steps, inner_steps, margin=margin)
    return optimize.run(
        objective, strategy, optimize.Budget(steps=strategy.requests), x0,
        validation_draws=validation_draws, validate_every=inner_steps + 1, progress=progress,
    )  # fmt: skip
