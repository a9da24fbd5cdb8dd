"""Fuzzing what the daemon lives on, in CI time.

- the protocol parser (``Framer``) under thousands of hypothesis examples: any bytes, any
  split — it never raises, holds less than one line, yields only lines that arrived intact, and
  gives the same result however the stream is chunked;
- the simulated board's command parser fed random command streams: no crash, and a reply
  (an ``A``, ``E`` or ``C`` line) to every non-blank line. The same property against the real
  firmware under the AVR emulator is in ``test_firmware_fuzz.py``.

Hypothesis draws raw bytes and a seed; the seed interleaves well-formed lines into the bytes
(drawing whole structured lists costs ~5 ms an example, this ~1 ms, so thousands fit in CI)."""

import random

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from magcal.devices.simboard import SimBoard
from magcal.wire.protocol import MAX_LINE, Framer, RawSample, encode_command, encode_line

FAST = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
SPECIAL = [b"$", b"\n", b"\r\n", b"$$", b"*", b"$S,1*", b"9" * 130, b"\x00", b"$A,1,2,G*00\n"]


def device_line(rng: random.Random) -> bytes:
    kind = rng.randrange(4)
    s = rng.randrange(65536)
    if kind == 0:
        a = rng.randrange(-4096, 4096)
        return encode_line("S", (s, 10 * s, a, -a, 7, 0, -2150))
    if kind == 1:
        return encode_line("H", (s, 1, "0.1.0", "68", "48", 176, 178, 166, 100))
    if kind == 2:
        return encode_line("A", (s, rng.randrange(1, 65536), "G"))
    return rng.choice(SPECIAL)


def mix(noise: bytes, seed: int, make) -> list[bytes]:
    """The noise cut at random places with generated pieces in between."""
    rng = random.Random(seed)
    cuts = sorted(rng.randrange(len(noise) + 1) for _ in range(rng.randrange(8)))
    out, last = [], 0
    for c in cuts + [len(noise)]:
        out.append(noise[last:c])
        last = c
        for _ in range(rng.randrange(4)):
            out.append(make(rng))
    return out


@pytest.mark.slow
@settings(max_examples=3000, **FAST)
@given(st.binary(max_size=300), st.integers(0, 2**32 - 1), st.integers(1, 64))
def test_framer_never_raises_and_is_split_invariant(noise, seed, step):
    data = b"".join(mix(noise, seed, device_line))
    whole = Framer()
    items = whole.feed(data)
    chunked = Framer()
    got = []
    for i in range(0, len(data), step):
        got += chunked.feed(data[i : i + step])
        assert len(chunked._carry) < MAX_LINE
    assert got == items
    assert chunked.counters == whole.counters
    for it in items:
        if isinstance(it, RawSample):  # a sample only from a line that is in the input intact
            assert encode_line("S", (it.seq, it.ms, *it.raw, it.st2, it.temp_raw)) in data
    n_samples = sum(isinstance(it, RawSample) for it in items)
    assert n_samples <= data.count(b"$S,")


def host_line(rng: random.Random) -> bytes:
    kind = rng.randrange(5)
    if kind < 3:
        args = [rng.randrange(-10**6, 10**6) for _ in range(rng.choice([0, 1, 1, 2, 19, 25]))]
        return encode_command(rng.choice("IGXRMKWZFNQg"), rng.randrange(1, 65536), *args)
    if kind == 3:  # a good command with its checksum spoilt
        line = encode_command(rng.choice("IGXK"), rng.randrange(1, 65536))
        return line[:-3] + b"00\n"
    return b"$" + bytes(rng.randrange(32, 127) for _ in range(rng.randrange(200))) + b"\n"


@pytest.mark.slow
@settings(max_examples=2000, **FAST)
@given(st.binary(max_size=200), st.integers(0, 2**32 - 1))
def test_sim_board_replies_to_every_line(noise, seed):
    board = SimBoard(rate_hz=100)
    board.read(4096)  # the boot hello
    text = b"".join(mix(noise, seed, host_line))
    for line in text.split(b"\n"):
        line += b"\n"
        board.write(line)
        out = bytes(board._out)
        board._out.clear()
        board._streaming = False  # keep the replies apart from samples
        board._fit = None
        if not line.strip():
            continue
        replies = [ln for ln in out.split(b"\n") if ln[:2] in (b"$A", b"$E", b"$C")]
        assert replies, f"no reply to {line!r}: {out!r}"
