"""SX algorithms written as C statements, one instruction at a time, from a whitelist of
operations: the bodies of the hand-written C loops (constrained.model.pairs.fused, the pair
forces; constrained.manifold.vectorized.fused, the constraint rows) that evaluate a CasADi
kernel inside a loop over instances read by index, where CasADi's own ``map`` would gather
every input into arrays first."""

from __future__ import annotations

import math

import casadi as ca

#: C for each whitelisted SX operation, from its operands a (and b).
C_OPERATIONS = {
    ca.OP_ASSIGN: "{a}", ca.OP_ADD: "{a}+{b}", ca.OP_SUB: "{a}-{b}", ca.OP_MUL: "{a}*{b}",
    ca.OP_DIV: "{a}/{b}", ca.OP_NEG: "-{a}", ca.OP_EXP: "exp({a})", ca.OP_LOG: "log({a})",
    ca.OP_POW: "pow({a},{b})", ca.OP_CONSTPOW: "pow({a},{b})", ca.OP_SQRT: "sqrt({a})",
    ca.OP_SQ: "{a}*{a}", ca.OP_TWICE: "2.*{a}", ca.OP_INV: "1./{a}",
    ca.OP_SIN: "sin({a})", ca.OP_COS: "cos({a})", ca.OP_TAN: "tan({a})",
    ca.OP_ASIN: "asin({a})", ca.OP_ACOS: "acos({a})", ca.OP_ATAN: "atan({a})",
    ca.OP_SINH: "sinh({a})", ca.OP_COSH: "cosh({a})", ca.OP_TANH: "tanh({a})",
    ca.OP_ASINH: "asinh({a})", ca.OP_ACOSH: "acosh({a})", ca.OP_ATANH: "atanh({a})",
    ca.OP_ATAN2: "atan2({a},{b})", ca.OP_HYPOT: "hypot({a},{b})", ca.OP_ERF: "erf({a})",
    ca.OP_LOG1P: "log1p({a})", ca.OP_EXPM1: "expm1({a})",
    ca.OP_FABS: "fabs({a})", ca.OP_FLOOR: "floor({a})", ca.OP_CEIL: "ceil({a})",
    ca.OP_FMOD: "fmod({a},{b})", ca.OP_FMIN: "fmin({a},{b})", ca.OP_FMAX: "fmax({a},{b})",
    ca.OP_COPYSIGN: "copysign({a},{b})", ca.OP_SIGN: "({a}>0?1.:({a}<0?-1.:{a}))",
    ca.OP_LT: "({a}<{b})", ca.OP_LE: "({a}<={b})", ca.OP_EQ: "({a}=={b})", ca.OP_NE: "({a}!={b})",
    ca.OP_NOT: "(!{a})", ca.OP_AND: "({a}&&{b})", ca.OP_OR: "({a}||{b})",
    ca.OP_IF_ELSE_ZERO: "({a}?{b}:0.)",
}


def _divisors(function: ca.Function) -> dict[int, int]:
    """For each instruction, how often its value is divided by (the values, not the slots)."""
    producer: dict[int, int] = {}
    count: dict[int, int] = {}
    for k in range(function.n_instructions()):
        op = function.instruction_id(k)
        if op == ca.OP_DIV:
            source = producer.get(function.instruction_input(k)[1])
            count[source] = count.get(source, 0) + 1
        if op != ca.OP_OUTPUT:
            producer[function.instruction_output(k)[0]] = k
    return count


def scalar_c(function: ca.Function, inputs: list[str], outputs: list[str], prefix: str = "s",
             reciprocals: dict[str, str] | None = None, repeated_divisors: bool = False) -> str | None:
    """C statements evaluating the SX Function ``function`` (its inputs the C variables
    ``inputs``: a name ending in ``[]`` an array, read as ``name[k]``) into the C variables
    ``outputs`` (declared by the caller), its work in locals ``{prefix}0, {prefix}1, …``; None
    when it uses an operation outside ``C_OPERATIONS``. ``reciprocals`` {input: C variable holding
    1/input}: a division by that scalar input is written as a product with its reciprocal (one
    division for all of them); ``repeated_divisors``: the same for every value divided by more
    than once (the result changes by rounding; CasADi itself folds a·(1/b) back into a/b)."""
    reciprocals = reciprocals or {}
    holds: dict[int, str] = {}  # work slot -> the scalar input it holds unchanged
    divisors = _divisors(function) if repeated_divisors else {}
    made: dict[int, int] = {}  # work slot -> the instruction whose value it holds
    if not function.is_a("SXFunction"):
        return None
    work = function.sz_w()
    lines = [f"casadi_real {', '.join(f'{prefix}{k}' for k in range(work))};"] if work else []

    def operand(k: int) -> str:
        return f"{prefix}{k}"

    for k in range(function.n_instructions()):
        op = function.instruction_id(k)
        if op == ca.OP_INPUT:
            index, nz = function.instruction_input(k)
            name = inputs[index]
            source = f"{name[:-2]}[{nz}]" if name.endswith("[]") else name
            slot = function.instruction_output(k)[0]
            lines.append(f"{operand(slot)} = {source};")
            holds[slot] = source
            made[slot] = k
            if divisors.get(k, 0) > 1 and name not in reciprocals:
                lines.append(f"const casadi_real {prefix}r{k} = 1./{operand(slot)};")
            continue
        elif op == ca.OP_OUTPUT:
            index, nz = function.instruction_output(k)
            if function.nnz_out(index) != 1:
                return None
            lines.append(f"{outputs[index]} = {operand(function.instruction_input(k)[0])};")
        elif op == ca.OP_CONST:
            value = float(function.instruction_constant(k))
            if not math.isfinite(value):
                return None  # (no C literal)
            lines.append(f"{operand(function.instruction_output(k)[0])} = {value!r};")
        elif op in C_OPERATIONS:
            slots = function.instruction_input(k)
            args = [operand(a) for a in slots]
            if op == ca.OP_DIV and holds.get(slots[1]) in reciprocals:
                expression = f"{args[0]}*{reciprocals[holds[slots[1]]]}"
            elif op == ca.OP_DIV and divisors.get(made.get(slots[1]), 0) > 1:
                expression = f"{args[0]}*{prefix}r{made[slots[1]]}"
            else:
                expression = C_OPERATIONS[op].format(a=args[0], b=args[1] if len(args) > 1 else "")
            lines.append(f"{operand(function.instruction_output(k)[0])} = {expression};")
        else:
            return None
        for slot in function.instruction_output(k)[:1] if op != ca.OP_OUTPUT else ():
            holds.pop(slot, None)
            made[slot] = k
            if divisors.get(k, 0) > 1:
                lines.append(f"const casadi_real {prefix}r{k} = 1./{operand(slot)};")
    return "\n".join(lines)
