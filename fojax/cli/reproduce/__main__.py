"""``python -m fojax.cli.reproduce``: the same as ``fojax reproduce``."""

import sys

from fojax.cli.reproduce.command import main

sys.exit(main())
