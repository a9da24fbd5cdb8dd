"""The daemon's view of the stream: each sample line taken once, in order, and counted.

``epoch`` counts connections and device resets: sequence numbers restart with each, so a repeated
number is a duplicate only within one epoch. A replay resumed after a restart is read from its
start again: the lines the saved session already holds are skipped here, their events too.
"""

from __future__ import annotations

from enum import Enum
from typing import Iterable, Iterator

from ...core.events import Item
from ...core.sample import Sample


class Take(Enum):
    """What a received sample line is to the daemon."""

    GOOD = "good"  # a valid raw reading: collected
    UNUSABLE = "unusable"  # flagged invalid by the device, or already calibrated: counted, not collected
    DUPLICATE = "duplicate"  # the same sequence number again within an epoch: dropped


class Intake:
    def __init__(self):
        self.samples = 0  # valid samples collected (given to the session and the monitor)
        self.samples_in = 0  # every sample line received
        self.epoch = 0  # increases at every connection and every device reset
        self.last_seq: int | None = None
        self.replay_lines = 0  # sample lines taken from a replay:// source since its start
        self._skip = 0  # a resumed replay: lines taken before the restart, read again from its start

    def new_epoch(self) -> None:
        self.epoch += 1
        self.last_seq = None

    def admit(self, items: Iterable[Item], replay: bool) -> Iterator[Item]:
        """``items`` without those a resumed replay already took (neither their samples nor
        their events count again)."""
        for item in items:
            if self._skip:
                self._skip -= int(isinstance(item, Sample))
                continue
            if replay and isinstance(item, Sample):
                self.replay_lines += 1
            yield item

    def take(self, sample: Sample) -> Take:
        self.samples_in += 1
        if self.last_seq is not None and sample.seq == self.last_seq:
            return Take.DUPLICATE  # never expected; counted to prove it
        self.last_seq = sample.seq
        if not sample.valid or sample.aux.get("calibrated"):
            return Take.UNUSABLE
        self.samples += 1
        return Take.GOOD

    def skip_replayed(self, lines: int) -> None:
        """A replay restarts from its beginning: skip the ``lines`` the saved session holds."""
        self.replay_lines = self._skip = int(lines)

    def status(self) -> dict:
        return {"samples": self.samples, "samples_in": self.samples_in, "epoch": self.epoch,
                "last_seq": self.last_seq}

    def to_state(self) -> dict:
        return {"samples": self.samples, "samples_in": self.samples_in, "replay_lines": self.replay_lines,
                "epoch": self.epoch}

    def restore(self, samples: int, samples_in: int, epoch: int) -> None:
        self.samples, self.samples_in, self.epoch = samples, samples_in, epoch
