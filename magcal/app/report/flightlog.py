"""The report's flight-log section: the fit against the expected field (``app.flightlog``) —
each term it judged, with its coefficient, σ, floor, p-value and verdict, the coefficient the
calibration holds, and a figure of the expected against the measured field per axis over time."""

from __future__ import annotations

import numpy as np

from ..flightlog import UNIT, against_text, earth_field_text, moved_in_calibration
from .page import esc
from .section import AFTER_LINE, RAW, Figure, Section, save, wrap
from .views import thin, time_unit


def _vec(v, fmt: str = "+.3f") -> str:
    return "(" + ", ".join(format(float(x), fmt) for x in v) + ")"


def _term_row(t: dict) -> str:
    unit = UNIT.get(t["channel"], "µT per unit")
    if "coef_ut_per_unit" not in t:
        return f"<tr><th>{esc(t['channel'])}</th><td class='l' colspan='6'>could not be fitted</td></tr>"
    kept = "kept" if t["kept"] else "not kept"
    falls = "falls" if t.get("heldout_falls") else "does not fall"
    in_cal = t.get("coef_in_calibration_ut_per_unit")
    moved = moved_in_calibration(t)
    cal = ("—" if in_cal is None else _vec(in_cal) + (f" (fitted together with {', '.join(t['fitted_with'])})"
                                                      if moved else " (the same)"))
    return (f"<tr><th>{esc(t['channel'])} ({esc(t['role'])})</th><td class='l'>{kept}</td>"
            f"<td class='num'>{t['norm_ut_per_unit']:.3f} {esc(unit)}</td><td class='num'>{t['floor_ut_per_unit']:.3f}</td>"
            f"<td class='num'>{t['p_value']:.2g}</td><td class='num'>{_vec(t['coef_ut_per_unit'])} ± "
            f"{_vec(t['sigma_ut_per_unit'], '.3f')}; held-out residual {falls}</td>"
            f"<td class='num'>{esc(cal)}</td></tr>")


def terms_html(log: dict) -> str:
    """The judged terms as a table, and the held-out residuals that decided them."""
    head = ("<tr><th>term</th><th>verdict</th><th>|k|</th><th>floor</th><th>p</th>"
            "<th>k as judged ± 1σ (µT per unit)</th><th>k in the calibration</th></tr>")
    rows = "".join(_term_row(t) for t in log.get("terms", []))
    h = log["heldout_ut"]
    what = h["measure"].split("_")[1]
    against = esc(against_text(log["mode"], log.get("earth_field"), log["earth_model"], log["earth_field_ut"]))
    unknown = earth_field_text(log.get("earth_field"))
    return (f"<p>Each term is judged against {against} on {log['heldout']['blocks']} held-out time blocks — what |m| "
            f"alone cannot test — and kept only when the held-out {what} residual falls and it stands above its "
            f"floor. Held-out {what} residual: {h['none']:.3f} µT without terms, {h['chosen']:.3f} µT with "
            f"{esc(log['heldout']['chosen'])}.</p>" + (f"<p>{esc(unknown[0].upper() + unknown[1:])}.</p>" if unknown else "")
            + f"<table>{head}{rows}</table>")


def _axis_panel(ax, t, tr: dict, i: int, label: str) -> None:
    sel = thin(len(t), 6000)
    ax.plot(t[sel], tr["without_terms_ut"][sel, i], ".", ms=1.5, color=RAW, alpha=0.4,
            label="measured, calibrated without the terms")
    ax.plot(t[sel], tr["calibrated_ut"][sel, i], "-", lw=0.9, color=AFTER_LINE, label="measured, calibrated")
    ax.plot(t[sel], tr["expected_ut"][sel, i], "-", lw=1.4, color="black", label=f"expected ({tr.get('expected_from', 'attitude + Earth model')})")
    ax.set_ylabel(f"{label} (µT, body)")


def expected_figure(tr: dict, plt, out) -> Figure:
    """Per body axis over time: the expected field, the measured one calibrated, and without its terms."""
    unit, scale = time_unit(float(tr["t_s"][-1]) if len(tr["t_s"]) else 0.0)
    t = tr["t_s"] / scale
    fig, axes = plt.subplots(3, 1, figsize=(11, 8.4), sharex=True, constrained_layout=True)
    for i, (ax, name) in enumerate(zip(axes, "xyz")):
        _axis_panel(ax, t, tr, i, name)
    axes[-1].set_xlabel(f"time since the first sample ({unit})")
    axes[0].legend(loc="upper center", bbox_to_anchor=(0.5, 1.32), ncol=3, fontsize=8, frameon=False)
    rms = [float(np.sqrt(np.mean(np.sum((tr[k] - tr["expected_ut"]) ** 2, axis=1))))
           for k in ("without_terms_ut", "calibrated_ut")]
    per_axis = np.sqrt(np.mean((tr["calibrated_ut"] - tr["expected_ut"]) ** 2, axis=0))
    fig.suptitle(wrap(f"Expected against measured field per axis: vector RMS {rms[1]:.2f} µT "
                      f"({rms[0]:.2f} µT without the terms)", 90), fontweight="bold")
    name = save(fig, out, "expected", plt)
    terms = ", ".join(tr["terms"]) or "none"
    return Figure(name, "Expected against measured field, per axis",
                  "the navy line (measured, calibrated) on the black one (expected from the log's attitude and the "
                  "Earth model) on every axis; grey dots away from it where the motors run or the current is high: "
                  "what the terms take out. A steady gap on one axis is an offset or a frame left wrong.",
                  f"vector RMS {rms[1]:.3f} µT with the calibration (terms: {terms}), {rms[0]:.3f} µT without its "
                  f"terms; per axis x, y, z {per_axis[0]:.3f}, {per_axis[1]:.3f}, {per_axis[2]:.3f} µT.",
                  "expected and measured field per axis over time")


def flight_log_section(result: dict, traces: dict | None):
    """A section maker for ``write_report(sections=...)``: the flight-log fit's terms and figure."""

    def make(diagnosis, out, plt) -> Section:
        figs = (expected_figure(traces, plt, out),) if traces is not None and len(traces["t_s"]) else ()
        return Section("The flight-log fit against the expected field", figs, html=terms_html(result["flight_log"]),
                       key="flightlog")

    return make
