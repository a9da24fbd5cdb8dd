"""The README's exit-status table, walked: each command against each kind of error it can meet
exits with the status the table gives that kind (``cli.exits``)."""

import os
import re

import pytest

from magcal.cli import main
from magcal.cli.exits import MEANING, Exit

DATA = os.path.join(os.path.dirname(__file__), "data")
LOG = os.path.join(DATA, "px4_pyulog_sample_small_mags.ulg")  # two magnetometers, one of 6 samples
NO_DEVICE = "/dev/ttyMAGCAL_NONE"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("exits")
    assert main(["simulate", "-o", str(d / "ok.csv"), "--seconds", "10", "-q"]) == 0
    lines = (d / "ok.csv").read_text().splitlines()
    (d / "few.csv").write_text("\n".join(lines[:30]) + "\n")
    (d / "one_point.csv").write_text("\n".join([lines[0]] + [lines[1]] * 80) + "\n")
    assert main(["record", "--port", "sim://?pace=0", "-o", str(d / "full.cap"), "--count", "5", "-q"]) == 0
    (d / "empty.cap").write_bytes((d / "full.cap").read_bytes().split(b"\n", 1)[0] + b"\n")
    (d / "cal.json").write_text('{"offset_ut": [1, 2, 3], "field_ut": 48}')
    return d


CASES = [  # (command line with {d} for the files' folder, the kind of error, its status)
    ("fit {d}/ok.csv --unit bogus", "an option asks for something invalid", Exit.USAGE),
    ("fit {d}/ok.csv --unit 0", "an option asks for something invalid", Exit.USAGE),
    ("fit {d}/ok.csv --unit nan", "an option asks for something invalid", Exit.USAGE),
    ("fit {d}/ok.csv --columns mx,my", "an option asks for something invalid", Exit.USAGE),
    ("fit {d}/ok.csv --delimiter ''", "an option asks for something invalid", Exit.USAGE),
    ("diagnose {d}/ok.csv --unit bogus", "an option asks for something invalid", Exit.USAGE),
    ("export {d}/ok.csv --columns mx,my -o {d}/x.csv", "an option asks for something invalid", Exit.USAGE),
    ("fit " + LOG, "the command line names none of several magnetometers", Exit.USAGE),
    ("diagnose " + LOG, "the command line names none of several magnetometers", Exit.USAGE),
    ("export " + LOG, "the command line names none of several magnetometers", Exit.USAGE),
    ("fit {d}/few.csv", "too few samples", Exit.GATE),
    ("diagnose {d}/few.csv", "too few samples", Exit.GATE),
    ("fit {d}/one_point.csv", "degenerate samples", Exit.GATE),
    ("diagnose {d}/one_point.csv", "degenerate samples", Exit.GATE),
    ("diagnose " + LOG + " --mag 0", "too few samples in a flight log", Exit.GATE),
    ("write {d}/cal.json --port sim://?pace=0", "a gate that cannot be judged", Exit.GATE),
    ("write {d}/cal.json --port replay://{d}/full.cap --force", "a read-only source", Exit.WRITE),
    ("show --port " + NO_DEVICE, "a port that cannot be opened", Exit.DEVICE),
    ("stream --port " + NO_DEVICE, "a port that cannot be opened", Exit.DEVICE),
    ("calibrate --port " + NO_DEVICE, "a port that cannot be opened", Exit.DEVICE),
    ("write {d}/cal.json --force --port " + NO_DEVICE, "a port that cannot be opened", Exit.DEVICE),
    ("fit {d}/missing.csv", "a recording that cannot be read", Exit.INPUT),
    ("diagnose {d}/missing.csv", "a recording that cannot be read", Exit.INPUT),
    ("export {d}/missing.csv", "a recording that cannot be read", Exit.INPUT),
    ("export {d}/empty.cap -o {d}/empty.csv", "a capture with no samples", Exit.INPUT),
    ("write {d}/missing.json --port sim://?pace=0", "a calibration JSON that cannot be read", Exit.INPUT),
    ("show --port sim://?pace=0", "nothing stored", Exit.NO),
    ("status --state-dir {d}/no_daemon", "no daemon running", Exit.NO),
]


@pytest.mark.parametrize("line, kind, status", CASES, ids=[f"{c[0].split()[0]}: {c[1]}" for c in CASES])
def test_every_command_exits_as_the_table_says(files, capsys, line, kind, status):
    argv = [a.strip("'") for a in line.format(d=files).split()]
    assert main(argv) == status, f"{line}: {kind} should exit {int(status)} ({MEANING[status]})"
    err = capsys.readouterr().err
    assert "Traceback" not in err
    if status is Exit.INPUT:
        assert not (files / "empty.csv").exists()


def test_the_readme_table_is_the_table_the_code_uses():
    readme = open(os.path.join(os.path.dirname(__file__), "..", "README.md"), encoding="utf-8").read()
    rows = dict(re.findall(r"^\| (\d+) \| (.+?) \|$", readme, flags=re.M))
    assert {int(k): v for k, v in rows.items()} == {int(c): m for c, m in MEANING.items()}
