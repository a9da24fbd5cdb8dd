"""Record from the simulated board, replay, and get the same samples and the same calibration,
bit for bit."""

import json

import numpy as np
import pytest

from magcal.app.load import load_series
from magcal.cli import main
from magcal.core.errors import DeviceError, PortError
from magcal.core.sample import Sample
from magcal.core.series import Series
from magcal.devices import open_device, parse_port
from magcal.devices.base import read_to_end
from magcal.devices.replay import BytesTransport
from magcal.recordings.capture import CaptureReader, CaptureWriter, make_header


def record_live(path, url="sim://?pace=0&seed=5", n=2500, faults=True):
    """Record from sim:// through the tap, with a device reset and line noise on the way;
    returns the samples the live client produced."""
    w = CaptureWriter(path, make_header(url, 115200))
    dev = open_device(url, tap=w)
    live = []
    dev.open()
    dev.start(100)

    def take(k):
        while len(live) < k:
            live.extend(i for i in dev.read(0.05) if isinstance(i, Sample))

    take(n // 2)
    if faults:
        dev.board._out += b"\x00garbage$S,1,2*00\n$S,3,"  # noise, a bad line, a torn one
        dev.board.power_cycle()  # an unsolicited reset: fresh hello, seq 0, millis 0
        dev.start(100)
    take(n)
    dev.stop()
    dev.close()
    w.close()
    return live


def same_series(a: Series, b: Series):
    assert len(a) == len(b)
    for x, y in ((a.t_s, b.t_s), (a.field_ut, b.field_ut), (a.valid, b.valid), (a.seq, b.seq)):
        assert np.array_equal(x, y)
    assert a.channels.keys() == b.channels.keys()
    for k in a.channels:
        assert np.array_equal(a.channels[k], b.channels[k], equal_nan=True)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "sim.cap"
    live = record_live(path)
    return path, Series.from_samples(live)


def test_replay_reproduces_the_live_samples(recorded):
    path, live = recorded
    replayed = Series.from_samples(read_to_end(open_device(f"replay://{path}")))
    n = len(replayed)
    assert n >= len(live)  # the capture may hold a few samples read after the last count
    same_series(live, replayed.take(np.arange(len(live))))
    assert (np.diff(live.t_s) > 0).all()  # time keeps rising across the device reset


def test_load_series_equals_the_replay_through_the_live_client(recorded):
    path, _ = recorded
    same_series(load_series(path), Series.from_samples(read_to_end(open_device(f"replay://{path}"))))


def test_replay_reports_the_link_defects_it_saw(recorded):
    path, _ = recorded
    dev = open_device(f"replay://{path}")
    dev.open()
    events = []
    while True:
        try:
            events.extend(i for i in dev.read(0.05) if not isinstance(i, Sample))
        except EOFError:
            break
    assert [e.kind for e in events if e.kind == "reset"] == ["reset"]
    c = dev.framer.counters
    assert c["bad_checksums"] == 1 and c["torn_lines"] == 1 and c["noise_bytes"] >= 8


def test_fit_on_capture_csv_and_replay_is_bit_identical(recorded, tmp_path, capsys):
    from magcal.fit import fit_calibration

    path, _ = recorded
    outputs = []
    for _ in range(2):
        assert main(["fit", str(path), "--json"]) == 0
        outputs.append(capsys.readouterr().out)
    csv = tmp_path / "sim.csv"
    assert main(["export", str(path), "--csv", "-o", str(csv)]) == 0
    capsys.readouterr()
    assert main(["fit", str(csv), "--json"]) == 0
    (from_csv,) = json.loads(capsys.readouterr().out)["fits"]
    # the CSV's fit also says how the table was read; every number is the same, bit for bit
    assert from_csv.pop("input").startswith("field from mx,my,mz in µT; time from t (s)")
    assert outputs[0] == outputs[1]
    (from_capture,) = json.loads(outputs[0])["fits"]
    # how each file was read differs (the capture's framing met noise; the CSV's nothing)
    assert from_capture.pop("reading")["bad_checksums"] == 1 and from_csv.pop("reading") == {}
    assert {**from_capture, "file": None} == {**from_csv, "file": None}
    replayed = Series.from_samples(read_to_end(open_device(f"replay://{path}")))
    via_replay = json.loads(json.dumps(fit_calibration(replayed, model="auto").to_dict()))
    evidence = {"evidence": from_capture.pop("evidence"), "coverage": from_capture.pop("coverage")}  # fit's CLI adds them
    assert evidence["evidence"]["coverage"] == evidence["coverage"]
    assert {**via_replay, "warnings": [], "file": str(path), "n_samples": len(replayed)} == from_capture


def test_record_command_writes_a_capture_that_replays(tmp_path, capsys):
    out = tmp_path / "cli.cap"
    assert main(["record", "--port", "sim://?pace=0&seed=9", "-o", str(out), "--count", "500", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["n_samples"] >= 500 and summary["capture"]["error"] is None
    r = CaptureReader(out)
    assert r.header["port"] == "sim://?pace=0&seed=9" and len(r) > 0
    s = load_series(out)
    assert len(s) >= summary["n_samples"]  # everything read was recorded
    assert main(["record", "--port", "sim://?pace=0", "-o", str(tmp_path / "x.cap")]) == 2  # no stop condition: usage


def test_paced_replay_releases_chunks_at_their_receive_times():
    now = [0.0]
    slept = []

    def sleep(dt):
        slept.append(dt)
        now[0] += dt

    t = BytesTransport([(10.0, b"a"), (10.5, b"b"), (12.0, b"c")], pace=1, clock=lambda: now[0], sleep=sleep)
    t.timeout = 0.2
    assert t.read(10) == b"a"
    assert t.in_waiting == 0
    assert t.read(10) == b""  # not due for 0.5 s: waits one timeout, returns nothing
    now[0] = 0.5
    assert t.read(10) == b"b"
    now[0] = 2.0
    assert t.read(10) == b"c"
    with pytest.raises(EOFError):
        t.read(10)
    fast = BytesTransport([(10.0, b"a"), (99.0, b"b")], pace=0, clock=lambda: 0.0, sleep=sleep)
    assert fast.read(5) + fast.read(5) == b"ab"  # unpaced: no waiting at all


def test_a_truncated_capture_replays_and_says_so(recorded, tmp_path):
    path, _ = recorded
    blob = path.read_bytes()
    cut = tmp_path / "cut.cap"
    cut.write_bytes(blob[:-7])
    dev = open_device(f"replay://{cut}")
    samples = read_to_end(dev)
    assert len(samples) > 1000 and dev.counters["capture_truncated_bytes"] > 0


def test_replay_urls_are_checked_with_clear_errors(tmp_path):
    p = parse_port("replay:///abs/x.cap?pace=1")
    assert (p.target, p.get("pace")) == ("/abs/x.cap", 1.0)
    p = parse_port("replay://rel/x.cap")
    assert (p.target, p.get("pace", 0.0)) == ("rel/x.cap", 0.0)
    with pytest.raises(PortError, match="pace"):
        parse_port("replay://x.cap?pace=fast")
    with pytest.raises(PortError, match="speed"):
        parse_port("replay://x.cap?speed=2")
    with pytest.raises(DeviceError, match="missing.cap"):
        open_device(f"replay://{tmp_path}/missing.cap")


def test_the_daemon_on_a_capture_read_in_the_wrong_dialect_stops_and_says_so(recorded, tmp_path, capsys):
    """A protocol-v1 capture asked for as --dialect motioncal: the capture will not change, so
    no reconnection can help — ``magcal run`` ends with a usage error naming both dialects (it
    retried for ever), and a one-shot command says the same."""
    port = f"replay://{recorded[0]}?pace=0"
    with pytest.raises(PortError, match="'native' dialect, not motioncal"):
        open_device(port, dialect="motioncal")
    for argv in (["run", "--state-dir", str(tmp_path / "st")], ["stream", "--count", "5"]):
        assert main([*argv, "--port", port, "--dialect", "motioncal"]) == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert err.startswith(f"magcal {argv[0]}: ") and "--dialect auto or native" in err
