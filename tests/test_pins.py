"""Pinned versions: constraints.txt pins what is installed, ``fojax --version`` and
every run's provenance name the versions."""

import platform
import re
from importlib import metadata
from pathlib import Path

from fojax import cli
from fojax.cli import output

ROOT = Path(__file__).resolve().parent.parent
CONSTRAINTS = ROOT / "constraints.txt"
KEY_PACKAGES = ("jax", "jaxlib", "optax", "numpy", "scipy", "matplotlib")
"""Packages whose versions do not depend on Python's and move the docs' numbers."""


def _normal(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def pins() -> dict[str, str]:
    """Package name (normalised) -> pinned version, from constraints.txt."""
    pinned = {}
    for number, line in enumerate(CONSTRAINTS.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        name, separator, version = line.partition("==")
        assert separator and version.strip(), f"constraints.txt:{number}: not an exact pin: {line}"
        pinned[_normal(name.strip())] = version.strip()
    return pinned


def test_key_packages_are_installed_at_their_pins():
    pinned = pins()
    wrong = {
        name: (metadata.version(name), pinned.get(name))
        for name in KEY_PACKAGES
        if metadata.version(name) != pinned.get(name)
    }
    assert not wrong, (
        "installed versions differ from constraints.txt (installed, pinned): "
        f'{wrong}; install with `pip install -c constraints.txt -e ".[tests]"` so that '
        "the docs' generated numbers correspond to what runs"
    )


def test_every_dependency_of_fojax_is_pinned_and_fojax_is_not():
    pinned = pins()
    assert "fojax" not in pinned
    required = {
        _normal(re.match(r"[A-Za-z0-9_.-]+", requirement).group())
        for requirement in metadata.requires("fojax") or ()
    } - {"fojax"}
    missing = sorted(required - set(pinned))
    assert required and not missing, (
        f"constraints.txt pins no version of {missing} (required by pyproject.toml): "
        "produce it again as its header says"
    )


def test_version_names_fojax_python_and_the_key_packages(capsys):
    assert cli.main(["--version"]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"fojax {metadata.version('fojax')} (")
    assert f"Python {platform.python_version()}" in line
    for name in ("jax", "jaxlib", "optax", "numpy"):
        assert f"{name} {metadata.version(name)}" in line, name
    # A command's own --help is unaffected.
    parser_help = cli.main(["--help"])
    assert parser_help == 0 and "--version" in capsys.readouterr().out


def test_provenance_records_python_and_the_key_versions():
    import jax

    record = output.provenance(["fojax", "simulate", "--draws", "2"])
    assert record["command"] == "fojax simulate --draws 2"
    assert record["python"] == platform.python_version()
    for name in ("jax", "jaxlib", "optax", "numpy"):
        assert record[name] == metadata.version(name), name
    assert record["jax"] == jax.__version__
    assert output.versions() == {k: record[k] for k in ("python", *output.VERSIONED)}
