"""A JSON document from a file or a stream, or an ``InputError`` that names it and the problem:
missing, unreadable, a directory, too large, not UTF-8 text, not JSON (with the line), or nested
deeper than any magcal document (which Python's parser would otherwise answer with a
``RecursionError``).
"""

from __future__ import annotations

import json
import os

from ..core.errors import InputError

MAX_BYTES = 64 << 20  # the largest fit result (a 3 M-sample fit with its outlier list) is far below


def parse_json(data: bytes | str, name: str):
    if isinstance(data, bytes):
        try:
            data = data.decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            raise InputError(f"{name}: not UTF-8 text (byte {exc.start}): not a JSON document") from None
    try:
        return json.loads(data)
    except json.JSONDecodeError as exc:
        raise InputError(f"{name} line {exc.lineno}: not JSON ({exc.msg})") from None
    except RecursionError:
        raise InputError(f"{name}: JSON nested too deeply to be a magcal document") from None


def read_json(path, max_bytes: int = MAX_BYTES):
    """The document in the file ``path`` (see the module docstring for the errors)."""
    name = os.fspath(path)
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size > max_bytes:
                raise InputError(f"{name}: {size} bytes is too large for a JSON result (at most {max_bytes})")
            data = fh.read(max_bytes + 1)
    except OSError as exc:
        raise InputError(f"{name}: cannot read: {exc.strerror or exc}") from None
    if len(data) > max_bytes:  # a stream or a file still growing
        raise InputError(f"{name}: too large for a JSON result (more than {max_bytes} bytes)")
    return parse_json(data, name)
