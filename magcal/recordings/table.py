"""Tables: a recording as delimited text (CSV, tab- or space-separated, with or without a header)
→ ``Series``, and ``Series`` → magcal's own CSV.

magcal's own CSV has a header row with ``mx,my,mz`` (µT) and optionally ``t`` (s); every other
numeric column is kept as a channel (``temp_c``, ``current_a`` …), a ``valid`` column of 0/1 is
the validity flag, and a text column is left out. ``save_csv`` writes ``t,mx,my,mz,temp_c`` then
the other channels, floats in shortest round-trip form, so loading it again gives the same bits.

Other people's tables are read with a ``TableFormat``:

* the delimiter is found from the first data line (comma, tab, semicolon, else white space);
* lines before the table that have fewer columns (``Fs,50.00``) are a preamble and skipped; a
  row of units under the header (``s,uT,uT,uT``) gives the units and is not data;
* a first line that is all numbers is data, not a header; its columns are named ``col1`` …
  (so is a column whose header cell is empty);
* the magnetometer columns: ``columns`` (three header names or 1-based positions), else
  ``mx,my,mz``, else one unambiguous triple of common names — ``mag_x``, ``magX``, ``m_x``,
  ``mag.x``, ``magnetometer_x``, ``compass_x``, ``imu_mx`` … (case-insensitive), possibly with a unit suffix
  (``mag_x_ut``, ``mx_gauss``, ``mag_x [mG]``). Bare ``x,y,z`` are not taken (they could be an
  accelerometer);
* the unit: ``unit`` (a name, or the µT of one unit of the file), else the suffix of the column
  names, else µT. A field far from any Earth field is a sign of a wrong unit; the commands that
  fit say so (``plausible_field``), the reader cannot know the field;
* the time column: ``time`` (name or position, with ``time_unit``), else ``t``, ``t_s``,
  ``time``, ``time_s``, ``timestamp`` (s), ``t_ms``, ``time_ms`` (ms), ``t_us``, ``time_us`` (µs);
  without one, the sample index;
* every other numeric column is a channel (a candidate covariate for diagnosis), except a
  second magnetometer's (it measures the same field); ``channels`` keeps only the ones named;
* ``temp`` and ``current`` name the columns diagnosis should take as the die temperature (°C)
  and the interfering current (A); they are read as ``temp_c`` and ``current_a``.

Every problem is an ``InputError`` naming the file, the line and what is wrong. ``row`` is the
0-based data row counted from the line after the header (from the first line when there is no
header); blank lines and lines starting with ``#`` are skipped but keep their place.
"""

from __future__ import annotations

import csv
import io
import math
import re
import warnings
from dataclasses import dataclass
from itertools import chain, islice

import numpy as np

from ..core.calibration import EARTH_FIELD_UT
from ..core.errors import InputError
from ..core.series import Series
from .atomic import write_atomic

NATIVE = ("mx", "my", "mz")

# µT per unit
UNITS_UT = {
    "ut": 1.0, "µt": 1.0, "μt": 1.0, "microtesla": 1.0,
    "nt": 1e-3, "nanotesla": 1e-3,
    "mg": 0.1, "mgauss": 0.1, "milligauss": 0.1,
    "g": 100.0, "gauss": 100.0, "ga": 100.0,
    "t": 1e6, "tesla": 1e6,
}
_UNIT_SHOWN = {1.0: "µT", 1e-3: "nT", 0.1: "mG", 100.0: "gauss", 1e6: "T"}
TIME_UNITS_S = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6}
_TIME_NAMES = {"t": "s", "t_s": "s", "time": "s", "time_s": "s", "timestamp": "s", "unix_time": "s",
               "t_ms": "ms", "time_ms": "ms", "timestamp_ms": "ms", "t_us": "us", "time_us": "us"}
_MAG_NAME = re.compile(
    r"^(?P<prefix>[a-z0-9]+[ _.\-])??(?P<stem>m|mag|magn|magnet|magnetometer|compass|b|h)[ _.\-]?(?P<axis>[xyz])"
    r"(?:[ _.\-]*[\[(]?(?P<unit>[a-zµμ]+)[\])]?)?$",
    re.IGNORECASE,
)
KNOWN_CHANNELS = ("temp_c", "current_a")  # diagnosis names these effects; taken in any case


@dataclass(frozen=True)
class TableFormat:
    """How to read a table. Every field left at None is worked out from the file."""

    columns: tuple | None = None  # three header names or 1-based positions (as text)
    unit: str | None = None  # a name in UNITS_UT or the µT of one unit, as text
    time: str | None = None  # header name or 1-based position
    channels: tuple | None = None  # the columns kept as channels (names or positions); None: all numeric
    temp: str | None = None  # the die temperature (°C) column, read as temp_c
    current: str | None = None  # the interfering current (A) column, read as current_a
    time_unit: str | None = None  # s, ms or us; None: from the time column's name, else s
    delimiter: str | None = None  # one character; None: found from the first line

    @property
    def explicit(self) -> bool:
        return any(v is not None for v in (self.columns, self.unit, self.time, self.time_unit, self.delimiter,
                                           self.channels, self.temp, self.current))

    def __post_init__(self):
        if self.columns is not None and len(self.columns) != 3:
            raise InputError(f"--columns needs three columns (x, y, z), got {len(self.columns)}: {','.join(self.columns)}")
        if self.unit is not None:
            unit_scale(self.unit)
        if self.delimiter is not None and len(self.delimiter) != 1:
            raise InputError(f"a column delimiter is one character, got {self.delimiter!r}")
        if self.time_unit is not None and self.time_unit not in TIME_UNITS_S:
            raise InputError(f"time unit {self.time_unit!r} is not one of {', '.join(TIME_UNITS_S)}")


def unit_scale(unit: str) -> float:
    """µT per unit of ``unit``: a name (``gauss``, ``mG``, ``nT`` …) or a positive number."""
    key = unit.strip().lower()
    if key in UNITS_UT:
        return UNITS_UT[key]
    try:
        v = float(key)
    except ValueError:
        raise InputError(
            f"unknown field unit {unit!r}: give one of uT, nT, mG, gauss, tesla, or the µT of one "
            "count (e.g. 0.3 for an AK8975)"
        ) from None
    if not (math.isfinite(v) and v > 0):
        raise InputError(f"field unit {unit!r}: µT per count must be a positive number")
    return v


def unit_guess(field_ut: float) -> str | None:
    """The unit (gauss, mG, nT) in which a field read as ``field_ut`` µT would be an Earth field."""
    lo, hi = EARTH_FIELD_UT
    return next((name for name, s in (("gauss", 100.0), ("mG", 0.1), ("nT", 1e-3)) if lo <= field_ut * s <= hi), None)


def plausible_field(field_ut: float) -> str | None:
    """None when ``field_ut`` could be the Earth's field, else a sentence saying which unit
    would make it one — for a recording read in the wrong unit."""
    lo, hi = EARTH_FIELD_UT
    if not math.isfinite(field_ut) or lo <= field_ut <= hi:
        return None
    said = f"the fitted field is {field_ut:.4g} µT, outside the Earth's {lo:.0f}–{hi:.0f} µT"
    guess = unit_guess(field_ut)
    if guess:
        return (f"{said}, so the file may be in another unit: read in {guess} it would be "
                f"{field_ut * UNITS_UT[guess.lower()]:.1f} µT (--unit {guess})")
    if field_ut < lo:
        return (f"{said}: the board may have hardly turned (a sphere of a few µT wraps a small cloud of "
                "samples: turn it through more directions), or the file is in another unit (--unit)")
    from .count_units import count_guess

    return f"{said}, so the file may hold raw counts: {count_guess(field_ut)}"


def _number(text: str) -> float | None:
    try:
        return float(text)
    except ValueError:
        return None


def _sniff(line: str) -> str | None:
    """The delimiter of one data line; None means runs of white space."""
    for d in (",", "\t", ";"):
        if d in line:
            return d
    return None


def _split(line: str, delimiter: str | None, name: str = "<table>", line_no: int = 0) -> list[str]:
    if delimiter is None:
        return line.split()
    try:
        return [c.strip() for c in next(csv.reader([line], delimiter=delimiter))]
    except csv.Error as exc:  # e.g. a field longer than the csv module's limit
        raise InputError(f"{name} line {line_no}: cannot split into columns: {exc}") from None


def _position(spec: str, cols: list[str], name: str, what: str) -> int:
    spec = spec.strip()
    if spec in cols:
        return cols.index(spec)
    if spec.isdigit():
        k = int(spec)
        if 1 <= k <= len(cols):
            return k - 1
        raise InputError(f"{name}: {what} column {k} does not exist (the table has {len(cols)} columns)")
    raise InputError(f"{name}: no {what} column {spec!r} (columns: {','.join(cols)})")


def _mag_triples(cols: list[str]) -> dict[tuple, dict]:
    """Every whole x/y/z triple of magnetometer-like names: (prefix, stem, unit) → {axis: position}."""
    triples: dict[tuple, dict] = {}
    for i, c in enumerate(cols):
        m = _MAG_NAME.match(c.strip())
        if m and (m["unit"] is None or m["unit"].lower() in UNITS_UT):
            key = ((m["prefix"] or "").lower(), m["stem"].lower(), (m["unit"] or "").lower())
            triples.setdefault(key, {})[m["axis"].lower()] = i
    return {k: v for k, v in triples.items() if len(v) == 3}


def _find_mag(cols: list[str], fmt: TableFormat, name: str, line_no: int) -> tuple[list[int], float | None]:
    """Positions of x, y, z and the unit their names carry (None: not said)."""
    if fmt.columns is not None:
        pos = [_position(c, cols, name, "magnetometer") for c in fmt.columns]
        return pos, None
    if all(c in cols for c in NATIVE):
        return [cols.index(c) for c in NATIVE], UNITS_UT["ut"]
    whole = _mag_triples(cols)
    if len(whole) == 1:
        (_, _, unit), axes = next(iter(whole.items()))
        return [axes["x"], axes["y"], axes["z"]], (UNITS_UT[unit] if unit else None)
    if len(whole) > 1:
        names = "; ".join(",".join(cols[i] for i in (v["x"], v["y"], v["z"])) for v in whole.values())
        raise InputError(f"{name} line {line_no}: more than one magnetometer triple ({names}); "
                         "choose one with --columns X,Y,Z")
    headerless = all(re.fullmatch(r"col\d+", c) for c in cols)
    if headerless and len(cols) == 3:
        return [0, 1, 2], None  # x y z and nothing else (Magneto's input, for one)
    if headerless:
        raise InputError(
            f"{name} line {line_no}: the first line is numbers, not a header; name the magnetometer "
            f"columns by position, e.g. --columns 1,2,3 (the table has {len(cols)} columns)"
        )
    missing = [c for c in NATIVE if c not in cols]
    raise InputError(
        f"{name} line {line_no}: header row lacks column(s) {', '.join(missing)} "
        f"(need mx,my,mz in µT, or name the columns with --columns X,Y,Z; found {','.join(cols)})"
    )


def _width(line: str, delimiter: str | None) -> int:
    return len(_split(line, delimiter))


def header_index(lines: list[str], delimiter: str | None = None, look: int = 20) -> int | None:
    """Index of the table's first line (its header, or its first data row) in ``lines``: the
    first non-comment line that has at least three columns and as many as the line after it.
    Lines before it are a preamble (``Fs,50.00``, ``Initialization time,60`` …) and are skipped.
    Falls back to the first non-comment line; None for an empty text."""
    idx = [i for i, ln in enumerate(lines[: 4 * look]) if ln.strip() and not ln.lstrip().startswith("#")][:look]
    if not idx:
        rest = next((i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")), None)
        return rest
    for a, b in zip(idx, idx[1:]):
        d = delimiter if delimiter is not None else _sniff(lines[b])
        wa = _width(lines[a], d)
        if wa >= 3 and wa == _width(lines[b], d):
            return a
    return idx[0]


def looks_like_table(lines: list[str]) -> bool:
    """Do these first lines hold a table of at least three columns?"""
    i = header_index(lines)
    return i is not None and _width(lines[i], _sniff(lines[i])) >= 3


def _find_time(cols: list[str], fmt: TableFormat, name: str) -> tuple[int | None, float]:
    if fmt.time is not None:
        return _position(fmt.time, cols, name, "time"), TIME_UNITS_S[fmt.time_unit or "s"]
    lower = [c.strip().lower() for c in cols]
    for alias, unit in _TIME_NAMES.items():
        if alias in lower:
            return lower.index(alias), TIME_UNITS_S[fmt.time_unit or unit]
    return None, 1.0


def _units_row(lines: list[str], hdr_i: int, delimiter: str | None, ncol: int, name: str = "<table>"):
    """(index, cells) of a row of units right under the header (``s,uT,uT,uT``), or None."""
    for i in range(hdr_i + 1, min(len(lines), hdr_i + 20)):
        ln = lines[i]
        if not ln.strip() or ln.lstrip().startswith("#"):
            continue
        cells = _split(ln, delimiter, name, i + 1)
        if len(cells) == ncol and all(c and _number(c) is None for c in cells):
            return i, cells
        return None
    return None


MAX_COLUMNS = 10_000  # a magnetometer log with more is not one this reader takes whole
MAX_LINE_CHARS = 1 << 20  # characters in one line (10 000 columns of 100 characters)
HEAD_LINES = 100  # the header, a preamble before it and a row of units are found in these
BLOCK_ROWS = 65536  # data rows converted to arrays at a time (bounds the Python objects held)


def parse_table(text: str, name: str = "<table>", fmt: TableFormat | None = None) -> Series:
    """Delimited text → Series (see the module docstring)."""
    return read_table(iter(text.splitlines()), name, fmt)


def _head(lines) -> tuple[list[str], int]:
    """(the first HEAD_LINES lines from the first one that is not blank or a comment, the number
    of lines before them) — blank and comment lines before a table are not kept."""
    skipped = 0
    for ln in lines:
        if ln.strip() and not ln.lstrip().startswith("#"):
            return [ln, *islice(lines, HEAD_LINES - 1)], skipped
        skipped += 1
    return [], skipped


def _not_too_long(ln: str, name: str, line_no: int) -> str:
    if len(ln) > MAX_LINE_CHARS:
        raise InputError(f"{name} line {line_no}: {len(ln.rstrip(chr(13) + chr(10)))} characters in one line, more than a table of at most "
                         f"{MAX_COLUMNS} columns holds ({MAX_LINE_CHARS}); is it a table with one line per sample?")
    return ln


@dataclass
class _Layout:
    """How the table's columns are to be read, as found from its head."""

    cols: list
    delimiter: str | None
    has_header: bool
    hdr_i: int  # index in the head of the last line before the data (-1: the data start at once)
    mag: list
    scale: float
    assumed_unit: bool
    t_col: int | None
    t_scale: float
    must: set
    keep: dict  # column → channel name, for every column that may become a channel
    renamed: dict  # column → temp_c / current_a, as --temp / --current named them


def read_table(lines, name: str = "<table>", fmt: TableFormat | None = None) -> Series:
    """Lines of delimited text (any iterator; read once, in bounded memory) → Series."""
    fmt = fmt or TableFormat()
    lines = iter(lines)
    head, skipped = _head(lines)
    for j, ln in enumerate(head):
        _not_too_long(ln, name, skipped + j + 1)
    lay = _layout(head, fmt, name, skipped)
    rest = chain(head[lay.hdr_i + 1:], lines)
    data, text_cols, rows = _read_rows(rest, skipped + lay.hdr_i + 1, lay, name)
    for k, as_name in lay.renamed.items():
        if k in text_cols:
            raise InputError(f"{name}: column {lay.cols[k]!r}, to be read as {as_name}, holds text, not numbers")
    n = len(rows)
    field = lay.scale * np.column_stack([data[k] for k in lay.mag])
    t = lay.t_scale * data[lay.t_col] if lay.t_col is not None else np.arange(n, dtype=np.float64)
    valid, channels = None, {}
    for k, as_name in lay.keep.items():
        if k in text_cols:
            continue
        if as_name == "valid":
            valid = data[k] != 0
        else:
            channels[as_name] = data[k]
    source = _describe([lay.cols[k] for k in lay.mag], lay.scale, lay.assumed_unit,
                       None if lay.t_col is None else (lay.cols[lay.t_col], lay.t_scale), list(channels))
    return Series(t_s=t, field_ut=field, channels=channels, valid=valid, row=rows, source=source,
                  clock=lay.t_col is not None, unit_assumed=lay.assumed_unit)


def _layout(head: list[str], fmt: TableFormat, name: str, skipped: int) -> _Layout:
    first = header_index(head, fmt.delimiter)
    if first is None:
        raise InputError(f"{name}: empty file (no header row)")
    delimiter = fmt.delimiter if fmt.delimiter is not None else _sniff(head[first])
    if delimiter is not None and delimiter.strip() == "" and delimiter != "\t":
        delimiter = None
    cells = _split(head[first], delimiter, name, skipped + first + 1)
    if len(cells) > MAX_COLUMNS:
        raise InputError(f"{name} line {skipped + first + 1}: {len(cells)} columns, more than {MAX_COLUMNS}; keep the "
                         "columns you need (e.g. cut -d, -f7-10 FILE) and read that")
    has_header = any(_number(c) is None for c in cells)
    cols = [c if c else f"col{k + 1}" for k, c in enumerate(cells)] if has_header else \
        [f"col{k + 1}" for k in range(len(cells))]
    hdr_i = first if has_header else first - 1
    mag, named_unit = _find_mag(cols, fmt, name, skipped + first + 1)
    t_col, t_scale = _find_time(cols, fmt, name)
    if has_header:
        seen, dup = set(), set()
        for c in cols:
            (dup if c in seen else seen).add(c)
        if dup:
            raise InputError(f"{name} line {skipped + hdr_i + 1}: duplicate column(s) {', '.join(sorted(dup)[:10])}")
    if len(set(mag)) != 3 or (t_col is not None and t_col in mag):
        raise InputError(f"{name}: the magnetometer and time columns must be different columns")
    units_row = _units_row(head, hdr_i, delimiter, len(cols), name) if has_header else None
    if units_row is not None:
        hdr_i, unit_cells = units_row
        said = {unit_cells[k].strip("[]() ").lower() for k in mag}
        if named_unit is None and len(said) == 1 and next(iter(said)) in UNITS_UT:
            named_unit = UNITS_UT[next(iter(said))]
        t_unit = unit_cells[t_col].strip("[]() ").lower() if t_col is not None else ""
        if fmt.time_unit is None and t_unit in TIME_UNITS_S:
            t_scale = TIME_UNITS_S[t_unit]
    scale = unit_scale(fmt.unit) if fmt.unit is not None else (named_unit or 1.0)
    must = set(mag) | ({t_col} if t_col is not None else set())
    keep, renamed = _channels(cols, fmt, name, mag, must)
    return _Layout(cols, delimiter, has_header, hdr_i, mag, scale, fmt.unit is None and named_unit is None,
                   t_col, t_scale, must, keep, renamed)


def _channels(cols: list, fmt: TableFormat, name: str, mag: list, must: set) -> tuple[dict, dict]:
    """(column → the name it is kept under: a channel, ``valid``, or temp_c/current_a when
    named by --temp/--current; the renamed ones). The other columns are not kept."""
    other_mags = {i for tri in _mag_triples(cols).values() for i in tri.values()} - set(mag)
    index = {c: k for k, c in enumerate(cols)}
    if all(c in index for c in NATIVE):
        other_mags |= {index[c] for c in NATIVE} - set(mag)
    wanted = None
    if fmt.channels is not None:
        wanted = {_position(c, cols, name, "channel") for c in fmt.channels if c.strip()}
    renamed = {}
    for spec, as_name in ((fmt.temp, "temp_c"), (fmt.current, "current_a")):
        if spec is not None:
            k = _position(spec, cols, name, as_name)
            if k in must or k in renamed:
                raise InputError(f"{name}: column {cols[k]!r} cannot be both {as_name} and another column")
            renamed[k] = as_name
    keep = {}
    for k, c in enumerate(cols):
        if k in must:
            continue
        if c == "valid" or k in renamed:
            keep[k] = "valid" if c == "valid" else renamed[k]
            continue
        if (wanted is not None and k not in wanted) or (wanted is None and k in other_mags):
            continue
        known = c.lower() if c.lower() in KNOWN_CHANNELS and c.lower() not in index else c
        if known not in renamed.values():  # the column given by --temp/--current takes the name
            keep[k] = known
    return keep, renamed


def _read_rows(lines, first_no: int, lay: _Layout, name: str):
    """The data rows (``lines``, the first being line ``first_no + 1`` of the file): (an array
    per column, text columns, 0-based data row of each sample). A column whose first value is
    text is a text column (not a channel); a required column must hold a finite number on every
    row. Rows are taken in blocks; a block is read at once when it is plain numbers, else line by
    line, which names the first line that is wrong."""
    ncol = len(lay.cols)
    blocks: list[list[np.ndarray]] = [[] for _ in range(ncol)]
    text_cols: set[int] | None = None
    rows: list[np.ndarray] = []
    block: list[str] = []
    at: list[int] = []
    for i, ln in enumerate(lines, start=first_no):
        if not _not_too_long(ln, name, i + 1).strip() or ln.lstrip().startswith("#"):
            continue
        block.append(ln)
        at.append(i)
        if len(block) == BLOCK_ROWS:
            text_cols = _take_block(block, at, lay, name, blocks, text_cols)
            rows.append(np.array(at, np.int64) - first_no)
            block, at = [], []
    if block:
        text_cols = _take_block(block, at, lay, name, blocks, text_cols)
        rows.append(np.array(at, np.int64) - first_no)
    if not rows:
        raise InputError(f"{name}: no data rows after the header (line {first_no})")
    data = {}
    for k in range(ncol):
        if k not in text_cols and (k in lay.must or k in lay.keep):
            data[k] = np.concatenate(blocks[k])
        blocks[k] = []
    return data, text_cols, np.concatenate(rows)


def _take_block(block, at, lay: _Layout, name: str, blocks, text_cols):
    """Append one block's values to ``blocks`` (per column); returns the text columns (decided
    by the first data row, so the first block too is read at once when it is plain numbers)."""
    decided = text_cols if text_cols is not None else _rows_one_by_one(block[:1], at[:1], lay, name, None)[1]
    values = _plain_block(block, lay, decided)
    if values is not None:
        for k, col in values.items():
            blocks[k].append(col)
        return decided
    values, text_cols = _rows_one_by_one(block, at, lay, name, text_cols)
    for k, col in values.items():
        blocks[k].append(np.array(col, np.float64))
    return text_cols


def _plain_block(block, lay: _Layout, text_cols: set) -> dict | None:
    """The block's numeric columns at once, when every cell is a number and every required one
    finite; else None (the block is then read line by line)."""
    use = [k for k in range(len(lay.cols)) if k not in text_cols and (k in lay.must or k in lay.keep)]
    if not use:
        return {}
    text = dict.fromkeys(text_cols, _zero)  # parsed for their place only: the count is checked
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # an empty block or a short line: not plain
            a = np.loadtxt(block, delimiter=lay.delimiter, dtype=np.float64, ndmin=2, comments=None,
                           converters=text or None, quotechar='"' if lay.delimiter is not None else None)
    except (ValueError, UserWarning):
        return None
    if a.shape != (len(block), len(lay.cols)):
        return None
    out = {k: a[:, k].copy() for k in use}
    if not all(np.isfinite(out[k]).all() for k in lay.must):
        return None
    return out


def _zero(_cell) -> float:
    return 0.0


def _rows_one_by_one(block, at, lay: _Layout, name: str, text_cols):
    ncol = len(lay.cols)
    data: dict[int, list[float]] = {k: [] for k in range(ncol)}
    first = text_cols is None
    text_cols = set() if text_cols is None else set(text_cols)
    for ln, i in zip(block, at):
        row_cells = _split(ln, lay.delimiter, name, i + 1)
        if len(row_cells) != ncol:
            what = "the header has" if lay.has_header else "the first line has"
            raise InputError(f"{name} line {i + 1}: {len(row_cells)} values, {what} {ncol}")
        for k, cell in enumerate(row_cells):
            if k in text_cols:
                continue
            v = _number(cell) if cell else math.nan
            if v is None or (k in lay.must and not cell):
                if k in lay.must:
                    problem = "is empty" if not cell else f"{_short(cell)} is not a number"
                    raise InputError(f"{name} line {i + 1}: column {_short(lay.cols[k])}: {problem}")
                if first and not data[k]:  # a text column: not a channel
                    text_cols.add(k)
                    continue
                raise InputError(f"{name} line {i + 1}: column {_short(lay.cols[k])}: {_short(cell)} is not a number")
            if k in lay.must and not math.isfinite(v):
                raise InputError(f"{name} line {i + 1}: column {_short(lay.cols[k])}: {_short(cell)} is not finite")
            data[k].append(v)
        first = False
    return {k: v for k, v in data.items() if k not in text_cols and (k in lay.must or k in lay.keep)}, text_cols


def _short(text) -> str:
    text = repr(text)
    return text if len(text) <= 40 else text[:37] + "…"


def _describe(mag_names, scale, assumed, time_col, channels) -> str:
    """How a table was read, in one line for the user to check."""
    unit = _UNIT_SHOWN.get(scale) or f"units of {scale:g} µT"
    if time_col is None:
        when = "no time column: sample index"
    else:
        t_unit = next((k for k, v in TIME_UNITS_S.items() if v == time_col[1]), f"{time_col[1]:g} s")
        when = f"time from {time_col[0]} ({t_unit})"
    return (f"field from {','.join(mag_names)} in {unit}" + (" (assumed: no unit given)" if assumed else "")
            + f"; {when}; " + (f"channels {', '.join(channels)}" if channels else "no channels"))


def parse_csv(text: str, name: str = "<csv>") -> Series:
    """magcal's own CSV (``mx,my,mz`` µT) or any table whose columns can be found by name."""
    return parse_table(text, name, TableFormat(delimiter=","))


def load_table(path, fmt: TableFormat | None = None) -> Series:
    """A table file, read line by line: memory bounded by the samples it holds, time linear
    in its size."""
    try:
        with open(path, "r", encoding="utf-8-sig") as fh:
            return read_table(fh, str(path), fmt)
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read as text: {getattr(exc, 'strerror', None) or exc}") from exc


def load_csv(path) -> Series:
    return load_table(path, TableFormat(delimiter=","))


def _fmt(v: float) -> str:
    return "" if v != v else repr(float(v))


def save_csv(series: Series, path) -> list[str]:
    """Write ``t,mx,my,mz,temp_c`` (µT, °C), then the other channels, then ``valid`` when any
    sample is flagged invalid. Floats in shortest round-trip form (``load_csv`` reads back the
    same bits). Missing temperature → the column is left out. What reading the source assumed
    stays assumed: no ``t`` when its time was the sample index (``Series.clock``), and the field
    as ``mag_x,mag_y,mag_z`` (no unit named, so µT is assumed again) when its unit was a guess."""
    field = ["mag_x", "mag_y", "mag_z"] if series.unit_assumed else ["mx", "my", "mz"]
    names = (["t"] if series.clock else []) + field
    cols = ([series.t_s] if series.clock else []) + [series.field_ut[:, 0], series.field_ut[:, 1],
                                                     series.field_ut[:, 2]]
    ch = dict(series.channels)
    if "temp_c" in ch:
        names.append("temp_c")
        cols.append(ch.pop("temp_c"))
    for k in sorted(ch):
        names.append(k)
        cols.append(ch[k])
    with_valid = not bool(np.all(series.valid))
    buf = io.StringIO()
    buf.write(",".join(names + (["valid"] if with_valid else [])) + "\n")
    lists = [c.tolist() for c in cols]
    vl = series.valid.tolist()
    for i in range(len(series)):
        row = [_fmt(c[i]) for c in lists]
        if with_valid:
            row.append("1" if vl[i] else "0")
        buf.write(",".join(row) + "\n")
    try:
        write_atomic(path, buf.getvalue().encode("utf-8"))
    except OSError as exc:
        raise InputError(f"{path}: cannot write: {exc.strerror or exc}") from exc
    return names + (["valid"] if with_valid else [])
