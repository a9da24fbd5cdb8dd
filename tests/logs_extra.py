"""The flight-log tests need the optional extra 'logs': skipped without it on a developer's
machine, a failure in CI (CI=true), where .ci/run installs it."""

import os

import pytest


def need(*modules: str) -> None:
    for m in modules:
        try:
            __import__(m)
        except ImportError:
            if os.environ.get("CI") == "true":
                pytest.fail(f"{m} (the 'logs' extra) is required in CI")
            pytest.skip(f"{m} is not installed (pip install '.[logs]')")
