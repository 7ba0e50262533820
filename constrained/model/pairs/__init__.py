"""Pair potentials V = Σ_{i<j} φ(r_ij) as one mapped kernel each (issue 28): the kernel and its
graph (``kernel``), the neighbour lists of a cutoff (``neighbours``), and a Structure's pair
potentials together (``potentials``)."""

from .kernel import BLOCK, GROUP, PairSpec, PairTerm, effective
from .neighbours import GROUP_ROWS, ROW, pair_rows
from .potentials import MAPPED_PAIRS_FROM, PairPotentials

__all__ = ["BLOCK", "GROUP", "MAPPED_PAIRS_FROM", "PairPotentials", "PairSpec", "PairTerm",
           "effective", "pair_rows", "GROUP_ROWS", "ROW"]
