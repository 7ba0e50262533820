"""The compile cache survives damage: a truncated, garbage or foreign library in place of a
cached one is detected (size and checksum record), rebuilt with a one-line notice, and the
run still gives the right answer. Each step runs in its own process, as separate runs do
(a library a process has loaded must not be damaged under it)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from constrained.codegen import compiled

ROOT = Path(__file__).resolve().parents[1]

needs_cc = pytest.mark.skipif(compiled.compiler() is None, reason="no C compiler on this machine")

# Two functions named alike (so their libraries are interchangeable by name) with different
# shapes and values: f(x) = sin(x) + 2 x (3 entries), and its impostor (2 entries).
SCRIPT = """
import sys, casadi as ca, numpy as np
from constrained.codegen import compiled
which = sys.argv[1]
if which == "f":
    x = ca.SX.sym("x", 3); f = ca.Function("cachetest", [x], [ca.sin(x) + 2 * x])
    arg, want = np.array([0.1, 0.2, 0.3]), np.sin([0.1, 0.2, 0.3]) + 2 * np.array([0.1, 0.2, 0.3])
elif which == "planted":  # the same name and shapes as f, another body: what an attacker plants
    x = ca.SX.sym("x", 3); f = ca.Function("cachetest", [x], [-7 * x])
    arg, want = np.array([0.1, 0.2, 0.3]), -7 * np.array([0.1, 0.2, 0.3])
else:
    x = ca.SX.sym("x", 2); f = ca.Function("cachetest", [x], [ca.cos(x)])
    arg, want = np.array([0.1, 0.2]), np.cos([0.1, 0.2])
g = compiled.compile_function(f)
assert compiled.last_error is None, compiled.last_error
assert g is not f and g.has_free() is False
got = np.asarray(g(arg)).ravel()
print("value-ok" if np.allclose(got, want, rtol=0, atol=1e-14) else f"value-wrong {got}")
"""


def run(which: str, cache: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, CONSTRAINED_CACHE=str(cache), PYTHONPATH=str(ROOT))
    env.pop("CONSTRAINED_COMPILE", None)
    return subprocess.run([sys.executable, "-c", SCRIPT, which], env=env, capture_output=True,
                          text=True, timeout=120)


def entry(cache: Path) -> Path:
    (so,) = cache.glob("cachetest_*.so")
    return so


def damage_truncate(so: Path, cache: Path) -> None:
    data = so.read_bytes()
    so.write_bytes(data[: len(data) // 3])  # in place, as a disk-full or killed copy leaves it


def damage_garbage(so: Path, cache: Path) -> None:
    so.write_bytes(b"\x7fELF" + os.urandom(so.stat().st_size - 4))


def damage_foreign_library(so: Path, cache: Path) -> None:
    other = cache.parent / "other"
    assert run("impostor", other).returncode == 0
    shutil.copyfile(entry(other), so)  # a valid library, the wrong one


def damage_foreign_entry(so: Path, cache: Path) -> None:
    other = cache.parent / "other"
    assert run("impostor", other).returncode == 0
    shutil.copyfile(entry(other), so)  # library and its record: checksums agree, shapes do not
    shutil.copyfile(entry(other).with_suffix(".json"), so.with_suffix(".json"))


@needs_cc
@pytest.mark.parametrize("damage", [damage_truncate, damage_garbage, damage_foreign_library,
                                    damage_foreign_entry])
def test_a_damaged_cache_entry_is_rebuilt_and_the_answer_is_right(tmp_path, damage):
    cache = tmp_path / "cache"
    first = run("f", cache)
    assert first.returncode == 0 and "value-ok" in first.stdout, first.stderr
    so = entry(cache)
    record = json.loads(so.with_suffix(".json").read_text())
    assert record["size"] == so.stat().st_size  # the record is written with the library
    good = so.read_bytes()
    damage(so, cache)
    assert so.read_bytes() != good

    again = run("f", cache)
    assert again.returncode == 0, f"exit {again.returncode}: {again.stderr[-2000:]}"
    assert "value-ok" in again.stdout
    notices = [line for line in again.stderr.splitlines() if "compile cache" in line]
    assert len(notices) == 1 and "rebuilding" in notices[0] and str(so) in notices[0]
    assert json.loads(so.with_suffix(".json").read_text())["size"] == so.stat().st_size

    third = run("f", cache)  # repaired: loaded from the cache without a notice
    assert third.returncode == 0 and "value-ok" in third.stdout
    assert "compile cache" not in third.stderr
    # no temporaries (the signing key is the user's secret, kept there)
    assert not [p for p in cache.iterdir() if p.suffix not in (".so", ".json") and p.name != "signing.key"]


@needs_cc
def test_a_missing_record_means_rebuild_not_trust(tmp_path):
    cache = tmp_path / "cache"
    assert run("f", cache).returncode == 0
    so = entry(cache)
    so.with_suffix(".json").unlink()
    damage_truncate(so, cache)
    again = run("f", cache)
    assert again.returncode == 0 and "value-ok" in again.stdout, again.stderr[-2000:]
    assert "no size and checksum record" in again.stderr


@needs_cc
def test_concurrent_writers_leave_one_whole_entry(tmp_path):
    cache = tmp_path / "cache"
    env = dict(os.environ, CONSTRAINED_CACHE=str(cache), PYTHONPATH=str(ROOT))
    procs = [subprocess.Popen([sys.executable, "-c", SCRIPT, "f"], env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(3)]
    outs = [p.communicate(timeout=120) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs
    assert all("value-ok" in out for out, _ in outs)
    so = entry(cache)
    assert compiled._verify(so) is None
    assert sorted(p.suffix for p in cache.iterdir() if p.name != "signing.key") == [".json", ".so"]


def test_the_cache_folder_can_be_set_by_either_variable(monkeypatch, tmp_path):
    monkeypatch.delenv("CONSTRAINED_CACHE", raising=False)
    monkeypatch.setenv("CONSTRAINED_CACHE_DIR", str(tmp_path / "c2"))
    assert compiled.cache_dir() == tmp_path / "c2"
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "c1"))
    assert compiled.cache_dir() == tmp_path / "c1"


def test_the_key_holds_everything_that_decides_the_machine_code(monkeypatch, tmp_path):
    """Same functions, same setup: same key. A different CasADi version, compiler binary,
    flag set, CPU architecture or platform: a different key (never a foreign library)."""
    import casadi as ca

    def function():
        x = ca.SX.sym("x", 2)
        return ca.Function("keytest", [x], [ca.sin(x) * 3])

    cc = tmp_path / "cc"
    cc.write_text("#!/bin/sh\n")
    base = compiled.cache_key([function()], str(cc))
    assert compiled.cache_key([function()], str(cc)) == base  # deterministic, rebuilt graph
    assert compiled.cache_key([function()], str(cc), flags=("-O3",)) != base
    x = ca.SX.sym("x", 2)
    assert compiled.cache_key([ca.Function("keytest", [x], [ca.sin(x) * 4])], str(cc)) != base
    other = tmp_path / "cc2"
    other.write_text("#!/bin/sh\n# another compiler\n")
    assert compiled.cache_key([function()], str(other)) != base
    native = compiled.build_environment(str(cc), ("-O2", "-march=native"))
    assert "cpu" in native and "cpu" not in compiled.build_environment(str(cc))
    for module, name, value in ((compiled.platform, "machine", lambda: "riscv64"),
                                (compiled.sys, "platform", "plan9"), (ca, "__version__", "0.0.1")):
        with monkeypatch.context() as m:
            m.setattr(module, name, value)
            assert compiled.cache_key([function()], str(cc)) != base, name


@needs_cc
def test_an_entry_recorded_for_another_setup_is_rebuilt(tmp_path):
    cache = tmp_path / "cache"
    assert run("f", cache).returncode == 0
    so = entry(cache)
    record = json.loads(so.with_suffix(".json").read_text())
    assert record["machine"] and record["compiler"] and record["casadi"]
    record["machine"] = "vax"  # e.g. a cache folder shared between machines
    so.with_suffix(".json").write_text(json.dumps(record))
    again = run("f", cache)
    assert again.returncode == 0 and "value-ok" in again.stdout, again.stderr[-2000:]
    assert "built for another setup (machine 'vax'" in again.stderr


# A compiled run (dopri's chained steps) prints its end state.
RUN = """
import numpy as np, constrained as C
from constrained.codegen import compiled
sc = C.load_scene("scenarios/double_pendulum.toml")
tr = C.simulate(sc.system, 0.3, method="dopri", rtol=1e-9, atol=1e-11, compiled=True, outputs=[])
assert compiled.last_error is None, compiled.last_error
print(repr(tr.x[-1].ravel().tolist()))
"""


@needs_cc
@pytest.mark.parametrize("damage", [damage_truncate, damage_garbage])
def test_a_run_survives_a_damaged_cache_and_rebuilds_it(tmp_path, damage):
    cache = tmp_path / "cache"
    env = dict(os.environ, CONSTRAINED_CACHE=str(cache), PYTHONPATH=str(ROOT))
    env.pop("CONSTRAINED_COMPILE", None)

    def simulate():
        return subprocess.run([sys.executable, "-c", RUN], env=env, capture_output=True, text=True,
                              timeout=300, cwd=ROOT)

    first = simulate()
    assert first.returncode == 0, first.stderr[-2000:]
    (so,) = cache.glob("*.so")
    damage(so, cache)
    again = simulate()
    assert again.returncode == 0, f"exit {again.returncode}: {again.stderr[-2000:]}"
    assert again.stdout == first.stdout  # the same end state, to the last digit
    assert "rebuilding it" in again.stderr and str(so) in again.stderr
    assert compiled._verify(so) is None  # the entry is whole again


# --- issue 27, item 1: a shared or planted cache never runs another user's code --------------------
def _plant(cache: Path, tmp_path: Path, *, sign: bool) -> Path:
    """Our entry for f replaced by a library computing -7 x (same name and shapes) and a record
    that matches it: copied from another user's cache (signed with their key), or written by
    hand with the right size and checksum (no signature)."""
    assert run("f", cache).returncode == 0
    so = entry(cache)
    other = tmp_path / "other-user"
    assert run("planted", other).returncode == 0
    shutil.copyfile(entry(other), so)
    record = json.loads(entry(other).with_suffix(".json").read_text())
    if not sign:
        record.pop("hmac", None)
    record.update(size=so.stat().st_size, sha256=compiled._sha256(so))
    so.with_suffix(".json").write_text(json.dumps(record))
    return so


@needs_cc
@pytest.mark.parametrize("sign", [True, False], ids=["record-signed-by-another-key", "unsigned-record"])
def test_a_planted_library_with_a_matching_record_is_never_loaded(tmp_path, sign):
    cache = tmp_path / "cache"
    so = _plant(cache, tmp_path, sign=sign)
    assert compiled._verify(so) is None  # size and checksum agree: only the signature tells
    again = run("f", cache)
    assert again.returncode == 0 and "value-ok" in again.stdout, (again.stdout, again.stderr[-2000:])
    if sign:
        assert "signature does not match" in again.stderr and "rebuilding" in again.stderr
    third = run("f", cache)  # the rebuilt entry is ours: loaded without a word
    assert "value-ok" in third.stdout and "compile cache" not in third.stderr


@needs_cc
def test_the_cache_folder_key_and_entries_are_private(tmp_path):
    cache = tmp_path / "deep" / "cache"
    assert run("f", cache).returncode == 0
    assert cache.stat().st_mode & 0o777 == 0o700
    assert (cache / "signing.key").stat().st_mode & 0o777 == 0o600
    so = entry(cache)
    assert so.stat().st_mode & 0o077 == 0 and so.with_suffix(".json").stat().st_mode & 0o077 == 0
    assert "hmac" in json.loads(so.with_suffix(".json").read_text())


@needs_cc
@pytest.mark.parametrize("mode", [0o777, 0o775, 0o757])
def test_a_cache_folder_others_can_write_is_not_used(tmp_path, mode, monkeypatch, capsys):
    import casadi as ca

    cache = tmp_path / "shared"
    cache.mkdir()
    cache.chmod(mode)
    monkeypatch.setenv("CONSTRAINED_CACHE", str(cache))
    monkeypatch.delenv("CONSTRAINED_COMPILE", raising=False)
    x = ca.SX.sym("x", 2)
    f = ca.Function("sharedtest", [x], [ca.cos(x)])
    for _ in range(2):  # refused each time, said once
        g = compiled.compile_function(f)
        assert g is f and "is writable by" in compiled.last_error
    err = capsys.readouterr().err
    assert err.count("is not used") == 1 and str(cache) in err and "chmod 700" in err
    # who can write it, as its mode says (0o757: others, not its group)
    writers = {0o777: "group and others", 0o775: "its group", 0o757: "others"}[mode]
    assert f"is writable by {writers};" in err, err
    assert list(cache.iterdir()) == []  # nothing written into it, nothing loaded from it


@needs_cc
def test_a_cache_folder_of_another_user_is_not_used(tmp_path, monkeypatch, capsys):
    import casadi as ca

    cache = tmp_path / "theirs"
    monkeypatch.setenv("CONSTRAINED_CACHE", str(cache))
    monkeypatch.delenv("CONSTRAINED_COMPILE", raising=False)
    x = ca.SX.sym("x", 2)
    f = ca.Function("theirstest", [x], [ca.cos(x)])
    assert compiled.compile_function(f).class_name() == "External"  # our folder: compiled
    owner = os.geteuid()
    monkeypatch.setattr(compiled, "_user", lambda: owner + 1)  # the same folder seen by another user
    assert compiled.compile_function(f) is f
    assert "belongs to another user" in compiled.last_error
    err = capsys.readouterr().err
    assert "belongs to another user" in err
    assert "chmod" not in err  # another user's folder is not ours to chmod: only "a folder of your own"


@needs_cc
@pytest.mark.parametrize("which", [".so", ".json"])
def test_an_entry_others_can_write_is_rebuilt(tmp_path, which):
    cache = tmp_path / "cache"
    assert run("f", cache).returncode == 0
    target = entry(cache).with_suffix(which)
    target.chmod(0o666)
    again = run("f", cache)
    assert again.returncode == 0 and "value-ok" in again.stdout, again.stderr[-2000:]
    assert "writable by group and others" in again.stderr and "rebuilding" in again.stderr
    assert target.stat().st_mode & 0o077 == 0


def _entries(folder, sizes_and_ages):
    """Fake cache entries (library and record) of the given sizes (bytes), used ``age`` s ago."""
    import time

    now = time.time()
    paths = []
    for k, (size, age) in enumerate(sizes_and_ages):
        library, record = folder / f"f{k}_key.so", folder / f"f{k}_key.json"
        library.write_bytes(b"\0" * size)
        record.write_text("{}")
        os.utime(library, (now - age, now - age))
        paths.append(library)
    return paths


def test_the_cache_is_kept_within_its_limit_least_recently_used_first(tmp_path, monkeypatch):
    """Over the limit, the oldest entries go (library and record together) until 80 % of it is
    left; the entry just written and the signing key stay, whatever their age."""
    from constrained.codegen import eviction

    folder = tmp_path / "cache"
    folder.mkdir()
    (folder / "signing.key").write_bytes(b"k" * 32)
    old, older, newest, kept = _entries(folder, [(300_000, 100), (300_000, 200), (300_000, 1),
                                                 (300_000, 500)])
    monkeypatch.setenv("CONSTRAINED_CACHE_LIMIT_MB", "1")
    # 1.2 MB: the oldest but the one kept goes (0.9 MB), then the next (0.6 MB, below 80 %)
    assert eviction.evict(folder, keep=kept) == [older.name, old.name]
    assert not older.exists() and not older.with_suffix(".json").exists()
    assert not old.exists() and newest.exists() and kept.exists() and (folder / "signing.key").exists()


def test_under_its_limit_or_without_one_nothing_is_removed(tmp_path, monkeypatch):
    from constrained.codegen import eviction

    folder = tmp_path / "cache"
    folder.mkdir()
    paths = _entries(folder, [(400_000, 10), (400_000, 20)])
    monkeypatch.setenv("CONSTRAINED_CACHE_LIMIT_MB", "1")
    assert eviction.evict(folder, keep=paths[0]) == []
    for value in ("0", "none"):
        monkeypatch.setenv("CONSTRAINED_CACHE_LIMIT_MB", value)
        assert eviction.limit_bytes() is None and eviction.evict(folder, keep=paths[0]) == []
    assert all(p.exists() for p in paths)


@pytest.mark.parametrize("value", ["lots", "-5", "nan", "inf"])
def test_a_limit_that_is_not_a_size_is_named_and_the_default_used(value, monkeypatch, capsys):
    from constrained.codegen import eviction

    monkeypatch.setenv("CONSTRAINED_CACHE_LIMIT_MB", value)
    eviction._warned.discard(value)
    assert eviction.limit_bytes() == eviction.DEFAULT_LIMIT_MB * 1e6
    assert f"CONSTRAINED_CACHE_LIMIT_MB={value!r}" in capsys.readouterr().err


@pytest.mark.skipif(not compiled.enabled(), reason="no C compiler")
def test_a_hit_marks_its_entry_used_and_a_new_entry_evicts_the_stale(tmp_path, monkeypatch):
    """Through the cache itself: a library loaded again becomes the most recently used; with a
    limit below two libraries, writing a second removes the first (not the one just written)."""
    import time

    import casadi as ca

    from constrained.codegen import external

    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("CONSTRAINED_CACHE_LIMIT_MB", "none")

    def build(name):
        scalar = [ca.Sparsity.dense(1, 1)]
        return external.c_function(name, "  out[0] = 2 * x[0];\n  return 0;", ["x"], scalar, ["out"], scalar)
    assert float(build("evict_a")(3)) == 6
    (first,) = (tmp_path / "cache").glob("evict_a_*.so")
    os.utime(first, (time.time() - 1000, time.time() - 1000))
    assert float(build("evict_a")(4)) == 8
    assert first.stat().st_mtime > time.time() - 100  # (the hit)
    size = first.stat().st_size
    monkeypatch.setenv("CONSTRAINED_CACHE_LIMIT_MB", str(1.5 * size / 1e6))
    assert float(build("evict_b")(5)) == 10
    (second,) = (tmp_path / "cache").glob("evict_b_*.so")
    assert second.exists() and not first.exists() and not first.with_suffix(".json").exists()


@needs_cc
def test_cached_source_loads_each_function_when_first_used_and_finds_what_was_compiled(
        monkeypatch, tmp_path):
    """``cached_source`` gives ``Deferred`` Functions: each gives what the compiled one gives
    (values, shapes, name), is loaded only when used, and a name the library lacks means None."""
    import casadi as ca
    import numpy as np
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path))
    x, y = ca.SX.sym("x", 3), ca.SX.sym("y", 2)
    functions = [ca.Function("deferred_a", [x], [ca.sin(x) + 2 * x]), ca.Function("deferred_b", [y], [y * y])]
    key = b"deferred test source"
    source = compiled._generated(functions)
    eager = compiled.compile_source(source, functions, key=key)
    assert compiled.last_error is None and eager is not None
    lazy = compiled.cached_source(["deferred_a", "deferred_b"], key)
    assert all(f._function is None for f in lazy)  # nothing loaded yet
    got = np.asarray(lazy[1](np.array([3.0, -4.0]))).ravel()
    assert lazy[0]._function is None and lazy[1]._function is not None
    assert got.tolist() == np.asarray(eager[1](np.array([3.0, -4.0]))).ravel().tolist() == [9.0, 16.0]
    assert lazy[0].name() == "deferred_a" and lazy[0].sparsity_in(0) == eager[0].sparsity_in(0)
    point = np.array([0.1, 0.2, 0.3])
    assert np.asarray(lazy[0](point)).tolist() == np.asarray(eager[0](point)).tolist()
    assert compiled.cached_source(["deferred_a", "deferred_missing"], key) is None
