"""Settings: YAML → frozen dataclasses, validated, with one precedence order.

    built-in defaults  <  config file  <  environment (MAGCAL_*)  <  command line

Every input is checked at this edge before any is merged: the file (it exists, is a readable
text file of at most ``MAX_FILE_BYTES``, is YAML, holds a mapping with text keys), each
environment variable on its own, and the command-line values. Unknown keys are rejected with a
message naming them (and the keys that are allowed); wrong types, numbers that are not finite,
out-of-range values and malformed lists name the key, the value and where it was set (the file,
the variable, the command line). Each setting's bounds are declared with it
(``core.bounds.setting``).

Environment variables address keys by path with ``__`` between levels:
``MAGCAL_PORT=/dev/ttyACM0``, ``MAGCAL_GATES__MIN_COVERAGE=0.5``; a text setting takes the
variable's value as it is, any other is parsed as a YAML scalar or list.

``config/magcal.yaml`` documents every key with its default.
"""

from __future__ import annotations

import dataclasses
import enum
import os
import re
import reprlib
import typing
from dataclasses import dataclass
from typing import Any, Mapping

import yaml

from ..core.bounds import check_bounds, setting
from ..core.errors import ConfigError
from ..logic.gates import Gates
from ..wire.dialect import Dialect

MAX_FILE_BYTES = 1 << 20  # the documented file is ~3 KB
MAX_TEXT = 4096  # characters in a port or a path
# PyYAML builds nested collections by recursion, one Python frame and more per level, so a file
# of "[[[[…" makes it walk the stack to the recursion limit before it fails (seconds, and
# minutes where the limit is raised); the settings nest three levels (a list in a section), and
# the text is checked for depth in one linear pass first
MAX_DEPTH = 32
_short = reprlib.Repr()
_short.maxstring, _short.maxother, _short.maxlevel, _short.maxlist, _short.maxdict = 40, 40, 2, 4, 4


class Keep(enum.Enum):
    """How the service keeps the device calibrated (``daemon.keep``)."""

    TRACKER = "tracker"  # write the tracker's calibration when it is significantly better than the device's
    ALARM = "alarm"  # refit and write only after the drift monitor rings


@dataclass(frozen=True)
class DaemonSettings:
    """The long-running service (``magcal run``)."""

    state_dir: str = ""  # empty: the user's state directory, $XDG_STATE_HOME/magcal or ~/.local/state/magcal
    recalibrate: bool = False  # collect, refit and write back when the calibration stops fitting
    monitor_window: int = setting(500, lo=40, hi=100_000)  # samples per drift test window
    monitor_alpha: float = setting(0.001, lo=0, lo_open=True, hi=0.5, hi_open=True)  # false-alarm probability
    reconnect_min_s: float = setting(0.5, lo=0, lo_open=True, hi=3600)
    reconnect_max_s: float = setting(30.0, lo=0, lo_open=True, hi=86400)
    # rolling capture size bound; 0 = no capture
    capture_max_bytes: int = setting(0, lo=0, hi=1 << 40)
    state_every_s: float = setting(5.0, lo=0, lo_open=True, hi=86400)  # how often the state file is written
    socket: bool = True  # local UNIX status socket in state_dir
    stall_s: float = setting(5.0, lo=0, lo_open=True, hi=86400)  # no sample for this long on an open link ⇒ reconnect
    # how a written calibration is kept: "tracker" writes the tracker's when it is significantly
    # better than the device's (gates and budget permitting); "alarm" only after the monitor rings
    keep: Keep = Keep.TRACKER
    # EEPROM writes the keeper may spend (ATmega328P: 100 000 cycles rated): per day, back to back
    write_budget_per_day: float = setting(24.0, lo=0, lo_open=True, hi=1440)
    write_burst: int = setting(3, lo=1, hi=100)

    def check(self) -> None:
        check_bounds(self, "daemon.")
        if self.reconnect_max_s < self.reconnect_min_s:
            raise ConfigError(f"daemon.reconnect_max_s ({self.reconnect_max_s:g}) must be ≥ daemon.reconnect_min_s "
                              f"({self.reconnect_min_s:g})", keys=("daemon.reconnect_min_s", "daemon.reconnect_max_s"))
        if 0 < self.capture_max_bytes < CAPTURE_MIN_BYTES:
            raise ConfigError(f"daemon.capture_max_bytes must be 0 (no capture) or at least {CAPTURE_MIN_BYTES}, "
                              f"got {self.capture_max_bytes}", keys=("daemon.capture_max_bytes",))


CAPTURE_MIN_BYTES = 4096  # a capture header and a few chunks


@dataclass(frozen=True)
class Settings:
    port: str = ""  # no default device: --port, MAGCAL_PORT, this key, or the one plugged in
    dialect: Dialect = Dialect.NATIVE  # native | motioncal | auto
    baud: int = setting(115200, lo=50, hi=4_000_000)
    rate_hz: int = setting(50, lo=1, hi=100, why="the AK8975 needs ≥ 10 ms per measurement")
    model: str = "auto"  # sphere | ellipsoid | auto
    timeout_s: float = setting(120.0, lo=0, lo_open=True, hi=1e7)
    write: bool = True
    gates: Gates = dataclasses.field(default_factory=Gates)
    daemon: DaemonSettings = dataclasses.field(default_factory=DaemonSettings)

    def check(self) -> None:
        check_bounds(self)
        if self.model not in ("sphere", "ellipsoid", "auto"):
            raise ConfigError(f"model must be sphere, ellipsoid or auto, got {self.model!r}", keys=("model",))
        self.gates.check()
        self.daemon.check()


# -- types ---------------------------------------------------------------------------------------
def _show(value) -> str:
    return _short.repr(value)


def _text(value, key: str, empty_ok: bool = False) -> str:
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise ConfigError(f"{key} must be text, got {_show(value)}")
    text = str(value)
    if (not text and not empty_ok) or len(text) > MAX_TEXT or any(ord(c) < 32 or ord(c) == 127 for c in text):
        raise ConfigError(f"{key} must be {'' if empty_ok else 'non-empty '}text of printable characters (at most "
                          f"{MAX_TEXT}), got {_show(value)}")
    return text


def _choice(value, typ: type[enum.Enum], key: str) -> enum.Enum:
    if isinstance(value, typ):
        return value
    names = [m.value for m in typ]
    if isinstance(value, str) and value in names:
        return typ(value)
    raise ConfigError(f"{key} must be {' or '.join(names)}, got {_show(value)}", keys=(key,))


_EXPONENT_NUMBER = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d{1,3}")


def _scalar(value, typ, key: str, empty_ok: bool = False):
    if isinstance(typ, type) and issubclass(typ, enum.Enum):
        return _choice(value, typ, key)
    if typ is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{key} must be true or false, got {_show(value)}")
    if typ is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ConfigError(f"{key} must be an integer, got {_show(value)}")
    if typ is float:
        if isinstance(value, str) and _EXPONENT_NUMBER.fullmatch(value.strip()):
            value = float(value)  # YAML 1.1 reads 1e-3 (no dot) as text; it is a number
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            try:
                return float(value)
            except OverflowError:
                raise ConfigError(f"{key} must be a finite number, got {_show(value)}") from None
        raise ConfigError(f"{key} must be a number, got {_show(value)}")
    return _text(value, key, empty_ok)


def _coerce(value: Any, typ, key: str, empty_ok: bool = False):
    if dataclasses.is_dataclass(typ):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key} must be a mapping of settings, got {_show(value)}")
        return _build(typ, value, key + ".")
    if typing.get_origin(typ) is tuple:
        args = typing.get_args(typ)
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            raise ConfigError(f"{key} must be a list of {len(args)} numbers, got {_show(value)}")
        return tuple(_scalar(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    return _scalar(value, typ, key, empty_ok)


def _build(cls, data: Mapping, prefix: str = ""):
    fields = {f.name: f for f in dataclasses.fields(cls)}
    bad = [k for k in data if not isinstance(k, str)]
    if bad:
        raise ConfigError(f"setting names are text; {'the top level' if not prefix else prefix[:-1]} has the key "
                          f"{_show(bad[0])} ({type(bad[0]).__name__})")
    unknown = sorted(set(data) - set(fields))
    if unknown:
        names = ", ".join(prefix + _show(k)[1:-1] for k in unknown[:5])
        raise ConfigError(f"unknown setting(s): {names} (allowed here: {', '.join(sorted(fields))})")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, f in fields.items():
        if name in data:  # a text setting whose default is empty may be empty (port: none named)
            kwargs[name] = _coerce(data[name], hints[name], prefix + name, empty_ok=f.default == "")
    return cls(**kwargs)


def _merge(base: dict, over: Mapping) -> dict:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


# -- sources ---------------------------------------------------------------------------------------
def _shallow(text: str) -> bool:
    """Whether no collection in the YAML ``text`` nests deeper than ``MAX_DEPTH`` (the parser's
    events, read without recursion and only as far as the first level too deep)."""
    depth = 0
    for event in yaml.parse(text, Loader=yaml.SafeLoader):
        if isinstance(event, yaml.CollectionStartEvent):
            depth += 1
            if depth > MAX_DEPTH:
                return False
        elif isinstance(event, yaml.CollectionEndEvent):
            depth -= 1
    return True


def read_file(path: str) -> dict:
    """The mapping in the YAML file ``path``; ConfigError naming the file for anything else."""
    try:
        with open(path, "rb") as fh:
            blob = fh.read(MAX_FILE_BYTES + 1)
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {path}") from None
    except OSError as exc:
        raise ConfigError(f"config file {path}: cannot read: {exc.strerror or exc}") from None
    if len(blob) > MAX_FILE_BYTES:
        raise ConfigError(f"config file {path}: larger than {MAX_FILE_BYTES} bytes: not a magcal config "
                          "(`magcal config` prints every setting)")
    try:
        text = blob.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"config file {path}: not UTF-8 text (byte {exc.start}): is it the right file?") from None
    if "\0" in text:
        raise ConfigError(f"config file {path}: a binary file (holds NUL bytes), not YAML settings")
    too_deep = f"config file {path}: nested too deeply to be magcal settings (more than {MAX_DEPTH} levels)"
    try:
        if not _shallow(text):
            raise ConfigError(too_deep)
        data = yaml.safe_load(text)
    except ValueError as exc:  # an integer too long to convert (thousands of digits)
        raise ConfigError(f"config file {path}: {_too_long(exc)}") from None
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        at = f" (line {where.line + 1})" if where is not None else ""
        what = " ".join(str(getattr(exc, "problem", None) or exc).split())  # one line
        raise ConfigError(f"config file {path} is not valid YAML{at}: {what}") from None
    except RecursionError:  # a Python stack already deep when the file is read
        raise ConfigError(too_deep) from None
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"config file {path} must hold a mapping of settings, got {type(data).__name__}")
    return dict(data)


def _too_long(exc: ValueError) -> str:
    return f"a number too long to be a setting ({' '.join(str(exc).split()[:10])}…)"


def _field_type(path: list[str]):
    """The declared type of the setting at ``path`` (None when there is no such setting)."""
    cls = Settings
    for p in path:
        if not dataclasses.is_dataclass(cls):
            return None
        hints = typing.get_type_hints(cls)
        if p not in hints:
            return None
        cls = hints[p]
    return cls


def _env_value(key: str, raw: str, typ):
    if typ is str or (isinstance(typ, type) and issubclass(typ, enum.Enum)):
        return raw
    try:
        if _shallow(raw):
            return yaml.safe_load(raw)
    except ValueError as exc:  # an integer too long to convert (thousands of digits)
        raise ConfigError(f"{key}: {_too_long(exc)}") from None
    except (yaml.YAMLError, RecursionError):
        pass
    raise ConfigError(f"{key}={_show(raw)}: not a value (a number, true/false, or a list like [15, 100])")


# MAGCAL_* variables that are not settings: where the host store and the config file are, and
# where the benchmarks find the real recordings and the MotionCal driver (bench/README.md) —
# a shell that exports those for the benches must still run every command
NOT_SETTINGS = frozenset({"MAGCAL_STORE_DIR", "MAGCAL_CONFIG", "MAGCAL_REAL_DATA", "MAGCAL_MOTIONCAL_DRIVER"})


def from_environment(environ: Mapping[str, str]) -> dict:
    """The settings in ``MAGCAL_*`` variables, each checked on its own (the error names the
    variable); two variables that set one key both as a value and as a section are refused."""
    out: dict = {}
    owner: dict[tuple, str] = {}
    for key in sorted(environ):
        if not key.startswith("MAGCAL_") or key in NOT_SETTINGS:
            continue
        path = key[len("MAGCAL_"):].lower().split("__")
        if not all(path):
            raise ConfigError(f"{key}: not a setting name (levels are joined by a double underscore, e.g. "
                              "MAGCAL_GATES__MIN_COVERAGE)")
        value = _env_value(key, environ[key], _field_type(path))
        single: dict = {}
        node = single
        for p in path[:-1]:
            node = node.setdefault(p, {})
        node[path[-1]] = value
        try:
            _build(Settings, single)
        except ConfigError as exc:
            raise ConfigError(f"{key}: {exc}") from None
        for i in range(1, len(path)):  # MAGCAL_PORT and MAGCAL_PORT__X cannot both hold
            if tuple(path[:i]) in owner:
                raise ConfigError(f"{key} and {owner[tuple(path[:i])]} both set {'.'.join(path[:i])}")
        owner[tuple(path)] = key
        out = _merge(out, single)
    return out


def _sources(file_path: str | None, file_data: Mapping, environ: Mapping[str, str], overrides: Mapping) -> dict:
    """Where each key was last set: dotted key → description of the source."""
    out: dict[str, str] = {}

    def walk(data: Mapping, prefix: str, source: str) -> None:
        for k, v in data.items():
            if isinstance(v, Mapping):
                walk(v, f"{prefix}{k}.", source)
            else:
                out[prefix + str(k)] = source

    walk(file_data, "", f"in config file {file_path}")
    for key in environ:
        if key.startswith("MAGCAL_") and key not in NOT_SETTINGS:
            out[".".join(key[len("MAGCAL_"):].lower().split("__"))] = f"in the environment: {key}"
    walk(overrides, "", "on the command line")
    return out


def load(
    path: str | None = None,
    overrides: Mapping | None = None,
    environ: Mapping[str, str] | None = None,
) -> Settings:
    """Defaults < file (``path`` or ``$MAGCAL_CONFIG``) < environment < ``overrides`` (CLI)."""
    environ = os.environ if environ is None else environ
    via_env = not path and bool(environ.get("MAGCAL_CONFIG"))
    path = path or environ.get("MAGCAL_CONFIG") or None
    try:
        file_data = read_file(path) if path else {}
    except ConfigError as exc:
        raise ConfigError(f"MAGCAL_CONFIG: {exc}" if via_env else str(exc)) from None
    if file_data:
        try:
            _build(Settings, file_data)
        except ConfigError as exc:
            raise ConfigError(f"config file {path}: {exc}") from None
    env = from_environment(environ)
    over = {k: v for k, v in (overrides or {}).items() if v is not None}
    if over:
        try:
            _build(Settings, over)
        except ConfigError as exc:
            raise ConfigError(f"command line: {exc}") from None
    settings = _build(Settings, _merge(_merge(file_data, env), over))
    try:
        settings.check()
    except ConfigError as exc:
        where = _sources(path, file_data, environ, over)
        said = sorted({where[k] for k in exc.keys if k in where})
        raise ConfigError(f"{exc}" + (f" (set {'; '.join(said)})" if said else ""), keys=exc.keys) from None
    return settings


def to_dict(settings) -> dict:
    """The settings as plain data (a choice as its text), as the config file spells them."""
    return dataclasses.asdict(settings, dict_factory=lambda kv: {k: v.value if isinstance(v, enum.Enum) else v
                                                                  for k, v in kv})
