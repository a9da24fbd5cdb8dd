"""Bulk framing: a whole recorded byte stream → the same messages as ``protocol.Framer``, fast.

``parse_stream(data)`` gives exactly what a fresh ``Framer`` gives when fed ``data`` in any
chunking (items and counters; the property tests hold the two together), but does the work
with numpy so that replaying an hour of 100 Hz data takes a fraction of a second;
``parse_blocks(blocks)`` gives the same for a stream handed over in blocks, holding one block
at a time beside the sample arrays (steps 1–3 run per block, cut after a newline; step 4 once):

1. every ``$`` opens a run that ends at the next ``$`` or ``\\n`` (positions by vectorised
   search); runs are sorted into complete lines, torn runs, over-long runs and the unfinished
   tail, and ``noise_bytes`` is everything that is not a complete line or the tail;
2. complete ``S``/``U`` lines are grouped by length, so each group is a rectangular byte
   matrix: printability, the ``*CC`` position, the CRC-8 (one table lookup per column across
   all lines of the group) and the seven decimal fields (ten with the accelerometer's) (digit weights summed per token) are
   checked and parsed column-wise;
3. any line the fast path does not accept — other message types, odd but legal spellings,
   numbers too long for int64, and every defective line — is judged by
   ``protocol.classify_line``, the same function the incremental framer uses, so defects are
   named identically;
4. sequence gaps and restarts are computed from the merged, position-ordered sequence numbers
   with the ``SequenceTracker`` rules (vectorised while every step is plain; duplicates and
   out-of-sequence lines are judged by the tracker itself and not delivered).

Pure: bytes in, arrays out; no I/O.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from .protocol import (
    CRC8_TABLE_NP,
    MAX_DROPOUT,
    MAX_LINE,
    SEQ_MOD,
    CalibratedSample,
    Frame,
    Gap,
    Hello,
    Message,
    RawSample,
    Restart,
    SequenceTracker,
    classify_line,
)

_DOLLAR, _NL, _CR, _COMMA, _STAR = 0x24, 0x0A, 0x0D, 0x2C, 0x2A
_MAX_DIGITS = 18  # a decimal token of at most 18 digits fits int64 exactly
_WITH_ACCEL = 10  # the tokens of a sample line that carries the accelerometer's three
_BLOCK = 16384  # lines per vectorised block (bounds the temporary index arrays)
_HEXVAL = np.full(256, -1, np.int16)
for _i, _ch in enumerate(b"0123456789ABCDEF"):
    _HEXVAL[_ch] = _i


@dataclass
class Frames:
    """The parsed stream. Samples (``S`` and ``U`` lines) are arrays in stream order; every
    other message is kept as an object with its byte position. ``counters`` equals the
    incremental framer's; ``tail`` is the unfinished last line (not counted, as in Framer)."""

    pos: np.ndarray  # (n,) byte offset of each sample line's '$'
    kind: np.ndarray  # (n,) b'S' or b'U' as uint8
    seq: np.ndarray  # (n,) int64
    ms: np.ndarray  # (n,) int64
    values: np.ndarray  # (n, 3) int64: raw counts (S) or nT (U)
    st2: np.ndarray  # (n,) int64
    temp: np.ndarray  # (n,) int64 TEMP_OUT
    accel: np.ndarray  # (n, 3) float64: the accelerometer's counts, NaN for a line without them
    others: list[tuple[int, Message]]  # (position, message) for every non-sample message
    events: list[tuple[int, Frame]]  # (position of the message it precedes, Gap | Restart)
    counters: Counter = field(default_factory=Counter)
    tail: bytes = b""

    def __len__(self) -> int:
        return len(self.pos)

    def items(self) -> list[Frame]:
        """Everything in order, as the incremental framer returns it (for tests and tools)."""
        seq = self.seq.tolist()
        ms = self.ms.tolist()
        vals = self.values.tolist()
        st2 = self.st2.tolist()
        temp = self.temp.tolist()
        kinds = self.kind.tolist()
        acc = self.accel.tolist()
        merged: list[tuple[int, int, object]] = []
        for k, p in enumerate(self.pos.tolist()):
            cls = RawSample if kinds[k] == ord("S") else CalibratedSample
            a = None if acc[k][0] != acc[k][0] else tuple(int(x) for x in acc[k])  # NaN: none sent
            merged.append((p, 1, cls(seq[k], ms[k], tuple(vals[k]), st2[k], temp[k], a)))
        merged.extend((p, 1, m) for p, m in self.others)
        merged.extend((p, 0, e) for p, e in self.events)
        merged.sort(key=lambda x: (x[0], x[1]))
        return [m for _, _, m in merged]


def _runs(a: np.ndarray):
    """Classify every '$' run: returns (starts, ends, kind) with kind 0 line, 1 torn, 2 over-long,
    3 unfinished tail; ``ends`` is the index of the terminator (or len for the tail)."""
    n = len(a)
    d = np.flatnonzero(a == _DOLLAR)
    nl = np.flatnonzero(a == _NL)
    next_d = np.empty_like(d)
    next_d[:-1] = d[1:]
    if len(d):
        next_d[-1] = n
    k = np.searchsorted(nl, d)
    nl_ext = np.append(nl, n)
    next_nl = nl_ext[k]
    ends = np.minimum(next_d, next_nl)
    length = ends - d
    kind = np.where(length >= MAX_LINE, 2, np.where(ends == n, 3, np.where(ends == next_d, 1, 0)))
    return d, ends, kind


_CRC8_PAIR = None


def _crc8_pairs() -> np.ndarray:
    """T2[(x << 8) | y] = T[T[x] ^ y]: two bytes per lookup."""
    global _CRC8_PAIR
    if _CRC8_PAIR is None:
        t = CRC8_TABLE_NP
        x = np.arange(65536)
        _CRC8_PAIR = t[t[x >> 8] ^ (x & 0xFF)].astype(np.uint16)
    return _CRC8_PAIR


# byte classes for the numeric fields: 0 digit, 1 comma, 2 sign, 3 anything else
_CLASS = np.full(256, 3, np.uint8)
_CLASS[0x30:0x3A] = 0
_CLASS[_COMMA] = 1
_CLASS[0x2B] = 2
_CLASS[0x2D] = 2
_BAD_PAIR = np.zeros(16, bool)
for _p in range(4):
    for _c in range(4):
        _BAD_PAIR[_p * 4 + _c] = (
            _p == 3 or _c == 3  # a byte that has no place in a number
            or (_c == 2 and _p != 1)  # a sign that does not open a token
            or (_c == 1 and _p != 0)  # a token that does not end with a digit (or is empty)
        )


def _fast_group(a: np.ndarray, starts: np.ndarray, le: int):
    """Lines of effective length ``le`` (no '\\r') starting at ``starts``, all beginning with
    ``$S,`` or ``$U,``: returns (ok mask, values (k, 10) int64, which carry the accelerometer)."""
    k = len(starts)
    m = np.lib.stride_tricks.sliding_window_view(a, le)[starts]  # (k, le) uint8 copy
    ok = np.all((m - np.uint8(32)) < 95, axis=1)  # printable ASCII (uint8 wraps below 32)
    ok &= m[:, le - 3] == _STAR
    h1 = _HEXVAL[m[:, le - 2]]
    h0 = _HEXVAL[m[:, le - 1]]
    ok &= (h1 >= 0) & (h0 >= 0)
    # CRC-8 of the payload m[:, 1 : le - 3], column by column, two bytes per table lookup
    pt = np.ascontiguousarray(m[:, 1 : le - 3].T).astype(np.uint16)
    pair = _crc8_pairs()
    crc = np.zeros(k, np.uint16)
    j = 0
    while j + 1 < len(pt):
        crc = pair[((crc ^ pt[j]) << 8) | pt[j + 1]]
        j += 2
    if j < len(pt):
        crc = CRC8_TABLE_NP[crc ^ pt[j]].astype(np.uint16)
    ok &= crc.astype(np.int16) == (h1 * 16 + h0)
    # the seven (or, with the accelerometer's, ten) decimal tokens after "S," and a closing comma
    w = le - 5
    f = np.empty((k, w), np.uint8)
    f[:, :-1] = m[:, 3 : le - 3]
    f[:, -1] = _COMMA
    cls = _CLASS[f]
    comma = cls == 1
    ntok = np.count_nonzero(comma, axis=1)
    ok &= (ntok == 7) | (ntok == _WITH_ACCEL)
    # (previous class, class) pairs, with a virtual comma before column 0: one table says
    # which pairs break "[+-]?digits" tokens
    pairs = np.empty((k, w), np.uint8)
    pairs[:, 0] = 4 + cls[:, 0]
    pairs[:, 1:] = cls[:, :-1] * np.uint8(4) + cls[:, 1:]
    ok &= ~np.any(_BAD_PAIR[pairs], axis=1)
    start = np.empty_like(comma)  # a token starts at column 0 and after every comma
    start[:, 0] = True
    start[:, 1:] = comma[:, :-1]
    vals = np.zeros((k, _WITH_ACCEL), np.int64)
    has = ntok == _WITH_ACCEL
    for width in (7, _WITH_ACCEL):
        sel = np.flatnonzero(ok & (has == (width == _WITH_ACCEL)))
        if len(sel):
            good, vals[sel, :width] = _token_values(f[sel], cls[sel], start[sel], width)
            ok[sel[~good]] = False
    return ok, vals, has


def _token_values(fs: np.ndarray, cs: np.ndarray, st: np.ndarray, width: int):
    """The ``width`` decimal tokens of each line (its bytes ``fs``, their classes ``cs``, token
    starts ``st``): (which lines hold numbers the arrays take, the values)."""
    w = fs.shape[1]
    cols = np.arange(w, dtype=np.int16)
    nxt = np.where(cs == 1, cols, np.int16(w))
    nxt = np.minimum.accumulate(nxt[:, ::-1], axis=1)[:, ::-1]  # next comma at or after
    expo = nxt - cols - 1
    digit = cs == 0
    long_tok = np.any(digit & (expo >= _MAX_DIGITS), axis=1)
    pw = 10 ** np.arange(_MAX_DIGITS + 1, dtype=np.int64)
    contrib = np.where(digit, (fs - np.uint8(0x30)).astype(np.int64) * pw[np.minimum(expo, _MAX_DIGITS)], 0)
    tok_start = np.flatnonzero(st.reshape(-1))  # exactly ``width`` per line, in order
    sums = np.add.reduceat(contrib.reshape(-1), tok_start).reshape(len(fs), width)
    neg = (fs.reshape(-1)[tok_start] == 0x2D).reshape(len(fs), width)
    v = np.where(neg, -sums, sums)
    exact = np.all(np.abs(v[:, 7:]) < 2**53, axis=1)  # the accelerometer's column is float64
    return ~long_tok & (v[:, 0] >= 0) & (v[:, 0] < SEQ_MOD) & exact, v


def _fast_lines(a: np.ndarray, ls: np.ndarray, le_: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sample lines (``S``/``U``) the vectorised path parses, grouped by length:
    (which lines it took, their 10 values, which of them carry the accelerometer's 3)."""
    eff = le_ - ls  # the length without a trailing '\r'
    has_cr = np.zeros(len(ls), bool)
    nz = eff > 1
    has_cr[nz] = a[le_[nz] - 1] == _CR
    eff = eff - has_cr
    cand = np.zeros(len(ls), bool)
    ok_len = eff >= 8  # shortest possible "$S,a*CC" never parses; keep indices in range
    cand[ok_len] = ((a[ls[ok_len] + 1] == ord("S")) | (a[ls[ok_len] + 1] == ord("U"))) & (
        a[ls[ok_len] + 2] == _COMMA
    )
    fast_ok = np.zeros(len(ls), bool)
    fast_vals = np.zeros((len(ls), _WITH_ACCEL), np.int64)
    fast_has = np.zeros(len(ls), bool)
    ci = np.flatnonzero(cand)
    for le in np.unique(eff[ci]):
        grp = ci[eff[ci] == le]
        for b in range(0, len(grp), _BLOCK):
            g = grp[b : b + _BLOCK]
            fast_ok[g], fast_vals[g], fast_has[g] = _fast_group(a, ls[g], int(le))
    return fast_ok, fast_vals, fast_has


def _judged_lines(raw: bytes, ls: np.ndarray, le_: np.ndarray, counters: Counter):
    """Every other line, judged by the incremental framer's own line judge: (positions, kinds
    and values of the samples among them, the other messages with their positions); defects
    go to ``counters``."""
    sample_pos: list[int] = []
    sample_kind: list[int] = []
    sample_vals: list[tuple] = []
    others: list[tuple[int, Message]] = []
    for p, e in zip(ls.tolist(), le_.tolist()):
        msg = classify_line(raw[p:e])
        if isinstance(msg, str):
            counters[msg] += 1
        elif isinstance(msg, (RawSample, CalibratedSample)) and _fits(msg):
            sample_pos.append(p)
            sample_kind.append(ord("S") if isinstance(msg, RawSample) else ord("U"))
            v = msg.raw if isinstance(msg, RawSample) else msg.field_nt
            sample_vals.append((msg.seq, msg.ms, *v, msg.st2, msg.temp_raw, *(msg.accel or (np.nan,) * 3)))
        else:
            others.append((p, msg))
    return sample_pos, sample_kind, sample_vals, others


def parse_stream(data: bytes) -> Frames:
    """Parse a whole byte stream as a fresh ``Framer`` would (see the module docstring)."""
    lines = _Lines()
    lines.add(bytes(data), 0, last=True)
    return lines.frames()


def parse_blocks(blocks: Iterable[bytes]) -> Frames:
    """``parse_stream`` of the concatenated ``blocks``, holding one block at a time beside the
    arrays: each block is cut after its last newline and the rest carried into the next. No
    line, torn run or stretch of noise crosses such a cut (each ends at the newline), so every
    count is the one the whole stream gives; sequence rules then run over all lines at once."""
    lines, carry, at = _Lines(), b"", 0
    for block in blocks:
        buf = carry + block
        cut = buf.rfind(b"\n") + 1
        if cut:
            lines.add(buf[:cut], at, last=False)
            at += cut
        carry = buf[cut:]
    lines.add(carry, at, last=True)
    return lines.frames()


class _Lines:
    """Every line of a stream fed in pieces that end after a newline (and a last piece):
    sample lines as columns, other messages as objects, framing counters. The columns grow in
    place (few large allocations, so memory freed between pieces is reused, not scattered)."""

    _COLS = (("pos", np.int64, ()), ("kind", np.uint8, ()), ("seq", np.int64, ()), ("ms", np.int64, ()),
             ("values", np.int64, (3,)), ("st2", np.int64, ()), ("temp", np.int64, ()), ("accel", np.float64, (3,)))

    def __init__(self):
        self.cols = {name: np.empty((1024, *shape), dtype) for name, dtype, shape in self._COLS}
        self.n = 0
        self.others: list[tuple[int, Message]] = []
        self.counters: Counter = Counter()
        self.tail = b""

    def add(self, data: bytes, at: int, last: bool) -> None:
        """Parse ``data``, found at offset ``at`` of the stream; only the ``last`` piece may
        end inside a line (its unfinished tail)."""
        a = np.frombuffer(data, np.uint8)
        starts, ends, kind = _runs(a)
        line = kind == 0
        ls, le_ = starts[line], ends[line]
        tail_len = 0
        if last and len(kind) and kind[-1] == 3:
            self.tail = bytes(a[starts[-1] :])
            tail_len = len(self.tail)
        self.counters["torn_lines"] += int(np.sum(kind == 1))
        self.counters["overlong_lines"] += int(np.sum(kind == 2))
        self.counters["noise_bytes"] += int(len(a) - np.sum(le_ - ls + 1) - tail_len)
        fast_ok, fast_vals, fast_has = _fast_lines(a, ls, le_)
        sample_pos, sample_kind, sample_vals, others = _judged_lines(data, ls[~fast_ok], le_[~fast_ok], self.counters)
        fi = np.flatnonzero(fast_ok)
        pos = np.concatenate([ls[fi], np.array(sample_pos, np.int64)])
        kinds = np.concatenate([a[ls[fi] + 1], np.array(sample_kind, np.uint8)])
        fast = np.where(fast_has[fi, None], fast_vals[fi].astype(np.float64), np.nan)  # NaN accel: none sent
        vals = np.concatenate([fast, np.array(sample_vals, np.float64).reshape(-1, _WITH_ACCEL)])
        order = np.argsort(pos, kind="stable")
        vals = vals[order]
        ints = np.concatenate([fast_vals[fi, :7], np.array([v[:7] for v in sample_vals], np.int64).reshape(-1, 7)])[order]
        self._append(pos=pos[order] + at, kind=kinds[order], seq=ints[:, 0], ms=ints[:, 1], values=ints[:, 2:5],
                     st2=ints[:, 5], temp=ints[:, 6], accel=vals[:, 7:])
        self.others.extend((p + at, m) for p, m in others)

    def _append(self, **rows) -> None:
        m = len(rows["pos"])
        cap = len(self.cols["pos"])
        if self.n + m > cap:
            cap = max(self.n + m, 2 * cap)
            for c in self.cols.values():
                c.resize((cap, *c.shape[1:]), refcheck=False)  # in place: no second copy
        for name, c in self.cols.items():
            c[self.n : self.n + m] = rows[name]
        self.n += m

    def frames(self) -> Frames:
        for c in self.cols.values():
            c.resize((self.n, *c.shape[1:]), refcheck=False)
        cols, self.cols = self.cols, {}
        counters = self.counters
        events, keep_s, keep_o = _sequence(cols["pos"], cols["seq"], self.others, counters)
        if not keep_s.all():  # duplicates and out-of-sequence lines are not delivered
            for k in list(cols):  # one column at a time: the old one goes as the new one comes
                cols[k] = cols[k][keep_s]
        others = [o for o, k in zip(self.others, keep_o.tolist()) if k]
        counters["lines"] = len(cols["pos"]) + len(others)
        return Frames(**cols, others=sorted(others, key=lambda x: x[0]), events=events,
                      counters=+counters,  # drop zero entries, as the incremental framer never creates them
                      tail=self.tail)


def _fits(msg) -> bool:
    vals = (msg.seq, msg.ms, *(msg.raw if isinstance(msg, RawSample) else msg.field_nt), msg.st2, msg.temp_raw)
    return all(-(2**62) < v < 2**62 for v in vals) and all(-(2**53) < v < 2**53 for v in msg.accel or ())


def _sequence(pos: np.ndarray, seq: np.ndarray, others: list, counters: Counter):
    """Gaps and restarts over all messages in position order, by the ``SequenceTracker``
    rules: (events, which samples continue the stream, which others do). Vectorised while
    every step is a plain one (1 … MAX_DROPOUT ahead, or a restart); from the first line that
    is not, the tracker itself judges each line."""
    o_pos = np.array([p for p, _ in others], np.int64)
    o_seq = np.array([m.seq for _, m in others], np.int64)
    o_h0 = np.array([isinstance(m, Hello) and m.seq == 0 for _, m in others], bool)
    all_pos = np.concatenate([pos, o_pos])
    all_seq = np.concatenate([seq, o_seq])
    h0 = np.concatenate([np.zeros(len(pos), bool), o_h0])
    order = np.argsort(all_pos, kind="stable")
    all_pos, all_seq, h0 = all_pos[order], all_seq[order], h0[order]
    keep = np.ones(len(all_pos), bool)
    events: list[tuple[int, Frame]] = []
    if len(all_seq) >= 2:
        last, cur = all_seq[:-1], all_seq[1:]
        hello0 = h0[1:] & (last != SEQ_MOD - 1)
        ahead = (cur - last) % SEQ_MOD
        plain = hello0 | ((ahead >= 1) & (ahead <= MAX_DROPOUT))
        odd = np.flatnonzero(~plain)
        stop = int(odd[0]) if len(odd) else len(plain)  # steps 0 … stop-1 are plain
        hello0, ahead = hello0[:stop], ahead[:stop]
        gap = ~hello0 & (ahead > 1)
        counters["restarts"] += int(hello0.sum())
        counters["gaps"] += int(gap.sum())
        counters["lost_lines"] += int((ahead[gap] - 1).sum())
        for i in np.flatnonzero(hello0 | gap).tolist():
            at = int(all_pos[i + 1])
            events.append((at, Restart(0) if hello0[i] else Gap(int(cur[i]), int(ahead[i] - 1))))
        if len(odd):
            _track(all_pos, order, stop + 1, len(pos), others, seq, counters, events, keep)
    kept = np.empty(len(all_pos), bool)
    kept[order] = keep
    return events, kept[: len(pos)], kept[len(pos):]


def _track(all_pos, order, start, n_samples, others, seq, counters, events, keep) -> None:
    """The tracker over the messages from position-ordered index ``start`` on."""
    tracker = SequenceTracker()
    prev = order[start - 1]
    tracker.last = int(seq[prev] if prev < n_samples else others[prev - n_samples][1].seq)
    for k in range(start, len(order)):
        j = order[k]
        msg = _Seq(int(seq[j])) if j < n_samples else others[j - n_samples][1]
        out: list = []
        keep[k] = tracker.step(msg, counters, out)
        events.extend((int(all_pos[k]), e) for e in out)


@dataclass(frozen=True, slots=True)
class _Seq:
    """A sample line, as far as the sequence rules see it."""

    seq: int
