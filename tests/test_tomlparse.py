"""constrained.tomlparse reads every TOML text exactly as tomli does (the same values, types, key
order and errors), whether rtoml reads it first or not: on the bundled scenes, on texts where
rtoml alone would differ, and on generated documents; and it works without rtoml."""

from __future__ import annotations

import importlib
import math
import random
import re
import sys
from pathlib import Path

import pytest
import tomli

from constrained import tomlparse
from constrained.cli.main import main

ROOT = Path(__file__).resolve().parents[1]


def _same(a, b) -> bool:
    """Equal values of the same types, dicts with keys in the same order, floats of the same sign."""
    if type(a) is not type(b):
        return False
    if isinstance(a, dict):
        return list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(map(_same, a, b))
    if isinstance(a, float):
        return (math.isnan(a) and math.isnan(b)) or (a == b and math.copysign(1, a) == math.copysign(1, b))
    return a == b and repr(a) == repr(b)


def _outcome(loads, text: str):
    try:
        return "value", loads(text)
    except RecursionError:
        return "RecursionError", None
    except Exception as exc:  # noqa: BLE001 - tomli's errors, or a ValueError tomli lets through
        return type(exc).__name__, str(exc)


def _assert_read_as_tomli(text: str) -> None:
    expected, got = _outcome(tomli.loads, text), _outcome(tomlparse.loads, text)
    if expected[0] == "ValueError":  # (Python's bare refusal of a long integer, given its place here)
        assert got[0] == "NumberTooLong" and "too long to read" in got[1], (text[:200], got)
        return
    assert expected[0] == got[0], (text[:200], expected, got)
    if expected[0] == "value":
        assert _same(expected[1], got[1]), (text[:200], expected[1], got[1])
    else:
        assert expected[1] == got[1], text[:200]


def _bundled_texts() -> list[tuple[str, str]]:
    """Every scene file of the repository and every TOML block of its documentation."""
    files = [ROOT / "pyproject.toml", *(p for folder in ("scenarios", "benchmarks", "constrained", "tests")
                                        for p in sorted((ROOT / folder).glob("**/*.toml")))]
    texts = [(str(p.relative_to(ROOT)), p.read_text(encoding="utf-8")) for p in files]
    for doc in sorted([*ROOT.glob("docs/**/*.md"), ROOT / "README.md"]):
        blocks = re.findall(r"```toml\n(.*?)```", doc.read_text(encoding="utf-8"), re.S)
        texts += [(f"{doc.name} block {i}", block) for i, block in enumerate(blocks)]
    return texts


def test_every_bundled_scene_and_docs_block_reads_as_tomli_reads_it():
    texts = _bundled_texts()
    assert len(texts) > 40
    for _name, text in texts:
        _assert_read_as_tomli(text)


def test_rtoml_reads_the_bundled_scenes_and_gives_tomlis_values():
    """Where the text's checks let rtoml read, its own result is tomli's (most scenes go there)."""
    rtoml = pytest.importorskip("rtoml")
    read = 0
    for name, text in _bundled_texts():
        if tomlparse.rtoml_reads_as_tomli(text):
            try:
                value = rtoml.loads(text)
            except rtoml.TomlParsingError:
                continue
            assert _same(tomli.loads(text), value), name
            read += 1
    assert read > 30


#: Texts on which rtoml alone reads differently from tomli (accepts what tomli refuses, or gives
#: other values or key order): the text's checks send each to tomli.
RTOML_DIFFERS = {
    "CRLF in a multi-line string": 'a = 1\r\nb = """x\r\ny"""\r\n',
    "byte order mark": "\ufeffa = 1\n",
    "date-time with an offset": "a = 1979-05-27T07:32:00-07:00\n",
    "date-time in UTC": "a = 1979-05-27T07:32:00Z\n",
    "line break before '=' in an inline table": "a = {b\n= 1}\n",
    "line break after '=' in an inline table": "a = {b =\n1}\n",
    "a '}' in a string hiding a line break": 'a = {c = "}", b\n= 1}\n',
    "[x] after [x.y]": "[x.y]\nz = 3\n[t]\n[x]\nw = 4\n",
    "[x] after [[x.y]]": "[[x.y]]\nz = 3\n[t]\n[x]\nw = 4\n",
    "float beyond the double range": "a = 1e309\n",
    "arrays nested 100 deep": "a = " + "[" * 100 + "]" * 100 + "\n",
    "tables nested 100 deep": "[" + ".".join(["a"] * 100) + "]\n",
}

#: Texts both read alike, or refuse (each with its own words: tomli's must come out).
EDGE_CASES = {
    "nan and inf": "a = nan\nb = -nan\nc = +inf\nd = -inf\ne = -0.0\n",
    "floats that round": "a = 0.1000000000000000055511151231257827\nb = 2.4703282292062328e-324\n"
                         "c = 1e-400\n",
    "2**70": "a = 1180591620717411303424\nb = -1180591620717411303424\nc = 0xFFFFFFFFFFFFFFFFFF\n",
    "int64 edges": "a = 9223372036854775807\nb = -9223372036854775808\nc = 9223372036854775808\n",
    "an integer of 5000 digits": "a = " + "9" * 5000 + "\n",
    "escapes": 'a = "\\u00e9\\U0001F600\\t\\"\\\\"\nb = \'C:\\\\x\'\nc = "\\e\\x41"\n',
    "a surrogate escape": 'a = "\\uD800"\n',
    "local date": "a = 1979-05-27\n",
    "local time": "a = 07:32:00\n",
    "duplicate key": "a = 1\na = 2\n",
    "duplicate table": "[a]\nx = 1\n[a]\ny = 2\n",
    "table over an array of tables": "[[a]]\nx = 1\n[a]\ny = 2\n",
    "dotted keys": "a.b.c = 1\na.b.d = 2\n[x.y]\nz = 3\n[x.y.w]\n",
    "dotted key redefined": "a.b = 1\n[a]\nc = 2\n",
    "inline table extended": "a = {b = 1}\n[a.c]\nd = 2\n",
    "inline table over lines after commas": "a = {b = 1,\n  c = [1,\n 2]}\n",
    "bare carriage return": "a = 1\rb = 2\n",
    "arrays nested 10,000 deep": "a = " + "[" * 10_000 + "]" * 10_000 + "\n",
    "tables nested 100,000 deep": "[" + ".".join(["a"] * 100_000) + "]\n",
    "a key of 100,000 parts": ".".join(["a"] * 100_000) + " = 1\n",
    "invalid value": "a = \n",
    "unclosed table": "[particles\nname = 'x'\n",
    "control character": 'a = "x\x01"\n',
    "leading zero": "a = 01\n",
    "empty": "",
}


@pytest.mark.parametrize("text", [*RTOML_DIFFERS.values(), *EDGE_CASES.values()],
                         ids=[*RTOML_DIFFERS, *EDGE_CASES])
def test_edge_cases_read_as_tomli_reads_them(text):
    _assert_read_as_tomli(text)


@pytest.mark.parametrize("text", RTOML_DIFFERS.values(), ids=RTOML_DIFFERS)
def test_the_texts_rtoml_reads_differently_do_differ(text):
    """(Each case of RTOML_DIFFERS is one: the test above would miss a check that lets it through.)"""
    rtoml = pytest.importorskip("rtoml")
    assert not _same(_outcome(tomli.loads, text), _outcome(rtoml.loads, text))


def _generated_document(rng: random.Random) -> str:
    """A short TOML text of headers, dotted keys, inline tables and arrays over few names, often
    invalid (tables declared twice, in any order, line breaks anywhere)."""
    names = ["a", "b", "c", '"a"', "'b'", " b", "1", "_x"]

    def key():
        return ".".join(rng.choice(names) for _ in range(rng.choice([1, 1, 2, 3])))

    def value(depth=0):
        r = rng.random()
        if r < .25:
            return rng.choice(["1", "-0.5", "1e3", "nan", "-inf", "0x10", "1_000", "1e309",
                               "99999999999999999999", '"s"', "'l'", '"""m\nl"""', '"\\u00e9"', "true",
                               "1979-05-27", "07:32:00"])
        if r < .45 and depth < 3:
            sep = rng.choice([", ", ",\n", ",\n# c\n"])
            items = sep.join(value(depth + 1) for _ in range(rng.randint(0, 3)))
            return "[" + items + rng.choice(["", ",", "\n"]) + "]"
        if r < .65 and depth < 3:
            sep, equals = rng.choice([", ", ",\n", "\n, "]), rng.choice([" = ", "\n= ", " =\n"])
            pairs = [key() + equals + value(depth + 1) for _ in range(rng.randint(0, 3))]
            return "{" + sep.join(pairs) + rng.choice(["", ","]) + "}"
        return rng.choice(["2", '"x"', "2.5"])

    lines = []
    for _ in range(rng.randint(1, 10)):
        r = rng.random()
        lines.append(f"[{key()}]" if r < .25 else f"[[{key()}]]" if r < .4 else "# c" if r < .45
                     else f"{key()} = {value()}")
    return "\n".join(lines) + rng.choice(["", "\n", "\r\n"])


def test_generated_documents_read_as_tomli_reads_them():
    rng = random.Random(20240917)
    for _ in range(4000):
        _assert_read_as_tomli(_generated_document(rng))


def _scene_like_document(rng: random.Random) -> str:
    """A scene-like text: runs of [[particles]]/[[constraints]]/[[effects]] with keys, among
    tables, sub-tables ([[effects.x]], [scene.sub]), static arrays of the same names, tables
    declared twice, header-like lines inside strings and arrays; valid or not."""
    arrays, tables = ["particles", "constraints", "effects"], ["scene", "simulate", "outputs"]
    lines = []
    for _ in range(rng.randint(2, 14)):
        r = rng.random()
        if r < .55:
            lines += [f"[[{rng.choice(arrays)}]]", "name = " + rng.choice(["1", "2.5", '"a"'])]
        elif r < .65:
            lines.append(f"[{rng.choice(tables)}]" + rng.choice(["", "", ".sub"]))
            lines.append(f"k{rng.randint(0, 2)} = {rng.randint(0, 9)}")
        elif r < .72:
            lines += [f"[[{rng.choice(arrays)}.more]]", "y = 1"]
        elif r < .78:
            lines += [f"[{rng.choice(arrays)}.sub]", "z = 2"]
        elif r < .84:
            lines.append(f'text = """\n[[{rng.choice(arrays)}]]\n"""')
        elif r < .9:
            lines.append(f"list = [\n[[{rng.randint(0, 3)}]],\n[[{rng.choice(arrays)}]]\n]")
        else:
            lines.append(f"{rng.choice(arrays)} = [{{x = 1}}]")
    return "\n".join(lines) + "\n"


PIECES_DIFFER = [  # where pieces cut before [[name]] lines must not be merged: read whole instead
    'a = 1\n[[p]]\nx = 1\n[[p]]\nx = 2\n[s]\nt = 3\n[[p]]\nx = 4\n[s.u]\nv = 5\n',  # [s], then [s.u]
    'p = [{x = 1}]\n[[q]]\ny = 1\n[[p]]\nx = 2\n',  # a static array, then [[p]]: an error
    's = """\n[[p]]\nx = 1\n"""\n[[p]]\nx = 2\n[[p]]\nx = 3\n',  # [[p]] inside a string
    'v = [\n1,\n2]\n[[p]]\nx = 1\n[t]\ny = 1\n[[p]]\nx = 2\n[t]\ny = 2\n',  # [t] twice: an error
    '[[p]]\nx = 1\n[[p.q]]\ny = 1\n[[p]]\nx = 2\n[[p.q]]\ny = 2\n[[r]]\nz = 1\n',  # merged
    '[[p]]\nx = 1\n[[p.q]]\ny = 1\n[[r]]\nz = 1\n[[p.q]]\ny = 3\n',  # [[p.q]] of the p before [[r]]
    '[[p]]\nx = 1\n[[q]]\nx = 2\n[[p]]\nx = 3\n[p.s]\nz = 1\n[[q]]\n[[p]]\nx = 4\n',
]


@pytest.mark.skipif(tomlparse._fast is None, reason="rtoml is not installed")
def test_a_large_scene_read_in_pieces_reads_as_tomli_reads_it(monkeypatch):
    """Pieces cut before [[name]] lines (every few characters here: PIECE = 8) merge into tomli's
    dict, or are not used: tables and arrays split over pieces, cuts inside strings and
    arrays, tables declared twice; and on the generated documents."""
    monkeypatch.setattr(tomlparse, "PIECE", 8)
    for text in PIECES_DIFFER:
        _assert_read_as_tomli(text)
    assert tomlparse._in_pieces(PIECES_DIFFER[0]) is None  # [s] then [s.u]: not merged
    assert tomlparse._in_pieces(PIECES_DIFFER[2]) is None  # cut inside the string: refused
    merged = tomlparse._in_pieces(PIECES_DIFFER[4])  # arrays of tables over pieces: merged
    assert merged is not None and _same(merged, tomli.loads(PIECES_DIFFER[4]))
    assert tomlparse._in_pieces(PIECES_DIFFER[5]) is None  # p: a list, then a table in its piece
    rng = random.Random(20261128)
    for _ in range(1500):
        _assert_read_as_tomli(_generated_document(rng))
    merged = 0
    for _ in range(1500):
        text = _scene_like_document(rng)
        _assert_read_as_tomli(text)
        merged += tomlparse.rtoml_reads_as_tomli(text) and tomlparse._in_pieces(text) is not None
    assert merged > 150  # (many are read in pieces, the rest whole: all as tomli reads them)
    scene = (ROOT / "scenarios" / "hanging_chain.toml").read_text(encoding="utf-8")
    assert _same(tomlparse._in_pieces(scene), tomli.loads(scene))


@pytest.mark.skipif(tomlparse._fast is None, reason="rtoml is not installed")
def test_pieces_walked_as_read_answer_as_the_whole_document(monkeypatch):
    """loads_walked's answers, one per piece (or one for the document read whole), say what
    the load's nesting and number walk says of the merged document: a huge number or a deep
    nesting in a later piece, pieces refused and read whole, tomli's errors first; and on the
    generated scene-like documents."""
    from constrained.scene import load
    monkeypatch.setattr(tomlparse, "PIECE", 8)

    def answer(text):
        raw, answers = tomlparse.loads_walked(text, load.nesting_and_numbers)
        assert _same(raw, tomli.loads(text))
        try:
            return load._refused_or_moderate(answers, "f"), len(answers)
        except load.SceneError as exc:
            return str(exc), len(answers)

    def whole(text):
        try:
            return load.refuse_deep_nesting(tomli.loads(text), "f")
        except load.SceneError as exc:
            return str(exc)

    deep = "[" * 70 + "1" + "]" * 70
    texts = [*(t for t in PIECES_DIFFER if t not in (PIECES_DIFFER[1], PIECES_DIFFER[3])),
             "[[p]]\nx = 1\n[[p]]\nx = 2\n[[p]]\nx = 1e300\n[[p]]\nx = 3\n",
             "[[p]]\nx = 1\n[[p]]\nx = 2\n[[p]]\nx = nan\n", "[[p]]\nx = -1e101\n[[p]]\nx = 2\n",
             f"[[p]]\nx = 1\n[[p]]\nx = 2\n[[p]]\nx = {deep}\n[[p]]\nx = 1e300\n",
             "[[p]]\nx = 1\n[[p]]\nx = [[2.5, 3], {y = 4}]\n"]
    counts = set()
    for text in texts:
        said, n = answer(text)
        assert said == whole(text), text
        counts.add(n)
    assert {1} < counts  # (some read in pieces, some whole)
    assert answer(texts[-3])[0] is False and "nested too deeply" in answer(texts[-2])[0]
    with pytest.raises(tomlparse.TOMLDecodeError):
        tomlparse.loads_walked(f"[[p]]\nx = {deep}\n[[p]]\nx = \n", load.nesting_and_numbers)
    rng = random.Random(20261129)
    for _ in range(300):
        text = _scene_like_document(rng)
        try:
            tomli.loads(text)
        except tomli.TOMLDecodeError:
            with pytest.raises(tomlparse.TOMLDecodeError):
                tomlparse.loads_walked(text, load.nesting_and_numbers)
            continue
        assert answer(text)[0] == whole(text)


def test_without_rtoml_tomli_reads_everything(monkeypatch):
    """rtoml not importable: tomlparse still loads, with tomli, and gives tomli's errors."""
    try:
        monkeypatch.setitem(sys.modules, "rtoml", None)  # (import rtoml raises ImportError)
        importlib.reload(tomlparse)
        assert tomlparse._fast is None
        assert tomlparse.loads("a = [1, 2.5]\n[b]\nc = 'x'\n") == {"a": [1, 2.5], "b": {"c": "x"}}
        with pytest.raises(tomlparse.TOMLDecodeError, match=r"at line 2, column 5"):
            tomlparse.loads("a = 1\nb = \n")
        for text in RTOML_DIFFERS.values():
            _assert_read_as_tomli(text)
    finally:
        monkeypatch.undo()
        importlib.reload(tomlparse)


@pytest.mark.parametrize("text, words", [
    ("\ufeff[scene]\nname = 'x'\n", "not valid TOML: Invalid statement (at line 1, column 1)"),
    ("[scene]\nname = {a\n= 1}\n", "not valid TOML: Expected '=' after a key in a key/value pair (at line 2"),
    ("x = " + "[" * 100 + "]" * 100 + "\n", "nested too deeply (more than 64 levels)"),
    ("[" + ".".join(["a"] * 100_000) + "]\n", "not valid TOML: its arrays or tables are nested too deeply"),
])
def test_a_scene_rtoml_would_read_is_refused_with_tomlis_words(tmp_path, capsys, text, words):
    scene = tmp_path / "scene.toml"
    scene.write_text(text, encoding="utf-8")
    assert main(["check", str(scene)]) == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err, err


def test_an_integer_too_long_to_read_is_refused_where_it_stands(tmp_path, capsys):
    """Python reads integers of at most 4,300 digits; tomli let its bare ValueError through, and
    `check` printed a traceback (found by the reading helper, session 17). In a scene file the
    refusal names the line and column; in a --set override, in a value or an index, the key."""
    long = "9" * 5000
    scene = tmp_path / "scene.toml"
    scene.write_text(f"[scene]\nname = 'x'\nbig = {long}\n", encoding="utf-8")
    assert main(["check", str(scene)]) == 2
    err = capsys.readouterr().err
    assert "a number too long to read (at line 3, column 7)" in err and "Traceback" not in err, err
    bundled = str(Path(__file__).resolve().parents[1] / "scenarios" / "atwood_machine.toml")
    for override in (f"simulate.t_end={long}", f"particles[{long}].mass=1"):
        assert main(["check", bundled, "--set", override]) == 2
        err = capsys.readouterr().err
        assert "a number too long to read" in err and "Traceback" not in err and long not in err, err
