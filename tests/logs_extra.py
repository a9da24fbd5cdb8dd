"""The flight-log tests need the optional extra 'logs' (the fleet tests also 'fleet'): skipped
without it on a developer's machine, a failure in CI (CI=true), where .ci/run installs it."""

import os

import pytest


def need(*modules: str, extra: str = "logs") -> None:
    for m in modules:
        try:
            __import__(m)
        except ImportError:
            if os.environ.get("CI") == "true":
                pytest.fail(f"{m} (the '{extra}' extra) is required in CI")
            pytest.skip(f"{m} is not installed (pip install '.[{extra}]')")
