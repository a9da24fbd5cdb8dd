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
    summary = json.loads(capsys.readouterr().out)
    assert summary["n_samples"] == 3000
    assert len(load_series(str(cap))) == 3000
    from magcal.recordings.capture import CaptureReader

    assert summary["capture"]["bytes"] == len(CaptureReader(cap).data())  # the file as it is after the cut


def test_replay_reports_the_rate_the_capture_was_taken_at(tmp_path, capsys):
    # the board boots saying 100 Hz; the capture was taken after R 50 (its reply is in the bytes)
    cap = tmp_path / "fifty.cap"
    assert main(["record", "--port", "sim://?pace=0&seed=4", "--rate", "50", "-o", str(cap), "--count", "60"]) == 0
    capsys.readouterr()
    main(["calibrate", "--port", f"replay://{cap}", "--no-write", "--json"])
    assert json.loads(capsys.readouterr().out)["rate_hz"] == 50


def test_sim_keeps_its_eeprom_across_commands_like_a_board(capsys):
    # calibrate wrote and verified; the next command on the same sim:// board finds the record
    url = "sim://?pace=0&seed=11"
    assert main(["calibrate", "--port", url, "--json"]) == 0
    written = json.loads(capsys.readouterr().out)
    assert written["verified"]
    assert main(["show", "--port", url, "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["record"]["state"] == "ok", shown
    for a, b in zip(shown["calibration"]["offset_ut"], written["calibration"]["offset_ut"]):
        assert abs(a - b) < 0.01  # as stored (the device's fixed point)


def _sphere_csv(path, radius, n=400, seed=2):
    import numpy as np

    u = np.random.default_rng(seed).normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    xyz = radius * u + np.array([3.0, -2.0, 1.0]) * radius / 50
    path.write_text("mx,my,mz\n" + "".join(f"{a:.4f},{b:.4f},{c:.4f}\n" for a, b, c in xyz))
    return str(path)


def test_fit_reports_coverage_in_text_and_json(tmp_path, capsys):
    f = _sphere_csv(tmp_path / "s.csv", 48.0)
    assert main(["fit", f, "--json"]) == 0
    cov = json.loads(capsys.readouterr().out)["fits"][0]["coverage"]
    assert 0.5 < cov <= 1.0
    assert main(["fit", f]) == 0
    assert f"coverage    {100 * cov:.0f} % of directions" in capsys.readouterr().out


def test_a_field_in_raw_counts_names_the_unit_that_makes_it_an_earth_field(tmp_path, capsys):
    import re

    f = _sphere_csv(tmp_path / "counts.csv", 1730.0)
    assert main(["fit", f, "--json"]) == 0
    warning = " ".join(json.loads(capsys.readouterr().out)["fits"][0]["warnings"])
    scales = [float(v) for v in re.findall(r"--unit (\d[\d.e-]*)", warning)]
    assert scales and all(15 <= 1730 * s <= 100 for s in scales), warning


def test_export_keeps_what_reading_assumed_so_a_reread_says_so_again(tmp_path):
    # no time column and no unit: the export must not turn the sample index into seconds, nor
    # the guessed µT into a stated one
    src = tmp_path / "bare.csv"
    src.write_text("mag_x,mag_y,mag_z\n" + "".join(f"{10 + i},{-20 - i},{30 + 2 * i}\n" for i in range(20)))
    first = load_series(str(src))
    assert not first.clock and "assumed" in first.source
    out = tmp_path / "bare-out.csv"
    assert main(["export", str(src), "-o", str(out), "-q"]) == 0
    again = load_series(str(out))
    assert not again.clock and "no time column: sample index" in again.source
    assert "assumed" in again.source
    assert (again.field_ut == first.field_ut).all()


def test_export_of_a_table_with_time_and_unit_still_states_them(tmp_path):
    src = tmp_path / "timed.csv"
    src.write_text("t_ms,mx_ut,my_ut,mz_ut\n" + "".join(f"{100 * i},{i},{-i},{2 * i}\n" for i in range(10)))
    out = tmp_path / "timed-out.csv"
    assert main(["export", str(src), "-o", str(out), "-q"]) == 0
    again = load_series(str(out))
    assert again.clock and again.t_s[1] == 0.1 and "assumed" not in again.source
