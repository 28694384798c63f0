"""``python -m fojax.cli``: the same as the ``fojax`` command."""

import sys

from fojax.cli import main

sys.exit(main())
