"""The SUNDIALS-based steppers (through CasADi): ``idas`` and ``ggl`` (IDAS on the index-1 and
the stabilized index-2 DAE) and ``pantelides`` (CasADi's structural index reduction, then IDAS).
Segment steppers: one call per group of output times (solvers/base.py's contract)."""

from .idas import GGL, Idas
from .pantelides import Pantelides

__all__ = ["GGL", "Idas", "Pantelides"]
