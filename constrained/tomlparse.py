"""TOML parsing for scenes, overrides and sweep designs, with tomli's grammar, results and errors.

tomli's compiled parser (a dependency) is the reference; the standard library's ``tomllib``
(tomli, vendored) stands in where it is missing. rtoml, a Rust parser, reads a large scene 2-2.5
times faster (a 10,000-bead cloth: 0.15 s against 0.36 s): where it is installed it reads first,
and tomli reads again whatever rtoml refuses, so every error (its wording, line and column) and
every value rtoml would give otherwise (an overflowing float tomli reads as inf, nesting deeper
than rtoml's limit) is tomli's. Texts where the two accept the same TOML differently go to tomli
directly: carriage returns (tomli reads CRLF in a multi-line string as one newline, rtoml keeps
it), a byte order mark (rtoml skips it, tomli refuses it) and dates and times (rtoml's time
zones are its own class). A large scene is read by rtoml in pieces cut before its ``[[name]]``
headers, merged where they read as the whole does (``_in_pieces``: rtoml's copy of the whole
document, 30 times the text, is what it costs)."""

from __future__ import annotations

import re

try:
    import tomli as _toml
except ImportError:  # pragma: no cover - tomli is a dependency
    import tomllib as _toml

try:
    import rtoml as _fast
except ImportError:  # rtoml is optional: tomli reads everything
    _fast = None

TOMLDecodeError = _toml.TOMLDecodeError

#: What any TOML date (1979-05-27) or time (07:32) contains: such a text goes to tomli.
_DATE = re.compile(r"-[0-9][0-9]-")
_TIME = re.compile(r":[0-9]")
#: The key path of a table header, [a.b] or [[a.b]] (at the start of a line).
_HEADER = re.compile(r"\n[ \t]*\[\[?([^\]\n]*)")
#: Quoted strings on one line, and the comment ending it.
_STRINGS = re.compile(r""""(?:[^"\\\n]|\\.)*"|'[^'\n]*'""")


def loads(text: str) -> dict:
    """The TOML document ``text`` as nested dicts and lists, exactly as tomli reads it; its
    errors are tomli's ``TOMLDecodeError`` (and ``RecursionError`` for nesting deeper than
    tomli's recursion takes)."""
    return loads_walked(text, None)[0]


def loads_walked(text: str, walk) -> tuple[dict, list]:
    """``(loads(text), answers)``: ``answers`` holds ``walk(table)`` of each table read, in
    order — the pieces of a large scene (``_in_pieces``), each walked as soon as it is read
    and before any merge (its objects still in the processor's cache: the cloth's nesting
    walk 0.046 -> 0.028 s), else the whole document alone. Every value of the document lies
    in exactly one of them. ``walk`` None: no answers."""
    answers: list = []
    if _fast is not None and rtoml_reads_as_tomli(text):
        read = None
        try:
            pieces = _in_pieces(text, walk, answers) if len(text) > 2 * PIECE else None
            if pieces is not None:
                return pieces, answers
            answers.clear()
            read = _fast.loads(text)
        except Exception:  # noqa: BLE001 - any refusal (or a value Python refuses): tomli's word
            read = None
        if read is not None:
            return read, [walk(read)] if walk is not None else []
    answers.clear()
    try:
        read = _toml.loads(text)
    except TOMLDecodeError:
        raise
    except ValueError as exc:  # (Python refuses to read an integer of more than 4,300 digits)
        raise NumberTooLong(text, exc) from None
    return read, [walk(read)] if walk is not None else []


#: A large scene is read by rtoml in pieces of about this many characters (``_in_pieces``): rtoml's
#: transient copy of a piece (30 times its text) then stays in the processor's cache (a 4 MB
#: cloth read in pieces of 64 kB: 0.105-0.110 s of CPU, of 256 kB: 0.125-0.135 s).
PIECE = 64 * 1024
#: An array-of-tables header alone on its line, ``[[effects]]``, of the key pattern put in.
_HEADER_OF = r"^\[\[[ \t]*{}[ \t]*\]\][ \t]*$"
#: Such a header of one bare key.
_ARRAY_HEADER = re.compile(_HEADER_OF.format(r"([A-Za-z0-9_-]+)"), re.M)


def _declares(piece: str, key: str) -> bool:
    """Whether a ``[[key]]`` header stands in ``piece`` (a bare key: as ``_ARRAY_HEADER`` finds)."""
    return re.search(_HEADER_OF.format(re.escape(key)), piece, re.M) is not None


def _in_pieces(text: str, walk=None, answers: list | None = None) -> dict | None:
    """rtoml's reading of ``text`` cut before ``[[name]]`` headers into pieces of about
    ``PIECE`` characters, merged: the same dict as reading it whole, without rtoml's transient
    copy of the whole document (130 MB for a 4 MB cloth, its pages faulted in and out: 0.07 s
    of system time). None when the pieces may not read as the whole does: a piece refused (a
    cut inside a multi-line string or array leaves one unterminated) or a key in two pieces
    that is not an array of tables declared by ``[[key]]`` headers in both (a table defined
    twice, ``[a]`` then ``[a.b]``, a static array then ``[[a]]``) — then it is read whole.
    ``walk``: appends ``walk(piece's table)`` to ``answers`` as each piece is read, before merging."""
    cuts = [0]
    while (found := _ARRAY_HEADER.search(text, cuts[-1] + PIECE)) is not None:
        cuts.append(found.start())
    if len(cuts) == 1:
        return None
    cuts.append(len(text))
    out: dict = {}
    origin: dict[str, str] = {}  # each key's first piece
    declared: set[str] = set()  # keys seen declared by [[key]] headers in their first piece
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        piece = text[a:b]
        try:
            read = _fast.loads(piece)
        except Exception:  # noqa: BLE001 - a cut inside a string or an array (or a real error)
            return None
        if walk is not None:
            answers.append(walk(read))
        for key, value in read.items():
            if key not in out:
                out[key], origin[key] = value, piece
                continue
            if key not in declared:
                if not _declares(origin[key], key):
                    return None
                declared.add(key)
            if not (isinstance(out[key], list) and isinstance(value, list) and _declares(piece, key)):
                return None
            out[key] += value
    return out


class NumberTooLong(TOMLDecodeError):
    """An integer literal longer than Python reads (``sys.get_int_max_str_digits()``), named by
    its line and column (tomli let Python's bare ValueError through: a traceback on the CLI)."""

    def __init__(self, text: str, exc: ValueError):
        found = _LONG_DIGITS.search(text)
        line = text.count("\n", 0, found.start()) + 1 if found else 0
        column = found.start() - text.rfind("\n", 0, found.start()) if found else 0
        where = f" (at line {line}, column {column})" if found else ""
        ValueError.__init__(self, f"a number too long to read{where}: {str(exc).split(';')[0]}")


#: A run of digits longer than Python reads as an integer by default.
_LONG_DIGITS = re.compile(r"[0-9_]{4301,}")


def rtoml_reads_as_tomli(text: str) -> bool:
    """Whether rtoml, accepting ``text``, gives what tomli gives (scans of the text: 15 ms for a
    4 MB scene): not for carriage returns, a byte order mark, dates or times, an inline table
    over several lines (rtoml takes a line break anywhere in it, tomli only after a comma), nor
    a table [a] declared after a table inside it, [a.b] (rtoml puts a among the tables in the
    order of [a], tomli of [a.b])."""
    if "\r" in text or "\ufeff" in text or _DATE.search(text) or _TIME.search(text):
        return False
    return _inline_tables_on_one_line(text) and _tables_declared_outside_in("\n" + text)


def _inline_tables_on_one_line(text: str) -> bool:
    """Whether every line with a ``{`` closes as many as it opens (outside strings and comments;
    a line with a multi-line string's quotes counts as not)."""
    start = text.find("{")
    while start >= 0:
        begin, end = text.rfind("\n", 0, start) + 1, text.find("\n", start)
        end = len(text) if end < 0 else end
        line = text[begin:end]
        if '"""' in line or "'''" in line:
            return False
        code = _STRINGS.sub("", line).partition("#")[0]
        if code.count("{") != code.count("}"):
            return False
        start = text.find("{", end)
    return True


def _tables_declared_outside_in(text: str) -> bool:
    """Whether no table header names a table inside which an earlier header declared one
    ([a] after [a.b]); a header with quoted keys, or of more than 8 keys, counts as such."""
    inside: set[tuple[str, ...]] = set()  # the tables containing the headers so far
    for header in dict.fromkeys(_HEADER.findall(text)):  # (each at its first place)
        if '"' in header or "'" in header:
            return False
        path = tuple(part.strip() for part in header.split(".", 8))
        if len(path) > 8 or path in inside:
            return False
        inside.update(path[:k] for k in range(1, len(path)))
    return True


__all__ = ["TOMLDecodeError", "loads"]
