"""The explicit Runge–Kutta pairs ``dopri`` can run (``base``): one module per pair."""

from scipy.integrate import DOP853, RK45

from ..tableau import Tableau, from_scipy
from .tsit5 import TSIT5

#: The pairs by name. Dormand–Prince 8(5,3) and 5(4) are SciPy's own coefficients.
TABLEAUS: dict[str, Tableau] = {t.name: t for t in (
    from_scipy("DOP853", DOP853, (DOP853.E5, DOP853.E3)),
    from_scipy("DOPRI5", RK45, (RK45.E,)),
    TSIT5,
)}
