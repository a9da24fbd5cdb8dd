"""The results of ``magcal fleet``: a Parquet dataset, one file per analysed log, written as
each log finishes.

``RESULTS/rows/<sha256>-<magcal version>.parquet`` holds the rows of the log whose content has
that hash, analysed by that version; it is written under a dot-name and renamed into place, so a
file is there whole or not at all (``recordings.atomic``: a run killed mid-write leaves only a
``.<name>.*.tmp`` file, which readers of the dataset skip — pyarrow ignores names starting with
"." — and the next run removes). A
log whose key is already there is not analysed again: a killed run restarted ends with the same
files, no row twice, and a re-run after new flights analyses only the new ones. Any Parquet
reader opens the folder as one table (``pyarrow.dataset.dataset(RESULTS/rows)``, pandas,
DuckDB, Spark).
"""

from __future__ import annotations

import os

from ...recordings.atomic import TMP_SUFFIX, write_atomic
from .analyse import ROW_FIELDS, TERMS

ROWS_DIR = "rows"
_VEC = ("offset_ut", "sigma_offset_ut", "soft_iron") + tuple(
    k for t in TERMS for k in (f"{t}_ut_per_unit", f"sigma_{t}_ut_per_unit"))
_INT = ("mag_index", "device_id", "n_samples", "n_used")
_FLOAT = ("flight_year", "duration_s", "field_ut", "sigma_field_ut", "rms_ut", "coverage") + tuple(
    f"{t}_p_value" for t in TERMS)
_BOOL = ("external",) + tuple(f"{t}_kept" for t in TERMS)


def _pyarrow():
    try:
        import pyarrow
        import pyarrow.parquet  # noqa: F401
    except ImportError as exc:
        from ...core.errors import ConfigError

        raise ConfigError("magcal fleet keeps its results with pyarrow, from the optional extra 'fleet': "
                          "pip install 'magcal-mpu9150[fleet]'") from exc
    return pyarrow


def schema():
    pa = _pyarrow()

    def typ(name):
        if name in _VEC:
            return pa.list_(pa.float64())
        if name in _INT:
            return pa.int64()
        if name in _FLOAT:
            return pa.float64()
        return pa.bool_() if name in _BOOL else pa.string()

    return pa.schema([(n, typ(n)) for n in ROW_FIELDS])


def key_name(sha256: str, version: str) -> str:
    return f"{sha256}-{version}.parquet"


class ResultStore:
    """The dataset folder: which keys are done, one log's rows written whole, every row read."""

    def __init__(self, root: str):
        self.root = root
        self.rows_dir = os.path.join(root, ROWS_DIR)
        os.makedirs(self.rows_dir, exist_ok=True)
        for f in os.listdir(self.rows_dir):  # a write a killed run left unfinished
            if f.startswith(".") and f.endswith(TMP_SUFFIX):
                os.remove(os.path.join(self.rows_dir, f))

    def done(self) -> set[str]:
        return {f for f in os.listdir(self.rows_dir) if f.endswith(".parquet") and not f.startswith(".")}

    def has(self, sha256: str, version: str) -> bool:
        return os.path.exists(os.path.join(self.rows_dir, key_name(sha256, version)))

    def write(self, sha256: str, version: str, rows: list[dict]) -> str:
        pa = _pyarrow()
        import pyarrow.parquet as pq

        buf = pa.BufferOutputStream()
        pq.write_table(pa.Table.from_pylist(rows, schema=schema()), buf)
        final = os.path.join(self.rows_dir, key_name(sha256, version))
        write_atomic(final, buf.getvalue().to_pybytes())
        return final

    def rows(self) -> list[dict]:
        """Every row, ordered by file then magnetometer."""
        _pyarrow()
        import pyarrow.dataset as ds

        if not self.done():
            return []
        out = ds.dataset(self.rows_dir, format="parquet", schema=schema()).to_table().to_pylist()
        return sorted(out, key=lambda r: (r["path"], r["mag_index"], r["file_sha256"]))
