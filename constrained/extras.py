"""Optional dependencies: the package's name on the package index and its extras.

The distribution is ``constrained-particles`` (the name ``constrained`` on the index belongs to
an unrelated project); the import name and the command stay ``constrained``. ``need(module,
extra, purpose)`` imports an optional module or raises an ImportError that says how to install
it. Ground floor: imports nothing of the package.
"""

from __future__ import annotations

import importlib
from types import ModuleType

#: The name to give pip: ``pip install 'constrained-particles[dask]'``.
DISTRIBUTION = "constrained-particles"


def install_hint(extra: str) -> str:
    """``pip install 'constrained-particles[EXTRA]'`` and its form in a source checkout."""
    return f"pip install '{DISTRIBUTION}[{extra}]' (from a source checkout: pip install '.[{extra}]')"


def need(module: str, extra: str, purpose: str) -> ModuleType:
    """``import module``, or an ImportError naming what needs it and how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        top = module.split(".")[0]
        raise ImportError(f"{purpose} needs {top}, which is not installed: {install_hint(extra)}, "
                          f"or pip install {top}") from None
