"""One process per serial port: a second opener is refused (exit 5), naming the port and the
process that holds it — two readers would split the byte stream between them."""

import os
import subprocess
import sys

import pytest

from magcal.cli import main
from magcal.devices.portlock import PortBusy
from magcal.devices.transport import SerialPort

HOLDER = """
import sys, serial
port = serial.Serial(sys.argv[1], exclusive=True)
print("held", flush=True)
sys.stdin.read()
"""


@pytest.fixture
def pty():
    controller, device = os.openpty()
    yield os.ttyname(device)
    os.close(controller)
    os.close(device)


def test_a_second_opener_in_one_process_is_refused(pty):
    first = SerialPort(pty)()
    try:
        with pytest.raises(PortBusy, match=pty):
            SerialPort(pty)()
    finally:
        first.close()
    SerialPort(pty)().close()  # released: the next opener gets it


def test_a_command_on_a_port_another_process_holds_exits_5_naming_the_holder(pty, capsys):
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, pty], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert holder.stdout.readline().strip() == b"held"
        code = main(["show", "--port", pty])
        err = capsys.readouterr().err
    finally:
        holder.stdin.close()
        holder.wait(timeout=10)
    assert code == 5
    assert pty in err and f"pid {holder.pid}" in err
