"""The report page: the calibration first, then what was found, then the figures with their
captions, the point cloud, and any further sections — one self-contained HTML file beside its
pictures (no script, style or font is fetched from anywhere)."""

from __future__ import annotations

import html

import numpy as np

from ... import __version__
from ...diagnose import channels as ch
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


def calibration_table(diagnosis) -> str:
    """Offset, field, soft iron and channel terms of the final model, with 1σ where known."""
    f = diagnosis.final
    sd = _sigma(f)
    ns = f.spec.n_soft
    rows = [f"<tr><th>offset (hard iron)</th><td class='num'>"
            + ", ".join(_pm(float(f.offset_ut[i]), None if sd is None else sd[i]) for i in range(3))
            + "</td><td class='l'>µT, x, y, z; 1σ</td></tr>",
            f"<tr><th>field</th><td class='num'>{_pm(f.field_ut, None if sd is None else sd[3 + ns])}</td>"
            "<td class='l'>µT: the magnitude every calibrated sample should have</td></tr>"]
    w = f.soft_iron
    soft = "<br>".join(" ".join(f"{x:+.5f}" for x in row) for row in w)
    note = "fitted" if ns else "not fitted (identity): the recording did not call for it"
    rows.append(f"<tr><th>soft iron</th><td class='num'>{soft}</td><td class='l'>calibrated = W (m − offset); {note}</td></tr>")
    for j, (c, k) in enumerate(f.coef_ut_per_unit.items()):
        base = 4 + ns + 3 * j
        unit = ch.unit_of(c, diagnosis.series.clock)
        vals = ", ".join(_pm(float(k[i]), None if sd is None else sd[base + i], ".4f") for i in range(3))
        ref = f.reference.get(c, 0.0)
        after = "s" if diagnosis.series.clock else "samples"
        about = (f"about {ref - float(diagnosis.series.t_s[0]):.0f} {after} after the first sample" if c == ch.TIME
                 else f"about {ref:.3g} {unit}")
        rows.append(f"<tr><th>{esc(c)} term</th><td class='num'>{vals}</td><td class='l'>µT per {esc(unit)}, "
                    f"{esc(about)}</td></tr>")
    b = diagnosis
    rows.append(f"<tr><th>residual RMS</th><td class='num'>{b.baseline.rms_ut:.3f} → {f.rms_ut:.3f}</td>"
                f"<td class='l'>µT, sphere → final; held out: {b.baseline_heldout_rms_ut:.3f} → "
                f"{b.final_heldout_rms_ut:.3f}; noise {b.noise_ut:.3f} per axis</td></tr>")
    return f"<table>{''.join(rows)}</table>"


def findings_html(d: dict) -> str:
    rows = "".join(f"<li class='finding'><b>{esc(f['effect'])}</b> — {esc(f['summary'])}</li>" for f in d["findings"])
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
    nav = "".join(f'<a href="#{esc(x.key or f"section-{i}")}">{esc(x.title)}</a>' for i, x in enumerate(sections))
    body = "".join(section_html(x, i) for i, x in enumerate(sections))
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><meta name="viewport" content="width=device-width,initial-scale=1">
<title>magcal diagnose — {esc(title)}</title><style>{STYLE}</style></head><body>
<h1>What the calibration left out — {esc(title)}</h1>
<p class="sub">{diagnosis.n_samples} samples over {span:.1f} s; white noise {diagnosis.noise_ut:.3f} µT per axis.{src}</p>
<nav>{nav}</nav>
{body}
<p class="sub">magcal {esc(__version__)} · every picture and script of this page is in its folder</p>
</body></html>
"""
