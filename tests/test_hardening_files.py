"""No write through a planted link: every file magcal writes whole goes through one writer
(``recordings.atomic``: a random temporary name created exclusively, renamed over the target,
which replaces a link rather than writing through it), and a capture never opens a link."""

import os

import pytest

from magcal.cli import main
from magcal.recordings.atomic import write_text

SECRET = "the target of a planted link\n"


def _plant(link, tmp_path, name="target.txt"):
    target = tmp_path / name
    target.write_text(SECRET)
    os.symlink(target, link)
    return target


def test_the_writer_replaces_a_planted_link_and_leaves_its_target(tmp_path):
    target = _plant(tmp_path / "out.json", tmp_path)
    write_text(tmp_path / "out.json", "{}\n")
    assert target.read_text() == SECRET
    assert not (tmp_path / "out.json").is_symlink() and (tmp_path / "out.json").read_text() == "{}\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json", "target.txt"]  # no temporary left


def test_simulate_writes_its_truth_file_past_a_planted_link(tmp_path):
    out = tmp_path / "out.csv"
    target = _plant(tmp_path / "out.csv.truth.json", tmp_path)
    assert main(["simulate", "-o", str(out), "--seconds", "2", "-q"]) == 0
    assert target.read_text() == SECRET
    assert '"truth"' in (tmp_path / "out.csv.truth.json").read_text()


@pytest.mark.slow
def test_diagnose_writes_its_model_and_report_past_planted_links(tmp_path, capsys):
    rec = tmp_path / "rec.csv"
    assert main(["simulate", "-o", str(rec), "--seconds", "40", "--seed", "2", "-q"]) == 0
    report = tmp_path / "report"
    report.mkdir()
    page_target = _plant(report / "index.html", tmp_path, "page_target.txt")
    model_target = _plant(tmp_path / "m.yaml", tmp_path, "model_target.txt")
    code = main(["diagnose", str(rec), "--model-out", str(tmp_path / "m.yaml"), "--report", str(report), "-q"])
    capsys.readouterr()
    assert code == 0
    assert page_target.read_text() == SECRET and model_target.read_text() == SECRET
    assert "<html" in (report / "index.html").read_text().lower()
    assert not any(p.name.startswith("m.yaml.tmp") for p in tmp_path.iterdir())


def test_a_capture_is_never_opened_through_a_link(tmp_path, capsys):
    target = _plant(tmp_path / "run.cap", tmp_path)
    code = main(["record", "--port", "sim://?pace=0", "-o", str(tmp_path / "run.cap"), "--count", "10"])
    err = capsys.readouterr().err
    assert code == 6 and "run.cap" in err
    assert target.read_text() == SECRET


@pytest.mark.parametrize("name", ["state.json", "writes.jsonl", "lock"])
def test_the_daemon_never_writes_through_a_planted_link(tmp_path, name):
    from magcal.app import config
    from magcal.app.daemon import Daemon
    from magcal.core.errors import StateError

    st = tmp_path / "st"
    st.mkdir()
    target = _plant(st / name, tmp_path)
    settings = config.load(None, {"port": "sim://?pace=0", "daemon": {"socket": False}}, environ={})
    try:
        Daemon(settings, state_dir=st, max_samples=1).run()
    except StateError as exc:  # the lock behind a link: refused, named
        assert name == "lock" and "lock" in str(exc)
    assert target.read_text() == SECRET
