"""Interchangeable solvers behind ``simulate(..., method=...)``; see base.Solver for the contract."""

from .base import Solution, Solver
from .projection import Projection

METHODS: dict[str, type[Solver]] = {Projection.name: Projection}

__all__ = ["METHODS", "Projection", "Solution", "Solver"]
