"""A Model holding only some of its constraint rows: what a run with one-sided constraints
integrates between two events (the two-sided rows and the one-sided rows in contact).

``held(model, rows)`` is a Model like any other — f, J, f_t and γ keep the rows held, the
forces, energy and masses are the model's — so every method, its compiled step loops and
its watches run it unchanged; it is built once per model and row set (a few CasADi calls
selecting rows, no differentiation).
"""

from __future__ import annotations

import functools

import casadi as ca

from .cache import built_once
from .structure import Model


class HeldRows(Model):
    """``model`` restricted to the constraint ``rows`` (indices into the model's rows)."""

    def __init__(self, model: Model, rows: tuple[int, ...]):  # noqa: D107 (no Model.__init__)
        self.__dict__.update({k: v for k, v in vars(model).items() if k not in _FUNCTIONS})
        self.full = model
        self.rows = tuple(int(k) for k in rows)
        self.constraint_labels = [model.constraint_labels[k] for k in self.rows]
        self.constraint_owner = model.constraint_owner[list(self.rows)]
        self.n_constraints = len(self.rows)
        #: The held rows of f (position rows come first, velocity rows after them).
        self.position_rows = tuple(k for k in self.rows if k < model.n_position_rows)
        self.n_position_rows = len(self.position_rows)

    def _selected(self, name: str, outputs: dict[int, str], *, parametric: bool = False,
                  differentiable: bool = False) -> ca.Function:
        """The model's Function ``name`` (with p as its last input when ``parametric``) with the
        row-indexed outputs (index -> 'rows' for a column vector, 'matrix' for J) restricted
        to the held rows."""
        f = (self.full.parametric(name, differentiable=differentiable) if parametric
             else getattr(self.full, name))
        kind = ca.MX if f.is_a("MXFunction") else ca.SX  # (pair potentials: mapped kernels)
        inputs = [kind.sym(f.name_in(i), f.sparsity_in(i)) for i in range(f.n_in())]
        out = f.call(inputs)
        rows = list(self.position_rows if name in ("constraint", "jacobian") else self.rows)
        for i in outputs:
            out[i] = out[i][rows, :] if rows else ca.SX(0, out[i].shape[1])
        return ca.Function(name, inputs, out, f.name_in(), f.name_out())

    constraint = functools.cached_property(lambda self: self._restricted("constraint"))
    jacobian = functools.cached_property(lambda self: self._restricted("jacobian"))
    velocity_terms = functools.cached_property(lambda self: self._restricted("velocity_terms"))
    dynamics = functools.cached_property(lambda self: self._restricted("dynamics"))

    def _restricted(self, name: str) -> ca.Function:
        return self._selected(name, _ROW_OUTPUTS[name])

    def parametric(self, name: str, *, differentiable: bool = False) -> ca.Function:
        outputs = _ROW_OUTPUTS.get(name)
        if outputs is None:
            return self.full.parametric(name, differentiable=differentiable)
        return built_once(self.full.structure, ("held parametric", name, self.rows, differentiable),
                          lambda: self._selected(name, outputs, parametric=True,
                                                 differentiable=differentiable))

    def with_parameters(self, parameters=None) -> Model:
        if not parameters:
            return self
        return held(self.full.with_parameters(parameters), self.rows)


#: The outputs of each Function that are indexed by constraint row.
_ROW_OUTPUTS = {"constraint": {0: "rows"}, "jacobian": {0: "rows", 1: "matrix"},
                "velocity_terms": {0: "matrix", 1: "rows"}, "dynamics": {1: "matrix", 2: "rows"}}
_FUNCTIONS = tuple(_ROW_OUTPUTS)


def held(model: Model, rows) -> Model:
    """``model`` holding only ``rows`` (the model itself when that is every row)."""
    rows = tuple(sorted(int(k) for k in rows))
    if rows == tuple(range(model.n_constraints)):
        return model
    return built_once(model, ("held", rows), lambda: HeldRows(model, rows))
