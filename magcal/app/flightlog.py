"""A flight log's magnetometer fitted against the expected field: the orchestration between the
log reader (``recordings.logs``) and the fit (``fit.vector``), as a JSON-ready dict."""

from __future__ import annotations

import numpy as np

from ..fit.vector import EARTH_FIELD_FORMAT, UnknownField, fit_vector
from ..recordings.logs import LogMag

FORMAT = "magcal.fit.log/1"
UNIT = {"current_a": "µT/A", "throttle": "µT per full throttle", "motors_on": "µT step"}


def model_name(d: dict) -> str:
    kept = [t["channel"] for t in d.get("terms", []) if t.get("kept")]
    return "+".join([d["mode"]] + kept)


def fit_flight_log(lm: LogMag, term: str | None = "auto", blocks: int = 5) -> tuple[dict, bool]:
    """(the fit as a dict, whether it succeeded). Vector mode where the log has attitude and a
    position; with attitude but no position fix, against an Earth field unknown but constant
    (``earth_field.mode`` "unknown_constant"); else the magnitude against the Earth model's |B|
    (or the fitted radius)."""
    s = lm.series.only_valid()
    expected, how = _expected(lm)
    result = fit_vector(s.field_ut, s.channels, expected, lm.earth_field_ut, term=term, blocks=blocks)
    base = {"format": FORMAT, "log": lm.describe(), "input": lm.series.source, "warnings": list(lm.warnings)}
    if not result:
        return {**base, **result.to_dict(), "earth_field": _earth_field(lm, how, None)}, False
    d = {**base, **result.to_dict(), "warnings": list(lm.warnings) + list(result.warnings)}
    d["format"] = FORMAT
    d["model"] = model_name(d)
    d["earth_field"] = _earth_field(lm, how, result.earth_field)
    _mark_calibration_terms(d)
    d["uncertainty"]["field_ut"] = 0.0 if how == "model" else None
    if how == "magnitude_only":
        d["warnings"].append("the log has no attitude: fitted against |m| only, which a mostly level flight cannot pin")
    return d, True


def attitude_rotations(lm: LogMag) -> np.ndarray | None:
    """The log's attitude (body → NED, (n, 3, 3)) at the valid samples, or None without one."""
    from ..recordings.logs.select import resample_rotations

    if lm.log.attitude is None:
        return None
    return resample_rotations(lm.log.attitude, lm.series.t_s[lm.series.valid])


def _expected(lm: LogMag):
    """(what the fit is against, how): the Earth model's field in the body frame ("model"), the
    attitude with the field unknown ("unknown_constant"), or nothing ("magnitude_only")."""
    if lm.earth_body_ut is not None:
        return lm.earth_body_ut[lm.series.valid], "model"
    r = attitude_rotations(lm)
    return (UnknownField(r), "unknown_constant") if r is not None else (None, "magnitude_only")


def _earth_field(lm: LogMag, how: str, fitted: dict | None) -> dict:
    """The JSON's ``earth_field``: which field the fit was against, and for an unknown one what
    the log's attitude determines of it and what it cannot."""
    if how == "model":
        return {"format": EARTH_FIELD_FORMAT, "mode": "model", "model": lm.earth_model, "size_ut": lm.earth_field_ut}
    if how == "magnitude_only" or fitted is None:
        return {"format": EARTH_FIELD_FORMAT, "mode": how, "model": lm.earth_model, "size_ut": lm.earth_field_ut}
    source, why = heading_source(lm.log.autopilot, lm.log.params)
    return {**fitted, "determined": ["offset", "soft_iron_shape", "terms", "inclination"],
            "not_determined": ["field_size", "soft_iron_scale", "declination"],
            "heading_source": source, "heading_source_from": why}


AP_YAW = {0: "none", 1: "magnetometer", 2: "gps", 3: "gps", 6: "external_navigation", 8: "gsf"}


def heading_source(autopilot: str, params) -> tuple[str, str]:
    """Where the log's heading came from, as its parameters say ("magnetometer",
    "external_navigation", another source, or "unknown"), and the parameter that says so."""
    if autopilot == "ardupilot":
        if "EK3_SRC1_YAW" in params:
            v = int(params["EK3_SRC1_YAW"])
            return AP_YAW.get(v, "unknown"), f"EK3_SRC1_YAW {v}"
        if "COMPASS_USE" in params:
            v = int(params["COMPASS_USE"])
            return ("magnetometer" if v else "unknown"), f"COMPASS_USE {v} (no EK3_SRC1_YAW: the compass is the yaw source)"
        return "unknown", "no EK3_SRC1_YAW or COMPASS_USE in the log"
    for name, bit in (("EKF2_EV_CTRL", 8), ("EKF2_AID_MASK", 16)):
        if name in params and int(params[name]) & bit:
            return "external_navigation", f"{name} {int(params[name])} (vision yaw)"
    if "EKF2_MAG_TYPE" in params:
        v = int(params["EKF2_MAG_TYPE"])
        return ("none" if v == 5 else "magnetometer"), f"EKF2_MAG_TYPE {v}"
    return "unknown", "no EKF2_MAG_TYPE in the log"


def earth_field_text(ef: dict | None) -> str:
    """The words for an unknown-field fit: what it pins and what it cannot, and where the
    heading came from ("" otherwise)."""
    if not ef or ef.get("mode") != "unknown_constant" or "inclination_deg" not in ef:
        return ""
    ef = {"heading_source": "unknown", **ef}
    return (f"the log has no position fix, so the Earth's field was fitted as unknown but constant from the log's "
            f"attitude. Determined: the offset, the soft iron's shape, the terms and the field's inclination "
            f"{ef['inclination_deg']:.1f} ± {ef['sigma_inclination_deg']:.1f}°. Not determined: the field's size "
            f"(it shares one scale with the soft iron; {ef['size_ut']:.2f} µT is this sensor's own reading, det W = 1) "
            f"and the declination ({ef['heading_frame_declination_deg']:.1f} ± "
            f"{ef['sigma_heading_frame_declination_deg']:.1f}° is in the attitude's heading frame; "
            + HEADING_WORDS.get(ef.get("heading_source"), f"the heading came from {ef.get('heading_source')}, not this "
                                "magnetometer, so that angle is the field's bearing in that heading frame")
            + f" ({ef.get('heading_source_from', 'the log does not say')}))")


HEADING_WORDS = {
    "magnetometer": "the heading came from the magnetometer, so that is the declination the autopilot assumed, not a "
                    "measurement, and the offset is pinned by the field's tilt and size more than by its heading",
    "external_navigation": "the heading came from external navigation, so that angle is the field's bearing in that "
                           "frame, the declination only if its north is true north",
    "unknown": "without GPS the heading usually comes from the magnetometer itself, so that is most likely the "
               "declination the autopilot assumed, not a measurement",
}


def against_text(mode: str, ef: dict | None, earth_model=None, earth_field_ut=None) -> str:
    """What the flight-log fit was judged against, in words."""
    how = (ef or {}).get("mode", "model" if mode == "vector" else "magnitude_only")
    if how == "unknown_constant":
        return "the log's attitude and an Earth field unknown but constant (no position fix)"
    if mode == "vector":
        size = "" if earth_field_ut is None else f", {earth_field_ut:.2f} µT"
        return f"the expected field vector ({earth_model or 'the Earth model'}{size}, and the log's attitude)"
    return "|m| only (the log has no attitude)"


def _mark_calibration_terms(d: dict) -> None:
    """Give each kept term the coefficient the calibration holds for it. A term is judged in the
    fit that adds it (the motors-running step alone, then the current with it), and the
    calibration is the last fit kept: where a later term joined, its coefficient moved (the step
    and the current share the time the motors run), and this says by how much."""
    coefs = d["calibration"].get("coef_ut_per_unit") or {}
    for t in d["terms"]:
        if t.get("kept") and t["channel"] in coefs:
            t["coef_in_calibration_ut_per_unit"] = [float(v) for v in coefs[t["channel"]]]
            t["fitted_with"] = [c for c in coefs if c != t["channel"]]


def moved_in_calibration(t: dict) -> str:
    """"", or where a kept term's coefficient in the calibration differs from the one it was
    judged by (fitted together with a later term): the calibration's, and why."""
    k, kc = t.get("coef_ut_per_unit"), t.get("coef_in_calibration_ut_per_unit")
    if k is None or kc is None or max(abs(a - b) for a, b in zip(k, kc)) < 5e-4:
        return ""
    return (f"; in the calibration, fitted together with {', '.join(t['fitted_with'])}: ("
            + ", ".join(f"{v:+.3f}" for v in kc) + ")")


def vector_traces(lm: LogMag, calibration: dict, earth_field: dict | None = None) -> dict | None:
    """Per sample, for a figure: time since the first sample (s), the expected field (the log's
    attitude and the Earth model — or, without a position, the fitted ``earth_field``'s NED
    vector — body frame, µT), the measured field calibrated with ``calibration`` (its terms
    included), and calibrated with no term; None without attitude."""
    from ..core.calibration import Calibration
    from ..fit.vector import motors_on

    s = lm.series.only_valid()
    if lm.earth_body_ut is not None:
        expected = np.asarray(lm.earth_body_ut[lm.series.valid], np.float64)
    elif (earth_field or {}).get("ned_ut") is not None and lm.log.attitude is not None:
        expected = UnknownField(attitude_rotations(lm)).body(earth_field["ned_ut"])
    else:
        return None
    ok = np.all(np.isfinite(s.field_ut), axis=1) & np.all(np.isfinite(expected), axis=1)
    chans = {k: np.asarray(v, np.float64)[ok] for k, v in s.channels.items()}
    step = motors_on(chans)
    if step is not None:
        chans["motors_on"] = step
    cal = Calibration.from_dict(calibration)
    plain = Calibration(offset_ut=cal.offset_ut, field_ut=cal.field_ut, soft_iron=cal.soft_iron)
    m = s.field_ut[ok]
    source = "attitude + Earth model" if lm.earth_body_ut is not None else "attitude + the fitted constant field"
    return {"t_s": s.t_s[ok] - s.t_s[ok][0], "expected_ut": expected[ok], "expected_from": source,
            "calibrated_ut": cal.correct(m, chans),
            "without_terms_ut": plain.correct(m), "terms": sorted(cal.coef_ut_per_unit)}


DIAGNOSE_FORMAT = "magcal.diagnose.log/1"
EFFECT = {"current_a": "current_interference", "throttle": "throttle_interference", "motors_on": "motors_running_step"}


def term_summary(t: dict, unit: str) -> str:
    """One sentence on a judged term: kept with its size, or why not (under its floor, or the
    held-out residual did not fall)."""
    if "coef_ut_per_unit" not in t:
        return f"{t['channel']}: could not be fitted"
    k, floor = t["norm_ut_per_unit"], t["floor_ut_per_unit"]
    size = (f"|k| {k:.3f} {unit} along (" + ", ".join(f"{v / k if k else 0:+.2f}" for v in t["coef_ut_per_unit"])
            + f"), σ ({', '.join(f'{v:.3f}' for v in t['sigma_ut_per_unit'])}), floor {floor:.3f}, p {t['p_value']:.2g}")
    if t["kept"]:
        return f"{t['channel']} kept: {size}; the held-out residual falls{moved_in_calibration(t)}"
    why = "under its floor" if k < floor else ("the held-out residual does not fall" if not t.get("heldout_falls")
                                               else f"p above {1e-3:g}")
    return f"{t['channel']} not kept ({why}): {size}"


def diagnose_flight_log(lm: LogMag, blocks: int = 5) -> dict:
    """What ``diagnose`` adds on a flight log: the interference terms tested against the expected
    field (vector mode where the log has attitude and a position; with attitude only, against an
    Earth field unknown but constant; else |m|) on held-out time
    blocks — the same machinery as ``fit`` (``fit.vector``): a motors-running step judged first,
    then the current (else throttle) term, each kept only when the held-out residual falls and it
    stands above its floor."""
    d, ok = fit_flight_log(lm, blocks=blocks)
    out = {"format": DIAGNOSE_FORMAT, "warnings": d.get("warnings", [])}
    if not ok:
        return {**out, "failure": d["failure"], "message": d["message"], "earth_field": d["earth_field"]}
    key = "rms_vector_ut" if d["mode"] == "vector" else "rms_magnitude_ut"
    ho = d["heldout"]
    findings = [{"effect": EFFECT.get(t["channel"], "covariate:" + t["channel"]), "channel": t["channel"],
                 "role": t["role"], "kept": t["kept"], "summary": term_summary(t, UNIT.get(t["channel"], "µT per unit"))}
                for t in d["terms"]]
    return {**out, "log": d["log"], "mode": d["mode"], "earth_model": lm.earth_model, "earth_field_ut": lm.earth_field_ut,
            "earth_field": d["earth_field"],
            "model": d["model"], "terms": d["terms"], "findings": findings, "heldout": ho,
            "heldout_ut": {"none": ho["none"].get(key), "chosen": ho[ho["chosen"]].get(key) if ho["chosen"] != "none"
                           else ho["none"].get(key), "measure": key},
            "calibration": d["calibration"], "uncertainty": d["uncertainty"], "rms_ut": d["rms_ut"], "n_used": d["n_used"]}
