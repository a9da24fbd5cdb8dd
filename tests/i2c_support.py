"""Test helpers for the i2c: backend on the fake bus: an opened device, and a bus that lets a
test act just before each burst read of the data registers (another master, a cable glitch)."""

from __future__ import annotations

from typing import Callable

from magcal.core.sample import Sample
from magcal.devices import open_device
from magcal.devices.fakebus import FakeBus
from magcal.devices.i2c import AK_ADDR, REG_HXL


def opened(bus: FakeBus, url: str = "i2c:1", **kw):
    dev = open_device(url, bus_factory=lambda n: bus, **kw)
    dev.open()
    return dev


def samples(items):
    return [i for i in items if isinstance(i, Sample)]


class BurstHookBus(FakeBus):
    """A fake bus that calls ``before_burst(bus)`` before every burst read of HXL..ST2."""

    def __init__(self, scenario, before_burst: Callable[["BurstHookBus"], None], **kw):
        super().__init__(scenario, **kw)
        self.before_burst = before_burst

    def read_i2c_block_data(self, addr, reg, n, force=None):
        if addr == AK_ADDR and reg == REG_HXL:
            self.before_burst(self)
        return super().read_i2c_block_data(addr, reg, n)
