"""RODAS (Hairer and Wanner, Solving ODEs II, §VI.4; their code rodas.f, METH = 1): the
stiffly accurate, L-stable Rosenbrock method of order 4 with an embedded order-3 estimate
and a third-order dense output, for problems M y' = f(t, y) with a singular M (index-1 DAEs).

In the form without matrix–vector products by the Jacobian (``solvers/rodas.py``), with
W = M/(γh) − ∂f/∂y factored once per step:

    W U_i = f(t + α_i h, y + Σ_{j<i} a_ij U_j) + M Σ_{j<i} (c_ij / h) U_j + h d_i ∂f/∂t,
    y_new = y + Σ_{j<5} a_5j U_j + U_5 + U_6,   error estimate U_6,

stiffly accurate: stage 6 is taken at y_new − U_6 and stage 5 at y + Σ_{j<5} a_5j U_j (both at
t + h). Dense output on [t, t + h], s = θ/h: y(s) = (1 − s) y + s (y_new + (1 − s)(Σ d2_j U_j
+ s Σ d3_j U_j)). The numbers are rodas.f's (also those of Numerical Recipes' StepperRoss).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Rosenbrock:
    name: str
    gamma: float
    A: np.ndarray  # (6, 6) strictly lower: stage arguments y + Σ a_ij U_j
    C: np.ndarray  # (6, 6) strictly lower: M Σ c_ij U_j / h on the right-hand side
    alpha: np.ndarray  # (6,) stage times t + α_i h
    d: np.ndarray  # (6,) coefficients of h ∂f/∂t
    dense: np.ndarray  # (2, 6): the dense output's Σ d2_j U_j and Σ d3_j U_j
    order: int
    error_order: int

    @property
    def stages(self) -> int:
        return len(self.alpha)


def _lower(rows) -> np.ndarray:
    out = np.zeros((6, 6))
    for i, row in enumerate(rows):
        out[i, :len(row)] = row
    return out


_A5 = [1.221224509226641, 6.019134481288629, 12.53708332932087, -0.6878860361058950]
RODAS4 = Rosenbrock(
    name="RODAS4",
    gamma=0.25,
    A=_lower([[], [1.544], [0.9466785280815826, 0.2557011698983284],
              [3.314825187068521, 2.896124015972201, 0.9986419139977817], _A5, [*_A5, 1.0]]),
    C=_lower([[], [-5.6688], [-2.430093356833875, -0.2063599157091915],
              [-0.1073529058151375, -9.594562251023355, -20.47028614809616],
              [7.496443313967647, -10.24680431464352, -33.99990352819905, 11.70890893206160],
              [8.083246795921522, -7.981132988064893, -31.52159432874371, 16.31930543123136,
               -6.058818238834054]]),
    alpha=np.array([0.0, 0.386, 0.21, 0.63, 1.0, 1.0]),
    d=np.array([0.25, -0.1043, 0.1035, -0.3620000000000023e-01, 0.0, 0.0]),
    dense=np.array([[10.12623508344586, -7.487995877610167, -34.80091861555747, -7.992771707568823,
                     1.025137723295662, 0.0],
                    [-0.6762803392801253, 6.087714651680015, 16.43084320892478, 24.76722511418386,
                     -6.594389125716872, 0.0]]),
    order=4,
    error_order=3,
)
