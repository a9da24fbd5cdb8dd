"""The real firmware's command parser, fed random command streams through the emulated board
(simavr running the very ELF a user flashes): no crash, no hang, and a reply — an ``A``, ``E``
or ``C`` line — to every line (docs/protocol.md: a line starts at ``$``; bytes outside lines are
noise, dropped without a reply), including garbage, bad checksums, wrong field counts,
out-of-range values and over-long lines. Noise between the lines must not disturb the replies
to the lines after it. Afterwards the board still identifies itself.

The streams are drawn from a seeded generator (the same kinds of lines as the sim board's fuzz
in ``test_daemon_fuzz.py``), one line at a time, each waiting for its whole reply (an ``I`` or
``Z`` is answered by an ``A`` and a hello, a ``W`` by an ``A`` and its record) before the next."""

from __future__ import annotations

import random
import time

import pytest
from firmware_support import RawBoard, require_firmware

from magcal.wire.protocol import (
    Ack,
    ErrorReply,
    Hello,
    ParseError,
    RecordReply,
    encode_command,
    parse_command,
)

LINES = 250
REPLY_TIMEOUT_S = 5.0
THEN = {"I": Hello, "Z": Hello, "W": RecordReply}  # what follows the A of these commands


@pytest.fixture(autouse=True)
def _firmware():
    require_firmware()


def random_line(rng: random.Random) -> bytes:
    kind = rng.randrange(7)
    if kind <= 2:  # a well-formed command with random arguments (counts and values)
        args = [rng.randrange(-10**7, 10**7) for _ in range(rng.choice([0, 1, 1, 2, 3, 18, 19, 25]))]
        return encode_command(rng.choice("IGXRMKWFNQgz"), rng.randrange(1, 65536), *args)
    if kind == 3:  # a good command with its checksum spoilt
        return encode_command(rng.choice("IGXKR"), rng.randrange(1, 65536))[:-3] + b"%02X\n" % rng.randrange(256)
    if kind == 4:  # printable garbage after a '$', sometimes longer than a line may be
        return b"$" + bytes(rng.randrange(32, 127) for _ in range(rng.choice([0, 3, 40, 118, 150]))) + b"\n"
    if kind == 5:  # a line torn by a second '$'
        good = encode_command("I", rng.randrange(1, 65536))
        cut = rng.randrange(1, len(good) - 1)
        return good[:cut] + encode_command("K", rng.randrange(1, 65536))
    # binary noise with a CR/LF ending
    return bytes(rng.randrange(256) for _ in range(rng.randrange(1, 30))).replace(b"\n", b"") + b"\r\n"


@pytest.mark.slow
def test_firmware_replies_to_every_random_line(tmp_path):
    rng = random.Random(9150)
    b = RawBoard(tmp_path, eager=True)
    try:
        b.wait_for(lambda i: isinstance(i, Hello), 5, "boot hello")
        b.pump(0.05)
        no_reply = []
        t0 = time.monotonic()
        for n in range(LINES):
            line = random_line(rng)
            b.write(line)
            if b"$" not in line:
                continue  # noise: the next line's reply shows the parser was not disturbed
            try:
                tag = parse_command(line[line.rfind(b"$"):])[1]
            except ParseError:
                tag = 0  # the device answers a line it cannot parse with tag 0
            reply = None
            try:
                reply = b.wait_for(lambda i: isinstance(i, (Ack, ErrorReply, RecordReply)) and i.tag in (tag, 0),
                                   REPLY_TIMEOUT_S, f"reply to line {n}")
            except AssertionError:
                no_reply.append(line)
            if isinstance(reply, Ack) and reply.cmd in THEN:
                b.wait_for(lambda i: isinstance(i, THEN[reply.cmd]), REPLY_TIMEOUT_S, f"the rest of the reply to {line!r}")
            assert b.proc.poll() is None, f"the emulator died after {line!r}"
            b.pump(0.0)
            if b._unseen and len(b._unseen) > 2000:
                b._unseen.clear()
        elapsed = time.monotonic() - t0
        assert not no_reply, f"{len(no_reply)} line(s) got no reply, e.g. {no_reply[:3]}"
        # still alive and sane
        b.write(encode_command("X", 1))
        b.pump(0.2)
        tag = b.send("I")
        b.wait_for(lambda i: isinstance(i, Ack) and i.tag == tag, 5, "reply to I after the fuzz")
        b.wait_for(lambda i: isinstance(i, Hello), 5, "hello after the fuzz")
        print(f"\n{LINES} random lines answered in {elapsed:.1f} s; link counters {dict(b.framer.counters)}")
    finally:
        err = b.close()
    assert "crash" not in err.lower(), err
