"""A flight log's magnetometer fitted against the expected field: the orchestration between the
log reader (``recordings.logs``) and the fit (``fit.vector``), as a JSON-ready dict."""

from __future__ import annotations

import numpy as np

from ..fit.vector import fit_vector
from ..recordings.logs import LogMag

FORMAT = "magcal.fit.log/1"
UNIT = {"current_a": "µT/A", "throttle": "µT per full throttle", "motors_on": "µT step"}


def model_name(d: dict) -> str:
    kept = [t["channel"] for t in d.get("terms", []) if t.get("kept")]
    return "+".join([d["mode"]] + kept)


def fit_flight_log(lm: LogMag, term: str | None = "auto", blocks: int = 5) -> tuple[dict, bool]:
    """(the fit as a dict, whether it succeeded). Vector mode where the log has attitude and a
    position, else the magnitude against the Earth model's |B| (or the fitted radius)."""
    s = lm.series.only_valid()
    expected = None
    if lm.earth_body_ut is not None:
        expected = lm.earth_body_ut[lm.series.valid]
    result = fit_vector(s.field_ut, s.channels, expected, lm.earth_field_ut, term=term, blocks=blocks)
    base = {"format": FORMAT, "log": lm.describe(), "input": lm.series.source, "warnings": list(lm.warnings)}
    if not result:
        return {**base, **result.to_dict()}, False
    d = {**base, **result.to_dict(), "warnings": list(lm.warnings) + list(result.warnings)}
    d["format"] = FORMAT
    d["model"] = model_name(d)
    _mark_calibration_terms(d)
    d["uncertainty"]["field_ut"] = 0.0 if lm.earth_field_ut else None
    if expected is None:
        d["warnings"].append("the log has no attitude or position: fitted against |m| only, "
                             "which a mostly level flight cannot pin")
    return d, True


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


def vector_traces(lm: LogMag, calibration: dict) -> dict | None:
    """Per sample, for a figure: time since the first sample (s), the expected field (the log's
    attitude and the Earth model, body frame, µT), the measured field calibrated with
    ``calibration`` (its terms included), and calibrated with no term; None without attitude."""
    from ..core.calibration import Calibration
    from ..fit.vector import motors_on

    if lm.earth_body_ut is None:
        return None
    s = lm.series.only_valid()
    expected = np.asarray(lm.earth_body_ut[lm.series.valid], np.float64)
    ok = np.all(np.isfinite(s.field_ut), axis=1) & np.all(np.isfinite(expected), axis=1)
    chans = {k: np.asarray(v, np.float64)[ok] for k, v in s.channels.items()}
    step = motors_on(chans)
    if step is not None:
        chans["motors_on"] = step
    cal = Calibration.from_dict(calibration)
    plain = Calibration(offset_ut=cal.offset_ut, field_ut=cal.field_ut, soft_iron=cal.soft_iron)
    m = s.field_ut[ok]
    return {"t_s": s.t_s[ok] - s.t_s[ok][0], "expected_ut": expected[ok], "calibrated_ut": cal.correct(m, chans),
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
    field (vector mode where the log has attitude and a position, else |m|) on held-out time
    blocks — the same machinery as ``fit`` (``fit.vector``): a motors-running step judged first,
    then the current (else throttle) term, each kept only when the held-out residual falls and it
    stands above its floor."""
    d, ok = fit_flight_log(lm, blocks=blocks)
    out = {"format": DIAGNOSE_FORMAT, "warnings": d.get("warnings", [])}
    if not ok:
        return {**out, "failure": d["failure"], "message": d["message"]}
    key = "rms_vector_ut" if d["mode"] == "vector" else "rms_magnitude_ut"
    ho = d["heldout"]
    findings = [{"effect": EFFECT.get(t["channel"], "covariate:" + t["channel"]), "channel": t["channel"],
                 "role": t["role"], "kept": t["kept"], "summary": term_summary(t, UNIT.get(t["channel"], "µT per unit"))}
                for t in d["terms"]]
    return {**out, "log": d["log"], "mode": d["mode"], "earth_model": lm.earth_model, "earth_field_ut": lm.earth_field_ut,
            "model": d["model"], "terms": d["terms"], "findings": findings, "heldout": ho,
            "heldout_ut": {"none": ho["none"].get(key), "chosen": ho[ho["chosen"]].get(key) if ho["chosen"] != "none"
                           else ho["none"].get(key), "measure": key},
            "calibration": d["calibration"], "uncertainty": d["uncertainty"], "rms_ut": d["rms_ut"], "n_used": d["n_used"]}
