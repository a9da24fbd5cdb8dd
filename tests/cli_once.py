"""One ``magcal diagnose`` run, its result printed both ways: what ``--json`` prints and what the
terminal shows. The command runs once in-process; its own printer is called twice on the one
result (once as with ``--json``, once as without), so a test that checks the JSON and the text
of the same recording pays for one diagnosis, not two."""

from __future__ import annotations

import argparse
import contextlib
import io
import json

import pytest


def diagnose_both_ways(*argv) -> tuple[dict, str]:
    """``magcal diagnose ARGV`` (without ``--json``): (its JSON document, its text). Its exit
    status must be 0."""
    from magcal.cli import diagnose as command
    from magcal.cli import main

    printer = command._print
    printed = {}

    def both(args, *rest, **kw):
        for as_json in (True, False):
            out = io.StringIO()
            with contextlib.redirect_stdout(out):
                printer(argparse.Namespace(**{**vars(args), "json": as_json}), *rest, **kw)
            printed[as_json] = out.getvalue()

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(command, "_print", both)
        code = main(["diagnose", *map(str, argv)])
    assert code == 0 and set(printed) == {True, False}, f"magcal diagnose exited {code}"
    return json.loads(printed[True]), printed[False]
