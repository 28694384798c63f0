"""``python -m fojax.cli``: the same as the ``fojax`` command."""

from fojax.cli import entry

entry()
