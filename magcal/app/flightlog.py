"""A flight log's magnetometer fitted against the expected field: the orchestration between the
log reader (``recordings.logs``) and the fit (``fit.vector``), as a JSON-ready dict."""

from __future__ import annotations

from ..fit.vector import fit_vector
from ..recordings.logs import LogMag

FORMAT = "magcal.fit.log/1"


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
    d["uncertainty"]["field_ut"] = 0.0 if lm.earth_field_ut else None
    if expected is None:
        d["warnings"].append("the log has no attitude or position: fitted against |m| only, "
                             "which a mostly level flight cannot pin")
    return d, True
