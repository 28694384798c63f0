"""What every command and study writes besides its numbers: progress lines, atomic JSON
files, the provenance of a run (command, versions, git commit, machine) and the
generated blocks of the docs.

* :func:`log`: one progress line on stderr (nothing with ``quiet``).
* :func:`write_json`, :func:`write_npz`, :func:`write_csv`: atomic JSON, NumPy and CSV
  files (a run stopped while writing leaves the old file or the new one, never half of
  one): those of :mod:`fojax.records`, the one place files are written.
* :func:`git_commit`, :func:`commit_label`: the checkout's commit and whether it has
  uncommitted changes; :func:`versions`: Python's and the key packages' versions;
  :func:`provenance`: what a result needs to be rerun exactly; :func:`run_context`:
  that, with the CPU model and the load average (the studies').
* :func:`splice`: replace a generated block of a Markdown document, either between
  ``<!-- name:begin -->`` and ``<!-- name:end -->`` or everything below a marker line,
  labelled by :func:`block_label` (command, commit, machine, load, versions).
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Any

from fojax import settings
from fojax.records import atomic_write, write_csv, write_json, write_npz

__all__ = [
    "block_label",
    "commit_label",
    "cpu_model",
    "git_commit",
    "invocation",
    "load_average",
    "log",
    "package_version",
    "provenance",
    "run_context",
    "splice",
    "versions",
    "write_csv",
    "write_json",
    "write_npz",
]


def log(quiet: bool, text: str) -> None:
    """``text`` on stderr, flushed, unless ``quiet`` (a command's ``--quiet``)."""
    if not quiet:
        print(text, file=sys.stderr, flush=True)


# ------------------------------------------------------------------------- provenance


DOCUMENTS = ("docs", "README.md")
"""Where generated blocks and their figures are written. No result depends on them, so
changes there do not make a checkout dirty (a generator writes its figures and
documents before its label, and one regeneration writes several blocks)."""


def git_commit(root: Path | None = None, exclude: tuple[str, ...] = DOCUMENTS) -> dict:
    """``{"commit", "dirty"}`` of the git checkout ``root`` (default: the one holding
    fojax), or ``{}`` (not one). ``dirty``: uncommitted changes to tracked files, outside
    the paths ``exclude`` (relative to the checkout's root; default :data:`DOCUMENTS`)."""
    root = Path(__file__).resolve().parents[2] if root is None else Path(root)  # fojax/cli/..
    if not (root / ".git").exists():
        return {}

    def git(*args: str) -> subprocess.CompletedProcess:
        command = ["git", "-C", str(root), *args]
        return subprocess.run(command, capture_output=True, text=True, timeout=10)

    try:
        commit = git("rev-parse", "HEAD")
        if commit.returncode != 0:
            return {}
        excluded = (f":(top,exclude){path}" for path in exclude)
        status = git("status", "--porcelain", "--untracked-files=no", "--", ".", *excluded)
        dirty = bool(status.stdout.strip()) if status.returncode == 0 else None
        return {"commit": commit.stdout.strip(), "dirty": dirty}
    except (OSError, subprocess.SubprocessError):
        return {}


def commit_label(provenance: dict | None = None, full: bool = False) -> str:
    """``abc1234`` (`` (with uncommitted changes)``) from a provenance record (default:
    the checkout now); ``full``: the whole hash."""
    git = provenance.get("fojax_git") if provenance is not None else git_commit()
    if not isinstance(git, dict) or not git.get("commit"):
        return "unknown"
    commit = git["commit"] if full else git["commit"][:7]
    return commit + (" (with uncommitted changes)" if git.get("dirty") else "")


def package_version(package: str) -> str | None:
    """The installed version of ``package`` (``None``: not installed)."""
    from importlib import metadata

    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


VERSIONED = ("jax", "jaxlib", "optax", "numpy")
"""The packages whose versions every record names (with Python's): the compiled
programs, and so the float32 numbers, depend on them."""


def versions() -> dict[str, str | None]:
    """``{"python", "jax", "jaxlib", "optax", "numpy"}``: the versions installed
    (``None``: not installed), read without importing the packages."""
    return {"python": platform.python_version()} | {
        name: package_version(name) for name in VERSIONED
    }


def provenance(command: list[str] | None = None, gains: dict | None = None) -> dict:
    """What a result needs to be rerun exactly.

    command: the command line as a list (``["fojax", "simulate", ...]``; default
    ``sys.argv``). gains: optional, recorded as given
    (:func:`fojax.cli.study.gains_record`). Returns the command (quoted for a shell)
    and the folder it ran in, the fojax version and git commit (:func:`git_commit`),
    the Python, JAX, jaxlib, Optax and NumPy versions (:func:`versions`), the backend,
    the device and process counts and devices (the draws are split over the devices,
    and a draw's float32 rounding depends on the batch it runs in), ``jax_enable_x64``,
    ``XLA_FLAGS``, the platform and the time (UTC).
    """
    import jax

    import fojax

    record: dict[str, Any] = {
        "command": shlex.join(sys.argv if command is None else command),
        "working_directory": os.getcwd(),
        "fojax_version": package_version("fojax") or getattr(fojax, "__version__", None),
        "fojax_git": git_commit() or None,
        **versions(),
        "backend": jax.default_backend(),
        "device_count": jax.device_count(),
        "local_device_count": jax.local_device_count(),
        "process_count": jax.process_count(),
        "devices": [str(d) for d in jax.local_devices()],
        "jax_enable_x64": bool(jax.config.jax_enable_x64),
        "xla_flags": settings.read().xla_flags or None,
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "created_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    return record if gains is None else record | {"gains": gains}


def load_average() -> list[float]:
    """The 1, 5 and 15-minute load averages (``[]`` where the platform has none)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return []


def cpu_model() -> str | None:
    """The CPU's model name, family and model numbers (XLA compiles for the host CPU,
    and float32 rounding can depend on the instructions it picks)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return None
    fields = {}
    for line in text.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    return (
        f"{fields.get('model name', '?')} (family {fields.get('cpu family', '?')}, "
        f"model {fields.get('model', '?')})"
    )


def run_context(command: list[str]) -> dict:
    """Provenance of a study run (:func:`provenance`), the CPU model and the load
    average."""
    return provenance(command) | {"cpu_model": cpu_model(), "load_average": load_average()}


# ------------------------------------------------------------------------------- docs

LABEL_PREFIX = "<!-- generated-block "
"""How the first line of every generated block starts (:func:`block_label`)."""


def invocation() -> str:
    """This process's command line as typed: ``python -m NAME ARGS`` for a module run
    with ``-m``, else the program's name and its arguments."""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    if spec is not None and spec.name:
        return shlex.join(["python", "-m", spec.name.removesuffix(".__main__"), *sys.argv[1:]])
    return shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]])


def block_label(command: str | None = None, root: Path | None = None) -> str:
    """The first two lines of every generated block of the docs (:func:`splice`).

    A comment holding, as JSON, the command (default :func:`invocation`), the commit of
    the checkout ``root`` (default: the one holding fojax) and whether it had
    uncommitted changes (:func:`git_commit`: outside :data:`DOCUMENTS`), the CPU model,
    the cores this process may use, the load average and :func:`versions`; then the
    same in a line for the reader (:func:`format_label`).
    """
    git = git_commit(root)
    affinity = getattr(os, "sched_getaffinity", None)
    return format_label(
        {
            "command": invocation() if command is None else command,
            "commit": git.get("commit"),
            "dirty": git.get("dirty"),
            "cpu": cpu_model(),
            "cores": os.cpu_count() if affinity is None else len(affinity(0)),
            "load": load_average(),
            **versions(),
        }
    )


def format_label(record: dict) -> str:
    """The two label lines of a block from its ``record`` (:func:`block_label`'s keys;
    optional: ``commit_given``, the commit as given by hand for a result that records
    none; ``backend``, ``device_count`` and ``device_kind``, the devices it ran on;
    ``load_when``, when the load was read)."""
    data = json.dumps(record, separators=(",", ":")).replace(">", "\\u003e")  # no "-->"
    commit = (record["commit"] or "unknown")[:7]
    state = " (clean)" if record["dirty"] is False else " with uncommitted changes"
    if record.get("commit_given"):
        state += ", the commit as given with --commit"
    load = ", ".join(f"{x:g}" for x in record["load"]) or "unknown"
    packages = ", ".join(f"{k} {record[k]}" for k in VERSIONED)
    devices = ""
    if record.get("backend"):
        devices = f"{record['device_count']} {record['backend']} device(s)"
        if record.get("device_kind") and record["backend"] != "cpu":
            devices += f" ({record['device_kind']})"
        devices += ", "
    when = f" {record['load_when']}" if record.get("load_when") else ""
    reader = (
        f"*Generated by `{record['command']}` at commit {commit}{state} on {record['cpu']}, "
        f"{record['cores']} cores, {devices}load average {load}{when}; Python "
        f"{record['python']}, {packages}.*"
    )
    return f"{LABEL_PREFIX}{data} -->\n{reader}"


def splice(
    document: Path,
    text: str,
    *,
    name: str | None = None,
    marker: str | None = None,
    command: str | None = None,
    label: dict | None = None,
) -> None:
    """Replace a generated block of the Markdown file ``document`` with ``text``,
    labelled (:func:`block_label` of ``command``, default this process's command line;
    or, for a result made elsewhere, :func:`format_label` of its ``label`` record).

    name: the block between ``<!-- name:begin -->`` and ``<!-- name:end -->`` (each on
    its own line, kept). marker: everything below the line ``marker`` (kept, followed
    by a blank line, the label, a blank line and ``text``). Exactly one of the two; a
    document without the block raises ValueError. Every block is listed, with the
    command that regenerates it, in the clone's ``experiments/blocks.py``.
    """
    document = Path(document)
    if (name is None) == (marker is None):
        raise ValueError("splice: give exactly one of name and marker")
    content = document.read_text()
    head = block_label(command) if label is None else format_label(label)
    text = f"{head}\n\n{text}"
    if marker is not None:
        if marker not in content:
            raise ValueError(f"{document}: no line {marker!r} to regenerate below")
        atomic_write(document, content[: content.index(marker) + len(marker)] + "\n\n" + text)
        return
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    if begin not in content or end not in content:
        raise ValueError(f"{document} has no {begin} ... {end} block")
    head, _, rest = content.partition(begin)
    atomic_write(document, f"{head}{begin}\n{text}\n{end}{rest.partition(end)[2]}")
