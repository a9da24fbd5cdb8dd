"""The fleet's answer as one JSON-ready dict (``magcal.fleet/1``): per vehicle, per compass, the
flights in order with their calibration and σ, and the changes found (``logic.fleet``); the
rows that failed with their reasons. The page and ``--json`` both show this dict."""

from __future__ import annotations

import math

from ...logic.fleet import CompassHistory, FleetReport

FLIGHT_KEYS = ("path", "flight_time_utc", "status", "model", "offset_ut", "sigma_offset_ut", "field_ut",
               "current_a_ut_per_unit", "sigma_current_a_ut_per_unit", "current_a_kept", "coverage", "rms_ut")


def _clean(v):
    """JSON has no NaN: a value not fitted is null."""
    if isinstance(v, float):
        return None if math.isnan(v) else v
    if isinstance(v, list):
        return None if v and all(isinstance(a, float) and math.isnan(a) for a in v) else [_clean(a) for a in v]
    return v


def _compass(h: CompassHistory, report: FleetReport) -> dict:
    first = h.rows[0] if h.rows else {}
    return {"compass": h.compass, "device_id": first.get("device_id"), "external": first.get("external"),
            "flights": [{k: _clean(r.get(k)) for k in FLIGHT_KEYS} for r in h.rows],
            "changes": [c.to_dict() for c in report.changes_of(h.vehicle, h.compass)]}


def document(report: FleetReport, rows: list[dict], counts: dict, results: str, version: str) -> dict:
    vehicles = []
    for v in report.vehicles():
        hs = [h for h in report.histories if h.vehicle == v]
        vehicles.append({"vehicle": v, "compasses": [_compass(h, report) for h in hs],
                         "changes": len(report.changes_of(v))})
    failures = [{k: r.get(k) for k in ("path", "vehicle", "mag_index", "compass", "status", "failure", "message")}
                for r in rows if r["status"] != "ok"]
    return {"results": results, "magcal_version": version, "logs": counts, "rows": len(rows),
            "failed_rows": len(failures), "alpha": report.alpha, "vehicles": vehicles,
            "changes": [c.to_dict() for c in report.changes], "failures": failures}
