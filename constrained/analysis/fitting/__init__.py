"""Measurements and a model: observables, exact sensitivities of a run, least-squares fits."""
