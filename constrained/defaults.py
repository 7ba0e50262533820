"""Defaults that several layers read, written once (no imports: the ground floor)."""

#: The method a run takes when none is named: the CasADi-stepped DOP853 with projection after
#: every step (``dopri``), which has every feature of the driver loop; ``projection``
#: (SciPy-stepped) stays the reference method. See docs/methods.md.
DEFAULT_METHOD = "dopri"
