"""The exit status of every ``magcal`` command: one table, printed by ``magcal --help`` and
given in the README (a test keeps the three in step).

A script can tell from the number alone what happened: whether a calibration is on the device
and verified (0), whether the data were not good enough (3) or the write did not stick (4), and
whether to look at the command line (2), the device (5) or a file (6).
"""

from __future__ import annotations

import functools
from enum import IntEnum


class Exit(IntEnum):
    OK = 0
    NO = 1
    USAGE = 2
    GATE = 3
    WRITE = 4
    DEVICE = 5
    INPUT = 6
    INTERRUPTED = 130
    PIPE = 141


MEANING = {
    Exit.OK: "done: a calibration written and verified by read-back, a fit that passed, a report written",
    Exit.NO: "the answer is no: nothing stored (show), no daemon running (status)",
    Exit.USAGE: "the command line, config file or environment asks for something invalid, or names no device",
    Exit.GATE: "the data did not pass: a calibration gate, a fit the data cannot support, a failed self-test",
    Exit.WRITE: "not written, or not verified by read-back (refused, read back different, a read-only source)",
    Exit.DEVICE: "the device or its port: cannot be opened, wrong chip, silent, unplugged",
    Exit.INPUT: "a file cannot be read or written: a recording, a calibration JSON, a state or capture file",
    Exit.INTERRUPTED: "interrupted (Ctrl-C); what was collected is kept where the command keeps it",
    Exit.PIPE: "the reader of the output went away (e.g. output piped into head)",
}


def code_for(exc: BaseException) -> Exit:
    """The exit status for one of magcal's own errors (a typed decision, never the message)."""
    from ..core.errors import ConfigError, DataInsufficient, DeviceError, ExtraMissing, NeedsChoice

    if isinstance(exc, (ConfigError, NeedsChoice, ExtraMissing)):
        return Exit.USAGE
    if isinstance(exc, DataInsufficient):
        return Exit.GATE
    if isinstance(exc, DeviceError):
        return Exit.DEVICE
    return Exit.INPUT  # InputError, StateError, a capture that cannot be written


@functools.cache
def failure_exits() -> dict:
    """The exit status of each reason a calibration is not on the device (``logic.failures``):
    the data did not pass (3), or the write did not stick (4). Built on first use, so that
    ``--help`` imports nothing of magcal's values."""
    from ..logic.failures import Reason

    return {Reason.TIMEOUT: Exit.GATE, Reason.END_OF_DATA: Exit.GATE, Reason.FIT_FAILED: Exit.GATE,
            Reason.GATE: Exit.GATE, Reason.WRITE_FAILED: Exit.WRITE, Reason.VERIFY_MISMATCH: Exit.WRITE,
            Reason.VERIFY_FAILED: Exit.WRITE}


def exit_for(failure) -> Exit:
    """The exit status of a ``logic.failures.Failure``."""
    return failure_exits()[failure.reason]


def epilog() -> str:
    """The table as ``--help`` prints it."""
    rows = "\n".join(f"  {int(code):>3}  {MEANING[code]}" for code in Exit)
    return "exit status:\n" + rows
