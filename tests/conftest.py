import os
import sys

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")  # as magcal does, before any test module imports numpy

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

import itertools

import pytest

_STATE = itertools.count()


@pytest.fixture(autouse=True)
def _own_state_directory(tmp_path_factory, monkeypatch):
    """Each test keeps what a user's state directory would hold (emu:// EEPROMs) to itself: a
    folder of its own, named here and made by magcal only when something is kept in it, as a
    user's is (mktemp per test scanned the ever fuller base folder: ~0.7 ms CPU a test)."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path_factory.getbasetemp() / f"xdg-state-{next(_STATE)}"))


def pytest_collection_modifyitems(config, items):
    """The tests marked slow run first (stable order otherwise): pytest-xdist hands out work in
    collection order, so a long test collected last (the wheel install) ran alone at the end
    while the other worker sat idle; started first, the short ones fill in around it."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
