"""When a generated block is stale (experiments/blocks.py): the code its numbers depend on
(the first-party modules its generators import, found in their source, and the files it
declares) changed since its label's commit, a change counting only where the code
differs once docstrings and comments are left out."""

import ast
import json
import shlex
import subprocess

import pytest

from experiments import blocks
from fojax.cli import output

# ----------------------------------------------------------- code without docstrings

MODULE = '''"""A module."""

import math

SCALE = 2.0
"""How far."""


class Box:
    """A box."""

    def area(self, side):
        """Its area."""
        return SCALE * side**2  # squared


def label(x):
    return f"{x:.3f}"
'''


def _same(after: str, before: str = MODULE, path: str = "fojax/m.py") -> bool:
    return blocks.same_code(before, after, path)


def test_docstrings_comments_and_layout_are_not_code():
    assert _same(MODULE)
    assert _same(MODULE.replace('"""A module."""', '"""A module, said otherwise."""'))
    assert _same(MODULE.replace('"""Its area."""', '"""Its area.\n\n        In m^2."""'))
    assert _same(MODULE.replace('    """A box."""\n', ""))  # a docstring removed
    assert _same(MODULE.replace('"""How far."""', '"""How far, in m."""'))  # of a name
    assert _same(MODULE.replace("# squared", "# the side squared"))
    assert _same(MODULE.replace("import math\n", "import math  # for pi\n\n# constants\n"))
    assert _same(
        MODULE.replace(
            "return SCALE * side**2", "return (\n            SCALE * side ** 2\n        )"
        )
    )


def test_a_change_of_code_is_a_change():
    assert not _same(MODULE.replace("SCALE = 2.0", "SCALE = 2.5"))
    assert not _same(MODULE.replace("side**2", "side**3"))
    assert not _same(MODULE.replace('f"{x:.3f}"', 'f"{x:.4f}"'))  # a string in code
    assert not _same(MODULE + '\nf"{label(1)}"\n')  # an f-string alone runs its code
    assert not _same(MODULE.replace("import math\n", "import math\nimport cmath\n"))
    assert not blocks.same_code(MODULE, None, "fojax/m.py")  # removed
    assert not blocks.same_code(None, MODULE, "fojax/m.py")  # added
    assert blocks.same_code(None, None, "fojax/m.py")


def test_any_other_file_compares_by_its_bytes():
    toml = "mass = 0.74  # kg\n"
    assert blocks.same_code(toml, toml, "examples/vehicles/v.toml")
    assert not blocks.same_code(toml, "mass = 0.74  # in kg\n", "examples/vehicles/v.toml")
    broken = "def f(:\n    pass\n"  # Python that does not parse: its bytes
    assert not blocks.same_code(broken, broken + "# more\n", "fojax/broken.py")


# ---------------------------------------------------------------- the import closure


def _write(root, files: dict[str, str]) -> None:
    for path, text in files.items():
        (root / path).parent.mkdir(parents=True, exist_ok=True)
        (root / path).write_text(text)


PACKAGE = {
    # the root only gathers names; a module importing a submodule does not run its imports
    "fojax/__init__.py": "from fojax import heavy\nfrom fojax.core import Thing\n",
    "fojax/heavy.py": "",
    "fojax/core.py": "from . import helpers\n\n\ndef late():\n    import fojax.lazy\n",
    "fojax/helpers.py": "import numpy\nfrom .sub import part\n",
    "fojax/lazy.py": "from ..fojax import nothing\n",  # above the top: no module
    "fojax/sub/__init__.py": "from fojax.sub.inner import value\n",
    "fojax/sub/part.py": "from .. import core\n",  # a cycle back
    "fojax/sub/inner.py": "",
    "fojax/typed.py": "",
    "fojax/unused.py": "",
    "tuner/__init__.py": "",  # fojax.tuner, from the folder tuner/ (as optimize/)
    "tuner/driver.py": "from fojax.sub import inner\n",
    "experiments/__init__.py": "",
    "experiments/gen.py": (
        "from typing import TYPE_CHECKING\n"
        "from fojax import Thing\n"  # a name the root binds: its module
        "from fojax.tuner import driver\n"
        "if TYPE_CHECKING:\n    from fojax import typed\n"
        "from experiments import _shared\n"
    ),
    "experiments/_shared.py": "import fojax\n\n\ndef f():\n    return fojax.heavy\n",
    "experiments/alone.py": "import json\n",
}


def test_the_import_closure_of_a_small_package(tmp_path):
    _write(tmp_path, PACKAGE)
    packages = {"fojax": "fojax", "fojax.tuner": "tuner", "experiments": "experiments"}
    found = blocks.imports(["experiments.gen"], tmp_path, packages)
    assert found == {
        "experiments._shared": "experiments/_shared.py",
        "experiments.gen": "experiments/gen.py",
        "fojax": "fojax/__init__.py",
        "fojax.core": "fojax/core.py",
        "fojax.heavy": "fojax/heavy.py",
        "fojax.helpers": "fojax/helpers.py",
        "fojax.lazy": "fojax/lazy.py",
        "fojax.sub": "fojax/sub/__init__.py",
        "fojax.sub.inner": "fojax/sub/inner.py",
        "fojax.sub.part": "fojax/sub/part.py",
        "fojax.tuner": "tuner/__init__.py",
        "fojax.tuner.driver": "tuner/driver.py",
    }
    assert blocks.imports(["experiments.alone"], tmp_path, packages) == {
        "experiments.alone": "experiments/alone.py"
    }
    # the root's imports run with any submodule but count only through the names taken
    assert blocks.imports(["fojax.sub.inner"], tmp_path, packages) == {
        "fojax.sub": "fojax/sub/__init__.py",
        "fojax.sub.inner": "fojax/sub/inner.py",
    }
    assert blocks.imports(["experiments.missing"], tmp_path, packages) == {}
    # pyproject.toml's package-dir is read where none is given
    (tmp_path / "pyproject.toml").write_text(
        '[tool.setuptools.package-dir]\n"fojax.tuner" = "tuner"\n'
    )
    assert blocks.imports(["experiments.gen"], tmp_path) == found


def test_the_root_package_only_gathers_names():
    """What :func:`blocks.imports` assumes of fojax/__init__.py (and experiments'):
    imports, ``__all__`` and constants, no code that uses what it imports."""
    for package in ("fojax", "experiments"):
        tree = ast.parse((blocks.ROOT / package / "__init__.py").read_text())
        for node in tree.body:
            if isinstance(node, ast.Assign):
                assert isinstance(node.value, ast.List | ast.Constant), ast.dump(node)
            else:
                assert isinstance(node, ast.Import | ast.ImportFrom | ast.Expr), ast.dump(node)


def test_the_generators_of_a_block():
    def block(*command, modules=()):
        return blocks.Block("b", "d.md", command, (), modules=modules)

    assert blocks.generators(block("python", "-m", "experiments.vehicles", "--out", "r")) == (
        "experiments.vehicles",
    )
    for command in (("fojax", "tune", "--scenario", "2"), ("python", "-m", "fojax.cli", "tune")):
        assert blocks.generators(block(*command)) == ("fojax.cli", "fojax.cli.tune")
    assert blocks.generators(block("fojax", "--version")) == ("fojax.cli",)
    assert blocks.generators(block("python", "-c", "print()")) == ()
    assert blocks.generators(
        block("python", "-m", "experiments.x", modules=("fojax.cli.tune",))
    ) == (
        "experiments.x",
        "fojax.cli.tune",
    )


def test_what_the_real_generators_import():
    vehicles = blocks.imports(["experiments.vehicles"])
    assert vehicles["fojax.vehicle"] == "fojax/vehicle.py"
    assert vehicles["fojax.plant"] == "fojax/plant.py"
    assert vehicles["fojax.optimize.driver"] == "optimize/driver.py"  # through _common
    assert "fojax.cli.tune" not in vehicles  # run in processes of their own: declared
    assert "fojax/cli/tune.py" in blocks.dependencies(blocks.BLOCKS["vehicles"])
    assert "examples/vehicles" in blocks.dependencies(blocks.BLOCKS["vehicles"])
    # the case: the tuner's driver is no code of the accuracy or reproduction runs
    for name in ("accuracy", "reproduction", "reproduction-sat"):
        found = blocks.dependencies(blocks.BLOCKS[name])
        assert "constraints.txt" in found and "fojax/plant.py" in found
        assert not any(path.startswith("optimize/") for path in found), name
    assert blocks.dependencies(blocks.BLOCKS["regeneration"]) == (
        "experiments/blocks.py",
        "experiments/regenerate_docs.py",
        "experiments/_common.py",
    )


# ------------------------------------------------------ in a clone of this repository


def _git(repo, *args) -> str:
    done = subprocess.run(
        ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t", *args],
        capture_output=True,
        text=True,
        check=True,
    )
    return done.stdout.strip()


def _commit(repo, message) -> str:
    _git(repo, "add", "-A")
    _git(repo, "commit", "-q", "-m", message)
    return _git(repo, "rev-parse", "HEAD")


def _relabel(repo, commit: str) -> None:
    """Every block's label in the docs of ``repo`` as if generated at ``commit``, clean."""
    for path in [repo / "README.md", *sorted((repo / "docs").glob("*.md"))]:
        lines = path.read_text().split("\n")
        for i, line in enumerate(lines):
            if line.startswith(output.LABEL_PREFIX) and line.endswith(" -->"):
                label = json.loads(line[len(output.LABEL_PREFIX) : -len(" -->")])
                label.update(commit=commit, dirty=False)
                lines[i] = f"{output.LABEL_PREFIX}{json.dumps(label)} -->"
        path.write_text("\n".join(lines))


# A block whose generator imports no plant: it reads the records module alone.
NOTES = blocks.Block(
    "notes", "docs/notes.md", ("python", "-m", "experiments.notes", "--update-doc"), ()
)


def _stale(repo, registry) -> dict[str, str]:
    found = blocks.check_docs(repo, registry)
    assert all(": stale: " in line for line in found), found
    return {line.split(":")[0]: line for line in found}


@pytest.fixture
def clone(tmp_path):
    """A clone of this repository's HEAD with a block of its own (``notes``), every
    block labelled at one commit."""
    repo = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", str(blocks.ROOT), str(repo)], check=True)
    (repo / "experiments" / "notes.py").write_text("from fojax import records\n")
    command = shlex.join(NOTES.command)
    label = f"{output.LABEL_PREFIX}{json.dumps({'command': command})} -->"
    (repo / "docs" / "notes.md").write_text(
        f"# Notes\n\n<!-- notes:begin -->\n{label}\n\n| 1 |\n<!-- notes:end -->\n"
    )
    _relabel(repo, _commit(repo, "a generator of notes"))
    _commit(repo, "every block generated")
    return repo


def test_a_docstring_or_comment_stales_no_block_and_a_constant_of_the_plant_stales_its_users(
    clone,
):
    registry = {**blocks.BLOCKS, "notes": NOTES}
    assert blocks.check_docs(clone, registry) == []
    labelled = _git(clone, "rev-parse", "HEAD~1")
    plant = clone / "fojax" / "plant.py"
    text = plant.read_text()
    assert text.count("_GRAVITY = 9.81  # m / s^2\n") == 1
    edited = text.replace('"""Quadrotor plant', '"""The quadrotor plant', 1)
    edited = edited.replace("_GRAVITY = 9.81  # m / s^2", "# g\n_GRAVITY = 9.81  # m/s^2")
    plant.write_text(edited)
    _commit(clone, "plant: its docstring and comments")
    assert blocks.check_docs(clone, registry) == []

    plant.write_text(edited.replace("_GRAVITY = 9.81", "_GRAVITY = 9.80"))
    gravity = _commit(clone, "plant: gravity 9.80")
    plant.write_text(edited.replace("_GRAVITY = 9.81", "_GRAVITY = 9.80").replace("# g\n", ""))
    _commit(clone, "plant: a comment less")  # later, and no change of code
    stale = _stale(clone, registry)

    def uses_plant(block):
        found = blocks.dependencies(block, clone)
        return any(p == "fojax/plant.py" or "fojax/plant.py".startswith(p + "/") for p in found)

    assert set(stale) == {name for name, block in registry.items() if uses_plant(block)}
    simulating = (
        "bench reproduction reproduction-sat distributed sensitivity fair-comparison"
        " tuning-study tune-paper-gains requirements-study requirements-methods vehicles"
        " remark3-inverted bench-gpu setup"
    )
    assert set(simulating.split()) <= set(stale)
    assert "regeneration" not in stale and "notes" not in stale
    assert "fojax/plant.py" not in blocks.dependencies(NOTES, clone)
    command = " ".join(registry["vehicles"].command)
    assert stale["vehicles"] == (
        f"vehicles: stale: the code of 1 file(s) it depends on changed since "
        f"{labelled[:7]} (fojax/plant.py), the last at "
        f"{gravity[:7]} plant: gravity 9.80; regenerate it: {command}"
    )
