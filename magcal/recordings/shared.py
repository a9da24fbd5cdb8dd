"""The files the package carries beside its code: the configuration template, the systemd unit,
the docs and the firmware sources (``magcal/share/``).

In a source checkout ``magcal/share/config``, ``docs``, ``firmware`` and ``README.md`` are links
to the one copy at the top of the tree; a wheel carries them as plain files. Either way they are
found here, next to the code, so no command needs the source tree.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..core.errors import ConfigError

SHARE = Path(__file__).resolve().parents[1] / "share"


def shared_path(*parts: str) -> Path:
    """The packaged file or folder ``parts`` (links resolved); ``ConfigError`` naming it when the
    installation lacks it."""
    path = SHARE.joinpath(*parts)
    if not path.exists():
        raise ConfigError(f"{'/'.join(parts)} is not installed with magcal (looked in {SHARE}); "
                          "reinstall the package")
    return path.resolve()


def in_source_checkout(folder: Path) -> bool:
    """True when ``folder`` (a resolved packaged folder) lies in a source checkout rather than an
    installed package: its parent holds the project's ``pyproject.toml``."""
    return (folder.parent / "pyproject.toml").is_file()


def user_cache_dir() -> Path:
    """The user's cache directory for magcal (XDG base directories): ``$XDG_CACHE_HOME/magcal``,
    else ``~/.cache/magcal``."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "magcal"
