"""The Earth's field where and when a log was flown: the World Magnetic Model via ``pygeomag``.

pygeomag ships NOAA's WMM coefficient files for 2010, 2015 (v2), 2020 and 2025 and picks the
one for the date, so a log from 2015 is evaluated with WMM2015 rather than extrapolated from
WMM2025 (NOAA's own ``wmm-calculator`` package holds WMM2025 only and refuses earlier dates).
Outside 2010–2030 the nearest model is extrapolated, and the result says so.
"""

from __future__ import annotations

import numpy as np

NT_PER_UT = 1000.0
FIRST_YEAR, LAST_YEAR = 2010.0, 2029.999


class EarthFieldUnavailable(RuntimeError):
    """pygeomag is not installed (it comes with the ``logs`` extra)."""


def _geomag(year: float):
    try:
        from pygeomag import GeoMag
    except ImportError as exc:
        raise EarthFieldUnavailable("the World Magnetic Model needs pygeomag: pip install 'magcal-mpu9150[logs]'") from exc
    return GeoMag(base_year=int(min(max(year, FIRST_YEAR), LAST_YEAR)))


def earth_field_ned_ut(lat_deg, lon_deg, alt_m, decimal_year: float, max_points: int = 64):
    """((n, 3) north/east/down µT at each position, model name, note or None).

    The field changes by a few nT per km, so it is evaluated at up to ``max_points`` positions
    spread through the flight and interpolated in between."""
    lat, lon, alt = (np.asarray(a, np.float64).reshape(-1) for a in (lat_deg, lon_deg, alt_m))
    n = len(lat)
    gm = _geomag(decimal_year)
    outside = not FIRST_YEAR <= decimal_year <= LAST_YEAR + 1e-3
    picks = np.unique(np.linspace(0, n - 1, min(n, max_points)).round().astype(int))
    vals = []
    for i in picks:
        r = gm.calculate(glat=float(lat[i]), glon=float(lon[i]), alt=float(alt[i]) / 1000.0,
                         time=float(decimal_year), allow_date_outside_lifespan=True)
        vals.append((r.x, r.y, r.z))
    vals = np.asarray(vals) / NT_PER_UT
    out = np.column_stack([np.interp(np.arange(n), picks, vals[:, k]) for k in range(3)])
    note = (f"the log's date {decimal_year:.1f} is outside the models pygeomag holds (2010–2030): "
            f"{gm.model} extrapolated") if outside else None
    return out, gm.model, note
