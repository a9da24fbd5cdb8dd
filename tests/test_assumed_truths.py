"""What a command reports about its input is what the input was: the count asked for, the
rate a capture was taken at, the store a write went to, the coverage of a fit, the unit a
field implies, and what a table reader assumed (issue 44, point 4)."""

from __future__ import annotations

import json

from magcal.app.load import load_series
from magcal.cli import main


def test_record_count_n_records_exactly_n_samples_in_summary_and_capture(tmp_path, capsys):
    # a source that answers a read with a thousand samples at once used to overshoot (3000 → 3072)
    cap = tmp_path / "n.cap"
    assert main(["record", "--port", "sim://?pace=0&seed=3", "-o", str(cap), "--count", "3000", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["n_samples"] == 3000
    assert len(load_series(str(cap))) == 3000


def test_replay_reports_the_rate_the_capture_was_taken_at(tmp_path, capsys):
    # the board boots saying 100 Hz; the capture was taken after R 50 (its reply is in the bytes)
    cap = tmp_path / "fifty.cap"
    assert main(["record", "--port", "sim://?pace=0&seed=4", "--rate", "50", "-o", str(cap), "--count", "60"]) == 0
    capsys.readouterr()
    main(["calibrate", "--port", f"replay://{cap}", "--no-write", "--json"])
    assert json.loads(capsys.readouterr().out)["rate_hz"] == 50
