"""The rings of the architecture, checked from the imports (see README, Architecture)."""

import ast
import os

ROOT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "magcal")

VALUES = {"sample", "series", "calibration", "errors", "selftest"}
PURE = {"protocol", "coverage", "session", "physics", "motioncal", "monitor"}
PURE_PACKAGES = {"fit", "diagnose"}
EFFECTS = {"serial", "smbus2", "socket", "signal", "subprocess", "threading", "select", "fcntl"}


def modules():
    for dirpath, _, files in os.walk(ROOT):
        for f in files:
            if f.endswith(".py"):
                path = os.path.join(dirpath, f)
                rel = os.path.relpath(path, ROOT)[:-3].replace(os.sep, ".")
                yield rel.replace(".__init__", ""), path


def imports_of(path):
    tree = ast.parse(open(path, encoding="utf-8").read())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                out.add("magcal." + base if base else "magcal")
                for a in node.names:
                    out.add(("magcal." + base + "." if base else "magcal.") + a.name)
            else:
                out.add(base)
    return out


def top(name):
    return name.split(".")[0]


def test_values_import_only_numpy_and_each_other():
    for name, path in modules():
        if name in VALUES:
            for imp in imports_of(path):
                assert top(imp) in {"numpy", "magcal", "__future__", "dataclasses", "typing"} , (name, imp)
                if imp.startswith("magcal."):
                    assert imp.split(".")[1] in VALUES, (name, imp)


def test_pure_logic_touches_no_ports_threads_or_signals():
    for name, path in modules():
        if name in PURE or name.split(".")[0] in PURE_PACKAGES:
            bad = {i for i in imports_of(path) if top(i) in EFFECTS}
            assert not bad, f"{name} imports {bad}"
            assert not any(i.startswith("magcal.devices") or i.startswith("magcal.daemon") for i in imports_of(path)
                           if name != "session" or not i.startswith("magcal.devices.base")), name


def test_io_never_imports_fits_or_the_session():
    for name, path in modules():
        if name.startswith("devices") or name == "capture":
            bad = {i for i in imports_of(path) if i.startswith(("magcal.fit", "magcal.session", "magcal.diagnose"))}
            assert not bad, f"{name} imports {bad}"


def test_only_the_daemon_and_cli_install_signal_handlers():
    for name, path in modules():
        tree = ast.parse(open(path, encoding="utf-8").read())
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr == "signal" and getattr(node.value, "id", "") == "signal":
                assert name in {"daemon", "cli"} or name.startswith("commands."), name
