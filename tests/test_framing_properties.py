"""Framing as a pure function over bytes: whatever arrives, split however it arrives, the framer
never raises, never yields a message that was not sent intact, counts every defect, and the
bulk parser used for replays gives exactly the same answer."""

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from magcal.wire.bulk import parse_stream
from magcal.wire.protocol import MAX_LINE, Framer, Gap, Hello, RawSample, Restart, crc8, encode_line

SETTINGS = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def sample_line(seq, ms=1000, raw=(-123, 456, -789), st2=0, temp=-2150, accel=()):
    return encode_line("S", (seq, ms, *raw, st2, temp, *accel))


def hello_line(seq=0, asa=(176, 178, 166)):
    return encode_line("H", (seq, 1, "0.1.0", "68", "48", *asa, 100))


ints16 = st.integers(-40000, 40000)
good_lines = st.one_of(
    st.builds(sample_line, st.integers(0, 65535), st.integers(-(2**33), 2**33), st.tuples(ints16, ints16, ints16),
              st.integers(0, 255), ints16),
    st.builds(sample_line, st.integers(0, 65535), st.integers(-(2**33), 2**33), st.tuples(ints16, ints16, ints16),
              st.integers(0, 255), ints16, st.tuples(ints16, ints16, ints16)),  # with the accelerometer's fields
    st.builds(hello_line, st.integers(0, 65535), st.tuples(*[st.integers(0, 255)] * 3)),
    st.builds(lambda s, t: encode_line("U", (s, 5, 1000, -2000, 3000, 0, t)), st.integers(0, 65535), ints16),
    st.builds(lambda s, tag: encode_line("A", (s, tag, "G")), st.integers(0, 65535), st.integers(1, 65535)),
    st.builds(lambda s: encode_line("L", (s, "hello world")), st.integers(0, 65535)),
)


@st.composite
def damaged(draw, line):
    """A line with one defect a serial link produces: a flipped byte, a cut, an inserted '$',
    lower-case checksum, a CR, padding to over-long, or a run of noise before it."""
    how = draw(st.sampled_from(["flip", "cut", "dollar", "lower", "cr", "long", "noise", "intact"]))
    if how == "flip":
        i = draw(st.integers(0, len(line) - 2))
        return line[:i] + bytes([line[i] ^ draw(st.integers(1, 255))]) + line[i + 1 :]
    if how == "cut":
        return line[: draw(st.integers(0, len(line) - 1))]
    if how == "dollar":
        i = draw(st.integers(1, len(line) - 1))
        return line[:i] + b"$" + line[i:]
    if how == "lower":
        return line[:-3] + line[-3:-1].lower() + b"\n"
    if how == "cr":
        return line[:-1] + b"\r\n"
    if how == "long":
        return line[:-4] + b"9" * MAX_LINE + line[-4:]
    if how == "noise":
        return draw(st.binary(max_size=40)) + line
    return line


@st.composite
def streams(draw):
    parts = []
    for _ in range(draw(st.integers(0, 25))):
        kind = draw(st.integers(0, 9))
        line = draw(good_lines)
        if kind < 6:
            parts.append(line)
        elif kind < 9:
            parts.append(draw(damaged(line)))
        else:
            parts.append(draw(st.binary(max_size=200)))
    return b"".join(parts)


def split(data, cuts):
    points = sorted({c % (len(data) + 1) for c in cuts})
    out, last = [], 0
    for p in points + [len(data)]:
        out.append(data[last:p])
        last = p
    return out


def feed_all(chunks):
    f = Framer()
    items = []
    for c in chunks:
        items.extend(f.feed(c))
    return items, f


def sent_intact(data):
    """Every line that appears intact in ``data``: a '$'…'\\n' run with no '$' inside whose
    checksum matches (what a message may legitimately come from)."""
    out = set()
    for piece in data.split(b"\n"):
        seg = piece[piece.rfind(b"$") :] if b"$" in piece else b""
        if seg.endswith(b"\r"):
            seg = seg[:-1]
        if len(seg) >= 4 and seg[-3:-2] == b"*" and len(seg) + 2 <= MAX_LINE + 1:
            try:
                if crc8(seg[1:-3]) == int(seg[-2:], 16) and seg[-2:].upper() == seg[-2:]:
                    out.add(seg[1:-3])
            except ValueError:
                pass
    return out


def payload_of(msg):
    if isinstance(msg, RawSample):
        accel = "".join(f",{a}" for a in msg.accel or ())
        return f"S,{msg.seq},{msg.ms},{msg.raw[0]},{msg.raw[1]},{msg.raw[2]},{msg.st2},{msg.temp_raw}{accel}"
    return None


@pytest.mark.slow
@SETTINGS
@given(streams(), st.lists(st.integers(0, 10**6), max_size=12))
def test_any_split_gives_the_same_items_and_counters(data, cuts):
    whole, f1 = feed_all([data])
    parts, f2 = feed_all(split(data, cuts))
    bytewise, f3 = feed_all([data[i : i + 1] for i in range(len(data))])
    assert whole == parts == bytewise
    assert +f1.counters == +f2.counters == +f3.counters


@SETTINGS
@given(st.binary(max_size=2000), st.lists(st.integers(0, 10**6), max_size=12))
def test_arbitrary_bytes_never_raise_and_memory_stays_bounded(data, cuts):
    f = Framer()
    for c in split(data, cuts):
        f.feed(c)
        assert len(f._carry) < MAX_LINE
    assert sum(v for k, v in f.counters.items() if v < 0) == 0


@pytest.mark.slow
@SETTINGS
@given(streams(), st.lists(st.integers(0, 10**6), max_size=12))
def test_every_sample_was_sent_intact(data, cuts):
    items, _ = feed_all(split(data, cuts))
    intact = sent_intact(data)
    for m in items:
        p = payload_of(m)
        if p is not None:
            # the canonical spelling is how encode_line sent it; odd spellings never occur here
            assert p.encode() in intact


@pytest.mark.slow
@SETTINGS
@given(streams())
def test_bulk_parser_matches_the_incremental_framer(data):
    items, f = feed_all([data])
    frames = parse_stream(data)
    assert frames.items() == items
    assert frames.counters == +f.counters


@SETTINGS
@given(st.binary(max_size=600))
def test_bulk_parser_matches_on_raw_noise(data):
    items, f = feed_all([data])
    frames = parse_stream(data)
    assert frames.items() == items
    assert frames.counters == +f.counters


def _with_crc(payload: bytes) -> bytes:
    return b"$" + payload + b"*" + f"{crc8(payload):02X}".encode() + b"\n"


big = st.one_of(
    st.integers(0, 5000),
    st.integers(2**63 - 3, 2**63 + 3),
    st.integers(10**17 - 3, 10**17 + 3),
    st.integers(10**18 - 3, 10**19 + 3),
)


@SETTINGS
@pytest.mark.slow
@given(st.lists(st.tuples(st.sampled_from(["+", "-", "", "0", "00"]), big), min_size=7, max_size=11),
       st.sampled_from([b"S", b"U"]))
def test_bulk_fast_path_agrees_on_odd_but_legal_numbers(tokens, kind):
    """Leading zeros, '+' signs, numbers at and beyond int64: the fast path must either agree
    with the line judge or hand the line over to it."""
    line = _with_crc(kind + b"," + ",".join(f"{s}{v}" for s, v in tokens).encode())
    stream = hello_line() + line
    items, f = feed_all([stream])
    frames = parse_stream(stream)
    assert frames.items() == items
    assert frames.counters == +f.counters


@SETTINGS
@given(
    st.lists(
        st.integers(0, 65535).map(str) | st.just("") | st.text(alphabet="0123456789+-", max_size=6),
        min_size=6, max_size=11,
    ).map(",".join)
    | st.text(alphabet="0123456789+-,*", max_size=60),
    st.sampled_from([b"S", b"U"]),
)
def test_bulk_fast_path_agrees_on_garbled_fields_with_valid_checksums(fields, kind):
    """Signs inside numbers, empty fields, wrong field counts, stray '*': correct checksum,
    wrong syntax — judged exactly as the incremental framer judges them."""
    stream = hello_line() + _with_crc(kind + b"," + fields.encode())
    items, f = feed_all([stream])
    frames = parse_stream(stream)
    assert frames.items() == items
    assert frames.counters == +f.counters


def test_defects_are_counted_by_name():
    good = [sample_line(i) for i in range(1, 6)]
    bad_crc = good[3][:-3] + (b"00" if good[3][-3:-1] != b"00" else b"01") + b"\n"  # seq 4
    stream = (
        hello_line(0)
        + good[0]
        + b"\x00\xffnoise"
        + good[1][:10]  # torn by the next '$'
        + good[2]
        + bad_crc
        + b"$" + b"7" * (MAX_LINE + 5) + b"\n"  # over-long
        + good[4]  # seq 5: 2 (torn) and 4 (bad checksum) lost
        + hello_line(0)  # an unsolicited restart
        + encode_line("Q", (1, 2))  # a type this host does not know
    )
    items, f = feed_all(split(stream, [7, 50, 51, 130, 300]))
    c = f.counters
    assert c["torn_lines"] == 1
    assert c["bad_checksums"] == 1
    assert c["overlong_lines"] == 1
    assert c["unknown_types"] == 1
    assert c["restarts"] == 1
    assert [i for i in items if isinstance(i, Gap)] == [Gap(3, 1), Gap(5, 1)]
    assert sum(isinstance(i, Restart) for i in items) == 1
    assert [m.seq for m in items if isinstance(m, RawSample)] == [1, 3, 5]
    assert sum(isinstance(m, Hello) for m in items) == 2
    # noise: 7 junk bytes, the torn line, the over-long run with its newline
    assert c["noise_bytes"] == 7 + 10 + (1 + MAX_LINE + 5 + 1)
    assert parse_stream(stream).counters == +c


def test_a_dollar_inside_an_overlong_run_starts_a_fresh_line():
    line = sample_line(1)
    stream = b"$" + b"x" * (MAX_LINE + 10) + line
    for chunks in ([stream], [stream[:60], stream[60:]], [stream[:MAX_LINE + 3], stream[MAX_LINE + 3 :]]):
        items, f = feed_all(chunks)
        assert [m.seq for m in items if isinstance(m, RawSample)] == [1]
        assert f.counters["overlong_lines"] == 1


def test_counter_totals_account_for_every_byte():
    """noise + bytes of complete lines + the held unfinished line = bytes fed."""
    lines = [sample_line(i) for i in range(20)]
    good = b"".join(lines)
    head = lines[0] + lines[1] + lines[2][:9]  # two whole lines, then a cut one
    stream = b"junk" + head + b"$$$" + good + b"\x00" * 300 + good[:9]
    items, f = feed_all(split(stream, [3, 77, 400, 401]))
    c = f.counters
    assert c["lines"] == 20 and c["duplicate_lines"] == 2  # seq 0 and 1 came twice: delivered once
    assert c["torn_lines"] == 4  # the cut line and three lone '$'
    assert len(f._carry) == 9
    assert c["noise_bytes"] == len(stream) - (len(lines[0]) + len(lines[1]) + len(good)) - 9
    assert parse_stream(stream).counters == +c


@st.composite
def numbered_streams(draw):
    """A stream as a link delivers it: numbers mostly in order, with copies of older lines,
    losses, long jumps, restarts and renumberings without a hello; some lines damaged."""
    seq, parts = draw(st.integers(0, 65535)), []
    sent: list[bytes] = []
    for _ in range(draw(st.integers(1, 80))):
        r = draw(st.integers(0, 19))
        if r == 0 and sent:
            parts.append(sent[-draw(st.integers(1, min(len(sent), 150)))])  # an older line again
            continue
        if r == 1:
            seq += draw(st.integers(2, 5000))  # lines lost, or a jump too long to be loss
        elif r == 2:
            seq = 0
            parts.append(hello_line(0))
        elif r == 3:
            seq = draw(st.integers(0, 65535))  # renumbered without a hello
        else:
            seq += 1
        line = sample_line(seq % 65536, ms=seq)
        sent.append(line)
        parts.append(draw(damaged(line)) if r == 4 else line)
    return b"".join(parts)


@pytest.mark.slow
@SETTINGS
@given(numbered_streams(), st.lists(st.integers(0, 10**6), max_size=8))
def test_sequence_rules_are_the_same_in_bulk_and_never_deliver_a_line_twice(data, cuts):
    items, f = feed_all(split(data, cuts))
    frames = parse_stream(data)
    assert frames.items() == items and frames.counters == +f.counters
    epoch: set[int] = set()
    span = 0  # numbers passed since the numbering began (a wrap may reuse them)
    for it in items:  # within one numbering, each sequence number is delivered once
        span += it.count if isinstance(it, Gap) else 1
        if isinstance(it, Restart) or span >= 65536:
            epoch, span = set(), 0
        elif isinstance(it, RawSample):
            assert it.seq not in epoch
            epoch.add(it.seq)
