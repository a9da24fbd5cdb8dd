"""``magcal config``: print the configuration template, every setting with its built-in default
and what it means (the packaged ``config/magcal.yaml``), to start a ``--config`` file from::

    magcal config > magcal.yaml
"""

from __future__ import annotations

import sys

from ..recordings.shared import shared_path

HELP = "print the configuration template: every setting, its default and meaning (for --config)"


def add_arguments(p) -> None:
    """No options: the template goes to stdout."""


def run(args) -> int:
    sys.stdout.write(shared_path("config", "magcal.yaml").read_text(encoding="utf-8"))
    return 0
