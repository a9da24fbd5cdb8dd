"""The documents the code relies on are in the repository and say what the code does: every
``docs/…`` a file cites exists, no code points outside the repository, the wire protocol's
examples and check values are the ones the code computes, and every doctest in magcal runs."""

from __future__ import annotations

import doctest
import importlib
import os
import re

import pytest

from magcal.wire.protocol import classify_line, crc8, crc16_ccitt, parse_command

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SOURCES = ("magcal", "tests", "bench", "firmware", "config")
TEXT = (".py", ".md", ".c", ".h", ".ino", ".yaml", ".service")


def _files():
    for top in SOURCES:
        for dirpath, dirnames, files in os.walk(os.path.join(ROOT, top)):
            dirnames[:] = [d for d in dirnames if d not in ("build", "__pycache__")]
            for f in files:
                path = os.path.join(dirpath, f)
                # magcal/share's links name the top level's one copy, read where it lives
                if f.endswith(TEXT) and not os.path.islink(path):
                    yield path


def _read(path: str) -> str:
    with open(path, encoding="utf-8") as fh:
        return fh.read()


def test_every_document_the_code_cites_is_in_the_repository():
    cited = {}
    for path in _files():
        for name in re.findall(r"\bdocs/([\w-]+\.md)", _read(path)):
            cited.setdefault(name, path)
    assert {"physics.md", "hardware.md", "protocol.md"} <= set(cited)
    missing = {n: p for n, p in cited.items() if not os.path.exists(os.path.join(ROOT, "docs", n))}
    assert not missing, missing


def test_a_bare_document_name_is_always_given_with_its_folder():
    """``physics.md`` alone names no file a reader can find; ``docs/physics.md`` does."""
    bare = []
    for path in _files():
        if path.startswith(os.path.join(ROOT, "magcal")) or path.endswith((".c", ".h", ".ino")):
            for line in _read(path).splitlines():
                if re.search(r"(?<![/\w])(physics|hardware|protocol|PROTOCOL)\.md", line):
                    bare.append(f"{os.path.relpath(path, ROOT)}: {line.strip()}")
    assert not bare, "\n".join(bare)


def test_no_code_points_outside_the_repository():
    outside = [os.path.relpath(p, ROOT) for p in _files()
               if p.startswith(os.path.join(ROOT, "magcal")) and "../shared" in _read(p)]
    assert not outside, outside


def _protocol_doc() -> str:
    return _read(os.path.join(ROOT, "docs", "protocol.md"))


def test_the_protocol_examples_are_lines_the_code_accepts():
    doc = _protocol_doc()
    example = doc[doc.index("## Example"):]
    lines = re.findall(r"^(\$[^\n]*\*[0-9A-F]{2})$", example, flags=re.M)
    assert len(lines) == 4
    device = [classify_line(ln.encode()) for ln in lines if not ln.startswith("$G")]
    assert [type(m).__name__ for m in device] == ["Hello", "RawSample", "Ack"]
    assert parse_command(b"$G,7*47\n") == ("G", 7, ())


def test_the_protocol_check_values_are_the_codes():
    doc = _protocol_doc()
    assert "CRC-8 of `123456789` is `F4`" in doc and crc8(b"123456789") == 0xF4
    assert "check value of `123456789` is `29B1`" in doc and crc16_ccitt(b"123456789") == 0x29B1


def _modules_with_doctests():
    for dirpath, dirnames, files in os.walk(os.path.join(ROOT, "magcal")):
        dirnames[:] = [d for d in dirnames if d != "__pycache__"]
        for f in sorted(files):
            path = os.path.join(dirpath, f)
            if f.endswith(".py") and ">>>" in _read(path):
                rel = os.path.relpath(path, ROOT)[:-3].replace(os.sep, ".")
                yield rel[: -len(".__init__")] if rel.endswith(".__init__") else rel


@pytest.mark.parametrize("name", list(_modules_with_doctests()))
def test_the_doctests_run_and_pass(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0 and result.failed == 0, result


def test_the_doctests_are_all_found():
    """Eleven examples in three modules when this test was written; none may go unrun."""
    attempted = sum(doctest.testmod(importlib.import_module(n)).attempted for n in _modules_with_doctests())
    assert attempted >= 11
