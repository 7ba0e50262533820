"""Interchangeable solvers behind ``simulate(..., method=...)``; see base.Solver for the contract."""

from ..defaults import DEFAULT_METHOD
from .base import Solution, Solver
from .baumgarte import Baumgarte
from .dopri import Dopri
from .projection import Projection
from .rattle import Rattle
from .reduced import Reduced
from .rodas import Rodas
from .sundials import GGL, Idas, Pantelides

METHODS: dict[str, type[Solver]] = {
    cls.name: cls for cls in (Projection, Baumgarte, Dopri, Rodas, Rattle, Idas, GGL, Pantelides, Reduced)
}

__all__ = ["DEFAULT_METHOD", "GGL", "METHODS", "Baumgarte", "Dopri", "Idas", "Pantelides", "Projection",
           "Rattle", "Reduced", "Rodas", "Solution", "Solver"]
