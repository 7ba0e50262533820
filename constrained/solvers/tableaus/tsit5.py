"""Tsitouras' 5(4) pair (Ch. Tsitouras, Comput. Math. Appl. 62 (2011) 770–775): fifth order,
a fourth-order embedded estimate, 6 stages plus first-same-as-last. Its coefficients are
tuned for a small principal error: at equal work often more accurate than Dormand–Prince 5(4).
"""

import numpy as np

from .tableau import Tableau

_c = [0.0, 0.161, 0.327, 0.9, 0.9800255409045096857, 1.0]
_a = [
    [],
    [0.161],
    [-0.008480655492356988544, 0.3354806554923569885],
    [2.897153057105493432, -6.359448489975074843, 4.362295432869581411],
    [5.325864828439256604, -11.74888356406282788, 7.495539342889836208, -0.09249506636175524926],
    [5.861455442946420029, -12.92096931784710929, 8.159367898576158643, -0.07158497328140099722,
     -0.02826905039406838291],
]
_b = [0.09646076681806522952, 0.01, 0.4798896504144995748, 1.379008574103741893, -3.290069515436080680,
      2.324710524099773982]
# the embedded fourth-order weights b̂ (with 1/66 on the first-same-as-last stage)
_b_hat = [0.09468075576583945807, 0.009183565540343253097, 0.4877705284247615708, 1.234297566930478986,
          -2.707712349983525455, 1.866628418170587036, 1 / 66]

A = np.zeros((6, 6))
for i, row in enumerate(_a):
    A[i, : len(row)] = row
B = np.array(_b)

TSIT5 = Tableau("Tsit5", A, B, np.array(_c), (np.append(B, 0.0) - np.array(_b_hat),), order=5, error_order=4)
