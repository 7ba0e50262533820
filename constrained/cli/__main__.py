"""``python -m constrained.cli``: the ``constrained`` command."""

import sys

from .main import main

sys.exit(main())
