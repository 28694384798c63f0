"""A hash of a package's source, for caches that must not outlive the code that filled
them (stored draws, exported programs)."""

from __future__ import annotations

import hashlib
from pathlib import Path


def digest(root: Path) -> str:
    """16 hex digits of SHA-256 over every ``*.py`` below ``root`` (relative paths and
    contents, in sorted order)."""
    root = Path(root)
    hashed = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        hashed.update(path.relative_to(root).as_posix().encode())
        hashed.update(path.read_bytes())
    return hashed.hexdigest()[:16]
