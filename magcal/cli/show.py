"""``magcal show [--port URL] [--json]``: print the calibration the device (or its host-side
store) holds. Works for every backend through the generic Device API: serial boards answer
from EEPROM, ``i2c:`` devices from the host-side store. A stored record that cannot be used — corrupt
(it fails its own check) or invalid (its CRC holds but it is no calibration, e.g. a matrix that
is not positive definite) — is named as such, never shown as the calibration; writing a new one
(``magcal calibrate`` or ``magcal write``) replaces it. Exit status: 0 when a calibration is
stored, 1 when none (or no usable one) is, 5 for the device.

``--self-test`` also runs the magnetometer's self-test (judged against that chip's datasheet window) on backends that can (``i2c:``, the magcal firmware
over serial, ``sim://``, ``emu://``) and prints each axis against the datasheet window; then the
self-test is the question: exit 0 when it passed (whether or not a calibration is stored), 3
when it failed. ``--json`` prints ``magcal.show/1``."""

from __future__ import annotations

import numpy as np

from ..core.chips import MPU9150, Chip
from ..core.errors import DeviceError
from .common import device_settings, document, open_from_settings, print_json
from .exits import Exit
from .options import add

HELP = "print the calibration stored for a device"


def add_arguments(p) -> None:
    add(p, "port", "baud", "dialect", "config", "json")
    p.add_argument("--self-test", action="store_true",
                   help="also run the magnetometer's self-test (i2c:, the magcal firmware, sim://, emu://)")


def _fmt_vec(v) -> str:
    return " ".join(f"{x:10.4f}" for x in v)


def format_text(identity: dict, cal, where: str | None, record=None) -> str:
    """The human-readable report (pure); ``record``: the StoredRecord when it is not usable."""
    ident = "  ".join(
        f"{k} {identity[k]}" for k in ("transport", "bus", "address", "firmware", "who_am_i", "wia") if identity.get(k)
    )
    lines = [f"device      {ident}  asa {' '.join(str(a) for a in identity.get('asa', []))}"]
    if identity.get("chip"):
        lines.append(f"chip        {identity['chip']}")
    if where:
        lines.append(f"stored in   {where}")
    if cal is None and record is not None and record.problem:
        lines.append(f"calibration none usable: the stored record is {record.state.value.upper()} — {record.problem}")
        lines.append("            (magcal does not use it; `magcal calibrate` or `magcal write FILE` replaces it)")
        return "\n".join(lines)
    if cal is None:
        lines.append("calibration none stored (run `magcal calibrate` first)")
        return "\n".join(lines)
    lines.append(f"offset_ut   {_fmt_vec(cal.offset_ut)}")
    lines.append(f"field_ut    {cal.field_ut:10.4f}")
    w = np.asarray(cal.soft_iron)
    for i, row in enumerate(w):
        lines.append(f"{'soft_iron' if i == 0 else '':<11} {_fmt_vec(row)}")
    for name, coef in cal.coef_ut_per_unit.items():
        ref = cal.reference.get(name)
        ref_txt = f"  (reference {ref:g})" if ref is not None else ""
        lines.append(f"coef {name:<6} {_fmt_vec(coef)}  µT per unit{ref_txt}")
    return "\n".join(lines)


def format_self_test(result, chip: Chip | None = None) -> str:
    """The self-test judgement in the counts the window is stated in: ASA-adjusted where the
    part has sensitivity adjustment, its plain counts where it has none (the AK09916)."""
    chip = chip or MPU9150
    counts = "ASA-adjusted counts" if chip.has_asa else f"counts; the {chip.magnetometer.value} has no sensitivity adjustment"
    lines = [f"self-test   {'PASS' if result.passed else 'FAIL'} ({counts}; window from the "
             f"{chip.magnetometer.value} datasheet)"]
    for name, raw, adj, (lo, hi), ok in zip("xyz", result.raw, result.adjusted, result.window, result.axis_passed):
        lines.append(f"  {name}  raw {raw:6d}  adjusted {adj:8.1f}  window [{lo}, {hi}]  {'ok' if ok else 'OUT'}")
    return "\n".join(lines)


def run(args) -> int:
    settings = device_settings(args)
    dev = open_from_settings(settings)
    result = None
    with dev:
        identity = dev.open()
        if args.self_test:
            if not dev.abilities.self_test:
                raise DeviceError(f"{settings.port}: this backend cannot run the magnetometer self-test "
                                  "(i2c:, the magcal firmware over serial, sim:// and emu:// can)")
            result = dev.self_test()
        record = dev.read_stored()
        cal = record.calibration
        where = dev.stored_in()
    if args.json:
        out = {"device": identity.to_dict(), "port": settings.port,
               "calibration": None if cal is None else cal.to_dict(), "record": record.to_dict(),
               "stored_in": where,
               "self_test": None if result is None else result.to_dict()}
        print_json(document("show", out))
    else:
        print(format_text(identity.to_dict(), cal, where, record))
        if result is not None:
            print(format_self_test(result, identity.chip))

    if result is not None:
        return Exit.OK if result.passed else Exit.GATE
    return Exit.OK if cal is not None else Exit.NO
