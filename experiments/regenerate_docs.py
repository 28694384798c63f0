"""Regenerate the generated blocks of README.md and docs/ (:mod:`experiments.blocks`).

    python -m experiments.regenerate_docs [--only NAME | --only-stale] [--list] [--stale]
                                          [--render]

Runs the command of every block (or of ``--only NAME``) from the repository root, in
the order of :data:`experiments.blocks.BLOCKS`, each in a process of its own, and
prints how long each took and the total; stops at the first command that fails, with
its exit status. Each block's time is kept in ``docs/data/regeneration.json`` (with the
label the run wrote, the commit, the machine, the load at its start and whether its
results folder already held results a run reuses), and docs/regeneration.md's
``regeneration`` block lists every block from its label, with that time where this
command made the label (:func:`render`; ``--render`` rewrites that block alone).
``--list`` prints each
block's document, command, the sources it declares and the modules its generators
import (:func:`experiments.blocks.dependencies`); ``--stale`` lists the blocks to
regenerate (no label, a label whose command is not the registry's, generated with
uncommitted changes, a commit not in the history, or the code of a file their numbers
depend on changed since their commit, docstrings and comments left out, with the latest
commit that changed it) and exits with status 1 when there are any;
``--only-stale`` regenerates those alone (a full run that was interrupted goes on with it:
the studies keep their finished runs under their settings and code). Commit before
regenerating: a block records the commit it was generated at.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shlex
import subprocess
import sys
import time

from experiments import _common, blocks
from fojax import records
from fojax.cli import output

TIMES = blocks.ROOT / "docs" / "data" / "regeneration.json"
PAGE = blocks.ROOT / "docs" / "regeneration.md"
COMMAND = "python -m experiments.regenerate_docs"
RENDER = f"{COMMAND} --render"
"""The command of the ``regeneration`` block (its registry entry's)."""


def _reused(block: blocks.Block) -> bool:
    """Whether ``block``'s results folder holds files a run would reuse."""
    folder = blocks.ROOT / block.results if block.results else None
    return folder is not None and folder.is_dir() and any(p.is_file() for p in folder.rglob("*"))


def _times() -> dict:
    return json.loads(TIMES.read_text()) if TIMES.is_file() else {}


def label(block: blocks.Block) -> dict | None:
    """``block``'s label record as its document holds it now (``None``: no document,
    block or label)."""
    path = blocks.ROOT / block.document
    text = blocks.block_text(path.read_text(), block) if path.is_file() else None
    return None if text is None else blocks.read_label(text)


def record(block: blocks.Block, seconds: float, reused: bool, load: list[float]) -> None:
    """Keep ``block``'s regeneration time (``seconds``) in :data:`TIMES`, with the label
    its command wrote."""
    git = output.git_commit(blocks.ROOT)
    times = _times()
    times[block.name] = {
        "seconds": round(seconds, 1),
        **{name: git.get(name) for name in ("commit", "dirty")},
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "cpu": output.cpu_model(),
        "cores": len(os.sched_getaffinity(0)),
        "load_at_start": load,
        "results_present": reused,
        "label": label(block),
    }
    records.write_json(TIMES, times)


def made(entry: dict | None, found: dict | None) -> bool:
    """Whether the regeneration recorded in ``entry`` (:data:`TIMES`) wrote the label
    ``found``: the label it kept, or for an entry that kept none, the same commit, CPU
    and cores."""
    if entry is None or found is None:
        return False
    if "label" in entry:
        return entry["label"] == found
    return all(entry.get(k) == found.get(k) for k in ("commit", "cpu", "cores"))


def _machine(found: dict) -> str:
    machine = f"{found.get('cpu', 'unknown')}, {found.get('cores', '?')} cores"
    if found.get("backend") and found["backend"] != "cpu":
        machine += f", {found.get('device_count', '?')} {found['backend']}"
        machine += f" ({found['device_kind']})" if found.get("device_kind") else ""
    return machine


def render(times: dict) -> str:
    """docs/regeneration.md's ``regeneration`` block: every timed block of the registry
    from its label (commit, machine, load), with its time from ``times``
    (:data:`TIMES`) where ``regenerate_docs`` wrote that label (:func:`made`), and the
    sum of those times."""
    rows = _common.table_head(
        "block | document | commit | machine | load average | regeneration time"
        " | results already present"
    )
    total, timed, chosen = 0.0, 0, [b for b in blocks.BLOCKS.values() if b.timed]
    for block in chosen:
        found, entry = label(block), times.get(block.name)
        if found is None:
            rows.append(f"| {block.name} | {block.document} | no label | | | | |")
            continue
        commit = str(found.get("commit") or "unknown")[:7]
        commit += "" if found.get("dirty") is False else " (uncommitted changes)"
        load = ", ".join(f"{x:g}" for x in found.get("load") or []) or "unknown"
        load += f" {found['load_when']}" if found.get("load_when") else ""
        if made(entry, found):
            total, timed = total + entry["seconds"], timed + 1
            time, present = f"{entry['seconds']:.0f} s", "yes" if entry["results_present"] else "no"
        elif block.recorded is not None:
            time, present = f"run elsewhere, rendered from `{block.recorded}`", ""
        else:
            time, present = "not timed", ""
        rows.append(
            f"| {block.name} | {block.document} | {commit} | {_machine(found)} | {load} | "
            f"{time} | {present} |"
        )
    head = (
        "Every block's label (`experiments/blocks.py` lists them): the commit it was "
        "generated at, the machine and the load average it records (at the end of the run "
        f"unless stated); and, where `{COMMAND}` (`--only NAME` or a full run) wrote that "
        "label, how long the block's command took, from `docs/data/regeneration.json`: "
        f"{timed} of {len(chosen)} blocks, {total:.0f} s ({total / 3600:.1f} h) in all. "
        "*Not timed*: the label was written by the block's command run on its own. "
        "*Results already present*: the block's results folder held results of an earlier "
        "run, which a run reuses where their settings and code match (a fresh clone has none)."
    )
    return head + "\n\n" + "\n".join(rows)


def _rerender() -> None:
    output.splice(PAGE, render(_times()), name="regeneration", command=RENDER)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=COMMAND,
        description="Regenerate the docs' generated blocks, list them, or list the stale ones.",
    )
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--only", choices=list(blocks.BLOCKS), metavar="NAME", help="one block")
    which.add_argument(
        "--only-stale", action="store_true", help="the blocks --stale lists, regenerated"
    )
    parser.add_argument(
        "--list", action="store_true", help="each block, its command and what it depends on"
    )
    parser.add_argument("--stale", action="store_true", help="the blocks to regenerate")
    parser.add_argument(
        "--render", action="store_true", help="docs/regeneration.md's table of the labels"
    )
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.render:
        _rerender()
        return 0
    chosen = [b for b in blocks.BLOCKS.values() if args.only in (None, b.name)]
    if args.only_stale:
        chosen = [b for b in chosen if blocks.problems(b, blocks.ROOT)]
    if args.list:
        for block in chosen:
            print(f"{block.name} ({block.document}): {shlex.join(block.command)}")
            print(f"    sources: {' '.join(block.sources) or '(none)'}")
            if block.imports:
                modules = blocks.imports(blocks.generators(block), blocks.ROOT, commit="HEAD")
                print(f"    imports ({len(modules)} modules): {' '.join(modules)}")
        return 0
    if args.stale:
        found = [line for block in chosen for line in blocks.problems(block, blocks.ROOT)]
        print("\n".join(found) if found else "every block is labelled and current")
        return 1 if found else 0
    total = time.perf_counter()
    for block in chosen:
        if not block.timed and len(chosen) > 1:
            continue  # rewritten after every block
        print(f"{block.name}: {shlex.join(block.command)}", flush=True)
        reused, load, start = _reused(block), output.load_average(), time.perf_counter()
        program = sys.executable if block.command[0] == "python" else block.command[0]
        status = subprocess.run([program, *block.command[1:]], cwd=blocks.ROOT).returncode
        seconds = time.perf_counter() - start
        print(f"{block.name}: {seconds:.0f} s" + (f", exit status {status}" if status else ""))
        if status:
            return status
        if block.timed:
            record(block, seconds, reused, load)
        _rerender()
    print(f"{len(chosen)} block(s) regenerated in {time.perf_counter() - total:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
