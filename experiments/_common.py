"""What several studies share: their command lines (numeric options, the output and
smoke-run options, the gradient tuner's settings), float64, and the files every study
ends with (``results.json``, ``table.md``, a document's block). Held-out draws are
:func:`fojax.optimize.draw_keys`'s (``"heldout"``); a run kept under its fingerprint is
:func:`fojax.records.cached`'s."""

from __future__ import annotations

import argparse
from pathlib import Path

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


def enable_float64(on: bool = True) -> None:
    """Turn on ``jax_enable_x64`` (before any array is made) where ``on``."""
    if on:
        import jax

        jax.config.update("jax_enable_x64", True)


def tuner_config(args, steps: int, validation_draws: int, **fields):
    """The gradient tuner's settings (:class:`fojax.optimize.tuner.TunerConfig`) of a
    study with ``--gradient-method``, ``--learning-rate``, ``--max-step`` and
    ``--validate-every``; ``fields``: other settings."""
    from fojax.optimize.tuner import TunerConfig

    given = {k: getattr(args, k) for k in ("learning_rate", "max_step", "validate_every")}
    given.update(steps=steps, method=args.gradient_method, validation_draws=validation_draws)
    return TunerConfig(**given, **fields)


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


def mean_cell(entry: dict, diverged: str) -> str:
    """``mean ± half-width`` of ``entry["cost"]`` (:func:`fojax.statistics.mean_ci`), and
    ``(n <diverged>)`` where draws diverged; ``n/a`` without a mean."""
    cost = entry["cost"]
    if cost["mean"] is None:
        return "n/a"
    half = "" if not cost["ci95"] else f" ± {(cost['ci95'][1] - cost['ci95'][0]) / 2:.2g}"
    count = f" ({entry['diverged']} {diverged})" if entry["diverged"] else ""
    return f"{cost['mean']:.4g}{half}{count}"


def table_head(columns: str) -> list[str]:
    """A Markdown table's header row (``columns``: ``"a | b | c"``) and the line below."""
    return [f"| {columns} |", "|" + "---|" * (columns.count("|") + 1)]


def settings(args, leave_out=()) -> dict:
    """The arguments, JSON-ready (tuples as lists, paths as text), but ``leave_out``."""
    plain = {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(args).items()}
    return {
        k: (str(v) if isinstance(v, Path) else v) for k, v in plain.items() if k not in leave_out
    }
