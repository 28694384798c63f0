"""Regenerate the generated blocks of README.md and docs/ (:mod:`experiments.blocks`).

    python -m experiments.regenerate_docs [--only NAME | --only-stale] [--list] [--stale]
                                          [--render]

Runs the command of every block (or of ``--only NAME``) from the repository root, in
the order of :data:`experiments.blocks.BLOCKS`, each in a process of its own, and
prints how long each took and the total; stops at the first command that fails, with
its exit status. Each block's time is kept in ``docs/data/regeneration.json`` (with the
commit, the machine, the load at its start and whether its results folder already held
results a run reuses), and README.md's ``regeneration`` block lists them with their sum
(:func:`render`; ``--render`` rewrites that block alone). ``--list`` prints each
block's document, command, the sources it declares and the modules its generators
import (:func:`experiments.blocks.dependencies`); ``--stale`` lists the blocks to
regenerate (no label, generated with uncommitted changes, a commit not in the history,
or the code of a file their numbers depend on changed since their commit, docstrings and
comments left out, with the latest commit that changed it) and exits with status 1 when
there are any;
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
README = blocks.ROOT / "README.md"
COMMAND = "python -m experiments.regenerate_docs"


def _reused(block: blocks.Block) -> bool:
    """Whether ``block``'s results folder holds files a run would reuse."""
    folder = blocks.ROOT / block.results if block.results else None
    return folder is not None and folder.is_dir() and any(p.is_file() for p in folder.rglob("*"))


def _times() -> dict:
    return json.loads(TIMES.read_text()) if TIMES.is_file() else {}


def record(block: blocks.Block, seconds: float, reused: bool, load: list[float]) -> None:
    """Keep ``block``'s regeneration time (``seconds``) in :data:`TIMES`."""
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
    }
    records.write_json(TIMES, times)


def render(times: dict) -> str:
    """README's ``regeneration`` block: each block's last regeneration from ``times``
    (:data:`TIMES`) and the sum of those timed."""
    rows = _common.table_head(
        "block | document | time | at commit | load at its start | results already present"
    )
    total = 0.0
    for block in (b for b in blocks.BLOCKS.values() if b.timed):
        entry = times.get(block.name)
        if entry is None:
            rows.append(f"| {block.name} | {block.document} | not timed | | | |")
            continue
        total += entry["seconds"]
        load = ", ".join(f"{x:g}" for x in entry["load_at_start"]) or "unknown"
        commit = (entry["commit"] or "unknown")[:7] + (" (dirty)" if entry["dirty"] else "")
        rows.append(
            f"| {block.name} | {block.document} | {entry['seconds']:.0f} s | {commit} | "
            f"{load} | {'yes' if entry['results_present'] else 'no'} |"
        )
    timed = [name for name in blocks.BLOCKS if name in times]
    count = sum(block.timed for block in blocks.BLOCKS.values())
    head = (
        f"Each block's last regeneration by `{COMMAND}` (`--only NAME` or a full run), "
        f"from `docs/data/regeneration.json`: {len(timed)} of {count} blocks timed, "
        f'{total:.0f} s ({total / 3600:.1f} h) in all. "Results already present": the '
        "block's results folder held results of an earlier run, which a run reuses where "
        "their settings and code match (a fresh clone has none). Machine of each: "
        + "; ".join(sorted({f"{times[n]['cpu']}, {times[n]['cores']} cores" for n in timed}))
        + "."
    )
    return head + "\n\n" + "\n".join(rows)


def _rerender() -> None:
    output.splice(README, render(_times()), name="regeneration", command=COMMAND)


def main(argv=None) -> int:
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
    parser.add_argument("--render", action="store_true", help="README's regeneration block")
    args = parser.parse_args(argv)
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
