"""``magcal service install [--root DIR]``: install the systemd unit from the package.

Writes what ``config/README.md`` ("systemd: one daemon per port") lists, under ``--root``
(default ``/``; a temporary root for a package build or a test):

- ``etc/systemd/system/magcal@.service`` — the template unit, its ``ExecStart`` naming this
  installation's own ``magcal`` (a virtual environment's works too);
- ``etc/magcal/magcal.yaml`` — the configuration template, only when none is there (an edited
  file is kept);
- ``usr/share/doc/magcal/service.md`` and ``README.md`` — the unit's ``Documentation=``.

Then it prints the ``systemctl`` steps; it starts nothing itself.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from ..core.errors import ConfigError
from ..recordings.shared import shared_path

HELP = "install the systemd unit (magcal@PORT.service), its config file and docs"
UNIT = "magcal@.service"
DEFAULT_EXEC = "/usr/bin/env magcal"
# what the unit's ProtectHome=yes hides from the service (and a dynamic user could not read)
HIDDEN_FROM_SERVICE = (Path("/home"), Path("/root"), Path("/run/user"))


def add_arguments(p) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    inst = sub.add_parser("install", help="write the unit, the config template and the docs",
                          description=__doc__.split("\n\n")[1])
    inst.add_argument("--root", default="/", metavar="DIR",
                      help="install under DIR instead of / (a staging or temporary root)")


def this_magcal() -> str:
    """The command line that starts this installation's ``magcal``: the script beside the
    running interpreter when there is one, else whatever ``magcal`` is on PATH."""
    script = Path(sys.executable).parent / "magcal"
    if script.is_file() and os.access(script, os.X_OK):
        return str(script.absolute())
    return DEFAULT_EXEC


def hidden_installation(prefix: Path) -> Path | None:
    """The protected directory an installation under ``prefix`` (a virtual environment's or the
    interpreter's ``sys.prefix``) lies in, when the unit's service cannot reach it; else None."""
    prefix = Path(os.path.abspath(prefix))
    return next((h for h in HIDDEN_FROM_SERVICE if prefix == h or h in prefix.parents), None)


def unit_text() -> str:
    """The packaged unit with ``ExecStart`` pointing at this installation's ``magcal``."""
    text = shared_path("config", UNIT).read_text(encoding="utf-8")
    if DEFAULT_EXEC not in text:
        raise ConfigError(f"the packaged {UNIT} has no '{DEFAULT_EXEC}' in ExecStart")
    return text.replace(f"ExecStart={DEFAULT_EXEC} ", f"ExecStart={this_magcal()} ", 1)


def _write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".new")
    tmp.write_text(text, encoding="utf-8")
    os.chmod(tmp, 0o644)
    os.replace(tmp, path)


def install(root: Path) -> list[tuple[Path, str]]:
    """Write the files under ``root``; (path, what was done) for each."""
    done = []
    unit = root / "etc/systemd/system" / UNIT
    _write(unit, unit_text())
    done.append((unit, "written"))
    config = root / "etc/magcal/magcal.yaml"
    if config.exists():
        done.append((config, "kept (already there)"))
    else:
        _write(config, shared_path("config", "magcal.yaml").read_text(encoding="utf-8"))
        done.append((config, "written"))
    for name, source in (("service.md", ("config", "README.md")), ("README.md", ("README.md",))):
        doc = root / "usr/share/doc/magcal" / name
        _write(doc, shared_path(*source).read_text(encoding="utf-8"))
        done.append((doc, "written"))
    return done


def run(args) -> int:
    root = Path(args.root)
    if not root.is_dir():
        raise ConfigError(f"--root {root}: no such directory")
    try:
        done = install(root)
    except PermissionError as exc:
        raise ConfigError(f"cannot write {exc.filename}: permission denied (run as root, or use --root DIR)") from None
    for path, what in done:
        print(f"{path}: {what}")
    hidden = hidden_installation(Path(sys.prefix))
    if hidden is not None:
        print(f"warning: this magcal is installed under {sys.prefix}, inside {hidden}, which the unit hides"
              " from its service (ProtectHome=yes, a dynamic user): the service would fail to start."
              " Install magcal outside home directories (e.g. python3 -m venv /opt/magcal, then"
              " /opt/magcal/bin/pip install the same package) and run that one's 'magcal service install'.",
              file=sys.stderr)
    print("next: systemctl daemon-reload; systemctl enable --now magcal@ttyACM0.service"
          " (the instance name is the device node)")
    return 0
