"""Damaged flight logs found by mutating the shipped ArduPilot excerpt (tests/data/PROVENANCE.md):
each once ended in a traceback after the work was done — a soft iron turned inside out by the
fit against an unknown constant field (the mutation cut the GPS), a held-out figure of a refit
that failed (NaN), a step sized against a floor of zero (infinity) in the JSON. Each is a named
refusal or a document with ``null`` where the number could not be determined."""

import json
import os

import numpy as np
import pytest

from magcal.cli import main

LOG = os.path.join(os.path.dirname(__file__), "data", "ardupilot_log171_excerpt.bin")


def _mutated(index: int, seed: int = 11) -> bytes:
    """The ``index``-th of a seeded run of mutations: cut, bytes overwritten, a span deleted, or
    random bytes inserted."""
    data = open(LOG, "rb").read()
    rng = np.random.default_rng(seed)
    for i in range(index + 1):
        b = bytearray(data)
        kind = rng.integers(0, 4)
        if kind == 0:
            b = b[: rng.integers(0, len(b))]
        elif kind == 1:
            for _ in range(rng.integers(1, 50)):
                b[rng.integers(0, len(b))] = rng.integers(0, 256)
        elif kind == 2:
            s = rng.integers(0, len(b))
            b[s:s + rng.integers(1, 5000)] = b""
        else:
            s = rng.integers(0, len(b))
            b[s:s] = rng.integers(0, 256, rng.integers(1, 3000), dtype=np.uint8).tobytes()
    return bytes(b)


@pytest.mark.slow
@pytest.mark.parametrize("index,command", [(0, "fit"), (29, "diagnose"), (31, "diagnose")])
def test_a_mutated_log_is_a_named_refusal_or_a_json_document(tmp_path, capsys, index, command):
    path = tmp_path / "m.bin"
    path.write_bytes(_mutated(index))
    code = main([command, str(path), "--mag", "0", "--json"])
    out, err = capsys.readouterr()
    assert code in (0, 3), err
    if code == 0:
        doc = json.loads(out)  # strict JSON: no NaN or Infinity
        assert doc["schema"] == f"magcal.{command}/1"
    else:
        assert "not_positive_definite" in err or "too_few" in err, err


@pytest.mark.slow
def test_a_timestamp_from_far_away_does_not_make_the_search_unbounded(tmp_path, capsys):
    """Bytes overwritten in a timestamp put one sample ~10⁶ s away: the locate step's grids over
    that span asked for terabytes (the command ran minutes and was killed). The damaged log is
    diagnosed, and nothing is located on a time axis that is mostly gap."""
    path = tmp_path / "m.bin"
    path.write_bytes(_mutated(73, seed=12))
    code = main(["diagnose", str(path), "--mag", "0", "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert json.loads(out)["located"]["found"] == []
