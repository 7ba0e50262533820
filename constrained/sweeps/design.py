"""What a sweep runs: ``--vary`` specs, the design (grid x random draws, or rows of a design
file), run ids, and ``--summary`` columns. Nothing here simulates.

Specs (the part after ``KEY=``): a TOML value or list (``[1, 2, 3]``, ``0.5``), ``lin(a, b, n)``,
``log(a, b, n)`` (geometric), or a seeded random distribution ``uniform(a, b)``,
``normal(mu, sigma)``, ``loguniform(a, b)`` (these need ``samples``). Several specs make a full
grid (first key slowest); random specs draw ``samples`` points, crossed with the grid of the
others. Specs are read by a regular expression and :mod:`tomllib`, never ``eval``.

A design file (``--design FILE.csv|.parquet``) gives the variants as rows, one column per
scene key (``parameters.m1``), numbers only; its rows are crossed with the grid of any
``--vary`` specs (the file's rows slowest).
"""

from __future__ import annotations

import csv
import hashlib
import itertools
import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .. import tomlparse
from ..errors import InputError
from ..extras import install_hint
from ..scene.load import NESTED_TOO_DEEPLY, SceneError, parse_override, refuse_deep_nesting

#: The most runs one design may have (values of one spec, and grid x samples): a larger
#: design is refused before it is built (it would take minutes and gigabytes to list).
MAX_DESIGN_RUNS = 100_000

RANDOM = ("uniform", "normal", "loguniform")
RANGES = ("lin", "log")
REDUCTIONS = ("final", "max", "min", "max_abs", "mean")
#: The kind of the pseudo-specs made of a design file's columns.
DESIGN_FILE = "design file"

# --- specs -----------------------------------------------------------------------------------

_CALL_RE = re.compile(r"\s*([A-Za-z_]\w*)\s*\((.*)\)\s*", re.S)
_NAME_RE = re.compile(r"[A-Za-z_]\w*")


@dataclass(frozen=True)
class Spec:
    """One ``--vary`` spec: ``kind`` is ``values``, ``lin``, ``log`` or a distribution name."""

    key: str
    text: str
    kind: str
    args: tuple = ()
    values: tuple = ()

    @property
    def random(self) -> bool:
        return self.kind in RANDOM

    @property
    def source(self) -> str:
        """Where the values were given, for messages."""
        if self.kind == DESIGN_FILE:
            return f"--design {self.text}, column '{self.key}'"
        return f"--vary {self.key}={self.text}"

    @property
    def scattered(self) -> bool:
        """Whether the values are not a grid (random draws or a design file's rows)."""
        return self.random or self.kind == DESIGN_FILE

    @property
    def log(self) -> bool:
        return self.kind in ("log", "loguniform")

    def draw(self, rng: np.random.Generator, n: int) -> list[float]:
        a, b = self.args
        if self.kind == "uniform":
            out = rng.uniform(a, b, n)
        elif self.kind == "normal":
            out = rng.normal(a, b, n)
        else:
            out = np.exp(rng.uniform(math.log(a), math.log(b), n))
        return [float(v) for v in out]

    @property
    def name(self) -> str:
        """The last name of the key (``parameters.a`` -> ``a``), for formulas and axis labels."""
        names = _NAME_RE.findall(self.key)
        return names[-1] if names else self.key



def parse_spec(key: str, text: str) -> Spec:
    """Read one spec (see the module doc); an InputError says what is wrong."""
    where = f"--vary {key}={text}"
    m = _CALL_RE.fullmatch(text)
    if m:
        fn, inner = m.group(1), m.group(2)
        known = RANGES + RANDOM
        if fn not in known:
            raise InputError(f"unknown spec function '{fn}' (known: {', '.join(f + '(...)' for f in known)}, "
                             "or a list of values like [1, 2, 3])", where=where)
        parts = [p.strip() for p in inner.split(",")]
        want = 3 if fn in RANGES else 2
        if len(parts) != want or not all(parts):
            usage = {"lin": "lin(start, stop, n)", "log": "log(start, stop, n)",
                     "uniform": "uniform(low, high)",
                     "normal": "normal(mean, sigma)", "loguniform": "loguniform(low, high)"}[fn]
            raise InputError(f"'{fn}' takes {want} numbers: {usage}", where=where)
        nums = []
        for p in parts:
            try:
                v = float(p)
            except ValueError:
                raise InputError(f"'{p}' is not a number (spec arguments must be plain numbers)",
                                 where=where) from None
            if not math.isfinite(v):
                raise InputError(f"'{p}' is not finite", where=where)
            nums.append(v)
        if fn in RANGES:
            n = nums[2]
            if n != int(n) or n < 1:
                raise InputError(f"the number of values must be a whole number >= 1, got {parts[2]}",
                                 where=where)
            n = int(n)
            if n > MAX_DESIGN_RUNS:
                raise InputError(f"{n} values is more than the {MAX_DESIGN_RUNS} runs a sweep may have; "
                                 "use fewer values (or several sweeps)", where=where)
            a, b = nums[0], nums[1]
            if fn == "log":
                if a <= 0 or b <= 0:
                    raise InputError("a log range needs positive start and stop", where=where)
                vals = np.geomspace(a, b, n) if n > 1 else np.array([a])
            else:
                vals = np.linspace(a, b, n) if n > 1 else np.array([a])
            return Spec(key, text, fn, (a, b, n), tuple(float(v) for v in vals))
        a, b = nums
        if fn == "normal" and b < 0:
            raise InputError("sigma must be >= 0", where=where)
        if fn in ("uniform", "loguniform") and not a < b:
            raise InputError(f"'{fn}' needs low < high, got {parts[0]} and {parts[1]}", where=where)
        if fn == "loguniform" and a <= 0:
            raise InputError("'loguniform' needs positive bounds", where=where)
        return Spec(key, text, fn, (a, b))
    try:
        value = tomlparse.loads(f"value = {text}")["value"]
    except (tomlparse.TOMLDecodeError, RecursionError):
        raise InputError(
            f"cannot read the spec {text!r}: give a list [1, 2, 3], lin(start, stop, n), "
            "log(start, stop, n), "
            "uniform(low, high), normal(mean, sigma) or loguniform(low, high)", where=where) from None
    values = value if isinstance(value, list) else [value]
    if not values:
        raise InputError("the list of values is empty", where=where)
    _refuse_unusable_values(key, values, where)
    return Spec(key, text, "values", (), tuple(values))


def _refuse_unusable_values(key: str, values: list, where: str) -> None:
    """A listed value that no run can use is refused before anything runs, as ``lin(nan, ...)``
    and a design file's cells are: a number that is not finite (TOML's ``nan``, ``inf``, or
    ``1e400``, read as inf) anywhere in a value, and, for a ``parameters.NAME`` key, a value
    that is not a plain number (a parameter is a number; formulas go in [definitions]).
    Otherwise each such value would only become a failed row, found after the others ran."""
    parameter = re.fullmatch(r"parameters\.[^.\[\]]+", key) is not None

    def nonfinite(value) -> bool:
        if isinstance(value, float):
            return not math.isfinite(value)
        if isinstance(value, list):
            return any(nonfinite(v) for v in value)
        return False

    for i, value in enumerate(values):
        if nonfinite(value):
            raise InputError(f"value {i + 1} ({toml_value(value)}) is not a finite number (inf and nan "
                             "are not accepted; a number beyond 1.8e308 reads as inf); give finite values",
                             where=where)
        if parameter and (isinstance(value, bool) or not isinstance(value, int | float)):
            raise InputError(f"value {i + 1} ({toml_value(value)}) is not a number: a parameter takes "
                             "plain numbers (a formula of other parameters goes in [definitions])",
                             where=where)


def parse_vary(text: str) -> Spec:
    """``"KEY=SPEC"`` -> Spec. KEY uses the ``--set`` syntax."""
    if not isinstance(text, str) or "=" not in text:
        raise InputError(f"--vary {text!r}: expected KEY=SPEC, e.g. parameters.k=lin(1, 10, 5)")
    key, spec = text.split("=", 1)
    key = key.strip()
    try:
        parse_override(f"{key}=0")
    except SceneError:
        raise InputError(f"--vary {text!r}: {key!r} is not a key path (write e.g. parameters.k, "
                         "particles.p1.mass or particles[0].position[1])") from None
    return parse_spec(key, spec.strip())


def design(specs: Sequence[Spec], samples: int | None = None, seed: int = 0,
           rows: Sequence[dict[str, float]] | None = None) -> list[dict[str, Any]]:
    """The runs: a list of {key: value}. ``rows`` (a design file's, slowest) x the grid of the
    fixed specs x ``samples`` random draws."""
    fixed = [s for s in specs if not s.random]
    rand = [s for s in specs if s.random]
    if rand and samples is None:
        raise InputError(f"--vary {rand[0].key}={rand[0].text}: a random spec needs --samples N")
    if samples is not None:
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
            raise InputError(f"--samples must be a whole number >= 1, got {samples!r}")
        if not rand:
            raise InputError("--samples needs at least one random spec (uniform, normal, loguniform)")
    rows = list(rows) if rows else [{}]
    size = len(rows) * math.prod(len(s.values) for s in fixed) * (samples if rand else 1)
    if size > MAX_DESIGN_RUNS:
        counts = " x ".join(([f"{len(rows)} design rows"] if rows != [{}] else [])
                            + [str(len(s.values)) for s in fixed] + ([f"{samples} samples"] if rand else []))
        raise InputError(f"the design has {size} runs ({counts}), more than the {MAX_DESIGN_RUNS} a sweep "
                         "may have; use fewer values or samples (or split it into several sweeps)")
    keys = [s.key for s in specs]
    if len(set(keys)) != len(keys):
        dup = next(k for k in keys if keys.count(k) > 1)
        raise InputError(f"--vary {dup}: the key is varied twice")
    both = [k for k in rows[0] if k in keys]
    if both:
        raise InputError(f"--vary {both[0]}: the key is also a column of the design file; give it once")
    draws: list[dict[str, Any]] = [{}]
    if rand:
        rng = np.random.default_rng(seed)
        cols = {s.key: s.draw(rng, samples) for s in rand}
        draws = [{k: cols[k][i] for k in cols} for i in range(samples)]
    runs = []
    grid = list(itertools.product(*(s.values for s in fixed)))
    for row in rows:
        for combo in grid:
            base = dict(zip([s.key for s in fixed], combo, strict=True))
            for d in draws:
                point = {**base, **d}
                runs.append({**row, **{k: point[k] for k in keys}})
    return runs


def read_design_file(path) -> tuple[list[Spec], list[dict[str, float]]]:
    """A design file's columns (as specs of kind DESIGN_FILE, for the table and figures) and
    its rows. CSV (a header line of scene keys, then numbers) or Parquet (numeric columns).
    An InputError names the file, the column and the line or row of what is wrong."""
    path = Path(path)
    where = f"--design {path}"
    if not path.is_file():
        raise InputError("no such file" if not path.exists() else "is not a file", where=where)
    suffix = path.suffix.lower()
    if suffix == ".csv":
        keys, columns = _read_csv(path, where)
    elif suffix in (".parquet", ".pq"):
        keys, columns = _read_parquet(path, where)
    else:
        raise InputError(f"unknown design file type '{path.suffix}': give a .csv or .parquet file",
                         where=where)
    for key in keys:
        try:
            parse_override(f"{key}=0")
        except SceneError:
            raise InputError(f"the column '{key}' is not a scene key (write e.g. parameters.m1 or "
                             "particles.p1.mass)", where=where) from None
    n = len(columns[0])
    if n > MAX_DESIGN_RUNS:
        raise InputError(f"{n} rows is more than the {MAX_DESIGN_RUNS} runs a sweep may have; split the file",
                         where=where)
    specs = [Spec(k, str(path), DESIGN_FILE, (), tuple(c)) for k, c in zip(keys, columns, strict=True)]
    rows = [{k: columns[j][i] for j, k in enumerate(keys)} for i in range(n)]
    return specs, rows


def _check_keys(keys: list[str], where: str) -> None:
    if not keys:
        raise InputError("the file is empty: expected a header of scene keys (parameters.m1, ...) and "
                         "one row per variant", where=where)
    for j, k in enumerate(keys):
        if not k:
            raise InputError(f"column {j + 1} has no name (the header must name a scene key per column)",
                             where=where)
    dup = [k for k in keys if keys.count(k) > 1]
    if dup:
        raise InputError(f"the column '{dup[0]}' appears twice", where=where)


def _number(text, key: str, where: str, row: str) -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise InputError(f"{row}, column '{key}': {text!r} is not a number", where=where) from None
    if not math.isfinite(value):
        raise InputError(f"{row}, column '{key}': {text!r} is not a finite number", where=where)
    return value


def _read_csv(path: Path, where: str) -> tuple[list[str], list[list[float]]]:
    try:
        with open(path, newline="", encoding="utf-8") as f:
            lines = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"cannot read the file: {exc}", where=where) from None
    lines = [(i + 1, line) for i, line in enumerate(lines) if any(c.strip() for c in line)]
    keys = [k.strip() for k in lines[0][1]] if lines else []
    _check_keys(keys, where)
    if len(lines) < 2:
        raise InputError("the file has a header but no rows: give one row of numbers per variant",
                         where=where)
    columns: list[list[float]] = [[] for _ in keys]
    for number, line in lines[1:]:
        if len(line) != len(keys):
            raise InputError(f"line {number} has {len(line)} values for {len(keys)} columns", where=where)
        for j, k in enumerate(keys):
            columns[j].append(_number(line[j].strip(), k, where, f"line {number}"))
    return keys, columns


def _read_parquet(path: Path, where: str) -> tuple[list[str], list[list[float]]]:
    try:
        import pyarrow.parquet as pq
    except ImportError:
        raise InputError(f"reading Parquet needs pyarrow: {install_hint('dask')}, or give a .csv file",
                         where=where) from None
    try:
        table = pq.read_table(path)
    except Exception as exc:  # pyarrow's errors (ArrowInvalid, OSError) for a file that is not Parquet
        raise InputError(f"not a readable Parquet file ({' '.join(str(exc).split())})", where=where) from None
    keys = [str(k) for k in table.column_names]
    _check_keys(keys, where)
    if table.num_rows == 0:
        raise InputError("the file has columns but no rows: give one row per variant", where=where)
    columns = []
    for k in keys:
        values = table.column(k).to_pylist()
        column = []
        for i, v in enumerate(values):
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise InputError(f"row {i + 1}, column '{k}': {v!r} is not a number", where=where)
            column.append(_number(v, k, where, f"row {i + 1}"))
        columns.append(column)
    return keys, columns


def toml_value(value) -> str:
    """A value as TOML text that reads back exactly (floats by repr)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        v = float(value)
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        text = repr(v)
        return text if any(c in text for c in ".eE") else text + ".0"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {toml_value(v)}" for k, v in value.items()) + "}"
    raise InputError(f"cannot write {value!r} as a scene value")


def overrides_of(point: dict[str, Any]) -> list[str]:
    return [f"{k}={toml_value(v)}" for k, v in point.items()]


def run_id(point: dict[str, Any]) -> str:
    """A stable id of one run: a hash of its overrides (16 hex digits)."""
    text = "\n".join(overrides_of(point))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


# --- summaries -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Summary:
    """A user-named scalar: ``reduction:NAME=FORMULA`` (reduction ``final`` when left out)."""

    name: str
    formula: str
    reduction: str = "final"

    @property
    def text(self) -> str:
        return f"{self.reduction}:{self.name}={self.formula}"


def parse_summary(text: str) -> Summary:
    """``[REDUCTION:]NAME=FORMULA``; REDUCTION one of final, max, min, max_abs, mean."""
    where = f"--summary {text!r}"
    if not isinstance(text, str) or "=" not in text:
        raise InputError("expected NAME=FORMULA or REDUCTION:NAME=FORMULA, "
                         "e.g. max_abs:theta=atan2(x_bob, -y_bob)",
                         where=where)
    head, formula = text.split("=", 1)
    reduction = "final"
    if ":" in head:
        reduction, head = (p.strip() for p in head.split(":", 1))
        if reduction not in REDUCTIONS:
            raise InputError(f"unknown reduction '{reduction}' (known: {', '.join(REDUCTIONS)})", where=where)
    name = head.strip()
    if not name.isidentifier():
        raise InputError(f"the summary name {name!r} must be a plain identifier", where=where)
    if not formula.strip():
        raise InputError("the formula is empty", where=where)
    return Summary(name, formula.strip(), reduction)



def load_raw(scene_text: str, file: str) -> dict:
    """The scene's TOML as a dict; a SceneError names the file when it is not TOML."""
    try:
        raw = tomlparse.loads(scene_text)
    except tomlparse.TOMLDecodeError as exc:
        raise SceneError(f"not valid TOML: {exc}", file=file) from None
    except RecursionError:
        raise SceneError(f"not valid TOML: {NESTED_TOO_DEEPLY}", file=file) from None
    refuse_deep_nesting(raw, file)
    return raw
