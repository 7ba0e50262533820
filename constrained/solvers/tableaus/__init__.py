"""The explicit Runge–Kutta pairs ``dopri`` can run (``base``): one module per pair."""

from .dop853 import DOP853
from .dopri5 import DOPRI5
from .tableau import Tableau
from .tsit5 import TSIT5

#: The pairs by name. Dormand–Prince 8(5,3) and 5(4) are SciPy's own coefficients.
TABLEAUS: dict[str, Tableau] = {t.name: t for t in (DOP853, DOPRI5, TSIT5)}
