"""Does a stored calibration make physical sense? A record can pass its CRC (or a store file its
checksum) and still be nonsense: a soft iron of 1e-6·I turns every reading into 0 µT, an offset
of two million µT is no magnetometer's. ``record_problem`` says what is wrong (pure); a store
holding such a record holds an INVALID one — taken as no calibration, replaced by the next write.

The limits are wide: a calibration any supported part can need passes.

* soft iron: every eigenvalue within [1/3, 3] (near unit scale: it corrects the sensor's
  scale factors, which differ from one by a few per cent to tens of per cent) and condition
  (largest over smallest eigenvalue) at most 10;
* offset per axis and field radius within the widest measuring range of a supported part,
  ±4912 µT (AK8963 and AK09916 at 16 bits; the AK8975 reads ±1229 µT);
* channel coefficients at most 1000 µT per unit (°C, A), a temperature reference in −60…150 °C.
"""

from __future__ import annotations

import numpy as np

from .calibration import Calibration

SOFT_IRON_EIGEN = (1.0 / 3.0, 3.0)
SOFT_IRON_MAX_CONDITION = 10.0
RANGE_UT = 4912.0
MAX_COEF_UT_PER_UNIT = 1000.0
TEMP_REF_C = (-60.0, 150.0)


def record_problem(cal: Calibration) -> str | None:
    """What makes ``cal`` no physical calibration, or None."""
    eig = np.linalg.eigvalsh(0.5 * (cal.soft_iron + cal.soft_iron.T))
    lo, hi = SOFT_IRON_EIGEN
    if eig[0] < lo or eig[-1] > hi:
        return (f"its soft iron scales the field by {eig[0]:.3g}…{eig[-1]:.3g} "
                f"(a calibration's stays within {lo:.2f}…{hi:g})")
    if eig[-1] / eig[0] > SOFT_IRON_MAX_CONDITION:
        return f"its soft iron is ill-conditioned ({eig[-1] / eig[0]:.3g} > {SOFT_IRON_MAX_CONDITION:g})"
    worst = float(np.max(np.abs(cal.offset_ut)))
    if worst > RANGE_UT or cal.field_ut > RANGE_UT:
        return (f"its offset ({worst:.6g} µT) or field ({cal.field_ut:.6g} µT) lies beyond any supported "
                f"part's range (±{RANGE_UT:g} µT)")
    for name, coef in cal.coef_ut_per_unit.items():
        if float(np.max(np.abs(coef))) > MAX_COEF_UT_PER_UNIT:
            return f"its {name} coefficient exceeds {MAX_COEF_UT_PER_UNIT:g} µT per unit"
    ref = cal.reference.get("temp_c")
    if ref is not None and not TEMP_REF_C[0] <= ref <= TEMP_REF_C[1]:
        return f"its temperature reference {ref:g} °C is outside {TEMP_REF_C[0]:g}…{TEMP_REF_C[1]:g} °C"
    return None
