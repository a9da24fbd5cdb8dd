"""The report page: the calibration first, then what was found, then the figures with their
captions, the point cloud, and any further sections — one self-contained HTML file beside its
pictures (no script, style or font is fetched from anywhere)."""

from __future__ import annotations

import html

import numpy as np

from ... import __version__
from ...diagnose import channels as ch
from ..flightlog import moved_in_calibration
from .section import Figure, Section

esc = html.escape

STYLE = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;max-width:1320px;margin:1.5em auto;
padding:0 1.2em;color:#1d1d1d;line-height:1.45}
h1{font-size:1.6em;margin-bottom:.2em;overflow-wrap:anywhere} h2{margin-top:1.6em;border-bottom:1px solid #ddd}
.sub{color:#555;margin-top:0} table{border-collapse:collapse;margin:.6em 0}
td,th{padding:3px 12px;text-align:right;border-bottom:1px solid #eee} th{text-align:left;background:#f6f6f6}
td.l{text-align:left} .num{font-variant-numeric:tabular-nums}
figure{margin:1.2em 0 2em} figure img{max-width:100%;height:auto;border:1px solid #eee}
figcaption,.caption{max-width:980px;color:#333} figcaption b,.caption b{color:#000}
.finding{color:#b03a00} canvas{border:1px solid #ddd;max-width:100%;cursor:grab;background:#fff}
nav a{margin-right:1em} .how{color:#444}
"""


def _sigma(fit) -> np.ndarray | None:
    cov = getattr(fit, "cov", None)
    if cov is None:
        return None
    d = np.diag(np.asarray(cov, dtype=np.float64))
    return np.sqrt(np.where(d > 0, d, np.nan))


def _pm(value: float, sigma, fmt: str = ".3f") -> str:
    if sigma is None or not np.isfinite(sigma):
        return format(value, fmt)
    return f"{format(value, fmt)} ± {format(float(sigma), fmt)}"


def calibration_of(diagnosis, result: dict | None = None) -> tuple[dict, dict]:
    """(the calibration the page shows — the result's, as its JSON prints it and ``write`` and
    ``export`` take it — and its 1σ per part where known: offset, field, each term)."""
    from ...diagnose.diagnosis import calibration_dict

    cal = (result or {}).get("calibration") or calibration_dict(diagnosis.final)
    if (result or {}).get("calibration_from") == "flight_log":
        log = result["flight_log"]
        terms = {t["channel"]: t for t in log.get("terms", []) if t.get("kept")}
        return cal, {"offset_ut": log.get("uncertainty", {}).get("offset_ut"),
                     **{c: t.get("sigma_ut_per_unit") for c, t in terms.items()
                        if "coef_in_calibration_ut_per_unit" in t and not moved_in_calibration(t)}}
    f, sd = diagnosis.final, _sigma(diagnosis.final)
    if sd is None:
        return cal, {}
    ns, scale = f.spec.n_soft, cal["field_ut"] / f.field_ut if f.field_ut else 1.0
    sigma = {"offset_ut": sd[:3].tolist(), "field_ut": float(sd[3 + ns] * scale)}
    for j, c in enumerate(f.coef_ut_per_unit):
        sigma[c] = sd[4 + ns + 3 * j: 7 + ns + 3 * j].tolist()
    return cal, sigma


def _term_row(diagnosis, c: str, k, ref: float, sigma) -> str:
    clock = diagnosis.series.clock if diagnosis is not None else True
    unit = {"motors_on": "motors-running step", "current_a": "A"}.get(c) or ch.unit_of(c, clock)
    vals = ", ".join(_pm(float(k[i]), None if sigma is None else sigma[i], ".4f") for i in range(3))
    after = "s" if clock else "samples"
    about = (f"about {ref - float(diagnosis.series.t_s[0]):.0f} {after} after the first sample" if c == ch.TIME
             else "0 with the motors stopped, 1 running" if c == "motors_on" else f"about {ref:.3g} {unit}")
    return (f"<tr><th>{esc(c)} term</th><td class='num'>{vals}</td><td class='l'>µT per {esc(unit)}, "
            f"{esc(about)}</td></tr>")


def calibration_table(diagnosis, result: dict | None = None) -> str:
    """Offset, field, soft iron and channel terms of the result's calibration — the numbers its
    JSON and text print — with 1σ where known, and any alternative set aside, with why."""
    cal, sd = calibration_of(diagnosis, result)
    rows = [f"<tr><th>offset (hard iron)</th><td class='num'>"
            + ", ".join(_pm(float(cal["offset_ut"][i]), None if sd.get("offset_ut") is None else sd["offset_ut"][i])
                        for i in range(3))
            + "</td><td class='l'>µT, x, y, z; 1σ</td></tr>",
            f"<tr><th>field</th><td class='num'>{_pm(cal['field_ut'], sd.get('field_ut'))}</td>"
            "<td class='l'>µT: the magnitude every calibrated sample should have</td></tr>"]
    w = np.asarray(cal["soft_iron"], np.float64)
    soft = "<br>".join(" ".join(f"{x:+.5f}" for x in row) for row in w)
    note = "fitted" if np.abs(w - np.eye(3)).max() > 0 else "not fitted (identity): the recording did not call for it"
    rows.append(f"<tr><th>soft iron</th><td class='num'>{soft}</td><td class='l'>calibrated = W (m − offset"
                + (" − Σ term·x" if cal.get("coef_ut_per_unit") else "") + f"); {note}</td></tr>")
    for c, k in (cal.get("coef_ut_per_unit") or {}).items():
        rows.append(_term_row(diagnosis, c, k, float((cal.get("reference") or {}).get(c, 0.0)), sd.get(c)))
    rows += _residual_rows(diagnosis, result)
    return f"<p>{esc(_whose(result))}</p><table>{''.join(rows)}</table>" + _alternatives_html(result)


def _residual_rows(diagnosis, result: dict | None) -> list[str]:
    if diagnosis is None:  # a flight log whose |m| alone could not be diagnosed
        return _log_residual_rows(result)
    b, f = diagnosis, diagnosis.final
    rows = [f"<tr><th>residual RMS{' of |m| alone' if (result or {}).get('calibration_from') else ''}</th>"
            f"<td class='num'>{b.baseline.rms_ut:.3f} → {f.rms_ut:.3f}</td>"
            f"<td class='l'>µT, |m|: sphere → final; held out: {b.baseline_heldout_rms_ut:.3f} → "
            f"{b.final_heldout_rms_ut:.3f}; noise {b.noise_ut:.3f} per axis</td></tr>"]
    return _log_residual_rows(result) + rows


def _log_residual_rows(result: dict | None) -> list[str]:
    if (result or {}).get("calibration_from") != "flight_log":
        return []
    log = result["flight_log"]
    h = log["heldout_ut"]
    what = h["measure"].split("_")[1]
    return [f"<tr><th>residual RMS</th><td class='num'>{log['rms_ut']:.3f}</td><td class='l'>µT, {what} "
            f"against the expected field, {log['n_used']} samples; held out: {h['none']:.3f} without "
            f"terms → {h['chosen']:.3f} with {esc(log['heldout']['chosen'])}</td></tr>"]


def _whose(result: dict | None) -> str:
    if (result or {}).get("calibration_from") == "flight_log":
        return (f"The flight-log fit's calibration ({result['calibration_model']}), fitted against the expected "
                "field: the one magcal fit gives, write puts on a device and export turns into parameters. "
                + ("The |m| figures further down are of the |m| diagnosis, an alternative (below)."
                   if "magnitude_failure" not in result else f"|m| alone was not diagnosed: {result['magnitude_failure']}."))
    return "The calibration the result's JSON holds: the one write puts on a device and export turns into parameters."


def _alternatives_html(result: dict | None) -> str:
    items = "".join(f"<li><b>{esc(a['name'])}</b> — offset ("
                    + ", ".join(f"{v:.3f}" for v in a["calibration"]["offset_ut"])
                    + f") µT, field {a['calibration']['field_ut']:.3f} µT: {esc(a['why'])}</li>"
                    for a in (result or {}).get("alternatives", []))
    return f"<h3>Set aside</h3><ul>{items}</ul>" if items else ""


def findings_html(d: dict, result: dict | None = None) -> str:
    """What the |m| diagnosis found and could not test; on a flight log, then each term judged
    against the expected field (what |m| alone cannot test)."""
    rows = "".join(f"<li class='finding'><b>{esc(f['effect'])}</b> — {esc(f['summary'])}</li>" for f in d["findings"])
    log = [f for f in ((result or {}).get("flight_log") or {}).get("findings", [])]
    rows += "".join(f"<li class='{'finding' if f['kept'] else ''}'><b>{esc(f['effect'])}</b> (against the expected "
                    f"field) — {esc(f['summary'])}</li>" for f in log)
    if not rows:
        suspected = any(x.get("suspected") for x in d.get("limits", []))
        rows = ("<li>Nothing proven — but see the limits below.</li>" if suspected else
                "<li>Nothing left out: the sphere (hard-iron) model explains the recording to its noise.</li>")
    out = f"<ul>{rows}</ul>"
    limits = "".join(f"<li><b>{esc(x['effect'])}</b> — {esc(x['summary'])}</li>" for x in d.get("limits", []))
    if limits:
        out += f"<h3>Limits: what this recording could not test or pin down</h3><ul>{limits}</ul>"
    return out


def figure_html(fig: Figure) -> str:
    return (f'<figure><h3>{esc(fig.title)}</h3><img src="{esc(fig.file)}" alt="{esc(fig.alt or fig.title)}">'
            f"<figcaption><b>Look for:</b> {esc(fig.look_for)}<br><b>Found:</b> {esc(fig.found)}</figcaption></figure>")


def section_html(s: Section, n: int) -> str:
    key = s.key or f"section-{n}"
    return f'<section id="{esc(key)}"><h2>{esc(s.title)}</h2>{s.html}{"".join(figure_html(f) for f in s.figures)}</section>'


def page(diagnosis, title: str, sections: list[Section]) -> str:
    """The whole page: header, then each section in order."""
    s = diagnosis.series
    span = float(s.t_s[-1] - s.t_s[0]) if len(s) else 0.0
    src = f" Read as: {esc(s.source)}." if s.source else ""
    over = f" over {span:.1f} s" if s.clock else " (no time column: timed by sample index)"
    return page_html(title, f"{diagnosis.n_samples} samples{over}; white noise "
                            f"{diagnosis.noise_ut:.3f} µT per axis.{src}", sections)


def page_html(title: str, sub: str, sections: list[Section]) -> str:
    """The page around its sections; ``sub`` the line under the title (HTML, data escaped)."""
    nav = "".join(f'<a href="#{esc(x.key or f"section-{i}")}">{esc(x.title)}</a>' for i, x in enumerate(sections))
    body = "".join(section_html(x, i) for i, x in enumerate(sections))
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><meta name="viewport" content="width=device-width,initial-scale=1">
<title>magcal diagnose — {esc(title)}</title><style>{STYLE}</style></head><body>
<h1>What the calibration left out — {esc(title)}</h1>
<p class="sub">{sub}</p>
<nav>{nav}</nav>
{body}
<p class="sub">magcal {esc(__version__)} · every picture and script of this page is in its folder</p>
</body></html>
"""
