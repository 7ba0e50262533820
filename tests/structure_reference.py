"""The reference description of what a Structure is built from, item by item: what
``lifting.fingerprint_walk`` hashes column by column (it was the fingerprint's own walk until
session 17), kept for the tests that compare the two."""

from __future__ import annotations

import numpy as np

from constrained.model import lifting


def structure_data(system, walked: list | None = None) -> tuple[list, list[float]]:
    """``(data, values)``: JSON-able data of everything a Structure is built from (what
    ``structure_fingerprint`` hashes: particle names and masses — Numbers, or their formulas —,
    each constraint and effect — its class and every attribute —, the parameter names in order
    and the definitions) and the plain numbers ``numbers(system)`` gives. NotPlain (or
    TypeError, ValueError) when an item holds a value that cannot be described exactly.
    ``walked``: a list that receives the walk for ``lift`` (the lifted masses, each item's
    lifted fields), once it is complete."""
    values: list[float] = []
    particles = system.particles
    masses = [p.mass for p in particles]
    if set(map(type, masses)) == {float} and not any("mass" in p.formulas for p in particles) \
            and np.all(np.isfinite(masses)) and np.all(np.asarray(masses) != 0):
        values += masses  # every mass a Number (lifted_mass), in order: at once
        described = [[p.name, ["number", k]] for k, p in enumerate(particles)]
        lifted_masses = [lifting.Number(k) for k in range(len(particles))] if walked is not None else None
    else:
        lifted_masses = [lifting.lifted_mass(p, values) for p in particles]
        described = [[p.name, ["formula", p.formulas["mass"]] if "mass" in p.formulas
                      else lifting.plain_data(mass)]
                     for p, mass in zip(particles, lifted_masses, strict=True)]
    item_fields = []
    # Items in runs of one class and one set of attributes: [module, class, numeric fields, other
    # attributes, [[numeric values, other values] per item]] (a run's names written once).
    runs: list = []
    header = None
    # (the lifted fields' and the other attributes' names of an item with the class and the
    # attribute names of the one before: a run's, found once, not per item)
    shape, names, other = None, (), ()
    for item in (*system.constraints, *system.effects):
        attributes = vars(item)
        cls = type(item)
        if shape is None or shape[0] is not cls or shape[1] != tuple(attributes):
            shape, names = (cls, tuple(attributes)), lifting.fields(item)
            other = tuple(k for k in attributes if k not in names)
        lifted = {name: lifting._entries(getattr(item, name), values) for name in names}  # (lifted_fields)
        item_fields.append(lifted)
        key = (cls, tuple(lifted), other)
        if key != header:
            header = key
            runs.append([cls.__module__, cls.__qualname__, list(key[1]), list(other), []])
        runs[-1][4].append([[lifting._plain_value(v) for v in lifted.values()],
                            [lifting._plain_value(attributes[k]) for k in other]])
    data = [described, runs, list(system.parameters), lifting.plain_data(system.definitions)]
    if walked is not None:
        walked[:] = [lifted_masses, item_fields, values]
    return data, values
