"""Every Python example in the README and in docs/ runs as written."""

import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BLOCK = re.compile(r"```python\n(.*?)```", re.S)


def _examples():
    for page in PAGES:
        for i, match in enumerate(BLOCK.finditer(page.read_text())):
            yield pytest.param(match.group(1), id=f"{page.name}-{i}")


@pytest.mark.parametrize("code", list(_examples()))
def test_example_runs(code, monkeypatch):
    from fojax.controllers import registry

    monkeypatch.setattr(registry, "_LAWS", dict(registry._LAWS))  # examples register laws
    exec(compile(code, "<example>", "exec"), {"__name__": "__main__"})  # as a script


def test_there_are_examples():
    names = {p.id.split("-")[0] for p in _examples()}
    assert {"README.md", "extending.md"} <= names
