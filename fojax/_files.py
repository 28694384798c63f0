"""Reading the project's input files (vehicle, reference and requirement files): one
table of TOML (or JSON), or one error of the file's own kind that says why not."""

from __future__ import annotations

import json
import os
import tomllib
from pathlib import Path


def read_table(path: str | os.PathLike, error: type[Exception], kind: str,
               formats: tuple[str, ...] = (".toml",)) -> object:  # fmt: skip
    """The content of the file at ``path``, parsed by its suffix among ``formats``
    (``.toml``; ``.json``); ``error(message)`` for a file that cannot be read, has
    another suffix (where several formats are accepted) or does not parse. ``kind``
    names the file in messages (``"requirement file"``)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as failure:
        raise error(f"{path}: cannot read the {kind}: {failure.strerror or failure}") from None
    except UnicodeDecodeError as failure:
        raise error(f"{path} is not a text file: {failure}") from None
    suffix = path.suffix.lower() if len(formats) > 1 else formats[0]
    if suffix not in formats:
        raise error(f"{path}: the {kind} must end in {' or '.join(formats)}")
    try:
        return tomllib.loads(text) if suffix == ".toml" else json.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as failure:
        raise error(f"{path} is not valid {suffix[1:].upper()}: {failure}") from None
