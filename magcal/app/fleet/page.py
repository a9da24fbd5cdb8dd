"""The fleet page (``RESULTS/index.html``): one self-contained HTML file drawn from the fleet
document (``summary.document``) — the changes first, then per vehicle each compass's hard iron
across its flights (x, y, z with their ±1σ, a dashed line where a change was found) and its
current term. Inline SVG, no scripts, no other files: it opens from a disk or a mail."""

from __future__ import annotations

import html

W, H, PAD = 640, 150, 34
COLOURS = ("#c0392b", "#27ae60", "#2c6fbb")
KIND_WORDS = {"hard_iron_step": "hard-iron step", "current_term_appeared": "current term appeared",
              "current_term_changed": "current term changed"}


def _e(v) -> str:
    return html.escape(str(v))


def _scale(values: list[float], lo_px: float, hi_px: float):
    lo, hi = min(values), max(values)
    if hi - lo < 1e-9:
        lo, hi = lo - 1.0, hi + 1.0
    return lambda v: hi_px - (v - lo) / (hi - lo) * (hi_px - lo_px), lo, hi


def _points(flights: list[dict], key: str, skey: str):
    """(flight index, value less the compass's median per axis, σ) of the flights where fitted:
    a step of a few σ is visible beside a hard iron of tens of µT."""
    pts = []
    for i, f in enumerate(flights):
        v, s = f.get(key), f.get(skey)
        if v and s and all(a is not None for a in v + s):
            pts.append((i, v, s))
    if not pts:
        return pts
    med = [sorted(v[a] for _, v, _ in pts)[len(pts) // 2] for a in range(3)]
    return [(i, [v[a] - med[a] for a in range(3)], s) for i, v, s in pts]


def chart(flights: list[dict], key: str, skey: str, unit: str, change_at: list[int]) -> str:
    """An SVG of a vector quantity across the flights (x, y, z, ±1σ); '' when none was fitted."""
    pts = _points(flights, key, skey)
    if not pts:
        return ""
    n = max(len(flights) - 1, 1)
    xs = lambda i: PAD + i / n * (W - 2 * PAD)  # noqa: E731
    ys, lo, hi = _scale([v[a] + sgn * s[a] for _, v, s in pts for a in range(3) for sgn in (-1, 1)], 8, H - 18)
    out = [f'<svg width="{W}" height="{H}" role="img"><rect width="{W}" height="{H}" fill="#fafafa"/>',
           f'<text x="2" y="12" font-size="10">{hi:+.3g} {unit}</text><text x="2" y="{H - 20}" font-size="10">{lo:+.3g}</text>']
    for k in change_at:
        x = xs(k - 0.5)
        out.append(f'<line x1="{x:.1f}" x2="{x:.1f}" y1="4" y2="{H - 14}" stroke="#333" stroke-dasharray="4 3"/>')
    for a, colour in enumerate(COLOURS):
        line = " ".join(f"{xs(i):.1f},{ys(v[a]):.1f}" for i, v, _ in pts)
        out.append(f'<polyline points="{line}" fill="none" stroke="{colour}" stroke-width="1.2"/>')
        out += [f'<line x1="{xs(i):.1f}" x2="{xs(i):.1f}" y1="{ys(v[a] - s[a]):.1f}" y2="{ys(v[a] + s[a]):.1f}" '
                f'stroke="{colour}" stroke-opacity="0.5"/>' for i, v, s in pts]
    out.append(f'<text x="{PAD}" y="{H - 3}" font-size="10">flight 1</text>'
               f'<text x="{W - PAD - 40}" y="{H - 3}" font-size="10">flight {len(flights)}</text></svg>')
    return "".join(out)


def _change_row(c: dict) -> str:
    sib = "—" if c["alone"] is None else ("this compass alone" if c["alone"] else "with its siblings")
    step = ", ".join(f"{v:+.3g}" for v in c["step"])
    sig = ", ".join(f"{v:.2g}" for v in c["sigma_step"])
    return (f"<tr><td>{_e(c['vehicle'])}</td><td>{_e(c['compass'])}</td><td>{_e(KIND_WORDS[c['kind']])}</td>"
            f"<td>{_e(c['flight'])}<br><small>after {_e(c['previous_flight'])}</small></td>"
            f"<td>({step}) ± ({sig})</td><td>{c['chi2']:.1f}</td><td>{c['p_value']:.2g}</td><td>{sib}</td></tr>")


def _compass_block(cmp: dict) -> str:
    at = {"offset": [c["index"] for c in cmp["changes"] if c["kind"] == "hard_iron_step"],
          "current": [c["index"] for c in cmp["changes"] if c["kind"] != "hard_iron_step"]}
    where = {True: "external", False: "internal", None: ""}[cmp["external"]]
    parts = [f"<h3>{_e(cmp['compass'])} {where} — {_count(len(cmp['flights']), 'flight')}, "
             f"{_count(len(cmp['changes']), 'change')}</h3>"]
    if len(_points(cmp["flights"], "offset_ut", "sigma_offset_ut")) < 2:
        return "".join(parts) + _one_flight(cmp["flights"])
    off = chart(cmp["flights"], "offset_ut", "sigma_offset_ut", "µT", at["offset"])
    cur = chart(cmp["flights"], "current_a_ut_per_unit", "sigma_current_a_ut_per_unit", "µT/A", at["current"])
    parts += [f"<p>hard iron, less its median (µT; x red, y green, z blue; ±1σ)</p>{off}" if off
              else "<p>no flight fitted</p>", f"<p>current term, less its median (µT/A)</p>{cur}" if cur else ""]
    return "".join(parts)


def _count(n: int, word: str) -> str:
    return f"{n} {word}" + ("" if n == 1 else "s")


def _one_flight(flights: list[dict]) -> str:
    """A compass fitted on one flight at most: its numbers in words, no history to draw yet."""
    fitted = [f for f in flights if f.get("offset_ut") and f.get("sigma_offset_ut")]
    if not fitted:
        return "<p>no flight fitted</p>"
    f = fitted[0]
    vec = lambda v, s: "(" + ", ".join(f"{a:+.2f}" for a in v) + ") ± (" + ", ".join(f"{b:.2f}" for b in s) + ")"  # noqa: E731
    text = f"<p>one flight fitted, no history yet: hard iron {vec(f['offset_ut'], f['sigma_offset_ut'])} µT"
    cur, scur = f.get("current_a_ut_per_unit"), f.get("sigma_current_a_ut_per_unit")
    if cur and scur and None not in cur + scur:
        text += f"; current term {vec(cur, scur)} µT/A"
    return text + "</p>"


def render(doc: dict) -> str:
    head = ["<!doctype html><html><head><meta charset='utf-8'><title>magcal fleet</title><style>",
            "body{font-family:sans-serif;margin:1.5em;max-width:60em}table{border-collapse:collapse}",
            "td,th{border:1px solid #ccc;padding:3px 6px;font-size:13px;vertical-align:top}</style></head><body>",
            f"<h1>Compass health across the fleet</h1><p>{doc['logs']['total']} logs, {doc['rows']} rows "
            f"({doc['failed_rows']} without a calibration), {len(doc['vehicles'])} vehicles, "
            f"{len(doc['changes'])} changes at family-wise level {doc['alpha']:g} per vehicle; magcal "
            f"{_e(doc['magcal_version'])}; results in {_e(doc['results'])}.</p>"]
    rows = "".join(_change_row(c) for c in doc["changes"]) or "<tr><td colspan='8'>no change found</td></tr>"
    body = ["<h2>Changes</h2><table><tr><th>vehicle</th><th>compass</th><th>what</th><th>at flight</th>"
            "<th>step ± σ</th><th>χ²</th><th>p</th><th>siblings</th></tr>", rows, "</table>"]
    for v in doc["vehicles"]:
        body.append(f"<h2>{_e(v['vehicle'])}</h2>" + "".join(_compass_block(c) for c in v["compasses"]))
    fails = "".join(f"<tr><td>{_e(f['path'])}</td><td>{_e(f['mag_index'])}</td><td>{_e(f['failure'])}</td>"
                    f"<td>{_e(f['message'])}</td></tr>" for f in doc["failures"])
    if fails:
        body.append("<h2>Without a calibration</h2><table><tr><th>file</th><th>mag</th><th>why</th><th></th></tr>"
                    + fails + "</table>")
    return "".join(head + body) + "</body></html>\n"
