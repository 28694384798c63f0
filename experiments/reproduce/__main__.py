"""``python -m experiments.reproduce``: the same as ``fojax reproduce``."""

import sys

from experiments.reproduce.command import main

sys.exit(main())
