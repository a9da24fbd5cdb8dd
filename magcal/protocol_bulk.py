"""Bulk framing: a whole recorded byte stream → the same messages as ``protocol.Framer``, fast.

``parse_stream(data)`` gives exactly what a fresh ``Framer`` gives when fed ``data`` in any
chunking (items and counters; the property tests hold the two together), but does the work
with numpy so that replaying an hour of 100 Hz data takes a fraction of a second:

1. every ``$`` opens a run that ends at the next ``$`` or ``\\n`` (positions by vectorised
   search); runs are sorted into complete lines, torn runs, over-long runs and the unfinished
   tail, and ``noise_bytes`` is everything that is not a complete line or the tail;
2. complete ``S``/``U`` lines are grouped by length, so each group is a rectangular byte
   matrix: printability, the ``*CC`` position, the CRC-8 (one table lookup per column across
   all lines of the group) and the seven decimal fields (digit weights summed per token) are
   checked and parsed column-wise;
3. any line the fast path does not accept — other message types, odd but legal spellings,
   numbers too long for int64, and every defective line — is judged by
   ``protocol.classify_line``, the same function the incremental framer uses, so defects are
   named identically;
4. sequence gaps and restarts are computed from the merged, position-ordered sequence numbers
   with the ``SequenceTracker`` rule.

Pure: bytes in, arrays out; no I/O.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from .protocol import (
    MAX_LINE,
    SEQ_MOD,
    CRC8_TABLE_NP,
    CalibratedSample,
    Gap,
    Hello,
    Item,
    Message,
    RawSample,
    Restart,
    classify_line,
)

_DOLLAR, _NL, _CR, _COMMA, _STAR = 0x24, 0x0A, 0x0D, 0x2C, 0x2A
_MAX_DIGITS = 18  # a decimal token of at most 18 digits fits int64 exactly
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
    others: list[tuple[int, Message]]  # (position, message) for every non-sample message
    events: list[tuple[int, Item]]  # (position of the message it precedes, Gap | Restart)
    counters: Counter = field(default_factory=Counter)
    tail: bytes = b""

    def __len__(self) -> int:
        return len(self.pos)

    def items(self) -> list[Item]:
        """Everything in order, as the incremental framer returns it (for tests and tools)."""
        seq = self.seq.tolist()
        ms = self.ms.tolist()
        vals = self.values.tolist()
        st2 = self.st2.tolist()
        temp = self.temp.tolist()
        kinds = self.kind.tolist()
        merged: list[tuple[int, int, object]] = []
        for k, p in enumerate(self.pos.tolist()):
            cls = RawSample if kinds[k] == ord("S") else CalibratedSample
            merged.append((p, 1, cls(seq[k], ms[k], tuple(vals[k]), st2[k], temp[k])))
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


def _fast_group(a: np.ndarray, starts: np.ndarray, le: int):
    """Lines of effective length ``le`` (no '\\r') starting at ``starts``, all beginning with
    ``$S,`` or ``$U,``: returns (ok mask, values (k, 7) int64)."""
    k = len(starts)
    m = a[starts[:, None] + np.arange(le)]  # (k, le) uint8
    ok = np.all((m >= 32) & (m < 127), axis=1)
    ok &= m[:, le - 3] == _STAR
    h1 = _HEXVAL[m[:, le - 2]]
    h0 = _HEXVAL[m[:, le - 1]]
    ok &= (h1 >= 0) & (h0 >= 0)
    crc = np.zeros(k, np.uint8)
    for j in range(1, le - 3):
        crc = CRC8_TABLE_NP[crc ^ m[:, j]]
    ok &= crc.astype(np.int16) == (h1 * 16 + h0)
    # the seven decimal tokens after "S," with a closing comma appended
    f = np.empty((k, le - 5), np.uint8)
    f[:, :-1] = m[:, 3 : le - 3]
    f[:, -1] = _COMMA
    w = f.shape[1]
    comma = f == _COMMA
    digit = (f >= 0x30) & (f <= 0x39)
    sign = (f == 0x2B) | (f == 0x2D)
    ok &= np.all(comma | digit | sign, axis=1)
    ok &= comma.sum(axis=1) == 7
    prev = np.empty_like(f)
    prev[:, 0] = _COMMA
    prev[:, 1:] = f[:, :-1]
    start = prev == _COMMA
    ok &= ~np.any(sign & ~start, axis=1)  # a sign only opens a token
    prev_digit = np.zeros_like(comma)
    prev_digit[:, 1:] = digit[:, :-1]
    ok &= ~np.any(comma & ~prev_digit, axis=1)  # every token ends with a digit
    cols = np.arange(w)
    nxt = np.where(comma, cols, w)
    nxt = np.minimum.accumulate(nxt[:, ::-1], axis=1)[:, ::-1]  # next comma at or after
    expo = nxt - cols - 1
    ok &= ~np.any(digit & (expo >= _MAX_DIGITS), axis=1)
    vals = np.zeros((k, 7), np.int64)
    if not ok.any():
        return ok, vals
    sel = np.flatnonzero(ok)
    fs, dg, ex, st = f[sel], digit[sel], np.clip(expo[sel], 0, _MAX_DIGITS - 1), start[sel]
    pw = 10 ** np.arange(_MAX_DIGITS, dtype=np.int64)
    contrib = np.where(dg, (fs.astype(np.int64) - 0x30) * pw[ex], 0)
    flat = contrib.reshape(-1)
    tok_start = np.flatnonzero(st.reshape(-1))  # exactly 7 per line, in order
    sums = np.add.reduceat(flat, tok_start).reshape(len(sel), 7)
    neg = (fs.reshape(-1)[tok_start] == 0x2D).reshape(len(sel), 7)
    v = np.where(neg, -sums, sums)
    good = (v[:, 0] >= 0) & (v[:, 0] < SEQ_MOD)
    ok[sel[~good]] = False
    vals[sel] = v
    return ok, vals


def parse_stream(data: bytes) -> Frames:
    """Parse a whole byte stream as a fresh ``Framer`` would (see the module docstring)."""
    a = np.frombuffer(bytes(data), np.uint8)
    n = len(a)
    counters: Counter = Counter()
    starts, ends, kind = _runs(a)
    line = kind == 0
    ls, le_ = starts[line], ends[line]
    tail = b""
    tail_len = 0
    if len(kind) and kind[-1] == 3:
        tail = bytes(a[starts[-1] :])
        tail_len = len(tail)
    counters["torn_lines"] = int(np.sum(kind == 1))
    counters["overlong_lines"] = int(np.sum(kind == 2))
    counters["noise_bytes"] = int(n - np.sum(le_ - ls + 1) - tail_len)

    # effective length without a trailing '\r'
    eff = le_ - ls
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
    fast_vals = np.zeros((len(ls), 7), np.int64)
    ci = np.flatnonzero(cand)
    for le in np.unique(eff[ci]):
        grp = ci[eff[ci] == le]
        for b in range(0, len(grp), _BLOCK):
            g = grp[b : b + _BLOCK]
            ok, vals = _fast_group(a, ls[g], int(le))
            fast_ok[g] = ok
            fast_vals[g] = vals

    # everything else is judged by the incremental framer's own line judge
    sample_pos: list[int] = []
    sample_kind: list[int] = []
    sample_vals: list[tuple] = []
    others: list[tuple[int, Message]] = []
    raw = bytes(data)
    for idx in np.flatnonzero(~fast_ok).tolist():
        p, e = int(ls[idx]), int(le_[idx])
        msg = classify_line(raw[p:e])
        if isinstance(msg, str):
            counters[msg] += 1
        elif isinstance(msg, (RawSample, CalibratedSample)) and _fits(msg):
            sample_pos.append(p)
            sample_kind.append(ord("S") if isinstance(msg, RawSample) else ord("U"))
            v = msg.raw if isinstance(msg, RawSample) else msg.field_nt
            sample_vals.append((msg.seq, msg.ms, *v, msg.st2, msg.temp_raw))
        else:
            others.append((p, msg))

    fi = np.flatnonzero(fast_ok)
    pos = np.concatenate([ls[fi], np.array(sample_pos, np.int64)])
    kinds = np.concatenate([a[ls[fi] + 1], np.array(sample_kind, np.uint8)])
    vals = np.concatenate([fast_vals[fi], np.array(sample_vals, np.int64).reshape(-1, 7)])
    order = np.argsort(pos, kind="stable")
    pos, kinds, vals = pos[order], kinds[order], vals[order]

    events = _sequence(pos, vals[:, 0], others, counters)
    counters["lines"] = len(pos) + len(others)
    counters = +counters  # drop zero entries, as the incremental framer never creates them
    return Frames(
        pos=pos,
        kind=kinds.astype(np.uint8),
        seq=vals[:, 0].copy(),
        ms=vals[:, 1].copy(),
        values=vals[:, 2:5].copy(),
        st2=vals[:, 5].copy(),
        temp=vals[:, 6].copy(),
        others=sorted(others, key=lambda x: x[0]),
        events=events,
        counters=counters,
        tail=tail,
    )


def _fits(msg) -> bool:
    vals = (msg.seq, msg.ms, *(msg.raw if isinstance(msg, RawSample) else msg.field_nt), msg.st2, msg.temp_raw)
    return all(-(2**62) < v < 2**62 for v in vals)


def _sequence(pos: np.ndarray, seq: np.ndarray, others: list, counters: Counter) -> list:
    """Gaps and restarts over all messages in position order (the SequenceTracker rule)."""
    o_pos = np.array([p for p, _ in others], np.int64)
    o_seq = np.array([m.seq for _, m in others], np.int64)
    o_h0 = np.array([isinstance(m, Hello) and m.seq == 0 for _, m in others], bool)
    all_pos = np.concatenate([pos, o_pos])
    all_seq = np.concatenate([seq, o_seq])
    h0 = np.concatenate([np.zeros(len(pos), bool), o_h0])
    order = np.argsort(all_pos, kind="stable")
    all_pos, all_seq, h0 = all_pos[order], all_seq[order], h0[order]
    if len(all_seq) < 2:
        return []
    last = all_seq[:-1]
    cur = all_seq[1:]
    at = all_pos[1:]
    hello0 = h0[1:] & (last != SEQ_MOD - 1)
    lost = (cur - last - 1) % SEQ_MOD
    gap = ~hello0 & (lost != 0)
    counters["restarts"] += int(hello0.sum())
    counters["gaps"] += int(gap.sum())
    counters["lost_lines"] += int(lost[gap].sum())
    events: list[tuple[int, Item]] = []
    for i in np.flatnonzero(hello0 | gap).tolist():
        if hello0[i]:
            events.append((int(at[i]), Restart(0)))
        else:
            events.append((int(at[i]), Gap(int(cur[i]), int(lost[i]))))
    return events
