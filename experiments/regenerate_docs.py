"""Regenerate the generated blocks of README.md and docs/ (:mod:`experiments.blocks`).

    python -m experiments.regenerate_docs [--only NAME] [--list] [--stale]

Runs the command of every block (or of ``--only NAME``) from the repository root, in
the order of :data:`experiments.blocks.BLOCKS`, each in a process of its own, and
prints how long each took and the total; stops at the first command that fails, with
its exit status. ``--list`` prints each block's document, command and sources;
``--stale`` lists the blocks to regenerate (no label, generated with uncommitted
changes, a commit not in the history, or sources changed since their commit) and
exits with status 1 when there are any. Commit before regenerating: a block records
the commit it was generated at.
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
import time

from experiments import blocks


def _run(block: blocks.Block) -> tuple[int, float]:
    command = [sys.executable if block.command[0] == "python" else block.command[0]]
    start = time.perf_counter()
    done = subprocess.run(command + list(block.command[1:]), cwd=blocks.ROOT, check=False)
    return done.returncode, time.perf_counter() - start


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m experiments.regenerate_docs",
        description="Regenerate the docs' generated blocks, list them, or list the stale ones.",
    )
    parser.add_argument("--only", choices=list(blocks.BLOCKS), metavar="NAME", help="one block")
    parser.add_argument("--list", action="store_true", help="each block, command and sources")
    parser.add_argument("--stale", action="store_true", help="the blocks to regenerate")
    args = parser.parse_args(argv)
    chosen = [b for b in blocks.BLOCKS.values() if args.only in (None, b.name)]
    if args.list:
        for block in chosen:
            print(f"{block.name} ({block.document}): {shlex.join(block.command)}")
            print(f"    sources: {' '.join(block.sources)}")
        return 0
    if args.stale:
        found = [line for block in chosen for line in blocks.problems(block, blocks.ROOT)]
        print("\n".join(found) if found else "every block is labelled and current")
        return 1 if found else 0
    total = time.perf_counter()
    for block in chosen:
        print(f"{block.name}: {shlex.join(block.command)}", flush=True)
        status, seconds = _run(block)
        print(f"{block.name}: {seconds:.0f} s" + (f", exit status {status}" if status else ""))
        if status:
            return status
    print(f"{len(chosen)} block(s) regenerated in {time.perf_counter() - total:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
