"""Settings: YAML → frozen dataclasses, validated, with one precedence order.

    built-in defaults  <  config file  <  environment (MAGCAL_*)  <  command line

Unknown keys are rejected with a message naming them (and the keys that are allowed); wrong
types and out-of-range values name the key and the value. Environment variables address keys
by path with ``__`` between levels: ``MAGCAL_PORT=/dev/ttyACM0``,
``MAGCAL_GATES__MIN_COVERAGE=0.5``; their values are parsed as YAML scalars.

``config/magcal.yaml`` documents every key with its default.
"""

from __future__ import annotations

import dataclasses
import os
import types
import typing
from dataclasses import dataclass, field
from typing import Any, Mapping

import yaml

from ..core.errors import ConfigError
from ..logic.gates import Gates


@dataclass(frozen=True)
class DaemonSettings:
    """The long-running service (``magcal run``)."""

    state_dir: str = "~/.local/state/magcal"
    recalibrate: bool = False  # collect, refit and write back when the calibration stops fitting
    monitor_window: int = 500  # samples per drift test window
    monitor_alpha: float = 0.001  # false-alarm probability of one drift test
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 30.0
    capture_max_bytes: int = 0  # rolling capture size bound; 0 = no capture
    state_every_s: float = 5.0  # how often the state file is written
    socket: bool = True  # local UNIX status socket in state_dir
    stall_s: float = 5.0  # no sample for this long on an open link ⇒ reconnect

    def check(self) -> None:
        if not 0 < self.monitor_alpha < 0.5:
            raise ConfigError(f"daemon.monitor_alpha must be in (0, 0.5), got {self.monitor_alpha}")
        if self.reconnect_min_s <= 0 or self.reconnect_max_s < self.reconnect_min_s:
            raise ConfigError("daemon.reconnect_min_s must be > 0 and ≤ daemon.reconnect_max_s")
        if self.monitor_window < 40:
            raise ConfigError(f"daemon.monitor_window must be at least 40 samples, got {self.monitor_window}")
        if self.capture_max_bytes < 0 or self.state_every_s <= 0 or self.stall_s <= 0:
            raise ConfigError("daemon.capture_max_bytes must be ≥ 0, daemon.state_every_s and daemon.stall_s > 0")


@dataclass(frozen=True)
class Settings:
    port: str = ""  # no default device: --port, MAGCAL_PORT, this key, or the one plugged in
    dialect: str = "native"  # native | motioncal | auto
    baud: int = 115200
    rate_hz: int = 50
    model: str = "auto"  # sphere | ellipsoid | auto
    timeout_s: float = 120.0
    write: bool = True
    gates: Gates = field(default_factory=Gates)
    daemon: DaemonSettings = field(default_factory=DaemonSettings)

    def check(self) -> None:
        if self.model not in ("sphere", "ellipsoid", "auto"):
            raise ConfigError(f"model must be sphere, ellipsoid or auto, got {self.model!r}")
        if self.dialect not in ("native", "motioncal", "auto"):
            raise ConfigError(f"dialect must be native, motioncal or auto, got {self.dialect!r}")
        if not 1 <= self.rate_hz <= 100:
            raise ConfigError(f"rate_hz must be 1…100 (the AK8975 needs ≥ 10 ms per measurement), got {self.rate_hz}")
        if self.timeout_s <= 0:
            raise ConfigError(f"timeout_s must be positive, got {self.timeout_s}")
        self.gates.check()
        self.daemon.check()


def _coerce(value: Any, typ, key: str):
    origin = typing.get_origin(typ)
    if dataclasses.is_dataclass(typ):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key} must be a mapping, got {value!r}")
        return _build(typ, value, key + ".")
    if typ is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{key} must be true or false, got {value!r}")
    if typ is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ConfigError(f"{key} must be an integer, got {value!r}")
    if typ is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        raise ConfigError(f"{key} must be a number, got {value!r}")
    if typ is str:
        if isinstance(value, (str, int, float)) and not isinstance(value, bool):
            return str(value)
        raise ConfigError(f"{key} must be a string, got {value!r}")
    if typ is tuple or origin is tuple:
        if isinstance(value, (list, tuple)) and all(isinstance(v, (int, float)) for v in value):
            return tuple(float(v) for v in value)
        raise ConfigError(f"{key} must be a list of numbers, got {value!r}")
    if origin in (typing.Union, types.UnionType):
        return value
    return value


def _build(cls, data: Mapping, prefix: str = ""):
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        names = ", ".join(prefix + k for k in unknown)
        raise ConfigError(f"unknown setting(s): {names} (allowed here: {', '.join(sorted(fields))})")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, f in fields.items():
        if name in data:
            kwargs[name] = _coerce(data[name], hints[name], prefix + name)
    return cls(**kwargs)


def _merge(base: dict, over: Mapping) -> dict:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def read_file(path: str) -> dict:
    try:
        with open(path, encoding="utf-8") as f:
            data = yaml.safe_load(f)
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {path}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path} is not valid YAML: {exc}") from None
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"config file {path} must hold a mapping of settings")
    return dict(data)


def from_environment(environ: Mapping[str, str]) -> dict:
    out: dict = {}
    for key, raw in environ.items():
        if not key.startswith("MAGCAL_") or key in ("MAGCAL_STORE_DIR", "MAGCAL_CONFIG"):
            continue
        path = key[len("MAGCAL_") :].lower().split("__")
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError:
            value = raw
        node = out
        for p in path[:-1]:
            node = node.setdefault(p, {})
        node[path[-1]] = value
    return out


def load(
    path: str | None = None,
    overrides: Mapping | None = None,
    environ: Mapping[str, str] | None = None,
) -> Settings:
    """Defaults < file (``path`` or ``$MAGCAL_CONFIG``) < environment < ``overrides`` (CLI)."""
    environ = os.environ if environ is None else environ
    data: dict = {}
    path = path or environ.get("MAGCAL_CONFIG")
    if path:
        data = _merge(data, read_file(path))
    env = from_environment(environ)
    if env:
        try:
            _build(Settings, env)
        except ConfigError as exc:
            raise ConfigError(f"in the environment (MAGCAL_*): {exc}") from None
        data = _merge(data, env)
    if overrides:
        data = _merge(data, {k: v for k, v in overrides.items() if v is not None})
    settings = _build(Settings, data)
    settings.check()
    return settings


def to_dict(settings) -> dict:
    return dataclasses.asdict(settings)
