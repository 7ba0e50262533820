"""``python -m constrained``: the ``constrained`` command."""

import sys

from .cli.main import main

sys.exit(main())
