"""A hand-written C loop as a CasADi Function, through the compile cache.

``c_function(name, body, …)`` wraps ``body`` in CasADi's external-function API (the entry
point ``name(arg, res, iw, w, mem)`` with ``name_n_in``, ``name_sparsity_in`` … and
``name_work``), compiles it with ``compiled.compile_source`` — cached on disk by the source
itself, signed and checked on loading like every compiled library — and loads it with
``casadi.external``: the next run with the same source loads it without compiling. The body
reads its inputs as ``const casadi_real *NAME`` (null: all zeros) and writes its outputs
through ``casadi_real *NAME`` (null: not wanted). The Function has no derivatives.

A loop's index data (which coordinates each instance reads) goes into an ``IndexTable``: one
static string literal, read by the loops in place, and the bytes the cache key hashes.

``casadi.Function.jit`` does the same but compiles at every construction (0.6 s each here),
which a run that builds a few such loops could not afford.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from . import compiled

#: Each byte as the shortest octal escape (its characters, padded to 4, and their count):
#: every byte is escaped, so the next character is always a backslash (or the closing quote),
#: never a digit that would extend the escape.
_ESCAPES = [f"\\{k:o}".encode() for k in range(256)]
_OCTAL = np.array([list(e.ljust(4, b" ")) for e in _ESCAPES], np.uint8)
_OCTAL_LENGTH = np.array([len(e) for e in _ESCAPES])


def octal_literal(data: bytes) -> str:
    """The bytes as the characters of a C string literal, built as one array (a Python string
    per byte of a 10⁷-byte table would take ten times its memory)."""
    codes = np.frombuffer(data, np.uint8)
    wanted = np.arange(4)[None, :] < _OCTAL_LENGTH[codes][:, None]
    return _OCTAL[codes][wanted].tobytes().decode("ascii")


class IndexTable:
    """Integer arrays (index data) laid end to end in one static table ``TABLE`` of a C
    source: ``add`` gives each array's place as a C expression, ``c()`` the table itself, as
    one string literal, which a compiler reads ten times faster (and in a tenth of the
    memory) than a list of numbers."""

    def __init__(self):
        self.parts: list[np.ndarray] = []
        self.size = 0

    def add(self, values) -> str:
        """The C expression of ``values``' place in the table."""
        values = np.asarray(values, np.int32).reshape(-1)
        at = self.size
        self.parts.append(values)
        self.size += values.size
        return f"(TABLE + {at})"

    def data(self) -> bytes:
        return (np.concatenate(self.parts) if self.parts else np.zeros(1, np.int32)).tobytes()

    def c(self) -> str:
        """The table's C (before the entry points that read it)."""
        data = self.data()
        text, size = octal_literal(data), len(data) + 1
        return (f'static const char table_bytes[{size}] __attribute__((aligned(8))) = "{text}";\n'
                "#define TABLE ((const int *) table_bytes)\n")


def element(table: IndexTable, values, var: str = "i") -> str:
    """``values[var]`` as a C expression: ``a + b var`` where the values step evenly (a chain's
    rows and coordinates: no index read, and loops the compiler can vectorize), else a read of
    the values put in ``table``."""
    values = np.asarray(values, np.int64).reshape(-1)
    if values.size == 0:
        return "0"
    step = int(values[1] - values[0]) if values.size > 1 else 0
    if values.size == 1 or np.all(np.diff(values) == step):
        start = int(values[0])
        term = var if step == 1 else f"{step} * {var}"
        return f"({start} + {term})" if step and start else (f"({term})" if step else str(start))
    return f"{table.add(values)}[{var}]"


def _array(name: str, values: list[int]) -> str:
    return f"static const casadi_int {name}[{len(values)}] = {{{', '.join(map(str, values))}}};"


def _compressed(sparsity: ca.Sparsity) -> list[int]:
    """CasADi's compressed form of ``sparsity``; a dense one as its shorthand (rows, columns, 1)."""
    if sparsity.is_dense():
        return [sparsity.size1(), sparsity.size2(), 1]
    return list(sparsity.compress())


def _switch(name: str, kind: str, cases: list[str]) -> str:
    lines = "\n".join(f"    case {k}: return {c};" for k, c in enumerate(cases))
    return f"""CASADI_SYMBOL_EXPORT {kind} {name}(casadi_int i) {{
  switch (i) {{
{lines}
    default: return 0;
  }}
}}"""


#: The loops' flags: -O3 vectorizes a group's kernel over its instances (one rod per lane), and
#: -fno-math-errno lets ``sqrt`` be the instruction (errno is never read here): on the 1 cm rope
#: the rows 1.8x, the products 1.2-2x faster. No ``-march=native`` (no gain measured; the
#: library stays portable) and no fast-math (the sums keep their order and rounding).
LOOP_FLAGS = ("-O3", "-fno-math-errno", *compiled.FLAGS[1:])

PRELUDE = """#include <math.h>
#ifndef casadi_real
#define casadi_real double
#endif
#ifndef casadi_int
#define casadi_int long long int
#endif
#ifndef CASADI_SYMBOL_EXPORT
#define CASADI_SYMBOL_EXPORT __attribute__ ((visibility ("default")))
#endif
"""


def entry(name: str, body: str, names_in: list[str], sparsity_in: list[ca.Sparsity], names_out: list[str],
          sparsity_out: list[ca.Sparsity], work: int = 0, iwork: int = 0) -> str:
    """The C of one entry point ``name`` running ``body`` (after ``PRELUDE``); ``work``,
    ``iwork``: the lengths of the scratch arrays ``w`` (reals) and ``iw`` (integers) it may use
    (CasADi's, per call: safe across threads)."""
    sparsities = [*sparsity_in, *sparsity_out]
    arrays = "\n".join(_array(f"{name}_s{k}", _compressed(s)) for k, s in enumerate(sparsities))
    unpack = "\n".join([f"  const casadi_real *{v} = arg[{k}];" for k, v in enumerate(names_in)]
                       + [f"  casadi_real *{v} = res[{k}];" for k, v in enumerate(names_out)])
    n_in, n_out = len(names_in), len(names_out)
    return f"""{arrays}
static int {name}_body(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w) {{
{unpack}
{body}
}}
CASADI_SYMBOL_EXPORT int {name}(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w,
                               int mem) {{
  return {name}_body(arg, res, iw, w);
}}
CASADI_SYMBOL_EXPORT int {name}_casadi_int_size(void) {{ return (int) sizeof(casadi_int); }}
CASADI_SYMBOL_EXPORT int {name}_casadi_real_size(void) {{ return (int) sizeof(casadi_real); }}
CASADI_SYMBOL_EXPORT casadi_int {name}_n_in(void) {{ return {n_in}; }}
CASADI_SYMBOL_EXPORT casadi_int {name}_n_out(void) {{ return {n_out}; }}
{_switch(f"{name}_name_in", "const char*", [f'"{v}"' for v in names_in])}
{_switch(f"{name}_name_out", "const char*", [f'"{v}"' for v in names_out])}
{_switch(f"{name}_sparsity_in", "const casadi_int*", [f"{name}_s{k}" for k in range(n_in)])}
{_switch(f"{name}_sparsity_out", "const casadi_int*", [f"{name}_s{n_in + k}" for k in range(n_out)])}
CASADI_SYMBOL_EXPORT int {name}_work(casadi_int *sz_arg, casadi_int* sz_res, casadi_int *sz_iw,
                                     casadi_int *sz_w) {{
  if (sz_arg) *sz_arg = {n_in};
  if (sz_res) *sz_res = {n_out};
  if (sz_iw) *sz_iw = {iwork};
  if (sz_w) *sz_w = {work};
  return 0;
}}
"""


def c_functions(specs: list[tuple], shared=None, key: bytes | None = None,
                decided_by: bytes | None = None) -> list[ca.Function] | None:
    """Several C loops, each ``(name, body, names_in, sparsity_in, names_out, sparsity_out[,
    work[, iwork]])``, as CasADi Functions (see the module) from one library (one compiler run), with
    ``shared`` C (static data; a callable giving it, with ``key`` the bytes that decide it,
    builds it only when the library is not in the cache) before them; or None where
    compiled code cannot be had: no C compiler, ``CONSTRAINED_COMPILE=0``, a cache folder
    that is not private, or a failed compilation (``compiled.last_error`` says why).
    ``decided_by``: bytes that decide the whole source (``shared`` and the specs), the cache's
    key then, so that ``compiled.cached_source`` finds the library without the source."""
    if not specs or not compiled.enabled():
        return None
    like = [ca.Function(name, [ca.MX.sym(v, s) for v, s in zip(ni, si, strict=True)], [ca.MX(s) for s in so],
                        ni, no) for name, _, ni, si, no, so, *_ in specs]
    code = "".join(entry(*s) for s in specs)
    if decided_by is not None:
        text = shared if callable(shared) else lambda: shared or ""
        loaded = compiled.compile_source(lambda: PRELUDE + text() + code, like, key=decided_by,
                                         flags=LOOP_FLAGS)
    elif key is None:
        loaded = compiled.compile_source(_source(specs, shared or ""), like, flags=LOOP_FLAGS)
    else:
        loaded = compiled.compile_source(lambda: PRELUDE + shared() + code, like, key=key + code.encode(),
                                         flags=LOOP_FLAGS)
    return None if loaded[0] is like[0] else loaded


def _source(specs: list[tuple], shared: str = "") -> str:
    """The C source of the library of ``specs`` (``c_functions`` without a key: its cache key)."""
    return PRELUDE + shared + "".join(entry(*s) for s in specs)


def cached_loops(specs: list[tuple]):
    """The path of the library ``c_functions(specs)`` builds (no shared code, no key) when the
    compile cache holds it whole and signed, else None: nothing compiled or loaded, so that a
    caller may load its entry points one by one (``casadi.external``)."""
    return compiled.cached_library(specs[0][0], _source(specs).encode(), flags=LOOP_FLAGS)


def c_function(name: str, body: str, names_in: list[str], sparsity_in: list[ca.Sparsity],
               names_out: list[str], sparsity_out: list[ca.Sparsity]) -> ca.Function | None:
    """The C ``body`` as a CasADi Function (``c_functions`` of one)."""
    loaded = c_functions([(name, body, names_in, sparsity_in, names_out, sparsity_out)])
    return None if loaded is None else loaded[0]
