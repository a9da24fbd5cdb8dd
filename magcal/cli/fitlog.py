"""``magcal fit LOG --mag N``: the text and JSON of a flight log's fit (see ``app.flightlog``).

The JSON (``format`` ``magcal.fit.log/1``)::

    {"log": {"file", "autopilot", "firmware", "magnetometer": {...}, "undone": sentence,
             "channels": [...], "attitude": bool, "earth_model", "earth_field_ut", "sensor_to_body"},
     "mode": "vector" | "magnitude" | "magnitude-sphere", "model": "vector+motors_on+current_a",
     "earth_field": {"format": "magcal.earth_field/1", "mode": "model" | "unknown_constant" | "magnitude_only",
                     ...},  # unknown_constant (attitude, no position fix): "ned_ut", "size_ut" (det W = 1,
                     # "size_determined": false), "inclination_deg" ± σ, "heading_frame_declination_deg" ± σ
                     # ("declination_determined": false), "determined", "not_determined"
     "calibration": {"offset_ut", "field_ut", "soft_iron", "coef_ut_per_unit", "reference"},
     "uncertainty": {"offset_ut", "field_ut", "autocorrelation_factor"},
     "terms": [{"channel", "role": "nuisance"|"interference", "kept", "coef_ut_per_unit",
                "sigma_ut_per_unit", "norm_ut_per_unit", "floor_ut_per_unit", "p_value",
                "heldout_falls", "heldout_model",
                "coef_in_calibration_ut_per_unit", "fitted_with"}],  # kept: its coefficient in the
                # calibration (the last fit kept), which moves where a later term joined it
     "heldout": {"blocks": 5, "none": {"rms_vector_ut", "rms_magnitude_ut", ...}, ..., "chosen"},
     "rms_ut", "n_used", "warnings": [...]}

A calibrated sample is ``soft_iron @ (m − offset_ut − Σ coef·x)`` in the body frame (µT).
"""

from __future__ import annotations

import sys

from .exits import Exit


def is_flight_log(path) -> bool:
    """True when the file starts like a PX4 ULog or an ArduPilot DataFlash log."""
    from ..recordings.logs import HEAD_BYTES, log_kind

    try:
        with open(path, "rb") as fh:
            return log_kind(fh.read(HEAD_BYTES)) is not None
    except OSError:
        return False


def fit_log_file(path: str, args) -> tuple[dict, int]:
    from ..app.flightlog import fit_flight_log
    from ..recordings.logs import load_log

    lm = load_log(path, args.mag)
    for w in lm.warnings:
        print(f"magcal: warning: {path}: {w}", file=sys.stderr)
    term = None if args.term == "none" else args.term
    d, ok = fit_flight_log(lm, term)
    if not ok:
        print(f"magcal fit: {path}: {d['failure']}: {d['message']}", file=sys.stderr)
        return d, Exit.GATE
    return d, Exit.OK


def _term_line(t: dict) -> str:
    from ..app.flightlog import UNIT, moved_in_calibration

    unit = UNIT.get(t["channel"], "µT per unit")
    if "coef_ut_per_unit" not in t:
        return f"term        {t['channel']}: could not be fitted"
    verdict = "kept" if t["kept"] else "not kept"
    why = ("held-out residual falls" if t.get("heldout_falls") else "held-out residual does not fall")
    return (f"term        {t['channel']} ({t['role']}): {verdict} — |k| {t['norm_ut_per_unit']:.3f} {unit}, floor "
            f"{t['floor_ut_per_unit']:.3f}, p {t['p_value']:.2g}, {why}; k = ("
            + ", ".join(f"{v:+.3f}" for v in t["coef_ut_per_unit"]) + ") ± ("
            + ", ".join(f"{v:.3f}" for v in t["sigma_ut_per_unit"]) + ")" + moved_in_calibration(t))


def format_log_text(d: dict) -> str:
    from ..app.flightlog import against_text, earth_field_text

    log, c, u = d["log"], d["calibration"], d["uncertainty"]
    key = "rms_vector_ut" if d["mode"] == "vector" else "rms_magnitude_ut"
    lines = [
        f"log         {log['file']} ({log['firmware']})",
        f"magnet.     {log['magnetometer']['name']}: {log['magnetometer']['device']}",
        f"undone      {log['undone']}",
        f"mode        {d['mode']} against " + against_text(d["mode"], d.get("earth_field"), log["earth_model"],
                                                        log["earth_field_ut"]),
        f"model       {d['model']}",
        "offset_ut   " + " ".join(f"{v:9.3f}" for v in c["offset_ut"]) + "   ± " + " ".join(f"{v:.3f}" for v in u["offset_ut"]),
    ]
    for i, row in enumerate(c["soft_iron"]):
        lines.append(("soft_iron   " if i == 0 else "            ") + " ".join(f"{v:9.5f}" for v in row))
    lines += [_term_line(t) for t in d["terms"]]
    ho = d["heldout"]
    lines.append("held-out    " + ", ".join(f"{k} {v[key]:.3f} µT" for k, v in ho.items() if isinstance(v, dict) and key in v)
                 + f" ({ho['blocks']} time blocks; chosen {ho['chosen']})")
    lines.append(f"rms_ut      {d['rms_ut']:.3f} ({d['n_used']} samples)")
    if earth_field_text(d.get("earth_field")):
        lines.append("earth field " + earth_field_text(d.get("earth_field")))
    return "\n".join(lines)


def format_log_diagnosis(d: dict) -> str:
    """The flight-log section of ``magcal diagnose`` (``app.flightlog.diagnose_flight_log``)."""
    if "failure" in d:
        return f"log terms   could not be tested: {d['failure']}: {d['message']}"
    from ..app.flightlog import against_text, earth_field_text

    against = against_text(d["mode"], d.get("earth_field"), d["earth_model"], d["earth_field_ut"])
    h = d["heldout_ut"]
    lines = [f"log terms   judged against {against} on {d['heldout']['blocks']} held-out time blocks"
             + (" (what |m| alone could not test):" if d["mode"] == "vector" else ":")]
    lines += [f"{'finding' if f['kept'] else 'not found':<12}{f['effect']}: {f['summary']}" for f in d["findings"]]
    what = f"held-out {h['measure'].split('_')[1]} residual"
    lines.append(f"log model   {d['model']}: " + (f"no term kept; {what} {h['none']:.3f} µT" if d["heldout"]["chosen"] == "none"
                 else f"{what} {h['none']:.3f} µT without terms, {h['chosen']:.3f} µT with ({d['heldout']['chosen']})"))
    if earth_field_text(d.get("earth_field")):
        lines.append("earth field " + earth_field_text(d.get("earth_field")))
    return "\n".join(lines)
