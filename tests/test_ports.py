"""Port strings and the device interface, across every backend: one parser, one vocabulary of
options, one error; abilities declared, not probed; a device opened again reconnects to the
same board or recording (no registry anywhere)."""

from __future__ import annotations

import pytest

from magcal.core.errors import ConfigError, PortError, Unsupported
from magcal.core.sample import Sample
from magcal.devices import open_device, parse_port
from magcal.devices.base import RECORDING, batches, read_to_end
from magcal.devices.faults import FaultKind, LinkFaults, parse_fault
from magcal.devices.port import VOCABULARY


@pytest.mark.parametrize("url, words", [
    ("sim://?sede=3", r"unknown option 'sede' \(sim:// takes: seed, rate"),
    ("emu://?rate=50", r"unknown option 'rate' \(emu:// takes"),
    ("replay://x.cap?seed=1", r"unknown option 'seed' \(replay:// takes: pace, fault\)"),
    ("i2c:1?speed=3", r"unknown option 'speed' \(i2c: takes: addr, rate, chip, bits\)"),
    ("sim://?seed=-1", "seed"),
    ("sim://?rate=0", "out of range"),
    ("i2c:1?rate=500", "out of range"),
    ("sim://?motion=loop", "sphere, tilt, yaw, still"),
    ("sim://?offset=1,2", "three comma-separated"),
    ("sim://?noise=nan", "finite"),
    ("sim://?seed=1&seed=2", "more than once"),
    ("sim://?fault=explode", "unknown fault 'explode'"),
    ("sim://?fault=stuck_drdy", "cannot inject 'stuck_drdy'"),
    ("replay://x.cap?fault=hard_iron@3=1,2,3", "cannot inject 'hard_iron'"),
    ("emu://?fault=stuck_drdy@5", "register-model flag"),
    ("sim://?fault=unplug@-1", "≥ 0"),
    ("sim://board7", "options only"),
    ("replay://", "needs a file"),
    ("i2c:", "no bus"),
])
def test_every_backend_refuses_a_bad_port_string_with_one_error_naming_it(url, words):
    with pytest.raises(PortError, match=words) as exc:
        open_device(url)
    assert isinstance(exc.value, ConfigError)  # a setting to fix, not a device that failed


def test_an_option_means_the_same_everywhere():
    assert parse_port("sim://?pace=2").get("pace") == parse_port("replay://x.cap?pace=2").get("pace") == 2.0
    assert parse_port("sim://?pace=2").get("pace") == 2.0  # the earlier spelling still reads
    assert parse_port("emu://?addr=0x69").get("addr") == parse_port("i2c:1?address=105").get("addr") == 0x69
    assert parse_port("sim://?rate=50").get("rate") == parse_port("i2c:1?rate=50").get("rate") == 50
    assert set(VOCABULARY) >= {"seed", "rate", "pace", "eeprom", "fault", "addr"}
    serial = parse_port("socket://localhost:7777?logging=debug")  # pyserial's own options pass untouched
    assert serial.scheme == "serial" and serial.target == serial.url


def test_keyword_options_a_backend_does_not_take_are_refused_the_same_way():
    with pytest.raises(PortError, match="takes no option baud"):
        open_device("sim://", baud=9600)
    with pytest.raises(PortError, match="takes no option bogus"):
        open_device("i2c:1", bogus=1)
    with pytest.raises(PortError, match="dialect"):
        open_device("sim://", dialect="klingon")


def test_a_fault_is_one_value_whoever_injects_it():
    f = parse_fault("unplug@3+0.2")
    assert (f.t_s, f.kind, f.duration_s) == (3.0, FaultKind.UNPLUG, 0.2)
    assert parse_fault("hard_iron@50=30.5,-38.2,14.8").value == (30.5, -38.2, 14.8)
    assert parse_port("sim://?fault=garbage@1=400;reset@2&fault=stall@0.5").faults == (
        parse_fault("stall@0.5"), parse_fault("garbage@1=400"), parse_fault("reset@2"))


def test_the_one_injector_holds_an_interruption_until_the_host_has_drained_the_link():
    now = [0.0]
    link = LinkFaults([parse_fault("unplug@2+0.5"), parse_fault("stall@4+1")], clock=lambda: now[0])
    assert link.next_s() == 2.0 and not link.due(1.9)
    (unplug,) = link.due(2.0)
    link.interrupt(unplug)
    assert link.waiting and not link.settle(drained=False) and not link.unplugged  # lines still unread
    link.settle(drained=True)
    with pytest.raises(OSError, match="unplugged"):
        link.check_present("board")
    now[0] = 0.6
    assert link.settle(drained=True) is True  # replugged: the source boots
    link.check_present("board")
    assert len(link.noise(7)) == 7 and LinkFaults().noise(5) == LinkFaults().noise(5)  # one seed


def test_abilities_are_declared_by_each_backend(tmp_path):
    from magcal.devices.fakebus import FakeBus
    from magcal.sim.physics import demo_scenario

    sim = open_device("sim://?pace=0")
    assert sim.abilities.live and sim.abilities.store and sim.abilities.self_test
    assert open_device("i2c:1", bus_factory=lambda n: FakeBus(demo_scenario(1))).abilities.self_test
    cap = tmp_path / "x.cap"
    _record(cap)
    replay = open_device(f"replay://{cap}")
    assert replay.abilities == RECORDING
    replay.open()
    with pytest.raises(Unsupported, match="cannot run the AK8975 self-test"):
        replay.self_test()
    replay.close()


def _record(path, seconds: float = 3.0):
    from magcal.recordings.capture import CaptureWriter, make_header

    w = CaptureWriter(path, make_header("sim://?seed=2", 115200))
    dev = open_device("sim://?pace=0&seed=2", tap=w)
    dev.open()
    dev.start(100)
    n = 0
    for items in batches(dev, 0.1):
        n += sum(isinstance(i, Sample) for i in items)
        if n >= seconds * 100:
            break
    dev.close()
    w.close()


def test_a_device_opened_again_reconnects_to_the_same_board():
    dev = open_device("sim://?pace=0&seed=3")
    dev.open()
    dev.start(100)
    first = [i for i in dev.read(0.2) if isinstance(i, Sample)]
    board = dev.board
    dev.close()
    dev.open()  # a replug: the same board (physics time goes on), booted afresh
    assert dev.board is board
    dev.start(100)
    again = [i for i in dev.read(0.2) if isinstance(i, Sample)]
    assert again and again[0].seq < first[-1].seq  # it booted: sequence numbers start over
    dev.close()


def test_a_replay_opened_again_resumes_where_it_was(tmp_path):
    cap = tmp_path / "x.cap"
    _record(cap)
    whole = [s.seq for s in read_to_end(open_device(f"replay://{cap}"))]
    dev = open_device(f"replay://{cap}")
    dev.open()
    got = []
    while len(got) < 50:
        got += [i.seq for i in dev.read(0.05) if isinstance(i, Sample)]
    dev.close()
    dev.open()
    for items in batches(dev, 0.05):
        got += [i.seq for i in items if isinstance(i, Sample)]
    dev.close()
    assert got == whole  # nothing read twice, nothing skipped
