"""README's two set-up commands timed as a new user runs them.

    python -m experiments.setup_timing [--update-doc]

Clones this checkout's ``HEAD`` into a temporary folder for each command and runs it
there with a fresh ``HOME`` and ``XDG_CACHE_HOME`` (no pip cache, no compilation cache), the two
commands of README.md's "Set-up" (the ``bash`` blocks after "Install and run the main
job" and "Install and run the tests"), read from README.md itself. Each command is a
chain of ``&&`` parts; the last part is the run, the ones before it the installation,
and each part is timed on its own. Prints the times; ``--update-doc`` writes them into
README.md's ``setup`` block. Run it on an otherwise idle machine: the label records the
load at the start, the block the load at the end.
"""

from __future__ import annotations

import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from experiments import _common
from fojax.cli import output

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
JOBS = {"main job": "Install and run the main job", "tests": "Install and run the tests"}


def commands(text: str) -> dict[str, str]:
    """The command of each of :data:`JOBS` in README ``text``: the first ``bash`` block
    after its heading phrase."""
    found = {}
    for job, phrase in JOBS.items():
        start = text.find(phrase)
        block = re.search(r"```bash\n(.+?)\n```", text[start:], re.DOTALL) if start >= 0 else None
        if block is None:
            raise SystemExit(f"README.md: no bash block after {phrase!r}")
        found[job] = block.group(1).strip()
    return found


def _summary(log: str) -> str:
    """pytest's last summary line (``N passed, M skipped in T s``), or ``""``."""
    lines = [line for line in log.splitlines() if re.search(r"\d+ passed", line)]
    return lines[-1].strip(" =") if lines else ""


def run_job(command: str, clone: Path, env: dict) -> dict:
    """Run ``command``'s ``&&`` parts in turn in ``clone`` in the environment ``env``
    (:func:`experiments._common.cold_environment`'s); each part's wall time, the exit
    status, and the output's tail."""
    parts, times, log = command.split(" && "), [], ""
    for part in parts:
        start = time.perf_counter()
        done = subprocess.run(
            ["bash", "-c", part], cwd=clone, env=env, capture_output=True, text=True
        )
        times.append(time.perf_counter() - start)
        log += done.stdout + done.stderr
        print(f"  {times[-1]:7.1f} s  {part}", flush=True)
        if done.returncode:
            break
    return {"parts": parts, "seconds": times, "status": done.returncode, "log": log}


def table(results: dict) -> str:
    rows = _common.table_head("command | installation | the run | both | outcome")
    for job, result in results["jobs"].items():
        install, run = sum(result["seconds"][:-1]), result["seconds"][-1]
        outcome = f"exit status {result['status']}"
        if result.get("summary"):
            outcome += f"; {result['summary']}"
        both = install + run
        rows.append(f"| {job} | {install:.0f} s | {run:.0f} s | {both:.0f} s | {outcome} |")
    load = ", ".join(f"{x:g}" for x in results["load_at_end"]) or "unknown"
    return (
        "README's two commands above, run as written from a fresh clone of the commit in "
        "the label with a fresh HOME and XDG_CACHE_HOME (packages downloaded, nothing "
        f"compiled yet), one after the other; load average at the end {load}.\n\n" + "\n".join(rows)
    )


def main(argv=None) -> int:
    parser = _common.parser("setup_timing")
    parser.add_argument("--update-doc", action="store_true", help="write README's setup block")
    args = parser.parse_args(argv)
    results = {"jobs": {}}
    with tempfile.TemporaryDirectory(prefix="fojax-setup-") as folder:
        for job, command in commands(README.read_text()).items():
            print(f"{job}: {command}", flush=True)
            clone = Path(folder) / job.replace(" ", "-")
            subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
            with _common.cold_environment("fojax-setup-home-") as env:
                result = run_job(command, clone, env)
            result["summary"] = _summary(result["log"]) if job == "tests" else ""
            if result["status"]:
                print(result["log"][-4000:], file=sys.stderr)
            result.pop("log")
            results["jobs"][job] = result
    results["load_at_end"] = output.load_average()
    text = table(results)
    print(text)
    if args.update_doc:
        output.splice(README, text, name="setup")
    return max(r["status"] for r in results["jobs"].values())


if __name__ == "__main__":
    sys.exit(main())
