"""A sensor model on disk: YAML (or JSON, by the file's suffix), the shape of
``SensorModel.to_dict`` with its schema version. Reading refuses a file that is not one with an
:class:`~magcal.errors.InputError` naming the file and the problem."""

from __future__ import annotations

import json
import os

import yaml

from ..core.errors import InputError
from ..recordings.atomic import write_text
from ..sim.model import SensorModel


def load_model(path) -> SensorModel:
    try:
        with open(path, encoding="utf-8") as f:
            data = yaml.safe_load(f)
    except OSError as exc:
        raise InputError(f"{path}: cannot read the sensor model ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not YAML or JSON ({str(exc).splitlines()[0]})") from None
    try:
        return SensorModel.from_dict(data)
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None


def save_model(model: SensorModel, path) -> None:
    """Write atomically (``recordings.atomic``: an unpredictable temporary name renamed over the
    target, never through a link)."""
    d = model.to_dict()
    text = json.dumps(d, indent=2) + "\n" if str(path).endswith(".json") else yaml.safe_dump(d, sort_keys=False, default_flow_style=None, allow_unicode=True)
    parent = os.path.dirname(os.fspath(path)) or "."
    if not os.path.isdir(parent):  # a folder is not made for it (a mistyped path is said)
        raise InputError(f"{path}: cannot write the sensor model (no such folder {parent})")
    try:
        write_text(path, text)
    except OSError as exc:
        raise InputError(f"{path}: cannot write the sensor model ({exc.strerror})") from None
