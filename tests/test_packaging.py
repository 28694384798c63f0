"""fojax as users install it: the wheel's package list is complete, and (slow tier) every
command works from a wheel installed into a clean environment, outside the clone."""

import os
import pathlib
import shutil
import subprocess
import sys
import tomllib

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent


def _setuptools_config() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def _packages_on_disk() -> set[str]:
    """The import name of every folder with an ``__init__.py`` that the wheel must hold:
    those under each folder that ``package-dir`` maps to an import package (the root
    package ``fojax`` from its own folder), found on disk."""
    folders = {"fojax": "fojax", **_setuptools_config().get("package-dir", {})}
    found = set()
    for name, folder in folders.items():
        base = ROOT / folder
        for init in base.rglob("__init__.py"):
            parts = init.parent.relative_to(base).parts
            if "__pycache__" not in parts:
                found.add(".".join((name, *parts)))
    return found


def test_the_wheel_lists_every_package():
    """pyproject.toml lists the packages by hand (setuptools' discovery cannot map
    optimize/ into fojax): a folder with an ``__init__.py`` left out of the list is left
    out of the wheel, and the editable install, which maps whole folders, never notices."""
    listed = _setuptools_config()["packages"]
    assert isinstance(listed, list), "tool.setuptools.packages: expected a list of packages"
    on_disk = _packages_on_disk()
    assert {"fojax", "fojax.optimize", "fojax.optimize.strategies"} <= on_disk
    missing, extra = sorted(on_disk - set(listed)), sorted(set(listed) - on_disk)
    assert not missing, f"pyproject.toml's tool.setuptools.packages lacks {missing}"
    assert not extra, f"pyproject.toml's tool.setuptools.packages lists no package: {extra}"


# ------------------------------------------------------------------ the installed wheel

SOURCE_IGNORED = (
    ".git", ".venv", "venv", "results", ".jax_cache", "build", "dist", "*.egg-info",
    "__pycache__", ".pytest_cache", ".ruff_cache", "out", "tests", "docs",
)  # fmt: skip
"""Left out of the copy the wheel is built from (the build writes into its source)."""

TINY_RUN = ["--scenario", "2", "--horizon", "0.3", "--seed", "5"]
TUNE = [*TINY_RUN, "--validation-draws", "2", "--eval-draws", "2", "--quiet"]


def _run(argv, cwd, env, timeout=300) -> str:
    done = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"{' '.join(map(str, argv))}: exit status {done.returncode}\n" + (
        done.stdout[-2000:] + done.stderr[-4000:]
    )
    return done.stdout


@pytest.mark.slow
def test_every_command_runs_from_the_wheel_in_a_clean_environment(tmp_path):
    """Build the wheel, install it with its pinned dependencies into a fresh virtual
    environment, and from a folder outside the clone (no PYTHONPATH, a fresh HOME) run
    every command's --help and a seconds-long run of each command that computes."""
    source = tmp_path / "source"
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(*SOURCE_IGNORED))
    wheels = tmp_path / "wheels"
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", wheels, source],
         tmp_path, None)  # fmt: skip
    (wheel,) = wheels.glob("fojax-*.whl")
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", venv], tmp_path, None)
    python, fojax = venv / "bin" / "python", venv / "bin" / "fojax"
    _run([python, "-m", "pip", "install", "-q", "-c", ROOT / "constraints.txt",
          f"{wheel}[experiments]"], tmp_path, None)  # fmt: skip

    home, work = tmp_path / "home", tmp_path / "work"
    home.mkdir()
    work.mkdir()
    env = {
        "PATH": f"{venv / 'bin'}{os.pathsep}/usr/bin{os.pathsep}/bin",
        "HOME": str(home),
        "XDG_CACHE_HOME": str(home / ".cache"),
        "MPLBACKEND": "Agg",
    }
    env.update({k: os.environ[k] for k in ("LANG", "TMPDIR") if k in os.environ})

    # The package comes from the environment, not from the clone.
    where = _run([python, "-c", "import fojax, fojax.optimize, fojax.optimize.strategies, "
                  "fojax.cli.tune; print(fojax.__file__)"], work, env)  # fmt: skip
    assert pathlib.Path(where.strip()).is_relative_to(venv), where
    assert not list(venv.glob("lib/python*/site-packages/__editable__*")), "an editable install"

    assert "COMMAND" in _run([fojax, "--help"], work, env)
    assert _run([fojax, "--version"], work, env).startswith("fojax 0.")
    for command in ("simulate", "reproduce", "tune", "bench", "accuracy"):
        assert f"fojax {command}" in _run([fojax, command, "--help"], work, env)

    _run([fojax, "simulate", *TINY_RUN, "--controller", "afonftsmc", "--draws", "3",
          "--device-batch", "2", "--keep", "2", "--quiet", "--out", "sim"], work, env)  # fmt: skip
    for name in ("summary.json", "draws.npz", "trajectories.npz", "tracking.png"):
        assert (work / "sim" / name).is_file(), name

    _run([fojax, "tune", *TUNE, "--controller", "afonftsmc", "--init", "paper", "--steps", "1",
          "--out", "tune"], work, env)  # fmt: skip
    for name in ("gains.json", "history.csv", "evaluation.json", "run.json"):
        assert (work / "tune" / name).is_file(), name

    requirements = work / "small_quadrotor.toml"
    shutil.copy(ROOT / "examples" / "requirements" / "small_quadrotor.toml", requirements)
    _run([fojax, "tune", *TUNE, "--controller", "fl", "--requirements", requirements.name,
          "--outer-steps", "1", "--inner-steps", "1", "--out", "tune_req"],
         work, env)  # fmt: skip
    for name in ("gains.json", "history.csv", "evaluation.json"):
        assert (work / "tune_req" / name).is_file(), name

    _run([fojax, "reproduce", "--horizon", "0.2", "--seed", "4", "--draws", "3",
          "--device-batch", "2", "--keep", "2", "--compare", "fl", "--quiet", "--out", "rep"],
         work, env)  # fmt: skip
    for name in ("report.md", "report.json", "s1/summary.json", "s3/summary.json"):
        assert (work / "rep" / name).is_file(), name
    assert list((work / "rep" / "figures").glob("fig*.png"))

    _run([fojax, "accuracy", "--horizon", "1", "--dt", "0.01", "--out", "acc"], work, env)
    for name in ("accuracy.json", "accuracy.md", "accuracy.png"):
        assert (work / "acc" / name).is_file(), name
