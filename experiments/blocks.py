"""Every generated block of README.md and docs/: the command that regenerates it, the
source paths its numbers depend on, and the checks of its label.

A generator writes its block with :func:`fojax.cli.output.splice`, which starts it with
a label (:func:`fojax.cli.output.block_label`: command, commit, machine, load,
versions). :data:`BLOCKS` lists the blocks in the order ``python -m
experiments.regenerate_docs`` runs their commands (a later one may reuse an earlier
one's results). :func:`problems` says what is wrong with one block's label (none, made
with uncommitted changes, a commit not in the history, sources changed since);
:func:`check_docs` checks every block and that the docs hold no block this registry
does not list.
"""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
from pathlib import Path

from experiments import regenerate_reproduction, sensitivity_report
from fojax.cli import output

__all__ = ["BLOCKS", "ROOT", "Block", "block_text", "check_docs", "problems", "read_label"]

ROOT = Path(__file__).resolve().parent.parent


@dataclasses.dataclass(frozen=True)
class Block:
    """One generated block: ``name``, the ``document`` holding it (relative to the
    repository root), the ``command`` that regenerates it (run from the root), the
    ``sources`` (files or folders) its numbers depend on, ``marker``: for a block that
    is everything below a marker line, that line (otherwise the block is between
    ``<!-- name:begin -->`` and ``<!-- name:end -->``), and ``results``: the folder
    where its command keeps results that a later run reuses (``None``: none). timed:
    whether a full regeneration runs it and keeps its time (``False``: a block made of
    the others' times, rewritten after each of them)."""

    name: str
    document: str
    command: tuple[str, ...]
    sources: tuple[str, ...]
    marker: str | None = None
    results: str | None = None
    timed: bool = True


# What the numbers depend on: the pinned versions and the closed loop; Monte Carlo
# studies add the study layer, tuning studies the tuner.
_CLOSED_LOOP = (
    "constraints.txt",
    "fojax/_arrays.py",
    "fojax/controllers",
    "fojax/draws.py",
    "fojax/fractional",
    "fojax/metrics.py",
    "fojax/observers.py",
    "fojax/plant.py",
    "fojax/scenarios.py",
    "fojax/simulator.py",
    "fojax/statistics.py",
)
_MONTE_CARLO = (
    *_CLOSED_LOOP,
    "fojax/sharding.py",
    "fojax/study",
    "fojax/cli/simulate.py",
    "fojax/cli/study.py",
    "fojax/cli/study_files.py",
)
# The reproduction's report and figures (the paper's figures draw with fojax.cli.figures).
_REPORT = ("fojax/cli/reproduce", "fojax/cli/figures.py", "fojax/cli/style.py")
_TUNING = (
    *_CLOSED_LOOP,
    "fojax/blocks.py",
    "fojax/sharding.py",
    "optimize",
    "experiments/_common.py",
)
_REQUIREMENTS = (*_TUNING, "fojax/requirements", "fojax/cli/requirements.py")
_REQUIREMENTS_STUDY = (
    *_REQUIREMENTS,
    "experiments/requirements_study.py",
)


_BENCH = (
    *_CLOSED_LOOP,
    "fojax/settings.py",
    "fojax/sharding.py",
    "fojax/cli/bench.py",
    "fojax/cli/bench_measure.py",
    "fojax/cli/numpy_reference.py",
    "experiments/bench_report.py",
)


def _study(module: str, *options: str) -> tuple[str, ...]:
    return ("python", "-m", f"experiments.{module}", *options)


BLOCKS: dict[str, Block] = {
    block.name: block
    for block in (
        Block(  # fojax bench's default sizes, run here
            "bench",
            "docs/performance.md",
            _study("bench_report", "--json", "results/bench/bench.json")
            + ("--update-doc", "docs/performance.md"),
            _BENCH,
        ),
        *(  # the example reports, one per switching function
            Block(
                document.replace("_", "-"),
                f"docs/{document}.md",
                _study("regenerate_reproduction", "--only", switching),
                (*_MONTE_CARLO, *_REPORT, "experiments/regenerate_reproduction.py"),
                regenerate_reproduction.MARKER,
                f"results/{folder}",
            )
            for switching, (folder, _, document) in regenerate_reproduction.RUNS.items()
        ),
        Block(  # fojax accuracy: every fractional method against exact results
            "accuracy",
            "docs/fractional.md",
            _study("accuracy_report", "--update-doc"),
            ("constraints.txt", "fojax/fractional", "fojax/cli/accuracy.py")
            + ("experiments/accuracy_report.py",),
        ),
        Block(  # one process against two jax.distributed processes on this machine
            "distributed",
            "docs/distributed.md",
            _study("distributed_timing", "--update-doc"),
            (*_MONTE_CARLO, "fojax/cli/arguments.py", "experiments/distributed_timing.py"),
        ),
        Block(
            "sensitivity",
            "docs/sensitivity.md",
            _study("sensitivity"),
            (
                *_MONTE_CARLO,
                "optimize",
                "fojax/requirements",
                "fojax/cli/reproduce/claims.py",
                "experiments/fair_comparison.py",
                "experiments/sensitivity.py",
                "experiments/sensitivity_plan.py",
                "experiments/sensitivity_report.py",
            ),
            sensitivity_report.MARKER,
            "results/sensitivity",
        ),
        Block(  # reuses the tuning of the sensitivity study (its --out)
            "fair-comparison",
            "docs/tuning.md",
            _study(
                "fair_comparison",
                *("--out", "results/sensitivity/tuning", "--steps", "20", "--draws", "8"),
                *("--horizon", "5", "--update-doc", "docs/tuning.md"),
            ),
            (*_TUNING, "experiments/fair_comparison.py"),
            results="results/sensitivity/tuning",
        ),
        Block(
            "tuning-study",
            "docs/tuning.md",
            _study(
                "tuning_study",
                *("--out", "results/tuning_study", "--bench", "5", "--user-view", "2"),
                *("--update-doc", "docs/tuning.md"),
            ),
            (
                *_TUNING,
                "fojax/cli/tune.py",
                "experiments/tuning_study.py",
                "experiments/tuning_study_report.py",
                "experiments/tuning_study_user.py",
            ),
            results="results/tuning_study",
        ),
        Block(
            "tune-paper-gains",
            "docs/tuning.md",
            _study("tune_paper_gains", "--out", "results/tune_paper_gains", "--update-doc")
            + ("docs/tuning.md",),
            (*_TUNING, "experiments/tune_paper_gains.py"),
            results="results/tune_paper_gains",
        ),
        Block(
            "tune-memory",
            "docs/tuning.md",
            _study("tune_memory", "--horizons", "5", "10", "20", "40", "80")
            + ("--execute-up-to", "10", "--update-doc", "docs/tuning.md"),
            (*_TUNING, "experiments/tune_memory.py"),
        ),
        Block(
            "remark3",
            "docs/tuning.md",
            _study("remark3", "--out", "results/remark3", "--update-doc", "docs/tuning.md"),
            (*_TUNING, "experiments/remark3.py"),
        ),
        Block(
            "requirements-study",
            "docs/requirements.md",
            _study("requirements_study", "--update-doc"),
            _REQUIREMENTS_STUDY,
            results="results/requirements_study",
        ),
        Block(
            "requirements-study-union",
            "docs/requirements.md",
            _study(
                "requirements_study",
                *("--tune-scenario", "2,3", "--controllers", "afonftsmc,fobsmc,bsmc,fl"),
                *("--out", "results/requirements_union", "--update-doc"),
            ),
            _REQUIREMENTS_STUDY,
            results="results/requirements_union",
        ),
        Block(  # fojax tune --requirements per method, each cold in a fresh process
            "requirements-methods",
            "docs/requirements.md",
            _study("requirements_methods", "--update-doc"),
            (
                *_REQUIREMENTS,
                "fojax/cli/tune.py",
                "examples/requirements/small_quadrotor.toml",
                "experiments/requirements_methods.py",
            ),
        ),
        Block(
            "remark3-inverted",
            "docs/requirements.md",
            _study("remark3_inverted", "--update-doc"),
            (
                *_REQUIREMENTS,
                "experiments/remark3.py",
                "experiments/remark3_inverted.py",
                "experiments/remark3_inverted_report.py",
            ),
            results="results/remark3_inverted",
        ),
        Block(  # rendered from the JSON of a run on a GPU machine (last: it runs nothing)
            "bench-gpu",
            "docs/performance.md",
            _study("bench_report", "--from", "docs/data/bench_gpu.json", "--name", "bench-gpu")
            + ("--update-doc", "docs/performance.md"),
            _BENCH,
        ),
        Block(
            "bench-gpu-large",
            "docs/performance.md",
            _study("bench_report", "--from", "docs/data/bench_gpu_large.json")
            + ("--name", "bench-gpu-large", "--update-doc", "docs/performance.md"),
            _BENCH,
        ),
        Block(  # README's two commands from a fresh clone (its own processes, ~10 min)
            "setup",
            "README.md",
            _study("setup_timing", "--update-doc"),
            ("constraints.txt", "pyproject.toml", "fojax", "tests", "experiments/setup_timing.py"),
        ),
        Block(  # each block's last regeneration time (rewritten after every block)
            "regeneration",
            "README.md",
            _study("regenerate_docs", "--render"),
            ("experiments/blocks.py", "experiments/regenerate_docs.py"),
            timed=False,
        ),
    )
}


# ------------------------------------------------------------------------ reading


def block_text(content: str, block: Block) -> str | None:
    """The text of ``block`` in a document's ``content`` (between its begin and end
    lines, or below its marker line), or ``None`` where the document has no such block."""
    if block.marker is not None:
        head, found, rest = content.partition(block.marker)
        return rest if found else None
    begin, end = f"<!-- {block.name}:begin -->", f"<!-- {block.name}:end -->"
    if begin not in content:
        return None
    inner, found, _ = content.split(begin, 1)[1].partition(end)
    return inner if found else None


def read_label(text: str) -> dict | None:
    """The label record at the top of a block's ``text`` (its first non-blank line,
    written by :func:`fojax.cli.output.block_label`), or ``None`` where there is none."""
    first = text.lstrip().split("\n", 1)[0]
    if not (first.startswith(output.LABEL_PREFIX) and first.endswith(" -->")):
        return None
    try:
        record = json.loads(first[len(output.LABEL_PREFIX) : -len(" -->")])
    except ValueError:
        return None
    return record if isinstance(record, dict) else None


# ----------------------------------------------------------------------- checking


def _git(root: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True)


def problems(block: Block, root: Path | None = None, stale: bool = True) -> list[str]:
    """What is wrong with ``block`` in the checkout ``root``: missing from its document,
    no label, generated with uncommitted changes, a commit that is not in the history
    of ``HEAD``, or (with ``stale``) a commit older than the last commit that changed its
    sources (git log). ``root``: default :data:`ROOT`. ``[]`` when it is current."""
    root = ROOT if root is None else Path(root)
    path = root / block.document
    text = block_text(path.read_text(), block) if path.is_file() else None
    if text is None:
        return [f"{block.name}: {block.document} has no such block"]
    again = f"regenerate it: {' '.join(block.command)}"
    label = read_label(text)
    if label is None:
        return [f"{block.name} ({block.document}): no label; {again}"]
    commit = str(label.get("commit") or "")
    found = []
    if label.get("dirty") is not False:
        found.append(f"{block.name}: generated with uncommitted changes ({again})")
    if not commit or _git(root, "cat-file", "-e", f"{commit}^{{commit}}").returncode != 0:
        return [*found, f"{block.name}: its commit {commit or '(none)'} is not in this repository"]
    if _git(root, "merge-base", "--is-ancestor", commit, "HEAD").returncode != 0:
        return [*found, f"{block.name}: its commit {commit[:7]} is not in the history of HEAD"]
    if not stale:
        return found
    changed = _git(root, "log", "--format=%h %s", f"{commit}..HEAD", "--", *block.sources)
    later = changed.stdout.splitlines()
    if later:
        found.append(
            f"{block.name}: stale: {len(later)} commit(s) since {commit[:7]} changed its "
            f"sources, the last {later[0]}; {again}"
        )
    return found


_BEGIN = re.compile(r"^<!-- ([\w.-]+):begin -->$", re.MULTILINE)


def check_docs(
    root: Path | None = None,
    blocks: dict[str, Block] | None = None,
    labels: bool = True,
    stale: bool = True,
) -> list[str]:
    """Every problem of the generated blocks in ``root``: the :func:`problems` of each
    block of ``blocks`` (default :data:`BLOCKS`; with ``labels=False`` only whether its
    document holds it; ``stale``: as :func:`problems`), and every block in README.md or
    docs/*.md that ``blocks`` does not list. ``root``: default :data:`ROOT`. ``[]`` when
    all are labelled (and, with ``stale``, current)."""
    root = ROOT if root is None else Path(root)
    blocks = BLOCKS if blocks is None else blocks
    found = []
    for block in blocks.values():
        if labels:
            found += problems(block, root, stale)
        else:
            path = root / block.document
            if not path.is_file() or block_text(path.read_text(), block) is None:
                found.append(f"{block.name}: {block.document} has no such block")
    listed = {(b.document, b.name) for b in blocks.values() if b.marker is None}
    markers = {(b.document, b.marker) for b in blocks.values() if b.marker is not None}
    for path in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        if not path.is_file():
            continue
        document, content = path.relative_to(root).as_posix(), path.read_text()
        for name in _BEGIN.findall(content):
            if (document, name) not in listed:
                found.append(f"{document}: block {name!r} is not listed in experiments/blocks.py")
        for line in content.splitlines():
            replaced = "everything below is replaced on regeneration" in line
            if replaced and line.startswith("<!--") and (document, line) not in markers:
                found.append(f"{document}: marker {line!r} is not listed in experiments/blocks.py")
    return found
